"""Recurrent regressor R(beta, gamma) -> garment latent for motion sequences (seed 002, Sec. 5).

Per frame the input is the motion descriptor gamma
(:mod:`learn.collision_aware.motion_descriptor`), the body shape beta and the garment style,
normalised; Gated Recurrent Units carry the sequence's history, so the garment's dynamics (lag,
swing) can follow from the motion so far; a linear layer maps the last GRU layer's state to the
latent. Nothing of the output is fed back (no teacher forcing): training and inference see the
same inputs. The GRU runs forward in time only, so the latent at frame t depends on frames <= t.

Seed 002 names GRUs but gives no sizes; the defaults (``learn.collision_aware.train``) are 2
layers of 256 units. Trained on windows of the training sequences (truncated back-propagation,
each window from a zero state) with seed Eq. 18: L1 of the latent positions plus rho_1, rho_2 times
the L1 of their per-frame first and second differences.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from learn.collision_aware.motion_descriptor import descriptor_pose_indices, descriptor_size, motion_descriptor


class RecurrentLatentRegressor(nn.Module):
    """``forward(pose (B, T, P), shape (B, T, S), style (B, T, G), time (B, T) [s], root (B, T, 3) [m]
    or None, state=None) -> (latent (B, T, L), state (layers, B, H))``.

    Args:
        pose_indices: garment-relevant pose entries (the root's are dropped: the descriptor feeds
            the root's motion through its derivatives), (P',) ints.
        shape_size, style_size: S and G.
        latent_size: L.
        fps: frame rate [1/s] of the training sequences; frames fed without times are taken
            1/fps apart.
        hidden_size, layers, dropout: the GRU's (dropout between layers).
        input_mean, input_scale: normalisation of the concatenated (gamma, shape, style), each
            (3 P'' + 12 + S + G,), P'' the entries left of ``pose_indices``.
    """

    def __init__(self, pose_indices: list[int], shape_size: int, style_size: int, latent_size: int, fps: float, *,
                 hidden_size: int = 256, layers: int = 2, dropout: float = 0.0,
                 input_mean: list[float] | None = None, input_scale: list[float] | None = None) -> None:
        super().__init__()
        theta = descriptor_pose_indices(pose_indices)
        width = descriptor_size(len(theta)) + int(shape_size) + int(style_size)
        if not float(fps) > 0:
            raise ValueError(f"recurrent regressor fps must be > 0, got {fps!r}")
        if int(layers) < 1 or int(hidden_size) < 1:
            raise ValueError(f"recurrent regressor layers and hidden_size must be >= 1, got {layers} and {hidden_size}")
        self.config: dict[str, Any] = {
            "pose_indices": [int(i) for i in pose_indices], "shape_size": int(shape_size),
            "style_size": int(style_size), "latent_size": int(latent_size), "fps": float(fps),
            "hidden_size": int(hidden_size), "layers": int(layers), "dropout": float(dropout),
            "input_mean": [0.0] * width if input_mean is None else [float(x) for x in input_mean],
            "input_scale": [1.0] * width if input_scale is None else [float(x) for x in input_scale],
        }
        if len(self.config["input_mean"]) != width or len(self.config["input_scale"]) != width:
            raise ValueError(f"input_mean and input_scale must have {width} values (descriptor + shape + style)")
        self.register_buffer("theta_indices", torch.as_tensor(theta, dtype=torch.int64))
        self.register_buffer("input_mean", torch.as_tensor(self.config["input_mean"], dtype=torch.float32))
        self.register_buffer("input_scale", torch.as_tensor(self.config["input_scale"], dtype=torch.float32))
        self.gru = nn.GRU(width, int(hidden_size), num_layers=int(layers), batch_first=True,
                          dropout=float(dropout) if int(layers) > 1 else 0.0)
        self.head = nn.Linear(int(hidden_size), int(latent_size))

    def inputs(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor, time: torch.Tensor | None = None,
               root: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised per-frame inputs (B, T, width): gamma, shape and style."""
        if shape.shape[-1] != self.config["shape_size"] or style.shape[-1] != self.config["style_size"]:
            raise ValueError(f"regressor expects shape ({self.config['shape_size']}) and style "
                             f"({self.config['style_size']}) values, got {tuple(shape.shape)} and {tuple(style.shape)}")
        if time is None:
            steps = torch.arange(pose.shape[1], dtype=pose.dtype, device=pose.device)
            time = (steps / self.config["fps"]).expand(pose.shape[0], -1)
        gamma = motion_descriptor(pose, time, root, self.theta_indices)
        return (torch.cat([gamma, shape, style], dim=-1) - self.input_mean) / self.input_scale

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor, time: torch.Tensor | None = None,
                root: torch.Tensor | None = None, state: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        hidden, state = self.gru(self.inputs(pose, shape, style, time, root), state)
        return self.head(hidden), state

    def run_inputs(self, inputs: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        """Latent (B, T, L) of already normalised inputs (B, T, width) (training windows)."""
        return self.head(self.gru(inputs, state)[0])


def input_normalisation(inputs: np.ndarray, valid: np.ndarray) -> tuple[list[float], list[float]]:
    """Mean and scale (std, floored) of un-normalised inputs (B, T, width) over valid (B, T) frames."""
    x = inputs[valid].astype(np.float64)
    return x.mean(0).tolist(), np.maximum(x.std(0), 1e-3).tolist()


def sequence_windows(lengths: list[int], window: int, stride: int) -> np.ndarray:
    """(sequence, start, length) rows (K, 3) of the training windows: every ``stride`` frames a
    window of ``window`` frames, plus one ending at the sequence's last frame; a sequence shorter
    than ``window`` is one window of its own length."""
    if window < 1 or stride < 1:
        raise ValueError(f"regressor window and stride must be >= 1, got {window} and {stride}")
    rows = []
    for s, n in enumerate(lengths):
        if n <= window:
            rows.append((s, 0, n))
            continue
        starts = list(range(0, n - window + 1, stride))
        if starts[-1] != n - window:
            starts.append(n - window)
        rows.extend((s, b, window) for b in starts)
    return np.asarray(rows, np.int64).reshape(-1, 3)


def sequence_loss(latent: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, *, velocity_weight: float,
                  acceleration_weight: float) -> dict[str, torch.Tensor]:
    """Seed Eq. 18 on windows: latent, target (B, T, L), valid (B, T) bool. Each term is the L1
    norm over the latent, averaged over the frames (or frame pairs, triples) inside the windows;
    ``loss`` = position + velocity_weight velocity + acceleration_weight acceleration."""
    def mean_l1(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        weight = mask.to(a.dtype)
        return ((a - b).abs().sum(-1) * weight).sum() / weight.sum().clamp_min(1.0)

    position = mean_l1(latent, target, valid)
    dv, dt_ = latent[:, 1:] - latent[:, :-1], target[:, 1:] - target[:, :-1]
    v_valid = valid[:, 1:] & valid[:, :-1]
    velocity = mean_l1(dv, dt_, v_valid)
    acceleration = mean_l1(dv[:, 1:] - dv[:, :-1], dt_[:, 1:] - dt_[:, :-1], v_valid[:, 1:] & v_valid[:, :-1])
    loss = position + velocity_weight * velocity + acceleration_weight * acceleration
    return {"loss": loss, "position": position, "velocity": velocity, "acceleration": acceleration}
