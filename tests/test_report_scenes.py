"""Report scenes: pose paths, float16 storage rounding, edge stretch (against a naive loop), the
capsule scene's body, and run_worlds input checks (no anny load: CI-sized)."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.reports.scenes import (ACCURACY_POSES, EXTREME_POSES, build_scene, edge_stretch, named_pose, pose_path,
                                     round_float16, run_worlds)

FLOAT16_BOUND_M = 2.0**-11
"""float16 round trip of |x| < 2 m: half the spacing 2**-10 m."""


def test_named_poses_respect_joint_limits() -> None:
    from simulate.body import JOINT_LIMITS, POSE_JOINTS

    for name in [*ACCURACY_POSES, *EXTREME_POSES]:
        pose = named_pose(name).reshape(len(POSE_JOINTS), 3)
        for j, joint in enumerate(POSE_JOINTS):
            for axis in range(3):
                lo, hi = JOINT_LIMITS[joint][axis]
                assert lo - 1e-6 <= pose[j, axis] <= hi + 1e-6, f"{name}: {joint}[{axis}] = {pose[j, axis]} outside [{lo}, {hi}]"
    with pytest.raises(ValueError, match="pose name"):
        named_pose("cartwheel")


def test_pose_path_endpoints_and_steps() -> None:
    a, b = named_pose("canonical"), named_pose("arms-up")
    path = pose_path(a, b, steps=12)
    assert path.shape == (13, 60)
    np.testing.assert_allclose(path[0], a, atol=1e-6, err_msg="path must start at the start pose")
    np.testing.assert_allclose(path[-1], b, atol=1e-5, err_msg="path must end at the target pose")
    assert pose_path(a, b, steps=0).shape == (1, 60)
    with pytest.raises(ValueError, match="steps"):
        pose_path(a, b, steps=-1)


def test_round_float16_is_within_the_storage_bound() -> None:
    rng = np.random.default_rng(3)
    origin = rng.uniform(-5.0, 5.0, size=(4, 3))
    x = origin[:, None, :] + rng.uniform(-1.9, 1.9, size=(4, 100, 3))
    err = np.abs(round_float16(x, origin) - x).max()
    assert 0.0 < err <= FLOAT16_BOUND_M, f"float16 round trip error {err} m outside (0, {FLOAT16_BOUND_M}]"


def test_edge_stretch_matches_naive_loop() -> None:
    scene = build_scene(body="capsule", resolution=60)
    rng = np.random.default_rng(0)
    x = scene.rest_vertices[None] + rng.normal(0.0, 0.003, size=(2,) + scene.rest_vertices.shape)
    smax, smean = edge_stretch(x, scene.rest_vertices, scene.faces)
    for w in range(2):
        ratios = {}
        for f in scene.faces:
            for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
                key = (min(a, b), max(a, b))
                ratios[key] = np.linalg.norm(x[w, a] - x[w, b]) / np.linalg.norm(scene.rest_vertices[a] - scene.rest_vertices[b])
        vals = np.array(list(ratios.values()))
        assert abs(smax[w] - vals.max()) < 1e-12 and abs(smean[w] - vals.mean()) < 1e-12, f"world {w} differs from naive"


def test_capsule_body_poses_and_shapes() -> None:
    scene = build_scene(body="capsule", resolution=60)
    shapes = np.array([[0.5], [1.0], [0.5]])
    poses = np.stack([named_pose("canonical"), named_pose("canonical"), named_pose("tilt")])
    verts, roots = scene.body_vertices(shapes, poses)
    assert verts.shape == (3, scene.body_vertex_count, 3) and roots.shape == (3, 3)
    rel = verts - roots[:, None, :]
    radius = np.linalg.norm(rel[:, :, 1:], axis=2).max(axis=1)  # bar along x in the canonical pose
    assert np.isclose(radius[1] / radius[0], 1.2 / 1.0, rtol=1e-5), f"shape 1.0 vs 0.5 radius ratio {radius[1] / radius[0]}"
    np.testing.assert_allclose(np.linalg.norm(rel[2], axis=1), np.linalg.norm(rel[0], axis=1), atol=1e-6,
                               err_msg="a pose must rotate the bar rigidly about its centre")
    assert np.abs(rel[2] - rel[0]).max() > 0.01, "the tilt pose did not move the bar"
    with pytest.raises(ValueError, match="body"):
        build_scene(body="sphere")
    with pytest.raises(ValueError, match="garment"):
        build_scene("cape")


def test_run_worlds_rejects_bad_inputs() -> None:
    scene = build_scene(body="capsule", resolution=60)
    body, _ = scene.body_vertices(scene.neutral_shape[None], scene.canonical_pose[None])
    with pytest.raises(ValueError, match="fabrics"):
        run_worlds(scene, start=scene.start_vertices, paths=[body], fabrics=[], settings=None)
    with pytest.raises(ValueError, match="start"):
        run_worlds(scene, start=scene.start_vertices[:-1], paths=[body], fabrics=["silk"], settings=None)
    with pytest.raises(ValueError, match=r"paths\[0\]"):
        run_worlds(scene, start=scene.start_vertices, paths=[body[:, :-1]], fabrics=["silk"], settings=None)
