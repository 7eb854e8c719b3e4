"""Projection of simulated frames into the canonical space (seed 002, Sec. 4.3, Eq. 9-12).

For a simulated garment M (posed, shape beta, pose theta) the canonical X minimises

    E_rec + w_strain E_strain + w_collision E_collision

- E_rec = mean_v |M_G(X, beta, theta) - M|^2 [m^2] (Eq. 10, :mod:`learn.collision_aware.garment_model`);
- E_strain = area-weighted mean over triangles of |E|_F^2, E = 1/2 (F^T F - I) the Green-Lagrange
  strain of the deshaped garment T_G = X + B~s(X, beta) (Eq. 11). Its reference state is the
  simulated frame itself: the unposing should be as close to an isometry as it can be. A dataset
  garment has one rest state per style, so the frame is the one reference that is right for
  every style; it also makes the term zero for a perfect rigid unposing;
- E_collision = mean_v max(epsilon - SDF(X), 0)^2 [m^2] (Eq. 12 squared, so that it is measured
  in the same unit as E_rec and its gradient vanishes smoothly at the margin), SDF the canonical
  body's :class:`learn.collision_aware.sdf.BodySDF`.

Frames are solved as a batch: each step of :func:`project_sequences` takes frame t of every
sequence (shard) at once. A frame starts from the garment template (in a motion sequence, from
the previous frame's X: the seed's warm start), is brought close to E_rec = 0 by the fixed-point
unposing (:func:`learn.collision_aware.garment_model.unpose_garment`, which keeps vertices on
their neighbours' branch where the weights fold), then refined by Adam on the full objective.
:func:`projection_quality` scores every frame, so a failed one shows. :func:`project_split` caches the result per shard, keyed by the shard's sha256 and a
hash of the fields, the SDF and the settings, so a regenerated shard or retrained fields never
reuse a stale projection.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import asdict, dataclass, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learn import distributed
from learn.collision_aware.fields import DiffusedBody
from learn.collision_aware.garment_model import pose_garment, shape_garment, unpose_garment
from learn.collision_aware.sdf import BodySDF, collision_penalty
from learn.common.hyperparameters import checked_override
from learn.common.mesh import mesh_edges


@dataclass(frozen=True)
class ProjectionSettings:
    """Settings of the canonical projection.

    steps: Adam steps per frame after the fixed-point start.
    lr: Adam's initial step [m], decayed geometrically to ``lr * final_lr_fraction``. Adam moves a
        coordinate at most about ``lr`` per step, so the 60 steps move a vertex ~0.25 x 60 x lr in
        all: at 1e-2 ~15 cm, enough to undo the fixed point's error; on a full-range t-shirt set at
        7k vertices 1e-3 left a reconstruction rms median of 8.7 mm against 3.6, and 2e-2 / 3e-2
        strained the garment (p90 1.2 / 2.1 against 0.49).
    warm_lr: Adam's initial step [m] for a warm-started frame (a motion sequence's frames after
        its first, which start from the previous frame's X, millimetres from their answer). On
        procedural motion sequences of an 800-vertex t-shirt, ``lr`` (1e-2) there added 19-50 %
        to the mean second difference of X from frame to frame (0.68 -> 0.82 and 0.33 -> 0.49 mm
        at amplitudes 1 and 0.5) and raised the reconstruction rms; 1e-3 matched a projection at
        1e-3 throughout and 3e-4 did no better (docs/learners/collision_aware.md).
    strain_weight: w_strain (E_strain is dimensionless, E_rec in m^2).
    collision_weight: w_collision (both in m^2).
    epsilon_m: collision margin epsilon [m] kept between X and the canonical body.
    fixed_point_iterations: unposing iterations before the refinement. One (the default) unposes
        with the weights at the start (the template, or the previous frame under a warm start);
        further iterations re-evaluate the weights where the last one landed, and near a fold of
        the weights (the armpit) hop between its branches: on a full-range t-shirt set at 7k
        vertices, 5 iterations left the projections' strain at p90 257 against 0.45 with one, at
        the same reconstruction after the refinement (docs/learners/collision_aware.md).
    """

    steps: int = 60
    lr: float = 1.0e-2
    warm_lr: float = 1.0e-3
    final_lr_fraction: float = 0.02
    strain_weight: float = 1.0e-5
    collision_weight: float = 10.0
    epsilon_m: float = 3.0e-3
    fixed_point_iterations: int = 1

    def __post_init__(self) -> None:
        # the learners' shared rule on settings (types; steps, weights >= 0; lr, warm_lr > 0)
        for setting in dataclass_fields(self):
            value = checked_override(f"projection.{setting.name}", getattr(self, setting.name), setting.default)
            object.__setattr__(self, setting.name, value)
        if not self.final_lr_fraction > 0:
            raise ValueError(f"projection.final_lr_fraction must be > 0 (got {self.final_lr_fraction!r})")


def triangle_reference(reference: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse 2D edge matrices (B, F, 2, 2) and areas [m^2] (B, F) of the reference triangles
    (B, V, 3) [m], each expressed in an orthonormal frame of its own plane."""
    a, b, c = (reference[:, faces[:, k]] for k in range(3))  # (B, F, 3) each
    e1, e2 = b - a, c - a
    normal = torch.cross(e1, e2, dim=-1)
    area = 0.5 * torch.linalg.vector_norm(normal, dim=-1)
    u = e1 / torch.linalg.vector_norm(e1, dim=-1, keepdim=True).clamp_min(1e-12)
    v = torch.cross(normal, u, dim=-1)
    v = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(1e-12)
    dm = torch.stack([torch.stack([(e1 * u).sum(-1), (e2 * u).sum(-1)], -1),
                      torch.stack([(e1 * v).sum(-1), (e2 * v).sum(-1)], -1)], -2)  # (B, F, 2, 2)
    degenerate = area < 1e-14
    dm = torch.where(degenerate[..., None, None], torch.eye(2, dtype=dm.dtype, device=dm.device), dm)
    return torch.linalg.inv(dm), torch.where(degenerate, torch.zeros_like(area), area)


def green_lagrange_energy(vertices: torch.Tensor, faces: torch.Tensor, dm_inverse: torch.Tensor,
                          area: torch.Tensor) -> torch.Tensor:
    """Area-weighted mean of |1/2 (F^T F - I)|_F^2 per frame, (B,); vertices [m] (B, V, 3)."""
    a, b, c = (vertices[:, faces[:, k]] for k in range(3))
    ds = torch.stack([b - a, c - a], dim=-1)  # (B, F, 3, 2)
    deformation = ds @ dm_inverse  # (B, F, 3, 2)
    strain = 0.5 * (deformation.transpose(-1, -2) @ deformation - torch.eye(2, dtype=ds.dtype, device=ds.device))
    per_face = (strain ** 2).sum((-1, -2))  # (B, F)
    return (per_face * area).sum(-1) / area.sum(-1).clamp_min(1e-12)


def mesh_edges_torch(faces: torch.Tensor) -> torch.Tensor:
    """:func:`learn.common.mesh.mesh_edges` of ``faces`` (F, 3), as a tensor on their device."""
    return torch.as_tensor(mesh_edges(faces.cpu().numpy()), device=faces.device)


def unrooted_targets(frames: Any, rows: Any) -> np.ndarray:
    """The simulated garments [m] (len(rows), V, 3) of ``frames`` (a FrameArrays with
    posed_vertices) at ``rows``, without their root translation: what the projection fits."""
    target = np.asarray(frames.posed_vertices[rows], np.float32)
    if frames.translation is not None:
        target = target - np.asarray(frames.translation[rows], np.float32)[:, None, :]
    return target


def projection_terms(canonical: torch.Tensor, target: torch.Tensor, shape: torch.Tensor, transforms: torch.Tensor,
                     fields: DiffusedBody, sdf: BodySDF, faces: torch.Tensor, reference: tuple[torch.Tensor, torch.Tensor],
                     settings: ProjectionSettings) -> dict[str, torch.Tensor]:
    """Per-frame terms (B,) of the objective: ``reconstruction`` [m^2], ``strain`` (dimensionless),
    ``collision`` [m^2] and their weighted sum ``objective``."""
    shaped = shape_garment(fields, canonical, shape)
    posed = pose_garment(fields, canonical, shape, transforms, shaped=shaped)
    reconstruction = ((posed - target) ** 2).sum(-1).mean(-1)
    strain = green_lagrange_energy(shaped, faces, *reference)
    collision = (collision_penalty(sdf(canonical), settings.epsilon_m) ** 2).mean(-1)
    objective = reconstruction + settings.strain_weight * strain + settings.collision_weight * collision
    return {"reconstruction": reconstruction, "strain": strain, "collision": collision, "objective": objective}


def project_frames(target: torch.Tensor, shape: torch.Tensor, transforms: torch.Tensor, *, fields: DiffusedBody,
                   sdf: BodySDF, faces: torch.Tensor, initial: torch.Tensor,
                   settings: ProjectionSettings = ProjectionSettings(),
                   edges: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Canonical X of a batch of frames.

    target: simulated garments [m] (B, V, 3) (without any root translation); shape (B, S);
    transforms: the body's skinning transforms (B, J, 4, 4); initial: starting X [m] (B, V, 3).
    edges: the mesh's unique edges (E, 2) where the caller has them (else derived from ``faces``).
    Returns X (B, V, 3) and the terms of :func:`projection_terms` at the start (``*_start``, after
    the fixed point) and at the end, each (B,).
    """
    frozen = [p for p in (*fields.parameters(), *sdf.parameters()) if p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    try:
        with torch.no_grad():
            x0 = unpose_garment(fields, target, shape, transforms, initial=initial,
                                iterations=settings.fixed_point_iterations,
                                edges=mesh_edges_torch(faces) if edges is None else edges)
            reference = triangle_reference(target, faces)
        x = x0.clone().requires_grad_(True)
        optimizer = torch.optim.Adam([x], lr=settings.lr)
        decay = settings.final_lr_fraction ** (1.0 / max(settings.steps, 1))
        scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, decay)
        start = None
        for _ in range(settings.steps):
            terms = projection_terms(x, target, shape, transforms, fields, sdf, faces, reference, settings)
            if start is None:
                start = {k: v.detach() for k, v in terms.items()}
            optimizer.zero_grad(set_to_none=True)
            terms["objective"].sum().backward()  # frames are independent: the sum's gradient is each frame's
            optimizer.step()
            scheduler.step()
        with torch.no_grad():
            end = projection_terms(x, target, shape, transforms, fields, sdf, faces, reference, settings)
        start = start or end
    finally:
        for p in frozen:
            p.requires_grad_(True)
    info = {f"{k}_start": v for k, v in start.items()}
    info.update({k: v.detach() for k, v in end.items()})
    return x.detach(), info


def project_sequences(sequences: list[dict[str, np.ndarray]], *, body: Any, fields: DiffusedBody, sdf: BodySDF,
                      faces: np.ndarray, template: np.ndarray, settings: ProjectionSettings = ProjectionSettings(),
                      device: str = "cpu", warm_start: bool = False) -> tuple[list[np.ndarray], dict[str, float]]:
    """Canonical X of every frame of several sequences, the sequences batched together.

    sequences: each ``{"target": (F_i, V, 3) [m], "pose": (F_i, P), "shape": (S,)}``, frames in
    visiting order; template: the garment's rest vertices [m] (V, 3), the first frame's start.
    warm_start: each frame after the first starts from the previous frame's X (motion sequences,
    where consecutive frames are close) and is refined at ``settings.warm_lr``; without it every
    frame starts from the template (quasi-static shards, whose frames are unrelated poses: a
    failed frame's X would otherwise be the next frame's start).
    Returns X per sequence (F_i, V, 3) float32 and the mean terms over all frames (start and end).
    """
    if not sequences:
        return [], {}
    faces_t = torch.as_tensor(np.asarray(faces, np.int64), device=device)
    edges_t = mesh_edges_torch(faces_t)
    body_on = body.on_device(device)
    out = [np.empty_like(np.asarray(s["target"], np.float32)) for s in sequences]
    previous = torch.as_tensor(np.asarray(template, np.float32), device=device)[None].repeat(len(sequences), 1, 1)
    totals: dict[str, float] = {}
    frames_done = 0
    warm_settings = replace(settings, lr=settings.warm_lr)
    for t in range(max(len(s["target"]) for s in sequences)):
        live = [i for i, s in enumerate(sequences) if t < len(s["target"])]
        target = torch.as_tensor(np.stack([sequences[i]["target"][t] for i in live]), dtype=torch.float32, device=device)
        pose = torch.as_tensor(np.stack([sequences[i]["pose"][t] for i in live]), dtype=torch.float32, device=device)
        shape = torch.as_tensor(np.stack([sequences[i]["shape"] for i in live]), dtype=torch.float32, device=device)
        with torch.no_grad():
            transforms = body_on.pose_torch(shape, pose).skinning_transforms.to(device)
        x, info = project_frames(target, shape, transforms, fields=fields, sdf=sdf, faces=faces_t, edges=edges_t,
                                 initial=previous[live], settings=warm_settings if warm_start and t else settings)
        if warm_start:
            previous[live] = x
        for row, i in enumerate(live):
            out[i][t] = x[row].cpu().numpy()
        for key, value in info.items():
            totals[key] = totals.get(key, 0.0) + float(value.sum())
        frames_done += len(live)
    return out, {k: v / frames_done for k, v in totals.items()}


@torch.no_grad()
def projection_quality(canonical: np.ndarray, frames: Any, *, body: Any, fields: DiffusedBody, sdf: BodySDF,
                       faces: np.ndarray, settings: ProjectionSettings = ProjectionSettings(), batch_size: int = 64,
                       device: str = "cpu") -> dict[str, Any]:
    """Per-frame quality of projections ``canonical`` [m] (N, V, 3) of ``frames`` (a FrameArrays
    with posed_vertices): each frame's objective terms re-evaluated, summarised as the median, 90th
    and 99th percentiles and maximum of the reconstruction rms [mm] (how far M_G(X) lies from
    the simulated garment) and of the strain, and the frames whose reconstruction rms exceeds
    10 and 50 mm. Means alone hide a few failed frames: one frame 1 m off moves the mean
    reconstruction of a thousand by 1 mm^2 and the rms of the mean by 30 mm."""
    faces_t = torch.as_tensor(np.asarray(faces, np.int64), device=device)
    body_on = body.on_device(device)
    rms, strain = [], []
    for begin in range(0, canonical.shape[0], batch_size):
        rows = slice(begin, begin + batch_size)
        target_t = torch.as_tensor(unrooted_targets(frames, rows), device=device)
        shape = torch.as_tensor(np.asarray(frames.shape[rows], np.float32), device=device)
        pose = torch.as_tensor(np.asarray(frames.pose[rows], np.float32), device=device)
        transforms = body_on.pose_torch(shape, pose).skinning_transforms.to(device)
        terms = projection_terms(torch.as_tensor(canonical[rows], device=device), target_t, shape, transforms, fields,
                                 sdf, faces_t, triangle_reference(target_t, faces_t), settings)
        rms.append(terms["reconstruction"].sqrt().cpu().numpy() * 1e3)
        strain.append(terms["strain"].cpu().numpy())
    rms_mm, strain_all = np.concatenate(rms), np.concatenate(strain)

    def spread(values: np.ndarray) -> dict[str, float]:
        q = np.percentile(values, [50, 90, 99]) if values.size else [float("nan")] * 3
        return {"median": float(q[0]), "p90": float(q[1]), "p99": float(q[2]),
                "max": float(values.max()) if values.size else float("nan")}

    return {"frames": int(rms_mm.size), "reconstruction_rms_mm": spread(rms_mm), "strain": spread(strain_all),
            "frames_over_10mm": int((rms_mm > 10.0).sum()), "frames_over_50mm": int((rms_mm > 50.0).sum()),
            "per_frame_reconstruction_rms_mm": rms_mm}


#: Bumped when the projection's method changes, so that caches of the old method are not reused.
PROJECTION_METHOD = 3


def projection_key(fields: DiffusedBody, sdf: BodySDF, template: np.ndarray, settings: ProjectionSettings, *,
                   warm_start: bool = False) -> str:
    """sha256 of what a projection depends on besides the shard: the fields' and the SDF's
    weights, the garment template's rest vertices, the settings, the start and the method
    (``warm_lr`` only under a warm start, the one projection it enters)."""
    digest = hashlib.sha256(f"method {PROJECTION_METHOD} warm_start {bool(warm_start)}".encode())
    for module in (fields, sdf):
        buffer = io.BytesIO()
        for name, value in sorted(module.state_dict().items()):
            buffer.write(name.encode())
            buffer.write(value.detach().cpu().contiguous().numpy().tobytes())
        digest.update(buffer.getvalue())
    digest.update(np.ascontiguousarray(template, np.float32).tobytes())
    used = asdict(settings)
    if not warm_start:
        used.pop("warm_lr")
    digest.update(json.dumps(used, sort_keys=True).encode())
    return digest.hexdigest()


def _save_atomic(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as handle:
        np.save(handle, array)
    os.replace(tmp, path)


def project_split(reader: Any, split: str, frames: Any, *, body: Any, fields: DiffusedBody, sdf: BodySDF,
                  template: dict[str, np.ndarray], settings: ProjectionSettings = ProjectionSettings(),
                  cache_dir: str | Path | None = None, batch_sequences: int = 64, device: str = "cpu",
                  warm_start: bool = False, log: Any = None) -> tuple[np.ndarray, dict[str, float]]:
    """Canonical X (N, V, 3) of every frame of ``split``, in ``reader.index(split)`` order.

    frames: the split's ``FrameArrays`` (posed vertices, pose, shape, optional translation).
    Each shard (a task: one shape and style through its poses, rows in visiting order) is one
    sequence; projections are read from and written to
    ``<cache_dir or reader.root/cache/canonical>/<task>-<shard sha256[:16]>-<key[:16]>.npy``.
    Returns X and the mean projection terms of the shards computed in this call (empty when all
    came from the cache).
    """
    if frames.posed_vertices is None:
        raise ValueError(f"split {split!r} frames carry no posed_vertices; the projection needs the simulated garments")
    index = reader.index(split)  # (N, 2): shard number, row
    if index.shape[0] != frames.frame_count:
        raise ValueError(f"split {split!r} has {index.shape[0]} frames in the reader but {frames.frame_count} given")
    cache_dir = Path(cache_dir) if cache_dir is not None else Path(reader.root) / "cache" / "canonical"
    key = projection_key(fields, sdf, template["rest_vertices"], settings, warm_start=warm_start)[:16]
    out = np.empty(frames.displacements.shape, np.float32)
    pending: list[tuple[Path, np.ndarray]] = []
    for shard_no in np.unique(index[:, 0]):
        entry = reader.shard_entries[int(shard_no)]
        rows = np.flatnonzero(index[:, 0] == shard_no)
        rows = rows[np.argsort(index[rows, 1], kind="stable")]
        path = cache_dir / f"{entry['task_id']}-{entry['sha256'][:16]}-{key}.npy"
        if path.is_file():
            out[rows] = np.load(path)
        else:
            pending.append((path, rows))
    totals: dict[str, float] = {}
    done = 0
    # data-parallel training (learn.distributed): each rank projects every N-th pending shard
    parallel = distributed.active()
    mine = pending[distributed.rank()::distributed.world_size()] if parallel else pending
    for begin in range(0, len(mine), batch_sequences):
        group = mine[begin:begin + batch_sequences]
        sequences = []
        for _, rows in group:
            sequences.append({"target": unrooted_targets(frames, rows), "pose": frames.pose[rows], "shape": frames.shape[rows[0]]})
        results, info = project_sequences(sequences, body=body, fields=fields, sdf=sdf, faces=template["faces"],
                                          template=template["rest_vertices"], settings=settings, device=device,
                                          warm_start=warm_start)
        count = sum(len(rows) for _, rows in group)
        for (path, rows), x in zip(group, results):
            out[rows] = x
            _save_atomic(path, x)
        for k, v in info.items():
            totals[k] = totals.get(k, 0.0) + v * count
        done += count
        if log is not None:
            log(f"projected {begin + len(group)}/{len(mine)} shards to the canonical space")
    if parallel:  # the other ranks' shards, from the cache files they wrote
        distributed.barrier()
        for k, (path, rows) in enumerate(pending):
            if k % distributed.world_size() != distributed.rank():
                out[rows] = np.load(path)
        totals = distributed.sum_over_ranks({**totals, "frames": float(done)})
        done = int(totals.pop("frames"))
    return out, {k: v / done for k, v in totals.items()} if done else {}
