"""The shipped seed-001 spec (``uvimage-seed001``): what it asks for, the regularization split it
adds, and a tiny version of it through generate-dataset, ``drape train uvimage`` and ``drape
evaluate`` on CPU."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from pipelines.spec import OPTIONAL_KEYS, SpecError, load_spec, validate_spec

SPEC = Path(__file__).resolve().parents[1] / "pipelines" / "configs" / "uvimage-seed001.yaml"
TINY_HYPER = {"image_size": 32, "padding": 2, "start_channels": 64, "batch_size": 4}


def tiny_spec() -> dict:
    """The shipped spec with its counts scaled down to a handful of poses and the CPU's stepping
    budget. What changes besides the counts: the garment's resolution (400), the pose range
    (0.2 of each joint's), coarse stepping without self-contact, no audit, and filters that let
    the coarse garment's frames through (at 400 the seed's "any triangle" drops half of them);
    every other field is the shipped spec's."""
    raw = yaml.safe_load(SPEC.read_text())
    raw["name"] = "uvimage-seed001-tiny"
    raw["garment"]["resolution"] = 400
    raw["poses"].update(range_scale=0.2, train_count=2, regularization_count=1, test_count=1)
    raw["simulation"].update(device="cpu", worlds=4, substeps=5, iterations=5, tolerance=0.05, max_relax_frames=12,
                             interpolation_threshold=0.5, poses_per_task=1)
    raw["simulation"]["contact"]["self_contact"] = False
    raw["filters"].update(require_converged=False, max_distorted_fraction=0.05, max_self_intersections=10)
    raw["audit"] = {"samples": 0}
    return raw


def test_the_shipped_spec_is_seed_001s_setting():
    spec = load_spec("uvimage-seed001")
    assert spec["garment"]["type"] == "tshirt" and spec["pairs"] == {"train": 1, "test": 0}
    assert spec["styles"]["train"] == [{}] and len(spec["shapes"]["train"]) == 1
    poses = spec["poses"]
    assert (poses["source"], poses["joints"], poses["range_scale"]) == ("sampled", "upper", 1.0)
    assert (poses["train_count"], poses["regularization_count"], poses["test_count"]) == (16_000, 2_000, 2_000)
    assert spec["splits"] == {"train_train": "all", "train_test": "all", "test_train": 0, "test_test": 0}
    # D.6: a frame goes if any triangle's area shrinks by more than 75 % or grows by more than 100 %
    f = spec["filters"]
    assert (f["max_area_shrink"], f["max_area_growth"], f["max_distorted_fraction"]) == (0.75, 1.0, 0.0)
    raw = yaml.safe_load(SPEC.read_text())
    fields = set(load_spec("quickstart")["simulation"]) | set(OPTIONAL_KEYS["simulation"])
    assert set(raw["simulation"]) <= fields, "a simulation field beyond the spec's (a library setting)"
    assert "regularization_count" not in load_spec("tailornet-tshirt")["poses"], "absent, it stays out of the hash"


def test_the_regularization_split_plans_every_pose_of_its_own_set(anny_body):
    from pipelines.dataset_plan import plan_dataset

    raw = tiny_spec()
    raw["poses"].update(train_count=5, regularization_count=3, test_count=2)
    raw["simulation"]["poses_per_task"] = 2
    plan = plan_dataset(validate_spec(raw), anny_body)
    assert {k: len(v) for k, v in plan.poses.items()} == {"train": 5, "regularization": 3, "test": 2}
    by_split: dict[str, list[int]] = {}
    for task in plan.tasks:
        by_split.setdefault(task.split, []).extend(task.pose_ids.tolist())
        np.testing.assert_array_equal(task.poses, plan.poses[
            {"train_train": "train", "train_test": "test", "regularization": "regularization"}[task.split]][task.pose_ids])
    assert {k: sorted(v) for k, v in by_split.items()} == {
        "train_train": [0, 1, 2, 3, 4], "train_test": [0, 1], "regularization": [0, 1, 2]}
    train, held = plan.poses["train"], plan.poses["regularization"]
    assert np.abs(train[:, None] - held[None]).max(-1).min() > 0, "a regularization pose is also a training pose"


@pytest.mark.parametrize("patch, expected", [
    ({"regularization_count": -1}, "spec.poses.regularization_count must be an integer >= 0 (got -1)"),
    ({"regularization_count": "2k"}, "spec.poses.regularization_count must be an integer >= 0 (got '2k')"),
    ({"regularization_count": 5, "source": "motion"},
     "spec.poses.regularization_count must be absent when poses.source is motion"),
    ({"regularisation_count": 5}, "spec.poses.regularisation_count is not a known field (did you mean regularization_count?)"),
])
def test_a_bad_regularization_count_names_field_value_and_expectation(patch, expected):
    raw = yaml.safe_load(SPEC.read_text())
    raw["poses"].update(patch)
    with pytest.raises(SpecError, match=expected.replace("(", r"\(").replace(")", r"\)").replace("?", r"\?")):
        validate_spec(raw, source="uvimage-seed001.yaml")


def test_the_cli_exits_2_on_a_bad_regularization_count(tmp_path, capsys):
    from pipelines.cli import main

    raw = yaml.safe_load(SPEC.read_text())
    raw["poses"]["regularization_count"] = -3
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    assert main(["generate-dataset", str(tmp_path / "s.yaml"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "spec.poses.regularization_count must be an integer >= 0 (got -3)" in err
    assert err.count("\n") == 1 and "Traceback" not in err and not (tmp_path / "out").exists()


@pytest.fixture
def one_torch_thread():
    """The tiny workloads run faster on one thread than on two contended ones."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_tiny_seed_001_spec_generates_trains_and_evaluates(tmp_path, monkeypatch, one_torch_thread):
    """generate-dataset -> drape train uvimage (the regularization split picks the epoch kept)
    -> drape evaluate on the seed's test set (train_test)."""
    import learn.tailornet.evaluate as harness
    from learn.tailornet.train import load_checkpoint
    from pipelines.cli import main

    spec = tmp_path / "tiny.yaml"
    spec.write_text(yaml.safe_dump(tiny_spec()))
    data, run = tmp_path / "data", tmp_path / "run"
    assert main(["generate-dataset", str(spec), "--out", str(data), "--no-progress"]) == 0
    manifest = json.loads((data / "manifest.json").read_text())
    assert set(manifest["splits"]) == {"train_train", "regularization", "train_test"}
    kept = {s: sum(e["frame_count"] for e in manifest["shards"] if s in e["splits"]) for s in manifest["splits"]}
    assert all(kept.values()), f"a split kept no frame: {kept}"

    config = tmp_path / "uv.yaml"
    config.write_text(json.dumps({"uvimage": {**TINY_HYPER, "checkpoint_interval_s": 1e9}}))
    assert main(["train", "uvimage", "--data", str(data), "--out", str(run), "--epochs", "3", "--config", str(config),
                 "--no-progress"]) == 0
    losses = np.loadtxt(run / "uvimage_regularization.csv", delimiter=",", skiprows=1)
    assert losses.shape == (3, 2) and np.array_equal(losses[:, 0], [1, 2, 3])
    model = load_checkpoint(run / "uvimage_model.pt")
    chosen = model["regularization"]
    assert chosen["epoch"] == int(losses[np.argmin(losses[:, 1]), 0]) and chosen["frames"] == kept["regularization"]
    best = load_checkpoint(run / "uvimage_best.pt")
    for key, value in best["model_state"].items():
        assert torch.equal(model["model_state"][key], value), f"the saved model is not the kept epoch's ({key})"

    timed = harness.time_inference  # the CPU timing repeats dominate the tiny evaluation; keep one of each
    monkeypatch.setattr(harness, "time_inference", lambda *a, **k: timed(*a, **{**k, "repeats": 1, "warmup": 0}))
    assert main(["evaluate", str(run), "--data", str(data), "--renders", "0", "--postprocess-frames", "1"]) == 0
    report = json.loads((run / "evaluation" / "evaluation.json").read_text())
    assert set(report["splits"]) == {"train_test"}, "evaluated on the test poses only"
    metrics = report["splits"]["train_test"]["uvimage"]
    for key in ("unposed_error_mm", "posed_error_mm", "normal_error"):
        assert np.isfinite(metrics[key]) and metrics[key] >= 0, key
