"""Where batches of dataset tasks run: in this process (``local``, default) or as Ray
tasks with one GPU each (``ray``, extra ``distributed``).

Both take the same work description: the spec, the output directory and batches of
task ids. A Ray worker rebuilds the context from the spec (the garment cache in
``OUT/cache`` is shared storage, so it is computed once), writes its shards straight
to ``OUT/shards`` and returns their manifest records; the driver lists them in the
manifest as each batch returns.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable

EXECUTORS = ("local", "ray")


def _run_batch(build_context: Callable, simulate_batch: Callable, spec: dict, out_dir: str, task_ids: list[str],
               device: str | None, skip: frozenset = frozenset()) -> list:
    """Ray entry point (module level so it pickles by reference; so do the two functions it gets)."""
    ctx = build_context(spec, Path(out_dir), device=device, log=lambda msg: None)
    return simulate_batch(ctx, Path(out_dir), task_ids, skip=skip)


def run_local(ctx, out_dir: Path, batches: Iterable[list[str]], *, simulate_batch: Callable, on_shard: Callable,
              on_progress: Callable, on_batch: Callable[[], None] | None = None, skip: set[str] = frozenset()) -> None:
    """Runs the batches one after another in this process (``simulate_batch(ctx, out_dir, batch, ...)``,
    generate-dataset's); ``on_batch()`` after each."""
    for batch in batches:
        simulate_batch(ctx, out_dir, batch, on_shard=on_shard, on_progress=on_progress, skip=skip)
        if on_batch is not None:
            on_batch()


def run_ray(spec: dict, out_dir: Path, batches: list[list[str]], *, build_context: Callable, simulate_batch: Callable,
            device: str | None, on_shard: Callable, on_progress: Callable, on_batch: Callable[[], None] | None = None,
            address: str | None = None, num_cpus: int | None = None, skip: set[str] = frozenset()) -> None:
    """Schedules each batch as a Ray task (``num_gpus=1`` when the device is CUDA) that builds its
    context with ``build_context`` and runs ``simulate_batch`` (generate-dataset's); ``on_batch()``
    after each batch's shards are listed."""
    try:
        import ray
    except ImportError as exc:
        raise ValueError("--executor ray needs Ray: pip install -e '.[distributed]'") from exc
    started = False
    if not ray.is_initialized():
        kwargs = {"address": address} if address else {"num_cpus": num_cpus, "include_dashboard": False}
        ray.init(log_to_driver=False, ignore_reinit_error=True, **kwargs)
        started = True
    try:
        gpu = bool(device and device.startswith("cuda"))
        remote = ray.remote(num_gpus=1 if gpu else 0, num_cpus=1, max_retries=1)(_run_batch)
        pending = {remote.remote(build_context, simulate_batch, spec, str(out_dir), batch, device,
                                 frozenset(skip) & set(batch)): batch for batch in batches}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                batch = pending.pop(ref)
                records = ray.get(ref)
                for record in records:
                    on_shard(record)
                on_progress(0, batch=batch)
                if on_batch is not None:
                    on_batch()
    finally:
        if started:
            ray.shutdown()
