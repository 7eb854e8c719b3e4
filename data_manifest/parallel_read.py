"""A split's frames read from its shards by several processes at once.

h5py serialises every HDF5 call behind one lock and keeps the GIL while gzip/lzf chunks are
decompressed, so threads read shards no faster than one thread (measured: 8 shards of 100
frames x 7,744 vertices, 2.29 s with 1 thread, 2.12 s with 4). Shards are therefore read
by a pool of ``spawn``-ed processes, one shard per job, each process with its own
``DatasetReader``, made once when the process starts (no HDF5 state is inherited: a file open
in the parent, the template's shard for instance, would otherwise be shared with the children
through HDF5's open-file list). The arrays come back through the pool's pipe and are copied once into the stacked
result.

Integrity (size and sha256 against the manifest, ``integrity.IntegrityChecker``) is checked
in the calling process before any shard is read, by a thread pool: ``hashlib`` releases the
GIL, so hashing does run in parallel, and the digest cache is written by one process. A
script that calls this must guard its entry point with ``if __name__ == "__main__":`` (the
``spawn`` start method imports the main module in each child).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Collection
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from .integrity import IntegrityChecker
from .reader import DatasetReader, per_vertex_names
from .schema import QUALITY_GROUP, CorruptShardError, MissingShardError

#: Below this many bytes of shards a split is read in the calling process: starting the
#: processes (about 0.5 s each, importing numpy and h5py) costs more than it saves.
MIN_PARALLEL_BYTES = 64 * 2**20


def default_workers() -> int:
    """Processes used by :func:`load_split_parallel` when not told: the CPUs this process may
    use, at most 16."""
    try:
        count = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        count = os.cpu_count() or 1
    return max(1, min(16, count))


_READER: dict[str, DatasetReader] = {}
"""The pool process's reader of the dataset, one per process: loading the manifest for each
shard cost more than reading it (0.08 s for a 2,000-shard manifest against ~12 frames a shard)."""


def _open_reader(root: str) -> None:
    """Pool initializer: the dataset's reader, once per process (integrity was checked by the caller)."""
    _READER[root] = DatasetReader(root, integrity=False)


def _read_task(root: str, task_id: str, per_vertex: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """One shard's arrays (``DatasetReader.load_task``), in a pool process; its file is closed
    after the read (a process reads many shards, one at a time)."""
    reader = _READER[root]
    try:
        return reader.load_task(task_id, per_vertex)
    finally:
        reader.close()


def check_integrity(root: str | os.PathLike[str], entries: list[dict[str, Any]], *, threads: int) -> None:
    """Check each shard entry's file (size, sha256) against the manifest; raise
    MissingShardError / CorruptShardError naming the file and task, as ``DatasetReader`` does."""
    checker = IntegrityChecker(root)
    with checker.batch(), ThreadPoolExecutor(max(1, threads)) as pool:
        problems = list(pool.map(checker.problem, entries))
    for problem in problems:
        if problem is not None:
            kind, message = problem
            raise (MissingShardError if kind == "missing" else CorruptShardError)(
                f"{message}; run `drape dataset validate {root}`")


def load_split_parallel(root: str | os.PathLike[str], split: str, *, workers: int | None = None,
                        min_parallel_bytes: int = MIN_PARALLEL_BYTES, integrity: bool = True,
                        per_vertex: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """``DatasetReader(root).load_split(split, per_vertex)``, same keys, shapes, dtypes and values,
    with the shards read by ``workers`` processes (default :func:`default_workers`). Splits of fewer
    than ``min_parallel_bytes`` bytes of shards, or of one shard, are read in this process.
    Errors are the reader's (unknown split: ValueError listing the available ones)."""
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be an integer >= 1 (got {workers!r})")
    reader = DatasetReader(root, integrity=integrity)
    reader.index(split)  # unknown split: the reader's error
    entries = [entry for entry in reader.shard_entries if split in entry["splits"] and entry["frame_count"] > 0]
    workers = default_workers() if workers is None else workers
    total_bytes = sum(int(entry["bytes"]) for entry in entries)
    per_vertex = None if per_vertex is None else per_vertex_names(per_vertex)
    if workers == 1 or len(entries) < 2 or total_bytes < min_parallel_bytes:
        with reader:
            return reader.load_split(split, per_vertex)
    if integrity:
        check_integrity(root, entries, threads=workers)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(workers, len(entries)), mp_context=context,
                             initializer=_open_reader, initargs=(str(Path(root)),)) as pool:
        futures = [pool.submit(_read_task, str(Path(root)), entry["task_id"], per_vertex) for entry in entries]
        return _stack([future.result() for future in futures], entries, split)


def _stack(parts: list[dict[str, np.ndarray]], entries: list[dict[str, Any]], split: str) -> dict[str, np.ndarray]:
    """Shards' arrays stacked in manifest order, with ``load_split``'s rules: every shard must
    have the same quality metrics; ``body_translation`` is kept when every shard has it."""
    metrics = sorted(key for key in parts[0] if key.startswith(f"{QUALITY_GROUP}/"))
    keys = set(parts[0])
    for part, entry in zip(parts[1:], entries[1:]):
        mine = sorted(key for key in part if key.startswith(f"{QUALITY_GROUP}/"))
        if mine != metrics:
            raise ValueError(f"shards of split {split!r} disagree on quality metrics: {entry['task_id']!r} has "
                             f"{mine}, earlier shards {metrics}")
        keys &= set(part)
    total = sum(part["pose"].shape[0] for part in parts)
    out: dict[str, np.ndarray] = {}
    for key in sorted(keys):
        first = parts[0][key]
        stacked = np.empty((total, *first.shape[1:]), dtype=first.dtype)
        row = 0
        for part in parts:
            block = part.pop(key)  # free each shard's copy as soon as it is stacked
            stacked[row:row + block.shape[0]] = block
            row += block.shape[0]
        out[key] = stacked
    return out
