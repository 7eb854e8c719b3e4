"""Mini-batches of a split's frames for the learners' epoch loops, from memory or streamed.

An epoch function (:func:`learn.tailornet.train.run_epochs`) takes its steps from
``source.epoch(generator, optimizer)``, ``source`` being :func:`batches_for`'s answer for the
learner's training data:

- :class:`MemoryBatches` over arrays in memory (a ``FrameArrays``): the epoch's order is one
  ``torch.randperm`` drawn from the loop's generator (``arange`` without shuffling), batches are
  gathered by device-side indexing, and under data parallelism each global batch is dealt over the
  ranks (:func:`learn.distributed.shard`);
- :class:`StreamBatches` over a :class:`learn.streamed_split.StreamedSplit`: each epoch one
  ``DataLoader`` over a :class:`learn.streaming.StreamingDrapeDataset` whose order seed is drawn
  from the loop's generator (so a resumed run streams what an uninterrupted one streams). Shards
  are dealt over ranks and workers, each rank reads batches of ``ceil(batch_size / ranks)`` frames
  of its own shards, and each rank's gradient is weighted by its frames over the step's frames
  (:func:`learn.distributed.share_of_frames`).

Unequal ranks. Shards differ in length and in number per rank, so ranks may have different
batch counts in an epoch. Every rank computes from the manifest how many batches every rank's
loader yields (the dealing is a function of the epoch's seed) and all run the largest count: a rank
out of batches takes zero-weight steps, without a forward pass, entering the share's all-reduce
and the optimizer's gradient sum like the others. An epoch function must therefore run no
collective of its own between two steps.

Batches are :class:`Batch` dicts of tensors on the training device with ``frames``, this rank's
frame count in the step (0 in a zero-weight step of the in-memory deal).
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch

from learn import distributed


class Batch(dict):
    """Tensors of one step's frames (name -> (b, ...)) on the training device; ``frames``: this
    rank's frames in the step (what its loss sum counts)."""

    def __init__(self, tensors: Mapping[str, torch.Tensor], frames: int) -> None:
        super().__init__(tensors)
        self.frames = int(frames)


def _tensor(value: Any, device: str | torch.device) -> torch.Tensor:
    array = value if isinstance(value, torch.Tensor) else np.asarray(value)
    integer = array.dtype in (torch.int64, torch.int32) if isinstance(array, torch.Tensor) else array.dtype.kind in "iu"
    return torch.as_tensor(array, dtype=torch.int64 if integer else torch.float32, device=device)


class MemoryBatches:
    """Batches of ``batch_size`` frames of ``arrays`` (name -> (N, ...), all the same N), copied to
    ``device`` once; ``shuffle``: a random order per epoch, else the frames' order."""

    def __init__(self, arrays: Mapping[str, Any], *, batch_size: int, device: str | torch.device = "cpu",
                 shuffle: bool = True) -> None:
        self.tensors = {name: _tensor(value, device) for name, value in arrays.items()}
        counts = {name: int(t.shape[0]) for name, t in self.tensors.items()}
        if len(set(counts.values())) > 1:
            raise ValueError(f"arrays must all hold the same number of frames, got {counts}")
        self.frame_count = next(iter(counts.values()), 0)
        self.batch_size, self.device, self.shuffle = int(batch_size), device, bool(shuffle)

    def indices(self, generator: torch.Generator) -> Iterator[tuple[torch.Tensor, int]]:
        """One epoch's steps as (this rank's frame indices on the device, (b,) int64; its frame count)."""
        n = self.frame_count
        if self.shuffle:
            order = torch.randperm(n, generator=generator).to(self.device)
        else:
            order = torch.arange(n, device=self.device)
        for begin in range(0, n, self.batch_size):
            index = distributed.shard(order[begin:begin + self.batch_size])  # this rank's frames (all in one process)
            yield index, 0 if distributed.share() == 0.0 else int(index.numel())

    def gather(self, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """The frames ``index`` ((b,) int64 on the device) of every array (name -> (b, ...))."""
        return {name: t[index] for name, t in self.tensors.items()}

    def epoch(self, generator: torch.Generator, optimizer: Any = None) -> Iterator[Batch]:
        """One epoch's batches (``optimizer`` is not used: the deal leaves no rank without a step)."""
        for index, frames in self.indices(generator):
            yield Batch(self.gather(index), frames)


class StreamBatches:
    """Batches of ``fields`` (names of :data:`learn.streaming.ITEM_FIELDS`) streamed from
    ``split`` (a :class:`learn.streamed_split.StreamedSplit`), ``batch_size`` frames per global step.
    ``shuffle``: shard order and frames within each shard permuted per epoch; frames of one worker's
    shards fill its batches in turn, so a batch holds consecutive (permuted) frames of one or two
    shards."""

    def __init__(self, split: Any, fields: Sequence[str], *, batch_size: int, device: str | torch.device = "cpu",
                 shuffle: bool = True) -> None:
        self.split, self.fields = split, tuple(fields)
        self.frame_count = int(split.frame_count)
        self.batch_size, self.device, self.shuffle = int(batch_size), device, bool(shuffle)
        self.frequencies = bool({"low_frequency", "high_frequency"} & set(self.fields))

    def dataset(self, seed: int, rank: int, world: int):
        from learn.streaming import StreamingDrapeDataset

        return StreamingDrapeDataset(self.split.root, self.split.split, frequencies=self.frequencies,
                                     shuffle=self.shuffle, seed=seed, rank=rank, world_size=world,
                                     cache_dir=self.split.cache_dir, fields=self.fields)

    def steps(self, dataset: Any, world: int) -> int:
        """Steps of an epoch: the largest batch count of a rank (each worker batches its own shards)."""
        per_rank = -(-self.batch_size // world)
        consumers = max(1, self.split.workers)
        return max(sum(-(-sum(dataset.frames_for(r, w, consumers)) // per_rank) for w in range(consumers))
                   for r in range(world))

    def stream(self, seed: int = 0, rank: int = 0, world: int = 1) -> tuple[Iterator[dict[str, torch.Tensor]], int]:
        """(this rank's batches of ``ceil(batch_size / world)`` frames on the CPU, the step count of
        the rank with the most batches) for the order drawn from ``seed``."""
        dataset = self.dataset(seed, rank, world)
        loader = torch.utils.data.DataLoader(dataset, batch_size=-(-self.batch_size // world),
                                             num_workers=self.split.workers,
                                             pin_memory=torch.device(self.device).type == "cuda")
        return iter(loader), self.steps(dataset, world)

    def epoch(self, generator: torch.Generator, optimizer: Any) -> Iterator[Batch]:
        """One epoch's batches of this rank; after them, the zero-weight steps that bring it to the
        step count of the rank with the most batches (run on ``optimizer`` here)."""
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=generator)) if self.shuffle else 0
        rank, world = (distributed.rank(), distributed.world_size()) if distributed.active() else (0, 1)
        items, steps = self.stream(seed, rank, world)
        cuda = torch.device(self.device).type == "cuda"
        taken = 0
        for item in items:
            taken += 1
            if taken > steps:
                raise RuntimeError(f"the loader of rank {rank} yielded more than the {steps} batches its shards make")
            frames = int(next(iter(item.values())).shape[0])
            distributed.share_of_frames(frames)
            yield Batch({name: value.to(self.device, non_blocking=cuda) for name, value in item.items()}, frames)
        for _ in range(steps - taken):
            optimizer.zero_grad(set_to_none=True)
            distributed.share_of_frames(0)
            optimizer.step()

    def once(self) -> Iterator[Batch]:
        """Every frame of the split once, in order, for a whole-split statistic: under data
        parallelism this rank's shards only (callers sum their statistics over the ranks)."""
        rank, world = (distributed.rank(), distributed.world_size()) if distributed.active() else (0, 1)
        items, _ = self.stream(0, rank, world)
        for item in items:
            yield Batch({name: value.to(self.device) for name, value in item.items()},
                        int(next(iter(item.values())).shape[0]))


def frame_field(data: Any, name: str) -> np.ndarray:
    """Array ``name`` of in-memory frames ``data`` (a ``FrameArrays``): pose, shape, style, pair,
    displacements, posed_vertices, low_frequency or high_frequency (displacements less low_frequency)."""
    if name == "pair":
        return data.pair_id
    if name == "high_frequency":
        if data.low_frequency is None:
            raise ValueError("data.low_frequency is None: call add_low_frequency(data, faces) first")
        return data.displacements - data.low_frequency
    value = getattr(data, name, None)
    if value is None:
        raise ValueError(f"the training frames have no {name}")
    return value


def is_streamed(data: Any) -> bool:
    """Whether ``data`` is a :class:`learn.streamed_split.StreamedSplit`."""
    from learn.streamed_split import StreamedSplit

    return isinstance(data, StreamedSplit)


def batches_for(data: Any, fields: Sequence[str], *, batch_size: int, device: str | torch.device = "cpu",
                shuffle: bool = True) -> MemoryBatches | StreamBatches:
    """The batch source of ``fields`` of ``data``: streamed for a ``StreamedSplit``, else in memory."""
    if is_streamed(data):
        return StreamBatches(data, fields, batch_size=batch_size, device=device, shuffle=shuffle)
    return MemoryBatches({name: frame_field(data, name) for name in fields}, batch_size=batch_size, device=device,
                         shuffle=shuffle)
