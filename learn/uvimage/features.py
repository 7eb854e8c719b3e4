"""Network inputs of the UV-image learner: joint rotation matrices, plus shape and style.

Seed 001 feeds 90 numbers: the 3 x 3 rotation matrices of 10 upper-body joints (root
fixed). Our pose is axis-angle per joint of :data:`simulate.body.base.POSE_JOINTS`; the
seed's skeleton (lower back, spine, spine1, neck, neck1, shoulders, arms, forearms)
maps to spine1-3, neck, collars, shoulders and elbows (:data:`UPPER_BODY_JOINTS`); the
head and wrists move no t-shirt vertex. Garments that are not tops use the joints their
skinning weights depend on (:func:`learn.tailornet.pose_mask.garment_pose_joints`),
root excluded.

Shape and style: a dataset that varies them (several style-shape pairs) gets them
appended to the rotations, each standardised by its training mean and standard
deviation (constant columns are dropped: std 0). The embedding already follows the body
shape (embedded points sit on the shaped body), so the shape input only carries how
the cloth hangs differently on another body; style changes the garment itself.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from simulate.body.base import POSE_JOINTS
from simulate.body.kinematics import axis_angle_to_matrix

#: The seed's 10 upper-body joints, as our pose joints.
UPPER_BODY_JOINTS: tuple[str, ...] = (
    "spine1", "spine2", "spine3", "neck", "left_collar", "right_collar",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
)
TOPS = ("tshirt", "shirt")


def input_joints(garment_type: str, skinning_weights: np.ndarray | None = None, *, parents: np.ndarray | None = None,
                 posable_joints: np.ndarray | None = None) -> list[str]:
    """Pose joints fed to the network: :data:`UPPER_BODY_JOINTS` for tops, else the
    posable joints (root excluded) that move the garment per its skinning weights."""
    if garment_type in TOPS:
        return list(UPPER_BODY_JOINTS)
    if skinning_weights is None:
        raise ValueError(f"garment type {garment_type!r} is not a top: its input joints come from its skinning "
                         "weights; pass skinning_weights")
    from learn.tailornet.pose_mask import garment_pose_joints

    moving = set(garment_pose_joints(skinning_weights, parents=parents).tolist())
    slots = np.arange(len(POSE_JOINTS)) if posable_joints is None else np.asarray(posable_joints)
    return [name for name, joint in zip(POSE_JOINTS, slots) if joint in moving and name != "pelvis"]


class PoseFeatures(torch.nn.Module):
    """(pose (B, 60) axis-angle [rad], shape (B, S), style (B, G)) -> features (B, 9 J + C).

    Args:
        joints: names of the pose joints whose rotation matrices are fed (J of them).
        shape_mean, shape_std: (S,) statistics of the training shapes, or None to leave
            shape out; columns with std 0 are dropped. style_mean, style_std: likewise (G,).
    """

    def __init__(self, joints: Sequence[str], *, shape_mean: np.ndarray | None = None,
                 shape_std: np.ndarray | None = None, style_mean: np.ndarray | None = None,
                 style_std: np.ndarray | None = None) -> None:
        super().__init__()
        unknown = [j for j in joints if j not in POSE_JOINTS]
        if unknown or not joints:
            raise ValueError(f"joints must be a non-empty list of {POSE_JOINTS}, got unknown {unknown}")
        self.joints = list(joints)
        self.register_buffer("slots", torch.as_tensor([POSE_JOINTS.index(j) for j in joints], dtype=torch.int64))
        self.conditions = []
        for name, mean, std in (("shape", shape_mean, shape_std), ("style", style_mean, style_std)):
            if mean is None:
                continue
            mean, std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
            columns = np.flatnonzero(std > 0)
            self.register_buffer(f"{name}_columns", torch.as_tensor(columns, dtype=torch.int64))
            self.register_buffer(f"{name}_mean", torch.as_tensor(mean[columns]))
            self.register_buffer(f"{name}_std", torch.as_tensor(std[columns]))
            self.conditions.append(name)
        self.size = 9 * len(self.joints) + sum(int(getattr(self, f"{n}_columns").numel()) for n in self.conditions)

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        rot = axis_angle_to_matrix(pose.reshape(pose.shape[0], -1, 3)[:, self.slots])  # (B, J, 3, 3)
        parts = [rot.reshape(pose.shape[0], -1)]
        for name, value in (("shape", shape), ("style", style)):
            if name in self.conditions:
                cols = getattr(self, f"{name}_columns")
                parts.append((value[:, cols] - getattr(self, f"{name}_mean")) / getattr(self, f"{name}_std"))
        return torch.cat(parts, 1)

    @classmethod
    def for_training(cls, joints: Sequence[str], shape: np.ndarray, style: np.ndarray, *, condition: str = "auto"
                     ) -> "PoseFeatures":
        """Features for training frames (shape (N, S), style (N, G)): ``condition`` "auto"
        appends shape and style when they vary over the frames, "none" never, "always"
        always (constant columns still dropped)."""
        if condition not in ("auto", "none", "always"):
            raise ValueError(f"condition must be 'auto', 'none' or 'always', got {condition!r}")
        stats = {}
        for name, value in (("shape", shape), ("style", style)):
            value = np.asarray(value, np.float64)
            std = value.std(0) if len(value) else np.zeros(value.shape[1:])
            std = np.where(std > 1e-8 * np.maximum(np.abs(value).max(0, initial=0.0), 1.0), std, 0.0)
            use = condition == "always" or (condition == "auto" and (std > 0).any())
            stats[name] = (value.mean(0), std) if use and value.shape[1] else (None, None)
        return cls(joints, shape_mean=stats["shape"][0], shape_std=stats["shape"][1],
                   style_mean=stats["style"][0], style_std=stats["style"][1])

    def config(self) -> dict:
        """What :meth:`from_config` needs (statistics travel in the state dict)."""
        return {"joints": self.joints, "conditions": {n: int(getattr(self, f"{n}_columns").numel()) for n in self.conditions}}

    @classmethod
    def from_config(cls, config: dict) -> "PoseFeatures":
        """An instance shaped like the saved one (load its state dict next)."""
        kwargs = {}
        for name, count in config["conditions"].items():
            kwargs[f"{name}_mean"] = np.zeros(count, np.float32)
            kwargs[f"{name}_std"] = np.ones(count, np.float32)
        return cls(config["joints"], **kwargs)
