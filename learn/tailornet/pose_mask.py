"""Restrict the pose input to the joints that move the garment.

TailorNet feeds only the joints that influence the garment (a t-shirt ignores the
ankles). We derive them from the garment template's skinning weights: a joint is kept
when its weight summed over garment vertices exceeds ``min_weight_sum`` (in units of
"fully attached vertices"), and every ancestor of a kept joint is kept too, since a
parent's rotation moves the child's vertices.
"""

from __future__ import annotations

import numpy as np

DEFAULT_MIN_WEIGHT_SUM = 1.0


def garment_pose_joints(
    skinning_weights: np.ndarray,
    *,
    parents: np.ndarray | None = None,
    min_weight_sum: float = DEFAULT_MIN_WEIGHT_SUM,
) -> np.ndarray:
    """Skeleton joints that move the garment, sorted, int64.

    Args:
        skinning_weights: garment skinning weights, shape (V, J), rows summing to 1.
        parents: parent joint of each joint, shape (J,), -1 (or any negative) for roots;
            None to skip the ancestor closure.
        min_weight_sum: a joint is kept when sum_v w[v, j] > min_weight_sum.
    """
    weights = np.asarray(skinning_weights, dtype=np.float64)
    if weights.ndim != 2:
        raise ValueError(f"skinning_weights must have shape (V, J), got {weights.shape}")
    if min_weight_sum < 0:
        raise ValueError(f"min_weight_sum must be >= 0, got {min_weight_sum}")
    joint_count = weights.shape[1]
    keep = weights.sum(axis=0) > min_weight_sum
    if parents is not None:
        parents = np.asarray(parents, dtype=np.int64).reshape(-1)
        if parents.shape[0] != joint_count:
            raise ValueError(
                f"parents must have one entry per joint ({joint_count}), got {parents.shape[0]}"
            )
        for joint in np.flatnonzero(keep):
            parent, steps = parents[joint], 0
            while parent >= 0:
                keep[parent] = True
                parent, steps = parents[parent], steps + 1
                if steps > joint_count:
                    raise ValueError(f"parents contains a cycle through joint {joint}")
    return np.flatnonzero(keep).astype(np.int64)


def pose_feature_indices(
    joints: np.ndarray,
    pose_size: int,
    *,
    posable_joints: np.ndarray | None = None,
) -> np.ndarray:
    """Entries of the flattened axis-angle pose (B, pose_size) that belong to ``joints``.

    Args:
        joints: skeleton joint ids to keep (from :func:`garment_pose_joints`).
        pose_size: P = 3 x posable joint count.
        posable_joints: skeleton joint id of each pose slot, shape (P / 3,); None when pose
            slot j is skeleton joint j.
    Returns sorted indices, shape (3 x kept posable joints,), int64.
    """
    if pose_size % 3:
        raise ValueError(f"pose_size must be a multiple of 3 (axis-angle), got {pose_size}")
    slot_joint = (
        np.arange(pose_size // 3)
        if posable_joints is None
        else np.asarray(posable_joints, dtype=np.int64).reshape(-1)
    )
    if slot_joint.shape[0] != pose_size // 3:
        raise ValueError(
            f"posable_joints must have pose_size / 3 = {pose_size // 3} entries, got {slot_joint.shape[0]}"
        )
    slots = np.flatnonzero(np.isin(slot_joint, np.asarray(joints)))
    if slots.size == 0:
        raise ValueError(
            "no posable joint moves the garment: lower min_weight_sum or check posable_joints"
        )
    return (3 * slots[:, None] + np.arange(3)[None, :]).reshape(-1).astype(np.int64)
