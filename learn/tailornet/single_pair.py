"""Single style-shape models (TailorNet section 4.3 / 6.1): one pose MLP per training pair.

Each pair's MLP maps pose to that pair's full unposed displacements [m] and sees only that
pair's frames; the K MLPs train together as one batched network
(:class:`learn.tailornet.hf.HighFrequencyPrototypes`, :func:`learn.tailornet.train.train_stacked_prototypes`)
with the HF stage's hyper-parameters (the paper's single style-shape models are its
D_HF prototypes). Their error on the pairs' unseen poses (``train_test``) is a floor for the
learners that must also generalise over style and shape: the paper reports 8.04 mm mean,
6.56-14.50 mm over pairs.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learn.tailornet.hf import HighFrequencyPrototypes, high_frequency_model
from learn.tailornet.train import (
    FrameArrays,
    stage_hyper,
    merged_hyperparameters,
    train_stacked_prototypes,
)

STAGE = "single_pair"


def pair_keys(data: FrameArrays) -> np.ndarray:
    """Each frame's style-shape pair as its (shape, style) values, (N, S + G) float32: pair ids
    are numbered per split, the values identify a pair across splits."""
    return np.concatenate([data.shape, data.style], axis=1).astype(np.float32)


def fit_single_pair(
    data: FrameArrays,
    pose_indices: np.ndarray,
    *,
    run_dir: str | os.PathLike[str],
    pairs: np.ndarray | None = None,
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = False,
) -> tuple[HighFrequencyPrototypes, np.ndarray]:
    """Train one pose MLP per pair of ``data`` (ids ``pairs``, default all) on its frames.

    Returns the K MLPs stacked (eval mode) and the pairs' keys (K, S + G) (see :func:`pair_keys`).
    Checkpoints and the loss log go to ``run_dir`` (stage ``single_pair``, resumable).
    """
    hyper = merged_hyperparameters(hyperparameters)
    pairs = np.unique(data.pair_id) if pairs is None else np.asarray(pairs).reshape(-1)
    frames = [np.flatnonzero(data.pair_id == p) for p in pairs]
    empty = [int(p) for p, f in zip(pairs, frames) if f.size == 0]
    if empty:
        raise ValueError(f"pairs {empty} have no frames in the training data")
    initial = []
    for k in range(len(frames)):
        torch.manual_seed(seed + 1 + k)  # deterministic initial weights
        initial.append(high_frequency_model(data.vertex_count, pose_indices, hidden_size=int(hyper["hf"]["hidden_size"]),
                                            dropout=float(hyper["hf"]["dropout"])))
    model = train_stacked_prototypes(
        HighFrequencyPrototypes.from_mlps(initial), data, data.displacements, frames, run_dir=run_dir,
        hyperparameters=stage_hyper(hyper["hf"], hyper["model"]), fingerprint=None, device=device, seed=seed + 1,
        progress=progress, stage=STAGE,
    )
    keys = pair_keys(data)
    return model, np.stack([keys[f[0]] for f in frames])


@torch.no_grad()
def single_pair_errors(
    model: HighFrequencyPrototypes, keys: np.ndarray, data: FrameArrays, *, device: str = "cpu",
    batch_size: int = 256,
) -> dict[str, Any]:
    """Mean per-vertex error [mm] of each pair's MLP on that pair's frames of ``data``.

    Frames of pairs the model has no MLP for are left out. Returns ``error_mm`` (mean over the
    frames covered), ``frames``, and ``per_pair``: one dict per MLP with ``frames`` and
    ``error_mm`` (None when ``data`` has no frame of that pair).
    """
    model = model.to(device).eval()
    frame_keys = pair_keys(data)
    owner = np.full(data.frame_count, -1, dtype=np.int64)
    for k, key in enumerate(np.asarray(keys, np.float32)):
        owner[np.all(frame_keys == key[None], axis=1)] = k
    covered = np.flatnonzero(owner >= 0)
    errors = np.empty(covered.size, dtype=np.float64)
    for start in range(0, covered.size, batch_size):
        rows = covered[start:start + batch_size]
        pose = torch.as_tensor(data.pose[rows]).to(device)
        weights = torch.nn.functional.one_hot(torch.as_tensor(owner[rows]), model.prototype_count).float().to(device)
        predicted = model(pose, weights, weight_floor=0.5)  # one-hot: only the frames' own MLPs run
        truth = torch.as_tensor(data.displacements[rows]).to(device)
        errors[start:start + rows.size] = (torch.linalg.vector_norm(predicted - truth, dim=-1).mean(-1) * 1e3).cpu().numpy()
    per_pair = []
    for k in range(model.prototype_count):
        mine = owner[covered] == k
        per_pair.append({"frames": int(mine.sum()), "error_mm": float(errors[mine].mean()) if mine.any() else None})
    return {"frames": int(covered.size), "error_mm": float(errors.mean()) if covered.size else None, "per_pair": per_pair}


def single_pair_floor(
    reader: Any,
    data: str | os.PathLike[str],
    *,
    run_dir: str | os.PathLike[str],
    device: str = "cpu",
    epochs: int | None = None,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, Any]:
    """The single-pair figure of ``drape report floor``: MLPs of the training pairs that have
    ``train_test`` frames, trained on their ``train_train`` frames, errors on both splits.
    ``reader``: the dataset's ``DatasetReader``; the pose input is masked as ``drape train``
    masks it (the joints that move the garment)."""
    from learn.data import DrapeDataset
    from learn.tailornet.train import frame_arrays_from_dataset, garment_pose_indices
    from simulate.body import load_body_model

    for split in ("train_train", "train_test"):
        if split not in reader.splits or reader.num_frames(split) == 0:
            raise ValueError(f"dataset {data} has no frames in split {split!r}; the single-pair floor needs "
                             "train_train and train_test")
    train = frame_arrays_from_dataset(DrapeDataset(data, "train_train", frequencies=False))
    test = frame_arrays_from_dataset(DrapeDataset(data, "train_test", frequencies=False))
    body_spec = reader.manifest.spec.get("body", {"backend": "anny", "path": None})
    body = load_body_model(body_spec.get("backend", "anny"), path=body_spec.get("path"))
    pose_indices = garment_pose_indices(reader.template["skinning_weights"], body.pose_size,
                                        parents=body.joint_parents, posable_joints=body.pose_joint_indices)
    test_keys = {k.tobytes() for k in pair_keys(test)}
    train_keys = pair_keys(train)
    pairs = np.array([p for p in np.unique(train.pair_id)
                      if train_keys[np.flatnonzero(train.pair_id == p)[0]].tobytes() in test_keys])
    if pairs.size == 0:
        raise ValueError(f"no training pair of dataset {data} has train_test frames")
    hyper = {"hf": {"epochs": int(epochs)}} if epochs is not None else None
    model, keys = fit_single_pair(train, pose_indices, run_dir=Path(run_dir), pairs=pairs, hyperparameters=hyper,
                                  device=device, seed=seed, progress=progress)
    on_train = single_pair_errors(model, keys, train, device=device)
    on_test = single_pair_errors(model, keys, test, device=device)
    per_pair = [{"train_frames": a["frames"], "test_frames": b["frames"], "train_error_mm": a["error_mm"],
                 "test_error_mm": b["error_mm"]} for a, b in zip(on_train["per_pair"], on_test["per_pair"])]
    tested = [p["test_error_mm"] for p in per_pair if p["test_error_mm"] is not None]
    return {"pairs": int(pairs.size), "epochs": int(merged_hyperparameters(hyper)["hf"]["epochs"]),
            "train_error_mm": on_train["error_mm"], "test_error_mm": on_test["error_mm"],
            "best_pair_test_error_mm": min(tested), "worst_pair_test_error_mm": max(tested), "per_pair": per_pair}
