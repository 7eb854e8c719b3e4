"""Signed distance of the canonical body (seed 002, Eq. 12 and 16).

In the canonical space every garment sits on one constant body (default shape, pose 0), so its
signed distance field is fixed and is computed once. Two representations, both differentiable in
the point, which the canonicalization and the VAE's collision loss need:

- :class:`GridSDF` (the default, ``sdf: {kind: grid}``): the exact signed distance sampled on a
  voxel grid around the body and interpolated trilinearly. With 5 mm voxels it is within ~0.1 mm
  of the exact field near the surface (the trilinear error of a smooth field grows with the voxel
  squared over the curvature radius) and costs one texture lookup per point.
- :class:`BodySDF` (``kind: mlp``, the seed's "shallow fully-connected network"): a
  :class:`FieldMLP` regressing the distance. Trained 300 epochs on 100k points it is still off by
  1.7 mm on average within 1 cm of the surface, with the wrong sign for 11 % of such points:
  coarser than the 1-3 mm margins the collision terms keep (docs/learners/collision_aware.md).

Targets of both come from Warp's closest-point query with the collision metric's inside/outside
test (``learn.common.collision``), so "outside" means what the evaluation's collision count means.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from learn.collision_aware.body_samples import points_near_body
from learn.collision_aware.field_mlp import FieldMLP
from learn.common.collision import body_signed_distance

#: Training points closer than this to the surface [m] get ``near_weight`` in the loss: the
#: collision terms only look at the first centimetres.
NEAR_SURFACE_M = 0.03


class BodySDF(nn.Module):
    """``forward(points (..., 3) [m]) -> signed distance (...) [m]``, negative inside the body."""

    def __init__(self, *, hidden_size: int = 128, layers: int = 3, frequencies: int = 4,
                 center: list[float] = (0.0, 0.0, 0.0), scale: float = 1.0) -> None:
        super().__init__()
        self.config: dict[str, Any] = {"hidden_size": int(hidden_size), "layers": int(layers),
                                       "frequencies": int(frequencies), "center": [float(c) for c in center],
                                       "scale": float(scale)}
        self.net = FieldMLP(1, **self.config)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.net(points)[..., 0]


class GridSDF(nn.Module):
    """``forward(points (..., 3) [m]) -> signed distance (...) [m]``, trilinear in a grid of the
    exact signed distance (``values`` (Nz, Ny, Nx) [m] at ``origin + voxel_m * (i, j, k)``);
    points beyond the grid (which reaches ``margin_m`` past the body) take its border value plus
    their distance to the grid."""

    def __init__(self, *, origin: list[float], voxel_m: float, shape: list[int]) -> None:
        super().__init__()
        if not voxel_m > 0 or len(shape) != 3 or min(shape) < 2:
            raise ValueError(f"GridSDF needs voxel_m > 0 and a shape of 3 sizes >= 2, got {voxel_m}, {shape}")
        self.config: dict[str, Any] = {"kind": "grid", "origin": [float(c) for c in origin],
                                       "voxel_m": float(voxel_m), "shape": [int(n) for n in shape]}
        self.register_buffer("values", torch.zeros(1, 1, *self.config["shape"]))
        extent = torch.tensor([(n - 1) * voxel_m for n in reversed(self.config["shape"])])  # x, y, z [m]
        self.register_buffer("_origin", torch.tensor(self.config["origin"]))
        self.register_buffer("_extent", extent)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        unit = 2.0 * (points - self._origin) / self._extent - 1.0  # grid_sample's [-1, 1], x fastest
        flat = unit.reshape(1, 1, 1, -1, 3).to(self.values.dtype)
        out = torch.nn.functional.grid_sample(self.values, flat, mode="bilinear", padding_mode="border",
                                              align_corners=True).reshape(points.shape[:-1]).to(points.dtype)
        # beyond the grid: its border value plus the distance to the grid (continuous, and an upper
        # bound: those points are at least margin_m off the body, where no collision term looks)
        inside = torch.minimum(torch.maximum(points, self._origin), self._origin + self._extent)
        return out + torch.linalg.vector_norm(points - inside, dim=-1)


def grid_sdf(vertices: np.ndarray, faces: np.ndarray, *, voxel_m: float, margin_m: float = 0.05,
             warp_device: str | None = None, chunk: int = 1 << 20) -> GridSDF:
    """:class:`GridSDF` of the body (``vertices`` [m] (Vb, 3), ``faces`` (F, 3)) over its bounding
    box grown by ``margin_m`` [m], at ``voxel_m`` [m]."""
    if not voxel_m > 0 or not margin_m >= 0:
        raise ValueError(f"grid_sdf needs voxel_m > 0 and margin_m >= 0, got {voxel_m}, {margin_m}")
    low = np.asarray(vertices, np.float64).min(0) - margin_m
    high = np.asarray(vertices, np.float64).max(0) + margin_m
    counts = np.ceil((high - low) / voxel_m).astype(int) + 1  # x, y, z
    axes = [low[k] + voxel_m * np.arange(counts[k]) for k in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([x, y, z], -1).reshape(-1, 3).astype(np.float32)
    distance = np.concatenate([
        euclidean_signed_distance(points[begin:begin + chunk], vertices, faces, warp_device=warp_device,
                                  max_distance=float(np.linalg.norm(high - low)))
        for begin in range(0, points.shape[0], chunk)])
    sdf = GridSDF(origin=low.tolist(), voxel_m=voxel_m, shape=[int(counts[2]), int(counts[1]), int(counts[0])])
    sdf.values.copy_(torch.as_tensor(distance.reshape(1, 1, counts[2], counts[1], counts[0])))
    return sdf


def collision_penalty(signed_distance: torch.Tensor, epsilon: float) -> torch.Tensor:
    """Eq. 12 / 16 per point: max(epsilon - SDF, 0) [m], same shape as ``signed_distance``."""
    return torch.relu(epsilon - signed_distance)


def euclidean_signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *,
                              warp_device: str | None = None, max_distance: float | None = None) -> np.ndarray:
    """Distance [m] (N,) of ``points`` (N, 3) to their closest point on the body, negative inside
    by the collision metric's test; ``max_distance``: the query radius (default the metric's)."""
    radius = {} if max_distance is None else {"max_distance": max_distance}
    query = body_signed_distance(points, vertices, faces, device=warp_device, **radius)
    return (np.linalg.norm(points - query.closest, axis=-1) * np.sign(query.distance)).astype(np.float32)


def sdf_targets(vertices: np.ndarray, faces: np.ndarray, point_count: int, *, seed: int = 0,
                extra_points: np.ndarray | None = None, warp_device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Training points [m] (N, 3) around the body and their Euclidean signed distance [m] (N,)."""
    points = points_near_body(vertices, faces, point_count, min_offset_m=-0.05, max_offset_m=0.15, seed=seed)
    if extra_points is not None:
        points = np.concatenate([points, np.asarray(extra_points, np.float32).reshape(-1, 3)])
    return points.astype(np.float32), euclidean_signed_distance(points, vertices, faces, warp_device=warp_device)


def sdf_from_config(config: dict[str, Any]) -> nn.Module:
    """An SDF module (weights or values to be loaded) from a ``.config``."""
    if config.get("kind") == "grid":
        return GridSDF(origin=config["origin"], voxel_m=config["voxel_m"], shape=config["shape"])
    return BodySDF(**{k: v for k, v in config.items() if k != "kind"})


def load_run_sdf(run_dir: str | Path, device: str | torch.device = "cpu") -> nn.Module | None:
    """The canonical body's SDF a ``drape train collision_aware`` run saved (``RUN/sdf.pt``, its
    ``sdf.done`` written), frozen on ``device``; None when the run has none."""
    from learn.tailornet.train import load_checkpoint

    run_dir = Path(run_dir)
    if not ((run_dir / "sdf.done").is_file() and (run_dir / "sdf.pt").is_file()):
        return None
    stored = load_checkpoint(run_dir / "sdf.pt", map_location=device)
    sdf = sdf_from_config(stored["model_config"])
    sdf.load_state_dict(stored["model_state"])
    for parameter in sdf.parameters():
        parameter.requires_grad_(False)
    return sdf.to(device).eval()


def new_body_sdf(vertices: np.ndarray, *, hidden_size: int, layers: int, frequencies: int) -> BodySDF:
    """Untrained SDF scaled for the canonical body ``vertices`` [m] (Vb, 3)."""
    low, high = np.asarray(vertices).min(0), np.asarray(vertices).max(0)
    return BodySDF(hidden_size=hidden_size, layers=layers, frequencies=frequencies,
                   center=(0.5 * (low + high)).tolist(), scale=float(0.5 * (high - low).max()) + 0.2)


def fit_body_sdf(sdf: BodySDF, points: np.ndarray, distance: np.ndarray, *, run_dir: str | Path,
                 hyperparameters: dict[str, Any], fingerprint: Any = None, device: str = "cpu", seed: int = 0,
                 progress: bool = True) -> BodySDF:
    """Fit ``sdf`` (stage ``sdf``): L1 of the signed distance [m], points within
    :data:`NEAR_SURFACE_M` of the surface weighted by ``near_weight``."""
    from learn import distributed
    from learn.tailornet.train import run_epochs

    p = torch.as_tensor(points, device=device)
    d = torch.as_tensor(distance, device=device)
    weight = torch.where(d.abs() < NEAR_SURFACE_M, float(hyperparameters.get("near_weight", 4.0)), 1.0)
    batch_size = int(hyperparameters["batch_size"])

    def epoch_fn(net: BodySDF, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        order = torch.randperm(p.shape[0], generator=generator).to(device)
        total = torch.zeros((), device=device)
        for begin in range(0, p.shape[0], batch_size):
            batch = distributed.shard(order[begin:begin + batch_size])  # this rank's points (all in one process)
            loss = (weight[batch] * (net(p[batch]) - d[batch]).abs()).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * batch.numel()
        return float(total) / p.shape[0]

    return run_epochs("sdf", sdf, epoch_fn, run_dir=run_dir, hyperparameters=hyperparameters,
                      fingerprint=fingerprint, device=device, seed=seed, progress=progress)
