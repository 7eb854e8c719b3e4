"""The default body: NAVER's anny (Apache-2.0, pip ``anny``), which ships its data.

``shape`` = anny's six phenotype parameters, each in [0, 1] (0.5 is the neutral
value anny uses as its default):

==============  ======================================================
gender          0 female ... 1 male
age             0 youngest ... 1 oldest anny blends (0.5 is a young adult)
muscle          0 least ... 1 most muscular
weight          0 lightest ... 1 heaviest
height          0 shortest ... 1 tallest
proportions     0 ... 1 anny's "ideal proportions" blend
==============  ======================================================

``pose`` = axis-angle rotations of the 20 joints of :data:`simulate.body.base.POSE_JOINTS`,
mapped to anny bones by :data:`ANNY_POSE_BONES` (fingers, toes, face, eyes and anny's
twist bones are fixed; twist bones follow their parent rigidly). anny's rest posture
is an A-pose, so ``pose = 0`` is the canonical A-pose.

anny works in z-up coordinates; this backend converts to the project frame (y up,
facing +z, left +x). The first construction on a fresh machine builds anny's cache
(tens of seconds); later constructions take about a second.
"""
from __future__ import annotations

import os
import time
import warnings
from functools import lru_cache

import numpy as np
import torch

from simulate.body.base import PARTS, POSE_JOINTS, BodyModel

#: anny bone driven by each posable joint, in POSE_JOINTS order.
ANNY_POSE_BONES: dict[str, str] = {
    "pelvis": "root", "left_hip": "upperleg01.L", "right_hip": "upperleg01.R", "spine1": "spine04",
    "left_knee": "lowerleg01.L", "right_knee": "lowerleg01.R", "spine2": "spine02",
    "left_ankle": "foot.L", "right_ankle": "foot.R", "spine3": "spine01", "neck": "neck01",
    "left_collar": "clavicle.L", "right_collar": "clavicle.R", "head": "head",
    "left_shoulder": "upperarm01.L", "right_shoulder": "upperarm01.R",
    "left_elbow": "lowerarm01.L", "right_elbow": "lowerarm01.R",
    "left_wrist": "wrist.L", "right_wrist": "wrist.R",
}

ANNY_SHAPE_NAMES = ["gender", "age", "muscle", "weight", "height", "proportions"]

# z-up (anny) -> y-up (project): (x, y, z) -> (x, z, -y)
_ZUP_TO_YUP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _bone_part(label: str) -> str:
    """Body region of an anny bone label."""
    base = label.split(".")[0]
    if base.startswith(("finger", "metacarpal", "wrist")):
        return "hands"
    if base.startswith(("foot", "toe")):
        return "feet"
    if base.startswith(("upperarm", "lowerarm")):
        return "arms"
    if base.startswith(("upperleg", "lowerleg")):
        return "legs"
    if base.startswith(("neck02", "neck03", "head", "eye", "jaw", "tongue")):
        return "head"
    return "torso"  # root, pelvis, spine, clavicle, shoulder blade, lower neck


class AnnyBody(BodyModel):
    """anny full-body model behind the :class:`BodyModel` interface.

    Attributes (beyond BodyModel): ``load_seconds`` (construction wall time) and
    ``anny_model`` (the underlying ``anny.Anny`` torch module, float32).
    """

    name = "anny"

    def _copy_on(self, device: torch.device) -> "AnnyBody":
        return anny_on(str(device))

    def __init__(self, *, device: str | torch.device = "cpu") -> None:
        start = time.perf_counter()
        os.environ.setdefault("TQDM_DISABLE", "1")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import anny

            model = anny.Anny()
        self.anny_model = model.to(dtype=torch.float32, device=device)
        self.device = torch.device(device)
        self.faces = model.faces.cpu().numpy().astype(np.int64)
        self.joint_names = list(model.bone_labels)
        self.joint_parents = np.asarray(model.bone_parents, dtype=np.int64)
        self.pose_joint_indices = np.array([self.joint_names.index(ANNY_POSE_BONES[j]) for j in POSE_JOINTS])
        self.shape_names = list(ANNY_SHAPE_NAMES)
        if list(model.phenotype_labels) != self.shape_names:
            raise RuntimeError(f"anny phenotype labels changed: {model.phenotype_labels}; expected {self.shape_names}")
        self.shape_ranges = np.tile(np.array([[0.0, 1.0]], dtype=np.float32), (len(self.shape_names), 1))
        self.shape_default = np.full(len(self.shape_names), 0.5, dtype=np.float32)
        weights = torch.zeros(model.vertex_bone_weights.shape[0], len(self.joint_names), dtype=torch.float32)
        weights.scatter_add_(1, model.vertex_bone_indices.long().cpu(), model.vertex_bone_weights.float().cpu())
        weights /= weights.sum(1, keepdim=True)
        self.skinning_weights_t = weights
        part_of_bone = np.array([PARTS.index(_bone_part(b)) for b in self.joint_names])
        self.vertex_parts = part_of_bone[weights.argmax(1).numpy()]
        self.canonical_pose = np.zeros(3 * len(POSE_JOINTS), dtype=np.float32)
        self._no_extra = torch.zeros(1, 0, device=self.device)
        self.load_seconds = time.perf_counter() - start

    def _rest_torch(self, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        shape = shape.to(self.device)
        batch = shape.shape[0]
        extra = self._no_extra.expand(batch, 0)
        model = self.anny_model
        coeffs = model._get_phenotype_blendshape_coefficients(shape, extra, extra)
        # the rest vertices and bone heads by the expressions anny's get_rest_model uses for them
        # (the same bits), without the rest bone orientations it also makes and nothing here reads
        # (a batched SVD per call: most of a one-shape blend on a GPU, and a dataset blends one
        # shape at a time, thousands of them in a motion run's shape transitions)
        vertices = model.get_rest_vertices(coeffs)
        heads = _anny_skinning().apply_linear_blendshape(model.template_bone_heads, model.bone_heads_blendshapes, coeffs)
        rot = _ZUP_TO_YUP.to(shape.device)
        return vertices @ rot.T, heads @ rot.T  # (B, V, 3), (B, J, 3)


def _anny_skinning():
    """anny's skinning module (``apply_linear_blendshape``, which its rest models use)."""
    import anny.skinning.skinning as skinning

    return skinning


@lru_cache(maxsize=4)
def anny_on(device: str) -> AnnyBody:
    """The anny body on a torch device, built once per device (a build takes seconds)."""
    return AnnyBody(device=device)
