"""Where batches of dataset tasks run: in this process (``local``, default) or as Ray
tasks on the GPUs of one host or of a cluster (``ray``, extra ``distributed``).

Both take the same work description: the spec, the output directory and batches of
task ids. A Ray worker rebuilds the context from the spec with the driver's plan and garment
template (put in Ray's object store once) and the garment cache in ``OUT/cache`` (shared
storage, so it is computed once, by the driver), writes its shards
straight to ``OUT/shards`` and returns their manifest records; the driver alone writes the
manifest, listing a batch's shards when the batch returns.

Ray placement and failures: each batch is one task holding one GPU (``num_gpus=1``) when the
device is CUDA, so a host with N GPUs runs N batches at once and a cluster all its GPUs. A
batch whose worker process dies (a crash, a lost node) is run again whole on whichever worker
is free, up to ``max_retries`` times; an exception raised by the code itself is not retried
(it would fail again). A shard is written to a temporary name and renamed when complete
(:mod:`data_manifest.shard`), and the driver lists only the records an attempt that finished
returned, so nothing a dead attempt wrote is trusted: its complete shards are written again
(bitwise the same) by the next attempt and its temporary files are removed at the end.

Progress: every worker reports the target poses its batch has finished (at most every
``progress_interval_s`` seconds, per simulator frame counts summed) to one small actor; the
driver polls it while it waits for batches, so the bar and the heartbeats move per frame, not
per batch. A re-run batch's count starts again from zero (the bar may step back).
"""
from __future__ import annotations

import os
import time
import uuid
from pathlib import Path
from typing import Callable, Iterable

EXECUTORS = ("local", "ray")

FAULT_ENV = "DRAPE_RAY_KILL_AFTER_FIRST_SHARD"
"""Test hook: a file path. The first Ray worker to finish a shard while the file does not exist
creates it and exits at once (``os._exit``), as a crashed worker would, leaving its batch half
done; later attempts run normally."""


class _ProgressBoard:
    """Ray actor: target poses finished by the current attempt of each batch."""

    def __init__(self) -> None:
        self.attempt: dict[int, str] = {}
        self.attempts: dict[int, int] = {}
        self.done: dict[int, int] = {}

    def start(self, batch_no: int, token: str) -> None:
        self.attempt[batch_no] = token
        self.attempts[batch_no] = self.attempts.get(batch_no, 0) + 1
        self.done[batch_no] = 0

    def report(self, batch_no: int, token: str, done: int) -> None:
        if self.attempt.get(batch_no) == token:  # a dead attempt's late report is ignored
            self.done[batch_no] = done

    def snapshot(self) -> tuple[dict[int, int], dict[int, int]]:
        return dict(self.done), dict(self.attempts)


def _run_batch(build_context: Callable, simulate_batch: Callable, spec: dict, out_dir: str, task_ids: list[str],
               device: str | None, skip: frozenset = frozenset(), batch_no: int = 0, board=None,
               progress_interval_s: float = 1.0, fault: str | None = None, prepared: dict | None = None) -> dict:
    """Ray entry point (module level so it pickles by reference; so do the two functions it gets).
    Returns the batch's shard records, its run_sequences statistics, the target poses it finished
    and where it ran."""
    import ray

    from data_manifest.lock import LOCK_NAME

    node = ray.get_runtime_context().get_node_id()
    if not (Path(out_dir) / LOCK_NAME).is_file():
        raise ValueError(f"--out {out_dir} is not visible from Ray node {node[:12]} (no {LOCK_NAME} there): "
                         f"the dataset directory must be on storage every node of the cluster mounts at the same path")
    token = uuid.uuid4().hex
    if board is not None:
        board.start.remote(batch_no, token)
    counted = {"done": 0, "sent": time.monotonic()}

    def on_progress(count: int) -> None:
        counted["done"] += int(count)
        if board is not None and time.monotonic() - counted["sent"] >= progress_interval_s:
            counted["sent"] = time.monotonic()
            board.report.remote(batch_no, token, counted["done"])

    def on_shard(record) -> None:
        if fault and not os.path.exists(fault):
            Path(fault).write_text(f"worker {os.getpid()} on node {node} exited after its first shard\n")
            os._exit(1)

    ctx = build_context(spec, Path(out_dir), device=device, log=lambda msg: None, prepared=prepared)
    ctx.phases = {}  # this batch's statistics only (a worker keeps its context between batches)
    records = simulate_batch(ctx, Path(out_dir), task_ids, skip=skip, on_shard=on_shard, on_progress=on_progress)
    if board is not None:
        board.report.remote(batch_no, token, counted["done"])
    return {"records": records, "phases": dict(ctx.phases), "targets": counted["done"],
            "worker": {"node": node, "pid": os.getpid(), "gpus": [str(g) for g in ray.get_gpu_ids()]}}


def run_local(ctx, out_dir: Path, batches: Iterable[list[str]], *, simulate_batch: Callable, on_shard: Callable,
              on_progress: Callable, on_batch: Callable[[], None] | None = None, skip: set[str] = frozenset()) -> None:
    """Runs the batches one after another in this process (``simulate_batch(ctx, out_dir, batch, ...)``,
    generate-dataset's); ``on_batch()`` after each."""
    for batch in batches:
        simulate_batch(ctx, out_dir, batch, on_shard=on_shard, on_progress=on_progress, skip=skip)
        if on_batch is not None:
            on_batch()


def run_ray(spec: dict, out_dir: Path, batches: list[list[str]], *, build_context: Callable, simulate_batch: Callable,
            device: str | None, on_shard: Callable, on_progress: Callable[[int], None],
            on_batch: Callable[[], None] | None = None, on_phases: Callable[[dict], None] | None = None,
            address: str | None = None, num_cpus: int | None = None, skip: set[str] = frozenset(),
            max_retries: int = 3, progress_interval_s: float = 1.0, log: Callable[[str], None] | None = None,
            prepared: dict | None = None) -> dict:
    """Schedules each batch as a Ray task (``num_gpus=1`` when the device is CUDA) that builds its
    context with ``build_context`` and runs ``simulate_batch`` (generate-dataset's). A worker
    process takes batch after batch (also on GPUs) and builds its context once, so a plan with
    more batches than GPUs pays a batch's set-up per extra batch, not a worker's start.

    ``address``: a running cluster (``ray start --head`` prints it; ``auto`` finds the local one);
    without it a Ray instance is started for this run (``num_cpus`` CPUs, default all) and ended
    with it. ``on_progress(count)`` gets target poses finished (negative after a batch is re-run),
    ``on_shard(record)`` each shard record of a finished batch, ``on_phases(stats)`` the batch's
    ``run_sequences`` statistics, then ``on_batch()``. Returns a summary: worker processes, nodes,
    GPUs used and batches re-run after a worker died. ``log`` gets a warning when the cluster has
    more GPUs than the plan has batches (``simulation.batches``). The summary also says when the
    first target pose finished (``first_target_s``: Ray's and the workers' start-up, their contexts
    and the first batch set-ups) and when each batch returned (``batch_done_s``), in seconds from
    the call: where a run's time went beside the simulation. ``prepared``: passed to every
    worker's ``build_context`` (the driver's plan and template, put in Ray's object store once)."""
    try:
        import ray
    except ImportError as exc:
        raise ValueError("--executor ray needs Ray: pip install -e '.[distributed]'") from exc
    t_start = time.perf_counter()
    started = False
    if not ray.is_initialized():
        kwargs = {"address": address} if address else {"num_cpus": num_cpus, "include_dashboard": False}
        ray.init(log_to_driver=False, ignore_reinit_error=True, **kwargs)
        started = True
    try:
        gpu = bool(device and device.startswith("cuda"))
        if gpu and not ray.cluster_resources().get("GPU"):
            raise ValueError(f"the device is {device} but the Ray cluster has no GPU "
                             f"(resources {ray.cluster_resources()}); start its nodes on GPU hosts or use --device cpu")
        cluster_gpus = int(ray.cluster_resources().get("GPU", 0))
        if gpu and log is not None and len(batches) < cluster_gpus:
            log(f"{len(batches)} batch(es) for {cluster_gpus} GPUs: {cluster_gpus - len(batches)} GPU(s) stay idle; "
                f"set simulation.batches to {cluster_gpus} (or a multiple) to use them all")
        # Ray shows each task only the GPU it holds, as cuda:0
        worker_device = "cuda:0" if gpu else device
        board = ray.remote(num_cpus=0)(_ProgressBoard).remote()
        # max_calls=0: a worker runs batch after batch and keeps its context (body, plan, CUDA and
        # kernels loaded); Ray's default for GPU tasks (1) starts a new worker process per batch
        remote = ray.remote(num_gpus=1 if gpu else 0, num_cpus=1, max_retries=max_retries,
                            retry_exceptions=False, max_calls=0)(_run_batch)
        fault = os.environ.get(FAULT_ENV) or None
        shared = None if prepared is None else ray.put(prepared)
        pending = {remote.remote(build_context, simulate_batch, spec, str(out_dir), batch, worker_device,
                                 frozenset(skip) & set(batch), number, board, progress_interval_s, fault, shared):
                   (number, batch) for number, batch in enumerate(batches)}
        shown = {number: 0 for number in range(len(batches))}  # target poses already passed to on_progress
        unfinished = set(shown)
        workers: set[tuple[str, int]] = set()
        gpus: set[tuple[str, str]] = set()
        attempts: dict[int, int] = {}

        first_target_s: list[float] = []
        batch_done_s: dict[int, float] = {}

        def show(number: int, done: int) -> None:
            if done > 0 and not first_target_s:
                first_target_s.append(time.perf_counter() - t_start)
            if done != shown[number]:
                on_progress(done - shown[number])
                shown[number] = done

        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=progress_interval_s)
            counts, attempts = ray.get(board.snapshot.remote())
            for number, count in counts.items():
                if number in unfinished:
                    show(number, count)
            for ref in done:
                number, batch = pending.pop(ref)
                unfinished.discard(number)
                batch_done_s[number] = time.perf_counter() - t_start
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayError as error:
                    for other in pending:
                        ray.cancel(other, force=True)
                    raise RuntimeError(f"batch {number} ({len(batch)} tasks, {batch[0]} ...) failed after "
                                       f"{attempts.get(number, 1)} attempt(s): {str(error).splitlines()[0]}; the "
                                       f"shards of the batches that finished are listed: rerun to resume") from error
                for record in result["records"]:
                    on_shard(record)
                show(number, int(result["targets"]))
                if on_phases is not None:
                    on_phases(result["phases"])
                where = result["worker"]
                workers.add((where["node"], int(where["pid"])))
                gpus.update((where["node"], g) for g in where["gpus"])
                if on_batch is not None:
                    on_batch()
        _, attempts = ray.get(board.snapshot.remote())
        from data_manifest.shard import SHARD_DIR, remove_orphan_temporaries

        # every batch returned: a temporary shard file left now was a dead attempt's
        remove_orphan_temporaries(Path(out_dir) / SHARD_DIR)
        return {"workers": len(workers), "nodes": len({node for node, _ in workers}), "gpus": len(gpus),
                "batches_rerun": sum(max(0, a - 1) for a in attempts.values()),
                "first_target_s": round(first_target_s[0], 2) if first_target_s else None,
                "batch_done_s": [round(batch_done_s[n], 2) for n in sorted(batch_done_s)]}
    finally:
        if started:
            ray.shutdown()
