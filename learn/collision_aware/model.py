"""The assembled collision-aware predictor: (pose, shape, style) -> latent -> canonical garment ->
posed garment, and the template-unposed displacements the evaluation harness compares.

``forward`` returns the unposed displacements of the dataset's convention (TailorNet Eq. 5:
LBS^-1 with the garment template's skinning weights, minus the unposed body under each vertex), so
``learn.tailornet.evaluate`` scores this model like the others: posing them back with the
template's weights gives exactly the garment this model posed with its diffused fields
(LBS^-1 then LBS with the same weights and transforms is the identity). Timings of ``forward``
therefore include the body's forward kinematics and both skinnings.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from learn.collision_aware.fields import DiffusedBody
from learn.collision_aware.garment_model import pose_garment
from learn.collision_aware.regressor import LatentRegressor
from learn.collision_aware.vae import GarmentVAE
from simulate.body.kinematics import inverse_lbs


class CollisionAwareModel(nn.Module):
    """Args:
        regressor: (pose, shape, style) -> latent.
        vae: the garment VAE (its decoder is used).
        fields: the diffused body fields.
        template: the dataset's garment template (``skinning_weights`` (V, J),
            ``body_vertex_index`` (V,), ``rest_vertices`` (V, 3) [m]).
        body_spec: ``{"backend": ..., "path": ...}`` of the body model, loaded on first use.
        body: an already loaded body model of that spec (optional).
    """

    def __init__(self, regressor: LatentRegressor, vae: GarmentVAE, fields: DiffusedBody,
                 template: dict[str, np.ndarray], body_spec: dict[str, Any], *, body: Any = None) -> None:
        super().__init__()
        self.regressor, self.vae, self.fields = regressor, vae, fields
        weights = np.asarray(template["skinning_weights"], np.float32)
        self.config: dict[str, Any] = {
            "regressor": regressor.config, "vae": vae.config, "fields": fields.config,
            "body": {"backend": body_spec.get("backend", "anny"), "path": body_spec.get("path")},
            "vertex_count": int(weights.shape[0]), "template_joint_count": int(weights.shape[1]),
            "style_components": regressor.config["style_size"],
        }
        self.register_buffer("template_weights", torch.as_tensor(weights))
        self.register_buffer("body_vertex_index", torch.as_tensor(np.asarray(template["body_vertex_index"], np.int64)))
        self.register_buffer("template_rest", torch.as_tensor(np.asarray(template["rest_vertices"], np.float32)))
        self._body = body

    @classmethod
    def from_config(cls, config: dict[str, Any], *, body: Any = None) -> "CollisionAwareModel":
        v, j = config["vertex_count"], config["template_joint_count"]
        template = {"skinning_weights": np.zeros((v, j), np.float32), "body_vertex_index": np.zeros(v, np.int64),
                    "rest_vertices": np.zeros((v, 3), np.float32)}
        return cls(LatentRegressor(**config["regressor"]), GarmentVAE.from_config(config["vae"]),
                   DiffusedBody(**config["fields"]), template, config["body"], body=body)

    def body_on(self, device: torch.device) -> Any:
        """The body model with its tensors on ``device`` (loaded from ``config['body']`` once)."""
        if self._body is None:
            from simulate.body import load_body_model

            self._body = load_body_model(self.config["body"]["backend"], path=self.config["body"]["path"])
        return self._body.on_device(device)

    def canonical(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Canonical garment X [m] (B, V, 3)."""
        return self.vae.decode(self.regressor(pose, shape, style))

    def _posed_and_body(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> tuple[torch.Tensor, Any]:
        body = self.body_on(pose.device).pose_torch(shape, pose)
        transforms = body.skinning_transforms.to(pose.device)
        return pose_garment(self.fields, self.canonical(pose, shape, style), shape, transforms), body

    def posed(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Posed garment [m] (B, V, 3) (no root translation): pose (B, P), shape (B, S), style (B, G)."""
        return self._posed_and_body(pose, shape, style)[0]

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Unposed displacements [m] (B, V, 3) in the dataset's template convention."""
        posed, body = self._posed_and_body(pose, shape, style)
        transforms = body.skinning_transforms.to(pose.device)
        rest = body.rest_vertices.to(pose.device)  # (B, Vb, 3)
        index = self.body_vertex_index
        under = rest[:, index.clamp_min(0)]  # (B, V, 3)
        base = torch.where((index < 0)[None, :, None], self.template_rest, under)
        return inverse_lbs(posed, self.template_weights, transforms) - base
