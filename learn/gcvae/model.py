"""The static GCVAE (seed 004, Sec. 4.2, Fig. 4c): a conditional VAE whose encoder and decoder
are Chebyshev graph convolutions over the common body mesh and its segment-aware pooling
hierarchy.

Input per vertex (7 channels): the normalised body vertex (3), the normalised offset (3) and
the mask bit (1); condition c = (shape (6), tightness (1)), standardised.

- Encoder: per level a ChebConv to that level's width and a residual block (two ChebConvs,
  skip connection), max-pool to the next level; at the last level (one vertex per segment)
  the features are flattened into an FC layer, from which mu, log sigma^2 (latent) and the
  regressed condition (the seed's MLP branch that factors c out of z) are read.
- Decoder: [z, MLP(c)] -> FC -> one vertex per segment; per level copy-unpool, concatenate
  the body vertices average-pooled to that level (a skip from the condition: the body of the
  shape is known when sampling), ChebConv and a residual block; two heads at the full mesh:
  offsets (3, normalised) and mask logits (1).

The seed's conditioning network is a separately trained auto-encoder of c whose middle layer
feeds the VAE; with 7 condition values an MLP trained with the VAE does that job here.
Normalisation (per-vertex offset mean, one offset scale, body mean/scale, condition mean/std)
is fitted on the training set and stored as buffers.
"""
from __future__ import annotations

import numpy as np
import torch

from learn.gcvae.chebyshev import ChebConv, scaled_laplacian, torch_sparse
from learn.gcvae.pooling import build_hierarchy, cluster_members, copy_unpool, max_pool

INPUT_CHANNELS = 7


class ResidualBlock(torch.nn.Module):
    """x + ChebConv(ELU(ChebConv(x)))."""

    def __init__(self, channels: int, order: int) -> None:
        super().__init__()
        self.a = ChebConv(channels, channels, order)
        self.b = ChebConv(channels, channels, order)

    def forward(self, x: torch.Tensor, laplacian: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.elu(x + self.b(torch.nn.functional.elu(self.a(x, laplacian)), laplacian))


class GCVAE(torch.nn.Module):
    """Static GCVAE on a graph of N vertices.

    Args:
        edges: graph edges (E, 2) of the full mesh; positions (N, 3) [m] (pooling clusters);
        segments (N,); condition_size: length of c; model: the ``model`` hyper-parameters.
    """

    def __init__(self, edges: np.ndarray, positions: np.ndarray, segments: np.ndarray, condition_size: int,
                 model: dict) -> None:
        super().__init__()
        self.config = dict(model)
        order, channels, latent = int(model["chebyshev_order"]), list(model["channels"]), int(model["latent_size"])
        hierarchy = build_hierarchy(positions, edges, segments, factor=float(model["pool_factor"]),
                                    levels=int(model["pool_levels"]))
        sizes = [len(positions)] + [lv.size for lv in hierarchy]
        self.sizes = sizes
        laps = [scaled_laplacian(edges, sizes[0])] + [scaled_laplacian(lv.edges, lv.size) for lv in hierarchy]
        for i, lap in enumerate(laps):
            self.register_buffer(f"laplacian_{i}", torch_sparse(lap), persistent=False)
        for i, lv in enumerate(hierarchy):
            self.register_buffer(f"assignment_{i}", torch.as_tensor(lv.assignment), persistent=False)
            self.register_buffer(f"members_{i}", torch.as_tensor(cluster_members(lv.assignment, lv.size)),
                                 persistent=False)
            self.register_buffer(f"counts_{i}", torch.as_tensor(np.bincount(lv.assignment, minlength=lv.size),
                                                                dtype=torch.float32), persistent=False)
        levels = len(hierarchy)
        self.levels = levels
        self.enc_in = torch.nn.ModuleList([ChebConv(INPUT_CHANNELS if i == 0 else channels[i - 1], channels[i], order)
                                           for i in range(levels + 1)])
        self.enc_res = torch.nn.ModuleList([ResidualBlock(channels[i], order) for i in range(levels + 1)])
        flat = sizes[-1] * channels[-1]
        hidden = 4 * latent
        self.enc_fc = torch.nn.Linear(flat, hidden)
        self.mu = torch.nn.Linear(hidden, latent)
        self.logvar = torch.nn.Linear(hidden, latent)
        self.regressor = torch.nn.Sequential(torch.nn.Linear(hidden, hidden), torch.nn.ELU(),
                                             torch.nn.Linear(hidden, condition_size))
        ch = int(model["condition_hidden"])
        self.condition = torch.nn.Sequential(torch.nn.Linear(condition_size, ch), torch.nn.ELU(), torch.nn.Linear(ch, ch))
        self.dec_fc = torch.nn.Linear(latent + ch, flat)
        self.dec_in = torch.nn.ModuleList([ChebConv(channels[i + 1 if i < levels else i] + 3, channels[i], order)
                                           for i in range(levels + 1)])
        self.dec_res = torch.nn.ModuleList([ResidualBlock(channels[i], order) for i in range(levels + 1)])
        self.offset_head = ChebConv(channels[0], 3, order)
        self.mask_head = ChebConv(channels[0], 1, order)
        n = sizes[0]
        for name, shape in (("offset_mean", (n, 3)), ("offset_scale", ()), ("body_mean", (3,)), ("body_scale", ()),
                            ("condition_mean", (condition_size,)), ("condition_std", (condition_size,))):
            self.register_buffer(name, torch.zeros(shape) if "mean" in name else torch.ones(shape))
        self.latent_size = latent
        self.channels = channels

    # ------------------------------------------------------------------ normalisation
    def fit_normalisation(self, body: np.ndarray, offsets: np.ndarray, mask: np.ndarray, condition: np.ndarray) -> None:
        """Statistics of the training set: body (M, N, 3), offsets (M, N, 3) [m], mask (M, N), condition (M, C)."""
        m = mask.astype(np.float64)[..., None]
        count = m.sum(0)
        mean = np.where(count > 0, (offsets * m).sum(0) / np.maximum(count, 1), 0.0)
        scale = np.sqrt((((offsets - mean) ** 2) * m).sum() / max(3 * m.sum(), 1))
        self.offset_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        self.offset_scale.fill_(float(max(scale, 1e-4)))
        self.body_mean.copy_(torch.as_tensor(body.reshape(-1, 3).mean(0), dtype=torch.float32))
        self.body_scale.fill_(float(body.reshape(-1, 3).std()))
        self.condition_mean.copy_(torch.as_tensor(condition.mean(0), dtype=torch.float32))
        # a value constant over the training set (anny's age; a joint no motion moves) is centred
        # only: dividing by its ~0 spread would blow up any other value given when sampling
        std = condition.std(0)
        self.condition_std.copy_(torch.as_tensor(np.where(std < 1e-3, 1.0, std), dtype=torch.float32))

    def normalise_offsets(self, offsets: torch.Tensor) -> torch.Tensor:
        return (offsets - self.offset_mean) / self.offset_scale

    def offsets_from(self, normalised: torch.Tensor) -> torch.Tensor:
        """Offsets [m] (B, N, 3) of normalised network output."""
        return normalised * self.offset_scale + self.offset_mean

    # ------------------------------------------------------------------ network
    def _lap(self, level: int) -> torch.Tensor:
        return getattr(self, f"laplacian_{level}")

    def _body_levels(self, body: torch.Tensor) -> list[torch.Tensor]:
        """Normalised body vertices (B, N, 3) average-pooled to every level, vertex-major (N_l, B, 3)."""
        x = ((body - self.body_mean) / self.body_scale).transpose(0, 1)
        out = [x]
        for i in range(self.levels):
            a = getattr(self, f"assignment_{i}")
            pooled = x.new_zeros(self.sizes[i + 1], x.shape[1], 3).index_add_(0, a, x)
            x = pooled / getattr(self, f"counts_{i}")[:, None, None]
            out.append(x)
        return out

    def encode(self, body: torch.Tensor, offsets: torch.Tensor, mask: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(mu, logvar) (B, Z) and the regressed standardised condition (B, C)."""
        x = torch.cat([(body - self.body_mean) / self.body_scale, self.normalise_offsets(offsets) * mask[..., None],
                       mask[..., None].float()], dim=-1).transpose(0, 1)
        for i in range(self.levels + 1):
            x = torch.nn.functional.elu(self.enc_in[i](x, self._lap(i)))
            x = self.enc_res[i](x, self._lap(i))
            if i < self.levels:
                x = max_pool(x, getattr(self, f"members_{i}"))
        h = torch.nn.functional.elu(self.enc_fc(x.transpose(0, 1).flatten(1)))
        return self.mu(h), self.logvar(h).clamp(-12.0, 8.0), self.regressor(h)

    def decode(self, z: torch.Tensor, condition: torch.Tensor, body: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised offsets (B, N, 3) and mask logits (B, N) of latent z (B, Z), raw
        condition (B, C) and body vertices (B, N, 3) [m]."""
        c = (condition - self.condition_mean) / self.condition_std
        bodies = self._body_levels(body)
        x = torch.nn.functional.elu(self.dec_fc(torch.cat([z, self.condition(c)], -1)))
        x = x.view(z.shape[0], self.sizes[-1], self.channels[-1]).transpose(0, 1)
        for i in range(self.levels, -1, -1):
            if i < self.levels:
                x = copy_unpool(x, getattr(self, f"assignment_{i}"))
            x = torch.nn.functional.elu(self.dec_in[i](torch.cat([x, bodies[i]], -1), self._lap(i)))
            x = self.dec_res[i](x, self._lap(i))
        return self.offset_head(x, self._lap(0)).transpose(0, 1), self.mask_head(x, self._lap(0))[..., 0].transpose(0, 1)

    def forward(self, body: torch.Tensor, offsets: torch.Tensor, mask: torch.Tensor, condition: torch.Tensor, *,
                sample: bool = True) -> dict[str, torch.Tensor]:
        """Reconstruction of a batch: {offsets (normalised), mask_logits, mu, logvar, condition_regressed}."""
        mu, logvar, regressed = self.encode(body, offsets, mask)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
        out, logits = self.decode(z, condition, body)
        return {"offsets": out, "mask_logits": logits, "mu": mu, "logvar": logvar, "condition_regressed": regressed}
