"""SMPL-family model files (SMPL, SMPL-H, SMPL-X) behind the :class:`BodyModel` interface.

The files are licensed by their owners: this project never downloads or ships them.
Users who hold a licence point ``body.path`` at their own ``.npz`` or ``.pkl`` file.
Keys read (the files' own names):

==================  ===========================  ==========================================
``v_template``      (V, 3)                       template vertices [m]
``f``               (F, 3)                       triangles
``shapedirs``       (V, 3, S_file)               shape blendshapes (first ``num_betas`` used)
``posedirs``        (V, 3, 9 (J-1)) or (3V, .)   pose-corrective blendshapes
``J_regressor``     (J, V) dense or sparse       joint regressor
``weights``         (V, J)                       skinning weights
``kintree_table``   (2, J)                       row 0 = parent ids (root's is -1 or 2^32-1)
==================  ===========================  ==========================================

Original SMPL ``.pkl`` files pickle chumpy arrays; they are read without chumpy by
mapping its classes to a shim that keeps the stored array. ``shape`` = the first
``num_betas`` (default 10) betas, range +-3 (standard deviations); ``pose`` uses SMPL's
own joints for :data:`POSE_JOINTS` (feet and hand joints fixed). SMPL's rest is a
T-pose; the canonical pose is an A-pose (shoulders lowered by 0.7 rad).
"""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import torch

from simulate.body.base import PARTS, POSE_JOINTS, BodyModel

#: SMPL skeleton index of each posable joint (identical in SMPL, SMPL-H and SMPL-X).
SMPL_POSE_JOINT_INDEX = {
    "pelvis": 0, "left_hip": 1, "right_hip": 2, "spine1": 3, "left_knee": 4, "right_knee": 5,
    "spine2": 6, "left_ankle": 7, "right_ankle": 8, "spine3": 9, "neck": 12, "left_collar": 13,
    "right_collar": 14, "head": 15, "left_shoulder": 16, "right_shoulder": 17, "left_elbow": 18,
    "right_elbow": 19, "left_wrist": 20, "right_wrist": 21,
}
# Body region of SMPL joints 0..21 (22+ are hand/face joints).
_SMPL_JOINT_PART = ["torso", "legs", "legs", "torso", "legs", "legs", "torso", "feet", "feet", "torso", "feet", "feet",
                    "torso", "torso", "torso", "head", "arms", "arms", "arms", "arms", "hands", "hands"]
REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table")


class _ChumpyShim:
    """Stands in for chumpy classes while unpickling; keeps the array in ``x``."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        self.__dict__.update(state if isinstance(state, dict) else {"x": state})


class _SMPLUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if module.startswith("chumpy"):
            return _ChumpyShim
        return super().find_class(module, name)


def _to_array(value, key: str, path: Path) -> np.ndarray:
    if isinstance(value, _ChumpyShim):
        value = value.__dict__.get("x", value.__dict__.get("r"))
    if hasattr(value, "toarray"):  # scipy sparse (J_regressor)
        value = value.toarray()
    try:
        return np.asarray(value)
    except Exception as exc:  # pragma: no cover - depends on foreign pickles
        raise ValueError(f"{path}: key {key!r} could not be read as an array ({exc})") from exc


def read_smpl_file(path: str | Path) -> dict[str, np.ndarray]:
    """Reads an SMPL-family model file into plain numpy arrays, validating keys and shapes."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"SMPL model file not found: {path} (body.path must name a .npz or .pkl file you hold)")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=True) as z:
            raw = {k: z[k] for k in z.files}
    elif path.suffix == ".pkl":
        try:
            with open(path, "rb") as fh:
                raw = _SMPLUnpickler(fh, encoding="latin1").load()
        except Exception as exc:
            raise ValueError(f"{path}: not a readable SMPL .pkl file ({exc})") from exc
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: expected a pickled dict of model arrays, got {type(raw).__name__}")
    else:
        raise ValueError(f"SMPL model file must end in .npz or .pkl, got {path.name!r}")
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise ValueError(f"{path}: missing keys {missing}; an SMPL-family file has {list(REQUIRED_KEYS)}")
    data = {k: _to_array(raw[k], k, path) for k in REQUIRED_KEYS}
    v = data["v_template"]
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{path}: v_template must have shape (V, 3), got {v.shape}")
    n_vert = v.shape[0]
    n_joint = data["kintree_table"].shape[-1]
    checks = {
        "f": (data["f"].ndim == 2 and data["f"].shape[1] == 3, "(F, 3)"),
        "shapedirs": (data["shapedirs"].ndim == 3 and data["shapedirs"].shape[:2] == (n_vert, 3), f"({n_vert}, 3, S)"),
        "J_regressor": (data["J_regressor"].shape == (n_joint, n_vert), f"({n_joint}, {n_vert})"),
        "weights": (data["weights"].shape == (n_vert, n_joint), f"({n_vert}, {n_joint})"),
        "kintree_table": (data["kintree_table"].shape == (2, n_joint), f"(2, {n_joint})"),
    }
    posedirs = data["posedirs"]
    if posedirs.ndim == 2 and posedirs.shape[0] == 3 * n_vert:
        posedirs = posedirs.reshape(n_vert, 3, -1)
    data["posedirs"] = posedirs
    checks["posedirs"] = (posedirs.shape == (n_vert, 3, 9 * (n_joint - 1)), f"({n_vert}, 3, {9 * (n_joint - 1)})")
    for key, (ok, expected) in checks.items():
        if not ok:
            raise ValueError(f"{path}: {key} must have shape {expected}, got {data[key].shape}")
    if n_joint < 22:
        raise ValueError(f"{path}: kintree_table has {n_joint} joints; SMPL-family models have at least 22 (body joints)")
    return data


class SMPLBody(BodyModel):
    """An SMPL/SMPL-H/SMPL-X model file; shape = betas, same pose convention as anny."""

    name = "smpl"

    def _copy_on(self, device: torch.device) -> "SMPLBody":
        return SMPLBody(self.path, num_betas=self.shape_size, device=device)

    def __init__(self, path: str | Path, *, num_betas: int = 10, device: str | torch.device = "cpu") -> None:
        data = read_smpl_file(path)
        self.path = Path(path)
        self.device = torch.device(device)
        n_file_betas = data["shapedirs"].shape[-1]
        if not 1 <= num_betas <= n_file_betas:
            raise ValueError(f"num_betas must be in [1, {n_file_betas}] for {self.path.name}, got {num_betas}")
        f32 = dict(dtype=torch.float32, device=self.device)
        self.v_template = torch.as_tensor(data["v_template"], **f32)
        self.shapedirs = torch.as_tensor(data["shapedirs"][..., :num_betas], **f32)  # (V, 3, S)
        self.posedirs = torch.as_tensor(data["posedirs"], **f32)  # (V, 3, 9(J-1))
        self.j_regressor = torch.as_tensor(data["J_regressor"], **f32)  # (J, V)
        parents = data["kintree_table"][0].astype(np.int64)
        parents[parents > 1_000_000] = -1
        parents[0] = -1
        if not all(0 <= parents[k] < k for k in range(1, len(parents))):
            raise ValueError(f"{self.path}: kintree_table parents must precede their children")
        self.faces = data["f"].astype(np.int64)
        self.joint_parents = parents
        self.joint_names = [f"joint{k}" for k in range(len(parents))]
        for name, k in SMPL_POSE_JOINT_INDEX.items():
            self.joint_names[k] = name
        self.pose_joint_indices = np.array([SMPL_POSE_JOINT_INDEX[j] for j in POSE_JOINTS])
        self.shape_names = [f"beta{k}" for k in range(num_betas)]
        self.shape_ranges = np.tile(np.array([[-3.0, 3.0]], dtype=np.float32), (num_betas, 1))
        self.shape_default = np.zeros(num_betas, dtype=np.float32)
        weights = torch.as_tensor(data["weights"], dtype=torch.float32)
        self.skinning_weights_t = weights / weights.sum(1, keepdim=True)
        joint_part = np.array([PARTS.index(_SMPL_JOINT_PART[k]) if k < 22 else PARTS.index("hands") for k in range(len(parents))])
        self.vertex_parts = joint_part[weights.argmax(1).numpy()]
        canonical = np.zeros((len(POSE_JOINTS), 3), dtype=np.float32)
        canonical[POSE_JOINTS.index("left_shoulder"), 2] = -0.7
        canonical[POSE_JOINTS.index("right_shoulder"), 2] = 0.7
        self.canonical_pose = canonical.reshape(-1)

    def _rest_torch(self, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        shape = shape.to(self.device)
        vertices = self.v_template + torch.einsum("vcs,bs->bvc", self.shapedirs, shape)  # (B, V, 3)
        joints = torch.einsum("jv,bvc->bjc", self.j_regressor, vertices)  # (B, J, 3)
        return vertices, joints

    def _pose_correctives(self, local_rotations: torch.Tensor) -> torch.Tensor:
        eye = torch.eye(3, dtype=local_rotations.dtype, device=local_rotations.device)
        feature = (local_rotations[:, 1:] - eye).flatten(1)  # (B, 9 (J-1))
        return torch.einsum("vcp,bp->bvc", self.posedirs, feature)
