"""TailorNet: low-frequency MLP plus a kernel mixture of prototype high-frequency MLPs.

D(pose, shape, style) = D_LF(pose, shape, style) + sum_k w_k(shape, style) D_HF_k(pose)
(paper Eq. 8), with w from the canonical-garment model g (Eq. 9). Everything is batched
and differentiable; the garment is then posed by adding the unposed body under it and
skinning (Eq. 3-4) through injected callables, so this module never loads a body model.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from learn.tailornet.hf import HighFrequencyPrototypes
from learn.tailornet.lf import DisplacementMLP
from learn.tailornet.mixture import DEFAULT_SIGMA, kernel_weights, prototype_distances
from learn.tailornet.shape_style import ShapeStyleModel

# (displaced unposed garment vertices [m] (B, V, 3), pose (B, P), shape (B, S)) -> posed
# garment vertices [m] (B, V, 3): skinning with the body model's transforms.
GarmentPoser = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
# shape (B, S) -> unposed body vertex under each garment vertex [m], (B, V, 3).
UnposedBody = Callable[[torch.Tensor], torch.Tensor]

DEFAULT_WEIGHT_FLOOR = 1.0e-6


def pose_displacements(
    displacements: torch.Tensor,
    pose: torch.Tensor,
    shape: torch.Tensor,
    *,
    garment_poser: GarmentPoser,
    unposed_body: UnposedBody,
) -> torch.Tensor:
    """Posed garment [m], (B, V, 3) = skin(unposed body(shape) + displacements)."""
    return garment_poser(unposed_body(shape) + displacements, pose, shape)


class TailorNet(nn.Module):
    """The mixture model.

    Args:
        low_frequency: D_LF(pose, shape, style).
        high_frequency: the K stacked prototype models D_HF_k(pose).
        shape_style: g(shape, style) -> canonical displacements.
        prototype_shape: shape coefficients of the K prototypes, shape (K, S).
        prototype_style: style coefficients of the K prototypes, shape (K, G).
        sigma: kernel bandwidth (default 0.01, dimensionless like dist).
        weight_floor: prototypes whose kernel weight is at most this for every frame of a
            batch are skipped at inference (default 1e-6: an error below K x 1e-6 of the
            high-frequency displacement, for a several-fold speed-up); 0 evaluates all.
    """

    def __init__(
        self,
        low_frequency: DisplacementMLP,
        high_frequency: HighFrequencyPrototypes,
        shape_style: ShapeStyleModel,
        prototype_shape: torch.Tensor,
        prototype_style: torch.Tensor,
        *,
        sigma: float = DEFAULT_SIGMA,
        weight_floor: float = DEFAULT_WEIGHT_FLOOR,
    ) -> None:
        super().__init__()
        k = high_frequency.prototype_count
        if prototype_shape.ndim != 2 or prototype_shape.shape[0] != k:
            raise ValueError(f"prototype_shape must have shape ({k}, S), got {tuple(prototype_shape.shape)}")
        if prototype_style.ndim != 2 or prototype_style.shape[0] != k:
            raise ValueError(f"prototype_style must have shape ({k}, G), got {tuple(prototype_style.shape)}")
        if sigma <= 0:
            raise ValueError(f"sigma must be > 0, got {sigma}")
        if not 0.0 <= weight_floor < 1.0:
            raise ValueError(f"weight_floor must be in [0, 1), got {weight_floor}")
        vertex_counts = {low_frequency.vertex_count, high_frequency.vertex_count, shape_style.vertex_count}
        if len(vertex_counts) != 1:
            raise ValueError(f"sub-models disagree on the vertex count: {sorted(vertex_counts)}")
        self.low_frequency = low_frequency
        self.high_frequency = high_frequency
        self.shape_style = shape_style
        self.sigma = float(sigma)
        self.weight_floor = float(weight_floor)
        device = shape_style.pose_indices.device
        self.register_buffer("prototype_shape", prototype_shape.detach().float().clone().to(device))
        self.register_buffer("prototype_style", prototype_style.detach().float().clone().to(device))
        self.register_buffer(
            "prototype_garments", torch.zeros(k, low_frequency.vertex_count, 3, device=device)
        )
        self.refresh_prototype_garments()

    @property
    def vertex_count(self) -> int:
        return self.low_frequency.vertex_count

    @property
    def config(self) -> dict[str, Any]:
        return {
            "low_frequency": self.low_frequency.config,
            "high_frequency": self.high_frequency.config,
            "shape_style": self.shape_style.config,
            "prototype_shape": self.prototype_shape.tolist(),
            "prototype_style": self.prototype_style.tolist(),
            "sigma": self.sigma,
            "weight_floor": self.weight_floor,
        }

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> TailorNet:
        """Rebuild an untrained module of the right shapes (load a state dict after)."""
        hf = dict(config["high_frequency"])
        return cls(
            DisplacementMLP(**config["low_frequency"]),
            HighFrequencyPrototypes(
                hf.pop("prototype_count"), hf.pop("vertex_count"), hf.pop("pose_indices"), **hf
            ),
            ShapeStyleModel(**config["shape_style"]),
            torch.as_tensor(config["prototype_shape"], dtype=torch.float32),
            torch.as_tensor(config["prototype_style"], dtype=torch.float32),
            sigma=config["sigma"],
            weight_floor=config.get("weight_floor", DEFAULT_WEIGHT_FLOOR),
        )

    @torch.no_grad()
    def refresh_prototype_garments(self) -> None:
        """Cache g(phi_k) for the prototypes; call after g changes (done on construction)."""
        was_training = self.shape_style.training
        self.shape_style.eval()
        self.prototype_garments.copy_(
            self.shape_style.canonical(self.prototype_shape, self.prototype_style)
        )
        self.shape_style.train(was_training)

    def mixture_weights(self, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Kernel weights over prototypes, shape (B, K), rows summing to one."""
        query = self.shape_style.canonical(shape, style)  # (B, V, 3)
        return kernel_weights(prototype_distances(query, self.prototype_garments), sigma=self.sigma)

    def components(
        self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """low_frequency (B, V, 3), high_frequency (B, V, 3), weights (B, K), displacements."""
        weights = self.mixture_weights(shape, style)
        low = self.low_frequency(pose, shape, style)
        # Skipping negligible prototypes is exact enough at inference; training keeps all.
        floor = 0.0 if torch.is_grad_enabled() else self.weight_floor
        high = self.high_frequency(pose, weights, weight_floor=floor)
        return {"low_frequency": low, "high_frequency": high, "weights": weights, "displacements": low + high}

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """pose (B, P), shape (B, S), style (B, G) -> unposed displacements [m], (B, V, 3)."""
        return self.components(pose, shape, style)["displacements"]

    def pose_garment(
        self,
        pose: torch.Tensor,
        shape: torch.Tensor,
        style: torch.Tensor,
        *,
        garment_poser: GarmentPoser,
        unposed_body: UnposedBody,
    ) -> torch.Tensor:
        """Posed garment vertices [m], (B, V, 3)."""
        return pose_displacements(
            self.forward(pose, shape, style),
            pose,
            shape,
            garment_poser=garment_poser,
            unposed_body=unposed_body,
        )
