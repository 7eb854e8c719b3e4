"""Garment-body signed distances and the collision-rate metric, with Warp mesh queries.

A garment vertex collides when its signed distance along the normal of the nearest body
face is below -1 mm (the HOOD-style metric REFERENCE.md names), i.e. it lies more than
1 mm inside the body. One kernel launch answers every (frame, vertex) query: each frame
has its own body ``wp.Mesh`` (the body is posed differently per frame) and the kernel
picks the mesh of its frame from an array of mesh ids. Runs on CPU and CUDA.

The query is the dataset's penetration filter's (``simulate.quality.query_body_signed_distance``),
so the learners' collision rate counts what the filter counts, in the unit published rates use:
the distance along the nearest face's normal, its side checked against the pseudo-normal of the
closest feature (a point off a sharp edge, or past an open cut of a culled body, is never called
inside when it is outside). Body contact in the simulator asks differently (Euclidean distance,
nearest face in world-local coordinates); ``simulate.contact.closest`` says why.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

# One implementation of the metric for the dataset filters and the learners.
from simulate.quality import query_body_signed_distance

COLLISION_THRESHOLD_M = 1.0e-3
DEFAULT_MAX_QUERY_DISTANCE_M = 10.0


@dataclass
class BodySignedDistance:
    """Per-point query results, numpy arrays.

    distance: signed distance along the nearest body face normal [m], shape (B, N);
        negative inside the body.
    closest: nearest point on the body surface [m], shape (B, N, 3).
    normal: outward unit normal of the nearest body face, shape (B, N, 3).
    """

    distance: np.ndarray
    closest: np.ndarray
    normal: np.ndarray


def _as_numpy(value: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _frames(points: np.ndarray | torch.Tensor, body_vertices: np.ndarray | torch.Tensor
            ) -> tuple[np.ndarray, np.ndarray, bool]:
    """(points (B, N, 3), body vertices (B, Vb, 3), whether a single (N, 3) frame was given)."""
    p = _as_numpy(points).astype(np.float32)
    bv = _as_numpy(body_vertices).astype(np.float32)
    single = p.ndim == 2
    if single:
        p = p[None]
    if bv.ndim == 2:
        bv = np.broadcast_to(bv[None], (p.shape[0],) + bv.shape)
    if p.ndim != 3 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (B, N, 3) or (N, 3), got {tuple(p.shape)}")
    if bv.ndim != 3 or bv.shape[-1] != 3 or bv.shape[0] != p.shape[0]:
        raise ValueError(
            f"body_vertices must have shape (B, Vb, 3) with B={p.shape[0]} "
            f"(or (Vb, 3)), got {tuple(bv.shape)}"
        )
    return p, bv, single


class BodyMeshes:
    """The BVHs of B posed bodies, built once and queried as often as needed: every model of an
    evaluation, and the ground truth, asks about the same bodies.

    body_vertices: [m], shape (B, Vb, 3); body_faces: (F, 3), shared by all frames; device: Warp
    device ("cpu", "cuda:0"), default Warp's default device.
    """

    def __init__(self, body_vertices: np.ndarray | torch.Tensor, body_faces: np.ndarray, *,
                 device: str | None = None) -> None:
        bv = _as_numpy(body_vertices).astype(np.float32)
        if bv.ndim != 3 or bv.shape[-1] != 3:
            raise ValueError(f"body_vertices must have shape (B, Vb, 3), got {tuple(bv.shape)}")
        faces = np.asarray(body_faces)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"body_faces must have shape (F, 3), got {faces.shape}")
        self.device = wp.get_device(device)
        self.frame_count = int(bv.shape[0])
        indices = wp.array(faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=self.device)
        self._meshes = [wp.Mesh(points=wp.array(bv[b], dtype=wp.vec3, device=self.device), indices=indices)
                        for b in range(self.frame_count)]
        self._ids = wp.array(np.array([m.id for m in self._meshes], dtype=np.uint64), dtype=wp.uint64,
                             device=self.device)

    def _query(self, points: np.ndarray, max_distance: float) -> tuple[wp.array, wp.array, wp.array]:
        if points.ndim != 3 or points.shape[0] != self.frame_count or points.shape[-1] != 3:
            raise ValueError(f"points must have shape ({self.frame_count}, N, 3), got {tuple(points.shape)}")
        total = points.shape[0] * points.shape[1]
        points_wp = wp.array(np.ascontiguousarray(points, np.float32).reshape(-1, 3), dtype=wp.vec3,
                             device=self.device)
        distance = wp.empty(total, dtype=float, device=self.device)
        closest = wp.empty(total, dtype=wp.vec3, device=self.device)
        normal = wp.empty(total, dtype=wp.vec3, device=self.device)
        if total:
            wp.launch(query_body_signed_distance, dim=total,
                      inputs=[self._ids, points_wp, points.shape[1], float(max_distance)],
                      outputs=[distance, closest, normal], device=self.device)
        return distance, closest, normal

    def signed_distance(self, points: np.ndarray | torch.Tensor, *,
                        max_distance: float = DEFAULT_MAX_QUERY_DISTANCE_M) -> BodySignedDistance:
        """Per-point results for query points [m], shape (B, N, 3)."""
        p = _as_numpy(points).astype(np.float32)
        distance, closest, normal = self._query(p, max_distance)
        b, n = p.shape[:2]
        return BodySignedDistance(distance.numpy().reshape(b, n), closest.numpy().reshape(b, n, 3),
                                  normal.numpy().reshape(b, n, 3))

    def distance(self, points: np.ndarray | torch.Tensor, *,
                 max_distance: float = DEFAULT_MAX_QUERY_DISTANCE_M) -> np.ndarray:
        """The signed distances alone [m], shape (B, N): one copy back from the device."""
        p = _as_numpy(points).astype(np.float32)
        return self._query(p, max_distance)[0].numpy().reshape(p.shape[:2])


def body_signed_distance(
    points: np.ndarray | torch.Tensor,
    body_vertices: np.ndarray | torch.Tensor,
    body_faces: np.ndarray,
    *,
    device: str | None = None,
    max_distance: float = DEFAULT_MAX_QUERY_DISTANCE_M,
) -> BodySignedDistance:
    """Signed distance of points to a per-frame body mesh.

    Args:
        points: query points [m], shape (B, N, 3) or (N, 3).
        body_vertices: body vertices [m] per frame, shape (B, Vb, 3) or (Vb, 3).
        body_faces: body triangles, shape (F, 3), shared by all frames.
        device: Warp device ("cpu", "cuda:0"); default Warp's default device.
        max_distance: query radius [m]; farther points get distance = max_distance.
    """
    p, bv, single = _frames(points, body_vertices)
    faces = np.asarray(body_faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"body_faces must have shape (F, 3), got {faces.shape}")
    if p.shape[0] == 0 or p.shape[1] == 0:
        empty = np.zeros(p.shape[:2], dtype=np.float32)
        return BodySignedDistance(empty, np.zeros(p.shape, np.float32), np.zeros(p.shape, np.float32))
    result = BodyMeshes(bv, faces, device=device).signed_distance(p, max_distance=max_distance)
    if single:
        return BodySignedDistance(result.distance[0], result.closest[0], result.normal[0])
    return result


def collision_mask(
    garment_vertices: np.ndarray | torch.Tensor,
    body_vertices: np.ndarray | torch.Tensor,
    body_faces: np.ndarray,
    *,
    threshold: float = COLLISION_THRESHOLD_M,
    device: str | None = None,
    meshes: BodyMeshes | None = None,
) -> np.ndarray:
    """Boolean mask of colliding garment vertices (signed distance < -threshold), shape (B, V)
    ((V,) for one (V, 3) frame). ``meshes``: the bodies' BVHs already built (``body_vertices``
    and ``device`` are then not read), e.g. shared by the models of an evaluation."""
    if threshold < 0:
        raise ValueError(f"threshold must be >= 0 m, got {threshold}")
    if meshes is not None:
        return meshes.distance(garment_vertices) < -threshold
    p, bv, single = _frames(garment_vertices, body_vertices)
    if p.shape[0] == 0 or p.shape[1] == 0:
        distance = np.zeros(p.shape[:2], dtype=np.float32)
    else:
        distance = BodyMeshes(bv, body_faces, device=device).distance(p)
    return distance[0] < -threshold if single else distance < -threshold


def collision_rate(
    garment_vertices: np.ndarray | torch.Tensor,
    body_vertices: np.ndarray | torch.Tensor,
    body_faces: np.ndarray,
    *,
    threshold: float = COLLISION_THRESHOLD_M,
    device: str | None = None,
) -> np.ndarray:
    """Fraction of garment vertices more than ``threshold`` [m] inside the body, per frame.

    garment_vertices: [m], shape (B, V, 3); body_vertices: [m], shape (B, Vb, 3) or (Vb, 3);
    body_faces: (F, 3). Returns shape (B,), values in [0, 1].
    """
    mask = collision_mask(
        garment_vertices, body_vertices, body_faces, threshold=threshold, device=device
    )
    return mask.reshape(mask.shape[0] if mask.ndim == 2 else 1, -1).mean(axis=1)
