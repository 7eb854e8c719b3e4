"""g(shape, style): the garment displacements in the canonical pose (TailorNet Eq. 9).

g feeds the mixture kernel: two style-shapes are similar when their predicted canonical
garments are close. A shallow MLP of hidden width 128, as in the authors' code.
"""

from __future__ import annotations

import torch

from learn.tailornet.lf import DisplacementMLP


class ShapeStyleModel(DisplacementMLP):
    """g(shape, style) -> canonical-pose displacements [m], shape (B, V, 3)."""

    def __init__(
        self,
        vertex_count: int,
        *,
        shape_components: int = 2,
        style_components: int = 2,
        hidden_size: int = 128,
        dropout: float = 0.2,
        pose_indices: tuple[int, ...] = (),
    ) -> None:
        if len(pose_indices):
            raise ValueError(f"ShapeStyleModel takes no pose input, got pose_indices={pose_indices}")
        super().__init__(
            vertex_count,
            shape_components=shape_components,
            style_components=style_components,
            hidden_size=hidden_size,
            dropout=dropout,
        )

    def canonical(self, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """shape (B, S), style (B, G) -> canonical displacements [m], (B, V, 3)."""
        empty_pose = shape.new_zeros((shape.shape[0], 0))
        return self.forward(empty_pose, shape, style)
