"""Training losses and error metrics on per-vertex garment displacements."""

from __future__ import annotations

import torch

METERS_TO_MM = 1000.0


def _check_pair(prediction: torch.Tensor, target: torch.Tensor) -> None:
    if prediction.shape != target.shape or prediction.ndim != 3 or prediction.shape[-1] != 3:
        raise ValueError(
            "prediction and target must both have shape (B, V, 3), got "
            f"{tuple(prediction.shape)} and {tuple(target.shape)}"
        )


def l1_displacement_loss(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """TailorNet's training loss: L1 norm of each vertex's displacement error, averaged.

    prediction, target: displacements [m], shape (B, V, 3). Returns a scalar [m]: the sum
    of absolute coordinate errors per vertex, averaged over vertices and frames.
    """
    _check_pair(prediction, target)
    return (prediction - target).abs().sum(dim=-1).mean()


def per_vertex_error_mm(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean per-vertex Euclidean error [mm] of each frame, shape (B,).

    prediction, target: vertices or displacements [m], shape (B, V, 3).
    """
    _check_pair(prediction, target)
    return torch.linalg.vector_norm(prediction - target, dim=-1).mean(dim=-1) * METERS_TO_MM
