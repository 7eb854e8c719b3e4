"""Training data from drape datasets: a torch Dataset over shards (through
:mod:`data_manifest.reader`), by split, with the TailorNet low/high-frequency split
of the unposed displacements computed once per shard and cached next to the data.

The split is read by several processes (:mod:`data_manifest.parallel_read`) and the
low-frequency smoothing of every uncached shard runs as a few large batches on the training
device (:func:`low_frequency_for_split`). :mod:`learn.streaming` serves splits larger than
memory from the same shards and the same cache.

The cache key is the shard's sha256, so a regenerated shard never reuses a stale
cache; the cache is written atomically. It lives in ``<dataset>/cache/low_frequency``, or in
the user cache directory when the dataset cannot be written (a read-only mount, another
user's data; :func:`data_manifest.integrity.cache_dir_for`); a cache that cannot be written
at all (a full disk) is skipped, the split is then computed on every load.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
import warnings
from pathlib import Path

import numpy as np
import torch

from data_manifest.integrity import cache_dir_for
from data_manifest.parallel_read import load_split_parallel
from data_manifest.reader import DatasetReader
from learn.common.smoothing import LaplacianSmoother, split_frequencies

#: TailorNet's smoothing (REFERENCE.md): uniform Laplacian, lambda 0.15, 80 iterations.
SMOOTHNESS = 0.15
ITERATIONS = 80
#: Frames per smoothing batch are bounded so one batch holds at most this many bytes of float32.
BATCH_BYTES = 256 * 2**20


def _cache_path(cache_dir: Path, entry: dict, smoother: LaplacianSmoother) -> Path:
    return cache_dir / f"{entry['task_id']}-{entry['sha256'][:16]}-{smoother.iterations}-{smoother.smoothness:g}.npy"


def _read_cache(path: Path, frames: int, vertices: int) -> np.ndarray | None:
    """A cached (frames, vertices, 3) float32 array, or None when absent or damaged."""
    if not path.is_file():
        return None
    try:
        low = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None  # a damaged cache file is computed again
    return low if low.shape == (frames, vertices, 3) and low.dtype == np.float32 else None


def _write_cache(path: Path, low: np.ndarray) -> None:
    """Write ``low`` to ``path`` atomically; a cache that cannot be written is skipped with a warning."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as fh:
            np.save(fh, low)
        os.replace(tmp, path)
    except OSError as error:  # the cache only saves time: go on without it
        try:
            tmp.unlink()
        except OSError:
            pass
        warnings.warn(f"low-frequency cache not written ({error.strerror or error}: {error.filename or path.parent}); "
                      f"it is computed again at the next load", RuntimeWarning, stacklevel=3)


def low_frequency_for_task(reader: DatasetReader, task_id: str, smoother: LaplacianSmoother, *,
                           cache_dir: Path | None = None, device: str | torch.device = "cpu",
                           displacements: np.ndarray | None = None) -> np.ndarray:
    """Smoothed displacements (F, V, 3) [m] of one shard, float32, computed once (on ``device``)
    and cached. ``displacements``: the shard's unposed displacements (F, V, 3) [m] when the
    caller has read them (else they are read from the shard)."""
    entry = reader.shard_entries[reader.shard_no(task_id)]
    cache_dir = Path(cache_dir) if cache_dir is not None else cache_dir_for(reader.root, "low_frequency")
    path = _cache_path(cache_dir, entry, smoother)
    low = _read_cache(path, int(entry["frame_count"]), smoother.vertex_count)
    if low is not None:
        return low
    if displacements is None:
        displacements = reader.load_task(task_id)["unposed_displacements"]
    low = _smooth(displacements, smoother, device)
    _write_cache(path, low)
    return low


def _smooth(displacements: np.ndarray, smoother: LaplacianSmoother, device: str | torch.device) -> np.ndarray:
    """Low-frequency part (N, V, 3) float32 of displacements (N, V, 3), in batches of at most
    :data:`BATCH_BYTES` on ``device``. On the CPU the smoother's scipy path (float64) runs:
    torch's CPU sparse product is 10-150x slower (measured: 1,793 vertices, 27 columns, 23 ms
    against 0.15 ms) and float32 rounding is the only difference."""
    out = np.empty(displacements.shape, dtype=np.float32)
    frames = max(1, BATCH_BYTES // max(1, displacements.shape[1] * 3 * 4))
    on_cpu = torch.device(device).type == "cpu"
    for start in range(0, displacements.shape[0], frames):
        block = np.ascontiguousarray(displacements[start:start + frames], dtype=np.float32)
        if on_cpu:
            out[start:start + frames] = split_frequencies(block, smoother)[0]
        else:
            low, _ = split_frequencies(torch.from_numpy(block).to(device), smoother)
            out[start:start + frames] = low.cpu().numpy()
    return out


def low_frequency_for_split(reader: DatasetReader, split: str, displacements: np.ndarray,
                            smoother: LaplacianSmoother, *, device: str | torch.device = "cpu",
                            cache_dir: str | os.PathLike | None = None) -> np.ndarray:
    """Smoothed displacements (N, V, 3) [m] float32 of ``split``, whose displacements (N, V, 3)
    [m] in ``reader.index(split)`` order are given. Shards with a cache file (keyed by the
    shard's sha256 and the smoothing settings) are read from it; the others are smoothed
    together, in batches of at most :data:`BATCH_BYTES` on ``device``, and cached one file per
    shard. Each frame's result depends on that frame only, so it matches
    :func:`low_frequency_for_task` (to float32 rounding of the device's sparse product)."""
    cache_dir = Path(cache_dir) if cache_dir is not None else cache_dir_for(reader.root, "low_frequency")
    entries = [entry for entry in reader.shard_entries if split in entry["splits"] and entry["frame_count"] > 0]
    out = np.empty(displacements.shape, dtype=np.float32)
    missing: list[tuple[dict, int, int]] = []
    row = 0
    for entry in entries:
        count = int(entry["frame_count"])
        low = _read_cache(_cache_path(cache_dir, entry, smoother), count, smoother.vertex_count)
        if low is None:
            missing.append((entry, row, count))
        else:
            out[row:row + count] = low
        row += count
    if row != displacements.shape[0]:
        raise ValueError(f"displacements hold {displacements.shape[0]} frames, split {split!r} has {row}")
    if missing:
        rows = np.concatenate([np.arange(start, start + count) for _, start, count in missing])
        contiguous = rows.size == displacements.shape[0]
        out[rows] = _smooth(displacements if contiguous else displacements[rows], smoother, device)
        for entry, start, count in missing:
            _write_cache(_cache_path(cache_dir, entry, smoother), out[start:start + count])
    return out


class DrapeDataset(torch.utils.data.Dataset):
    """Frames of one split as tensors: ``pose (P,)``, ``shape (S,)``, ``style (G,)``,
    ``displacements (V, 3)`` [m] (unposed, TailorNet Eq. 5), ``low_frequency (V, 3)``
    and ``high_frequency (V, 3)`` (when ``frequencies=True``), ``pair`` (int: which
    style-shape pair), ``posed_vertices (V, 3)`` (unless ``posed=False``: training that needs only
    the displacements reads half the bytes; the attribute is then None). Attributes ``sequence`` and ``frame_index`` (N,)
    int64 give each frame's shard (one task: one sequence) and its index in it; ``root_joint``
    (N, 3) [m] is set where every shard stores it (motion datasets), else None.

    Loads the split into memory (TailorNet-scale splits are a few GB in float32 at most;
    :class:`learn.streaming.StreamingDrapeDataset` serves larger ones). ``workers``: processes
    reading the shards (default: the usable CPUs, at most 16; small splits are read in this
    process, :func:`data_manifest.parallel_read.load_split_parallel`). ``device``: where the
    low-frequency smoothing of uncached shards runs (the tensors stay on the CPU).
    """

    def __init__(self, root: str | os.PathLike, split: str, *, frequencies: bool = True,
                 cache_dir: str | os.PathLike | None = None, device: str | torch.device = "cpu",
                 workers: int | None = None, posed: bool = True) -> None:
        self.reader = DatasetReader(root)
        if split not in self.reader.splits:
            raise ValueError(f"unknown split {split!r}; this dataset has {', '.join(sorted(self.reader.splits))}")
        self.split = split
        # the (N, V, 3) arrays are nearly all of the bytes: read those used (velocities never are)
        wanted = ("posed_vertices", "unposed_displacements") if posed else ("unposed_displacements",)
        arrays = load_split_parallel(root, split, workers=workers, per_vertex=wanted)

        def tensor(name: str) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(arrays[name], dtype=np.float32))

        self.pose, self.shape, self.style = tensor("pose"), tensor("shape"), tensor("style")
        self.displacements = tensor("unposed_displacements")
        self.posed_vertices = tensor("posed_vertices") if posed else None
        _, pair = np.unique(np.concatenate([arrays["shape"], arrays["style"]], axis=1), axis=0, return_inverse=True)
        self.pair = torch.from_numpy(pair.reshape(-1).astype(np.int64))
        self.sequence = torch.from_numpy(np.asarray(arrays["shard_no"], dtype=np.int64))
        self.frame_index = torch.from_numpy(np.asarray(arrays["frame_index"], dtype=np.int64))
        self.root_joint = tensor("root_joint") if "root_joint" in arrays else None
        self.template = self.reader.template
        self.low_frequency = None
        if frequencies and len(self.pose):
            smoother = LaplacianSmoother(self.template["faces"], self.displacements.shape[1],
                                         smoothness=SMOOTHNESS, iterations=ITERATIONS)
            self.low_frequency = torch.from_numpy(low_frequency_for_split(
                self.reader, split, arrays["unposed_displacements"], smoother, device=device, cache_dir=cache_dir))

    def __len__(self) -> int:
        return int(self.pose.shape[0])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = {"pose": self.pose[i], "shape": self.shape[i], "style": self.style[i],
                "displacements": self.displacements[i], "pair": self.pair[i]}
        if self.posed_vertices is not None:
            item["posed_vertices"] = self.posed_vertices[i]
        if self.low_frequency is not None:
            item["low_frequency"] = self.low_frequency[i]
            item["high_frequency"] = self.displacements[i] - self.low_frequency[i]
        return item


@dataclass
class FrameArrays:
    """Frames of one split, as arrays.

    pose: axis-angle pose, shape (N, P); shape: (N, S); style: (N, G);
    displacements: unposed displacements [m], shape (N, V, 3);
    pair_id: style-shape pair of each frame, 0..X-1, shape (N,);
    low_frequency: smoothed displacements [m], shape (N, V, 3), filled on demand;
    posed_vertices: simulated posed garment [m], shape (N, V, 3), optional (evaluation).
    translation: body root translation [m] added after skinning, shape (N, 3), optional.
    sequence, frame_index: which sequence (shard) each frame belongs to and its index in it,
    shape (N,) int64 each, optional (the recurrent collision-aware regressor runs sequences).
    root_joint: the body's root joint position [m] of motion datasets, shape (N, 3), optional.
    """

    pose: np.ndarray
    shape: np.ndarray
    style: np.ndarray
    displacements: np.ndarray
    pair_id: np.ndarray
    low_frequency: np.ndarray | None = None
    posed_vertices: np.ndarray | None = None
    translation: np.ndarray | None = None
    sequence: np.ndarray | None = None
    frame_index: np.ndarray | None = None
    root_joint: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.pose.shape[0]
        for name in ("shape", "style", "displacements", "pair_id"):
            if getattr(self, name).shape[0] != n:
                raise ValueError(
                    f"FrameArrays.{name} has {getattr(self, name).shape[0]} frames, pose has {n}"
                )
        if self.displacements.ndim != 3 or self.displacements.shape[-1] != 3:
            raise ValueError(
                f"FrameArrays.displacements must have shape (N, V, 3), got {self.displacements.shape}"
            )

    @property
    def frame_count(self) -> int:
        return int(self.pose.shape[0])

    @property
    def vertex_count(self) -> int:
        return int(self.displacements.shape[1])

    def subset(self, frames: np.ndarray) -> FrameArrays:
        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[frames]

        return FrameArrays(
            pose=self.pose[frames],
            shape=self.shape[frames],
            style=self.style[frames],
            displacements=self.displacements[frames],
            pair_id=self.pair_id[frames],
            low_frequency=pick(self.low_frequency),
            posed_vertices=pick(self.posed_vertices),
            translation=pick(self.translation),
            sequence=pick(self.sequence),
            frame_index=pick(self.frame_index),
            root_joint=pick(self.root_joint),
        )
