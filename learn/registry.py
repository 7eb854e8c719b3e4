"""Learner registry: names used in configs and on the command line -> their functions.

Each ``LearnerEntry`` gives:

- ``fit(data, faces, *, run_dir, pose_indices, canonical_pose, hyperparameters, fingerprint,
  device, seed, progress, **extra)``: trains, saves and returns the module;
- ``model_file``: the file name of the saved model inside the run directory, and
  ``load(path, *, fingerprint, require_same_manifest, device)`` reading it back;
- ``stages``: the hyper-parameter stages whose epochs ``drape train --epochs`` sets;
- ``context``: ``None`` or ``context(*, reader, dataset, body, body_spec, template) -> dict``,
  the ``extra`` keyword arguments of ``fit``. ``drape train`` calls it with everything it has
  (the dataset's ``DatasetReader``, the training split's ``DrapeDataset``, the body model, its
  ``{"backend", "path"}`` and the shards' template arrays); each learner takes the keywords it
  needs (``**_`` for the others), so one callable covers arguments passed through and
  arguments computed from the dataset (the UV-image learners rebuild the full garment template);
- ``data``: the kind of data ``--data`` names for ``drape train`` and ``drape evaluate``.
  ``"dataset"``: a ``drape generate-dataset`` directory; ``fit`` and ``context`` as above, and
  ``drape evaluate`` / ``drape predict`` compare the learner's drapes with the simulated ones.
  ``"static_set"``: a ``drape static-set`` directory (rest-pose garments registered on the common
  body mesh, learn/gcvae/static_set.py); ``fit(data, *, run_dir, hyperparameters, device, seed,
  progress)`` takes its ``StaticSet``, ``context`` is not called, ``load``'s fingerprint is the
  set's (learn.gcvae.train.set_fingerprint), and ``drape evaluate`` reports learn/gcvae/evaluate.py's
  per-type reconstruction metrics (surface, normals, mask IoU, KL). gcvae's ``--data`` may also be
  a motion dataset: its dynamic variant (learn/gcvae/dynamic_set.py, ``drape train --dynamic``).
- ``streams``: whether ``fit`` takes a :class:`learn.streamed_split.StreamedSplit` for ``data``
  (``drape train --data-mode stream``, docs/streaming.md); ``context`` then gets ``dataset=None``.
- ``posed``: whether ``fit`` reads the training frames' posed garments (``posed_vertices``);
  ``drape train`` leaves them on disk for a learner of the unposed displacements alone (half of
  the split's bytes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from learn.collision_aware.train import EPOCH_STAGES as COLLISION_AWARE_STAGES
from learn.collision_aware.train import collision_aware_context, fit_collision_aware, load_collision_aware
from learn.gcvae.train import fit_gcvae, load_gcvae
from learn.tailornet.train import fit_baseline, fit_tailornet, load_learner
from learn.uvimage.garment import uvimage_context
from learn.uvimage.train import fit_uvimage, fit_uvimage_pca, load_uvimage

DATA_KINDS = ("dataset", "static_set")


@dataclass(frozen=True)
class LearnerEntry:
    name: str
    fit: Callable[..., object]
    model_file: str
    load: Callable[..., object]
    description: str
    stages: tuple[str, ...] = ()
    context: Callable[..., dict] | None = None
    data: str = "dataset"
    streams: bool = True
    posed: bool = True

    def __post_init__(self) -> None:
        if self.data not in DATA_KINDS:
            raise ValueError(f"learner {self.name}: data must be one of {DATA_KINDS}, got {self.data!r}")


LEARNERS: dict[str, LearnerEntry] = {
    "tailornet": LearnerEntry(
        "tailornet", fit_tailornet, "tailornet_model.pt", load_learner,
        "TailorNet mixture: low-frequency MLP + kernel mixture of prototype high-frequency MLPs",
        ("lf", "hf", "shape_style", "baseline"), posed=False,
    ),
    "baseline": LearnerEntry(
        "baseline", fit_baseline, "baseline_model.pt", load_learner,
        "TailorNet's baseline: one MLP of (pose, shape, style)",
        ("baseline",), posed=False,
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
    "collision_aware": LearnerEntry(
        "collision_aware", fit_collision_aware, "collision_aware_model.pt", load_collision_aware,
        "seed 002: diffused body fields, canonical space, garment VAE with self-supervised collisions, MLP regressor "
        "(GRU over the motion for motion datasets)",
        COLLISION_AWARE_STAGES, collision_aware_context, streams=False,
    ),
    "gcvae": LearnerEntry(
        "gcvae", fit_gcvae, "gcvae_model.pt", load_gcvae,
        "seed 004 (CLOTH3D): offsets + mask on the body mesh, Chebyshev graph convolutions, segment-aware pooling",
        ("train",), data="static_set",
    ),
}


def get_learner(name: str) -> LearnerEntry:
    """The registry entry for ``name`` (``-`` read as ``_``); unknown names raise listing the known ones."""
    key = name.replace("-", "_")
    if key not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; expected one of {sorted(LEARNERS)}")
    return LEARNERS[key]
