"""One writer per dataset directory: ``<dataset>/writer.lock``.

``generate-dataset`` holds the lock for its whole run. The file names the holder (host, pid,
start time, command) so a second run can say who is writing; exclusivity comes from an
advisory ``flock`` on the file, which the kernel drops when the holder dies, however it dies
(SIGKILL, power loss of a client): a lock file left behind by a dead run is taken over by the
next run without anyone deleting it. Where ``flock`` is not supported (some network file
systems), the file itself is the lock (created exclusively) and a lock of this host whose pid
no longer runs is stale and taken over; a lock of another host is never taken over
automatically (its liveness cannot be checked from here): delete the file when sure.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import os
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .schema import DatasetError

LOCK_NAME = "writer.lock"

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]


class DatasetLockedError(DatasetError):
    """Another run is writing the dataset directory; the message names it."""


@dataclass(frozen=True)
class LockHolder:
    """Who holds (or held) a dataset's writer lock."""

    host: str
    pid: int
    start_time: str
    command: str | None = None

    def describe(self) -> str:
        text = f"host {self.host}, pid {self.pid}, started {self.start_time}"
        return text + (f", command: {self.command}" if self.command else "")

    def alive(self) -> bool | None:
        """Whether the holder process still runs: None when it is on another host (unknown)."""
        if self.host != socket.gethostname():
            return None
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:  # another user's live process
            return True
        return True

    @classmethod
    def parse(cls, text: str) -> "LockHolder | None":
        try:
            data = json.loads(text)
            return cls(str(data["host"]), int(data["pid"]), str(data["start_time"]), data.get("command"))
        except (ValueError, KeyError, TypeError):
            return None


def _me() -> LockHolder:
    return LockHolder(socket.gethostname(), os.getpid(),
                      _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                      " ".join(sys.argv) or None)


def _read(path: Path) -> LockHolder | None:
    try:
        return LockHolder.parse(path.read_text(encoding="utf-8"))
    except OSError:
        return None


def read_lock(root: str | os.PathLike[str]) -> LockHolder | None:
    """The holder of ``root``'s writer lock while a run holds it, else None (no lock, or a file
    left by a run that ended)."""
    path = Path(root) / LOCK_NAME
    if not path.is_file():
        return None
    holder = _read(path)
    if fcntl is not None:
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            return holder
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None  # nobody holds it: a file left by an ended run
        except BlockingIOError:
            return holder or LockHolder("?", 0, "?")
        except OSError:
            pass
        finally:
            os.close(fd)
    return holder if holder is not None and holder.alive() is not False else None


class DatasetLock:
    """The writer lock of dataset directory ``root`` (a context manager).

    ``acquire()`` raises :class:`DatasetLockedError` naming the holder when another run holds
    it; ``took_over`` is then the holder of a stale lock this one replaced (None otherwise).
    """

    def __init__(self, root: str | os.PathLike[str]):
        self.root = Path(root)
        self.path = self.root / LOCK_NAME
        self._fd: int | None = None
        self.took_over: LockHolder | None = None

    def _refuse(self, holder: LockHolder | None) -> DatasetLockedError:
        who = holder.describe() if holder is not None else "a process that has not written its name yet"
        return DatasetLockedError(
            f"dataset directory {str(self.root)!r} is being written by another run ({who}); only one run may "
            f"write a dataset: wait for it to finish (or stop it), then rerun this command to resume")

    def acquire(self) -> "DatasetLock":
        if fcntl is not None:
            for _ in range(10):
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    os.close(fd)
                    raise self._refuse(_read(self.path)) from None
                except OSError as error:
                    os.close(fd)
                    if error.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                        return self._acquire_by_file()
                    raise
                try:  # the path may have been unlinked and re-created meanwhile: lock the file it names now
                    same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
                except FileNotFoundError:
                    same = False
                if not same:
                    os.close(fd)
                    continue
                previous = LockHolder.parse(os.pread(fd, 1 << 16, 0).decode("utf-8", "replace"))
                self.took_over = previous
                self._fd = fd
                self._write(fd)
                return self
            raise self._refuse(_read(self.path))
        return self._acquire_by_file()

    def _acquire_by_file(self) -> "DatasetLock":
        for _ in range(10):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                holder = _read(self.path)
                if holder is not None and holder.alive() is False:
                    stale = self.path.with_name(f"{LOCK_NAME}.stale-{os.getpid()}")
                    try:
                        os.replace(self.path, stale)
                    except FileNotFoundError:
                        continue
                    if _read(stale) != holder:  # another run took it over first: give its lock back
                        os.replace(stale, self.path)
                        raise self._refuse(_read(self.path)) from None
                    stale.unlink()
                    self.took_over = holder
                    continue
                raise self._refuse(holder) from None
            self._fd = fd
            self._write(fd)
            return self
        raise self._refuse(_read(self.path))

    def _write(self, fd: int) -> None:
        me = _me()
        data = json.dumps({"host": me.host, "pid": me.pid, "start_time": me.start_time, "command": me.command})
        os.ftruncate(fd, 0)
        os.pwrite(fd, (data + "\n").encode("utf-8"), 0)
        os.fsync(fd)

    def release(self) -> None:
        """Removes the lock file and drops the lock (safe to call twice)."""
        if self._fd is None:
            return
        try:
            self.path.unlink()
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> "DatasetLock":
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()
