"""Training data from drape datasets: a torch Dataset over shards (through
:mod:`data_manifest.reader`), by split, with the TailorNet low/high-frequency split
of the unposed displacements computed once per shard and cached next to the data.

The cache key is the shard's sha256, so a regenerated shard never reuses a stale
cache; the cache is written atomically. It lives in ``<dataset>/cache/low_frequency``, or in
the user cache directory when the dataset cannot be written (a read-only mount, another
user's data; :func:`data_manifest.integrity.cache_dir_for`); a cache that cannot be written
at all (a full disk) is skipped, the split is then computed on every load.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import torch

from data_manifest.integrity import cache_dir_for
from data_manifest.reader import DatasetReader
from learn.common.smoothing import LaplacianSmoother, split_frequencies

#: TailorNet's smoothing (REFERENCE.md): uniform Laplacian, lambda 0.15, 80 iterations.
SMOOTHNESS = 0.15
ITERATIONS = 80


def low_frequency_for_task(reader: DatasetReader, task_id: str, smoother: LaplacianSmoother, *,
                           cache_dir: Path | None = None) -> np.ndarray:
    """Smoothed displacements (F, V, 3) of one shard, computed once and cached."""
    entry = next(e for e in reader.shard_entries if e["task_id"] == task_id)
    cache_dir = Path(cache_dir) if cache_dir is not None else cache_dir_for(reader.root, "low_frequency")
    path = cache_dir / f"{task_id}-{entry['sha256'][:16]}-{smoother.iterations}-{smoother.smoothness:g}.npy"
    if path.is_file():
        try:
            low = np.load(path, allow_pickle=False)
            if low.shape == (entry["frame_count"], *low.shape[1:]) and low.dtype == np.float32:
                return low
        except (OSError, ValueError, EOFError):
            pass  # a damaged cache file is computed again
    d = reader.load_task(task_id)["unposed_displacements"].astype(np.float32)
    low, _ = split_frequencies(torch.from_numpy(d), smoother)
    low = low.numpy().astype(np.float32)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as fh:
            np.save(fh, low)
        os.replace(tmp, path)
    except OSError as error:  # the cache only saves time: go on without it
        try:
            tmp.unlink()
        except OSError:
            pass
        warnings.warn(f"low-frequency cache not written ({error.strerror or error}: {error.filename or cache_dir}); "
                      f"it is computed again at the next load", RuntimeWarning, stacklevel=2)
    return low


class DrapeDataset(torch.utils.data.Dataset):
    """Frames of one split as tensors: ``pose (P,)``, ``shape (S,)``, ``style (G,)``,
    ``displacements (V, 3)`` [m] (unposed, TailorNet Eq. 5), ``low_frequency (V, 3)``
    and ``high_frequency (V, 3)`` (when ``frequencies=True``), ``pair`` (int: which
    style-shape pair), ``posed_vertices (V, 3)``.

    Loads the split into memory (TailorNet-scale splits are a few GB in float32 at
    most; use the reader's ``get`` for larger ones).
    """

    def __init__(self, root: str | os.PathLike, split: str, *, frequencies: bool = True,
                 cache_dir: str | os.PathLike | None = None) -> None:
        self.reader = DatasetReader(root)
        if split not in self.reader.splits:
            raise ValueError(f"unknown split {split!r}; this dataset has {', '.join(sorted(self.reader.splits))}")
        self.split = split
        arrays = self.reader.load_split(split)
        self.pose = torch.from_numpy(arrays["pose"].astype(np.float32))
        self.shape = torch.from_numpy(arrays["shape"].astype(np.float32))
        self.style = torch.from_numpy(arrays["style"].astype(np.float32))
        self.displacements = torch.from_numpy(arrays["unposed_displacements"].astype(np.float32))
        self.posed_vertices = torch.from_numpy(arrays["posed_vertices"].astype(np.float32))
        _, pair = np.unique(np.concatenate([arrays["shape"], arrays["style"]], axis=1), axis=0, return_inverse=True)
        self.pair = torch.from_numpy(pair.reshape(-1).astype(np.int64))
        self.template = self.reader.template
        self.low_frequency = None
        if frequencies and len(self.pose):
            smoother = LaplacianSmoother(self.template["faces"], self.displacements.shape[1],
                                         smoothness=SMOOTHNESS, iterations=ITERATIONS)
            index = self.reader.index(split)
            lows = []
            for shard_no in np.unique(index[:, 0]):
                task_id = self.reader.shard_entries[shard_no]["task_id"]
                rows = index[index[:, 0] == shard_no, 1]
                lows.append(low_frequency_for_task(self.reader, task_id, smoother, cache_dir=cache_dir)[rows])
            self.low_frequency = torch.from_numpy(np.concatenate(lows))

    def __len__(self) -> int:
        return int(self.pose.shape[0])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = {"pose": self.pose[i], "shape": self.shape[i], "style": self.style[i],
                "displacements": self.displacements[i], "posed_vertices": self.posed_vertices[i], "pair": self.pair[i]}
        if self.low_frequency is not None:
            item["low_frequency"] = self.low_frequency[i]
            item["high_frequency"] = self.displacements[i] - self.low_frequency[i]
        return item
