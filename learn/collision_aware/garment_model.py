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
                   initial: torch.Tensor, iterations: int = 5, edges: torch.Tensor | None = None,
                   max_edge_ratio: float = 3.0) -> torch.Tensor:
    """Canonical X with M_G(X) = ``posed``, by ``iterations`` fixed-point steps from ``initial``.

    posed, initial: [m] (B, V, 3); shape (B, S); transforms (B, J, 4, 4). Returns (B, V, 3).

    Where the diffused weights fold (the armpit: arm and torso weights blend over a few cm), LBS
    maps distant canonical points to the same posed point, and a vertex's step can land on the
    wrong one, tens of cm from its neighbours while still reproducing ``posed``. With the mesh's
    ``edges`` (E, 2) (:func:`learn.common.mesh.mesh_edges`) such a step is caught by its edges: a proposed vertex with an edge longer than
    ``max_edge_ratio`` times that edge in ``posed`` (lengths the unposing should nearly keep)
    takes its mesh neighbours' mean weights instead of its own for that step, which keeps it on
    the branch its neighbours are on.
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if edges is not None:
        reference = torch.linalg.vector_norm(posed[:, edges[:, 1]] - posed[:, edges[:, 0]], dim=-1)  # (B, E)
        degree = torch.zeros(posed.shape[1], dtype=posed.dtype, device=posed.device).index_add_(
            0, edges.reshape(-1), torch.ones(edges.numel(), dtype=posed.dtype, device=posed.device))
    x = initial
    for _ in range(iterations):
        weights = fields.skinning_weights(x)  # (B, V, J)
        offset = fields.shape_offset(x, shape)
        proposal = inverse_lbs(posed, weights, transforms) - offset
        if edges is not None:
            length = torch.linalg.vector_norm(proposal[:, edges[:, 1]] - proposal[:, edges[:, 0]], dim=-1)
            long = (length > max_edge_ratio * reference.clamp_min(1e-6)).to(posed.dtype)  # (B, E)
            strayed = torch.zeros_like(posed[..., 0]).index_add_(1, edges[:, 0], long).index_add_(1, edges[:, 1], long)
            if bool((strayed > 0).any()):
                summed = torch.zeros_like(weights).index_add_(1, edges[:, 0], weights[:, edges[:, 1]]).index_add_(
                    1, edges[:, 1], weights[:, edges[:, 0]])
                neighbours = summed / degree.clamp_min(1.0)[None, :, None]
                weights = torch.where((strayed > 0)[..., None], neighbours, weights)
                proposal = inverse_lbs(posed, weights, transforms) - offset
        x = proposal
    return x
