"""Motion sequences (docs/motion.md): motion inputs, the procedural generator, the motion schedule,
a tiny motion dataset through generate-dataset on CPU, velocities, PC16 export and import, and
older (schema 1) datasets staying readable."""
from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from simulate.body.base import JOINT_LIMITS, POSE_JOINTS, POSE_SIZE


# -- motion files ------------------------------------------------------------------------------


def _npz(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def test_a_motion_file_is_read_in_the_documented_joint_order(tmp_path):
    from simulate.motion import load_motion

    rng = np.random.default_rng(0)
    poses = rng.uniform(-0.5, 0.5, (7, 20, 3))
    motion = load_motion(_npz(tmp_path / "m.npz", poses=poses, fps=np.array(120.0), joints=np.array(POSE_JOINTS)))
    assert motion.fps == 120.0 and motion.poses.shape == (7, POSE_SIZE) and motion.poses.dtype == np.float32
    # joint j's axis-angle sits at columns 3j..3j+2 (POSE_JOINTS order, what the body model takes)
    np.testing.assert_allclose(motion.poses.reshape(7, 20, 3), poses, rtol=0, atol=1e-7)
    flat = load_motion(_npz(tmp_path / "flat.npz", poses=poses.reshape(7, 60), fps=120))
    np.testing.assert_array_equal(flat.poses, motion.poses)
    # a 120 fps motion at 30 fps: every 4th frame
    np.testing.assert_array_equal(motion.at_rate(30.0).poses, motion.poses[::4])
    with pytest.raises(ValueError, match=r"motion.fps is 50 .* runs at 120 fps; .*whole multiple"):
        motion.at_rate(50.0)


@pytest.mark.parametrize("arrays, message", [
    ({"fps": 30.0}, r"has no array 'poses'"),
    ({"poses": np.zeros((4, 20, 3))}, r"has no array 'fps'"),
    ({"poses": np.zeros((4, 24, 3)), "fps": 30.0}, r"shape \(F, 20, 3\).*got shape \(4, 24, 3\).*pass poses\[:, :20\]"),
    ({"poses": np.zeros((4, 72)), "fps": 30.0}, r"got shape \(4, 72\).*pass poses\[:, :60\]"),
    ({"poses": np.zeros((0, 20, 3)), "fps": 30.0}, r"F >= 1"),
    ({"poses": np.full((2, 20, 3), np.nan), "fps": 30.0}, r"finite \(frame 0, joint pelvis is nan\)"),
    ({"poses": np.full((2, 20, 3), 90.0), "fps": 30.0}, r"radians.*turns 156.*degrees\?"),
    ({"poses": np.zeros((2, 20, 3)), "fps": -1.0}, r"fps must be a number > 0.*got -1.0"),
    ({"poses": np.zeros((2, 20, 3)), "fps": np.array([30.0, 60.0])}, r"fps must be one number"),
    ({"poses": np.zeros((2, 20, 3)), "fps": 30.0, "joints": np.array(POSE_JOINTS[::-1])},
     r"joints is \['right_wrist'.*expected the 20 names pelvis, left_hip"),
])
def test_bad_motion_files_are_refused_naming_the_field_the_value_and_the_expectation(tmp_path, arrays, message):
    from simulate.motion import load_motion

    path = _npz(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError) as info:
        load_motion(path, field="motion.path[1]")
    text = str(info.value)
    assert text.startswith(f"motion.path[1]: {path}") and "\n" not in text, text  # the field and the file
    assert re.search(message, text), text  # the value and what was expected


def test_missing_and_unreadable_motion_files_are_refused(tmp_path):
    from simulate.motion import load_motion

    with pytest.raises(FileNotFoundError, match=r"motion.path: .*nope.npz does not exist"):
        load_motion(tmp_path / "nope.npz")
    (tmp_path / "text.npz").write_text("not a zip")
    with pytest.raises(ValueError, match=r"motion.path: .*text.npz is not a readable .npz file"):
        load_motion(tmp_path / "text.npz")


# -- procedural motions ------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["walk", "arm_raise", "torso_twist", "squat"])
def test_procedural_motions_stay_within_the_joint_limits_and_follow_their_seed(kind):
    from simulate.motion import MOTION_KINDS, procedural_motion

    lo = np.array([[a[0] for a in JOINT_LIMITS[j]] for j in POSE_JOINTS])
    hi = np.array([[a[1] for a in JOINT_LIMITS[j]] for j in POSE_JOINTS])
    one = procedural_motion(kind, 90, 30.0, np.random.default_rng(7), amplitude=1.0)
    poses = one.poses.reshape(-1, 20, 3)
    assert one.poses.shape == (90, POSE_SIZE) and one.fps == 30.0
    assert (poses >= lo - 1e-6).all() and (poses <= hi + 1e-6).all(), "a frame leaves the joint limits"
    moved = {j for j, _, *_ in MOTION_KINDS[kind][1]}
    for k, joint in enumerate(POSE_JOINTS):  # only the kind's joints move, and they do
        span = np.ptp(poses[:, k], axis=0).max()
        assert (span > 0.05) == (joint in moved), (joint, span)
    again = procedural_motion(kind, 90, 30.0, np.random.default_rng(7), amplitude=1.0)
    np.testing.assert_array_equal(again.poses, one.poses)
    other = procedural_motion(kind, 90, 30.0, np.random.default_rng(8), amplitude=1.0)
    assert not np.array_equal(other.poses, one.poses), "the seed must change the motion"
    # a smooth trajectory: no joint turns more than 0.2 rad between 30 fps frames
    assert np.abs(np.diff(poses, axis=0)).max() < 0.2


# -- the motion schedule -----------------------------------------------------------------------


def test_a_motion_schedule_slerps_in_then_records_every_nth_frame():
    from simulate.poses import joint_angle_change
    from simulate.sequence.schedule import RECORD, SETTLE, TRANSITION, build_schedule
    from simulate.sequence.settings import SequenceSettings, SequenceTask

    rng = np.random.default_rng(1)
    poses = rng.uniform(-0.3, 0.3, (5, POSE_SIZE)).astype(np.float32)
    task = SequenceTask(np.zeros((3, 3)), np.zeros((3, 3)), np.ones(2, np.float32), poses, motion_steps=3)
    canonical = np.zeros(POSE_SIZE, np.float32)
    settings = SequenceSettings(shape_transition_frames=2, interpolation_threshold=0.1)
    shapes, seq, kinds, keys = build_schedule(task, canonical, np.zeros(2, np.float32), settings)
    assert list(kinds[:3]) == [TRANSITION, TRANSITION, SETTLE] and np.allclose(shapes[2:], 1.0)
    rec = np.nonzero(kinds == RECORD)[0]
    assert list(keys[rec]) == [0, 1, 2, 3, 4] and (keys[kinds != RECORD] == -1).all()
    np.testing.assert_array_equal(seq[rec], poses)
    # the slerp-in turns no joint more than the threshold per frame; then 3 frames per motion frame
    lead = np.concatenate([canonical[None], seq[3:rec[0] + 1]])
    assert joint_angle_change(lead[:-1], lead[1:]).max() <= 0.1 + 1e-5
    assert list(np.diff(rec)) == [3, 3, 3, 3] and (kinds[rec[0] + 1:] != SETTLE).all()
    between = seq[rec[0] + 1:rec[1]]  # fractions 1/3 and 2/3 of the way from pose 0 to pose 1
    step = joint_angle_change(np.concatenate([poses[:1], between]), np.concatenate([between, poses[1:2]]))
    np.testing.assert_allclose(step, np.broadcast_to(step[:1], step.shape), atol=1e-4)


# -- the spec ----------------------------------------------------------------------------------


BASE = {"name": "m", "garment": {"type": "tshirt"}}


@pytest.mark.parametrize("extra, message", [
    ({"poses": {"source": "motion"}, "motion": {"fps": 25}},
     r"spec.motion.fps must be a rate whose frame time 1/fps is a whole number of simulation.frame_dt.*\(got 25\)"),
    ({"motion": {"fps": 30}}, r"spec.motion is read only when poses.source is motion \(got poses.source 'sampled'\)"),
    ({"poses": {"source": "motion"}, "motion": {"source": "file"}},
     r"spec.motion.path must be a .npz motion file or a non-empty list of them when motion.source is file \(got None\)"),
    ({"poses": {"source": "motion"}, "motion": {"kinds": ["walk", "jog"]}},
     r"spec.motion.kinds\[1\] must be a motion kind .*one of walk, arm_raise, torso_twist, squat\) \(got 'jog'\)"),
    ({"poses": {"source": "motion"}, "motion": {"frames": 0}}, r"spec.motion.frames must be an integer >= 1 \(got 0\)"),
    ({"poses": {"source": "motion"}, "motion": {"amplitude": 1.5}}, r"spec.motion.amplitude must be a number > 0.0 and <= 1.0"),
    ({"poses": {"source": "motion"}, "motion": {"fsp": 30}}, r"spec.motion.fsp is not a known field \(did you mean fps\?\)"),
])
def test_bad_motion_specs_name_the_field_the_value_and_the_expectation(extra, message):
    from pipelines.spec import SpecError, validate_spec

    with pytest.raises(SpecError, match=message):
        validate_spec({**BASE, **extra})


def test_a_spec_without_motions_resolves_as_without_the_section():
    from pipelines.spec import MOTION_DEFAULTS, load_spec, motion_steps, validate_spec

    assert "motion" not in load_spec("quickstart"), "hold specs (and their hashes) carry no motion section"
    spec = validate_spec({**BASE, "poses": {"source": "motion"}, "simulation": {"frame_dt": 0.01}, "motion": {"fps": 25}})
    assert spec["motion"] == {**MOTION_DEFAULTS, "fps": 25} and motion_steps(spec) == 4


def test_a_bad_motion_file_stops_generate_dataset_with_exit_2(tmp_path, capsys):
    import yaml

    from pipelines.cli import main

    bad = _npz(tmp_path / "deg.npz", poses=np.full((3, 20, 3), 45.0), fps=30.0)
    spec = tmp_path / "s.yaml"
    spec.write_text(yaml.safe_dump({**BASE, "poses": {"source": "motion"},
                                    "simulation": {"device": "cpu", "frame_dt": 1.0 / 60.0},
                                    "motion": {"source": "file", "path": [str(bad)], "frames": None}}))
    assert main(["generate-dataset", str(spec), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "motion.path[0]: " in err and "degrees?" in err, err


# -- PC16 --------------------------------------------------------------------------------------


def _header_by_hand(path: Path) -> dict:
    """The 32-byte PC2 header, read with struct alone (written from the layout, not from the
    exporter's code): 12-byte magic, int32 version, int32 points, float32 start frame, float32
    sample rate, int32 samples, little endian."""
    raw = path.read_bytes()
    magic = raw[:12]
    version, points = struct.unpack("<ii", raw[12:20])
    start, rate = struct.unpack("<ff", raw[20:28])
    (samples,) = struct.unpack("<i", raw[28:32])
    return {"magic": magic, "version": version, "points": points, "start": start, "rate": rate,
            "samples": samples, "body": raw[32:]}


def test_pc16_header_and_body_match_the_layout_read_independently(tmp_path):
    from data_manifest.export import import_pc16, write_pc16

    rng = np.random.default_rng(2)
    root = rng.uniform(-3, 3, (4, 3))  # the root wanders metres away: positions stay relative to it
    positions = root[:, None, :] + rng.uniform(-0.9, 0.9, (4, 9, 3))
    faces = np.array([[0, 1, 2], [2, 3, 8]])
    paths = write_pc16(tmp_path / "seq.pc16", positions, root, faces, start_frame=5.0, sample_rate=2.0)
    assert [p.name for p in paths] == ["seq.pc16", "seq.faces.npy", "seq.root.npy"]
    h = _header_by_hand(paths[0])
    assert h["magic"] == b"POINTCACHE2\x00" and h["version"] == 1
    assert (h["points"], h["samples"], h["start"], h["rate"]) == (9, 4, 5.0, 2.0)
    assert len(h["body"]) == 4 * 9 * 3 * 2, "float16 x, y, z per point per sample"
    body = np.frombuffer(h["body"], dtype="<f2").reshape(4, 9, 3).astype(np.float64)
    # within float16 precision of the positions relative to the root: |v| < 1 m -> 2**-12 m
    assert np.abs(body - (positions - root[:, None])).max() <= 2.0 ** -12
    stored_faces = np.load(paths[1])
    assert stored_faces.dtype == np.dtype("<u2") and (stored_faces == faces).all()
    back = import_pc16(paths[0])
    assert back["start_frame"] == 5.0 and back["sample_rate"] == 2.0 and (back["faces"] == faces).all()
    assert np.abs(back["positions"] - positions).max() <= 2.0 ** -12 + 1e-6  # + float32 rounding of the root
    np.testing.assert_array_equal(back["relative"], body.astype(np.float32))


def test_pc16_refuses_what_it_cannot_hold(tmp_path):
    from data_manifest.export import read_pc16, write_pc16

    ok = np.zeros((2, 3, 3))
    with pytest.raises(ValueError, match=r"faces are uint16.*got 70000 vertices"):
        write_pc16(tmp_path / "a.pc16", np.zeros((1, 70000, 3)), np.zeros((1, 3)), np.array([[0, 1, 69999]]))
    with pytest.raises(ValueError, match=r"root must have shape \(2, 3\)"):
        write_pc16(tmp_path / "a.pc16", ok, np.zeros((3, 3)), np.array([[0, 1, 2]]))
    (tmp_path / "short.pc16").write_bytes(b"POINTCACHE2\x00" + b"\x00" * 4)
    with pytest.raises(ValueError, match=r"too short for a PC16 header \(16 bytes, expected 32\)"):
        read_pc16(tmp_path / "short.pc16")
    write_pc16(tmp_path / "b.pc16", ok, np.zeros((2, 3)), np.array([[0, 1, 2]]))
    data = (tmp_path / "b.pc16").read_bytes()
    (tmp_path / "cut.pc16").write_bytes(data[:-2])
    with pytest.raises(ValueError, match=r"has 66 bytes, a PC16 of 2 samples x 3 points needs 68"):
        read_pc16(tmp_path / "cut.pc16")
    assert not list(tmp_path.glob("*.tmp")), "no temporary file stays behind"


# -- older datasets ----------------------------------------------------------------------------


def test_a_schema_1_dataset_stays_readable_and_valid(tmp_path, monkeypatch):
    import data_manifest.manifest as manifest_module
    import data_manifest.shard as shard_module
    from data_manifest.reader import DatasetReader
    from data_manifest.schema import SCHEMA_VERSION
    from data_manifest.synthetic import write_synthetic_dataset
    from data_manifest.validate import validate_dataset

    assert SCHEMA_VERSION == 2
    with monkeypatch.context() as m:  # written as this code wrote it before velocities existed
        m.setattr(shard_module, "SCHEMA_VERSION", 1)
        m.setattr(manifest_module, "SCHEMA_VERSION", 1)
        write_synthetic_dataset(tmp_path / "old")
    manifest = json.loads((tmp_path / "old" / "manifest.json").read_text())
    assert manifest["schema_version"] == 1
    report = validate_dataset(tmp_path / "old")
    assert report.ok, report.errors
    with DatasetReader(tmp_path / "old", verify=True) as reader:
        split = next(iter(reader.splits))
        frame = reader.get(split, 0)
        assert "velocities" not in frame and frame["posed_vertices"].shape[1] == 3
        assert reader.manifest.schema_version == 1 and reader.manifest.to_dict()["schema_version"] == 1
    future = dict(manifest, schema_version=3)
    (tmp_path / "old" / "manifest.json").write_text(json.dumps(future))
    with pytest.raises(ValueError, match=r"schema_version: expected one of 1, 2 \(this drape reads schema versions 1, 2\), got 3"):
        DatasetReader(tmp_path / "old")


def test_velocities_are_written_in_every_frame_or_none(tmp_path):
    from data_manifest.shard import ShardWriter, check_shard_layout, shard_path
    from data_manifest.synthetic import tube_template

    import h5py

    template = tube_template()
    v = template["rest_vertices"].shape[0]
    task = {"task_id": "t", "garment": "tube", "splits": ["train"], "seed": 0, "shape": [0.0], "style": [0.0]}
    with ShardWriter(shard_path(tmp_path, "t"), template=template, task=task, precision="float16") as writer:
        writer.write_frame(np.zeros((v, 3)), np.zeros((v, 3)), [0.0], {}, velocities=np.full((v, 3), 1.5),
                           root_joint=[0.0, 0.9, 0.1])
        with pytest.raises(ValueError, match=r"velocities of task 't' frame 1 must be given in every frame or in none"):
            writer.write_frame(np.zeros((v, 3)), np.zeros((v, 3)), [0.0], {}, root_joint=[0.0, 0.9, 0.1])
        with pytest.raises(ValueError, match=r"root_joint of task 't' frame 1 must be given in every frame or in none"):
            writer.write_frame(np.zeros((v, 3)), np.zeros((v, 3)), [0.0], {}, velocities=np.zeros((v, 3)))
        with pytest.raises(ValueError, match=r"velocities of task 't' frame 1 must have shape"):
            writer.write_frame(np.zeros((v, 3)), np.zeros((v, 3)), [0.0], {}, velocities=np.zeros((v, 2)),
                               root_joint=[0.0, 0.9, 0.1])
    with h5py.File(shard_path(tmp_path, "t"), "r") as handle:
        assert handle["velocities"].dtype == np.float16 and (handle["velocities"][()] == 1.5).all()
        assert handle["root_joint"].shape == (1, 3) and handle["root_joint"].dtype == np.float32
        assert int(handle.attrs["schema_version"]) == 2 and check_shard_layout(handle) == []


# -- a tiny motion dataset through generate-dataset on CPU -------------------------------------

MOTION_FRAMES = 8
MOTION_SPEC = {
    "name": "motion-tiny",
    "seed": 5,
    "garment": {"type": "tshirt", "resolution": 150},
    "styles": {"train": 1, "test": 1},
    "shapes": {"train": [[0.5, 0.5, 0.5, 0.5, 0.5, 0.5]], "test": [[0.5, 0.5, 0.5, 0.6, 0.5, 0.5]]},
    "pairs": {"train": 1, "test": 0},
    "poses": {"source": "motion"},
    "motion": {"kinds": ["arm_raise"], "fps": 30, "frames": MOTION_FRAMES},
    # SequenceSettings.restart_after_rejects (1) would send a world of held targets home after one dropped frame
    "simulation": {"device": "cpu", "worlds": 1, "iterations": 4, "substeps": 5, "tolerance": 0.05,
                   "max_relax_frames": 40, "interpolation_threshold": 0.25, "frame_dt": 1.0 / 60.0},
    "audit": {"samples": 0},
}
TASK = "train_train-p000-m00"


@pytest.fixture(scope="module")
def motion_dataset(tmp_path_factory):
    from pipelines.generate_dataset import generate

    out = tmp_path_factory.mktemp("motion")
    generate(MOTION_SPEC, out, progress=False, log=lambda m: None)
    return out


def test_every_motion_frame_is_recorded_once_with_its_pose_root_and_velocities(motion_dataset):
    from data_manifest.reader import DatasetReader
    from data_manifest.validate import validate_dataset
    from pipelines.generate_dataset import build_context
    from pipelines.spec import validate_spec

    assert validate_dataset(motion_dataset).ok
    manifest = json.loads((motion_dataset / "manifest.json").read_text())
    assert manifest["schema_version"] == 2 and [s["task_id"] for s in manifest["shards"]] == [TASK]
    shard = manifest["shards"][0]
    assert shard["frame_count"] == MOTION_FRAMES and not sum(shard["filter_stats"].values()), shard
    phases = manifest["audit"]["simulation"]["phases"]
    # 30 fps at frame_dt 1/60: one slerp'ed frame, then the recorded one; no hold of any motion frame
    assert phases["motion_world_frames"] == MOTION_FRAMES and phases["hold_world_frames"] == 0, phases
    assert phases["restarts_after_rejects"] == 0
    with DatasetReader(motion_dataset) as reader:
        arrays = reader.load_task(TASK)
    np.testing.assert_array_equal(arrays["frame_index"], np.arange(MOTION_FRAMES))
    plan = build_context(validate_spec(MOTION_SPEC), motion_dataset).plan
    task = plan.tasks[0]
    assert task.task_id == TASK and task.motion_steps == 2 and task.motion == "arm_raise"
    np.testing.assert_array_equal(arrays["pose"], task.poses)  # the motion's frames, in order
    assert np.ptp(arrays["pose"], axis=0).max() > 0.05, "the body moves through the motion"
    # the root joint per frame: the pelvis of the task's body (it does not translate under a pose)
    assert np.ptp(arrays["root_joint"], axis=0).max() < 1e-5 and abs(arrays["root_joint"][0, 1]) < 0.5
    assert "body_translation" not in arrays, "the body is not translated (learners add body_translation after skinning)"
    # velocities [m/s] agree with the positions' finite differences over the frame time 1/30 s far
    # better than a neighbour's frame does (a wrong frame, zeros or m/frame would not)
    x = arrays["posed_vertices"].astype(np.float64)
    v = arrays["velocities"].astype(np.float64)
    fd = (x[1:] - x[:-1]) * 30.0
    own = np.linalg.norm(fd - v[1:], axis=(1, 2)) / np.linalg.norm(fd, axis=(1, 2))
    earlier = np.linalg.norm(fd - v[:-1], axis=(1, 2)) / np.linalg.norm(fd, axis=(1, 2))
    assert (own < earlier).all() and own[2:].max() < 0.3 and np.linalg.norm(fd, axis=2).max() > 0.02, (own, earlier)


def test_a_rejected_motion_frame_is_dropped_and_the_sequence_goes_on_unchanged(motion_dataset, tmp_path, monkeypatch):
    import simulate.sequence as sequence
    from data_manifest.reader import DatasetReader
    from pipelines.generate_dataset import generate

    real = sequence.run_sequences

    def planting(*args, on_frames, **kwargs):
        def corrupt(frames):
            for f in frames:
                if f.key == 3:  # blow frame 3 up (a copy: the simulation's state is not touched)
                    c = f.positions.mean(0)
                    f.positions = c + 2.0 * (f.positions - c)
            return on_frames(frames)

        return real(*args, on_frames=corrupt, **kwargs)

    monkeypatch.setattr(sequence, "run_sequences", planting)
    manifest = generate(MOTION_SPEC, tmp_path, progress=False, log=lambda m: None)
    assert manifest.totals["frames_dropped"] == {"distortion": 1}
    assert manifest.audit["simulation"]["phases"]["restarts_after_rejects"] == 0, "a motion is not sent home"
    with DatasetReader(tmp_path) as reader, DatasetReader(motion_dataset) as clean:
        kept, ref = reader.load_task(TASK), clean.load_task(TASK)
        assert reader.dropped_frames("train_train")["frame_index"].tolist() == [3]
    assert kept["frame_index"].tolist() == [0, 1, 2, 4, 5, 6, 7]
    for name in ("posed_vertices", "velocities", "pose"):  # the frames after it are those of the clean run
        np.testing.assert_array_equal(kept[name], np.delete(ref[name], 3, axis=0))
    # a point cache holds consecutive samples: PC16 export names the gap
    from data_manifest.export import export_task

    with pytest.raises(ValueError, match=r"not consecutive \(frame 2 is followed by 4; 1 gap"):
        export_task(tmp_path, TASK, format="pc16", out=tmp_path / "x.pc16")


def test_pc16_export_of_a_motion_round_trips_within_float16_precision(motion_dataset, tmp_path, capsys):
    from data_manifest.export import import_pc16
    from data_manifest.reader import DatasetReader
    from pipelines.cli import main

    out = tmp_path / "seq"
    assert main(["dataset", "export", str(motion_dataset), "--task", TASK, "--format", "pc16", "--out", str(out)]) == 0
    assert "wrote 3 pc16 file(s)" in capsys.readouterr().out
    h = _header_by_hand(tmp_path / "seq.pc16")
    with DatasetReader(motion_dataset) as reader:
        arrays = reader.load_task(TASK)
        faces = reader.template["faces"]
    x, root = arrays["posed_vertices"], arrays["root_joint"]
    assert (h["magic"], h["version"], h["points"], h["samples"], h["start"]) == (b"POINTCACHE2\x00", 1, x.shape[1], MOTION_FRAMES, 0.0)
    back = import_pc16(tmp_path / "seq.pc16")
    relative = x.astype(np.float64) - root[:, None].astype(np.float64)
    assert np.abs(relative).max() < 1.0
    assert np.abs(back["relative"] - relative).max() <= 2.0 ** -12  # float16 within 1 m of the root joint
    assert np.abs(back["positions"] - x).max() <= 2.0 ** -12 + 1e-6
    np.testing.assert_array_equal(back["faces"], faces)
    np.testing.assert_array_equal(back["root"], root)
    # a shard without the root joint per frame (a dataset of held poses) cannot be made relative to it
    from data_manifest.manifest import Manifest, collect_provenance
    from data_manifest.schema import template_sha256
    from data_manifest.shard import ShardWriter, shard_path
    from data_manifest.synthetic import tube_template

    template, holds = tube_template(), tmp_path / "holds"
    manifest = Manifest.create(holds, name="holds", spec={"n": 1}, template_sha256=template_sha256(template),
                               precision="float32", provenance=collect_provenance(device="cpu", seeds={}),
                               splits={"train": ["t0"]})
    task = {"task_id": "t0", "garment": "tube", "splits": ["train"], "seed": 0, "shape": [0.0], "style": [0.0]}
    with ShardWriter(shard_path(holds, "t0"), template=template, task=task) as writer:
        writer.write_frame(template["rest_vertices"], np.zeros_like(template["rest_vertices"]), [0.0], {})
    manifest.add_shard(writer.record)
    manifest.save()
    assert main(["dataset", "export", str(holds), "--task", "t0", "--format", "pc16", "--out", str(tmp_path / "h.pc16")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "stores no root joint per frame (root_joint)" in err, err


def test_an_exploding_motion_hands_its_remaining_frames_over_as_failed(motion_dataset):
    """No recovery for a motion: the frame it exploded on and every later one come back EXPLODED,
    in order, while a calm motion in the next world records all its frames."""
    import dataclasses

    from pipelines.generate_dataset import build_context, sequence_settings
    from pipelines.spec import validate_spec
    from simulate.quasi_static import WorldStatus
    from simulate.sequence import SequenceTask, run_sequences

    spec = validate_spec(MOTION_SPEC)
    ctx = build_context(spec, motion_dataset)  # the fixture's context: body, garment and drape made once
    task = ctx.plan.tasks[0]
    calm = task.poses[:5]
    jump = calm.copy()
    jump[2:] += ctx.body.pose_from_dict({"spine1": [0.0, 1.2, 0.0]})  # a 1.2 rad twist within one frame
    tasks = [SequenceTask(ctx.style_rest[task.style_index], ctx.style_start[task.style_index], task.shape, poses,
                          motion_steps=1) for poses in (jump, calm)]
    settings = sequence_settings(spec)
    settings = dataclasses.replace(settings, recover_explosions=True,
                                   sim=dataclasses.replace(settings.sim, explosion_speed=3.0))
    frames = []
    stats = run_sequences(ctx.body, ctx.template.faces, tasks, body_faces=ctx.body_faces, settings=settings,
                          device="cpu", on_frame=frames.append, material_uv=ctx.template.face_uv)
    exploded = [(f.key, f.status == WorldStatus.EXPLODED) for f in frames if f.task == 0]
    assert exploded == [(0, False), (1, False), (2, True), (3, True), (4, True)], exploded
    assert stats["recoveries"] == 0 and stats["exploded_speed"] + stats["exploded_stretch"] + stats["exploded_non_finite"] == 1
    assert [(f.key, f.status == WorldStatus.EXPLODED, f.velocities is not None) for f in frames if f.task == 1] == \
        [(k, False, True) for k in range(5)]
