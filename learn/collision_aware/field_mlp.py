"""The small coordinate network behind every distilled field (skinning weights, shape offsets,
signed distance): points [m] -> values, smooth in the point.

Points are centred and scaled into about [-1, 1] by the body's bounding box, expanded with a few
sine/cosine frequencies (so a shallow network can follow the body's detail), and fed to an MLP
with SiLU activations: the fields are differentiated in the canonicalization and the collision
losses, and SiLU keeps their gradients continuous where ReLU's would jump.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn


class FieldMLP(nn.Module):
    """Coordinate MLP: ``forward(points (..., 3) [m], extra (..., E) | None) -> (..., out_features)``.

    Args:
        out_features: values per point.
        extra_features: conditioning inputs per point (e.g. body shape), 0 for none.
        hidden_size: width of the hidden layers.
        layers: number of hidden layers (>= 1).
        frequencies: octaves of the sine/cosine encoding (0: raw coordinates only).
        center: centre of the region of interest [m], 3 values.
        scale: half-size of the region of interest [m] (coordinates are divided by it).
    """

    def __init__(self, out_features: int, *, extra_features: int = 0, hidden_size: int = 128, layers: int = 3,
                 frequencies: int = 4, center: tuple[float, float, float] | list[float] = (0.0, 0.0, 0.0),
                 scale: float = 1.0) -> None:
        super().__init__()
        for name, value, low in (("out_features", out_features, 1), ("hidden_size", hidden_size, 1),
                                 ("layers", layers, 1), ("frequencies", frequencies, 0),
                                 ("extra_features", extra_features, 0)):
            if int(value) < low:
                raise ValueError(f"FieldMLP {name} must be >= {low}, got {value}")
        if not scale > 0:
            raise ValueError(f"FieldMLP scale must be > 0 m, got {scale}")
        self.config: dict[str, Any] = {
            "out_features": int(out_features), "extra_features": int(extra_features), "hidden_size": int(hidden_size),
            "layers": int(layers), "frequencies": int(frequencies), "center": [float(c) for c in center],
            "scale": float(scale),
        }
        self.register_buffer("center", torch.tensor(self.config["center"], dtype=torch.float32))
        self.register_buffer("octaves", (2.0 ** torch.arange(int(frequencies), dtype=torch.float32)) * math.pi)
        width = 3 * (1 + 2 * int(frequencies)) + int(extra_features)
        modules: list[nn.Module] = []
        for _ in range(int(layers)):
            modules += [nn.Linear(width, int(hidden_size)), nn.SiLU()]
            width = int(hidden_size)
        modules.append(nn.Linear(width, int(out_features)))
        self.net = nn.Sequential(*modules)

    def encode(self, points: torch.Tensor) -> torch.Tensor:
        """Normalized coordinates and their sine/cosine expansion, (..., 3) -> (..., 3 (1 + 2 K))."""
        x = (points - self.center) / self.config["scale"]  # (..., 3)
        if self.octaves.numel() == 0:
            return x
        angles = (x[..., None, :] * self.octaves[:, None]).flatten(-2)  # (..., 3 K)
        return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)

    def forward(self, points: torch.Tensor, extra: torch.Tensor | None = None) -> torch.Tensor:
        if points.shape[-1] != 3:
            raise ValueError(f"points must have shape (..., 3), got {tuple(points.shape)}")
        features = self.encode(points)
        if self.config["extra_features"]:
            if extra is None or extra.shape[-1] != self.config["extra_features"]:
                raise ValueError(f"this field needs {self.config['extra_features']} extra inputs per point, got "
                                 f"{None if extra is None else tuple(extra.shape)}")
            features = torch.cat([features, extra.expand(*features.shape[:-1], extra.shape[-1])], dim=-1)
        return self.net(features)
