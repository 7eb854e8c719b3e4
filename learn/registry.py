"""Learner registry: names used in configs and on the command line -> their functions.

Each entry gives ``fit(data, faces, *, run_dir, pose_indices, canonical_pose,
hyperparameters, fingerprint, device, seed, progress)`` returning the trained module,
the file name of the saved model inside the run directory, and ``load(path, *,
fingerprint, require_same_manifest, device)``. ``context`` names further keyword
arguments ``fit`` takes from the training command (``body``, ``body_spec``, ``template``,
``dataset``), and ``epoch_stages`` the hyper-parameter stages ``--epochs`` sets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from learn.collision_aware.train import EPOCH_STAGES as COLLISION_AWARE_EPOCH_STAGES
from learn.collision_aware.train import fit_collision_aware, load_collision_aware
from learn.tailornet.train import fit_baseline, fit_tailornet, load_learner


@dataclass(frozen=True)
class LearnerEntry:
    name: str
    fit: Callable[..., object]
    model_file: str
    load: Callable[..., object]
    description: str
    context: tuple[str, ...] = ()
    epoch_stages: tuple[str, ...] = ("lf", "hf", "shape_style", "baseline")


LEARNERS: dict[str, LearnerEntry] = {
    "tailornet": LearnerEntry(
        "tailornet", fit_tailornet, "tailornet_model.pt", load_learner,
        "TailorNet mixture: low-frequency MLP + kernel mixture of prototype high-frequency MLPs",
    ),
    "baseline": LearnerEntry(
        "baseline", fit_baseline, "baseline_model.pt", load_learner,
        "TailorNet's baseline: one MLP of (pose, shape, style)",
    ),
    "collision_aware": LearnerEntry(
        "collision_aware", fit_collision_aware, "collision_aware_model.pt", load_collision_aware,
        "seed 002: diffused body fields, canonical space, garment VAE with self-supervised collisions, MLP regressor",
        context=("body", "body_spec", "template", "dataset"), epoch_stages=COLLISION_AWARE_EPOCH_STAGES,
    ),
}


def get_learner(name: str) -> LearnerEntry:
    """The registry entry for ``name`` (``-`` read as ``_``); unknown names raise listing the known ones."""
    name = name.replace("-", "_")
    if name not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; expected one of {sorted(LEARNERS)}")
    return LEARNERS[name]
