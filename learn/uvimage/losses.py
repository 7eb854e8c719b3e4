"""Seed 001's losses (Appendix E.2): masked pixel loss (Eq. 1) and normal loss (Eq. 2).

The total loss is ``pixel + NORMAL_WEIGHT x normal`` (weight 0.01, the seed's).
"""

from __future__ import annotations

import torch

from learn.common.normals import normal_error_to

NORMAL_WEIGHT = 0.01
NORMS = ("l1", "l2")


def masked_image_loss(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, *, norm: str = "l1"
                      ) -> torch.Tensor:
    """Eq. 1: sum_ij W(i, j) |I_pd(i, j) - I_gt(i, j)| / sum_ij W(i, j), averaged over the batch.

    prediction, target: images (B, P C, H, W) [m]; mask: the padded mask W, (P, H, W)
    (1 on covered and padding pixels). ``norm`` "l1": sum of absolute channel errors of
    each panel's pixel; "l2": sum of their squares [m^2].
    """
    if norm not in NORMS:
        raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
    if prediction.shape != target.shape:
        raise ValueError(f"prediction and target images differ in shape: {tuple(prediction.shape)} vs {tuple(target.shape)}")
    b, pc, h, w = prediction.shape
    p = mask.shape[0]
    diff = (prediction - target).reshape(b, p, pc // p, h, w)
    per_pixel = diff.abs().sum(2) if norm == "l1" else diff.square().sum(2)  # (B, P, H, W)
    weights = mask.to(per_pixel.dtype)
    return (per_pixel * weights).sum((1, 2, 3)).mean() / weights.sum()


def normal_loss(normals: torch.Tensor, target_normals: torch.Tensor) -> torch.Tensor:
    """Eq. 2: mean over vertices and frames of 1 - n_pd . n_gt; unit normals (B, V, 3)."""
    return normal_error_to(normals, target_normals).mean()
