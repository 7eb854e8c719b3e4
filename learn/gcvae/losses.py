"""GCVAE loss (seed 004, Sec. 4.2): L = L_offsets + lambda_n L_normals + lambda_m L_mask
+ beta KL + lambda_c L_condition, and the KL warm-up schedule of beta.

- L_offsets: squared error of the normalised offsets, summed over xyz, averaged over the
  vertices of the ground-truth mask (off the mask an offset means nothing);
- L_normals: 1 - cos between predicted and true face normals of ``body + offsets``, averaged
  over the garment's faces (faces of its topology, standard or dual, with three masked
  vertices);
- L_mask: binary cross-entropy of the mask logits over all vertices, plus ``mask_iou_weight``
  times the soft IoU loss 1 - sum(p t) / sum(p + t - p t) per sample (p the mask probability,
  t the true mask): the mean BCE over all body vertices weighs the boundary of a small garment
  little (a skirt covers ~650 of 3,840 vertices), the IoU term weighs every garment's boundary
  by its own size, as the metric does;
- KL: of N(mu, sigma^2) from N(0, I), summed over the latent, averaged over the batch;
- L_condition: squared error of the condition regressed by the encoder (standardised).
The weights are in :data:`learn.gcvae.hyperparameters.LOSS`.
"""
from __future__ import annotations

import torch


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals (B, F, 3) of vertices (B, N, 3), faces (F, 3)."""
    tri = vertices[:, faces]
    n = torch.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def garment_faces(mask: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(B, F) bool: faces whose three vertices are in the mask (B, N)."""
    return mask[:, faces].all(-1)


def normal_cosines(pred: torch.Tensor, true: torch.Tensor, mask: torch.Tensor, dual: torch.Tensor,
                   faces: torch.Tensor, dual_faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """cos between predicted and true face normals and the garment-face selection, over the
    standard faces then the dual faces: (B, F + F_d) each; a sample's faces are those of its
    topology (``dual`` (B,) bool) with three vertices in the true ``mask``."""
    cos, sel = [], []
    for f, use in ((faces, ~dual), (dual_faces, dual)):
        cos.append((face_normals(pred, f) * face_normals(true, f)).sum(-1))
        sel.append(garment_faces(mask, f) & use[:, None])
    return torch.cat(cos, 1), torch.cat(sel, 1)


def soft_iou_loss(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """1 - soft IoU per sample (B,) of mask logits (B, N) against the true mask (B, N) bool."""
    p = torch.sigmoid(logits)
    t = mask.float()
    inter = (p * t).sum(-1)
    return 1.0 - inter / (p + t - p * t).sum(-1).clamp_min(1e-6)


def kl_divergence(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)) per sample (B,)."""
    return 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar).sum(-1)


def kl_weight(epoch: int, loss: dict) -> float:
    """beta at ``epoch`` (0-based): ``kl_start`` for ``kl_warmup_epochs``, then + ``kl_step``
    per epoch up to ``kl_max``."""
    if epoch < loss["kl_warmup_epochs"]:
        return float(loss["kl_start"])
    return float(min(loss["kl_max"], loss["kl_start"] + loss["kl_step"] * (epoch - loss["kl_warmup_epochs"] + 1)))


def gcvae_loss(model, out: dict, batch: dict, faces: torch.Tensor, dual_faces: torch.Tensor, loss: dict,
               beta: float) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and its terms (floats). ``batch``: body (B, N, 3), offsets (B, N, 3) [m],
    mask (B, N) bool, condition (B, C), dual (B,) bool."""
    mask = batch["mask"]
    m = mask.float()
    target = model.normalise_offsets(batch["offsets"])
    l_off = (((out["offsets"] - target) ** 2).sum(-1) * m).sum() / m.sum().clamp_min(1.0)
    pred_v = batch["body"] + model.offsets_from(out["offsets"])
    true_v = batch["body"] + batch["offsets"]
    cos, sel = normal_cosines(pred_v, true_v, mask, batch["dual"], faces, dual_faces)
    l_norm = ((1.0 - cos) * sel).sum() / sel.sum().clamp_min(1)
    l_mask = torch.nn.functional.binary_cross_entropy_with_logits(out["mask_logits"], m)
    l_iou = soft_iou_loss(out["mask_logits"], mask).mean()
    kl = kl_divergence(out["mu"], out["logvar"]).mean()
    c = (batch["condition"] - model.condition_mean) / model.condition_std
    l_cond = ((out["condition_regressed"] - c) ** 2).mean()
    total = (l_off + loss["normals_weight"] * l_norm + loss["mask_weight"] * l_mask
             + loss["mask_iou_weight"] * l_iou + beta * kl + loss["condition_weight"] * l_cond)
    return total, {"loss": float(total.detach()), "offsets": float(l_off.detach()), "normals": float(l_norm.detach()),
                   "mask": float(l_mask.detach()), "mask_iou": float(l_iou.detach()), "kl": float(kl.detach()),
                   "condition": float(l_cond.detach()),
                   "beta": beta}
