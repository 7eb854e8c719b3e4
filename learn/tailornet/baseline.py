"""TailorNet's baseline: one MLP from (pose, shape, style) to full displacements."""

from __future__ import annotations

from collections.abc import Sequence

from learn.tailornet.lf import DisplacementMLP


def baseline_model(
    vertex_count: int,
    pose_indices: Sequence[int],
    *,
    shape_components: int = 2,
    style_components: int = 2,
    hidden_size: int = 1024,
    dropout: float = 0.2,
) -> DisplacementMLP:
    """f_BL(pose, shape, style) -> unposed displacements [m], (B, V, 3) (paper Sec. 6.2).

    Same architecture and inputs as the low-frequency model, trained on the unsmoothed
    displacements, so the mixture-vs-baseline comparison isolates the decomposition.
    """
    return DisplacementMLP(
        vertex_count,
        pose_indices=pose_indices,
        shape_components=shape_components,
        style_components=style_components,
        hidden_size=hidden_size,
        dropout=dropout,
    )
