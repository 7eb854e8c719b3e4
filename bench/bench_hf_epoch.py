"""Where an epoch of TailorNet's stacked high-frequency stage goes, against its prototype count K:
wall seconds per epoch, the GPU's kernel time in it (``torch.profiler``), kernels and steps per
epoch, and the kernels that take the most time, printed as one JSON line.

    python bench/bench_hf_epoch.py --device cuda [--prototypes 1,6,7,10,20] [--frames-per-prototype 1097]

A fixed cost that the GPU's kernel time shares is work on the GPU that does not grow with K; one
it does not share is time the GPU waits for the host (docs/scale-out.md has the H200's figures:
with CUDA graphs the whole epoch is work on the GPU). Synthetic frames of the shipped t-shirt's
size (7,744 vertices, ``--frames-per-prototype`` frames per prototype, a 60-entry pose); the stage's
defaults (batch 32, hidden 1024, dropout 0.2, CUDA graphs unless ``--no-cuda-graphs``). The first
epoch (allocation, graph recording) is not timed.
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np


def _frames(prototypes: int, per_prototype: int, vertices: int, pose_size: int):
    from learn.tailornet.train import FrameArrays

    rng = np.random.default_rng(0)
    n = prototypes * per_prototype
    displacements = (0.01 * rng.standard_normal((n, vertices, 3))).astype(np.float32)
    return FrameArrays(pose=rng.uniform(-0.6, 0.6, (n, pose_size)).astype(np.float32),
                       shape=np.zeros((n, 6), np.float32), style=np.zeros((n, 4), np.float32),
                       displacements=displacements, pair_id=np.repeat(np.arange(prototypes), per_prototype),
                       low_frequency=np.zeros_like(displacements))


def measure(prototypes: int, *, per_prototype: int, vertices: int, pose_size: int, epochs: int, device: str,
            cuda_graphs: bool) -> dict:
    """One stacked hf stage of ``prototypes`` prototypes trained ``epochs`` + 1 epochs, the last
    ``epochs`` of them profiled."""
    from torch.profiler import ProfilerActivity, profile

    from learn.tailornet.train import train_hf

    data = _frames(prototypes, per_prototype, vertices, pose_size)
    hyper = {"hf": {"epochs": 1}, "model": {"checkpoint_interval_s": 1e9, "cuda_graphs": cuda_graphs}}
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    with tempfile.TemporaryDirectory() as tmp:
        run = dict(run_dir=Path(tmp), fingerprint=None, device=device, progress=False)
        train_hf(data, np.arange(pose_size), np.arange(prototypes), hyperparameters=hyper, **run)  # warm-up epoch
        hyper["hf"]["epochs"] = 1 + epochs
        with profile(activities=activities) as prof:
            train_hf(data, np.arange(pose_size), np.arange(prototypes), hyperparameters=hyper, **run)
        with (Path(tmp) / "hf_loss.csv").open() as handle:
            seconds = [float(row["seconds"]) for row in csv.DictReader(handle)][1:]
    events = [e for e in prof.events() if e.device_type.name == "CUDA"]

    def duration_us(event) -> float:
        return float(getattr(event, "device_time", None) or getattr(event, "cuda_time", 0.0))

    # copies: nearly all the checkpoint's load and save (GBs), outside the epochs; kernels per epoch without them
    copies = [e for e in events if e.name.startswith("Memcpy")]
    kernels = [e for e in events if not e.name.startswith("Memcpy")]
    kernel_us = sum(duration_us(e) for e in kernels)
    by_name: Counter = Counter()
    for e in kernels:
        by_name[e.name] += duration_us(e)
    steps = -(-per_prototype // 32)
    epoch_s = statistics.median(seconds)
    return {
        "prototypes": prototypes, "steps_per_epoch": steps, "epoch_s": round(epoch_s, 5),
        "ms_per_step": round(1e3 * epoch_s / steps, 4),
        # the profiled run also loads its checkpoint and saves one at its end (their few kernels
        # stay in): kernel time per epoch is an upper bound of the epochs' own
        "gpu_kernel_ms_per_epoch": round(kernel_us / 1e3 / epochs, 3) if events else None,
        "memcpy_ms_total": round(sum(duration_us(e) for e in copies) / 1e3, 1) if events else None,
        "kernels_per_step": round(len(kernels) / epochs / steps, 1) if events else None,
        "top_kernels_ms_per_epoch": {name[:80]: round(us / 1e3 / epochs, 3) for name, us in by_name.most_common(8)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--prototypes", default="1,6,7,10,20", help="comma-separated prototype counts K")
    parser.add_argument("--frames-per-prototype", type=int, default=1097,
                        help="frames per prototype (default 1,097: 21,940 train_train frames of 20 pairs)")
    parser.add_argument("--vertices", type=int, default=7744)
    parser.add_argument("--pose-size", type=int, default=60)
    parser.add_argument("--epochs", type=int, default=5, help="epochs timed per K (default 5)")
    parser.add_argument("--no-cuda-graphs", action="store_true")
    args = parser.parse_args()
    try:
        counts = [int(k) for k in args.prototypes.split(",") if k.strip()]
    except ValueError:
        parser.error(f"--prototypes {args.prototypes!r}: expected comma-separated integers >= 1")
    if not counts or min(counts) < 1:
        parser.error(f"--prototypes {args.prototypes!r}: expected comma-separated integers >= 1")
    for name in ("frames_per_prototype", "vertices", "pose_size", "epochs"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} {getattr(args, name)}: expected an integer >= 1")
    import torch

    started = time.perf_counter()
    rows = [measure(k, per_prototype=args.frames_per_prototype, vertices=args.vertices, pose_size=args.pose_size,
                    epochs=args.epochs, device=args.device, cuda_graphs=not args.no_cuda_graphs) for k in counts]
    if len(rows) > 1:
        slope, intercept = np.polyfit([r["prototypes"] for r in rows], [r["epoch_s"] for r in rows], 1)
        fit = {"epoch_s_per_prototype": round(float(slope), 5), "epoch_s_fixed": round(float(intercept), 5)}
    else:
        fit = None
    print(json.dumps({"device": args.device, "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda")
                      else None, "cuda_graphs": not args.no_cuda_graphs, "vertices": args.vertices,
                      "frames_per_prototype": args.frames_per_prototype, "linear_fit": fit, "rows": rows,
                      "seconds": round(time.perf_counter() - started, 1)}))


if __name__ == "__main__":
    main()
