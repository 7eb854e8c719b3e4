"""Pose sampler limits, pruning, pose files, greedy order and interpolation."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.body import JOINT_LIMITS, POSE_JOINTS
from simulate.poses import (PoseSampler, greedy_order, interpolate_sequence, joint_angle_change, load_pose_file,
                            sample_poses, slerp_poses)


def test_sampler_is_seeded_and_stays_near_limits():
    sampler = PoseSampler(range_scale=0.5)
    a = sampler.sample(500, np.random.default_rng(3))
    b = sampler.sample(500, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    per_joint = a.reshape(-1, 20, 3)
    for joint in ("spine1", "neck"):  # centre line: plain per-axis angles inside the limits
        lim = np.asarray(JOINT_LIMITS[joint]) * 0.5
        k = POSE_JOINTS.index(joint)
        assert (per_joint[:, k] >= lim[:, 0] - 1e-6).all() and (per_joint[:, k] <= lim[:, 1] + 1e-6).all()
    untouched = [POSE_JOINTS.index(j) for j in ("left_knee", "pelvis", "head")]
    assert np.abs(per_joint[:, untouched]).max() == 0.0, "joints outside the sampled set stay at the base pose"
    lim = np.abs(np.asarray(JOINT_LIMITS["left_shoulder"]) * 0.5).max()
    assert np.linalg.norm(per_joint[:, POSE_JOINTS.index("left_shoulder")], axis=1).max() <= np.sqrt(3) * lim + 1e-5


def test_pruning_drops_self_intersecting_poses(anny_body):
    from simulate.body.mesh_utils import SelfIntersectionChecker

    poses, pruned = sample_poses(anny_body, anny_body.shape_default, 50, PoseSampler(), np.random.default_rng(0))
    checker = SelfIntersectionChecker(anny_body, anny_body.shape_default)
    assert poses.shape == (50, 60) and not checker.check(poses)[0].any()
    assert len(pruned) > 0 and checker.check(pruned)[0].all(), "full-range arm poses must produce some pruned poses"


def test_greedy_order_visits_each_pose_once_nearest_first():
    rng = np.random.default_rng(1)
    poses = rng.normal(0, 0.3, (12, 60)).astype(np.float32)
    order = greedy_order(poses, np.zeros(60))
    assert sorted(order.tolist()) == list(range(12))
    first = joint_angle_change(np.zeros((12, 60)), poses).max(1)
    assert order[0] == np.argmin(first)


def test_greedy_order_matches_the_step_by_step_reference():
    """Each pose is the one nearest to the previous among those left, by joint_angle_change."""
    rng = np.random.default_rng(3)
    poses = rng.normal(0, 0.5, (40, 60)).astype(np.float32)
    start = rng.normal(0, 0.2, 60).astype(np.float32)
    order = greedy_order(poses, start)
    left, current = list(range(40)), start
    for k in range(40):
        d = joint_angle_change(np.broadcast_to(current, (len(left), 60)), poses[left]).max(1)
        assert left[int(np.argmin(d))] == order[k], f"step {k}"
        current = poses[left.pop(int(np.argmin(d)))]
    assert greedy_order(poses[:0], start).shape == (0,)


def test_interpolation_respects_threshold_and_keeps_keys():
    rng = np.random.default_rng(2)
    keys = rng.normal(0, 0.4, (4, 60)).astype(np.float32)
    seq, key_index = interpolate_sequence(keys, np.zeros(60), 0.1)
    steps = joint_angle_change(np.concatenate([np.zeros((1, 60)), seq[:-1]]), seq).max(1)
    assert steps.max() <= 0.1 + 1e-4, f"largest step {steps.max()} rad exceeds the threshold"
    np.testing.assert_allclose(seq[key_index >= 0], keys, atol=1e-6)
    mid = slerp_poses(np.zeros(60), keys[0], np.array([0.5]))[0]
    np.testing.assert_allclose(joint_angle_change(np.zeros(60), mid), 0.5 * joint_angle_change(np.zeros(60), keys[0]), atol=1e-5)


def test_pose_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="poses.path"):
        load_pose_file(tmp_path / "none.npz")
    np.savez(tmp_path / "bad.npz", poses=np.zeros((5, 59)))
    with pytest.raises(ValueError, match=r"must have shape \(N, 60\)"):
        load_pose_file(tmp_path / "bad.npz")
    np.savez(tmp_path / "ok.npz", poses=np.zeros((5, 20, 3)))
    assert load_pose_file(tmp_path / "ok.npz").shape == (5, 60)
    with pytest.raises(ValueError, match="range_scale"):
        PoseSampler(range_scale=0.0)
    with pytest.raises(ValueError, match="unknown joint"):
        PoseSampler(joints=("left_antenna",))
