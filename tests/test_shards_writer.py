"""ShardWriter: exact float32 round trip, float16 precision bound, atomicity under
exceptions and SIGKILL, deterministic bytes, and input errors."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from data_manifest.schema import FLOAT16_ERROR_BOUND_M, TMP_SUFFIX
from data_manifest.shard import (
    ShardWriter,
    ShardWriterSet,
    check_shard_layout,
    decode_positions,
    file_sha256,
    read_shard_attrs,
    read_template,
    remove_orphan_temporaries,
    shard_path,
)
from data_manifest.manifest import Manifest
from data_manifest.reader import DatasetReader
from data_manifest.synthetic import synthetic_frame, tube_template, write_synthetic_dataset
from data_manifest.validate import validate_dataset

BODY_GARMENT_FLOAT16_TOL_M = 2.0**-12
"""float16 round-trip bound [m] (0.244 mm) for vertices within 1 m of their origin."""


def make_task(task_id: str = "task-0", *, splits=("train",)) -> dict:
    return {"task_id": task_id, "garment": "tube", "splits": list(splits), "seed": 7,
            "shape": np.array([0.1, -0.2, 0.3, 0.0]), "style": np.array([1.0, -1.0]), "gender": "female"}


def write_frames(path: Path, frames: list[dict], **kwargs) -> ShardWriter:
    with ShardWriter(path, template=tube_template(), task=make_task(), **kwargs) as writer:
        for k, frame in enumerate(frames):
            writer.write_frame(**frame, frame_index=3 * k)
        writer.record_dropped("penetration", 2)
    return writer


def frames_for(count: int, seed: int = 0, translation=(1.5, 1.0, -2.0)) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [synthetic_frame(tube_template(), rng, translation_m=np.asarray(translation)) for _ in range(count)]


def test_float32_round_trip_is_exact(tmp_path):
    frames = frames_for(5)
    path = shard_path(tmp_path, "task-0")
    writer = write_frames(path, frames)
    record = writer.record
    assert record is not None and record.frame_count == 5, f"record {record}"
    assert record.sha256 == file_sha256(path), "record sha256 differs from the file's"
    assert record.bytes == path.stat().st_size
    assert record.filter_stats == {"penetration": 2}
    assert list(tmp_path.joinpath("shards").iterdir()) == [path], "writer left files besides the shard"
    with h5py.File(path, "r") as handle:
        assert check_shard_layout(handle) == []
        attrs = read_shard_attrs(handle)
        assert attrs["task_id"] == "task-0" and attrs["splits"] == ["train"] and attrs["seed"] == 7
        assert attrs["task"]["gender"] == "female"
        assert handle["posed_vertices"].chunks == (1, 50, 3), "expected one chunk per frame"
        for name in ("posed_vertices", "unposed_displacements", "pose"):
            expected = np.stack([f[name] for f in frames]).astype(np.float32)
            np.testing.assert_array_equal(handle[name][()], expected, err_msg=f"{name} differs")
        np.testing.assert_array_equal(handle["frame_index"][()], [0, 3, 6, 9, 12])
        np.testing.assert_array_equal(handle["quality/penetration_fraction"][()],
                                      np.float32([f["quality"]["penetration_fraction"] for f in frames]))
        template = read_template(handle)
    for key, value in tube_template().items():
        np.testing.assert_array_equal(template[key], value, err_msg=f"template {key} differs")


def test_float16_error_is_below_the_stated_bound_for_a_body_sized_garment(tmp_path):
    # A garment spanning 2 m vertically and 1 m across, worn by a body 1 m above the floor
    # and walked 2.5 m away from the world origin: every vertex within 1 m of the pelvis.
    rng = np.random.default_rng(1)
    template = tube_template()
    frames = []
    for k in range(4):
        translation = np.array([2.5, 1.0, -2.5 + 0.1 * k])
        relative = rng.uniform(-0.55, 0.55, (50, 3)) * np.array([1.0, 1.8, 1.0])
        frames.append({"posed_vertices": translation + relative,
                       "unposed_displacements": rng.uniform(-0.05, 0.05, (50, 3)),
                       "pose": rng.normal(size=6), "quality": {"q": 0.0}, "body_translation": translation})
    errors = {}
    for use_translation in (True, False):
        path = tmp_path / f"t{use_translation}.h5"
        with ShardWriter(path, template=template, task=make_task(), precision="float16") as writer:
            for frame in frames:
                frame = dict(frame) if use_translation else {k: v for k, v in frame.items() if k != "body_translation"}
                writer.write_frame(**frame)
        with h5py.File(path, "r") as handle:
            assert handle["posed_vertices"].dtype == np.float16
            assert check_shard_layout(handle) == []
            decoded = decode_positions(handle["posed_vertices"][()], handle["position_origin"][()])
            unposed = handle["unposed_displacements"][()].astype(np.float32)
        posed_error = np.abs(decoded - np.stack([f["posed_vertices"] for f in frames])).max()
        unposed_error = np.abs(unposed - np.stack([f["unposed_displacements"] for f in frames])).max()
        errors[use_translation] = posed_error
        assert 0 < posed_error <= BODY_GARMENT_FLOAT16_TOL_M, (
            f"float16 posed error {posed_error * 1e3:.4f} mm (origin from "
            f"{'body_translation' if use_translation else 'bbox'}) exceeds {BODY_GARMENT_FLOAT16_TOL_M * 1e3:.3f} mm")
        assert unposed_error <= 2.0**-16, f"float16 displacement error {unposed_error * 1e3:.4f} mm"
    # Storing absolute world coordinates in float16 would have been worse here.
    absolute = np.stack([f["posed_vertices"] for f in frames])
    absolute_error = np.abs(absolute.astype(np.float16).astype(np.float64) - absolute).max()
    assert absolute_error > max(errors.values()), (
        f"relative storage ({max(errors.values()) * 1e3:.3f} mm) should beat absolute float16 "
        f"({absolute_error * 1e3:.3f} mm)")
    assert BODY_GARMENT_FLOAT16_TOL_M < FLOAT16_ERROR_BOUND_M


def test_float16_rejects_coordinates_that_would_lose_millimetres(tmp_path):
    template = tube_template()
    with pytest.raises(ValueError, match="float16 shards need"):
        with ShardWriter(tmp_path / "x.h5", template=template, task=make_task(), precision="float16") as writer:
            far = template["rest_vertices"] * 20.0  # 3.6 m across: more than 2 m from the centre
            writer.write_frame(far, np.zeros((50, 3)), np.zeros(6), {})
    assert not (tmp_path / "x.h5").exists()
    assert not list(tmp_path.glob(f"*{TMP_SUFFIX}")), "aborted float16 writer left a temporary file"


def test_exception_inside_writer_leaves_nothing(tmp_path):
    path = shard_path(tmp_path, "task-0")
    frames = frames_for(3)
    with pytest.raises(RuntimeError, match="simulated failure"):
        with ShardWriter(path, template=tube_template(), task=make_task()) as writer:
            writer.write_frame(**frames[0])
            writer.write_frame(**frames[1])
            assert writer.tmp_path.exists(), "writer should be writing to its temporary file"
            raise RuntimeError("simulated failure")
    assert not path.exists(), "final shard exists after an exception"
    assert list(path.parent.iterdir()) == [], f"left files: {list(path.parent.iterdir())}"


def test_interruption_while_the_file_is_created_leaves_nothing(tmp_path, monkeypatch):
    """A Ctrl-C (or SIGTERM raised as one) that lands while h5py creates the temporary file, after
    the file exists on disk but before its handle is returned, leaves no file behind."""
    import data_manifest.shard as shard_module

    real_file = h5py.File

    def created_then_interrupted(name, *args, **kwargs):
        real_file(name, *args, **kwargs).close()
        raise KeyboardInterrupt

    monkeypatch.setattr(shard_module.h5py, "File", created_then_interrupted)
    path = shard_path(tmp_path, "task-0")
    with pytest.raises(KeyboardInterrupt):
        with ShardWriter(path, template=tube_template(), task=make_task()):
            pass
    assert list(path.parent.iterdir()) == [], f"left files: {list(path.parent.iterdir())}"


def test_identical_content_gives_identical_bytes(tmp_path):
    frames = frames_for(3)
    first = write_frames(tmp_path / "a" / "s.h5", frames).record
    time.sleep(1.1)  # HDF5 object timestamps would differ by now if they were stored
    second = write_frames(tmp_path / "b" / "s.h5", frames).record
    assert first.sha256 == second.sha256, "same frames written twice gave different files (not resumable bit-exactly)"


def test_a_template_checked_once_writes_the_bytes_of_the_dict(tmp_path):
    """generate-dataset hands its shard writers the template checked and hashed once
    (CanonicalTemplate): the shard is byte for byte the one written from the plain dict."""
    from data_manifest.schema import CanonicalTemplate, template_sha256

    frames = frames_for(3)
    plain = write_frames(tmp_path / "a" / "s.h5", frames).record
    prepared = CanonicalTemplate.of(tube_template())
    assert prepared.sha256 == template_sha256(tube_template())
    with ShardWriter(tmp_path / "b" / "s.h5", template=prepared, task=make_task()) as writer:
        for k, frame in enumerate(frames):
            writer.write_frame(**frame, frame_index=3 * k)
        writer.record_dropped("penetration", 2)
    assert writer.record.sha256 == plain.sha256
    # a changed template is a different template
    other = dict(tube_template(), rest_vertices=tube_template()["rest_vertices"] + 1e-3)
    assert CanonicalTemplate.of(other).sha256 != prepared.sha256


@pytest.mark.parametrize("case, match", [
    ("shape", r"posed_vertices of task 'task-0' frame 1 must have shape \(50, 3\)"),
    ("nan", "contains NaN"),
    ("pose_length", "pose of task 'task-0' frame 1 must have length 6"),
    ("quality_keys", "must have the metrics"),
    ("frame_order", "frame_index of task 'task-0' frame 1 must be > 5"),
    ("translation", "body_translation of task 'task-0' frame 1 must be given in every frame or in none"),
])
def test_bad_frames_raise_and_leave_nothing(tmp_path, case, match):
    frame = frames_for(1)[0]
    second = dict(frame)
    kwargs = {}
    if case == "shape":
        second["posed_vertices"] = frame["posed_vertices"][:-1]
    elif case == "nan":
        second["unposed_displacements"] = np.full((50, 3), np.nan)
    elif case == "pose_length":
        second["pose"] = np.zeros(5)
    elif case == "quality_keys":
        second["quality"] = {"other": 1.0}
    elif case == "frame_order":
        kwargs["frame_index"] = 5
    elif case == "translation":
        del second["body_translation"]
    path = tmp_path / "s.h5"
    with pytest.raises(ValueError, match=match):
        with ShardWriter(path, template=tube_template(), task=make_task()) as writer:
            writer.write_frame(**frame, frame_index=5)
            writer.write_frame(**second, **kwargs)
    assert list(tmp_path.iterdir()) == [], "a rejected frame left files behind"


@pytest.mark.parametrize("field, value, match", [
    ("task_id", "../escape", "task.task_id"),
    ("splits", "train", "task.splits must be a list"),
    ("seed", -1, "task.seed must be a non-negative integer"),
    ("shape", [[1.0]], "task.shape must be a 1-D array"),
    ("poses", np.zeros((2600, 72)), "keep per-frame arrays such as pose lists out of it"),
    ("fabric", object(), "must be JSON-serializable"),
])
def test_bad_task_fields_are_named(tmp_path, field, value, match):
    task = make_task()
    task[field] = value
    with pytest.raises(ValueError, match=match):
        ShardWriter(tmp_path / "s.h5", template=tube_template(), task=task)


def test_bad_template_is_named(tmp_path):
    template = tube_template()
    template["faces"] = template["faces"] + 100
    with pytest.raises(ValueError, match=r"template.faces must index vertices in \[0, 49\]"):
        ShardWriter(tmp_path / "s.h5", template=template, task=make_task())
    template = tube_template()
    template["skinning_weights"] = template["skinning_weights"][:10]
    with pytest.raises(ValueError, match=r"template.skinning_weights must have shape \(50, J\)"):
        ShardWriter(tmp_path / "s.h5", template=template, task=make_task())


CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from data_manifest.shard import ShardWriter, shard_path
    from data_manifest.synthetic import synthetic_frame, tube_template
    root = sys.argv[1]
    rng = np.random.default_rng(0)
    template = tube_template()
    task = {"task_id": "killed", "garment": "tube", "splits": ["train"], "seed": 0,
            "shape": np.zeros(4), "style": np.zeros(2)}
    with ShardWriter(shard_path(root, "killed"), template=template, task=task) as writer:
        for k in range(100000):
            writer.write_frame(**synthetic_frame(template, rng, translation_m=np.zeros(3)))
            if k == 3:
                print("writing", flush=True)
            time.sleep(0.002)
""")


def test_sigkill_mid_write_leaves_no_trusted_shard(tmp_path):
    write_synthetic_dataset(tmp_path, splits={"train": 1})  # a finished dataset the child adds a task to
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                             cwd=Path(__file__).resolve().parent.parent)
    try:
        line = child.stdout.readline()
        assert line.strip() == "writing", f"child did not start writing (got {line!r})"
        time.sleep(0.05)
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
            child.wait(timeout=30)
    assert child.returncode == -signal.SIGKILL
    final = shard_path(tmp_path, "killed")
    assert not final.exists(), "a killed writer left a file at the final shard path"
    leftovers = list(final.parent.iterdir())
    leftovers = [p for p in leftovers if p.name != "train-000.h5"]
    assert len(leftovers) == 1 and leftovers[0].name.endswith(TMP_SUFFIX), f"leftovers {leftovers}"
    report = validate_dataset(tmp_path)
    assert report.ok and [p.kind for p in report.warnings] == ["orphan_tmp"], str(report)
    assert not Manifest.load(tmp_path).is_complete("killed"), "a killed task must be redone on resume"
    reader = DatasetReader(tmp_path)
    assert [e["task_id"] for e in reader.shard_entries] == ["train-000"], "reader trusts the killed shard"
    assert reader.load_split("train")["posed_vertices"].shape == (4, 50, 3)
    removed = remove_orphan_temporaries(tmp_path)
    assert removed == leftovers and sorted(p.name for p in final.parent.iterdir()) == ["train-000.h5"]


def test_rejected_first_frame_does_not_fix_the_layout(tmp_path):
    """A frame refused with ValueError leaves the writer as it was: the next frame may use
    another pose length and other metrics."""
    template = tube_template()
    frame = frames_for(1)[0]
    with ShardWriter(tmp_path / "s.h5", template=template, task=make_task(), precision="float16") as writer:
        with pytest.raises(ValueError, match="float16 shards need"):
            writer.write_frame(frame["posed_vertices"] * 10, frame["unposed_displacements"], np.zeros(9),
                               {"bad": 1.0}, frame_index=0)
        writer.write_frame(**frame, frame_index=0)
    with h5py.File(tmp_path / "s.h5", "r") as handle:
        assert check_shard_layout(handle) == []
        assert handle["pose"].shape == (1, 6) and sorted(handle["quality"]) == sorted(frame["quality"])
        assert handle.attrs["position_origin_rule"] == "body_translation"


def test_dropped_frames_are_logged_with_their_pose_and_reason(tmp_path):
    """record_dropped(frame_index=, pose=) logs each dropped frame in the shard's `dropped`
    group; the layout check ties the log to filter_stats_json and to the kept frames' indices."""
    frames = frames_for(3)
    path = shard_path(tmp_path, "task-0")
    poses = {1: np.full(6, 0.25), 4: np.full(6, -0.5)}
    with ShardWriter(path, template=tube_template(), task=make_task()) as writer:
        writer.write_frame(**frames[0], frame_index=0)
        writer.record_dropped("penetration", frame_index=4, pose=poses[4])
        writer.record_dropped("nan", frame_index=1, pose=poses[1])
        writer.write_frame(**frames[1], frame_index=3)
        with pytest.raises(ValueError, match="logs all its dropped frames or none"):
            writer.record_dropped("nan")  # a drop without its index, after logged ones
        with pytest.raises(ValueError, match="pose of dropped frame .* must have length 6"):
            writer.record_dropped("nan", frame_index=5, pose=np.zeros(4))
    assert writer.record.filter_stats == {"nan": 1, "penetration": 1}
    with h5py.File(path, "r") as handle:
        assert check_shard_layout(handle) == []
        np.testing.assert_array_equal(handle["dropped/frame_index"][()], [1, 4])  # sorted by index
        assert [r.decode() for r in handle["dropped/reason"][()]] == ["nan", "penetration"]
        np.testing.assert_array_equal(handle["dropped/pose"][()], np.stack([poses[1], poses[4]]).astype(np.float32))
    with h5py.File(path, "r+") as handle:  # a log that disagrees with the counts is reported
        handle.attrs["filter_stats_json"] = '{"nan":2,"penetration":1}'
        assert any("counts" in p for p in check_shard_layout(handle)), check_shard_layout(handle)
        handle.attrs["filter_stats_json"] = '{"nan":1,"penetration":1}'
        handle["dropped/frame_index"][0] = 3  # the index of a kept frame
        assert any("no kept frame has" in p for p in check_shard_layout(handle)), check_shard_layout(handle)
    other = shard_path(tmp_path, "task-1")
    with pytest.raises(ValueError, match="must be unique and differ from the kept frames'"):
        with ShardWriter(other, template=tube_template(), task=make_task("task-1")) as writer:
            writer.write_frame(**frames[2], frame_index=2)
            writer.record_dropped("nan", frame_index=2, pose=np.zeros(6))
    assert not other.exists() and not list(other.parent.glob("*.tmp")), "a refused shard leaves nothing"
    unlogged = shard_path(tmp_path, "task-2")
    with ShardWriter(unlogged, template=tube_template(), task=make_task("task-2")) as writer:
        writer.record_dropped("nan", 2)
        with pytest.raises(ValueError, match="earlier dropped frames were counted without frame_index"):
            writer.record_dropped("nan", frame_index=3, pose=np.zeros(6))
        writer.write_frame(**frames[2], frame_index=0)
    with h5py.File(unlogged, "r") as handle:
        assert "dropped" not in handle and check_shard_layout(handle) == []


def test_a_writer_set_writes_the_bytes_of_lone_writers_and_aborts_only_the_shards_left_open(tmp_path):
    frames = frames_for(3)
    lone = write_frames(shard_path(tmp_path / "lone", "task-0"), frames)
    shards = ShardWriterSet(tmp_path / "set", tube_template())
    for key, task_id in ((0, "task-0"), (1, "task-1")):
        shards.open(key, make_task(task_id))
    with pytest.raises(ValueError, match=r"shard key 1 is already open \(task 'task-1'\)"):
        shards.open(1, make_task("task-1"))
    for k, frame in enumerate(frames):
        for key in (0, 1):
            shards.write_frame(key, **frame, frame_index=3 * k)
    shards.record_dropped(0, "penetration", 2)
    started = time.time() - 5.0
    record = shards.close(0, started_at=started)
    assert record.sha256 == lone.record.sha256 == file_sha256(shard_path(tmp_path / "set", "task-0"))
    assert 5.0 <= record.timings["wall_s"] < 60.0
    assert list(shards.writers) == [1]
    shards.abort()  # task-1 was never closed: its temporary file goes, the closed shard stays
    assert sorted(p.name for p in (tmp_path / "set").rglob("*")) == sorted(
        p.name for p in [shard_path(tmp_path / "set", "task-0"), shard_path(tmp_path / "set", "task-0").parent])
    assert not shards.writers
