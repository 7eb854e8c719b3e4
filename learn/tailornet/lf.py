"""Displacement MLPs over (pose, shape, style), and TailorNet's low-frequency model.

Every TailorNet network maps a subset of (pose, shape, style) to per-vertex garment
displacements in the unposed space: the low-frequency model D_LF(pose, shape, style),
the per-prototype high-frequency models D_HF_k(pose), the canonical-garment model
g(shape, style) and the baseline D(pose, shape, style). :class:`DisplacementMLP` is that
network; which inputs it reads is fixed at construction and stored in its buffers, so a
checkpoint carries its own input selection.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from learn.common.mlp import MLP


class DisplacementMLP(nn.Module):
    """MLP from selected pose/shape/style features to displacements [m], (B, V, 3).

    Args:
        vertex_count: garment vertices V.
        pose_indices: which entries of the flattened axis-angle pose (B, P) are inputs
            (see :mod:`learn.tailornet.pose_mask`); empty for pose-independent models.
        shape_components: the first this many shape coefficients are inputs (0: none).
        style_components: the first this many style coefficients are inputs (0: none).
        hidden_size: hidden width (TailorNet: 1024; 128 for g).
        dropout: dropout after the first hidden layer (TailorNet: 0.2).
    """

    def __init__(
        self,
        vertex_count: int,
        *,
        pose_indices: Sequence[int] = (),
        shape_components: int = 0,
        style_components: int = 0,
        hidden_size: int = 1024,
        dropout: float = 0.2,
    ) -> None:
        super().__init__()
        if vertex_count < 1:
            raise ValueError(f"vertex_count must be >= 1, got {vertex_count}")
        if shape_components < 0 or style_components < 0:
            raise ValueError(
                "shape_components and style_components must be >= 0, got "
                f"{shape_components} and {style_components}"
            )
        pose_index = torch.as_tensor(list(pose_indices), dtype=torch.int64)
        input_size = pose_index.numel() + shape_components + style_components
        if input_size == 0:
            raise ValueError("DisplacementMLP needs at least one input feature, got none")
        self.vertex_count = int(vertex_count)
        self.shape_components = int(shape_components)
        self.style_components = int(style_components)
        self.register_buffer("pose_indices", pose_index)
        # the pose length the inputs need, kept on the host: a step replayed as a CUDA graph cannot read the buffer
        self.min_pose_size = int(pose_index.max()) + 1 if pose_index.numel() else 0
        self.mlp = MLP(input_size, 3 * vertex_count, hidden_size=hidden_size, dropout=dropout)

    @property
    def config(self) -> dict[str, Any]:
        """Constructor arguments, enough to rebuild the module before loading weights."""
        return {
            "vertex_count": self.vertex_count,
            "pose_indices": self.pose_indices.tolist(),
            "shape_components": self.shape_components,
            "style_components": self.style_components,
            "hidden_size": self.mlp.hidden_size,
            "dropout": self.mlp.dropout,
        }

    def features(
        self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor
    ) -> torch.Tensor:
        """Selected inputs, shape (B, input_size)."""
        parts = []
        if self.pose_indices.numel():
            if pose.ndim != 2 or pose.shape[1] < self.min_pose_size:
                raise ValueError(
                    f"pose must have shape (B, P) with P >= {self.min_pose_size}, "
                    f"got {tuple(pose.shape)}"
                )
            parts.append(pose[:, self.pose_indices])
        for name, value, count in (
            ("shape", shape, self.shape_components),
            ("style", style, self.style_components),
        ):
            if count:
                if value.ndim != 2 or value.shape[1] < count:
                    raise ValueError(
                        f"{name} must have shape (B, >= {count}), got {tuple(value.shape)}"
                    )
                parts.append(value[:, :count])
        return torch.cat(parts, dim=1)

    def forward(
        self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor
    ) -> torch.Tensor:
        """pose (B, P), shape (B, S), style (B, G) -> displacements [m], (B, V, 3)."""
        out = self.mlp(self.features(pose, shape, style))  # (B, 3V)
        return out.reshape(-1, self.vertex_count, 3)


def low_frequency_model(
    vertex_count: int,
    pose_indices: Sequence[int],
    *,
    shape_components: int = 2,
    style_components: int = 2,
    hidden_size: int = 1024,
    dropout: float = 0.2,
) -> DisplacementMLP:
    """TailorNet's D_LF(pose, shape, style): smooth displacements [m], (B, V, 3).

    Defaults follow the authors' code: masked pose, first two shape and first two style
    components, hidden width 1024.
    """
    return DisplacementMLP(
        vertex_count,
        pose_indices=pose_indices,
        shape_components=shape_components,
        style_components=style_components,
        hidden_size=hidden_size,
        dropout=dropout,
    )
