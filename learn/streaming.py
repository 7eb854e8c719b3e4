"""A split streamed from its shards, for datasets larger than memory.

:class:`StreamingDrapeDataset` is a ``torch.utils.data.IterableDataset``: each
``DataLoader`` worker of each rank reads its own shards, one at a time, and yields their
frames as the dicts :class:`learn.data.DrapeDataset` gives. Constructing it reads only the
manifest: no HDF5 file is opened in the process that forks the workers (a handle open at
fork cannot serve the children), each worker opens its shards when it first iterates.

Shards are dealt by position: in an epoch's shard order, shard ``k`` goes to the consumer
``k mod (world_size * num_workers)``, consumer ``rank * num_workers + worker_id``. So each
frame of the split is yielded once per epoch over all ranks and workers; ranks may receive
different frame counts (shards differ in length), so a distributed loop must not assume
equal batch counts. With ``shuffle=True`` the shard order and the frames within each shard
are permuted from ``(seed, epoch)`` (:meth:`set_epoch`), identically on every rank.

``pair`` (the style-shape pair id, as in ``DrapeDataset``: the rank of the frame's (shape,
style) among the split's distinct ones) needs every shard's shape and style: a worker reads
those small arrays from every shard of the split once, without the integrity hash (the
frames it yields come from shards it checks when it opens them).
"""

from __future__ import annotations

import os
from collections.abc import Collection, Iterator
from pathlib import Path

import h5py
import numpy as np
import torch

from data_manifest.integrity import cache_dir_for
from data_manifest.reader import DatasetReader
from data_manifest.schema import SHAPE, STYLE
from learn.common.smoothing import LaplacianSmoother
from learn.data import ITERATIONS, SMOOTHNESS, low_frequency_for_task


#: The keys a :class:`StreamingDrapeDataset` item can hold.
ITEM_FIELDS = ("pose", "shape", "style", "displacements", "posed_vertices", "pair", "frame", "low_frequency",
               "high_frequency")


def distributed_rank() -> tuple[int, int]:
    """(rank, world size) from ``torch.distributed`` when it is initialised, else (0, 1)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


def _check_int(value: object, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum} (got {value!r})")
    return int(value)


class StreamingDrapeDataset(torch.utils.data.IterableDataset):
    """Frames of ``split`` of the dataset at ``root``, streamed shard by shard.

    Yields dicts with ``pose (P,)``, ``shape (S,)``, ``style (G,)``, ``displacements (V, 3)``
    [m], ``posed_vertices (V, 3)`` [m], ``pair`` (int64), ``low_frequency`` and
    ``high_frequency (V, 3)`` [m] when ``frequencies=True`` (from the per-shard cache of
    :mod:`learn.data`, computed on the worker's CPU when absent), and ``frame`` (int64, the
    frame's row in ``DatasetReader.index(split)``: ``DrapeDataset(root, split)[frame]`` holds
    the same values).

    rank, world_size: this process's share of the shards; default from ``torch.distributed``
    (:func:`distributed_rank`). shuffle, seed: per-epoch permutation of the shard order and
    of the frames within each shard; :meth:`set_epoch` before each epoch. fields: the keys
    each item holds (default all of the above); a loop that needs a few arrays collates only
    those, and without ``pair`` no worker reads the split's pair table.
    """

    def __init__(self, root: str | os.PathLike, split: str, *, frequencies: bool = False, shuffle: bool = False,
                 seed: int = 0, rank: int | None = None, world_size: int | None = None,
                 cache_dir: str | os.PathLike | None = None, fields: Collection[str] | None = None) -> None:
        super().__init__()
        self.reader = DatasetReader(root)  # the manifest only: files open lazily, in the process that reads
        self.root = Path(root)
        self.split = split
        self.index = self.reader.index(split)  # unknown split: the reader's error, listing the available ones
        self.frequencies = bool(frequencies)
        self.shuffle = bool(shuffle)
        self.seed = _check_int(seed, "seed", 0)
        default_rank, default_world = distributed_rank()
        self.world_size = default_world if world_size is None else _check_int(world_size, "world_size", 1)
        self.rank = default_rank if rank is None else _check_int(rank, "rank", 0)
        if self.rank >= self.world_size:
            raise ValueError(f"rank must be < world_size={self.world_size} (got {self.rank})")
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.epoch = 0
        entries = self.reader.shard_entries
        self.shards = [number for number, entry in enumerate(entries)
                       if self.split in entry["splits"] and entry["frame_count"] > 0]
        # first row of each shard in index(split)
        self._first_row = {int(number): int(np.flatnonzero(self.index[:, 0] == number)[0]) for number in self.shards}
        self._pairs: dict[int, int] | None = None
        known = set(ITEM_FIELDS) - (set() if self.frequencies else {"low_frequency", "high_frequency"})
        self.fields = tuple(sorted(known)) if fields is None else tuple(fields)
        unknown = sorted(set(self.fields) - known)
        if unknown:
            raise ValueError(f"fields {unknown} are not items of this dataset; expected among {sorted(known)}"
                             + ("" if self.frequencies else " (low_frequency, high_frequency need frequencies=True)"))

    def __len__(self) -> int:
        """Frames of the whole split (all ranks and workers together)."""
        return int(self.index.shape[0])

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose shuffled order the next iteration follows."""
        self.epoch = _check_int(epoch, "epoch", 0)

    def _rng(self, *salt: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.epoch, *salt])

    def shard_order(self) -> list[int]:
        """This epoch's shard numbers in dealing order (the same on every rank and worker)."""
        order = list(self.shards)
        if self.shuffle:
            order = [order[k] for k in self._rng().permutation(len(order))]
        return order

    def shards_for(self, rank: int, worker: int, num_workers: int) -> list[int]:
        """Shard numbers read by ``worker`` of ``num_workers`` on ``rank``, in reading order."""
        consumers = self.world_size * num_workers
        consumer = rank * num_workers + worker
        return self.shard_order()[consumer::consumers]

    def frames_for(self, rank: int, worker: int, num_workers: int) -> list[int]:
        """Frame counts of the shards ``worker`` of ``num_workers`` on ``rank`` reads (in reading order)."""
        entries = self.reader.shard_entries
        return [int(entries[number]["frame_count"]) for number in self.shards_for(rank, worker, num_workers)]

    def _pair_table(self) -> dict[int, int]:
        """shard number -> pair id (rank of its (shape, style) among the split's distinct ones)."""
        if self._pairs is None:
            keys = []
            for number in self.shards:
                with h5py.File(self.root / self.reader.shard_entries[number]["path"], "r") as handle:
                    keys.append(np.concatenate([np.asarray(handle[SHAPE][()], np.float32).reshape(-1),
                                                np.asarray(handle[STYLE][()], np.float32).reshape(-1)]))
            _, pair = np.unique(np.stack(keys), axis=0, return_inverse=True)
            self._pairs = dict(zip(self.shards, (int(p) for p in pair.reshape(-1))))
        return self._pairs

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        info = torch.utils.data.get_worker_info()
        worker, num_workers = (0, 1) if info is None else (info.id, info.num_workers)
        want = set(self.fields)
        pairs = self._pair_table() if "pair" in want else None
        frequencies = self.frequencies and bool(want & {"low_frequency", "high_frequency"})
        smoother = None
        cache_dir = self.cache_dir
        for number in self.shards_for(self.rank, worker, num_workers):
            task_id = self.reader.shard_entries[number]["task_id"]
            arrays = self.reader.load_task(task_id)
            frames = arrays["pose"].shape[0]
            tensors = {
                "pose": torch.from_numpy(arrays["pose"]),
                "shape": torch.from_numpy(arrays["shape"]),
                "style": torch.from_numpy(arrays["style"]),
                "displacements": torch.from_numpy(arrays["unposed_displacements"]),
                "posed_vertices": torch.from_numpy(arrays["posed_vertices"]),
            }
            if frequencies:
                if smoother is None:
                    template = self.reader.template
                    smoother = LaplacianSmoother(template["faces"], tensors["displacements"].shape[1],
                                                 smoothness=SMOOTHNESS, iterations=ITERATIONS)
                    cache_dir = cache_dir or cache_dir_for(self.root, "low_frequency")
                tensors["low_frequency"] = torch.from_numpy(
                    low_frequency_for_task(self.reader, task_id, smoother, cache_dir=cache_dir,
                                           displacements=arrays["unposed_displacements"]))
            rows = self._rng(number).permutation(frames) if self.shuffle else np.arange(frames)
            pair = None if pairs is None else torch.tensor(pairs[number], dtype=torch.int64)
            first = self._first_row[number]
            for row in rows:
                item = {key: value[int(row)] for key, value in tensors.items() if key in want}
                if "high_frequency" in want:
                    item["high_frequency"] = tensors["displacements"][int(row)] - tensors["low_frequency"][int(row)]
                if pair is not None:
                    item["pair"] = pair
                if "frame" in want:
                    item["frame"] = torch.tensor(first + int(row), dtype=torch.int64)
                yield item
        self.reader.close()
