"""What the ``drape`` command line tells a user when something is wrong, and the checks that
find it before any work starts.

Exit statuses (see docs/errors.md): 0 success; 1 a check found a problem in the data
(``dataset validate``/``info``) or an internal error; 2 bad input (an option, a spec, a dataset
that cannot be trusted, an output path that cannot be written, a dataset locked by another run,
a full disk); 130 interrupted by SIGINT (Ctrl-C); 143 stopped by SIGTERM.

Every error is one line naming the option or field, the value and what was expected; the
traceback is shown only with ``--debug`` (or ``DRAPE_DEBUG=1``).
"""
from __future__ import annotations

import errno
import math
import os
import shutil
import signal
import sys
from pathlib import Path
from typing import Any

EXIT_USAGE = 2
EXIT_INTERNAL = 1
EXIT_SIGINT = 130
EXIT_SIGTERM = 143


class UsageError(ValueError):
    """A bad option value or argument; the message names the option, the value and what was expected."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's KeyboardInterrupt so the same cleanup runs
    (temporary files removed, nothing half-written listed)."""

    signum = signal.SIGTERM


_received: list[int] = []  # signals raised as exceptions, in case one was swallowed


def install_signal_handlers() -> Any:
    """Makes SIGTERM raise :class:`Terminated` and SIGINT KeyboardInterrupt in the main thread,
    and remembers them for :func:`raise_if_interrupted`; returns the previous handlers (None
    where signals cannot be set: not the main thread)."""
    def handler(signum, frame):  # noqa: ARG001
        _received.append(signum)
        if signum == signal.SIGTERM:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not break the cleanup
            raise Terminated()
        raise KeyboardInterrupt()

    try:
        previous = {signum: signal.signal(signum, handler) for signum in (signal.SIGTERM, signal.SIGINT)}
    except ValueError:  # not the main thread
        return None
    hook = sys.unraisablehook

    def quiet(unraisable):  # the interruption swallowed by a finalizer is raised again, not printed
        if not (isinstance(unraisable.exc_value, KeyboardInterrupt) and _received):
            hook(unraisable)

    sys.unraisablehook = quiet
    previous["unraisablehook"] = hook
    return previous


def restore_signals(previous: Any) -> None:
    """Puts back the handlers :func:`install_signal_handlers` replaced."""
    for signum, handler in (previous or {}).items():
        if signum == "unraisablehook":
            sys.unraisablehook = handler
        else:
            signal.signal(signum, handler)
    _received.clear()


def raise_if_interrupted() -> None:
    """Raises the interruption again when a signal's exception was swallowed (an exception raised
    while Python runs a finalizer or weakref callback is printed and dropped): long loops call
    this at safe points so Ctrl-C and SIGTERM always stop the run."""
    if _received:
        raise Terminated() if _received[-1] == signal.SIGTERM else KeyboardInterrupt()


def one_line(text: str) -> str:
    """A message on one line: its lines joined with "; "."""
    return "; ".join(line.strip() for line in str(text).splitlines() if line.strip())


def human_bytes(count: float) -> str:
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if value < 1024 or unit == "TiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} TiB"


def free_bytes(path: str | os.PathLike[str]) -> int | None:
    """Free bytes on the file system holding ``path`` (or its nearest existing parent)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return int(shutil.disk_usage(p).free)
    except OSError:
        return None


def is_disk_full(error: BaseException) -> bool:
    """True for ENOSPC / EDQUOT / EFBIG, also when HDF5 reports it only in its message."""
    if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return True
    text = str(error)
    return ("No space left on device" in text or "errno = 28" in text or "Disk quota exceeded" in text
            or "File too large" in text or "errno = 27" in text)


def hdf5_files_left_open() -> bool:
    """Whether HDF5 still holds files (h5py loaded): after a failed write it cannot close them."""
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return False
    try:
        return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_FILE) > 0
    except Exception:  # noqa: BLE001 - only a hint for the exit path
        return False


def describe_os_error(error: OSError) -> str:
    """One line for an OSError naming the path and, when the disk is full, the free space."""
    where = error.filename or getattr(error, "path", None)
    what = error.strerror or one_line(str(error))
    if is_disk_full(error):
        free = free_bytes(where) if where else None
        return (f"not enough space to write {where or 'the output'}: {what}"
                + (f" ({human_bytes(free)} free)" if free is not None else "")
                + "; free some space and rerun the same command")
    if where:
        return f"cannot access {where}: {what}"
    return what


def describe(error: BaseException) -> tuple[int, str]:
    """(exit status, one-line message) of an exception that reached the command line."""
    if isinstance(error, OSError) and error.errno is not None and not _is_dataset_error(error):
        return EXIT_USAGE, describe_os_error(error)  # raised by the system: name the path and the reason
    if isinstance(error, (ValueError, OSError)) or _is_dataset_error(error):
        return EXIT_USAGE, one_line(str(error)) or type(error).__name__
    return EXIT_INTERNAL, (f"internal error: {type(error).__name__}: {one_line(str(error))} "
                           f"(rerun with --debug for the traceback, and please report it)")


def _is_dataset_error(error: BaseException) -> bool:
    try:
        from data_manifest.schema import DatasetError
    except ImportError:  # pragma: no cover
        return False
    return isinstance(error, DatasetError)


# -- checks made before work starts ----------------------------------------------------------


def _probe_writable(directory: Path, option: str) -> None:
    """Creates and removes a file in ``directory``: catches read-only mounts and ACLs that
    permission bits alone do not show."""
    from data_manifest.integrity import write_error

    error = write_error(directory)
    if error is not None:
        raise UsageError(f"{option} {str(directory)!r} is not writable ({error.strerror or error}); "
                         f"choose a directory you can write to")


def check_output_dir(path: str | os.PathLike[str], option: str = "--out") -> Path:
    """Creates ``path`` as a directory (with parents) and checks it is writable; raises UsageError
    naming ``option`` when it is a file, cannot be created or is read-only."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{option} {str(p)!r} is a file; expected a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UsageError(f"{option} {str(p)!r}: a parent of it is a file; expected a directory path") from None
    except NotADirectoryError:
        raise UsageError(f"{option} {str(p)!r}: a parent of it is a file; expected a directory path") from None
    except OSError as error:
        raise UsageError(f"{option} {str(p)!r} cannot be created ({error.strerror or error})") from None
    _probe_writable(p, option)
    return p


def check_output_file(path: str | os.PathLike[str], option: str = "--out", *,
                      suffixes: tuple[str, ...] | None = None) -> Path:
    """Checks that a file can be written at ``path`` (its directory created when missing): not a
    directory, a known suffix when ``suffixes`` is given, a writable parent."""
    p = Path(path)
    if suffixes is not None and p.suffix.lower() not in suffixes:
        raise UsageError(f"{option} must end in {' or '.join(suffixes)} (got {str(p)!r})")
    if p.is_dir():
        raise UsageError(f"{option} {str(p)!r} is a directory; expected a file name such as {str(p / ('out' + (suffixes or ('.obj',))[0]))!r}")
    check_output_dir(p.parent if str(p.parent) else Path("."), option=f"{option} {str(p)!r}: directory")
    if p.exists() and not os.access(p, os.W_OK):
        raise UsageError(f"{option} {str(p)!r} exists and is read-only")
    return p


def check_torch_device(value: str, option: str = "--device") -> str:
    """``value`` as a torch device that exists here (cpu, cuda, cuda:N); raises naming ``option``."""
    import torch

    try:
        device = torch.device(value)
    except (RuntimeError, TypeError, ValueError):
        raise UsageError(f"{option} must be cpu, cuda or cuda:N (got {value!r})") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise UsageError(f"{option} {value!r}: torch finds no CUDA device on this machine; use --device cpu")
        if device.index is not None and device.index >= count:
            raise UsageError(f"{option} {value!r}: this machine has {count} CUDA device(s) (cuda:0..cuda:{count - 1})")
    elif device.type != "cpu":
        raise UsageError(f"{option} must be cpu, cuda or cuda:N (got {value!r})")
    return value


def check_number(value: Any, option: str, *, minimum: float | None = None, maximum: float | None = None,
                 integer: bool = False, above: bool = False) -> Any:
    """A finite number (an integer with ``integer``) within bounds; raises naming ``option``.
    ``above``: the minimum itself is excluded."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (not integer or float(value).is_integer())
    if ok and minimum is not None:
        ok = value > minimum if above else value >= minimum
    if ok and maximum is not None:
        ok = value <= maximum
    if not ok:
        kind = "an integer" if integer else "a finite number"
        bounds = []
        if minimum is not None:
            bounds.append(f"{'>' if above else '>='} {minimum:g}")
        if maximum is not None:
            bounds.append(f"<= {maximum:g}")
        raise UsageError(f"{option} must be {kind}{' ' + ' and '.join(bounds) if bounds else ''} (got {value!r})")
    return value
