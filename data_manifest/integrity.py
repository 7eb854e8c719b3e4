"""A shard's bytes against its manifest entry (size and sha256), checked before it is read.

Hashing a shard reads the whole file (about 1 GB/s), so each file's digest is cached, keyed by
its size, modification time [ns] and inode: an unchanged shard is checked again with one
``stat``; a shard rewritten, replaced or touched is hashed again. The cache is a JSON file,
``<dataset>/cache/integrity.json``, or, when the dataset directory cannot be written (a
read-only mount, another user's data), ``<user cache>/integrity/<hash of the dataset path>.json``
(:func:`user_cache_dir`). Losing or deleting it only costs the hashing again.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Mapping

from .schema import TMP_SUFFIX
from .shard import file_sha256

CACHE_NAME = "integrity.json"
CACHE_FORMAT = "drape-integrity-cache-1"
#: Environment variable naming the user cache directory (else $XDG_CACHE_HOME/drape or ~/.cache/drape).
CACHE_ENV = "DRAPE_CACHE_DIR"
#: Serialises the digest cache's reads and writes between threads of one process (shards are
#: hashed by a thread pool in ``parallel_read``: hashlib releases the GIL).
_CACHE_LOCK = threading.Lock()


def user_cache_dir() -> Path:
    """Where drape keeps caches that do not belong beside a dataset: ``$DRAPE_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/drape``, else ``~/.cache/drape``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "drape"


def write_error(directory: str | os.PathLike[str]) -> OSError | None:
    """The error creating a file in the existing ``directory`` raises, or None when it can: a
    probe file, so read-only mounts and ACLs count, not only permission bits."""
    probe = Path(directory) / f".drape-probe-{os.getpid()}-{secrets.token_hex(3)}{TMP_SUFFIX}"
    try:
        with open(probe, "wb"):
            pass
        probe.unlink()
    except OSError as error:
        return error
    return None


def directory_is_writable(directory: str | os.PathLike[str]) -> bool:
    """Whether a file can be created in ``directory`` (created with its parents when missing)."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return write_error(directory) is None


def cache_dir_for(root: str | os.PathLike[str], name: str) -> Path:
    """A writable cache directory for dataset ``root``: ``root/cache/<name>`` when it can be
    written, else ``<user cache>/<name>/<first 16 hex of sha256 of root's absolute path>``."""
    local = Path(root) / "cache" / name
    if directory_is_writable(local):
        return local
    return user_cache_dir() / name / _path_key(root)


def _path_key(root: str | os.PathLike[str]) -> str:
    """First 16 hex digits of the sha256 of ``root``'s absolute path: one cache entry per dataset."""
    return hashlib.sha256(os.path.abspath(root).encode()).hexdigest()[:16]


class IntegrityChecker:
    """Checks listed shards of the dataset at ``root`` against their manifest entries.

    ``problem(entry)`` returns None for a sound shard, else ``(kind, message)`` with kind
    "missing", "size" or "checksum" and a message naming the file, the task and what differs.
    """

    def __init__(self, root: str | os.PathLike[str]):
        self.root = Path(root)
        self._cache_file: Path | None = None
        self._digests: dict[str, list] | None = None
        self._deferred = 0  # open batch() blocks: digests are written when the last one ends
        self._unsaved = False

    @contextmanager
    def batch(self):
        """Digests computed inside the block go to the cache file once, when it ends, not after
        each file: the cache is rewritten whole, so saving per file made checking n new shards
        cost n rewrites of an n-entry file."""
        with _CACHE_LOCK:
            self._deferred += 1
        try:
            yield self
        finally:
            with _CACHE_LOCK:
                self._deferred -= 1
                if not self._deferred and self._unsaved:
                    self._save()
                    self._unsaved = False

    # -- cache ---------------------------------------------------------------------------

    def _file(self) -> Path:
        if self._cache_file is None:
            local = self.root / "cache"
            if directory_is_writable(local):
                self._cache_file = local / CACHE_NAME
            else:
                self._cache_file = user_cache_dir() / "integrity" / f"{_path_key(self.root)}.json"
        return self._cache_file

    def _load(self) -> dict[str, list]:
        if self._digests is None:
            self._digests = self._read()
        return self._digests

    def _read(self) -> dict[str, list]:
        try:
            data = json.loads(self._file().read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}
        if not isinstance(data, dict) or data.get("format") != CACHE_FORMAT or not isinstance(data.get("files"), dict):
            return {}
        return {k: v for k, v in data["files"].items() if isinstance(v, list) and len(v) == 4}

    def _save(self) -> None:
        """Writes the cache (merged with what other readers wrote meanwhile); a cache that cannot
        be written is skipped: it only saves time."""
        path = self._file()
        merged = {**self._read(), **(self._digests or {})}
        tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}{TMP_SUFFIX}")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"format": CACHE_FORMAT, "root": os.path.abspath(self.root), "files": merged},
                                      sort_keys=True), encoding="utf-8")
            os.replace(tmp, path)
        except OSError:
            try:
                tmp.unlink()
            except OSError:
                pass

    def digest(self, path: Path) -> str:
        """sha256 of ``path``, from the cache when its size, mtime and inode are unchanged."""
        stat = path.stat()
        key = os.path.relpath(os.path.abspath(path), os.path.abspath(self.root))
        stamp = [int(stat.st_size), int(stat.st_mtime_ns), int(stat.st_ino)]
        with _CACHE_LOCK:
            cached = self._load().get(key)
        if cached is not None and cached[:3] == stamp:
            return str(cached[3])
        digest = file_sha256(path)
        with _CACHE_LOCK:
            self._load()[key] = stamp + [digest]
            if self._deferred:
                self._unsaved = True
            else:
                self._save()
        return digest

    # -- checks --------------------------------------------------------------------------

    def problem(self, entry: Mapping[str, Any]) -> tuple[str, str] | None:
        """What is wrong with a listed shard's file (see the class docstring), or None."""
        path = self.root / entry["path"]
        task = entry["task_id"]
        if not path.is_file():
            return "missing", f"shard {str(path)!r} of task {task!r} is listed in the manifest but does not exist"
        size = path.stat().st_size
        if size != entry["bytes"]:
            return "size", (f"shard {str(path)!r} of task {task!r} has {size} bytes, the manifest lists "
                            f"{entry['bytes']} (truncated or replaced)")
        digest = self.digest(path)
        if digest != entry["sha256"]:
            return "checksum", (f"shard {str(path)!r} of task {task!r} has sha256 {digest[:16]}..., the manifest "
                                f"lists {entry['sha256'][:16]}... (the file is corrupt or was replaced)")
        return None
