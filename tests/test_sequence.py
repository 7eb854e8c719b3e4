"""Sequence driver (simulate.sequence): key order, explosion recovery, world isolation."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.cloth.quasi_static import SimSettings, WorldStatus
from simulate.sequence import SequenceSettings, SequenceTask, drape_static, run_sequences

# A one-frame jump of the spine this far [rad] moves the shirt at metres per second.
JUMP_RAD = 1.2
# Speed [m/s] above which a world counts as exploded in these tests: far above any hold
# (speeds of cm/s) and far below the jump (about 10 m/s).
TEST_EXPLOSION_SPEED = 3.0


@pytest.fixture(scope="module")
def scene(anny_body):
    from simulate.garment.templates import make_template

    template = make_template("tshirt", anny_body, resolution=1000)
    canonical = np.asarray(anny_body.canonical_pose, np.float32)
    small = canonical + anny_body.pose_from_dict({"spine1": [0.0, 0.05, 0.0]})
    jump = canonical + anny_body.pose_from_dict({"spine1": [0.0, JUMP_RAD, 0.0]})
    # start from the drape at rest, so only the jump is fast; the settings' 2-frame hold budget is
    # lifted by drape_static's own max_frames (as generate-dataset does for its canonical drapes)
    draped, status = drape_static(anny_body, template.faces, template.vertices[None], shapes=anny_body.shape_default[None],
                                  poses=canonical[None], body_faces=anny_body.part_faces(("torso", "arms")),
                                  settings=SequenceSettings(sim=SimSettings(damping=20.0, tolerance=0.01, patience=3, max_frames=2)),
                                  device="cpu", max_frames=80)
    assert status[0] == WorldStatus.CONVERGED, "the start drape must come to rest within drape_static's max_frames"
    return anny_body, template, draped[0], canonical, small, jump


def _run(scene, key_lists, *, recover: bool):
    body, template, start, *_ = scene
    tasks = [SequenceTask(rest_vertices=template.vertices, start_vertices=start,
                          shape=np.asarray(body.shape_default, np.float32), poses=np.stack(keys)) for keys in key_lists]
    settings = SequenceSettings(
        sim=SimSettings(iterations=10, substeps=10, tolerance=0.05, patience=2, max_frames=25, damping=20.0,
                        explosion_speed=TEST_EXPLOSION_SPEED, explosion_stretch=50.0),
        shape_transition_frames=1, interpolation_threshold=10.0, recover_explosions=recover)
    frames = []
    stats = run_sequences(body, template.faces, tasks, body_faces=body.part_faces(("torso", "arms")), settings=settings,
                          device="cpu", on_frame=frames.append)
    return frames, stats


def test_an_exploding_world_loses_only_its_current_target_and_others_are_untouched(scene):
    *_, canonical, small, jump = scene
    calm_keys = [small, small, canonical]
    frames, stats = _run(scene, [[small, jump, canonical], calm_keys], recover=True)
    by_world = {w: [(f.key, f.status) for f in frames if f.task == w] for w in (0, 1)}
    assert [k for k, _ in by_world[0]] == [0, 1, 2], f"every target handed over once, in order: {by_world[0]}"
    assert by_world[0][1][1] == WorldStatus.EXPLODED, f"the jump must explode at {TEST_EXPLOSION_SPEED} m/s: {by_world[0]}"
    assert by_world[0][2][1] != WorldStatus.EXPLODED, f"the world must recover for the next target: {by_world[0]}"
    assert stats["recoveries"] == 1
    last = [f for f in frames if f.task == 0][-1]
    assert np.isfinite(last.positions).all() and np.abs(last.positions).max() < 2.0, "recovered cloth stays on the body"
    # world 1 shares the simulator but not the explosion: same frames as beside a calm world 0
    calm, _ = _run(scene, [calm_keys, calm_keys], recover=True)
    for a, b in zip([f for f in calm if f.task == 1], [f for f in frames if f.task == 1]):
        np.testing.assert_array_equal(a.positions, b.positions, err_msg="a neighbour's explosion changed world 1")


def test_without_recovery_an_exploded_world_fails_all_remaining_targets(scene):
    *_, canonical, small, jump = scene
    frames, stats = _run(scene, [[small, jump, canonical]], recover=False)
    assert [(f.key, f.status == WorldStatus.EXPLODED) for f in frames] == [(0, False), (1, True), (2, True)]
    assert stats["recoveries"] == 0
