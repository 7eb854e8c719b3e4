"""Signed-distance MLP of the canonical body (seed 002, Eq. 12 and 16).

In the canonical space every garment sits on one constant body (default shape, pose 0), so its
signed distance field is fixed and is learned once: a shallow :class:`FieldMLP` regressing the
Euclidean distance to the body surface [m], negative inside. It is differentiable in the point,
which the canonicalization and the VAE's collision loss need. Training points follow
:func:`learn.collision_aware.body_samples.points_near_body`; targets come from Warp's closest-point
query with the collision metric's inside/outside test (``learn.common.collision``).
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


def collision_penalty(signed_distance: torch.Tensor, epsilon: float) -> torch.Tensor:
    """Eq. 12 / 16 per point: max(epsilon - SDF, 0) [m], same shape as ``signed_distance``."""
    return torch.relu(epsilon - signed_distance)


def sdf_targets(vertices: np.ndarray, faces: np.ndarray, point_count: int, *, seed: int = 0,
                extra_points: np.ndarray | None = None, warp_device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Training points [m] (N, 3) around the body and their Euclidean signed distance [m] (N,)."""
    points = points_near_body(vertices, faces, point_count, min_offset_m=-0.05, max_offset_m=0.15, seed=seed)
    if extra_points is not None:
        points = np.concatenate([points, np.asarray(extra_points, np.float32).reshape(-1, 3)])
    query = body_signed_distance(points, vertices, faces, device=warp_device)
    distance = np.linalg.norm(points - query.closest, axis=-1) * np.sign(query.distance)
    return points.astype(np.float32), distance.astype(np.float32)


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
