"""A collision term in the posed space, where the body's parts touch.

The seed's collision terms (the VAE's, the projection's) test the canonical garment against the
canonical body. Where the arms lie on the torso, a garment point a centimetre outside the
canonical skin, posed by linear blend skinning, lands inside the other part, however exactly it
is skinned (docs/learners/collision_aware.md, "Where the posed collisions come from"). Only a
term on the posed garment against the posed body sees that.

:class:`PosedCollision` poses a batch of canonical garments with the diffused fields and the
frames' own body, and measures each vertex's signed distance along the normal of its nearest
posed body face: the collision metric's own query (``simulate.quality.query_body_signed_distance``,
the one :mod:`learn.common.collision` counts with). The query runs without gradient; the distance
is then its value plus ``(y - y0) . normal``, equal to the metric at the queried vertex ``y0`` and
differentiable in the posed vertex ``y`` along the nearest face's normal, and so in the canonical
garment and everything upstream of it. The penalty is the hinge ``max(epsilon - distance, 0)``
[m], averaged over vertices and frames.

The bodies' BVHs are built once, on the canonical body (one per frame of a batch), and refitted to
each batch's posed bodies in place; points and results pass between torch and Warp without copies
on the GPU.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import warp as wp

from learn.collision_aware.fields import DiffusedBody, canonical_body
from learn.collision_aware.garment_model import pose_garment
from learn.common.collision import DEFAULT_MAX_QUERY_DISTANCE_M
from simulate.quality import query_body_signed_distance


def warp_device_of(device: str | torch.device) -> str:
    """The Warp device of a torch device ("cpu", "cuda:K"; a bare "cuda" is the current one)."""
    device = torch.device(device)
    if device.type != "cuda":
        return "cpu"
    return f"cuda:{torch.cuda.current_device() if device.index is None else device.index}"


class PosedCollision:
    """``penalty(canonical, pose, shape)``: the posed-space hinge for canonical garments [m]
    (B, V, 3) with their frames' pose (B, P) and shape (B, S); a scalar [m], 0 when every posed
    vertex is at least ``epsilon_m`` outside the posed body.

    Args:
        body: the dataset's body model (posed on ``device``).
        fields: the diffused fields that pose the garment.
        epsilon_m: margin [m] the posed garment is pushed to keep from the body.
        device: torch device of the garments.
    """

    def __init__(self, body: Any, fields: DiffusedBody, *, epsilon_m: float, device: str | torch.device) -> None:
        if not epsilon_m >= 0.0:
            raise ValueError(f"epsilon_m must be >= 0 m, got {epsilon_m}")
        self.body = body.on_device(device)
        self.fields = fields
        self.epsilon_m = float(epsilon_m)
        self.warp_device = warp_device_of(device)
        self._rest = canonical_body(body).astype(np.float32)
        self._indices = wp.array(np.asarray(body.faces).reshape(-1).astype(np.int32), dtype=wp.int32,
                                 device=self.warp_device)
        self._meshes: list[wp.Mesh] = []
        self._ids: dict[int, wp.array] = {}

    def _scope(self) -> Any:
        """Warp on this term's device, on torch's current stream there (so Warp reads what torch
        wrote and torch reads what Warp wrote, in order)."""
        if self.warp_device == "cpu":
            return wp.ScopedDevice("cpu")
        return wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(torch.device(self.warp_device))))

    def _bodies(self, vertices: torch.Tensor) -> wp.array:
        """The mesh ids of B posed bodies [m] (B, Vb, 3): the kept BVHs refitted to them."""
        with self._scope():
            while len(self._meshes) < vertices.shape[0]:
                self._meshes.append(wp.Mesh(points=wp.array(self._rest, dtype=wp.vec3), indices=self._indices))
            for mesh, frame in zip(self._meshes, vertices):
                wp.copy(mesh.points, wp.from_torch(frame.detach().float().contiguous(), dtype=wp.vec3))
                mesh.refit()
            count = int(vertices.shape[0])
            if count not in self._ids:
                self._ids[count] = wp.array(np.array([m.id for m in self._meshes[:count]], np.uint64), dtype=wp.uint64)
            return self._ids[count]

    def posed(self, canonical: torch.Tensor, pose: torch.Tensor, shape: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed garments [m] (B, V, 3), differentiable in ``canonical``, and the posed bodies'
        vertices [m] (B, Vb, 3), without gradient."""
        with torch.no_grad():
            body = self.body.pose_torch(shape, pose)
        transforms = body.skinning_transforms.to(canonical.device)
        return pose_garment(self.fields, canonical, shape, transforms), body.vertices.to(canonical.device)

    def distance(self, posed: torch.Tensor, body_vertices: torch.Tensor) -> torch.Tensor:
        """Signed distance [m] (B, V) of posed garment vertices to the posed bodies (B, Vb, 3),
        negative inside: the collision metric's value, differentiable in ``posed`` along the
        nearest face's normal."""
        ids = self._bodies(body_vertices)
        points = posed.detach().float().reshape(-1, 3).contiguous()
        value = torch.empty(points.shape[0], device=posed.device)
        closest = torch.empty_like(points)
        normal = torch.empty_like(points)
        if points.shape[0]:
            with self._scope():
                wp.launch(query_body_signed_distance, dim=points.shape[0],
                          inputs=[ids, wp.from_torch(points, dtype=wp.vec3), posed.shape[1],
                                  DEFAULT_MAX_QUERY_DISTANCE_M],
                          outputs=[wp.from_torch(value), wp.from_torch(closest, dtype=wp.vec3),
                                   wp.from_torch(normal, dtype=wp.vec3)])
        value = value.reshape(posed.shape[:2]).to(posed.dtype)
        normal = normal.reshape(posed.shape).to(posed.dtype)
        return value + ((posed - posed.detach()) * normal).sum(-1)

    def __call__(self, canonical: torch.Tensor, pose: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        posed, body_vertices = self.posed(canonical, pose, shape)
        return torch.relu(self.epsilon_m - self.distance(posed, body_vertices)).mean()
