"""Glue from a body model to the learners' posing callables (torch, differentiable).

The learners pose garments through injected callables so that they (and their tests)
never load a body model. This module builds those callables from a
``simulate.body`` model and the garment template: the unposed body vertex under each
garment vertex (TailorNet's I T(beta)), skinning of the displaced unposed garment with
the template's skinning weights (Eq. 4), and the posed body for collision metrics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch


def garment_posing_functions(
    body_model: Any,
    body_vertex_index: np.ndarray,
    skinning_weights: np.ndarray,
    *,
    rest_vertices: np.ndarray | None = None,
) -> tuple[
    Callable[[torch.Tensor], torch.Tensor],
    Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
]:
    """(unposed_body, garment_poser, posed_body) for one garment template.

    Args:
        body_model: a ``simulate.body`` model with ``rest_torch(shape)`` and
            ``pose_torch(shape, pose)`` (returning ``.vertices`` and ``.skinning_transforms``).
        body_vertex_index: body vertex under each garment vertex, shape (V,); -1 where the
            garment vertex has no body vertex (a skirt's hem).
        skinning_weights: garment skinning weights, shape (V, J).
        rest_vertices: template rest vertices [m], shape (V, 3); the base of the vertices
            without a body vertex (TailorNet's skirt is attached to the root this way).
            Required when ``body_vertex_index`` has -1 entries.
    Returns callables: shape (B, S) -> (B, V, 3); (unposed garment (B, V, 3), pose (B, P),
    shape (B, S)) -> posed garment (B, V, 3); (pose, shape) -> posed body (B, Vb, 3).
    """
    from simulate.body.skinning import lbs

    index = torch.as_tensor(np.asarray(body_vertex_index), dtype=torch.int64)
    weights = torch.as_tensor(np.asarray(skinning_weights), dtype=torch.float32)
    if weights.ndim != 2 or weights.shape[0] != index.shape[0]:
        raise ValueError(
            f"skinning_weights must have shape ({index.shape[0]}, J) to match body_vertex_index, "
            f"got {tuple(weights.shape)}"
        )
    unattached = index < 0
    if unattached.any() and rest_vertices is None:
        raise ValueError(
            f"body_vertex_index has {int(unattached.sum())} entries of -1; pass rest_vertices "
            "(the template's) as their base"
        )
    base = None if rest_vertices is None else torch.as_tensor(np.asarray(rest_vertices), dtype=torch.float32)

    def unposed_body(shape: torch.Tensor) -> torch.Tensor:
        vertices, _ = body_model.rest_torch(shape)  # (B, Vb, 3)
        under = vertices[:, index.clamp_min(0).to(vertices.device)]  # (B, V, 3)
        if unattached.any():
            under = torch.where(unattached.to(vertices.device)[None, :, None], base.to(under), under)
        return under.to(getattr(shape, "device", under.device))  # the body model may live on another device than the learner

    def garment_poser(unposed: torch.Tensor, pose: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        transforms = body_model.pose_torch(shape, pose).skinning_transforms.to(unposed.device)  # (B, J, 4, 4)
        return lbs(unposed, weights.to(unposed.device), transforms)

    def posed_body(pose: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        vertices = body_model.pose_torch(shape, pose).vertices
        return vertices.to(getattr(pose, "device", vertices.device))

    return unposed_body, garment_poser, posed_body
