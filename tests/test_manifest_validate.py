"""validate_dataset / info / `drape dataset` CLI: corrupt, missing, orphan and inconsistent
datasets are reported by name; the summary table shows splits, drops and timings."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from data_manifest.cli import main as cli_main
from data_manifest.schema import MANIFEST_NAME
from data_manifest.shard import ShardWriter, shard_path
from data_manifest.synthetic import synthetic_frame, tube_template, write_synthetic_dataset
from data_manifest.validate import info, validate_dataset


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    root = tmp_path_factory.mktemp("pristine")
    write_synthetic_dataset(root, splits={"train": 2, "test": 1}, precision="float16")
    return root


@pytest.fixture
def dataset(pristine, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(pristine, root)
    return root


def kinds(report) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for problem in report.errors + report.warnings:
        found.setdefault(problem.kind, []).append(problem.where)
    return found


def test_valid_dataset(dataset):
    report = validate_dataset(dataset)
    assert report.ok, str(report)
    assert report.shards_checked == 3 and report.frames_checked == 12
    assert not report.warnings, str(report)


def test_corrupt_byte_is_reported_by_name(dataset):
    path = shard_path(dataset, "train-001")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    report = validate_dataset(dataset)
    assert not report.ok
    found = kinds(report)
    assert found.get("checksum") == [str(path)], f"expected a checksum error naming {path}: {report}"
    assert "train-001" in str(report)
    assert all("train-000" not in p.where for p in report.errors), "a sound shard was blamed"


def test_missing_shard_and_orphans_are_reported(dataset):
    missing = shard_path(dataset, "test-000")
    missing.unlink()
    (missing.parent / "train-009.h5.123-abcd.tmp").write_bytes(b"partial")
    shutil.copy(shard_path(dataset, "train-000"), missing.parent / "stray.h5")
    report = validate_dataset(dataset)
    found = kinds(report)
    assert found.get("missing") == [str(missing)], str(report)
    assert [p.split("/")[-1] for p in found.get("orphan_tmp", [])] == ["train-009.h5.123-abcd.tmp"]
    assert [p.split("/")[-1] for p in found.get("orphan_shard", [])] == ["stray.h5"]
    assert {p.kind for p in report.warnings} == {"orphan_tmp", "orphan_shard"}, "orphans are warnings"


def test_orphans_alone_do_not_fail_validation(dataset):
    (dataset / "shards" / "x.h5.1-2.tmp").write_bytes(b"")
    report = validate_dataset(dataset)
    assert report.ok and [p.kind for p in report.warnings] == ["orphan_tmp"], str(report)


def edit_manifest(root, edit) -> None:
    path = root / MANIFEST_NAME
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def test_inconsistent_manifest_is_reported(dataset):
    def edit(data):
        data["shards"][0]["frame_count"] += 1  # shard test-000 holds 4
        data["totals"]["frames_kept"] += 1
        data["splits"]["train"].append("train-002")  # planned, never written
        data["splits"]["test"].append("train-000")  # membership disagrees with the shard entry
        data["totals"]["frames_dropped"]["nan"] = 0

    edit_manifest(dataset, edit)
    report = validate_dataset(dataset)
    found = kinds(report)
    assert found.get("frame_count") == [str(shard_path(dataset, "test-000"))], str(report)
    assert any("$.splits.train" in w for w in found.get("pending", [])), str(report)
    assert any("$.splits.test" in w for w in found.get("split", [])), str(report)
    assert any(w.endswith("$.totals.frames_dropped") for w in found.get("totals", [])), str(report)


def test_schema_errors_are_reported_with_json_paths(dataset):
    edit_manifest(dataset, lambda data: data["shards"][2].__setitem__("sha256", "not-a-hash"))
    report = validate_dataset(dataset)
    assert [p.kind for p in report.errors] == ["schema"]
    assert report.errors[0].where.endswith("$.shards[2].sha256"), str(report)


def test_shard_from_another_template_is_reported(dataset, tmp_path):
    template = tube_template()
    template["rest_vertices"] = template["rest_vertices"] * 1.01
    task = {"task_id": "train-000", "garment": "tube", "splits": ["train"], "seed": 0,
            "shape": np.zeros(4), "style": np.zeros(2)}
    with ShardWriter(tmp_path / "other.h5", template=template, task=task, precision="float16") as writer:
        writer.write_frame(**synthetic_frame(template, np.random.default_rng(0), translation_m=np.zeros(3)))
    path = shard_path(dataset, "train-000")
    shutil.copy(tmp_path / "other.h5", path)

    def relist(data):
        entry = next(e for e in data["shards"] if e["task_id"] == "train-000")
        entry["sha256"], entry["bytes"] = writer.record.sha256, writer.record.bytes
        entry["frame_count"], entry["filter_stats"] = 1, {}
        data["totals"] = {"shards": 3, "bytes": sum(e["bytes"] for e in data["shards"]),
                          "frames_kept": sum(e["frame_count"] for e in data["shards"]), "frames_dropped": {"nan": 2}}

    edit_manifest(dataset, relist)
    report = validate_dataset(dataset)
    assert [(p.kind, p.where) for p in report.errors] == [("template", str(path))], str(report)


def test_info_prints_the_table(dataset):
    text = info(dataset)
    lines = text.splitlines()
    assert lines[0].startswith("dataset synthetic") and "precision float16" in lines[0] and "3 shards" in lines[0]
    rows = {line.split()[0]: line.split() for line in lines if line.split()}
    assert rows["train"][1:] == ["2", "2", "8"], f"train row: {rows['train']}"
    assert rows["test"][1:] == ["1", "1", "4"], f"test row: {rows['test']}"
    assert rows["all"][1:] == ["3", "3", "12"]
    assert rows["kept"][1:] == ["12", "80.0", "%"]
    assert "dropped: nan" in text and text.count("\n") > 10
    assert rows["simulate_s"][1:] == ["1.50", "0.500"], f"timings row {rows['simulate_s']}"
    # kept share by position in the sequence, from frame_index and the dropped logs: each synthetic
    # task keeps frames 0, 2, 4, 6 and drops frame 1 as nan
    table = text.split("position in sequence")[1].splitlines()[2:]
    by_position = {line.split()[0]: line.split()[1:] for line in table if line.strip()}
    assert by_position == {"0": ["3", "100.0", "%", "-"], "1": ["3", "0.0", "%", "nan", "(100", "%)"],
                           "2-4": ["6", "100.0", "%", "-"], "5-9": ["3", "100.0", "%", "-"]}, by_position


def test_cli_exit_codes_and_output(dataset, capsys):
    assert cli_main(["dataset", "validate", str(dataset)]) == 0
    assert "OK" in capsys.readouterr().out
    assert cli_main(["dataset", "info", str(dataset)]) == 0
    assert "frames" in capsys.readouterr().out
    shard_path(dataset, "train-000").unlink()
    assert cli_main(["dataset", "validate", str(dataset)]) == 1
    out = capsys.readouterr().out
    assert "INVALID" in out and "[missing]" in out and "train-000.h5" in out
    assert cli_main(["dataset", "validate", str(dataset / "nope")]) == 2  # bad input: no such directory
    assert cli_main(["dataset", "info", str(dataset / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_info_lists_the_pairs_keeping_least(tmp_path):
    """Pairs are read off the task ids (a train pair's train_train and train_test shards count
    together, the canonical split's apart); the pair that drops most comes first with its style,
    body shape and main drop reason."""
    from data_manifest.manifest import Manifest, collect_provenance
    from data_manifest.schema import template_sha256

    template = tube_template()
    rng = np.random.default_rng(0)
    # task id -> (style index, height, kept, distortion drops)
    tasks = {"train_train-p000": (0, 0.5, 4, 0), "train_test-p000": (0, 0.5, 2, 0),
             "train_train-p001-c000": (3, 0.875, 1, 3), "train_train-p001-c001": (3, 0.875, 0, 2),
             "test_test-p002": (1, 0.125, 3, 1), "canonical-p000": (3, 0.875, 0, 1)}
    splits: dict[str, list[str]] = {}
    for task_id in tasks:
        splits.setdefault(task_id.split("-")[0], []).append(task_id)
    manifest = Manifest.create(tmp_path, name="pairs", spec={}, template_sha256=template_sha256(template),
                               precision="float32", provenance=collect_provenance(device="cpu", seeds={}),
                               splits=splits)
    for task_id, (style, height, kept, dropped) in tasks.items():
        shape = np.full(6, 0.5)
        shape[4] = height
        task = {"task_id": task_id, "garment": "tube", "splits": [task_id.split("-")[0]], "seed": 0,
                "shape": shape, "style": np.zeros(4), "style_index": style}
        with ShardWriter(shard_path(tmp_path, task_id), template=template, task=task) as writer:
            for frame in range(kept):
                writer.write_frame(**synthetic_frame(template, rng, translation_m=np.zeros(3)), frame_index=frame)
            pose = synthetic_frame(template, rng, translation_m=np.zeros(3))["pose"]
            for frame in range(dropped):
                writer.record_dropped("distortion", frame_index=kept + frame, pose=pose)
        manifest.add_shard(writer.record)
    manifest.save()
    manifest.finish()

    text = info(tmp_path)
    assert "style-shape pairs: 3, kept share median 75.0 % (lowest 16.7 %, highest 100.0 %)" in text, text
    table = text.split("the 3 keeping least:")[1].splitlines()[3:]
    rows = [line.split() for line in table if line.strip()]
    assert rows[0] == ["train", "p001", "3", "0.50", "0.50", "0.50", "0.50", "0.88", "0.50", "6", "16.7", "%",
                       "distortion", "(83", "%)"], rows[0]
    assert rows[1][:3] == ["test", "p002", "1"] and rows[1][9:12] == ["4", "75.0", "%"], rows[1]
    assert rows[2][:2] == ["train", "p000"] and rows[2][9:] == ["6", "100.0", "%", "-"], rows[2]
