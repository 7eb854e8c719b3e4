"""Learner registry: names used in configs and on the command line -> their functions.

Each entry gives ``fit(data, faces, *, run_dir, pose_indices, canonical_pose,
hyperparameters, fingerprint, device, seed, progress)`` returning the trained module,
the file name of the saved model inside the run directory, and ``load(path, *,
fingerprint, require_same_manifest, device)``. A learner that trains on another kind of data
than a drape dataset's frames (gcvae: a static set of rest-pose garments) also gives
``train_command(args)`` and ``evaluate_command(run_dir, data, *, device, out)``, which
``drape train`` and ``drape evaluate`` hand the command to.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from learn.gcvae.evaluate import run_command as evaluate_gcvae
from learn.gcvae.train import fit_gcvae, load_gcvae, run_command as train_gcvae
from learn.tailornet.train import fit_baseline, fit_tailornet, load_learner


@dataclass(frozen=True)
class LearnerEntry:
    name: str
    fit: Callable[..., object]
    model_file: str
    load: Callable[..., object]
    description: str
    train_command: Callable[..., int] | None = None
    evaluate_command: Callable[..., object] | None = None


LEARNERS: dict[str, LearnerEntry] = {
    "tailornet": LearnerEntry(
        "tailornet", fit_tailornet, "tailornet_model.pt", load_learner,
        "TailorNet mixture: low-frequency MLP + kernel mixture of prototype high-frequency MLPs",
    ),
    "baseline": LearnerEntry(
        "baseline", fit_baseline, "baseline_model.pt", load_learner,
        "TailorNet's baseline: one MLP of (pose, shape, style)",
    ),
    "gcvae": LearnerEntry(
        "gcvae", fit_gcvae, "gcvae_model.pt", load_gcvae,
        "CLOTH3D's GCVAE: offsets + mask on the body mesh, Chebyshev graph convolutions, segment-aware pooling",
        train_command=train_gcvae, evaluate_command=evaluate_gcvae,
    ),
}


def get_learner(name: str) -> LearnerEntry:
    """The registry entry for ``name``; unknown names raise listing the known ones."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; expected one of {sorted(LEARNERS)}")
    return LEARNERS[name]
