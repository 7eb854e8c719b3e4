"""The multi-layer perceptron every TailorNet network uses.

Linear -> ReLU -> Dropout(0.2) -> Linear -> ReLU -> Linear, as in the authors' code
(two hidden layers of equal width). Outputs are flat; callers reshape to (B, V, 3).
"""

from __future__ import annotations

import torch
from torch import nn


class MLP(nn.Module):
    """Two-hidden-layer perceptron.

    Args:
        input_size: features in, shape (B, input_size).
        output_size: features out, shape (B, output_size).
        hidden_size: width of both hidden layers (TailorNet: 1024, or 128 for g).
        dropout: drop probability after the first hidden layer (TailorNet: 0.2).
    """

    def __init__(
        self, input_size: int, output_size: int, *, hidden_size: int = 1024, dropout: float = 0.2
    ) -> None:
        super().__init__()
        for name, value in (
            ("input_size", input_size),
            ("output_size", output_size),
            ("hidden_size", hidden_size),
        ):
            if value < 1:
                raise ValueError(f"MLP {name} must be >= 1, got {value}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"MLP dropout must be in [0, 1), got {dropout}")
        self.input_size = int(input_size)
        self.output_size = int(output_size)
        self.hidden_size = int(hidden_size)
        self.dropout = float(dropout)
        self.layers = nn.Sequential(
            nn.Linear(input_size, hidden_size),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(hidden_size, hidden_size),
            nn.ReLU(),
            nn.Linear(hidden_size, output_size),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: shape (B, input_size) -> shape (B, output_size)."""
        if x.ndim != 2 or x.shape[1] != self.input_size:
            raise ValueError(
                f"MLP input must have shape (B, {self.input_size}), got {tuple(x.shape)}"
            )
        return self.layers(x)

    def hidden(self, x: torch.Tensor) -> torch.Tensor:
        """Activations of the second hidden layer, shape (B, hidden_size)."""
        return self.layers[:5](x)
