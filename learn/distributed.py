"""Training over several processes (``torchrun``), one GPU each: data parallelism for the
epoch loop every learner shares (:func:`learn.tailornet.train.run_epochs`).

``torchrun --nproc-per-node N -m pipelines.cli train LEARNER ...`` starts N processes with
``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE`` and a rendezvous address in their environment;
:func:`init` joins them into one process group (NCCL on CUDA, gloo on the CPU) and gives each
rank its device (``cuda`` -> ``cuda:LOCAL_RANK``).

What data parallelism means here, and why it keeps the single-process math:

- every rank holds the whole training split and the same model and draws the same shuffled
  order (the epoch loop's generator is seeded alike on every rank); each global batch of
  ``batch_size`` frames is dealt out by :func:`shard` (rank ``r`` takes frames ``r, r + N, ...``
  of it), so the global batches, their order and their count are those of one process;
- after ``backward`` the gradients are summed over the ranks, each rank's weighted by its share
  of the global batch (:class:`DataParallelOptimizer`), which is exactly the gradient of the
  global batch's mean loss: the optimizer then takes the step one process would take. The
  parameters therefore stay identical on every rank, and equal the single-process run's up to
  float rounding (the sum runs in another order), for losses that are means over the frames of a
  batch and where the loss draws no random numbers (dropout and random samples draw per rank);
- checkpoints hold the model, the optimizer, the epoch and the shuffling generator, as in one
  process: no world size, so a run resumes on any number of processes. Only rank 0 writes
  checkpoints, logs and models (:func:`is_main`), and ranks meet at a :func:`barrier` after.

The averaging is done on the optimizer's step rather than by wrapping the model in
``DistributedDataParallel``: the learners' epoch functions call model methods other than
``forward`` (``features``, ``forward_each``, ``skinning_weights``), whose gradients DDP does not
synchronise. :func:`ddp` wraps a model for loops that only call ``forward``.
"""
from __future__ import annotations

import datetime
import os
from collections.abc import Iterable, Mapping
from typing import Any

import torch
import torch.distributed as dist

#: Gradients are summed in flat buckets of at most this many bytes (fewer, larger messages).
BUCKET_BYTES = 64 * 2**20

_state: dict[str, Any] = {"data_parallel": False, "share": None}


def env_world_size() -> int:
    """``WORLD_SIZE`` set by torchrun (1 when absent)."""
    return int(os.environ.get("WORLD_SIZE", "1") or 1)


def rank() -> int:
    """This process's rank (0 without a process group)."""
    return dist.get_rank() if dist.is_available() and dist.is_initialized() else 0


def world_size() -> int:
    """Processes in the group (1 without one)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def is_main() -> bool:
    """Whether this process writes the run's files (rank 0, or the only process)."""
    return rank() == 0


def active() -> bool:
    """Whether the epoch loop trains data-parallel: a process group of more than one process,
    joined by :func:`init` with ``data_parallel=True``."""
    return bool(_state["data_parallel"]) and world_size() > 1


def writes_files() -> bool:
    """Whether this process writes shared run files: always, except the ranks other than 0 of a
    data-parallel run (whose ranks hold the same model; the stage-parallel TailorNet run writes
    each stage from the rank that trains it)."""
    return not active() or is_main()


def init(device: str, *, data_parallel: bool = True, timeout_s: float = 1800.0) -> str:
    """Joins the torchrun process group when ``WORLD_SIZE`` > 1 and returns this rank's device.

    ``device``: ``cpu`` or ``cuda`` (each rank takes ``cuda:LOCAL_RANK``, or with ``data_parallel``
    off ``cuda:(LOCAL_RANK mod GPU count)``, so stages can share one GPU); a numbered CUDA device
    under torchrun raises ValueError naming it. ``data_parallel``: whether :func:`run_epochs
    <learn.tailornet.train.run_epochs>` shares batches over the ranks (False where the learner
    spreads whole stages over them). Single process: returns ``device`` unchanged."""
    _state["data_parallel"] = bool(data_parallel)
    world = env_world_size()
    if world <= 1:
        return device
    local = int(os.environ.get("LOCAL_RANK", "0"))
    kind = torch.device(device).type
    if kind == "cuda":
        if device not in ("cuda",):
            raise ValueError(f"--device {device} under torchrun: give --device cuda, each of the {world} processes "
                             f"takes cuda:LOCAL_RANK")
        count = torch.cuda.device_count()
        if local >= count and data_parallel:
            raise ValueError(f"LOCAL_RANK {local} but this host has {count} CUDA device(s): "
                             f"--nproc-per-node must not exceed the GPU count")
        # stage-parallel learners exchange no tensors: several ranks may share a GPU
        local = local % count
        torch.cuda.set_device(local)
        device = f"cuda:{local}"
    if not dist.is_initialized():
        # the stage-parallel ranks only meet at barriers: gloo, which also works for ranks sharing a GPU
        backend = "nccl" if kind == "cuda" and data_parallel else "gloo"
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s),
                                **({"device_id": torch.device(device)} if backend == "nccl" else {}))
    return device


def finish(*, wait: bool = True) -> None:
    """Leaves the process group; with ``wait`` (every rank ending normally) after a barrier."""
    if dist.is_available() and dist.is_initialized():
        if wait:
            dist.barrier()
        dist.destroy_process_group()
    _state["data_parallel"] = False


def barrier() -> None:
    """Waits for every rank (no-op in one process)."""
    if world_size() > 1:
        dist.barrier()


def shard(batch: torch.Tensor) -> torch.Tensor:
    """This rank's frames of a global batch (indices along dim 0): ``batch[rank::world]``.

    Records the rank's share of the global batch (its frames / the batch's) for the next
    :class:`DataParallelOptimizer` step. A rank left without frames (a last batch shorter than
    the world) gets the batch's first frame with share 0: it runs the same steps as the others
    and its gradient counts for nothing. Identity in one process or without data parallelism."""
    if not active():
        return batch
    world, me, total = world_size(), rank(), int(batch.shape[0])
    mine = batch[me::world]
    if mine.shape[0] == 0:
        _state["share"] = 0.0
        return batch[:1]
    _state["share"] = mine.shape[0] / total
    return mine


def share() -> float | None:
    """This rank's share of the coming step's global batch, as :func:`shard` or
    :func:`share_of_frames` recorded it (None: none recorded, the gradients are averaged)."""
    return _state["share"]


def share_of_frames(frames: int) -> None:
    """Records this rank's share of a step in which every rank brings its own ``frames`` (a
    streamed batch, :class:`learn.batches.StreamBatches`): ``frames`` / the sum over the ranks
    (one all-reduce). A rank with 0 frames takes a zero-weight step. Every rank calls it once per
    step. No-op without data parallelism."""
    if not active():
        return
    total = float(sum_over_ranks(float(frames)))
    _state["share"] = float(frames) / total if total > 0 else 0.0


def _buckets(tensors: list[torch.Tensor]) -> Iterable[list[torch.Tensor]]:
    bucket: list[torch.Tensor] = []
    size = 0
    for t in tensors:
        if bucket and (size + t.numel() * t.element_size() > BUCKET_BYTES or t.dtype != bucket[0].dtype
                       or t.device != bucket[0].device):
            yield bucket
            bucket, size = [], 0
        bucket.append(t)
        size += t.numel() * t.element_size()
    if bucket:
        yield bucket


def reduce_gradients(parameters: Iterable[torch.nn.Parameter], share: float | None = None) -> None:
    """Replaces each gradient by the sum over ranks of ``share`` x its gradient (``share``
    default 1 / world size: the mean). A parameter without a gradient on some rank counts as
    zero there; one without a gradient on every rank keeps none (as in one process)."""
    params = [p for p in parameters if p.requires_grad]
    if world_size() <= 1 or not params:
        return
    share = 1.0 / world_size() if share is None else float(share)
    has = torch.tensor([p.grad is not None for p in params], dtype=torch.float32,
                       device=params[0].device)
    dist.all_reduce(has, op=dist.ReduceOp.MAX)
    grads = []
    for p, flag in zip(params, has.tolist()):
        if not flag:
            continue
        if p.grad is None:
            p.grad = torch.zeros_like(p)
        grads.append(p.grad)
    for bucket in _buckets(grads):
        flat = torch.cat([g.reshape(-1) for g in bucket]).mul_(share)
        dist.all_reduce(flat)
        offset = 0
        for g in bucket:
            g.copy_(flat[offset:offset + g.numel()].view_as(g))
            offset += g.numel()


class DataParallelOptimizer:
    """An optimizer whose ``step`` first sums the gradients over the ranks, each weighted by the
    rank's share of the global batch (:func:`shard`; the mean when no share was recorded).
    Everything else (``zero_grad``, ``state_dict``, ``param_groups``...) is the wrapped
    optimizer's, so checkpoints are those of one process."""

    def __init__(self, optimizer: torch.optim.Optimizer) -> None:
        self.optimizer = optimizer

    def step(self, closure: Any = None) -> Any:
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        reduce_gradients(params, _state["share"])
        _state["share"] = None
        return self.optimizer.step(closure)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.optimizer, name)


def broadcast_module(module: torch.nn.Module) -> None:
    """Rank 0's parameters and dense buffers on every rank (after building or loading a model;
    sparse buffers, such as a mesh operator, are built alike on every rank and not sent)."""
    if world_size() <= 1:
        return
    for t in list(module.parameters()) + list(module.buffers()):
        if t.layout == torch.strided:
            dist.broadcast(t.data, src=0)


def sum_over_ranks(value: float | Mapping[str, float]) -> float | dict[str, float]:
    """A float summed over the ranks (in float64), or dicts of floats summed key by key over the
    union of the ranks' keys (a key a rank lacks counts 0 there); itself in one process."""
    if world_size() <= 1:
        return value if not isinstance(value, Mapping) else dict(value)
    if isinstance(value, Mapping):
        parts: list[Any] = [None] * world_size()
        dist.all_gather_object(parts, {k: float(v) for k, v in value.items()})
        keys = sorted(set().union(*parts))
        return {k: sum(part.get(k, 0.0) for part in parts) for k in keys}
    device = f"cuda:{torch.cuda.current_device()}" if dist.get_backend() == "nccl" else "cpu"
    t = torch.tensor([float(value)], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return float(t.item())


def epoch_seed(seed: int, epoch: int) -> int:
    """The seed of the global torch RNG (dropout, random samples) of ``epoch`` on this rank of a
    data-parallel run: different on every rank (their frames need their own draws), a function
    of (seed, epoch, rank) only, so a resumed run draws what an uninterrupted one draws."""
    return (int(seed) * 1_000_003 + int(epoch) * 7919 + rank()) % (2**63 - 1)


def ddp(module: torch.nn.Module) -> torch.nn.Module:
    """``DistributedDataParallel`` of ``module`` (on its device) for loops that call only its
    ``forward``; the module itself in one process."""
    if world_size() <= 1:
        return module
    device = next(module.parameters()).device
    return torch.nn.parallel.DistributedDataParallel(module, device_ids=[device] if device.type == "cuda" else None)
