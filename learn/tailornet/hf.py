"""K prototype high-frequency models D_HF_k(pose), trained and evaluated together.

Each prototype style-shape has its own pose MLP, trained on that pair's frames only (see
:func:`learn.tailornet.train.train_hf`). The K MLPs live in stacked weight tensors so
all prototypes run in three batched contractions instead of a Python loop over K, in
training (each prototype on its own batch, :meth:`HighFrequencyPrototypes.forward_each`)
and at inference, where the mixture sum is folded into the last layer:
sum_k w_k (h_k W3_k + b3_k) = [w_1 h_1, ..., w_K h_K] @ [W3_1; ...; W3_K] + w @ b3,
one (B, K H) @ (K H, 3V) matmul.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from learn.tailornet.lf import DisplacementMLP


def high_frequency_model(
    vertex_count: int,
    pose_indices: Sequence[int],
    *,
    hidden_size: int = 1024,
    dropout: float = 0.2,
) -> DisplacementMLP:
    """One prototype's D_HF(pose) -> high-frequency displacements [m], (B, V, 3)."""
    return DisplacementMLP(
        vertex_count, pose_indices=pose_indices, hidden_size=hidden_size, dropout=dropout
    )


class HighFrequencyPrototypes(nn.Module):
    """K stacked pose MLPs.

    :meth:`forward` mixes the K predictions with kernel weights (inference);
    :meth:`forward_each` gives prototype k its own batch of poses (training all K at
    once, with dropout in train mode, see :func:`learn.tailornet.train.train_hf`).

    Args:
        prototype_count: K.
        vertex_count: V.
        pose_indices: pose entries read by every prototype.
        hidden_size: hidden width H of each MLP.
        dropout: dropout after the first hidden layer, applied by :meth:`forward_each`
            in train mode.
        device: where the (zero) parameters are made (default: torch's default device).
    """

    def __init__(
        self,
        prototype_count: int,
        vertex_count: int,
        pose_indices: Sequence[int],
        *,
        hidden_size: int = 1024,
        dropout: float = 0.2,
        device: str | torch.device | None = None,
    ) -> None:
        super().__init__()
        if prototype_count < 1:
            raise ValueError(f"prototype_count must be >= 1, got {prototype_count}")
        pose_index = torch.as_tensor(list(pose_indices), dtype=torch.int64)
        if pose_index.numel() == 0:
            raise ValueError("HighFrequencyPrototypes needs pose_indices, got none")
        k, h, p, out = prototype_count, hidden_size, pose_index.numel(), 3 * vertex_count
        self.prototype_count = int(k)
        self.vertex_count = int(vertex_count)
        self.hidden_size = int(h)
        self.dropout = float(dropout)
        self.register_buffer("pose_indices", pose_index.to(device))
        # zeros where they are used (K = 20 at 7.7k vertices is 2 GB: made on the host and copied
        # over, assembling a model cost seconds); the weights come from from_mlps, cat or a checkpoint
        self.weight1 = nn.Parameter(torch.zeros(k, p, h, device=device))
        self.bias1 = nn.Parameter(torch.zeros(k, h, device=device))
        self.weight2 = nn.Parameter(torch.zeros(k, h, h, device=device))
        self.bias2 = nn.Parameter(torch.zeros(k, h, device=device))
        self.weight3 = nn.Parameter(torch.zeros(k * h, out, device=device))
        self.bias3 = nn.Parameter(torch.zeros(k, out, device=device))

    @property
    def config(self) -> dict[str, Any]:
        return {
            "prototype_count": self.prototype_count,
            "vertex_count": self.vertex_count,
            "pose_indices": self.pose_indices.tolist(),
            "hidden_size": self.hidden_size,
            "dropout": self.dropout,
        }

    @classmethod
    def from_mlps(cls, models: Sequence[DisplacementMLP]) -> HighFrequencyPrototypes:
        """Stack K trained pose-only :class:`DisplacementMLP`s (same inputs and width)."""
        if not models:
            raise ValueError("from_mlps needs at least one model, got 0")
        first = models[0]
        for i, m in enumerate(models):
            if (
                m.shape_components
                or m.style_components
                or not torch.equal(m.pose_indices.cpu(), first.pose_indices.cpu())
                or m.mlp.hidden_size != first.mlp.hidden_size
                or m.vertex_count != first.vertex_count
            ):
                raise ValueError(
                    f"prototype model {i} differs from model 0 in inputs, width or vertex count"
                )
        stacked = cls(
            len(models), first.vertex_count, first.pose_indices.tolist(), hidden_size=first.mlp.hidden_size,
            dropout=first.mlp.dropout,
        )
        layers = [(m.mlp.layers[0], m.mlp.layers[3], m.mlp.layers[5]) for m in models]
        with torch.no_grad():
            stacked.weight1.copy_(torch.stack([l1.weight.T for l1, _, _ in layers]))
            stacked.bias1.copy_(torch.stack([l1.bias for l1, _, _ in layers]))
            stacked.weight2.copy_(torch.stack([l2.weight.T for _, l2, _ in layers]))
            stacked.bias2.copy_(torch.stack([l2.bias for _, l2, _ in layers]))
            stacked.weight3.copy_(torch.cat([l3.weight.T for _, _, l3 in layers], dim=0))
            stacked.bias3.copy_(torch.stack([l3.bias for _, _, l3 in layers]))
        return stacked.to(first.pose_indices.device)

    @classmethod
    def cat(cls, parts: Sequence[HighFrequencyPrototypes]) -> HighFrequencyPrototypes:
        """The prototypes of ``parts`` (same inputs, width and vertex count) as one model, in
        order: parts trained by different processes (:func:`learn.tailornet.train.train_hf`'s
        ``part``) assembled."""
        if not parts:
            raise ValueError("cat needs at least one part, got 0")
        first = parts[0]
        for i, m in enumerate(parts):
            if (m.hidden_size, m.vertex_count, m.dropout) != (first.hidden_size, first.vertex_count, first.dropout) \
                    or not torch.equal(m.pose_indices.cpu(), first.pose_indices.cpu()):
                raise ValueError(f"prototype part {i} differs from part 0 in inputs, width, dropout or vertex count")
        joined = cls(sum(m.prototype_count for m in parts), first.vertex_count, first.pose_indices.tolist(),
                     hidden_size=first.hidden_size, dropout=first.dropout, device=first.weight1.device)
        with torch.no_grad():
            for name in ("weight1", "bias1", "weight2", "bias2", "weight3", "bias3"):
                getattr(joined, name).copy_(torch.cat([getattr(m, name) for m in parts], dim=0))
        return joined

    def _hidden(self, pose: torch.Tensor) -> torch.Tensor:
        x = pose[:, self.pose_indices]  # (B, P')
        h1 = torch.relu(torch.einsum("bp,kph->bkh", x, self.weight1) + self.bias1)  # (B, K, H)
        return torch.relu(torch.einsum("bkh,khj->bkj", h1, self.weight2) + self.bias2)  # (B, K, H)

    def forward(
        self, pose: torch.Tensor, weights: torch.Tensor, *, weight_floor: float = 0.0
    ) -> torch.Tensor:
        """Mixture sum_k w_k D_HF_k(pose): pose (B, P), weights (B, K) -> [m], (B, V, 3).

        Prototypes whose weight is <= ``weight_floor`` for every frame of the batch are
        skipped (their terms are dropped, an error of at most K x weight_floor x |D_HF|).
        TailorNet's kernel is narrow, so usually one or two of the K prototypes remain
        and the last layer, which dominates the cost, reads only their weights.
        """
        if weights.ndim != 2 or weights.shape[1] != self.prototype_count or weights.shape[0] != pose.shape[0]:
            raise ValueError(
                f"weights must have shape ({pose.shape[0]}, {self.prototype_count}), got "
                f"{tuple(weights.shape)}"
            )
        if weight_floor > 0.0:
            active = torch.nonzero((weights > weight_floor).any(dim=0)).reshape(-1).tolist()
            if len(active) < self.prototype_count:
                return self._forward_subset(pose, weights, active)
        h2 = self._hidden(pose)  # (B, K, H)
        mixed = (h2 * weights[..., None]).reshape(pose.shape[0], -1)  # (B, K H)
        out = mixed @ self.weight3 + weights @ self.bias3  # (B, 3V)
        return out.reshape(-1, self.vertex_count, 3)

    def _forward_subset(self, pose: torch.Tensor, weights: torch.Tensor, active: list[int]) -> torch.Tensor:
        x = pose[:, self.pose_indices]  # (B, P')
        h = self.hidden_size
        out = weights[:, active] @ self.bias3[active]  # (B, 3V)
        for k in active:  # a few prototypes: views of their weight slices, no copies
            h1 = torch.relu(x @ self.weight1[k] + self.bias1[k])  # (B, H)
            h2 = torch.relu(h1 @ self.weight2[k] + self.bias2[k])  # (B, H)
            out = out + (h2 * weights[:, k : k + 1]) @ self.weight3[k * h : (k + 1) * h]
        return out.reshape(-1, self.vertex_count, 3)

    def forward_each(self, pose: torch.Tensor) -> torch.Tensor:
        """Prototype k on its own poses: pose (K, b, P) -> [m], (K, b, V, 3).

        Dropout (p = ``dropout``) after the first hidden layer in train mode, as in
        :class:`learn.common.mlp.MLP`.
        """
        k = self.prototype_count
        if pose.ndim != 3 or pose.shape[0] != k:
            raise ValueError(f"pose must have shape ({k}, b, P), got {tuple(pose.shape)}")
        x = pose[..., self.pose_indices]  # (K, b, P')
        h1 = torch.relu(torch.baddbmm(self.bias1[:, None, :], x, self.weight1))  # (K, b, H)
        h1 = nn.functional.dropout(h1, p=self.dropout, training=self.training)
        h2 = torch.relu(torch.baddbmm(self.bias2[:, None, :], h1, self.weight2))  # (K, b, H)
        w3 = self.weight3.reshape(k, self.hidden_size, -1)  # (K, H, 3V)
        out = torch.baddbmm(self.bias3[:, None, :], h2, w3)  # (K, b, 3V)
        return out.reshape(k, pose.shape[1], self.vertex_count, 3)

    def forward_all(self, pose: torch.Tensor) -> torch.Tensor:
        """Every prototype's prediction: pose (B, P) -> [m], (B, K, V, 3)."""
        h2 = self._hidden(pose)  # (B, K, H)
        w3 = self.weight3.reshape(self.prototype_count, self.hidden_size, -1)  # (K, H, 3V)
        out = torch.einsum("bkh,kho->bko", h2, w3) + self.bias3  # (B, K, 3V)
        return out.reshape(pose.shape[0], self.prototype_count, self.vertex_count, 3)
