"""Training of the GCVAE on a static set (``drape train gcvae --data DIR --out RUN``) or, the
dynamic variant, on the frames of motion datasets (:class:`learn.gcvae.dynamic_set.DynamicSet`,
``drape train gcvae --dynamic``): the same network with the set's condition (shape, tightness
and the poses of ``dynamic.frames`` frames) and ``model.channels`` times ``dynamic.channel_factor``.

The train split is shuffled once (seeded) into training and validation
(``train.validation_fraction``); the epoch loop is TailorNet's resumable one
(:func:`learn.tailornet.train.run_epochs`: checkpoint ``RUN/gcvae.pt``, per-epoch log
``RUN/gcvae_loss.csv`` with the mean surface error of the training batches [m]); each epoch's
loss terms and validation error go to ``RUN/gcvae_terms.csv``, and the epoch with the lowest
validation surface error is kept in ``RUN/gcvae_best.pt`` (the seed: "we save the best model
with lowest error on the validation set"). The final model (``RUN/gcvae_model.pt``) holds
the best epoch's weights, the body mesh graph it runs on and the set's fingerprint.
"""
from __future__ import annotations

import csv
import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learn import distributed
from learn.gcvae.body_mesh import DUAL_TYPES, BodyMesh
from learn.gcvae.hyperparameters import merged
from learn.gcvae.losses import gcvae_loss, kl_weight
from learn.gcvae.model import GCVAE
from learn.gcvae.static_set import StaticSet
from learn.tailornet.train import (DatasetFingerprint, atomic_save, check_fingerprint, file_sha256, load_checkpoint,
                                   run_epochs)

MODEL_FILE = "gcvae_model.pt"
BEST_FILE = "gcvae_best.pt"


def set_fingerprint(data: StaticSet) -> DatasetFingerprint:
    """sha256 of the static set file (a dynamic set: of its datasets' manifests) and of its body
    mesh graph (edges, faces, segments)."""
    h = hashlib.sha256()
    for a in (data.mesh.edges, data.mesh.faces, data.mesh.dual_faces, data.mesh.segments):
        h.update(np.ascontiguousarray(a, np.int64).tobytes())
    source = data.sha256 if is_dynamic(data) else file_sha256(data.path)
    return DatasetFingerprint(source, h.hexdigest())


def is_dynamic(data) -> bool:
    """Whether ``data`` is a dynamic set (frames of motion sequences) rather than a static set."""
    return hasattr(data, "layout")


def condition_of(data: StaticSet, index: np.ndarray) -> np.ndarray:
    """The conditioning: static set (M, 7): anny shape (6) and tightness [m] (1); dynamic set
    (M, C): its ``condition`` (shape, tightness, poses of T frames)."""
    if is_dynamic(data):
        return data.condition[index].astype(np.float32)
    return np.concatenate([data.shape[index], data.tightness[index, None]], 1).astype(np.float32)


def tensors(data: StaticSet, index: np.ndarray, device: str = "cpu") -> dict[str, torch.Tensor]:
    """The samples ``index`` of a set as the batch dict the model and loss take."""
    dual = np.isin(np.asarray(data.types)[data.type[index]], list(DUAL_TYPES))
    return {"body": torch.as_tensor(data.body_vertices[index], dtype=torch.float32, device=device),
            "offsets": torch.as_tensor(data.offsets[index], dtype=torch.float32, device=device),
            "mask": torch.as_tensor(data.mask[index], dtype=torch.bool, device=device),
            "condition": torch.as_tensor(condition_of(data, index), device=device),
            "dual": torch.as_tensor(dual, device=device),
            "type": torch.as_tensor(data.type[index], device=device)}


def build_model(data: StaticSet, model_hyper: dict, train_index: np.ndarray) -> GCVAE:
    """A GCVAE for the set's body mesh and condition, normalised on the samples ``train_index``."""
    positions = data.body_vertices[train_index].mean(0)
    model = GCVAE(data.mesh.edges, positions, data.mesh.segments, condition_of(data, train_index[:1]).shape[1],
                  model_hyper)
    model.fit_normalisation(data.body_vertices[train_index], data.offsets[train_index], data.mask[train_index],
                            condition_of(data, train_index))
    model.graph = {**data.mesh.arrays(), "positions": positions, "types": np.array(data.types)}
    return model


def surface_error_m(model: GCVAE, out: dict, batch: dict) -> torch.Tensor:
    """Mean per-vertex distance [m] over the true mask, per sample (B,)."""
    m = batch["mask"].float()
    d = (model.offsets_from(out["offsets"]) - batch["offsets"]).norm(dim=-1)
    return (d * m).sum(1) / m.sum(1).clamp_min(1.0)


def _split(data: StaticSet, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Training and validation samples of the train split; a dynamic set is split by sequence
    (whole sequences validate) when its train split has at least 2 of them."""
    train = data.indices("train")
    if len(train) < 2:
        raise ValueError(f"the set's train split has {len(train)} samples; need at least 2")
    groups = data.sequence[train] if is_dynamic(data) else train
    unique = np.unique(groups)
    if len(unique) < 2:
        groups, unique = train, train
    order = np.random.default_rng(seed).permutation(unique)
    n_val = min(len(unique) - 1, max(1, int(round(fraction * len(unique)))))
    val = np.isin(groups, order[:n_val])
    return np.sort(train[~val]), np.sort(train[val])


def fit_gcvae(data: StaticSet, *, run_dir: str | os.PathLike, hyperparameters: dict | None = None,
              fingerprint: DatasetFingerprint | None = None, device: str = "cpu", seed: int = 0,
              progress: bool = True) -> GCVAE:
    """Trains (or resumes) the GCVAE on the set's train split; returns the best epoch's model with
    ``best_epoch``, ``split_sizes`` (training, validation samples) and ``hyperparameters`` (every
    section, defaults merged with ``hyperparameters``)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    hyper = merged(hyperparameters)
    tr, lo = hyper["train"], hyper["loss"]
    if int(tr["batch_size"]) < 1 or int(tr["epochs"]) < 1:
        raise ValueError(f"train.batch_size and train.epochs must be >= 1, got {tr['batch_size']}, {tr['epochs']}")
    fingerprint = fingerprint if fingerprint is not None else set_fingerprint(data)
    train_index, val_index = _split(data, float(tr["validation_fraction"]), seed)
    torch.manual_seed(seed)
    model_hyper = dict(hyper["model"])
    if is_dynamic(data):
        model_hyper["channels"] = [int(c) * int(hyper["dynamic"]["channel_factor"]) for c in model_hyper["channels"]]
    model = build_model(data, model_hyper, train_index)
    model.dynamic = dict(data.layout) if is_dynamic(data) else None
    model.register_buffer("epochs_done", torch.zeros((), dtype=torch.int64))
    train_batch = tensors(data, train_index, device)
    val_batch = tensors(data, val_index, device)
    faces = torch.as_tensor(data.mesh.faces, device=device)
    dual_faces = torch.as_tensor(data.mesh.dual_faces, device=device)
    terms_path, best_path = run_dir / "gcvae_terms.csv", run_dir / BEST_FILE
    if not (run_dir / "gcvae.pt").exists() and distributed.writes_files():
        for stale in (terms_path, best_path):
            stale.unlink(missing_ok=True)
    distributed.barrier()  # no rank reads a stale file rank 0 removes
    best = [float(load_checkpoint(best_path)["validation_error_m"]) if best_path.exists() else float("inf")]
    batch_size = int(tr["batch_size"])

    def epoch_fn(model: GCVAE, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        epoch = int(model.epochs_done)
        beta = kl_weight(epoch, lo)
        order = torch.randperm(len(train_index), generator=generator).to(device)
        sums: dict[str, float] = {}
        errors = []
        for start in range(0, len(order), batch_size):
            idx = distributed.shard(order[start:start + batch_size])  # this rank's samples (all in one process)
            batch = {k: v[idx] for k, v in train_batch.items()}
            out = model(batch["body"], batch["offsets"], batch["mask"], batch["condition"])
            loss, terms = gcvae_loss(model, out, batch, faces, dual_faces, lo, beta)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            errors.append(surface_error_m(model, out, batch).detach())
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v * len(idx)
        sums = distributed.sum_over_ranks(sums)  # this rank's sums in one process
        model.eval()
        with torch.no_grad():
            val = []
            for start in range(0, len(val_index), 64):
                b = {k: v[start:start + 64] for k, v in val_batch.items()}
                val.append(surface_error_m(model, model(b["body"], b["offsets"], b["mask"], b["condition"],
                                                        sample=False), b))
            val_error = float(torch.cat(val).mean())
        model.train()
        model.epochs_done += 1
        if distributed.writes_files():
            new_file = not terms_path.exists()
            with terms_path.open("a", newline="") as fh:
                w = csv.writer(fh)
                if new_file:
                    w.writerow(["epoch"] + sorted(sums) + ["validation_error_m"])
                w.writerow([epoch + 1] + [f"{sums[k] / len(order):.6g}" for k in sorted(sums)] + [f"{val_error:.6g}"])
        if val_error < best[0]:
            best[0] = val_error
            atomic_save({"epoch": epoch + 1, "validation_error_m": val_error, "model_state": model.state_dict()},
                         best_path)
        # this rank's part of the epoch's mean error (run_epochs sums the ranks' parts)
        return float(torch.cat(errors).sum()) / len(order)

    stage_hyper = {"lr": tr["lr"], "weight_decay": tr["weight_decay"], "batch_size": batch_size, "epochs": tr["epochs"],
                   "checkpoint_interval_s": 0.0}
    model = run_epochs("gcvae", model, epoch_fn, run_dir=run_dir, hyperparameters=stage_hyper,
                       fingerprint=fingerprint, device=device, seed=seed, progress=progress)
    chosen = load_checkpoint(best_path, map_location=device)
    model.load_state_dict(chosen["model_state"])
    model.best_epoch = int(chosen["epoch"])
    model.split_sizes = (int(len(train_index)), int(len(val_index)))
    model.hyperparameters = hyper
    save_gcvae(model, run_dir / MODEL_FILE, fingerprint=fingerprint,
               extra={"best_epoch": model.best_epoch, "validation_error_m": float(chosen["validation_error_m"]),
                      "hyperparameters": hyper, "train_samples": int(len(train_index)), "dynamic": model.dynamic,
                      "validation_samples": int(len(val_index))})
    return model.eval()


def save_gcvae(model: GCVAE, path: str | os.PathLike, *, fingerprint: DatasetFingerprint | None,
               extra: dict[str, Any] | None = None) -> Path:
    """The model, its configuration, its graph and the set's fingerprint in one file."""
    graph = {k: (list(map(str, v)) if np.asarray(v).dtype.kind == "U" else torch.as_tensor(np.asarray(v)))
             for k, v in model.graph.items()}
    state = {k: v for k, v in model.state_dict().items() if k != "epochs_done"}
    path = Path(path)
    atomic_save({"learner": "gcvae", "model_config": model.config, "model_state": state, "graph": graph,
                  "condition_size": int(model.condition_mean.shape[0]),
                  "fingerprint": None if fingerprint is None else fingerprint.as_dict(), **dict(extra or {})}, path)
    return path


def body_mesh_of(model: GCVAE) -> BodyMesh:
    """The common body mesh a trained model runs on."""
    return BodyMesh.from_arrays(model.graph)


def load_gcvae(path: str | os.PathLike, *, fingerprint: DatasetFingerprint | None = None,
               require_same_manifest: bool = True, device: str = "cpu") -> GCVAE:
    """A GCVAE saved by :func:`save_gcvae`; the body mesh graph must match ``fingerprint``'s."""
    checkpoint = load_checkpoint(path, map_location="cpu")
    if checkpoint.get("learner") != "gcvae":
        raise ValueError(f"{path} holds learner {checkpoint.get('learner')!r}, expected 'gcvae'")
    check_fingerprint(checkpoint.get("fingerprint"), fingerprint, source=str(path),
                      require_same_manifest=require_same_manifest)
    graph = {k: (v.numpy() if isinstance(v, torch.Tensor) else np.array(v)) for k, v in checkpoint["graph"].items()}
    model = GCVAE(graph["body_edges"], graph["positions"], graph["body_segments"], checkpoint["condition_size"],
                  checkpoint["model_config"])
    model.load_state_dict(checkpoint["model_state"])
    model.graph = graph
    model.best_epoch = checkpoint.get("best_epoch")
    model.dynamic = checkpoint.get("dynamic")
    model.saved = {k: checkpoint[k] for k in ("best_epoch", "validation_error_m", "hyperparameters") if k in checkpoint}
    return model.to(device).eval()

