"""One-command sweep of TailorNet's error against its free choices, printed as one JSON line:
kernel sigma, prototype count K, high-frequency epochs and pose-input masking.

    python bench/sweep_tailornet.py DATASET --device cuda [--sigmas 0.003,0.01,0.03,0.1]
        [--prototypes 10,20] [--hf-epochs 200,400,800] [--no-mask-variant] [--epochs N] [--out DIR]

What each variant retrains: sigma only weighs the trained prototypes (no training, one model
evaluated per sigma); K and the HF epochs retrain the HF stage only (g, the low-frequency MLP and
the baseline are shared: their finished checkpoints are copied into the variant's run, where
they load without further epochs; the epochs continue one run, 200 -> 400 -> 800); the unmasked
pose input (every pose entry, ``model.pose_mask: false``) retrains every stage. Each variant
reports the unposed error [mm] on every test split and on 4,000 training frames, and its seconds.
``--epochs N`` sets every stage's epochs (a smoke run); HF epochs then follow ``--hf-epochs``.
HF checkpoints (about 6 GB each at full scale) are written only at the end of a run and
deleted once a variant is evaluated, unless ``--out`` asks to keep the runs.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

SHARED_STAGES = ("shape_style", "lf")


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def _errors(model, train, tests, device) -> dict:
    from learn.tailornet.evaluate import evaluate_split

    rows = np.linspace(0, train.frame_count - 1, min(4000, train.frame_count)).round().astype(np.int64)
    out = {"train": round(evaluate_split(model, train.subset(rows), device=device)["unposed_error_mm"], 3)}
    out.update({s: round(evaluate_split(model, d, device=device)["unposed_error_mm"], 3) for s, d in tests.items()})
    return out


def _copy_shared(source: Path, target: Path) -> None:
    target.mkdir(parents=True, exist_ok=True)
    for stage in SHARED_STAGES:
        for suffix in (".pt", ".done", "_loss.csv"):
            shutil.copy2(source / f"{stage}{suffix}", target / f"{stage}{suffix}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sigmas", default="0.003,0.01,0.03,0.1")
    parser.add_argument("--prototypes", default="10,20")
    parser.add_argument("--hf-epochs", default="200,400,800")
    parser.add_argument("--no-mask-variant", action="store_true", help="skip the unmasked pose input (a full retrain)")
    parser.add_argument("--epochs", type=int, default=None, help="every stage's epochs (default the paper's)")
    parser.add_argument("--mixed-precision", action="store_true")
    parser.add_argument("--out", default=None, help="keep the runs here (default: a temporary directory)")
    args = parser.parse_args()
    from bench_train import _dataset

    from learn.tailornet.train import fit_baseline, fit_tailornet

    t_all = time.perf_counter()
    train, tests, faces, _, pose_indices, load_s = _dataset(Path(args.data), args.device)
    pairs = int(np.unique(train.pair_id).size)
    prototypes = [k for k in _ints(args.prototypes) if k <= pairs] or [pairs]
    hf_epochs = sorted(_ints(args.hf_epochs))
    base_hyper: dict = {"model": {"checkpoint_interval_s": 1e9, "mixed_precision": args.mixed_precision,
                                  "shape_components": train.shape.shape[1], "style_components": train.style.shape[1]}}
    if args.epochs is not None:
        base_hyper.update({stage: {"epochs": args.epochs} for stage in ("lf", "shape_style", "baseline")})
    result: dict = {"data": args.data, "device": args.device, "load_s": round(load_s, 2), "train_frames": train.frame_count,
                    "pairs": pairs, "rows": []}
    keep = args.out is not None
    root = Path(args.out) if keep else Path(tempfile.mkdtemp(prefix="sweep_tailornet_"))
    try:
        base = root / "shared"
        t0 = time.perf_counter()
        baseline = fit_baseline(train, faces, run_dir=base, pose_indices=pose_indices, hyperparameters=base_hyper,
                                device=args.device, progress=False)
        result["rows"].append({"variant": "baseline", "errors_mm": _errors(baseline, train, tests, args.device),
                               "seconds": round(time.perf_counter() - t0, 1)})
        fit_tailornet(train, faces, run_dir=base, pose_indices=pose_indices, stages=list(SHARED_STAGES),
                      hyperparameters=base_hyper, device=args.device, progress=False)
        for k in prototypes:
            run_dir = root / f"k{k}"
            _copy_shared(base, run_dir)
            for epochs in hf_epochs:
                t0 = time.perf_counter()
                hyper = {**base_hyper, "model": {**base_hyper["model"], "prototype_count": k}, "hf": {"epochs": epochs}}
                model = fit_tailornet(train, faces, run_dir=run_dir, pose_indices=pose_indices, hyperparameters=hyper,
                                      device=args.device, progress=False)
                fit_s = round(time.perf_counter() - t0, 1)
                for sigma in _floats(args.sigmas):
                    model.sigma = float(sigma)
                    result["rows"].append({"variant": "tailornet", "prototypes": k, "hf_epochs": epochs, "sigma": sigma,
                                           "pose_mask": True, "errors_mm": _errors(model, train, tests, args.device),
                                           "fit_s": fit_s})
                print(json.dumps(result["rows"][-1]), file=sys.stderr, flush=True)
            if not keep:
                shutil.rmtree(run_dir, ignore_errors=True)
        if not args.no_mask_variant:
            t0 = time.perf_counter()
            run_dir = root / "unmasked"
            all_entries = np.arange(train.pose.shape[1])
            k, epochs = max(prototypes), max(hf_epochs)
            hyper = {**base_hyper, "model": {**base_hyper["model"], "prototype_count": k}, "hf": {"epochs": epochs}}
            model = fit_tailornet(train, faces, run_dir=run_dir, pose_indices=all_entries, hyperparameters=hyper,
                                  device=args.device, progress=False)
            unmasked_baseline = fit_baseline(train, faces, run_dir=run_dir, pose_indices=all_entries,
                                             hyperparameters=base_hyper, device=args.device, progress=False)
            seconds = round(time.perf_counter() - t0, 1)
            result["rows"].append({"variant": "tailornet", "prototypes": k, "hf_epochs": epochs, "sigma": model.sigma,
                                   "pose_mask": False, "errors_mm": _errors(model, train, tests, args.device),
                                   "fit_s": seconds})
            result["rows"].append({"variant": "baseline", "pose_mask": False,
                                   "errors_mm": _errors(unmasked_baseline, train, tests, args.device)})
    finally:
        if not keep:
            shutil.rmtree(root, ignore_errors=True)
    result["seconds"] = round(time.perf_counter() - t_all, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
