"""Kernel weights of the high-frequency mixture (TailorNet Eq. 9).

w_k = exp(-dist(g(phi), g(phi_k)) / sigma) / sum_j exp(-dist(g(phi), g(phi_j)) / sigma),
with dist = 1000 x mean over vertices of the squared distance [m^2] between predicted
canonical garments. Normalising the exponentials is a softmax of -dist / sigma, which is
what we compute: it never overflows or divides by zero even when sigma is tiny and all
exponentials underflow.
"""

from __future__ import annotations

import torch

DEFAULT_SIGMA = 0.01
DISTANCE_SCALE = 1000.0


def prototype_distances(query: torch.Tensor, prototypes: torch.Tensor) -> torch.Tensor:
    """dist between canonical garments: 1000 x mean squared vertex distance, shape (B, K).

    query: predicted canonical displacements [m], shape (B, V, 3); prototypes: shape
    (K, V, 3). Expanded as |q|^2 + |p|^2 - 2 q.p so memory stays O(B V + K V).
    """
    if query.ndim != 3 or prototypes.ndim != 3 or query.shape[1:] != prototypes.shape[1:]:
        raise ValueError(
            "query and prototypes must have shapes (B, V, 3) and (K, V, 3), got "
            f"{tuple(query.shape)} and {tuple(prototypes.shape)}"
        )
    vertex_count = query.shape[1]
    q = query.reshape(query.shape[0], -1).double()  # (B, 3V)
    p = prototypes.reshape(prototypes.shape[0], -1).double()  # (K, 3V)
    squared = (q * q).sum(1, keepdim=True) + (p * p).sum(1)[None, :] - 2.0 * q @ p.T  # (B, K)
    return (squared.clamp_min(0.0) * (DISTANCE_SCALE / vertex_count)).to(query.dtype)


def kernel_weights(distances: torch.Tensor, *, sigma: float = DEFAULT_SIGMA) -> torch.Tensor:
    """Normalised kernel weights from distances (B, K); rows sum to one. sigma > 0."""
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    return torch.softmax(-distances / sigma, dim=-1)
