"""Skin clearance between arm and torso / between the legs (pose pruning)."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.body.clearance import CLEARANCE_PAIRS, LimbClearance


def _brute_force(body, shape, pose, measured, surface_faces):
    """Point-to-triangle distances by dense sampling of each triangle (a reference, not fast)."""
    v = body.pose(shape[None], pose[None]).vertices[0].astype(np.float64)
    tri = v[surface_faces]  # (F, 3, 3)
    w = np.array([[a, b, 1 - a - b] for a in np.linspace(0, 1, 9) for b in np.linspace(0, 1, 9) if a + b <= 1])
    samples = np.einsum("sk,fkd->fsd", w, tri).reshape(-1, 3)
    p = v[measured]
    best = np.full(len(p), np.inf)
    for s in range(0, len(samples), 20000):
        d = np.linalg.norm(p[:, None] - samples[None, s:s + 20000], axis=-1).min(1)
        best = np.minimum(best, d)
    return best.min()


def test_arm_clearance_falls_as_the_arm_comes_down_and_matches_a_reference(anny_body):
    shape = anny_body.shape_default
    clearance = LimbClearance(anny_body, shape, CLEARANCE_PAIRS["upper"])
    down = [anny_body.pose_from_dict({"left_shoulder": [0, 0, -a]}) for a in (0.0, 0.3, 0.6, 0.9)]
    c = clearance.measure(np.stack(down))
    assert c.shape == (4, 2)
    left, right = c[:, 0], c[:, 1]
    assert np.all(np.diff(left) < 0), f"left arm coming down must close its gap to the torso: {left}"
    assert np.ptp(right) < 1e-6, "the right arm did not move"
    assert left[0] > 0.04 and left[-1] < 0.01, f"A-pose clearance must be several cm, the lowered arm's ~0: {left}"
    # the kernel's closest points against densely sampled triangles (the sampling is ~2 mm coarse)
    ref = _brute_force(anny_body, shape, down[2], clearance._points[0], clearance.surface_faces["torso"])
    assert ref - 0.003 <= left[2] <= ref + 1e-6, (left[2], ref)


def test_forearm_through_the_chest_and_crossed_legs_have_no_clearance(anny_body):
    shape = anny_body.shape_default
    poses = np.stack([np.zeros(60, np.float32),
                      anny_body.pose_from_dict({"left_shoulder": [0, 0, -1.2], "left_elbow": [0, -2.0, 0]}),
                      anny_body.pose_from_dict({"left_hip": [0, 0, -0.6], "right_hip": [0, 0, 0.6]})])
    c = LimbClearance(anny_body, shape, CLEARANCE_PAIRS["all"]).measure(poses)
    assert c[0].min() > 0.02, c[0]
    assert c[1, 0] < 0.005, f"forearm through the chest: {c[1]}"
    assert c[2, 2] < 0.005 and c[2, :2].min() > 0.02, f"crossed legs only: {c[2]}"


def test_unknown_part_or_pairs_name_the_value(anny_body):
    from simulate.poses import PoseSampler, sample_poses

    with pytest.raises(ValueError, match="'left_wing'"):
        LimbClearance(anny_body, anny_body.shape_default, [("left_wing", "torso")])
    with pytest.raises(ValueError, match="'middle'"):
        sample_poses(anny_body, anny_body.shape_default, 4, PoseSampler(), np.random.default_rng(0), clearance_pairs="middle")
    with pytest.raises(ValueError, match="min_clearance"):
        sample_poses(anny_body, anny_body.shape_default, 4, PoseSampler(), np.random.default_rng(0), min_clearance=-0.01)


def test_min_clearance_prunes_close_arms_and_leaves_other_poses_alone(anny_body):
    from simulate.poses import PoseSampler, sample_poses

    shape = anny_body.shape_default
    plain, plain_pruned = sample_poses(anny_body, shape, 24, PoseSampler(), np.random.default_rng(5))
    poses, pruned = sample_poses(anny_body, shape, 24, PoseSampler(), np.random.default_rng(5), min_clearance=0.02)
    clearance = LimbClearance(anny_body, shape, CLEARANCE_PAIRS["upper"])
    assert clearance.measure(poses).min() >= 0.02
    assert len(pruned) > len(plain_pruned), "full-range arms must come within 2 cm of the torso in some of ~50 poses"
    assert (clearance.measure(pruned).min(axis=1) < 0.02).sum() >= len(pruned) - len(plain_pruned)
    # the poses that pass both tests are the plain sampler's, in order: pruning does not reseed
    keep = clearance.measure(plain).min(axis=1) >= 0.02
    np.testing.assert_array_equal(poses[:keep.sum()], plain[keep])


def test_clearances_beyond_max_distance_read_as_max_distance(anny_body):
    """A capped clearance equals max_distance exactly (float32 rounding put 0.02 below 0.02, and
    every pose was pruned when the pruner capped its search at the threshold)."""
    from simulate.poses import PoseSampler

    poses = PoseSampler().sample(32, np.random.default_rng(1))
    full = LimbClearance(anny_body, anny_body.shape_default, CLEARANCE_PAIRS["upper"]).measure(poses)
    capped = LimbClearance(anny_body, anny_body.shape_default, CLEARANCE_PAIRS["upper"], max_distance=0.02).measure(poses)
    np.testing.assert_array_equal(capped, np.where(full >= np.float32(0.02), 0.02, full))
    assert (capped < 0.02).sum() == (full < 0.02).sum() < len(poses) * 2
