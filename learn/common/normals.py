"""Per-vertex normals of batched meshes and the normal error (1 - cosine) between two.

Seed 001 reports the normal error of predicted garments next to the vertex error
(Table 1: 1 - cos between predicted and true unit vertex normals, averaged over
vertices); the UV-image learner also trains on it (Eq. 2). The evaluation harness
reports it for every learner, so it lives here, in torch (differentiable).
"""

from __future__ import annotations

import numpy as np
import torch

#: Unit normals are taken of vectors at least this long (degenerate one-rings give 0).
NORMAL_EPS = 1e-12


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Area-weighted unit vertex normals.

    Args:
        vertices: [m], shape (B, V, 3) or (V, 3).
        faces: triangles, shape (F, 3), counter-clockwise seen from the normal's side.
    Returns:
        unit normals, same shape as ``vertices`` (zero where a vertex has no face).
    """
    single = vertices.ndim == 2
    x = vertices[None] if single else vertices
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (B, V, 3) or (V, 3), got {tuple(vertices.shape)}")
    f = torch.as_tensor(np.asarray(faces) if not isinstance(faces, torch.Tensor) else faces,
                        dtype=torch.int64, device=x.device)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {tuple(f.shape)}")
    tri = x[:, f]  # (B, F, 3, 3)
    face_n = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)  # (B, F, 3), |.| = 2 area
    n = torch.zeros_like(x)
    for k in range(3):
        n = n.index_add(1, f[:, k], face_n)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(NORMAL_EPS)
    return n[0] if single else n


def normal_error(prediction: torch.Tensor, target: torch.Tensor, faces: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Mean over vertices of 1 - n_pred . n_true per frame, shape (B,) (seed 001 Eq. 2).

    prediction, target: vertices [m], shape (B, V, 3), on the same triangles ``faces``.
    """
    if prediction.shape != target.shape or prediction.ndim != 3:
        raise ValueError(f"prediction and target must both have shape (B, V, 3), got "
                         f"{tuple(prediction.shape)} and {tuple(target.shape)}")
    return normal_error_to(vertex_normals(prediction, faces), vertex_normals(target, faces))


def normal_error_to(normals: torch.Tensor, target_normals: torch.Tensor) -> torch.Tensor:
    """Mean over vertices of 1 - cos between unit normals (B, V, 3) and (B, V, 3): shape (B,)."""
    return (1.0 - (normals * target_normals).sum(-1)).mean(-1)
