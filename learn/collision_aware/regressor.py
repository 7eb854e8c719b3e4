"""Regressor R(pose, shape, style) -> garment latent (seed 002, Sec. 5), for quasi-static data.

Seed 002 regresses with GRUs from a motion descriptor (pose, its velocity and acceleration, root
motion) because its data are motion sequences with dynamics. The quasi-static datasets here
have one equilibrium per pose, no velocities, so the regressor is an MLP of the current pose
(the garment-relevant entries, as TailorNet's), shape and style; motion datasets get the
recurrent form (:mod:`learn.collision_aware.recurrent_regressor`). Trained with the seed's L1 on
the encoded positions.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from learn.common.mlp import MLP


class LatentRegressor(nn.Module):
    """``forward(pose (B, P), shape (B, S), style (B, G)) -> latent (B, L)``.

    Args:
        pose_indices: pose entries fed to the network, (P',) ints.
        shape_size, style_size: S and G.
        latent_size: L.
        hidden_size, dropout: of the two-hidden-layer :class:`learn.common.mlp.MLP`.
        input_mean, input_scale: normalisation of the concatenated inputs, (P' + S + G,) each.
    """

    def __init__(self, pose_indices: list[int], shape_size: int, style_size: int, latent_size: int, *,
                 hidden_size: int = 256, dropout: float = 0.0, input_mean: list[float] | None = None,
                 input_scale: list[float] | None = None) -> None:
        super().__init__()
        width = len(pose_indices) + int(shape_size) + int(style_size)
        self.config: dict[str, Any] = {
            "pose_indices": [int(i) for i in pose_indices], "shape_size": int(shape_size),
            "style_size": int(style_size), "latent_size": int(latent_size), "hidden_size": int(hidden_size),
            "dropout": float(dropout),
            "input_mean": [0.0] * width if input_mean is None else [float(x) for x in input_mean],
            "input_scale": [1.0] * width if input_scale is None else [float(x) for x in input_scale],
        }
        if len(self.config["input_mean"]) != width or len(self.config["input_scale"]) != width:
            raise ValueError(f"input_mean and input_scale must have {width} values (pose entries + shape + style)")
        self.register_buffer("pose_indices", torch.as_tensor(self.config["pose_indices"], dtype=torch.int64))
        self.register_buffer("input_mean", torch.as_tensor(self.config["input_mean"], dtype=torch.float32))
        self.register_buffer("input_scale", torch.as_tensor(self.config["input_scale"], dtype=torch.float32))
        self.mlp = MLP(width, int(latent_size), hidden_size=int(hidden_size), dropout=float(dropout))

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        if shape.shape[-1] != self.config["shape_size"] or style.shape[-1] != self.config["style_size"]:
            raise ValueError(f"regressor expects shape ({self.config['shape_size']}) and style "
                             f"({self.config['style_size']}) values, got {tuple(shape.shape)} and {tuple(style.shape)}")
        x = torch.cat([pose[:, self.pose_indices], shape, style], dim=-1)
        return self.mlp((x - self.input_mean) / self.input_scale)


def input_normalisation(pose: np.ndarray, shape: np.ndarray, style: np.ndarray,
                        pose_indices: np.ndarray) -> tuple[list[float], list[float]]:
    """Mean and scale (std, floored) of the regressor's inputs over training frames."""
    x = np.concatenate([pose[:, pose_indices], shape, style], axis=1).astype(np.float64)
    return x.mean(0).tolist(), np.maximum(x.std(0), 1e-3).tolist()
