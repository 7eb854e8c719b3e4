"""The assembled collision-aware predictor: (pose, shape, style) -> latent -> canonical garment ->
posed garment, and the template-unposed displacements the evaluation harness compares.

``forward`` returns the unposed displacements of the dataset's convention (TailorNet Eq. 5:
LBS^-1 with the garment template's skinning weights, minus the unposed body under each vertex), so
``learn.tailornet.evaluate`` scores this model like the others: posing them back with the
template's weights gives exactly the garment this model posed with its diffused fields
(LBS^-1 then LBS with the same weights and transforms is the identity). Timings of ``forward``
therefore include the body's forward kinematics and both skinnings.

With the recurrent regressor (motion datasets) the latent of a frame depends on the frames
before it: ``forward`` reads its B rows as one sequence of consecutive frames at the
regressor's fps (so ``forward`` of one row is a sequence's first frame), and
:meth:`CollisionAwareModel.predict_frames` runs every sequence of a split through in frame
order, the GRU state carried from frame to frame (what ``drape evaluate`` scores).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from learn.collision_aware.fields import DiffusedBody
from learn.collision_aware.garment_model import pose_garment
from learn.collision_aware.motion_descriptor import padded, padded_times, sequence_rows
from learn.collision_aware.recurrent_regressor import RecurrentLatentRegressor
from learn.collision_aware.regressor import LatentRegressor
from learn.collision_aware.vae import GarmentVAE
from learn.common.collision import COLLISION_THRESHOLD_M
from simulate.body.kinematics import inverse_lbs


class CollisionAwareModel(nn.Module):
    """Args:
        regressor: (pose, shape, style) -> latent: :class:`LatentRegressor` (per frame) or
            :class:`RecurrentLatentRegressor` (per sequence).
        vae: the garment VAE (its decoder is used).
        fields: the diffused body fields.
        template: the dataset's garment template (``skinning_weights`` (V, J),
            ``body_vertex_index`` (V,), ``rest_vertices`` (V, 3) [m]).
        body_spec: ``{"backend": ..., "path": ...}`` of the body model, loaded on first use.
        body: an already loaded body model of that spec (optional).
    """

    def __init__(self, regressor: LatentRegressor | RecurrentLatentRegressor, vae: GarmentVAE, fields: DiffusedBody,
                 template: dict[str, np.ndarray], body_spec: dict[str, Any], *, body: Any = None) -> None:
        super().__init__()
        self.regressor, self.vae, self.fields = regressor, vae, fields
        self.recurrent = isinstance(regressor, RecurrentLatentRegressor)
        weights = np.asarray(template["skinning_weights"], np.float32)
        self.config: dict[str, Any] = {
            "regressor": regressor.config, "regressor_kind": "gru" if self.recurrent else "mlp", "vae": vae.config, "fields": fields.config,
            "body": {"backend": body_spec.get("backend", "anny"), "path": body_spec.get("path")},
            "vertex_count": int(weights.shape[0]), "template_joint_count": int(weights.shape[1]),
            "style_components": regressor.config["style_size"],
        }
        self.register_buffer("template_weights", torch.as_tensor(weights))
        self.register_buffer("body_vertex_index", torch.as_tensor(np.asarray(template["body_vertex_index"], np.int64)))
        self.register_buffer("template_rest", torch.as_tensor(np.asarray(template["rest_vertices"], np.float32)))
        self._body = body
        if body is not None:
            fields.use_body(body)  # a basis shape field's coefficients come from the body model

    @classmethod
    def from_config(cls, config: dict[str, Any], *, body: Any = None) -> "CollisionAwareModel":
        v, j = config["vertex_count"], config["template_joint_count"]
        template = {"skinning_weights": np.zeros((v, j), np.float32), "body_vertex_index": np.zeros(v, np.int64),
                    "rest_vertices": np.zeros((v, 3), np.float32)}
        kind = RecurrentLatentRegressor if config.get("regressor_kind", "mlp") == "gru" else LatentRegressor
        return cls(kind(**config["regressor"]), GarmentVAE.from_config(config["vae"]),
                   DiffusedBody(**config["fields"]), template, config["body"], body=body)

    def body_on(self, device: torch.device) -> Any:
        """The body model with its tensors on ``device`` (loaded from ``config['body']`` once)."""
        if self._body is None:
            from simulate.body import load_body_model

            self._body = load_body_model(self.config["body"]["backend"], path=self.config["body"]["path"])
            self.fields.use_body(self._body)
        return self._body.on_device(device)

    def latent(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Latent (B, L) of B frames (recurrent: B consecutive frames of one sequence)."""
        if self.recurrent:
            return self.regressor(pose[None], shape[None], style[None])[0][0]
        return self.regressor(pose, shape, style)

    def canonical(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Canonical garment X [m] (B, V, 3)."""
        return self.vae.decode(self.latent(pose, shape, style))

    def _posed_and_body(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor,
                        latent: torch.Tensor | None = None) -> tuple[torch.Tensor, Any]:
        body = self.body_on(pose.device).pose_torch(shape, pose)
        transforms = body.skinning_transforms.to(pose.device)
        canonical = self.canonical(pose, shape, style) if latent is None else self.vae.decode(latent)
        return pose_garment(self.fields, canonical, shape, transforms), body

    def posed(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Posed garment [m] (B, V, 3) (no root translation): pose (B, P), shape (B, S), style (B, G)."""
        return self._posed_and_body(pose, shape, style)[0]

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor,
                latent: torch.Tensor | None = None) -> torch.Tensor:
        """Unposed displacements [m] (B, V, 3) in the dataset's template convention; ``latent``
        (B, L): decode these instead of regressing them."""
        posed, body = self._posed_and_body(pose, shape, style, latent)
        transforms = body.skinning_transforms.to(pose.device)
        rest = body.rest_vertices.to(pose.device)  # (B, Vb, 3)
        index = self.body_vertex_index
        under = rest[:, index.clamp_min(0)]  # (B, V, 3)
        base = torch.where((index < 0)[None, :, None], self.template_rest, under)
        return inverse_lbs(posed, self.template_weights, transforms) - base

    def decoder_only(self) -> nn.Module:
        """The regressor and the VAE's decoder alone, ``(pose, shape, style) -> canonical garment
        [m] (B, V, 3)``: what seed 002 times (Table 2), without the body posing and the diffused
        skinning that put the garment on the body."""
        return _CanonicalOnly(self)

    @torch.no_grad()
    def sequence_latents(self, pose: np.ndarray, shape: np.ndarray, style: np.ndarray, sequence: np.ndarray,
                         frame_index: np.ndarray, root: np.ndarray | None = None,
                         device: str | torch.device = "cpu") -> np.ndarray:
        """Latent (N, L) of N frames of several sequences, run by the recurrent regressor: each
        sequence (frames of one ``sequence`` value (N,), ordered by ``frame_index`` (N,)) from a
        zero state through its frames, the state carried frame to frame; frame times
        ``frame_index / fps``. pose (N, P), shape (N, S), style (N, G); root (N, 3) [m] or None."""
        if not self.recurrent:
            raise ValueError("sequence_latents needs the recurrent regressor; this model regresses frames one by one")
        rows = sequence_rows(sequence, frame_index)
        fps = float(self.regressor.config["fps"])

        def gathered(values: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(padded(rows, np.asarray(values, np.float32)), device=device)

        latent, _ = self.regressor(gathered(pose), gathered(shape), gathered(style),
                                   torch.as_tensor(padded_times(rows, frame_index, fps), device=device),
                                   None if root is None else gathered(root))
        out = np.empty((len(np.asarray(sequence).reshape(-1)), latent.shape[-1]), np.float32)
        latent = latent.cpu().numpy()
        for k, r in enumerate(rows):
            out[r] = latent[k, :len(r)]
        return out

    @torch.no_grad()
    def predict_frames(self, pose: np.ndarray, shape: np.ndarray, style: np.ndarray, sequence: np.ndarray,
                       frame_index: np.ndarray, root: np.ndarray | None = None, *, batch_size: int = 256,
                       device: str | torch.device = "cpu") -> torch.Tensor:
        """Unposed displacements [m] (N, V, 3) on ``device`` of N frames of several sequences, each
        run in frame order (:meth:`sequence_latents`, same arguments); the decoding and skinning
        run in batches of ``batch_size`` frames."""
        self.to(device).eval()
        latent = torch.as_tensor(self.sequence_latents(pose, shape, style, sequence, frame_index, root, device=device),
                                 device=device)
        inputs = [torch.as_tensor(np.asarray(a), dtype=torch.float32).to(device) for a in (pose, shape, style)]
        return torch.cat([self(*(x[b:b + batch_size] for x in inputs), latent=latent[b:b + batch_size]).float()
                          for b in range(0, latent.shape[0], batch_size)], dim=0)


    @torch.no_grad()
    def canonical_collision_rate(self, sdf: nn.Module, pose: np.ndarray, shape: np.ndarray, style: np.ndarray, *,
                                 sequence: np.ndarray | None = None, frame_index: np.ndarray | None = None,
                                 root: np.ndarray | None = None, threshold_m: float = COLLISION_THRESHOLD_M,
                                 batch_size: int = 256, device: str | torch.device = "cpu") -> float:
        """Fraction of the predicted canonical garments' vertices more than ``threshold_m`` inside the
        canonical body, by ``sdf`` (points [m] (..., 3) -> signed distance [m], negative inside; the
        run's ``sdf.pt``): the collisions the generative space and the regressor leave before any
        posing. What the posed rate adds to it comes from the posing (the diffused fields against
        the body's own skinning). Frames as in :meth:`predict_frames` (sequence, frame_index and
        root for the recurrent regressor)."""
        self.to(device).eval()
        sdf = sdf.to(device).eval()
        if self.recurrent:
            latent = torch.as_tensor(self.sequence_latents(pose, shape, style, sequence, frame_index, root,
                                                           device=device), device=device)
        else:
            inputs = [torch.as_tensor(np.asarray(a), dtype=torch.float32).to(device) for a in (pose, shape, style)]
            latent = torch.cat([self.latent(*(x[b:b + batch_size] for x in inputs))
                                for b in range(0, inputs[0].shape[0], batch_size)])
        inside = total = 0
        for b in range(0, latent.shape[0], batch_size):
            distance = sdf(self.vae.decode(latent[b:b + batch_size]))
            inside += int((distance < -threshold_m).sum())
            total += distance.numel()
        return inside / max(total, 1)


class _CanonicalOnly(nn.Module):
    def __init__(self, model: CollisionAwareModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        return self.model.canonical(pose, shape, style)
