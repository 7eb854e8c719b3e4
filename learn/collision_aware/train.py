"""Training of the collision-aware learner (``drape train collision_aware``), stage by stage.

1. ``fields``: diffused skinning weights and shape offsets around the canonical body, distilled
   (:mod:`learn.collision_aware.fields`);
2. ``sdf``: the canonical body's signed-distance MLP (:mod:`learn.collision_aware.sdf`);
3. ``projection``: every training frame projected to the canonical space, cached per shard
   (:mod:`learn.collision_aware.canonicalize`); mean objective terms go to ``projection.json``;
4. ``vae``: the garment VAE with the self-supervised collision loss (:mod:`learn.collision_aware.vae`);
5. ``regressor``: (pose, shape, style) -> latent mean of each training frame: an MLP per frame
   (:mod:`learn.collision_aware.regressor`) for quasi-static datasets, a GRU over each sequence's
   motion descriptor (:mod:`learn.collision_aware.recurrent_regressor`) for motion datasets
   (``poses.source: motion``). ``regressor.kind`` (``drape train --regressor``) picks it:
   ``auto`` (the default: by the dataset), ``gru`` or ``mlp``.

Each network stage runs through ``learn.tailornet.train.run_epochs`` (resumable checkpoints,
``<stage>_loss.csv``, dataset fingerprint checks); a finished stage is loaded, not retrained.
The assembled model is saved as ``collision_aware_model.pt``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import fields as dataclass_fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learn import distributed
from learn.batches import is_streamed
from learn.collision_aware.canonicalize import (ProjectionSettings, project_sequences, project_split,
                                               projection_quality, unrooted_targets)
from learn.collision_aware.fields import (canonical_body, field_targets, fit_fields, new_diffused_body,
                                         shape_field_error)
from learn.collision_aware.model import CollisionAwareModel
from learn.collision_aware.motion_descriptor import motion_fps, padded, padded_times, sequence_rows
from learn.collision_aware.posed_collision import PosedCollision
from learn.collision_aware.recurrent_regressor import (RecurrentLatentRegressor, sequence_loss, sequence_windows)
from learn.collision_aware.recurrent_regressor import input_normalisation as sequence_normalisation
from learn.collision_aware.regressor import LatentRegressor, input_normalisation
from learn.collision_aware.sdf import fit_body_sdf, grid_sdf, new_body_sdf, sdf_from_config, sdf_targets
from learn.collision_aware.vae import LATENT_SIZE, RANDOM_LATENTS, GarmentVAE, vae_loss
from learn.common.mesh import uniform_laplacian_torch
from learn.tailornet.evaluate import sequence_root
from learn.tailornet.train import (
    DatasetFingerprint,
    FrameArrays,
    check_fingerprint,
    load_checkpoint,
    merged_hyperparameters,
    run_epochs,
    save_learner,
)

MODEL_FILE = "collision_aware_model.pt"
LEARNER = "collision_aware"
#: Stages whose ``epochs`` ``drape train --epochs`` sets.
EPOCH_STAGES = ("fields", "sdf", "vae", "regressor")

_PROJECTION_DEFAULTS = {f.name: f.default for f in dataclass_fields(ProjectionSettings)}

DEFAULT_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    # shape_basis: C > 0, the shape field is linear in C principal components of the body's shape
    # offsets over the sampled shapes (the coefficients exact, from the body model); 0, one MLP of
    # (point, shape). shapes: random shapes within the body's ranges; data_shapes: up to this many
    # of the training frames' distinct shapes added to them, drawn data_share of the time by the
    # conditioned field. shape_*: the shape network's size (the weights network has hidden_size,
    # layers, frequencies). docs/learners/collision_aware.md, "The shape field".
    "fields": {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 4096, "epochs": 300, "hidden_size": 128, "layers": 3,
               "frequencies": 4, "points": 50000, "shapes": 512, "data_shapes": 256, "data_share": 0.5, "samples": 64,
               "spread": 1.0, "shape_basis": 32, "shape_hidden_size": 256, "shape_layers": 4, "shape_frequencies": 6},
    # kind: grid (the exact signed distance on voxel_m voxels, margin_m past the body) | mlp (the
    # seed's network; the other settings are its)
    "sdf": {"kind": "grid", "voxel_m": 0.005, "margin_m": 0.05,
            "lr": 1e-3, "weight_decay": 0.0, "batch_size": 4096, "epochs": 300, "hidden_size": 128, "layers": 3,
            "frequencies": 6, "points": 100000, "near_weight": 4.0},
    "projection": {**_PROJECTION_DEFAULTS, "batch_sequences": 64},
    # the seed gives no lambda values; collision 100 and kl 1e-5 measured best of kl 1e-5..1e-3 and
    # collision 10..1000 (docs/learners/collision_aware.md, "The VAE's weights")
    "vae": {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 32, "epochs": 300, "hidden_size": 512,
            "latent_size": LATENT_SIZE, "laplacian": 1.0, "collision": 100.0, "random_collision": 1.0, "kl": 1e-5,
            "epsilon_m": 2e-3, "random_samples": 32, "random_latents": "prior", "lr_schedule": "constant",
            "lr_final": 0.01, "posed_collision": 0.0, "posed_epsilon_m": 1.0e-3},
    # kind: auto | gru | mlp. target: auto | latent (seed Eq. 18) | canonical (mlp only: L1 of the
    # decoded garment against the projection); auto is canonical for the mlp (4-8 % lower error at
    # scale, docs/learners/collision_aware.md "The defaults at scale") and latent for the gru.
    # batch_size counts frames (mlp) or windows (gru); layers, window (frames), stride (frames
    # between window starts), velocity_weight and acceleration_weight (rho_1, rho_2 of seed Eq. 18)
    # are the GRU's. sampled_poses: poses per step, drawn as the dataset's spec draws its poses,
    # that join the posed collision term with no simulated garment (self-supervised; 0: off)
    "regressor": {"kind": "auto", "lr": 1e-3, "weight_decay": 1e-6, "batch_size": 32, "epochs": 300,
                  "hidden_size": 256, "dropout": 0.0, "layers": 2, "window": 32, "stride": 16,
                  "velocity_weight": 1.0, "acceleration_weight": 1.0, "lr_schedule": "constant", "lr_final": 0.01,
                  "target": "auto", "posed_collision": 0.0, "posed_epsilon_m": 1.0e-3, "sampled_poses": 0},
    "model": {"checkpoint_interval_s": 60.0},
}


def _epoch_settings(stage: Mapping[str, Any], model: Mapping[str, Any]) -> dict[str, Any]:
    return {**dict(stage), "checkpoint_interval_s": float(model["checkpoint_interval_s"])}


def _finished(module: torch.nn.Module, run_dir: Path, stage: str, fingerprint: DatasetFingerprint | None,
              device: str) -> bool:
    """Load a stage finished in an earlier call into ``module``; False when it has to be trained."""
    if not (run_dir / f"{stage}.done").is_file() or not (run_dir / f"{stage}.pt").is_file():
        return False
    checkpoint = load_checkpoint(run_dir / f"{stage}.pt", map_location=device)
    check_fingerprint(checkpoint.get("fingerprint"), fingerprint, source=str(run_dir / f"{stage}.pt"))
    if checkpoint["model_config"] != module.config:
        raise ValueError(f"{run_dir / (stage + '.pt')} holds a {stage} configured as {checkpoint['model_config']}, "
                         f"not {module.config}: use a new run directory for a new configuration")
    module.load_state_dict(checkpoint["model_state"])
    module.to(device).eval()
    return True


def _sdf_kind(settings: Mapping[str, Any]) -> str:
    """``settings["kind"]`` (default grid), checked to be grid or mlp."""
    kind = str(settings.get("kind", "grid"))
    if kind not in ("grid", "mlp"):
        raise ValueError(f"sdf.kind must be grid or mlp, got {kind!r}")
    return kind


def _projection_settings(settings: Mapping[str, Any]) -> tuple[ProjectionSettings, int]:
    """The projection's settings and its ``batch_sequences`` (>= 1), checked before any stage."""
    hp = dict(settings)
    batch_sequences = hp.pop("batch_sequences")
    if batch_sequences < 1:  # an integer: merged_hyperparameters checked its type
        raise ValueError(f"projection.batch_sequences must be an integer >= 1 (got {batch_sequences!r})")
    return ProjectionSettings(**hp), int(batch_sequences)


def _write_fields_quality(fields: torch.nn.Module, body: Any, template: Mapping[str, Any], shapes: np.ndarray,
                          run_dir: Path, seed: int, *, log: Any = print) -> None:
    """``fields.json``: :func:`shape_field_error` on the body vertices under the garment, for the
    training data's distinct shapes (up to 16) and for 16 random shapes within the body's ranges,
    and one log line: how far off the skin a garment point on it is posed."""
    index = np.asarray(template["body_vertex_index"])
    under = np.unique(index[index >= 0])
    distinct = np.unique(np.asarray(shapes, np.float32), axis=0)
    distinct = distinct[np.random.default_rng(seed + 8).permutation(len(distinct))[:16]]
    ranges = np.asarray(body.shape_ranges, np.float64)
    random = np.random.default_rng(seed + 9).uniform(ranges[:, 0], ranges[:, 1], size=(16, len(ranges)))
    report = {"shape_field_error_on_skin_under_garment": {"data_shapes": shape_field_error(fields, body, distinct, under),
                                                          "random_shapes": shape_field_error(fields, body, random, under)}}
    (run_dir / "fields.json").write_text(json.dumps(report, indent=2))
    data_err, random_err = (report["shape_field_error_on_skin_under_garment"][k] for k in ("data_shapes", "random_shapes"))
    log(f"fields: the skin under the garment, shaped by the shape field, is off by median {data_err['median_mm']:.1f} mm, "
        f"p99 {data_err['p99_mm']:.1f} mm at the data's shapes ({random_err['median_mm']:.1f} / "
        f"{random_err['p99_mm']:.1f} mm at random shapes)")


def _regressor_target(settings: Mapping[str, Any], kind: str) -> str:
    """``settings["target"]`` (default auto) resolved for regressor ``kind``: latent, or canonical
    for the mlp regressor; auto is canonical for the mlp, latent for the gru."""
    target = str(settings.get("target", "auto"))
    if target not in ("auto", "latent", "canonical"):
        raise ValueError(f"regressor.target must be auto, latent or canonical, got {target!r}")
    if target == "auto":
        return "canonical" if kind == "mlp" else "latent"
    if target == "canonical" and kind != "mlp":
        raise ValueError(f"regressor.target 'canonical' is for the mlp regressor (quasi-static data), "
                         f"not regressor.kind {kind!r}")
    return target


def body_sdf(rest: np.ndarray, faces: np.ndarray, settings: Mapping[str, Any], *, run_dir: Path,
             fingerprint: DatasetFingerprint | None, device: str, seed: int, extra_points: np.ndarray | None = None,
             checkpoint_interval_s: float = 60.0, progress: bool = False) -> torch.nn.Module:
    """The canonical body's SDF (stage ``sdf``, frozen, on ``device``) for ``settings`` (``kind``
    grid or mlp): loaded when finished in ``run_dir``, else computed (grid) or trained (mlp).
    rest: canonical body vertices [m] (Vb, 3); faces (F, 3); extra_points [m]: the MLP's
    additional training points (the garment template)."""
    kind = _sdf_kind(settings)
    if kind == "grid":
        checkpoint = run_dir / "sdf.pt"
        if (run_dir / "sdf.done").is_file() and checkpoint.is_file():
            stored = load_checkpoint(checkpoint, map_location=device)
            check_fingerprint(stored.get("fingerprint"), fingerprint, source=str(checkpoint))
            config = stored["model_config"]
            if config.get("kind") != "grid" or config["voxel_m"] != float(settings["voxel_m"]):
                described = f"a grid at {config['voxel_m']} m" if config.get("kind") == "grid" else "an MLP"
                raise ValueError(f"{checkpoint} holds {described}, not a grid at {settings['voxel_m']} m: "
                                 f"use a new run directory for a new configuration")
            sdf = sdf_from_config(stored["model_config"])
            sdf.load_state_dict(stored["model_state"])
        else:
            sdf = grid_sdf(rest, faces, voxel_m=float(settings["voxel_m"]), margin_m=float(settings["margin_m"]),
                           warp_device=device if str(device).startswith("cuda") else "cpu")
            if distributed.writes_files():
                save_learner(sdf, "sdf", checkpoint, fingerprint=fingerprint)
                (run_dir / "sdf.done").write_text(json.dumps({"stage": "sdf", "kind": "grid"}))
        return _frozen(sdf.to(device))
    torch.manual_seed(seed)
    sdf = new_body_sdf(rest, hidden_size=int(settings["hidden_size"]), layers=int(settings["layers"]),
                       frequencies=int(settings["frequencies"]))
    if not _finished(sdf, run_dir, "sdf", fingerprint, device):
        points, distance = sdf_targets(rest, faces, int(settings["points"]), seed=seed, extra_points=extra_points)
        mlp_settings = {k: v for k, v in settings.items() if k not in ("kind", "voxel_m", "margin_m")}
        sdf = fit_body_sdf(sdf, points, distance, run_dir=run_dir, fingerprint=fingerprint, device=device, seed=seed,
                           progress=progress, hyperparameters={**mlp_settings, "checkpoint_interval_s": checkpoint_interval_s})
    return _frozen(sdf.to(device))


def _frozen(module: torch.nn.Module) -> torch.nn.Module:
    for p in module.parameters():
        p.requires_grad_(False)
    return module.eval()


def train_vae(canonical: np.ndarray, faces: np.ndarray, sdf: Any, *, run_dir: str | Path,
              hyperparameters: Mapping[str, Any], fingerprint: DatasetFingerprint | None = None, device: str = "cpu",
              seed: int = 0, progress: bool = True, checkpoint_interval_s: float = 60.0,
              posed: PosedCollision | None = None, pose: np.ndarray | None = None,
              shape: np.ndarray | None = None) -> GarmentVAE:
    """Fit the garment VAE (stage ``vae``) to canonical garments [m] (N, V, 3) on ``faces``;
    ``sdf``: points (..., 3) -> signed distance of the canonical body [m] (frozen). With
    ``hyperparameters["posed_collision"]`` = w > 0, w times the posed-space collision hinge [m]
    of each reconstruction, posed by ``posed`` with its frame's ``pose`` (N, P) and ``shape``
    (N, S), joins the loss: the decoder learns garments that stay clear of the body where its
    parts touch, which no canonical-space term sees."""
    hyper = dict(hyperparameters)
    x = torch.as_tensor(np.asarray(canonical, np.float32), device=device)
    if x.ndim != 3 or x.shape[0] == 0:
        raise ValueError(f"canonical garments must have shape (N, V, 3) with N >= 1, got {tuple(x.shape)}")
    posed_weight = float(hyper.get("posed_collision", 0.0))
    if posed_weight > 0:
        if posed is None or pose is None or shape is None:
            raise ValueError("vae.posed_collision poses the reconstructions: it needs a PosedCollision and the "
                             "frames' poses and shapes")
        pose_t, shape_t = (torch.as_tensor(np.asarray(a, np.float32), device=device) for a in (pose, shape))
        if pose_t.shape[0] != x.shape[0] or shape_t.shape[0] != x.shape[0]:
            raise ValueError(f"pose and shape need one row per canonical garment ({x.shape[0]}), "
                             f"got {pose_t.shape[0]} and {shape_t.shape[0]}")
    mean = x.mean(0)
    scale = float((x - mean).std()) or 1e-3
    torch.manual_seed(seed)
    vae = GarmentVAE(x.shape[1], mean.cpu().numpy(), max(scale, 1e-3), latent_size=int(hyper["latent_size"]),
                     hidden_size=int(hyper["hidden_size"]))
    laplacian = uniform_laplacian_torch(faces, x.shape[1], boundary_aware=False, device=device)
    weights = {k: float(hyper[k]) for k in ("laplacian", "collision", "random_collision", "kl")}
    weights["posed_collision"] = posed_weight
    batch_size = int(hyper["batch_size"])
    log_rows: list[dict[str, float]] = []

    def epoch_fn(net: GarmentVAE, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        order = torch.randperm(x.shape[0], generator=generator).to(device)
        sums: dict[str, torch.Tensor] = {}  # on the device: one read per epoch, not a sync per step
        for begin in range(0, x.shape[0], batch_size):
            batch = distributed.shard(order[begin:begin + batch_size])  # this rank's frames (all in one process)
            posed_term = None if posed_weight <= 0 else (
                lambda garment, rows=batch: posed(garment, pose_t[rows], shape_t[rows]))
            terms = vae_loss(net, x[batch], laplacian=laplacian, sdf=sdf, weights=weights,
                             epsilon_m=float(hyper["epsilon_m"]), random_samples=int(hyper["random_samples"]),
                             latents=str(hyper["random_latents"]), posed=posed_term)
            optimizer.zero_grad(set_to_none=True)
            terms["loss"].backward()
            optimizer.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + v.detach() * batch.numel()
        mine = {k: float(v) / x.shape[0] for k, v in sums.items()}  # this rank's part of the epoch means (all in one process)
        log_rows.append(distributed.sum_over_ranks(mine))
        return mine["reconstruction"]  # run_epochs sums the ranks' parts

    vae = run_epochs("vae", vae, epoch_fn, run_dir=run_dir,
                     hyperparameters={**hyper, "checkpoint_interval_s": checkpoint_interval_s},
                     fingerprint=fingerprint, device=device, seed=seed, progress=progress)
    if log_rows and distributed.writes_files():
        (Path(run_dir) / "vae_terms.json").write_text(json.dumps(log_rows[-1], indent=2))
    return vae


def train_regressor(data: FrameArrays, latent: np.ndarray, pose_indices: np.ndarray, *, run_dir: str | Path,
                    hyperparameters: Mapping[str, Any], fingerprint: DatasetFingerprint | None = None,
                    device: str = "cpu", seed: int = 0, progress: bool = True,
                    checkpoint_interval_s: float = 60.0, vae: GarmentVAE | None = None,
                    canonical: np.ndarray | None = None, posed: PosedCollision | None = None,
                    sampled_pose: np.ndarray | None = None) -> LatentRegressor:
    """Fit R(pose, shape, style) -> latent (N, L) (stage ``regressor``). ``target: latent``: L1
    against the encoded frames ``latent`` (seed Eq. 18's position term); ``target: canonical``:
    L1 per vertex [m] of the frozen ``vae``'s decoding against the projected frames ``canonical``
    (N, V, 3), so the latent dimensions count by what they change in the garment. With ``posed``
    and ``hyperparameters["posed_collision"]`` = w > 0, w times the posed-space collision hinge
    [m] of the decoded garment (:class:`PosedCollision`) is added. With ``hyperparameters
    ["sampled_poses"]`` = S > 0 the hinge also covers S poses per step drawn from ``sampled_pose``
    (M, P), each with the shape and style of a random training frame: poses no simulated frame
    has, where the regressor must still choose a garment clear of the body (self-supervised: the
    seed's sampling of the inputs, in the posed space)."""
    hyper = dict(hyperparameters)
    decoded = _regressor_target(hyper, "mlp") == "canonical"
    if decoded and (vae is None or canonical is None):
        raise ValueError(f"regressor.target {hyper.get('target', 'auto')!r} trains against the decoded garment: "
                         "it needs the VAE and the projected frames")
    collision_weight = float(hyper.get("posed_collision", 0.0))
    if collision_weight > 0 and (posed is None or vae is None):
        raise ValueError("regressor.posed_collision poses the decoded garment: it needs the VAE and a PosedCollision")
    sampled_count = int(hyper.get("sampled_poses", 0))
    if sampled_count > 0 and (collision_weight <= 0 or sampled_pose is None or len(sampled_pose) == 0):
        raise ValueError("regressor.sampled_poses adds sampled poses to the posed collision term: it needs "
                         "regressor.posed_collision > 0 and the sampled poses")
    mean, scale = input_normalisation(data.pose, data.shape, data.style, pose_indices)
    torch.manual_seed(seed)
    regressor = LatentRegressor(np.asarray(pose_indices).tolist(), data.shape.shape[1], data.style.shape[1],
                                latent.shape[1], hidden_size=int(hyper["hidden_size"]), dropout=float(hyper["dropout"]),
                                input_mean=mean, input_scale=scale)
    pose, shape, style = (torch.as_tensor(a, dtype=torch.float32, device=device) for a in (data.pose, data.shape, data.style))
    target = torch.as_tensor(canonical if decoded else latent, dtype=torch.float32, device=device)
    batch_size = int(hyper["batch_size"])
    bank = None if sampled_count <= 0 else torch.as_tensor(sampled_pose, dtype=torch.float32, device=device)

    def sampled_term(net: LatentRegressor, generator: torch.Generator) -> torch.Tensor:
        # S poses of the bank, each with a random training frame's shape and style (drawn on every
        # rank from the shared generator, then dealt out like the frames)
        poses = bank[distributed.shard(torch.randint(bank.shape[0], (sampled_count,), generator=generator).to(device))]
        frames = distributed.shard(torch.randint(pose.shape[0], (sampled_count,), generator=generator).to(device))
        garment = vae.decode(net(poses, shape[frames], style[frames]))
        return collision_weight * posed(garment, poses, shape[frames])

    def error(predicted: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
        garment = vae.decode(predicted) if decoded or collision_weight > 0 else None
        if decoded:
            loss = (garment - target[batch]).abs().sum(-1).mean()
        else:
            loss = (predicted - target[batch]).abs().sum(-1).mean()
        if collision_weight > 0:
            loss = loss + collision_weight * posed(garment, pose[batch], shape[batch])
        return loss

    def epoch_fn(net: LatentRegressor, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        order = torch.randperm(target.shape[0], generator=generator).to(device)
        total = torch.zeros((), device=device)
        for begin in range(0, target.shape[0], batch_size):
            batch = distributed.shard(order[begin:begin + batch_size])  # this rank's frames (all in one process)
            loss = error(net(pose[batch], shape[batch], style[batch]), batch)
            if bank is not None:
                loss = loss + sampled_term(net, generator)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * batch.numel()
        return float(total) / target.shape[0]

    # latent target: L1 summed over the latent's dimensions (no unit); decoded: per-vertex L1 [m]
    return run_epochs("regressor", regressor, epoch_fn, run_dir=run_dir,
                      hyperparameters={**hyper, "checkpoint_interval_s": checkpoint_interval_s},
                      fingerprint=fingerprint, device=device, seed=seed, progress=progress,
                      loss_name=("loss_m" if decoded else "loss") if collision_weight > 0 else
                      ("l1_m" if decoded else "l1_latent"))


def train_recurrent_regressor(data: FrameArrays, latent: np.ndarray, pose_indices: np.ndarray, fps: float, *,
                              run_dir: str | Path, hyperparameters: Mapping[str, Any],
                              fingerprint: DatasetFingerprint | None = None, device: str = "cpu", seed: int = 0,
                              progress: bool = True, checkpoint_interval_s: float = 60.0) -> RecurrentLatentRegressor:
    """Fit the GRU R(beta, gamma) -> latent (N, L) (stage ``regressor``) on windows of the
    training sequences (``data.sequence``, ``data.frame_index``; frames ``1/fps`` [s] apart per
    index step) with seed Eq. 18. Each window starts from a zero state and sees only the
    descriptor, shape and style (no latent fed back); the descriptor of its first frames uses
    the frames before the window, as a sequence run from its start does."""
    hyper = dict(hyperparameters)
    if data.sequence is None or data.frame_index is None:
        raise ValueError("the recurrent regressor needs each training frame's sequence and frame_index "
                         "(FrameArrays.sequence, .frame_index)")
    rows = sequence_rows(data.sequence, data.frame_index)
    root = sequence_root(data)
    torch.manual_seed(seed)
    regressor = RecurrentLatentRegressor(np.asarray(pose_indices).tolist(), data.shape.shape[1], data.style.shape[1],
                                         latent.shape[1], fps, hidden_size=int(hyper["hidden_size"]),
                                         layers=int(hyper["layers"]), dropout=float(hyper["dropout"]))

    def gathered(values: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(padded(rows, np.asarray(values, np.float32)))

    lengths = [len(r) for r in rows]
    valid = np.arange(max(lengths))[None, :] < np.asarray(lengths)[:, None]  # (Q, T)
    with torch.no_grad():  # un-normalised inputs, for the normalisation
        raw = regressor.inputs(gathered(data.pose), gathered(data.shape), gathered(data.style),
                               torch.as_tensor(padded_times(rows, data.frame_index, fps)),
                               None if root is None else gathered(root)).numpy()
    mean, scale = sequence_normalisation(raw, valid)
    regressor = RecurrentLatentRegressor(np.asarray(pose_indices).tolist(), data.shape.shape[1], data.style.shape[1],
                                         latent.shape[1], fps, hidden_size=int(hyper["hidden_size"]),
                                         layers=int(hyper["layers"]), dropout=float(hyper["dropout"]),
                                         input_mean=mean, input_scale=scale)
    inputs = torch.as_tensor((raw - np.asarray(mean, np.float32)) / np.asarray(scale, np.float32), device=device)
    target = gathered(latent).to(device)
    windows = sequence_windows(lengths, int(hyper["window"]), int(hyper["stride"]))
    width = int(windows[:, 2].max())
    offsets = np.arange(width)[None, :]
    frame = np.minimum(windows[:, 1:2] + offsets, inputs.shape[1] - 1)  # (K, W), clipped past the end
    inside = torch.as_tensor(offsets < windows[:, 2:3], device=device)  # (K, W)
    seq_t, frame_t = torch.as_tensor(windows[:, :1], device=device), torch.as_tensor(frame, device=device)
    batch_size = int(hyper["batch_size"])
    weights = {"velocity_weight": float(hyper["velocity_weight"]), "acceleration_weight": float(hyper["acceleration_weight"])}
    count = windows.shape[0]

    def epoch_fn(net: RecurrentLatentRegressor, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        order = torch.randperm(count, generator=generator).to(device)
        total = torch.zeros((), device=device)
        for begin in range(0, count, batch_size):
            batch = distributed.shard(order[begin:begin + batch_size])  # this rank's windows (all in one process)
            where = (seq_t[batch], frame_t[batch])  # the batch's windows, gathered from the sequences: (b, W)
            terms = sequence_loss(net.run_inputs(inputs[where]), target[where], inside[batch], **weights)
            optimizer.zero_grad(set_to_none=True)
            terms["loss"].backward()
            optimizer.step()
            total += terms["loss"].detach() * batch.numel()
        return float(total) / count

    return run_epochs("regressor", regressor, epoch_fn, run_dir=run_dir,
                      hyperparameters={**hyper, "checkpoint_interval_s": checkpoint_interval_s},
                      fingerprint=fingerprint, device=device, seed=seed, progress=progress,
                      loss_name="loss")  # the seed's sequence loss (latent L1 and collision terms)


REGRESSOR_KINDS = ("auto", "gru", "mlp")


def regressor_kind(requested: str, fps: float | None) -> str:
    """``gru`` or ``mlp``: ``requested`` (``regressor.kind``, ``drape train --regressor``) resolved
    against the dataset, whose frame rate ``fps`` is None when it is quasi-static."""
    if requested not in REGRESSOR_KINDS:
        raise ValueError(f"--regressor (regressor.kind) must be one of {', '.join(REGRESSOR_KINDS)}, got {requested!r}")
    if requested == "auto":
        return "mlp" if fps is None else "gru"
    if requested == "gru" and fps is None:
        raise ValueError("--regressor gru (regressor.kind: gru) needs a motion dataset (spec poses.source: motion, "
                         "frames in sequences at motion.fps); this dataset is quasi-static: use --regressor mlp or auto")
    return requested


#: Poses drawn once for ``regressor.sampled_poses``; each step takes its poses from them.
POSE_BANK = 4096


def spec_poses(spec: Mapping[str, Any], body: Any, count: int, seed: int) -> np.ndarray:
    """``count`` poses (count, P) drawn as the dataset's spec draws its sampled poses (its joints,
    range and pruning, on the body's default shape; ``simulate.poses.spec_pose_sampling``), from a
    seed of their own: the same distribution as the dataset's train and test poses, not the same
    poses."""
    from simulate.poses import sample_poses, spec_pose_sampling

    sampler, pruning = spec_pose_sampling(spec["poses"], spec["garment"]["type"], body)
    return sample_poses(body, body.shape_default, count, sampler, np.random.default_rng(seed), **pruning)[0]


def collision_aware_context(*, body: Any, body_spec: Mapping[str, Any], template: Mapping[str, np.ndarray],
                            dataset: Any, reader: Any = None, **_: Any) -> dict:
    """Extra ``fit`` arguments of :func:`fit_collision_aware` for ``drape train`` (see
    :mod:`learn.registry`): the body model, its ``{"backend", "path"}``, the shards'
    template arrays, the training split's ``DrapeDataset``, the dataset's frame rate (``motion_fps``:
    None unless its spec has ``poses.source: motion``) and its spec (``dataset_spec``), as the command
    has them."""
    spec = reader.manifest.spec if reader is not None else None
    return {"body": body, "body_spec": body_spec, "template": template, "dataset": dataset,
            "motion_fps": motion_fps(spec), "dataset_spec": spec}


def fit_collision_aware(
    data: FrameArrays,
    faces: np.ndarray,
    *,
    run_dir: str | Path,
    pose_indices: np.ndarray | None = None,
    canonical_pose: np.ndarray | None = None,
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
    body: Any = None,
    body_spec: Mapping[str, Any] | None = None,
    template: Mapping[str, np.ndarray] | None = None,
    dataset: Any = None,
    motion_fps: float | None = None,
    dataset_spec: Mapping[str, Any] | None = None,
    log: Any = print,
) -> CollisionAwareModel:
    """Train every stage on ``data`` (training frames with ``posed_vertices``) and save the model.

    body: the dataset's body model (``simulate.body``); body_spec: its ``{"backend", "path"}`` for
    loading the saved model (default: the body's backend, no path). template: the dataset's
    garment template (faces, rest_vertices, skinning_weights, body_vertex_index). dataset: a
    ``learn.data.DrapeDataset`` of ``data``'s split; with it frames are grouped into their shards
    (sequences) and projections are cached per shard sha256, without it frames are grouped by
    style-shape pair and not cached. motion_fps: the frame rate [1/s] of a motion dataset (its
    frames in sequences, ``data.sequence`` and ``data.frame_index`` set), None for a
    quasi-static one; with ``regressor.kind`` it picks the regressor (:func:`regressor_kind`).
    dataset_spec: the dataset's spec, whose ``poses`` and ``garment.type`` say how the poses of
    ``regressor.sampled_poses`` are drawn (needed only then).
    ``canonical_pose`` is unused: the canonical space is the body model's pose 0 and default shape.
    """
    del canonical_pose
    if is_streamed(data):
        raise ValueError("fit_collision_aware trains from frames in memory (a FrameArrays), not a streamed split: "
                         "the VAE trains on the canonical projections of every frame together")
    if body is None or template is None:
        raise ValueError("fit_collision_aware needs body= (the dataset's body model) and template= "
                         "(the dataset's garment template)")
    if data.posed_vertices is None:
        raise ValueError("fit_collision_aware needs data.posed_vertices: the canonical projection fits the simulated garments")
    hyper = merged_hyperparameters(hyperparameters, DEFAULT_HYPERPARAMETERS)
    kind = regressor_kind(str(hyper["regressor"]["kind"]), motion_fps)  # before any stage: a wrong kind costs nothing
    hyper["regressor"]["kind"] = kind
    _sdf_kind(hyper["sdf"])  # also before any stage
    if not 0.0 <= float(hyper["fields"]["data_share"]) <= 1.0:
        raise ValueError(f"fields.data_share must be in [0, 1] (got {hyper['fields']['data_share']})")
    if not 0 <= int(hyper["fields"]["shape_basis"]) <= int(hyper["fields"]["shapes"]):
        raise ValueError(f"fields.shape_basis must be in [0, fields.shapes = {hyper['fields']['shapes']}] (0: the "
                         f"conditioned field; a basis comes from the sampled shapes), got {hyper['fields']['shape_basis']}")
    if hyper["vae"]["random_latents"] not in RANDOM_LATENTS:
        raise ValueError(f"vae.random_latents must be one of {', '.join(RANDOM_LATENTS)}, "
                         f"got {hyper['vae']['random_latents']!r}")
    hyper["regressor"]["target"] = _regressor_target(hyper["regressor"], kind)  # saved with the model as resolved
    if float(hyper["regressor"]["posed_collision"]) > 0 and kind == "gru":
        raise ValueError("regressor.posed_collision is for the mlp regressor (quasi-static data); the gru's "
                         "sequences train without it")
    sampled = int(hyper["regressor"]["sampled_poses"])  # an integer >= 0: merged_hyperparameters checks it
    if sampled and float(hyper["regressor"]["posed_collision"]) <= 0:
        raise ValueError(f"regressor.sampled_poses = {sampled} adds poses to the posed collision term, which is off: "
                         "set regressor.posed_collision > 0")
    if sampled and (dataset_spec is None or dataset_spec.get("poses", {}).get("source") != "sampled"):
        raise ValueError(f"regressor.sampled_poses = {sampled} draws poses as the dataset's spec draws them: it needs a "
                         "dataset whose spec samples its poses (poses.source: sampled)")
    settings, batch_sequences = _projection_settings(hyper["projection"])
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if pose_indices is None:
        pose_indices = np.arange(data.pose.shape[1])
    interval = float(hyper["model"]["checkpoint_interval_s"])
    common = dict(run_dir=run_dir, fingerprint=fingerprint, device=device, progress=progress)
    template = dict(template)
    rest = canonical_body(body)

    hf = hyper["fields"]
    torch.manual_seed(seed)
    fields = new_diffused_body(body, hidden_size=int(hf["hidden_size"]), layers=int(hf["layers"]),
                               frequencies=int(hf["frequencies"]), shape_basis=int(hf["shape_basis"]),
                               shape_hidden_size=int(hf["shape_hidden_size"]), shape_layers=int(hf["shape_layers"]),
                               shape_frequencies=int(hf["shape_frequencies"]))
    data_shapes = np.unique(np.asarray(data.shape, np.float32), axis=0)
    if len(data_shapes) > int(hf["data_shapes"]):  # a seeded choice where the data have more
        data_shapes = data_shapes[np.sort(np.random.default_rng(seed + 7).choice(
            len(data_shapes), int(hf["data_shapes"]), replace=False))]
    elif int(hf["data_shapes"]) == 0:
        data_shapes = data_shapes[:0]
    if not _finished(fields, run_dir, "fields", fingerprint, device):
        targets = field_targets(body, point_count=int(hf["points"]), shape_count=int(hf["shapes"]),
                                samples=int(hf["samples"]), spread=float(hf["spread"]),
                                extra_points=template["rest_vertices"], extra_shapes=data_shapes,
                                basis=int(hf["shape_basis"]), seed=seed)
        fields = fit_fields(fields, targets, hyperparameters=_epoch_settings(hf, hyper["model"]), seed=seed, **common)
    fields = _frozen(fields.to(device))
    if distributed.writes_files():
        _write_fields_quality(fields, body, template, data.shape, run_dir, seed, log=log)

    hs = hyper["sdf"]
    sdf = body_sdf(rest, body.faces, hs, run_dir=run_dir, fingerprint=fingerprint, device=device, seed=seed + 1,
                   extra_points=template["rest_vertices"], checkpoint_interval_s=interval, progress=progress)

    if dataset is not None:
        canonical, info = project_split(dataset.reader, dataset.split, data, body=body, fields=fields, sdf=sdf,
                                        template=template, settings=settings, batch_sequences=batch_sequences,
                                        device=device, warm_start=motion_fps is not None,
                                        log=log if progress else None)
    else:
        groups = [np.flatnonzero(data.pair_id == p) for p in np.unique(data.pair_id)]
        sequences = [{"target": unrooted_targets(data, g),
                      "pose": data.pose[g], "shape": data.shape[g[0]]} for g in groups]
        results, info = project_sequences(sequences, body=body, fields=fields, sdf=sdf, faces=template["faces"],
                                          template=template["rest_vertices"], settings=settings, device=device,
                                          warm_start=motion_fps is not None)
        canonical = np.empty(data.displacements.shape, np.float32)
        for g, x in zip(groups, results):
            canonical[g] = x
    if distributed.writes_files():
        quality = projection_quality(canonical, data, body=body, fields=fields, sdf=sdf, faces=template["faces"],
                                     settings=settings, device=device)
        quality.pop("per_frame_reconstruction_rms_mm")
        rms = quality["reconstruction_rms_mm"]
        log(f"projection: reconstruction rms median {rms['median']:.1f} mm, p90 {rms['p90']:.1f} mm, "
            f"max {rms['max']:.1f} mm; {quality['frames_over_50mm']} of {quality['frames']} frames over 50 mm")
        (run_dir / "projection.json").write_text(json.dumps({**info, "quality": quality}, indent=2))

    def posed_term(stage: str) -> PosedCollision | None:
        # the posed-space collision term of a stage whose posed_collision weight is on
        settings = hyper[stage]
        if float(settings["posed_collision"]) <= 0:
            return None
        return PosedCollision(body, fields, epsilon_m=float(settings["posed_epsilon_m"]), device=device)

    vae = train_vae(canonical, faces, sdf, hyperparameters=hyper["vae"], seed=seed + 2, checkpoint_interval_s=interval,
                    posed=posed_term("vae"), pose=data.pose, shape=data.shape, **common)
    vae = _frozen(vae)
    with torch.no_grad():
        latent = torch.cat([vae.encode(torch.as_tensor(canonical[i:i + 256], device=device))[0]
                            for i in range(0, canonical.shape[0], 256)]).cpu().numpy()
    if kind == "gru":
        regressor = train_recurrent_regressor(data, latent, pose_indices, float(motion_fps),
                                              hyperparameters=hyper["regressor"], seed=seed + 3,
                                              checkpoint_interval_s=interval, **common)
    else:
        regressor = train_regressor(data, latent, pose_indices, hyperparameters=hyper["regressor"], seed=seed + 3,
                                    checkpoint_interval_s=interval, vae=vae, canonical=canonical,
                                    posed=posed_term("regressor"),
                                    sampled_pose=spec_poses(dataset_spec, body, POSE_BANK, seed + 11) if sampled else None,
                                    **common)
    spec = dict(body_spec) if body_spec is not None else {"backend": getattr(body, "name", "anny"), "path": None}
    model = CollisionAwareModel(regressor, vae, fields, template, spec, body=body).to(device).eval()
    save_learner(model, LEARNER, run_dir / MODEL_FILE, fingerprint=fingerprint, extra={"hyperparameters": hyper})
    return model


def load_collision_aware(path: str | Path, *, fingerprint: DatasetFingerprint | None = None,
                         require_same_manifest: bool = True, device: str = "cpu", body: Any = None) -> CollisionAwareModel:
    """Load a model saved by :func:`fit_collision_aware`, checking the dataset fingerprint; the
    body model named in its configuration is loaded on first use unless ``body`` is given."""
    checkpoint = load_checkpoint(path, map_location=device)
    check_fingerprint(checkpoint.get("fingerprint"), fingerprint, source=str(path),
                      require_same_manifest=require_same_manifest)
    if checkpoint.get("learner") != LEARNER:
        raise ValueError(f"{path} holds learner '{checkpoint.get('learner')}', expected '{LEARNER}'")
    model = CollisionAwareModel.from_config(checkpoint["model_config"], body=body)
    model.load_state_dict(checkpoint["model_state"])
    return model.to(device).eval()
