"""A collision term in the posed space, where the body's parts touch.

The seed's collision terms (the VAE's, the projection's) test the canonical garment against the
canonical body. Where the arms lie on the torso, a garment point a centimetre outside the
canonical skin, posed by linear blend skinning, lands inside the other part, however exactly it
is skinned (docs/learners/collision_aware.md, "Where the posed collisions come from"). Only a
term on the posed garment against the posed body sees that.

:class:`PosedCollision` poses a batch of canonical garments with the diffused fields and the
frames' own body, and measures each vertex's signed distance along the normal of its nearest
posed body face: the collision metric's own query (:mod:`learn.common.collision`). The nearest
face and its normal are found without gradient; the distance ``(y - closest) . normal`` is then
differentiable in the posed vertex ``y``, and so in the canonical garment and everything
upstream of it. The penalty is the hinge ``max(epsilon - distance, 0)`` [m], averaged over
vertices and frames.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from learn.collision_aware.fields import DiffusedBody
from learn.collision_aware.garment_model import pose_garment
from learn.common.collision import BodyMeshes


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
        self.faces = np.asarray(body.faces)
        self.epsilon_m = float(epsilon_m)
        self.warp_device = warp_device_of(device)

    def posed(self, canonical: torch.Tensor, pose: torch.Tensor, shape: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed garments [m] (B, V, 3), differentiable in ``canonical``, and the posed bodies'
        vertices [m] (B, Vb, 3), without gradient."""
        with torch.no_grad():
            body = self.body.pose_torch(shape, pose)
        transforms = body.skinning_transforms.to(canonical.device)
        return pose_garment(self.fields, canonical, shape, transforms), body.vertices.to(canonical.device)

    def distance(self, posed: torch.Tensor, body_vertices: torch.Tensor) -> torch.Tensor:
        """Signed distance [m] (B, V) of posed garment vertices along their nearest body face's
        normal (negative inside), differentiable in ``posed``."""
        query = BodyMeshes(body_vertices.detach().float().cpu().numpy(), self.faces,
                           device=self.warp_device).signed_distance(posed.detach())
        closest = torch.as_tensor(query.closest, device=posed.device, dtype=posed.dtype)
        normal = torch.as_tensor(query.normal, device=posed.device, dtype=posed.dtype)
        return ((posed - closest) * normal).sum(-1)

    def __call__(self, canonical: torch.Tensor, pose: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        posed, body_vertices = self.posed(canonical, pose, shape)
        return torch.relu(self.epsilon_m - self.distance(posed, body_vertices)).mean()
