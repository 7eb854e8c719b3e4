"""The garment model of seed 002 (Eq. 7-8) and its inverse.

A canonical garment X (unposed, deshaped) is posed for shape beta and pose theta by
T_G = X + B~s(X, beta) (+ B~p(X, theta), zero for anny: see :mod:`learn.collision_aware.fields`)
and M_G = LBS(T_G, W~(X), A(beta, theta)), with the diffused weights evaluated at X itself, so a
garment that slides over the body is skinned by the body part it is on in that frame. The skinning
transforms A come from the body model (``pose_torch(...).skinning_transforms``).

The inverse has no closed form since the weights depend on X; :func:`unpose_garment` solves it by
the fixed-point iteration X <- LBS^-1(M_G, W~(X), A) - B~s(X, beta), which converges in a few
steps where the fields are smooth (the weights change little over the distance X moves).
"""

from __future__ import annotations

import torch

from learn.collision_aware.fields import DiffusedBody
from simulate.body.kinematics import inverse_lbs, lbs


def shape_garment(fields: DiffusedBody, canonical: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
    """T_G = X + B~s(X, beta): canonical vertices [m] (B, V, 3), shape (B, S) -> [m] (B, V, 3)."""
    return canonical + fields.shape_offset(canonical, shape)


def pose_garment(fields: DiffusedBody, canonical: torch.Tensor, shape: torch.Tensor,
                 transforms: torch.Tensor, *, shaped: torch.Tensor | None = None) -> torch.Tensor:
    """M_G(X, beta, theta): canonical vertices [m] (B, V, 3), shape (B, S), skinning transforms
    (B, J, 4, 4) -> posed vertices [m] (B, V, 3). Differentiable in X and in the fields.
    ``shaped``: T_G of :func:`shape_garment` where the caller has it (one evaluation of the shape
    field instead of two)."""
    weights = fields.skinning_weights(canonical)  # (B, V, J)
    if shaped is None:
        shaped = shape_garment(fields, canonical, shape)
    return lbs(shaped, weights, transforms)


def unpose_garment(fields: DiffusedBody, posed: torch.Tensor, shape: torch.Tensor, transforms: torch.Tensor, *,
                   initial: torch.Tensor, iterations: int = 5) -> torch.Tensor:
    """Canonical X with M_G(X) = ``posed``, by ``iterations`` fixed-point steps from ``initial``.

    posed, initial: [m] (B, V, 3); shape (B, S); transforms (B, J, 4, 4). Returns (B, V, 3).
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    x = initial
    for _ in range(iterations):
        shaped = inverse_lbs(posed, fields.skinning_weights(x), transforms)  # (B, V, 3)
        x = shaped - fields.shape_offset(x, shape)
    return x
