"""How a dataset's verdicts follow the poses' skin clearance (``simulate.body.clearance``): reads
every target of a kept dataset (kept frames and the dropped-frame logs of its shards), measures
each pose's arm-to-torso clearance (or leg-to-leg for bottoms) on the body model's neutral shape,
the shape ``poses.min_clearance`` prunes on, and prints one JSON line: per clearance bin the
share of the targets, the share kept and the share dropped for self-intersection, and the
Spearman rank correlation of clearance and verdict (and of the capsule test's overlap depth, which
the sampler prunes by anyway).

    python bench/bench_dataset.py ... --out DIR --keep        # (or T=... KEEP=1 device_suite.sh dataset-scale)
    python bench/bench_pose_clearance.py DIR [--pairs upper] [--bins 0 0.005 0.01 0.02 0.03 0.04 1]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def dataset_verdicts(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """Poses (N, P) and verdicts (N,) str ("kept" or the drop reason) of every listed shard."""
    import h5py

    from data_manifest.reader import DatasetReader
    from data_manifest.schema import POSE
    from data_manifest.shard import read_dropped_log

    reader = DatasetReader(root)
    poses, verdicts = [], []
    for entry in reader.shard_entries:
        with h5py.File(root / entry["path"], "r") as handle:
            if POSE in handle and handle[POSE].shape[0]:
                poses.append(np.asarray(handle[POSE][()], np.float32))
                verdicts += ["kept"] * len(poses[-1])
            log = read_dropped_log(handle)
            if log is not None and len(log["pose"]):
                poses.append(log["pose"])
                verdicts += [str(r) for r in log["reason"]]
    reader.close()
    if not poses:
        raise ValueError(f"{root}: no kept frames and no logged dropped frames to relate to clearance")
    return np.concatenate(poses), np.array(verdicts)


def rank_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rho (scipy), nan when either side is constant."""
    from scipy.stats import spearmanr

    a, b = np.asarray(a, float), np.asarray(b, float)
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(spearmanr(a, b).statistic)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--pairs", default="upper", help="clearance pairs: upper (arms-torso), lower (legs), all")
    parser.add_argument("--bins", type=float, nargs="+", default=[0, 0.005, 0.01, 0.015, 0.02, 0.025, 0.03, 0.04, 1.0],
                        help="bin edges of the clearance [m]")
    parser.add_argument("--backend", default="anny")
    args = parser.parse_args()

    from simulate.body import load_body_model
    from simulate.body.clearance import CLEARANCE_PAIRS, LimbClearance
    from simulate.body.mesh_utils import SelfIntersectionChecker

    poses, verdicts = dataset_verdicts(args.dataset)
    body = load_body_model(args.backend)
    shape = np.asarray(body.shape_default, np.float32).reshape(-1)
    clearance = LimbClearance(body, shape, CLEARANCE_PAIRS[args.pairs]).measure(poses).min(axis=1)
    depth = SelfIntersectionChecker(body, shape).check(poses)[1]
    kept = verdicts == "kept"
    edges = np.asarray(args.bins)
    which = np.clip(np.digitize(clearance, edges) - 1, 0, len(edges) - 2)
    bins = []
    for b in range(len(edges) - 1):
        m = which == b
        bins.append({"clearance_m": [float(edges[b]), float(edges[b + 1])], "targets": int(m.sum()),
                     "share": round(float(m.mean()), 4),
                     "kept": round(float(kept[m].mean()), 4) if m.any() else None,
                     "self_intersection": round(float((verdicts[m] == "self_intersection").mean()), 4) if m.any() else None,
                     "kept_if_pruned_below": round(float(kept[clearance >= edges[b + 1]].mean()), 4)
                     if (clearance >= edges[b + 1]).any() else None})
    print(json.dumps({"bench": "pose_clearance", "dataset": str(args.dataset), "pairs": args.pairs,
                      "targets": int(len(poses)), "kept": round(float(kept.mean()), 4),
                      "verdicts": {str(k): int(v) for k, v in zip(*np.unique(verdicts, return_counts=True))},
                      "spearman_clearance_kept": round(rank_correlation(clearance, kept), 3),
                      "spearman_capsule_depth_kept": round(rank_correlation(depth, kept), 3), "bins": bins}))


if __name__ == "__main__":
    main()
