"""Where a learner's error comes from: training against test error, error per style-shape pair,
error against the distance to the nearest training pose, and error by whether the training
pairs wear the test pair's style and shape.

Pose distance: the Euclidean norm [rad] of the axis-angle difference over the pose entries the
model reads (``pose_indices`` of its networks; all entries when it has none), so joints a
garment ignores do not count. Frames are binned by that distance at quantiles of the test
frames' distances, so each bin holds about as many frames; a frame of a training pose has
distance 0.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from learn.tailornet.evaluate import evaluate_split
from learn.tailornet.train import FrameArrays, row_keys


def model_pose_indices(model: torch.nn.Module, pose_size: int) -> np.ndarray:
    """The pose entries ``model`` reads: its (first) ``pose_indices`` buffer, else all ``pose_size``."""
    for module in model.modules():
        indices = getattr(module, "pose_indices", None)
        if isinstance(indices, torch.Tensor) and indices.numel():
            return indices.cpu().numpy().astype(np.int64)
    return np.arange(pose_size)


@torch.no_grad()
def nearest_pose_distance(query: np.ndarray, reference: np.ndarray, indices: np.ndarray, *,
                          device: str = "cpu", chunk: int = 4096) -> np.ndarray:
    """Distance [rad] of each query pose to its nearest reference pose over ``indices``, (N,).

    query (N, P), reference (M, P); ``torch.cdist`` in chunks of ``chunk`` queries on ``device``."""
    if len(reference) == 0:
        raise ValueError("nearest_pose_distance needs at least one reference pose")
    ref = torch.as_tensor(np.asarray(reference, np.float32)[:, indices]).to(device)
    out = []
    for start in range(0, len(query), chunk):
        q = torch.as_tensor(np.asarray(query[start:start + chunk], np.float32)[:, indices]).to(device)
        out.append(torch.cdist(q[None], ref[None])[0].min(dim=1).values.cpu().numpy())
    return np.concatenate(out) if out else np.zeros(0, np.float32)


def _pair_table(errors: np.ndarray, data: FrameArrays) -> list[dict[str, Any]]:
    rows = []
    for pair in np.unique(data.pair_id):
        mine = data.pair_id == pair
        first = int(np.flatnonzero(mine)[0])
        rows.append({"pair": int(pair), "frames": int(mine.sum()), "error_mm": float(errors[mine].mean()),
                     "shape": data.shape[first].tolist(), "style": data.style[first].tolist()})
    return sorted(rows, key=lambda r: -r["error_mm"])


#: The groups of :func:`coverage_groups`, in report order.
COVERAGE_GROUPS = ("style_and_shape_in_training", "style_not_in_training", "shape_not_in_training",
                   "neither_in_training")


def coverage_groups(train: FrameArrays, data: FrameArrays) -> np.ndarray:
    """For each frame of ``data``, (N,), the index into :data:`COVERAGE_GROUPS` of whether a
    training frame wears its style and whether one has its shape (each compared exactly): a test
    pair of seen styles and shapes can still wear a style that no training pair wears, and a
    learner then meets that style for the first time."""
    styles, shapes = set(row_keys(train.style)), set(row_keys(train.shape))
    style_seen = np.array([key in styles for key in row_keys(data.style)], dtype=bool)
    shape_seen = np.array([key in shapes for key in row_keys(data.shape)], dtype=bool)
    return np.where(style_seen, np.where(shape_seen, 0, 2), np.where(shape_seen, 1, 3)).astype(np.int64)


def error_analysis(
    models: dict[str, torch.nn.Module],
    train: FrameArrays,
    splits: dict[str, FrameArrays],
    *,
    bins: int = 5,
    device: str = "cpu",
    train_frames: int | None = 4000,
) -> dict[str, Any]:
    """The error analysis of ``models`` (JSON-serialisable).

    Args:
        models: name -> trained model (TailorNet, baseline, ...).
        train: the training split's frames; the error on it (at most ``train_frames`` evenly
            spaced frames, None: all) is the training error, its poses the nearest-pose reference.
        splits: test split name -> frames.
        bins: distance bins per split (quantiles of the split's nearest-pose distances).
    Returns ``{"train": {model: error_mm}, "splits": {split: {"models": {model: {"error_mm",
    "generalisation_gap_mm", "per_pair"}}, "distance_bins": [{"lower_rad", "upper_rad", "frames",
    "error_mm": {model: mm}}], "coverage": {group: {"frames", "pairs", "error_mm": {model: mm}}}}}}``;
    the gap is the split's error minus the training error; ``coverage`` splits the frames by whether
    a training frame wears their style and has their shape (:func:`coverage_groups`).
    """
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    if train_frames is not None and train_frames < train.frame_count:
        train_eval = train.subset(np.linspace(0, train.frame_count - 1, train_frames).round().astype(np.int64))
    else:
        train_eval = train
    report: dict[str, Any] = {"train_frames_evaluated": train_eval.frame_count, "train": {}, "splits": {}}
    for name, model in models.items():
        report["train"][name] = evaluate_split(model, train_eval, device=device)["unposed_error_mm"]
    indices = model_pose_indices(next(iter(models.values())), train.pose.shape[1])
    for split, data in splits.items():
        distance = nearest_pose_distance(data.pose, train.pose, indices, device=device)
        edges = np.unique(np.quantile(distance, np.linspace(0.0, 1.0, bins + 1)))
        which = np.clip(np.searchsorted(edges, distance, side="right") - 1, 0, max(len(edges) - 2, 0))
        per_model, per_frame = {}, {}
        for name, model in models.items():
            errors = evaluate_split(model, data, device=device, per_frame=True)["unposed_error_mm_per_frame"]
            per_frame[name] = errors
            per_model[name] = {"error_mm": float(errors.mean()),
                               "generalisation_gap_mm": float(errors.mean()) - report["train"][name],
                               "per_pair": _pair_table(errors, data)}
        table = []
        for b in range(max(len(edges) - 1, 1)):
            mine = which == b
            if not mine.any():
                continue
            table.append({"lower_rad": float(edges[b]), "upper_rad": float(edges[min(b + 1, len(edges) - 1)]),
                          "frames": int(mine.sum()),
                          "error_mm": {name: float(e[mine].mean()) for name, e in per_frame.items()}})
        group = coverage_groups(train, data)
        coverage = {}
        for g, label in enumerate(COVERAGE_GROUPS):
            mine = group == g
            if mine.any():
                coverage[label] = {"frames": int(mine.sum()), "pairs": int(np.unique(data.pair_id[mine]).size),
                                   "error_mm": {name: float(e[mine].mean()) for name, e in per_frame.items()}}
        report["splits"][split] = {"models": per_model, "distance_bins": table, "coverage": coverage,
                                   "median_nearest_pose_rad": float(np.median(distance))}
    return report


def format_analysis(report: dict[str, Any]) -> str:
    """The analysis as a few lines of text: train/test error per model, distance bins."""
    names = list(report["train"])
    lines = ["train error (mm): " + ", ".join(f"{n} {report['train'][n]:.2f}" for n in names)]
    for split, part in report["splits"].items():
        lines.append(f"{split}: " + ", ".join(
            f"{n} {m['error_mm']:.2f} (gap {m['generalisation_gap_mm']:+.2f}, worst pair {m['per_pair'][0]['error_mm']:.2f})"
            for n, m in part["models"].items()))
        for row in part["distance_bins"]:
            lines.append(f"  nearest training pose {row['lower_rad']:.3f}-{row['upper_rad']:.3f} rad, "
                         f"{row['frames']} frames: " + ", ".join(f"{n} {e:.2f}" for n, e in row["error_mm"].items()))
        for label, row in part.get("coverage", {}).items():
            lines.append(f"  {label.replace('_', ' ')}: {row['pairs']} pairs, {row['frames']} frames: "
                         + ", ".join(f"{n} {e:.2f}" for n, e in row["error_mm"].items()))
    return "\n".join(lines)
