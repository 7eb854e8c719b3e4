"""The dataset's own floor: history dependence of the drape (simulator) and single-pair MLPs."""
from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pipelines.floor import Probe, history_floor, plan_probes
from simulate.quasi_static import WorldStatus
from simulate.sequence import SequenceSettings, drape_static
from unit_sim import unit_settings

sys.path.insert(0, str(Path(__file__).parent))
from test_tailornet_train import _pairs, make_frames  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def context(anny_body):
    """What history_floor reads of generate-dataset's context, for one small t-shirt."""
    from simulate.garment.drape import COLLISION_PARTS
    from simulate.garment.templates import make_template

    template = make_template("tshirt", anny_body, resolution=400)
    body_faces = anny_body.part_faces(COLLISION_PARTS["tshirt"])
    canonical = np.asarray(anny_body.canonical_pose, np.float32)
    settings = SequenceSettings(
        sim=unit_settings(iterations=8, substeps=8, tolerance=0.05, patience=2, max_frames=30, damping=20.0,
                          explosion_speed=50.0, explosion_stretch=50.0),
        shape_transition_frames=1, interpolation_threshold=0.3)
    start, status = drape_static(anny_body, template.faces, template.vertices[None],
                                 shapes=anny_body.shape_default[None], poses=canonical[None], body_faces=body_faces,
                                 settings=settings, device="cpu", max_frames=60)
    ctx = SimpleNamespace(spec={"garment": {"fabric": "cotton"}}, body=anny_body, template=template,
                          body_faces=body_faces, body_face_groups=None, body_part=None, device="cpu",
                          style_rest=template.vertices[None], style_start=start)
    poses = {name: canonical + anny_body.pose_from_dict(rotations) for name, rotations in {
        "target": {"spine1": [0.0, 0.25, 0.0]},
        "near": {"spine1": [0.0, 0.1, 0.0]},
        "far": {"spine1": [0.0, -0.35, 0.0], "left_shoulder": [0.0, 0.0, 0.5]},
    }.items()}
    return ctx, settings, poses


def test_history_floor_is_zero_for_one_sequence_and_positive_for_two(context) -> None:
    ctx, settings, poses = context
    shape = np.asarray(ctx.body.shape_default, np.float32)
    same = np.stack([poses["near"], poses["target"]])
    identical = history_floor(ctx, [Probe(0, shape, same, same.copy())], settings=settings)
    assert identical["used"] == 1, identical
    assert identical["posed_mm"] == 0.0 and identical["unposed_mm"] == 0.0, identical
    other = np.stack([poses["far"], poses["target"]])
    different = history_floor(ctx, [Probe(0, shape, same, other)], settings=settings)
    row = different["probes"][0]
    assert WorldStatus.EXPLODED.name not in (row["status_a"], row["status_b"]), row
    assert different["posed_mm"] > 0.01 and different["unposed_mm"] > 0.01, different
    # the distance is a drape's, not a body's: far below the predecessors' own distance
    assert different["posed_mm"] < 50.0, different


def test_targets_from_home_make_the_rest_independent_of_the_poses_before(context) -> None:
    """With targets_from_home every target is reached from the settled canonical drape, so two
    histories that differ only before the last target rest identically (the history floor is 0)."""
    import dataclasses

    ctx, settings, poses = context
    shape = np.asarray(ctx.body.shape_default, np.float32)
    home = dataclasses.replace(settings, targets_from_home=True)
    probe = Probe(0, shape, np.stack([poses["near"], poses["target"]]), np.stack([poses["far"], poses["target"]]))
    floor = history_floor(ctx, [probe], settings=home)
    row = floor["probes"][0]
    assert floor["used"] == 1 and WorldStatus.EXPLODED.name not in (row["status_a"], row["status_b"]), floor
    assert floor["posed_mm"] == 0.0 and floor["unposed_mm"] == 0.0, floor


def test_probes_share_the_last_pose_and_differ_before_it() -> None:
    rng = np.random.default_rng(0)
    poses = rng.normal(size=(6, 9)).astype(np.float32)
    task = SimpleNamespace(style_index=0, shape=np.zeros(2), split="train_train", poses=poses, task_id="t0")
    probes = plan_probes([task], pairs=1, targets=3, prefix=2)
    assert [p.key for p in probes] == [2, 4, 5]
    for p in probes:
        np.testing.assert_array_equal(p.sequence_a, poses[p.key - 2:p.key + 1])
        np.testing.assert_array_equal(p.sequence_b[-1], poses[p.key])
        assert not any(np.array_equal(b, a) for b in p.sequence_b[:-1] for a in p.sequence_a), "same predecessors"
    with pytest.raises(ValueError, match="prefix"):
        plan_probes([task], prefix=0)
    with pytest.raises(ValueError, match="train_test"):
        plan_probes([task], split="train_test")


def test_single_pair_mlp_overfits_a_tiny_pair(tmp_path: Path) -> None:
    from learn.tailornet.single_pair import fit_single_pair, single_pair_errors

    train, _ = make_frames(0, 12, _pairs()[:2])
    test, _ = make_frames(1, 6, _pairs()[:2])
    hyper = {"hf": {"lr": 1e-3, "epochs": 1500, "hidden_size": 64, "batch_size": 12, "dropout": 0.0},
             "model": {"checkpoint_interval_s": 1e9}}
    model, keys = fit_single_pair(train, np.arange(train.pose.shape[1]), run_dir=tmp_path, pairs=np.array([1]),
                                  hyperparameters=hyper)
    on_train = single_pair_errors(model, keys, train)
    mean = train.displacements[train.pair_id == 1].mean(axis=0)
    mean_error = float(np.linalg.norm(train.displacements[train.pair_id == 1] - mean, axis=-1).mean() * 1e3)
    assert on_train["frames"] == 12, "only pair 1's frames are scored"
    assert on_train["error_mm"] < 0.15 * mean_error, (on_train, mean_error)
    on_test = single_pair_errors(model, keys, test)
    assert on_test["frames"] == 6 and on_test["error_mm"] > on_train["error_mm"], (on_test, on_train)


def test_floor_command_refuses_bad_options_in_one_line(tmp_path: Path, capsys) -> None:
    from pipelines.cli import main

    for args, fragment in ((["--pairs", "0"], "--pairs"), (["--skip-history", "--skip-single-pair"], "nothing"),
                           (["--train-device", "gpu"], "--train-device")):
        status = main(["report", "floor", "--data", str(tmp_path), "--out", str(tmp_path / "out"), *args])
        err = capsys.readouterr().err
        assert status == 2 and err.count("\n") == 1 and fragment in err and "Traceback" not in err, err


def test_floor_rows_halve_the_history_distance() -> None:
    from pipelines.evaluate import floor_rows

    rows = floor_rows({"history": {"unposed_mm": 3.0}, "single_pair": {"test_error_mm": 7.5}})
    assert rows == [("all", "floor:history", 1.5), ("train_test", "floor:1-pair", 7.5)]
    assert floor_rows({"history": {"unposed_mm": None}}) == []
