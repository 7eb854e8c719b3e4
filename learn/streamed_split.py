"""A training split that is never held whole: its per-frame vectors in memory, its per-vertex
arrays read from the shards when a loop asks for them.

:class:`StreamedSplit` stands where the learners take a :class:`learn.data.FrameArrays`
(``drape train --data-mode stream``). It holds ``pose (N, P)``, ``shape (N, S)``, ``style (N, G)``
and ``pair_id (N,)`` (P + S + G floats a frame), read in one pass over the shards' small datasets; the per-vertex arrays (``displacements``,
``posed_vertices``, ``low_frequency``: 3 x 7,744 x 3 float32 = 279 KB per t-shirt frame) stay in
the shards and reach the epoch loops through :class:`learn.batches.StreamBatches`, or, for the few
frames a learner needs at once (one frame per style-shape pair, the prototype pairs' frames), through
:meth:`StreamedSplit.subset`.

:func:`choose_data_mode` resolves ``auto``: stream when the per-vertex arrays the in-memory path
holds exceed :data:`MEMORY_SHARE` of the memory available to this process.
"""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import torch

from data_manifest.integrity import cache_dir_for
from data_manifest.reader import DatasetReader
from data_manifest.schema import POSE, POSED_VERTICES, SHAPE, STYLE
from learn.common.smoothing import LaplacianSmoother
from learn.data import ITERATIONS, SMOOTHNESS, FrameArrays, low_frequency_for_task

DATA_MODES = ("auto", "memory", "stream")
#: ``auto`` streams when the in-memory split would take more than this share of the available memory.
MEMORY_SHARE = 0.5
#: Per-vertex float32 arrays the in-memory path holds per frame: displacements, posed vertices and
#: (TailorNet) the low-frequency part.
ARRAYS_IN_MEMORY = 3


class StreamedSplit:
    """Split ``split`` of the dataset at ``root`` for the epoch loops (see the module docstring).

    workers: ``DataLoader`` worker processes of each streamed epoch (default: the usable CPUs
    of this process's share of the host, at most 4; 0 reads in the training process).
    cache_dir: the low-frequency cache (default: :func:`data_manifest.integrity.cache_dir_for`).
    Building it opens every shard of the split once for its small datasets and closes it: no
    HDF5 handle is open when a loader forks its workers.
    """

    def __init__(self, root: str | os.PathLike, split: str, *, workers: int | None = None,
                 cache_dir: str | os.PathLike | None = None) -> None:
        reader = DatasetReader(root)
        self.root = Path(root)
        self.split = split
        index = reader.index(split)  # unknown split: the reader's error, listing the available ones
        self.frame_count = int(index.shape[0])
        self.entries = [entry for entry in reader.shard_entries if split in entry["splits"] and entry["frame_count"] > 0]
        if workers is None:
            local = int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1)
            workers = min(4, max(1, len(os.sched_getaffinity(0)) // max(1, local)))
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise ValueError(f"workers must be an integer >= 0 (got {workers!r})")
        self.workers = workers
        self.cache_dir = Path(cache_dir) if cache_dir is not None else cache_dir_for(self.root, "low_frequency")
        self.template = reader.template
        reader.close()  # the template's shard: no handle stays open in this process
        self.vertex_count = int(self.template["rest_vertices"].shape[0])
        pose, shape, style = [], [], []
        for entry in self.entries:
            with h5py.File(self.root / entry["path"], "r") as handle:
                frames = int(handle[POSED_VERTICES].shape[0])
                if frames != int(entry["frame_count"]):
                    raise ValueError(f"shard {entry['path']} holds {frames} frames, the manifest lists "
                                     f"{entry['frame_count']}; run `drape dataset validate {self.root}`")
                pose.append(np.asarray(handle[POSE][()], np.float32))
                shape.append(np.repeat(np.asarray(handle[SHAPE][()], np.float32)[None], frames, axis=0))
                style.append(np.repeat(np.asarray(handle[STYLE][()], np.float32)[None], frames, axis=0))
        if not self.entries:
            raise ValueError(f"split {split!r} of {self.root} has no frames")
        self.pose, self.shape, self.style = (np.concatenate(a) for a in (pose, shape, style))
        # pair ids as DrapeDataset numbers them: the rank of (shape, style) among the split's distinct ones
        _, pair = np.unique(np.concatenate([self.shape, self.style], axis=1), axis=0, return_inverse=True)
        self.pair_id = pair.reshape(-1).astype(np.int64)
        self.translation = None  # as DrapeDataset: the learners see the shards' posed vertices as stored
        self.low_frequency_ready = False
        self._rows = np.concatenate([[0], np.cumsum([int(e["frame_count"]) for e in self.entries])])

    def smoother(self) -> LaplacianSmoother:
        """TailorNet's smoothing on this garment, with the settings of the low-frequency cache."""
        return LaplacianSmoother(self.template["faces"], self.vertex_count, smoothness=SMOOTHNESS, iterations=ITERATIONS)

    def prepare_low_frequency(self, device: str | torch.device = "cpu", *, rank: int = 0, world_size: int = 1) -> None:
        """Compute and cache the low-frequency part of every shard without a cache file, one shard
        at a time on ``device`` (the whole-split pre-pass TailorNet needs: its LF and HF targets);
        shard ``k`` by rank ``k mod world_size``. Callers meet at a barrier before streaming."""
        reader = DatasetReader(self.root)
        smoother = self.smoother()
        try:
            for entry in self.entries[rank::world_size]:
                low_frequency_for_task(reader, entry["task_id"], smoother, cache_dir=self.cache_dir, device=device)
        finally:
            reader.close()
        self.low_frequency_ready = True

    def subset(self, frames: np.ndarray):
        """Frames ``frames`` (indices into the split) as an in-memory ``FrameArrays``, with
        ``posed_vertices`` and, after :meth:`prepare_low_frequency`, ``low_frequency``; read shard
        by shard, each shard opened once. For the few frames a learner needs at once."""
        frames = np.asarray(frames, dtype=np.int64).reshape(-1)
        if frames.size and (frames.min() < 0 or frames.max() >= self.frame_count):
            raise IndexError(f"frames must lie in [0, {self.frame_count}) (got {frames.min()}..{frames.max()})")
        shard_of = np.searchsorted(self._rows, frames, side="right") - 1
        out = {name: np.empty((frames.size, self.vertex_count, 3), np.float32)
               for name in ("displacements", "posed_vertices", "low_frequency")}
        reader = DatasetReader(self.root)
        smoother = self.smoother() if self.low_frequency_ready else None
        try:
            for shard in np.unique(shard_of):
                entry = self.entries[int(shard)]
                where = np.flatnonzero(shard_of == shard)
                rows = frames[where] - self._rows[shard]
                arrays = reader.load_task(entry["task_id"])
                out["displacements"][where] = arrays["unposed_displacements"][rows]
                out["posed_vertices"][where] = arrays["posed_vertices"][rows]
                if smoother is not None:
                    low = low_frequency_for_task(reader, entry["task_id"], smoother, cache_dir=self.cache_dir,
                                                 displacements=arrays["unposed_displacements"])
                    out["low_frequency"][where] = low[rows]
        finally:
            reader.close()
        return FrameArrays(pose=self.pose[frames], shape=self.shape[frames], style=self.style[frames],
                           displacements=out["displacements"], pair_id=self.pair_id[frames],
                           low_frequency=out["low_frequency"] if smoother is not None else None,
                           posed_vertices=out["posed_vertices"])


def split_bytes(reader: DatasetReader, split: str, arrays: int = ARRAYS_IN_MEMORY) -> int:
    """Bytes of the per-vertex float32 arrays the in-memory path holds for ``split``: frames x
    vertices x 3 x 4 x ``arrays``."""
    vertices = int(reader.template["rest_vertices"].shape[0])
    return int(reader.num_frames(split)) * vertices * 3 * 4 * int(arrays)


def available_memory_bytes() -> int:
    """Memory available to this process [bytes]: ``MemAvailable`` of /proc/meminfo (Linux), else
    the free physical pages; divided among the ranks of this host under torchrun
    (``LOCAL_WORLD_SIZE``), each of which loads its own copy."""
    available = None
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if available is None:
        available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return available // max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1))


def choose_data_mode(mode: str, frame_bytes: int, available_bytes: int | None = None) -> str:
    """``memory`` or ``stream`` for ``mode`` (one of :data:`DATA_MODES`): ``auto`` streams when
    ``frame_bytes`` (:func:`split_bytes`) exceed :data:`MEMORY_SHARE` of ``available_bytes``
    (default :func:`available_memory_bytes`)."""
    if mode not in DATA_MODES:
        raise ValueError(f"data mode must be one of {', '.join(DATA_MODES)} (got {mode!r})")
    if mode != "auto":
        return mode
    available = available_memory_bytes() if available_bytes is None else int(available_bytes)
    return "stream" if frame_bytes > MEMORY_SHARE * available else "memory"
