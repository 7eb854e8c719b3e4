"""Scale-out on one host: (a) kept frames per second of ``generate-dataset`` with the local
executor on one GPU against Ray on N GPUs, same spec, in the same run; (b) epoch time of a
learner at world size 1 against N (``torchrun``). Prints one JSON object.

    python bench/bench_scale_out.py --spec tailornet-tshirt --gpus 2,4 --out /scratch/scale
    python bench/bench_scale_out.py --spec tailornet-tshirt --gpus 4 --local-batches 1 --out /scratch/scale
    python bench/bench_scale_out.py --spec tiny.yaml --gpus 2 --device cpu --epochs 2   # CPU smoke

(a) writes OUT/local and OUT/rayN (the Ray runs reuse the local run's garment cache, so both
time the simulation of the same tasks); the rate is kept frames / the simulation seconds each
run records (manifest ``audit.simulation``; for Ray this includes starting the workers and
building their contexts); the plan has one batch per GPU of the largest run (``simulation.batches``).
``--local-batches K`` has the local run simulate only the plan's first K batches (the whole
TailorNet spec takes ~23 minutes on one H100, longer than a device call): its rate is that of
those batches; ``--ray-batches-per-gpu K`` has a Ray run on N GPUs simulate the first K x N
(``--local-batches 2 --ray-batches-per-gpu 1 --gpus 2`` times the same two batches on one GPU and
on two). ``--batches`` sets the plan's batch count. Each Ray dataset is compared with the local
one on the tasks both list: shards compared, byte-identical, and whether every one kept the same
frames.
(b) trains ``--learner`` on ``--data`` (default: OUT/local) for ``--epochs`` epochs into
OUT/train-wN with ``torchrun --nproc-per-node N -m pipelines.cli train``; the epoch time is
the mean of the logged epoch seconds after the first (rank 0's clock: it includes the gradient
exchange), and ``speedup`` is the epoch rate at each N over the rate at 1; for ``tailornet``,
which trains its stages side by side (hf's prototypes in parts), it is the whole training's
time at 1 over that at N (``run.json`` seconds). Each run also gives every stage's mean epoch
seconds (``stage_epoch_s``). ``--processes`` adds tailornet runs with more processes than GPUs
(its stages then share GPUs). ``--pack`` runs the world sizes that fit on the host's GPUs side by
side on disjoint GPUs (``--gpus 2,4`` on 4 GPUs: 1 and 2 at once on GPUs 0 and 1-2, then 4): the
same stage's epoch seconds in a packed run and in a run alone show whether the runs slowed each
other (they share the host's CPUs).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The stage whose epochs are timed for each learner (its longest).
TIMED_STAGE = {"baseline": "baseline", "tailornet": "hf", "uvimage": "uvimage", "uvimage_pca": "uvimage_pca",
               "collision_aware": "vae", "gcvae": "gcvae"}


def _shards(root: Path) -> dict[str, tuple[str, int]]:
    """task id -> (sha256, kept frames) of every shard the dataset in ``root`` lists."""
    manifest = json.loads((root / "manifest.json").read_text())
    return {s["task_id"]: (s["sha256"], int(s["frame_count"])) for s in manifest["shards"]}


def compare_shards(local: Path, other: Path) -> dict:
    """The shards of the tasks both datasets list: how many, how many are byte-identical, and
    whether every one kept the same number of frames."""
    a, b = _shards(local), _shards(other)
    common = sorted(set(a) & set(b))
    return {"shards_compared": len(common), "shards_identical": sum(a[t][0] == b[t][0] for t in common),
            "kept_frames_equal": all(a[t][1] == b[t][1] for t in common),
            "identical_shards": bool(common) and all(a[t][0] == b[t][0] for t in common)}


def _generate(spec: dict, out: Path, *, executor: str, device: str, gpus: int, cpus: int | None,
              max_batches: int | None = None) -> dict:
    from pipelines.generate_dataset import generate

    started = time.perf_counter()
    if executor == "ray":
        import ray

        ray.init(num_gpus=gpus if device.startswith("cuda") else 0, num_cpus=cpus or max(gpus, os.cpu_count() or 1),
                 include_dashboard=False, log_to_driver=False)
    try:
        # the run's log and heartbeat lines on stderr: a run stopped by a time limit still says how far it got
        manifest = generate(spec, out, executor=executor, device=device, progress=False, heartbeat_s=30.0,
                            log=lambda m: print(f"[{executor} {gpus}] {m}", file=sys.stderr, flush=True),
                            max_batches=max_batches)
    finally:
        if executor == "ray":
            ray.shutdown()
    simulation = manifest.audit["simulation"]
    seconds = float(simulation["seconds"])
    return {"executor": executor, "gpus": gpus if executor == "ray" else min(gpus, 1), "device": device,
            "kept_frames": int(simulation["kept_frames"]), "target_frames": int(simulation["target_frames"]),
            "simulation_s": round(seconds, 2), "wall_s": round(time.perf_counter() - started, 2),
            "kept_frames_per_s": round(simulation["kept_frames"] / seconds, 3) if seconds > 0 else None,
            **({"ray": simulation.get("ray")} if executor == "ray" else {})}


def bench_generate(args: argparse.Namespace) -> dict:
    from pipelines.spec import load_spec

    spec = load_spec(args.spec)
    spec["audit"]["samples"] = 0  # the audit is not part of the simulation rate
    # one batch per GPU of the largest run at least (the same plan, so the same shards, on every run)
    spec["simulation"]["batches"] = max(int(args.batches or spec["simulation"]["batches"]), max(args.gpus))
    if args.train_count is not None:
        spec["poses"]["train_count"] = args.train_count
    local_out = args.out / "local"
    outs = [local_out] + [args.out / f"ray{n}" for n in args.gpus]
    for d in outs:
        if d.exists() and not args.keep:
            shutil.rmtree(d)
    local = _generate(spec, local_out, executor="local", device=args.sim_device(0), gpus=1, cpus=None,
                      max_batches=args.local_batches)
    local["batches"] = min(args.local_batches or spec["simulation"]["batches"], spec["simulation"]["batches"])
    # each run's figures as soon as they exist, on stderr: a run stopped later keeps them
    print(json.dumps({"local": local}), file=sys.stderr, flush=True)
    result = {"spec": str(args.spec), "batches": int(spec["simulation"]["batches"]),
              "train_count": int(spec["poses"]["train_count"]), "local": local, "ray": {}}
    if args.ray_data is not None:
        result["ray"] = ray_from_dataset(args.ray_data, local_out, local)
        return result
    for n, ray_out in zip(args.gpus, outs[1:]):
        if (local_out / "cache").is_dir() and not (ray_out / "cache").exists():
            shutil.copytree(local_out / "cache", ray_out / "cache")
        part = None if args.ray_batches_per_gpu is None else args.ray_batches_per_gpu * n
        ray_run = _generate(spec, ray_out, executor="ray", device=args.sim_device(0), gpus=n, cpus=args.cpus,
                            max_batches=part)
        ray_run["batches"] = min(part or spec["simulation"]["batches"], spec["simulation"]["batches"])
        rate = (ray_run["kept_frames_per_s"] or 0) / (local["kept_frames_per_s"] or float("nan"))
        ray_run.update(speedup=round(rate, 3), **compare_shards(local_out, ray_out))
        result["ray"][n] = ray_run
        print(json.dumps({f"ray{n}": ray_run}), file=sys.stderr, flush=True)
    return result


def ray_from_dataset(ray_out: Path, local_out: Path, local: dict) -> dict:
    """The figures of a Ray run made before into ``ray_out``, keyed by its GPU count, compared with the
    local run in ``local_out``: the same spec (and so plan) is required."""
    manifest = json.loads((ray_out / "manifest.json").read_text())
    local_sha = json.loads((local_out / "manifest.json").read_text())["spec_sha256"]
    if manifest["spec_sha256"] != local_sha:
        raise SystemExit(f"--ray-data {ray_out}: its spec (sha256 {manifest['spec_sha256'][:12]}) is not the local "
                         f"run's ({local_sha[:12]}): the rates would not be of the same tasks")
    simulation = manifest["audit"].get("simulation") or {}
    cluster = simulation.get("ray")
    if not cluster:
        raise SystemExit(f"--ray-data {ray_out}: its manifest records no Ray run (audit.simulation.ray)")
    seconds = float(simulation["seconds"])
    run = {"executor": "ray", "gpus": int(cluster["gpus"]), "device": simulation.get("device"),
           "kept_frames": int(simulation["kept_frames"]), "target_frames": int(simulation["target_frames"]),
           "simulation_s": round(seconds, 2), "kept_frames_per_s": round(simulation["kept_frames"] / seconds, 3),
           "ray": cluster, "batches": int(manifest["spec"]["simulation"]["batches"]), "from": str(ray_out)}
    run.update(speedup=round(run["kept_frames_per_s"] / (local["kept_frames_per_s"] or float("nan")), 3),
               **compare_shards(local_out, ray_out))
    return {run["gpus"]: run}


def _logged_seconds(path: Path) -> list[float]:
    """The ``seconds`` column of a stage's loss log: one value per epoch."""
    with path.open() as fh:
        return [float(row["seconds"]) for row in csv.DictReader(fh)]


def _epoch_seconds(run: Path, stage: str) -> list[float]:
    """Seconds of each epoch of ``stage`` (of its first part where hf was split over processes)."""
    path = run / f"{stage}_loss.csv"
    if not path.is_file():
        path = min(run.glob(f"{stage}_1of*_loss.csv"))
    return _logged_seconds(path)


def stage_epoch_seconds(run: Path) -> dict[str, float]:
    """Mean seconds of an epoch after the first (all of them where there is one) of every stage
    (or hf part) that logged a ``<stage>_loss.csv`` into ``run``."""
    means = {}
    for path in sorted(run.glob("*_loss.csv")):
        seconds = _logged_seconds(path)
        timed = seconds[1:] or seconds
        if timed:
            means[path.name[: -len("_loss.csv")]] = round(sum(timed) / len(timed), 4)
    return means


def pack_world_sizes(world_sizes: list[int], gpus: int) -> list[list[tuple[int, int]]]:
    """Rounds of training runs: each run as (world size, first GPU), the runs of a round side by
    side on disjoint GPUs of the ``gpus`` the host has, smallest first; a world size larger than
    ``gpus`` gets a round of its own from GPU 0."""
    rounds: list[list[tuple[int, int]]] = []
    free = 0
    for world in sorted(set(world_sizes)):
        if not rounds or free + world > gpus:
            rounds.append([])
            free = 0
        rounds[-1].append((world, free))
        free += world
    return rounds


def _train_command(args: argparse.Namespace, data: Path, run: Path, world: int) -> list[str]:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={world}",
               "-m", "pipelines.cli", "train", args.learner, "--data", str(data), "--out", str(run),
               "--device", args.train_device, "--no-progress"]
    if args.epochs is not None:
        command += ["--epochs", str(args.epochs)]
    if args.config:
        command += ["--config", str(args.config)]
    return command


def bench_train(args: argparse.Namespace, data: Path) -> dict:
    stage = TIMED_STAGE[args.learner.replace("-", "_")]
    results = {}
    worlds = sorted({1, *args.gpus, *(args.processes or [])})
    cuda = args.train_device != "cpu"
    rounds = pack_world_sizes(worlds, args.host_gpus) if args.pack else [[(w, 0)] for w in worlds]
    for members in rounds:
        running = {}
        for world, first in members:
            run = args.out / f"train-w{world}"
            if run.exists():
                shutil.rmtree(run)
            env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
            if not cuda:
                env.setdefault("OMP_NUM_THREADS", "1")
            elif args.pack:
                # more processes than GPUs (tailornet's --processes): they share all of them
                env["CUDA_VISIBLE_DEVICES"] = ",".join(str(first + k) for k in range(min(world, args.host_gpus)))
            log = (args.out / f"train-w{world}.log").open("w")
            running[world] = (run, log, time.perf_counter(),
                              subprocess.Popen(_train_command(args, data, run, world), env=env, cwd=ROOT,
                                               stdout=log, stderr=subprocess.STDOUT, text=True))
        for world, (run, log, started, process) in running.items():
            code = process.wait()
            wall = time.perf_counter() - started
            log.close()
            if code != 0:
                tail = (args.out / f"train-w{world}.log").read_text()[-4000:]
                raise SystemExit(f"torchrun with {world} process(es) failed ({code}):\n{tail}")
            seconds = _epoch_seconds(run, stage)
            timed = seconds[1:] or seconds
            run_s = json.loads((run / "run.json").read_text())["seconds"]
            results[world] = {"epoch_s": round(sum(timed) / len(timed), 4), "epochs": len(seconds),
                              "run_s": run_s, "wall_s": round(wall, 2), "stage_epoch_s": stage_epoch_seconds(run),
                              "beside": [w for w, _ in members if w != world]}
            print(json.dumps({f"train{world}": results[world]}), file=sys.stderr, flush=True)
    # tailornet spreads its stages (and hf's prototypes) over the processes: its gain is the whole
    # training's time (rank 0's run.json, which waits for every stage), not an epoch's
    basis = "run_s" if stage == "hf" else "epoch_s"
    one = results[1][basis]
    return {"learner": args.learner, "stage": stage, "data": str(data), "world_sizes": results, "speedup_of": basis,
            "speedup": {w: round(one / r[basis], 3) if r[basis] > 0 else None for w, r in results.items()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spec", default="tailornet-tshirt", help="dataset spec (shipped name or YAML path)")
    parser.add_argument("--gpus", default=None, help="N or N,M,...: GPU counts of the Ray runs and torchrun processes "
                        "(default: all the GPUs)")
    parser.add_argument("--local-batches", type=int, default=None,
                        help="one GPU simulates only the first K batches of the plan (default: all): the whole "
                        "TailorNet spec on one GPU outlasts a device call; its rate is then that of those batches")
    parser.add_argument("--ray-batches-per-gpu", type=int, default=None,
                        help="each Ray run on N GPUs simulates only the plan's first K x N batches (default: all): "
                        "with --local-batches K x N both time the same tasks")
    parser.add_argument("--batches", type=int, default=None,
                        help="simulation.batches of the plan (default: the spec's, at least the largest --gpus)")
    parser.add_argument("--train-count", type=int, default=None, help="poses.train_count of (a)'s spec (default: the spec's)")
    parser.add_argument("--out", type=Path, default=Path("scale-out-bench"), help="scratch directory")
    parser.add_argument("--device", default="auto", help="auto (CUDA when present), cuda or cpu")
    parser.add_argument("--cpus", type=int, default=None, help="CPUs of the Ray started for (a) (default: all)")
    parser.add_argument("--learner", default="baseline", help=f"learner of (b): {', '.join(TIMED_STAGE)}")
    parser.add_argument("--data", type=Path, default=None, help="dataset of (b) (default: OUT/local from (a))")
    parser.add_argument("--epochs", type=int, default=None,
                        help="epochs of every stage (default: the learner's, or --config's; tailornet's split of its "
                        "stages over the processes follows each stage's epochs)")
    parser.add_argument("--config", type=Path, default=None, help="drape train --config of (b)")
    parser.add_argument("--processes", default=None,
                        help="(b), tailornet only: also train with these process counts (N or N,M,...) above the GPU "
                        "count, the stages sharing the GPUs (process k on GPU k mod the GPU count)")
    parser.add_argument("--pack", action="store_true",
                        help="(b): world sizes that fit on the GPUs side by side run at once on disjoint GPUs")
    parser.add_argument("--ray-data", type=Path, default=None,
                        help="a Ray run of the same spec made before: (a) runs only the local run and compares with it")
    parser.add_argument("--skip-generate", action="store_true")
    parser.add_argument("--skip-train", action="store_true")
    parser.add_argument("--keep", action="store_true", help="resume (a)'s datasets instead of starting over")
    args = parser.parse_args(argv)
    import torch

    cuda = torch.cuda.is_available() if args.device == "auto" else args.device.startswith("cuda")
    if cuda and not torch.cuda.is_available():
        parser.error("--device cuda but torch sees no CUDA device")
    available = torch.cuda.device_count() if cuda else None
    try:
        args.gpus = sorted({int(n) for n in args.gpus.split(",")}) if args.gpus else [available or 2]
    except ValueError:
        parser.error(f"--gpus must be N or N,M,... (got {args.gpus!r})")
    try:
        args.processes = sorted({int(n) for n in args.processes.split(",")}) if args.processes else []
    except ValueError:
        parser.error(f"--processes must be N or N,M,... (got {args.processes!r})")
    if args.processes and (args.learner != "tailornet" or min(args.processes) < 1):
        parser.error(f"--processes is for --learner tailornet (its stages share GPUs), counts >= 1 (got "
                     f"{args.processes} with --learner {args.learner})")
    if args.ray_data is not None and not (args.ray_data / "manifest.json").is_file():
        parser.error(f"--ray-data {args.ray_data} is not a dataset (no manifest.json)")
    # with --ray-data and no training, only the local run needs a GPU here
    gpus_here = not (args.ray_data is not None and args.skip_train)
    if min(args.gpus) < 1 or (cuda and gpus_here and max(args.gpus) > available):
        parser.error(f"--gpus must be counts in 1..{available or 'N'} (got {args.gpus})")
    for name in ("local_batches", "ray_batches_per_gpu", "batches"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1 (got {getattr(args, name)})")
    args.sim_device = lambda k: f"cuda:{k}" if cuda else "cpu"
    args.host_gpus = available if cuda else max(args.gpus)
    args.train_device = "cuda" if cuda else "cpu"
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"machine": {"host": platform.node(), "cpus": os.cpu_count(),
                          "gpus": [torch.cuda.get_device_name(k) for k in range(torch.cuda.device_count())] if cuda else []},
              "date": time.strftime("%Y-%m-%d"), "gpus": args.gpus}
    if not args.skip_generate:
        report["generate"] = bench_generate(args)
    if not args.skip_train:
        data = args.data or args.out / "local"
        if not (data / "manifest.json").is_file() and not (data / "static_set.npz").is_file():
            parser.error(f"--data {data} is not a dataset (run (a) first or give --data)")
        report["train"] = bench_train(args, data)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
