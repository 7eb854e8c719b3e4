"""Training of the UV-image learners (registry names ``uvimage``, ``uvimage_pca``).

Adam, learning rate 1e-3 (seed 001); loss = masked pixel L1 (or L2) + 0.01 x normal
loss for the image decoder, mean |offset| L1 over cloth pixels + 0.01 x normal loss for
the PCA variant. The seed gives neither batch size nor epochs: we use batch 32 and 100
epochs for the image decoder (16k frames: 50k steps) and batch 64, 300 epochs for the
MLP; both are settings, not tuned results. Epochs run through
:func:`learn.tailornet.train.run_epochs` (resumable checkpoints ``<run>/<stage>.pt``,
losses in ``<run>/<stage>_loss.csv``, dataset fingerprints); the trained model goes to
``<run>/<stage>_model.pt`` with the layout arrays it is built from, so loading needs
the body model only.

With a ``regularization`` split (seed 001's held-out 2k poses; ``regularization`` below)
the training loss is evaluated on it after every epoch and the model saved is the epoch
with the lowest (:mod:`learn.uvimage.regularization`); without one, the last epoch.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learn import distributed
from learn.batches import MemoryBatches, StreamBatches, is_streamed
from learn.common.hyperparameters import checked_override
from learn.common.normals import vertex_normals
from learn.tailornet.train import (
    DatasetFingerprint,
    FrameArrays,
    check_fingerprint,
    load_checkpoint,
    run_epochs,
    save_learner,
)
from learn.uvimage.features import PoseFeatures, input_joints
from learn.uvimage.losses import NORMAL_WEIGHT, NORMS, masked_image_loss, normal_loss
from learn.uvimage.model import LAYOUT_KEYS, UVImageLearner, layout_arrays
from learn.uvimage.pca import OffsetMoments, offset_basis
from learn.uvimage.regularization import BestEpoch
from learn.uvimage.targets import ClothTargets, cloth_targets

DEFAULT_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    "uvimage": {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 32, "epochs": 100, "norm": "l1",
                "normal_weight": NORMAL_WEIGHT, "image_size": 256, "padding": 4, "start_channels": 384,
                "condition": "auto", "checkpoint_interval_s": 60.0},
    "uvimage_pca": {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 64, "epochs": 300, "normal_weight": NORMAL_WEIGHT,
                    "components": 128, "hidden": 256, "image_size": 256, "padding": 4, "condition": "auto",
                    "checkpoint_interval_s": 60.0},
}
STAGES = tuple(DEFAULT_HYPERPARAMETERS)


def merged_hyperparameters(stage: str, overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """Defaults of ``stage`` updated from ``overrides[stage]``; other stages' entries are
    ignored (a shared config may hold TailorNet's too); unknown keys raise."""
    merged = copy.deepcopy(DEFAULT_HYPERPARAMETERS[stage])
    for key, value in dict((overrides or {}).get(stage, {}) or {}).items():
        if key not in merged:
            raise ValueError(f"unknown hyper-parameter '{stage}.{key}'; expected one of {sorted(merged)}")
        merged[key] = checked_override(f"{stage}.{key}", value, merged[key])
    if merged.get("norm", "l1") not in NORMS:
        raise ValueError(f"{stage}.norm must be one of {NORMS}, got {merged['norm']!r}")
    return merged


def build_learner(stage: str, template: Any, body: Any, data: FrameArrays, hyper: Mapping[str, Any], *,
                  garment_type: str) -> UVImageLearner:
    """An untrained learner for ``template`` on ``body``, its inputs fitted to ``data``."""
    from simulate.garment.templates import body_joints

    rest, _ = body_joints(body, body.shape_default)
    layout = layout_arrays(template, rest, body.faces, image_size=int(hyper["image_size"]),
                           padding=int(hyper["padding"]))
    joints = input_joints(garment_type, template.skinning_weights, parents=body.joint_parents,
                          posable_joints=body.pose_joint_indices)
    features = PoseFeatures.for_training(joints, data.shape, data.style, condition=str(hyper["condition"]))
    kind = "image" if stage == "uvimage" else "pca"
    return UVImageLearner(layout, features, kind=kind, image_size=int(hyper["image_size"]), padding=int(hyper["padding"]),
                          start_channels=int(hyper.get("start_channels", 384)),
                          components=int(hyper.get("components", 128)), hidden=int(hyper.get("hidden", 256)),
                          style_components=int(data.style.shape[1])).attach_body(body)


def _batch_loss(net: UVImageLearner, target: ClothTargets, pose: torch.Tensor, shape: torch.Tensor,
                style: torch.Tensor, mask: torch.Tensor, *, weight: float, norm: str) -> torch.Tensor:
    """The training loss of a batch: masked pixel loss (image decoder) or mean |offset| L1 over
    cloth pixels (PCA variant), + ``weight`` x the normal loss."""
    features = net.features(pose, shape, style)
    if net.kind == "image":
        images = net.network(features)
        loss = masked_image_loss(images, net.pixels.to_images(target.local), mask, norm=norm)
        local = net.pixels.sample(images) if weight > 0 else None
    else:
        local = net.network(features)
        loss = (local - target.local).abs().sum(-1).mean()
    if weight > 0:
        garment = net.embedding.to_world(local, target.points, target.frames, net.pixels.pixel_weight)
        loss = loss + weight * normal_loss(vertex_normals(garment, net.faces), target.normals)
    return loss


def train_learner(stage: str, learner: UVImageLearner, data: FrameArrays | Any, *, run_dir: str | os.PathLike[str],
                  hyperparameters: Mapping[str, Any], fingerprint: DatasetFingerprint | None, device: str = "cpu",
                  seed: int = 0, progress: bool = True, regularization: FrameArrays | None = None) -> UVImageLearner:
    """Trains ``learner`` on ``data`` (frames with ``posed_vertices``); see the module docstring.

    In memory the targets of every frame are computed once. A streamed split
    (:class:`learn.streamed_split.StreamedSplit`) computes each batch's targets as it arrives,
    and the PCA variant's basis from the offsets' moments gathered in one streamed pass before
    training (:class:`learn.uvimage.pca.OffsetMoments`). ``hyperparameters["shuffle"]`` false
    keeps the frames' order (default: shuffled). ``regularization``: held-out frames (in memory)
    whose loss picks the epoch kept (None or no frames: the last epoch); the choice is in
    ``learner.regularization`` ({"epoch", "loss", "frames"}).
    """
    if data.frame_count == 0:
        raise ValueError(f"{stage}: no training frames")
    hyper = dict(hyperparameters)
    batch_size, weight, norm = int(hyper["batch_size"]), float(hyper["normal_weight"]), str(hyper.get("norm", "l1"))
    shuffle = bool(hyper.get("shuffle", True))
    streamed = is_streamed(data)
    if streamed:
        source = StreamBatches(data, ("pose", "shape", "style", "posed_vertices"), batch_size=batch_size,
                               device=device, shuffle=shuffle)
        if learner.kind == "pca":
            moments = OffsetMoments(learner.pixels.pixel_count, device)
            for batch in source.once():
                moments.add(_targets(learner, batch, device).local)
            moments.all_reduce()
            mean, basis, singular = moments.basis(int(hyper["components"]))
            learner.network.set_basis(mean.to(device), basis.to(device), singular.to(device), data.frame_count)
    else:
        targets = cloth_targets(learner, data.pose, data.shape, data.posed_vertices, translation=data.translation,
                                device=device)
        if learner.kind == "pca":
            mean, basis, singular = offset_basis(targets.local.cpu(), int(hyper["components"]))
            learner.network.set_basis(mean.to(device), basis.to(device), singular.to(device), data.frame_count)
        source = MemoryBatches({"pose": data.pose, "shape": data.shape, "style": data.style, "local": targets.local,
                                "points": targets.points, "frames": targets.frames, "normals": targets.normals},
                               batch_size=batch_size, device=device, shuffle=shuffle)
    mask = learner.pixels.mask.to(device)

    def epoch_fn(net: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        total = torch.zeros((), device=device)
        for batch in source.epoch(generator, optimizer):  # this rank's frames (all in one process)
            target = _targets(net, batch, device) if streamed else ClothTargets(
                batch["local"], batch["points"], batch["frames"], batch["normals"])
            loss = _batch_loss(net, target, batch["pose"], batch["shape"], batch["style"], mask, weight=weight,
                               norm=norm)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * batch.frames
        return float(total) / data.frame_count

    best = None
    held_out_count = 0
    if regularization is not None and regularization.frame_count > 0:
        held_out_count = regularization.frame_count
        held = cloth_targets(learner, regularization.pose, regularization.shape, regularization.posed_vertices,
                             translation=regularization.translation, device=device)
        held_inputs = [torch.as_tensor(a, dtype=torch.float32, device=device)
                       for a in (regularization.pose, regularization.shape, regularization.style)]

        def held_out_loss(net: torch.nn.Module) -> float:
            total = torch.zeros((), device=device)
            for begin in range(0, held_out_count, batch_size):
                rows = slice(begin, min(begin + batch_size, held_out_count))
                target = ClothTargets(held.local[rows], held.points[rows], held.frames[rows], held.normals[rows])
                loss = _batch_loss(net, target, *(a[rows] for a in held_inputs), mask, weight=weight, norm=norm)
                total += loss * (rows.stop - rows.start)
            return float(total) / held_out_count

        best = BestEpoch(stage, run_dir, held_out_loss, writes=distributed.writes_files())
    learner.train()
    learner = run_epochs(stage, learner.to(device), epoch_fn, run_dir=run_dir, hyperparameters=hyper,
                         fingerprint=fingerprint, device=device, seed=seed, progress=progress, after_epoch=best)
    learner.regularization = None
    if best is not None:
        learner.regularization = {**best.restore(learner), "frames": held_out_count}
    return learner


def _targets(learner: UVImageLearner, batch: Mapping[str, torch.Tensor], device: str) -> ClothTargets:
    """The targets of a streamed batch's frames (the training mode is kept: ``cloth_targets`` runs
    without gradients and uses no layer that trains)."""
    return cloth_targets(learner, batch["pose"], batch["shape"], batch["posed_vertices"], device=device)


def _fit(stage: str, data: FrameArrays, *, run_dir, hyperparameters, fingerprint, device, seed, progress,
         template=None, body=None, garment_type: str = "tshirt",
         regularization: FrameArrays | None = None) -> UVImageLearner:
    if template is None or body is None:
        raise ValueError(f"{stage} needs the garment template and the body model (drape train passes them: "
                         "learn.uvimage.garment.uvimage_context)")
    hyper = merged_hyperparameters(stage, hyperparameters)
    torch.manual_seed(seed)  # deterministic initial weights
    learner = build_learner(stage, template, body, data, hyper, garment_type=garment_type)
    learner = train_learner(stage, learner, data, run_dir=run_dir, hyperparameters=hyper, fingerprint=fingerprint,
                            device=device, seed=seed, progress=progress, regularization=regularization)
    save_uvimage(learner, stage, Path(run_dir) / f"{stage}_model.pt", fingerprint=fingerprint, hyperparameters=hyper,
                 body=body)
    if learner.regularization is not None and progress and distributed.writes_files():
        chosen = learner.regularization
        print(f"{stage}: kept epoch {chosen['epoch']} of {hyper['epochs']}, the lowest loss on the "
              f"{chosen['frames']} regularization frames ({chosen['loss']:.6g})")
    return learner


def fit_uvimage(data: FrameArrays, faces: np.ndarray, *, run_dir: str | os.PathLike[str], pose_indices=None,
                canonical_pose=None, hyperparameters: Mapping[str, Any] | None = None,
                fingerprint: DatasetFingerprint | None = None, device: str = "cpu", seed: int = 0,
                progress: bool = True, template=None, body=None, garment_type: str = "tshirt",
                regularization: FrameArrays | None = None) -> UVImageLearner:
    """Registry ``fit`` of the whole-image decoder: trains and saves ``uvimage_model.pt``.
    ``template`` (a ``GarmentTemplate``), ``body``, ``garment_type`` and ``regularization``
    (the dataset's regularization frames, or None) come from
    :func:`learn.uvimage.garment.uvimage_context`; ``faces``, ``pose_indices`` and
    ``canonical_pose`` are unused (the inputs are joint rotations, :mod:`features`)."""
    del faces, pose_indices, canonical_pose
    return _fit("uvimage", data, run_dir=run_dir, hyperparameters=hyperparameters, fingerprint=fingerprint,
                device=device, seed=seed, progress=progress, template=template, body=body, garment_type=garment_type,
                regularization=regularization)


def fit_uvimage_pca(data: FrameArrays, faces: np.ndarray, *, run_dir: str | os.PathLike[str], pose_indices=None,
                    canonical_pose=None, hyperparameters: Mapping[str, Any] | None = None,
                    fingerprint: DatasetFingerprint | None = None, device: str = "cpu", seed: int = 0,
                    progress: bool = True, template=None, body=None, garment_type: str = "tshirt",
                    regularization: FrameArrays | None = None) -> UVImageLearner:
    """Registry ``fit`` of the fully connected 128-PC variant: saves ``uvimage_pca_model.pt``."""
    del faces, pose_indices, canonical_pose
    return _fit("uvimage_pca", data, run_dir=run_dir, hyperparameters=hyperparameters, fingerprint=fingerprint,
                device=device, seed=seed, progress=progress, template=template, body=body, garment_type=garment_type,
                regularization=regularization)


def save_uvimage(learner: UVImageLearner, stage: str, path: str | os.PathLike[str], *,
                 fingerprint: DatasetFingerprint | None, hyperparameters: Mapping[str, Any], body: Any) -> Path:
    """The trained learner with its layout arrays and body backend (see :func:`load_uvimage`)."""
    layout = {k: torch.as_tensor(v) for k, v in learner.layout.items()}
    body_spec = {"backend": getattr(body, "name", "anny"), "path": getattr(body, "path", None)}
    return save_learner(learner, stage, path, fingerprint=fingerprint,
                        extra={"hyperparameters": dict(hyperparameters), "layout": layout, "body": body_spec,
                               "regularization": getattr(learner, "regularization", None)})


def load_uvimage(path: str | os.PathLike[str], *, fingerprint: DatasetFingerprint | None = None,
                 require_same_manifest: bool = True, device: str = "cpu", body: Any = None) -> UVImageLearner:
    """Loads a learner saved by :func:`save_uvimage`, checks its dataset fingerprint and
    attaches ``body`` (default: the saved backend through ``simulate.body.load_body_model``)."""
    checkpoint = load_checkpoint(path, map_location="cpu")
    check_fingerprint(checkpoint.get("fingerprint"), fingerprint, source=str(path),
                      require_same_manifest=require_same_manifest)
    if checkpoint.get("learner") not in STAGES:
        raise ValueError(f"{path} holds learner '{checkpoint.get('learner')}', expected one of {list(STAGES)}")
    config = checkpoint["model_config"]
    learner = UVImageLearner(checkpoint["layout"], PoseFeatures.from_config(config["features"]), kind=config["kind"],
                             image_size=config["image_size"], padding=config["padding"],
                             start_channels=config["start_channels"], components=config["components"],
                             hidden=config["hidden"], style_components=config["style_components"])
    learner.load_state_dict(checkpoint["model_state"])
    if body is None:
        from simulate.body import load_body_model

        spec = checkpoint.get("body") or {"backend": "anny", "path": None}
        body = load_body_model(spec.get("backend", "anny"), path=spec.get("path"))
    return learner.attach_body(body).to(device).eval()


__all__ = ["fit_uvimage", "fit_uvimage_pca", "load_uvimage", "save_uvimage", "build_learner", "train_learner",
           "DEFAULT_HYPERPARAMETERS", "LAYOUT_KEYS"]
