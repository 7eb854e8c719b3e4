"""Seed 001's fully connected variant (Appendix E.3, "Off. Loc. 128 PC"): a PCA basis of
the cloth-pixel offsets in their local frames, and an MLP (two hidden layers of 256,
ReLU) predicting the 128 coefficients."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

PCA_COMPONENTS = 128
HIDDEN = 256


def offset_basis(local: np.ndarray | torch.Tensor, components: int = PCA_COMPONENTS
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """PCA of training offsets (N, K, 3) [m]: (mean (K 3,), basis (C, K 3) orthonormal
    rows, singular values (C,)), C = min(components, N, K 3)."""
    x = torch.as_tensor(local, dtype=torch.float64).reshape(len(local), -1)
    mean = x.mean(0)
    _, s, vt = torch.linalg.svd(x - mean, full_matrices=False)
    c = min(int(components), vt.shape[0])
    return mean.float(), _oriented(vt[:c]).float(), s[:c].float()


def _oriented(basis: torch.Tensor) -> torch.Tensor:
    """``basis`` (C, D) with each row's entry of largest magnitude positive: the SVD's and the
    eigensolver's sign choices differ between libraries and devices, the oriented basis does not."""
    pick = basis.abs().argmax(dim=1, keepdim=True)
    return basis * torch.sign(basis.gather(1, pick)).clamp_min(0).mul(2).sub(1)


class OffsetMoments:
    """Sums over training offsets for their PCA without holding them (a streamed split): the
    frame count, the sum (D,) and the Gram matrix x^T x (D, D) in float64, D = 3 K (K cloth
    pixels; D^2 x 8 bytes on ``device``). :meth:`basis` gives what :func:`offset_basis` gives on
    the same frames, to float64 rounding of the centred Gram matrix's eigenvectors."""

    def __init__(self, pixel_count: int, device: str | torch.device = "cpu") -> None:
        size = 3 * int(pixel_count)
        self.count = torch.zeros((), dtype=torch.float64, device=device)
        self.sum = torch.zeros(size, dtype=torch.float64, device=device)
        self.gram = torch.zeros(size, size, dtype=torch.float64, device=device)

    def add(self, local: torch.Tensor) -> None:
        """Adds the offsets (B, K, 3) [m] of B frames."""
        x = local.detach().reshape(len(local), -1).to(self.sum.device, torch.float64)
        self.count += x.shape[0]
        self.sum += x.sum(0)
        self.gram += x.T @ x

    def all_reduce(self) -> None:
        """Sums the moments over the ranks of a process group (each rank having added its frames)."""
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            for t in (self.count, self.sum, self.gram):
                torch.distributed.all_reduce(t)

    def basis(self, components: int = PCA_COMPONENTS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(mean (D,), basis (C, D) orthonormal rows, singular values (C,)) as :func:`offset_basis`,
        C = min(components, frames, D)."""
        n = int(self.count)
        if n == 0:
            raise ValueError("no offsets were added")
        mean = self.sum / n
        centred = self.gram - n * torch.outer(mean, mean)
        values, vectors = torch.linalg.eigh((centred + centred.T) / 2)
        c = min(int(components), n, mean.numel())
        order = torch.argsort(values, descending=True)[:c]
        singular = values[order].clamp_min(0).sqrt()
        return mean.float(), _oriented(vectors[:, order].T).float(), singular.float()


class PCADecoder(nn.Module):
    """Features (B, N) -> cloth-pixel offsets (B, K, 3) [m] through C PCA coefficients.

    Args:
        in_features: N; pixel_count: K; components: C (128); hidden: width (256).
    Buffers ``mean`` (K 3,) and ``basis`` (C, K 3) are set by :meth:`set_basis`; the
    coefficients are predicted in units of each component's training standard deviation
    (``scale`` (C,)), so the MLP's outputs are O(1).
    """

    def __init__(self, in_features: int, pixel_count: int, *, components: int = PCA_COMPONENTS,
                 hidden: int = HIDDEN) -> None:
        super().__init__()
        self.config = {"in_features": int(in_features), "pixel_count": int(pixel_count),
                       "components": int(components), "hidden": int(hidden)}
        self.mlp = nn.Sequential(nn.Linear(in_features, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden),
                                 nn.ReLU(inplace=True), nn.Linear(hidden, components))
        self.register_buffer("mean", torch.zeros(3 * pixel_count))
        self.register_buffer("basis", torch.zeros(components, 3 * pixel_count))
        self.register_buffer("scale", torch.ones(components))

    def set_basis(self, mean: torch.Tensor, basis: torch.Tensor, singular_values: torch.Tensor, frames: int) -> None:
        """Installs a basis from :func:`offset_basis` over ``frames`` training frames
        (fewer components than configured are zero-padded)."""
        c = basis.shape[0]
        self.mean.copy_(mean)
        self.basis.zero_()
        self.basis[:c] = basis
        self.scale.fill_(1.0)
        self.scale[:c] = (singular_values / max(1, frames - 1) ** 0.5).clamp_min(1e-8)

    def coefficients(self, local: torch.Tensor) -> torch.Tensor:
        """Offsets (B, K, 3) -> their scaled coefficients (B, C) (projection on the basis)."""
        return ((local.reshape(len(local), -1) - self.mean) @ self.basis.T) / self.scale

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        coefficients = self.mlp(features) * self.scale  # (B, C)
        return (self.mean + coefficients @ self.basis).reshape(len(features), -1, 3)
