"""Training targets of the UV-image learner, computed from what shards store.

For each frame: the body posed with the frame's (pose, shape), the embedded points and
tangent frames on it, the simulated garment (``posed_vertices`` less the body
translation when the dataset has one) as cloth-pixel offsets (du, dv, dn), and the
garment's unit vertex normals (for the normal loss). Images are not stored: they are
one sparse matmul of the offsets (:meth:`learn.uvimage.pixels.ClothPixels.to_images`)
per batch, so targets take as much memory as the shards' vertices (plus frames).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from learn.common.normals import vertex_normals


@dataclass
class ClothTargets:
    """Per-frame targets, tensors on one device.

    local: cloth-pixel offsets (N, K, 3) [m]; points: embedded points (N, V, 3) [m];
    frames: tangent frames (N, K, 3, 3); normals: true unit vertex normals (N, V, 3).
    """

    local: torch.Tensor
    points: torch.Tensor
    frames: torch.Tensor
    normals: torch.Tensor


@torch.no_grad()
def cloth_targets(learner, pose: np.ndarray, shape: np.ndarray, posed_vertices: np.ndarray, *,
                  translation: np.ndarray | None = None, device: str = "cpu", chunk: int = 64) -> ClothTargets:
    """Targets of N frames for ``learner`` (a :class:`learn.uvimage.model.UVImageLearner`
    with a body attached): pose (N, 60), shape (N, S), posed_vertices (N, V, 3) [m],
    translation (N, 3) [m] or None."""
    if posed_vertices is None:
        raise ValueError("the frames have no posed_vertices: the UV-image learner trains on the simulated posed garments")
    n = len(pose)
    if posed_vertices.shape[:2] != (n, learner.vertex_count):
        raise ValueError(f"posed_vertices must have shape ({n}, {learner.vertex_count}, 3), got {posed_vertices.shape}")
    learner = learner.to(device)
    parts: dict[str, list[torch.Tensor]] = {"local": [], "points": [], "frames": [], "normals": []}
    for start in range(0, n, chunk):
        sl = slice(start, start + chunk)
        p = torch.as_tensor(pose[sl], dtype=torch.float32, device=device)
        s = torch.as_tensor(shape[sl], dtype=torch.float32, device=device)
        x = torch.as_tensor(posed_vertices[sl], dtype=torch.float32, device=device)
        if translation is not None:
            x = x - torch.as_tensor(translation[sl], dtype=torch.float32, device=device)[:, None]
        body = learner.pose_body(p, s).vertices.to(device)
        points, frames = learner.embedding(body)
        parts["local"].append(learner.embedding.to_local(x, points, frames))
        parts["points"].append(points)
        parts["frames"].append(frames)
        parts["normals"].append(vertex_normals(x, learner.faces))
    return ClothTargets(**{k: torch.cat(v) for k, v in parts.items()})
