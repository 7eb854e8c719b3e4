"""Garment VAE of the canonical space with the self-supervised collision loss (seed 002, Sec. 4.4).

Encoder and decoder are MLPs over the flattened canonical garment (normalised by the training
mean and one scale). The loss (Eq. 13-16) is

    L1 reconstruction + lambda_lap L1 of the uniform-Laplacian difference
    + lambda_coll (max(eps - SDF(D(E(X))), 0) + max(eps - SDF(D(z)), 0)) + lambda_kl KL,

z ~ N(0, I) random latents: since every canonical garment sits on one constant body, decoded
random latents can be checked against that body's SDF without any ground truth, which is what
keeps the whole latent space (and so the regressor's outputs) out of the body.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import nn

from learn.collision_aware.sdf import collision_penalty

LATENT_SIZE = 25


class GarmentVAE(nn.Module):
    """VAE of canonical garments X [m] (B, V, 3) with a ``latent_size`` Gaussian latent.

    Args:
        vertex_count: V.
        mean: training mean garment [m], (V, 3) nested lists; scale: normalising scale [m].
        latent_size: 25 in seed 002.
        hidden_size: width of the two hidden layers of encoder and decoder.
    """

    def __init__(self, vertex_count: int, mean: list, scale: float, *, latent_size: int = LATENT_SIZE,
                 hidden_size: int = 512) -> None:
        super().__init__()
        if latent_size < 1 or hidden_size < 1 or vertex_count < 1:
            raise ValueError(f"GarmentVAE needs vertex_count, latent_size and hidden_size >= 1, got "
                             f"{vertex_count}, {latent_size}, {hidden_size}")
        if not scale > 0:
            raise ValueError(f"GarmentVAE scale must be > 0 m, got {scale}")
        self.config: dict[str, Any] = {"vertex_count": int(vertex_count), "scale": float(scale),
                                       "latent_size": int(latent_size), "hidden_size": int(hidden_size)}
        mean_t = torch.as_tensor(np.asarray(mean, np.float32)).reshape(vertex_count, 3)
        self.register_buffer("mean", mean_t)
        flat = 3 * int(vertex_count)
        self.encoder = nn.Sequential(nn.Linear(flat, hidden_size), nn.SiLU(), nn.Linear(hidden_size, hidden_size),
                                     nn.SiLU(), nn.Linear(hidden_size, 2 * latent_size))
        self.decoder = nn.Sequential(nn.Linear(latent_size, hidden_size), nn.SiLU(),
                                     nn.Linear(hidden_size, hidden_size), nn.SiLU(), nn.Linear(hidden_size, flat))

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> "GarmentVAE":
        return cls(config["vertex_count"], np.zeros((config["vertex_count"], 3)), config["scale"],
                   latent_size=config["latent_size"], hidden_size=config["hidden_size"])

    @property
    def latent_size(self) -> int:
        return self.config["latent_size"]

    def encode(self, canonical: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """X [m] (B, V, 3) -> mean and log-variance of the latent, (B, L) each."""
        flat = ((canonical - self.mean) / self.config["scale"]).flatten(1)  # (B, 3 V)
        mu, log_var = self.encoder(flat).chunk(2, dim=-1)
        return mu, log_var.clamp(-12.0, 8.0)

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """latent (B, L) -> X [m] (B, V, 3)."""
        return self.mean + self.config["scale"] * self.decoder(latent).unflatten(-1, (-1, 3))

    def forward(self, canonical: torch.Tensor, *, sample: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reconstruction [m] (B, V, 3), latent mean and log-variance (B, L)."""
        mu, log_var = self.encode(canonical)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * log_var) if sample else mu
        return self.decode(z), mu, log_var


RANDOM_LATENTS = ("prior", "batch")


def random_latents(mu: torch.Tensor, count: int, source: str) -> torch.Tensor:
    """``count`` latents (count, L) for the self-supervised collision term. ``prior``: z ~ N(0, I)
    (the seed's). ``batch``: z ~ N(m, diag(s^2)) with m, s the mean and standard deviation over the
    batch of its latent means ``mu`` (B, L), detached: where the encoder puts the data, and so the
    regressor's outputs. The two agree when the KL term holds the latents at N(0, I); a weak KL
    weight spreads them wider, and N(0, I) then samples only their middle."""
    z = torch.randn(count, mu.shape[-1], device=mu.device)
    if source == "prior":
        return z
    if source != "batch":
        raise ValueError(f"vae.random_latents must be one of {', '.join(RANDOM_LATENTS)}, got {source!r}")
    m = mu.detach()
    return m.mean(0) + z * (m.std(0, unbiased=False) if m.shape[0] > 1 else torch.ones_like(m[0]))


def vae_loss(vae: GarmentVAE, canonical: torch.Tensor, *, laplacian: torch.Tensor,
             sdf: Callable[[torch.Tensor], torch.Tensor], weights: dict[str, float], epsilon_m: float,
             random_samples: int, latents: str = "prior",
             posed: Callable[[torch.Tensor], torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
    """Terms of Eq. 13 on a batch X [m] (B, V, 3) and their weighted sum ``loss``.

    laplacian: uniform Laplacian, sparse (V, V); sdf: points (..., 3) -> signed distance (...);
    weights: ``laplacian``, ``collision``, ``kl`` (lambda_1..3) and ``random_collision``
    (the self-supervised term's weight relative to lambda_2; 0 turns it off);
    random_samples: latents decoded per batch for it, drawn as ``latents`` says
    (:func:`random_latents`: ``prior`` or ``batch``).
    posed: reconstructions (B, V, 3) -> the posed-space collision hinge [m] of the batch's frames
    (:class:`learn.collision_aware.posed_collision.PosedCollision` with their poses and shapes),
    added with weight ``weights["posed_collision"]``; None: the term is 0.
    Reconstruction, Laplacian and collision terms are in metres (L1 per vertex, mean over
    vertices and frames), KL in nats per frame.
    """
    reconstruction, mu, log_var = vae(canonical)
    rec = (reconstruction - canonical).abs().sum(-1).mean()
    b, v, _ = canonical.shape

    def lap(x: torch.Tensor) -> torch.Tensor:
        return torch.sparse.mm(laplacian, x.permute(1, 0, 2).reshape(v, -1)).reshape(v, x.shape[0], 3)

    lap_term = (lap(reconstruction) - lap(canonical)).abs().sum(-1).mean()
    kl = (-0.5 * (1 + log_var - mu ** 2 - log_var.exp()).sum(-1)).mean()
    collision = collision_penalty(sdf(reconstruction), epsilon_m).mean()
    terms = {"reconstruction": rec, "laplacian": lap_term, "kl": kl, "collision": collision}
    if random_samples > 0 and weights.get("random_collision", 1.0) > 0:
        z = random_latents(mu, random_samples, latents)
        terms["random_collision"] = collision_penalty(sdf(vae.decode(z)), epsilon_m).mean()
    else:
        terms["random_collision"] = torch.zeros((), device=canonical.device)
    terms["posed_collision"] = posed(reconstruction) if posed is not None else torch.zeros((), device=canonical.device)
    terms["loss"] = (rec + weights["laplacian"] * lap_term + weights["kl"] * kl
                     + weights["collision"] * (collision + weights.get("random_collision", 1.0) * terms["random_collision"])
                     + weights.get("posed_collision", 0.0) * terms["posed_collision"])
    return terms
