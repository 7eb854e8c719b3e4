"""GCVAE metrics (seed 004, Sec. 5.1), per garment type and averaged over types:

- ``surface_mm``: mean Euclidean distance [mm] between reconstructed and true garment
  vertices over the true mask (the seed's "standard L2-norm": prediction and input share the
  body mesh's vertices and order);
- ``normal_rad``: mean angle [rad] between reconstructed and true face normals over the
  garment's faces (true mask, the type's topology);
- ``mask_iou``: intersection over union of the predicted mask (p > 0.5) and the true one;
- ``kl``: KL divergence of the posterior from N(0, I) [nats], summed over the latent.

Reconstruction encodes each sample and decodes the posterior mean (z = mu), as the seed
reports its ablations. ``registration`` adds the static set's registration error per type
(the floor under ``surface_mm``: what the representation itself loses).
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from learn.gcvae.losses import kl_divergence, normal_cosines
from learn.gcvae.model import GCVAE
from learn.gcvae.static_set import StaticSet
from learn.gcvae.train import surface_error_m, tensors

METRICS = ("surface_mm", "normal_rad", "mask_iou", "kl")
#: Seed 004, Table 3b (full model, static set): surface mm, normal rad, mask IoU, KL.
SEED_TABLE_3B: dict[str, tuple[float, float, float, float]] = {
    "top": (12.4, 1.19, 0.9038, 0.9229), "t-shirt": (15.9, 1.20, 0.9569, 1.1380),
    "trousers": (11.4, 0.82, 0.9475, 0.8728), "skirt": (21.3, 0.79, 0.9518, 0.9952),
    "jumpsuit": (13.8, 1.04, 0.9638, 0.8543), "dress": (16.8, 1.05, 0.9665, 0.9737),
}
#: Seed 004, Table 3a (all types): surface mm, normal rad, mask IoU, KL.
SEED_TABLE_3A_ALL = (14.7, 1.02, 0.9522, 0.9414)
#: Seed 004, Table 4 (DVAE, dynamic set): {frames: {type: (surface mm, normal rad)}}.
SEED_TABLE_4: dict[int, dict[str, tuple[float, float]]] = {
    1: {"top": (22.3, 1.22), "tshirt": (29.5, 1.29), "pants": (21.0, 0.88), "skirt": (37.6, 0.91),
        "jumpsuit": (29.6, 1.10), "dress": (35.5, 1.13), "average": (29.3, 1.09)},
    4: {"top": (20.3, 1.22), "tshirt": (28.1, 1.28), "pants": (18.7, 0.87), "skirt": (33.2, 0.88),
        "jumpsuit": (26.3, 1.09), "dress": (32.3, 1.11), "average": (26.4, 1.08)},
}
#: Our CLOTH3D type names -> the seed's (Table 4 rows).
SEED_TYPE_NAMES = {"top": "Top", "tshirt": "T-shirt", "pants": "Trousers", "skirt": "Skirt", "jumpsuit": "Jumpsuit",
                   "dress": "Dress", "average": "Avg."}


@torch.no_grad()
def sample_metrics(model: GCVAE, data: StaticSet, index: np.ndarray, *, device: str = "cpu",
                   batch_size: int = 32) -> dict[str, np.ndarray]:
    """Per-sample metrics (arrays (M,)) of the samples ``index``."""
    model = model.to(device).eval()
    faces = torch.as_tensor(data.mesh.faces, device=device)
    dual_faces = torch.as_tensor(data.mesh.dual_faces, device=device)
    out: dict[str, list] = {k: [] for k in METRICS}
    for start in range(0, len(index), batch_size):
        b = tensors(data, index[start:start + batch_size], device)
        r = model(b["body"], b["offsets"], b["mask"], b["condition"], sample=False)
        out["surface_mm"].append(1e3 * surface_error_m(model, r, b))
        pred_v = b["body"] + model.offsets_from(r["offsets"])
        cos, sel = normal_cosines(pred_v, b["body"] + b["offsets"], b["mask"], b["dual"], faces, dual_faces)
        angle = torch.arccos(cos.clamp(-1.0, 1.0))
        out["normal_rad"].append((angle * sel).sum(1) / sel.sum(1).clamp_min(1))
        pred_mask = r["mask_logits"] > 0
        inter = (pred_mask & b["mask"]).sum(1).float()
        union = (pred_mask | b["mask"]).sum(1).float()
        out["mask_iou"].append(torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union)))
        out["kl"].append(kl_divergence(r["mu"], r["logvar"]))
    return {k: torch.cat(v).cpu().numpy().astype(np.float64) for k, v in out.items()}


def evaluate_set(model: GCVAE, data: StaticSet, *, splits: tuple[str, ...] = ("test",), device: str = "cpu"
                 ) -> dict[str, Any]:
    """{split: {"types": {type: metrics}, "average_over_types": metrics, "samples": M}} plus
    ``registration`` (per type, mm) and ``timing`` (ms per sample, batch 32, reconstruction)."""
    report: dict[str, Any] = {"splits": {}}
    for split in splits:
        index = data.indices(split)
        if len(index) == 0:
            raise ValueError(f"the static set has no samples in its {split} split")
        per = sample_metrics(model, data, index, device=device)
        types = {}
        for ti, name in enumerate(data.types):
            sel = data.type[index] == ti
            if sel.any():
                types[name] = {k: float(per[k][sel].mean()) for k in METRICS} | {"samples": int(sel.sum())}
        report["splits"][split] = {
            "types": types, "samples": int(len(index)),
            "average_over_types": {k: float(np.mean([t[k] for t in types.values()])) for k in METRICS},
        }
    report["registration"] = data.registration_table()
    index = data.indices(splits[0])[:32]
    b = tensors(data, index, device)
    with torch.no_grad():
        for _ in range(2):
            model(b["body"], b["offsets"], b["mask"], b["condition"], sample=False)
        if str(device).startswith("cuda"):
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        model(b["body"], b["offsets"], b["mask"], b["condition"], sample=False)
        if str(device).startswith("cuda"):
            torch.cuda.synchronize(device)
    report["timing"] = {"device": str(device), "ms_per_sample_batch": 1e3 * (time.perf_counter() - t0) / len(index),
                        "batch": int(len(index))}
    return report


def format_dynamic_table(report: dict[str, Any], frames: int) -> str:
    """Per-type table of a dynamic run (T = ``frames`` poses per condition) with the seed's
    Table 4 (surface mm / normal rad for 1 and 4 frames) beside each type."""
    lines = []
    for split, r in report["splits"].items():
        lines.append(f"{split} split ({r['samples']} frames), dynamic, {frames} frame(s) of poses per condition")
        lines.append(f"{'type':<10}{'surface mm':>11}{'normal rad':>11}{'mask IoU':>10}{'KL':>9}{'reg. mm':>9}"
                     f"   seed Table 4 (mm / rad): 1 frame, 4 frames")
        rows = list(r["types"].items()) + [("average", r["average_over_types"])]
        for name, m in rows:
            reg = report["registration"].get(name, {}).get("garment_to_registered_mm", float("nan"))
            seed = "   " + ", ".join(f"{SEED_TABLE_4[k][name][0]:.1f} / {SEED_TABLE_4[k][name][1]:.2f}"
                                     if name in SEED_TABLE_4[k] else "-" for k in (1, 4))
            seed += f" ({SEED_TYPE_NAMES[name]})" if name in SEED_TYPE_NAMES else ""
            reg_s = f"{reg:>9.2f}" if name != "average" else " " * 9
            lines.append(f"{name:<10}{m['surface_mm']:>11.2f}{m['normal_rad']:>11.3f}{m['mask_iou']:>10.4f}"
                         f"{m['kl']:>9.3f}{reg_s}{seed}")
    for s in report.get("skipped", []):
        lines.append(f"skipped: {s['type']} {s['task_id']} (registration {s['registration_mm']:.1f} mm: "
                     f"not on the body)")
    return "\n".join(lines)


def format_table(report: dict[str, Any]) -> str:
    """Per-type table of every split with the registration error and the seed's Table 3."""
    lines = []
    for split, r in report["splits"].items():
        lines.append(f"{split} split ({r['samples']} samples)")
        lines.append(f"{'type':<10}{'surface mm':>11}{'normal rad':>11}{'mask IoU':>10}{'KL':>9}{'reg. mm':>9}")
        for name, m in r["types"].items():
            reg = report["registration"].get(name, {}).get("garment_to_registered_mm", float("nan"))
            lines.append(f"{name:<10}{m['surface_mm']:>11.2f}{m['normal_rad']:>11.3f}{m['mask_iou']:>10.4f}"
                         f"{m['kl']:>9.3f}{reg:>9.2f}")
        a = r["average_over_types"]
        lines.append(f"{'average':<10}{a['surface_mm']:>11.2f}{a['normal_rad']:>11.3f}{a['mask_iou']:>10.4f}"
                     f"{a['kl']:>9.3f}")
    s = SEED_TABLE_3A_ALL
    lines.append(f"{'seed 3a':<10}{s[0]:>11.2f}{s[1]:>11.3f}{s[2]:>10.4f}{s[3]:>9.3f}   (CLOTH3D, all types)")
    return "\n".join(lines)

