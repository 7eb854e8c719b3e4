"""Learner registry: names used in configs and on the command line -> their functions.

Each entry gives ``fit(data, faces, *, run_dir, pose_indices, canonical_pose,
hyperparameters, fingerprint, device, seed, progress, **context)`` returning the trained module,
the file name of the saved model inside the run directory, ``load(path, *,
fingerprint, require_same_manifest, device)``, the training stages whose epochs
``drape train --epochs`` sets, and optionally ``context(reader, body)``: further ``fit``
arguments taken from the dataset (the UV-image learners need the full garment template).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from learn.tailornet.train import fit_baseline, fit_tailornet, load_learner
from learn.uvimage.garment import uvimage_context
from learn.uvimage.train import fit_uvimage, fit_uvimage_pca, load_uvimage


@dataclass(frozen=True)
class LearnerEntry:
    name: str
    fit: Callable[..., object]
    model_file: str
    load: Callable[..., object]
    description: str
    stages: tuple[str, ...] = ()
    context: Callable[..., dict] | None = None


LEARNERS: dict[str, LearnerEntry] = {
    "tailornet": LearnerEntry(
        "tailornet", fit_tailornet, "tailornet_model.pt", load_learner,
        "TailorNet mixture: low-frequency MLP + kernel mixture of prototype high-frequency MLPs",
        ("lf", "hf", "shape_style", "baseline"),
    ),
    "baseline": LearnerEntry(
        "baseline", fit_baseline, "baseline_model.pt", load_learner,
        "TailorNet's baseline: one MLP of (pose, shape, style)",
        ("baseline",),
    ),
    "uvimage": LearnerEntry(
        "uvimage", fit_uvimage, "uvimage_model.pt", load_uvimage,
        "seed 001: cloth-pixel offsets as front/back UV images from a transposed-conv decoder of joint rotations",
        ("uvimage",), uvimage_context,
    ),
    "uvimage_pca": LearnerEntry(
        "uvimage_pca", fit_uvimage_pca, "uvimage_pca_model.pt", load_uvimage,
        "seed 001 appendix E.3: an MLP predicting 128 PCA coefficients of the cloth-pixel offsets",
        ("uvimage_pca",), uvimage_context,
    ),
}


def get_learner(name: str) -> LearnerEntry:
    """The registry entry for ``name``; unknown names raise listing the known ones."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; expected one of {sorted(LEARNERS)}")
    return LEARNERS[name]
