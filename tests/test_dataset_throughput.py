"""The dataset's faster host paths give the bytes of the straightforward ones (docs/dataset-throughput.md):
the anny rest blend without bone orientations, the rest-body cache's eviction, garments made by
worker processes, shard writing on several workers, and a whole tiny motion dataset."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch

from simulate.body.anny_backend import _ZUP_TO_YUP
from simulate.body.base import one_thread_on_cpu


def _reference_rest(body, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """anny's whole rest model (bone orientations too), as the backend read it before: the reference."""
    shape = shape.to(body.device)
    extra = body._no_extra.expand(shape.shape[0], 0)
    coeffs = body.anny_model._get_phenotype_blendshape_coefficients(shape, extra, extra)
    rest = body.anny_model.get_rest_model(coeffs)  # on as many CPU threads as the caller's blend
    rot = _ZUP_TO_YUP.to(shape.device)
    return rest["rest_vertices"] @ rot.T, rest["rest_bone_heads"] @ rot.T


@pytest.fixture(scope="module")
def anny_body():
    from simulate.body import load_body_model

    return load_body_model("anny")


def test_the_rest_blend_gives_the_bits_of_anny_s_whole_rest_model(anny_body):
    shapes = torch.as_tensor(np.random.default_rng(3).uniform(0.0, 1.0, (4, 6)), dtype=torch.float32)
    for batch in (shapes[:1], shapes[1:2], shapes):  # one shape (what the dataset blends) and a batch
        vertices, joints = anny_body._rest_torch(batch)
        ref_vertices, ref_joints = _reference_rest(anny_body, batch)
        assert vertices.shape == ref_vertices.shape and joints.shape == ref_joints.shape
        assert torch.equal(vertices, ref_vertices) and torch.equal(joints, ref_joints)
    # and the blend depends on the shape: a wrong (e.g. neutral) blend would pass the above only by luck
    assert not torch.equal(anny_body._rest_torch(shapes[:1])[0], anny_body._rest_torch(shapes[1:2])[0])


def test_the_rest_cache_drops_the_least_recently_used_shape(anny_body, monkeypatch):
    import simulate.body.base as base

    monkeypatch.setattr(base, "REST_CACHE_SIZE", 3)
    anny_body.__dict__.pop("_rest_cache", None)
    blended = []
    blend = anny_body._rest_torch

    def counting(shape):
        blended.append(shape.numpy().tobytes())
        return blend(shape)

    monkeypatch.setattr(anny_body, "_rest_torch", counting)
    a, b, c, d = (np.full((1, 6), v, np.float32) for v in (0.2, 0.4, 0.6, 0.8))
    try:
        for shape in (a, b, c, a, d):  # a used again before d arrives: b is the least recently used
            anny_body._rest_kept(torch.as_tensor(shape))
        assert len(blended) == 4
        before = len(blended)
        anny_body._rest_kept(torch.as_tensor(np.concatenate([a, c, d])))
        assert len(blended) == before, "a, c and d were kept"
        kept_b, _ = anny_body._rest_kept(torch.as_tensor(b))
        assert len(blended) == before + 1 and blended[-1] == b.tobytes(), "b was dropped and blended again"
        with one_thread_on_cpu("cpu"):  # the cache blends on one thread (see one_thread_on_cpu)
            assert torch.equal(kept_b, _reference_rest(anny_body, torch.as_tensor(b))[0])
    finally:
        anny_body.__dict__.pop("_rest_cache", None)


def test_bodies_kept_ahead_are_not_blended_again_and_stay(anny_body, monkeypatch):
    import simulate.body.base as base

    monkeypatch.setattr(base, "REST_CACHE_SIZE", 2)
    anny_body.__dict__.pop("_rest_cache", None)
    anny_body.__dict__.pop("_rest_capacity", None)
    shapes = np.random.default_rng(5).uniform(0.2, 0.8, (5, 6)).astype(np.float32)
    try:
        assert anny_body.keep_rest(np.concatenate([shapes, shapes[:2]])) == 5  # repeats blended once
        assert anny_body.keep_rest(shapes[1:3]) == 0
        blended = []
        blend = anny_body._rest_torch
        monkeypatch.setattr(anny_body, "_rest_torch", lambda shape: blended.append(1) or blend(shape))
        with torch.no_grad():
            posed = anny_body.pose_torch(shapes[::-1].copy(), np.zeros((5, 60), np.float32))
        assert not blended, "the kept bodies served the posing: none blended again, none dropped"
        with one_thread_on_cpu("cpu"):
            for i, row in enumerate(shapes[::-1]):
                assert torch.equal(posed.rest_vertices[i], _reference_rest(anny_body, torch.as_tensor(row[None]))[0][0])
        with pytest.raises(ValueError, match="shapes must have 6 values"):
            anny_body.keep_rest(np.zeros((2, 5)))
    finally:
        anny_body.__dict__.pop("_rest_cache", None)
        anny_body.__dict__.pop("_rest_capacity", None)


def test_the_bodies_blended_ahead_are_the_shapes_the_schedules_pose(anny_body):
    from pipelines.generate_dataset import keep_schedule_bodies
    from pipelines.spec import validate_spec
    from simulate.sequence import SequenceSettings, SequenceTask
    from simulate.sequence.schedule import build_schedule

    spec = validate_spec(dict(SPEC))
    rng = np.random.default_rng(9)
    tasks = [SequenceTask(rest_vertices=np.zeros((3, 3)), start_vertices=np.zeros((3, 3)), shape=rng.uniform(0, 1, 6),
                          poses=np.zeros((2, 60), np.float32), start_shape=start)
             for start in (None, rng.uniform(0, 1, 6))]  # float64 shapes, as plans give them

    class Recorder:
        shape_default = anny_body.shape_default

        def on_device(self, device):
            return self

        def keep_rest(self, shapes):
            self.kept = {row.tobytes() for row in np.asarray(shapes, np.float32)}
            return len(self.kept)

    recorder = Recorder()
    keep_schedule_bodies(recorder, tasks, spec, "cpu")
    n = SequenceSettings().shape_transition_frames
    canonical, neutral = np.zeros(60, np.float32), np.asarray(anny_body.shape_default, np.float32)
    posed_first = set()
    for t in tasks:
        shapes = build_schedule(t, canonical, neutral, SequenceSettings())[0]
        posed_first |= {row.tobytes() for row in shapes[:n + 1]}  # the transition, then the settle on the shape
        posed_first.add((neutral if t.start_shape is None else np.asarray(t.start_shape, np.float32)).tobytes())
    assert recorder.kept == posed_first and len(posed_first) == 2 * (n + 1)


def test_garment_workers_are_one_per_eight_garments_up_to_one_per_cpu():
    from pipelines.styled_garments import worker_count

    assert [worker_count(n, cpus=16) for n in (1, 7, 8, 40, 500)] == [1, 1, 1, 5, 16]
    assert worker_count(500, cpus=1) == 1


def _tube_template(v: int = 24) -> dict:
    angle = np.linspace(0.0, 2 * np.pi, v // 2, endpoint=False)
    ring = np.stack([np.cos(angle), np.zeros_like(angle), np.sin(angle)], 1) * 0.1
    vertices = np.concatenate([ring, ring + [0.0, 0.2, 0.0]]).astype(np.float32)
    n = v // 2
    faces = np.array([f for i in range(n) for f in ((i, (i + 1) % n, n + i), ((i + 1) % n, n + (i + 1) % n, n + i))],
                     np.int32)
    return {"faces": faces, "rest_vertices": vertices, "skinning_weights": np.ones((v, 1), np.float32),
            "body_vertex_index": np.zeros(v, np.int64), "uv": np.zeros((v, 2), np.float32)}


def _write_shards(out, lanes: int) -> dict[str, str]:
    """Eight shards of a few frames each, frames of different shards interleaved as a batch
    delivers them, through ``lanes`` writer threads; returns task id -> sha256."""
    from data_manifest.background import WriterLanes
    from data_manifest.shard import ShardWriterSet

    template = _tube_template()
    rng = np.random.default_rng(11)
    writers = WriterLanes(lanes, mode="thread")
    writers.create("shards", ShardWriterSet, out, template, precision="float16", compression="lzf")
    for i in range(8):
        writers.lane(i).call("shards", ShardWriterSet.open, i, {
            "task_id": f"train_train-p{i:03d}-m00", "garment": "top", "splits": ["train_train"], "seed": 0,
            "shape": np.full(6, 0.5), "style": np.zeros(3)})
    for k in range(5):
        for i in range(8):
            if (i + k) % 4 == 3:
                writers.lane(i).call("shards", ShardWriterSet.record_dropped, i, "self_intersection", frame_index=k,
                                     pose=rng.normal(size=60))
                continue
            writers.lane(i).call("shards", ShardWriterSet.write_frame, i, rng.normal(size=(24, 3)).astype(np.float32) * 0.2,
                                 rng.normal(size=(24, 3)) * 0.01, rng.normal(size=60), {"penetration_max_m": float(k)},
                                 frame_index=k, velocities=rng.normal(size=(24, 3)).astype(np.float32),
                                 root_joint=rng.normal(size=3))
    for i in range(8):
        writers.lane(i).call_collect("shards", ShardWriterSet.close, i)
    records = writers.close()
    return {r.task_id: r.sha256 for r in records}


def test_shards_written_on_several_workers_are_the_bytes_of_one(tmp_path):
    one = _write_shards(tmp_path / "one", 1)
    three = _write_shards(tmp_path / "three", 3)
    assert len(one) == 8 and one == three
    for task, digest in one.items():  # the records name the files' own bytes
        path = tmp_path / "three" / "shards" / f"{task}.h5"
        assert hashlib.sha256(path.read_bytes()).hexdigest() == digest


# -- a whole tiny motion dataset: the fast paths against the straightforward ones -----------------

SPEC = {
    "name": "throughput-tiny",
    "seed": 2,
    "garment": {"type": "top", "resolution": 150, "tightness": [0.02, 0.05]},
    "styles": {"train": 1, "test": 1},
    "shapes": {"train": 1, "test": 1},
    "pairs": {"train": 1, "test": 1},
    "poses": {"source": "motion"},
    "motion": {"kinds": ["arm_raise", "walk"], "fps": 30, "frames": 3},
    "simulation": {"device": "cpu", "worlds": 2, "iterations": 4, "substeps": 4, "tolerance": 0.05,
                   "max_relax_frames": 10, "interpolation_threshold": 0.25, "frame_dt": 1.0 / 60.0},
    "filters": {"max_self_intersections": 10},
    "audit": {"samples": 0},
}


def _generate(out, monkeypatch, *, reference: bool) -> list[tuple[str, str]]:
    import data_manifest.background as background
    import pipelines.generate_dataset as gd
    import pipelines.styled_garments as sg
    from simulate.body.anny_backend import AnnyBody, anny_on
    from simulate.body import load_body_model

    gd._CONTEXTS.clear()  # a context keeps its garments and drapes; bodies keep their blended shapes
    for body in {id(b): b for b in (anny_on("cpu"), load_body_model("anny"))}.values():
        body.__dict__.pop("_rest_cache", None)
        body.__dict__.pop("_rest_capacity", None)
    with monkeypatch.context() as patch:
        if reference:  # anny's whole rest model, one shard writer
            patch.setattr(AnnyBody, "_rest_torch", _reference_rest)
            patch.setattr(background, "lane_count", lambda mode, cpus=None: 1)
        else:  # two shard writers (threads on the CPU), the garments by two worker processes
            patch.setattr(background, "lane_count", lambda mode, cpus=None: 2)  # while the schedules'
            patch.setattr(sg, "worker_count", lambda garments, cpus=None: 2)  # bodies are blended here
        gd.generate(SPEC, out, progress=False, log=lambda m: None)
    gd._CONTEXTS.clear()
    manifest = json.loads((out / "manifest.json").read_text())
    return sorted((s["task_id"], s["sha256"]) for s in manifest["shards"])


def test_a_tiny_motion_dataset_is_the_bytes_the_straightforward_paths_write(tmp_path, monkeypatch):
    from simulate.body.anny_backend import anny_on

    reference = _generate(tmp_path / "reference", monkeypatch, reference=True)
    fast = _generate(tmp_path / "fast", monkeypatch, reference=False)
    assert len(reference) == 2 and fast == reference
    assert anny_on("cpu").__dict__.pop("_rest_capacity", 0) > 0, "the fast run blended its schedules' bodies ahead"
    anny_on("cpu").__dict__.pop("_rest_cache", None)
    # the garments the workers made are those one process makes (a garment the cache holds for
    # both runs would make the shards agree whatever the workers returned)
    ref_cache, fast_cache = (next((tmp_path / run / "cache").glob("garments-*.npz")) for run in ("reference", "fast"))
    with np.load(ref_cache) as ref_z, np.load(fast_cache) as fast_z:
        assert ref_z["style_rest"].tobytes() == fast_z["style_rest"].tobytes()
        assert ref_z["style_start"].tobytes() == fast_z["style_start"].tobytes()
    # the shards hold motion frames (not empty files that would trivially agree)
    from data_manifest.reader import DatasetReader

    with DatasetReader(tmp_path / "fast") as reader:
        arrays = reader.load_task(reference[0][0])
    assert arrays["posed_vertices"].shape[0] >= 1 and "velocities" in arrays
