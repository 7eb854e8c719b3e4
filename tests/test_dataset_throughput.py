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


def test_garments_made_by_worker_processes_are_the_bytes_of_one_process(anny_body):
    from simulate.garment.style import sample_styles
    from simulate.garment.templates import make_template

    from pipelines.styled_garments import styled_garments, worker_count

    template = make_template("top", anny_body, resolution=200)
    styles = sample_styles("top", 3, seed=7)
    jobs = [(styles[0], None), (styles[1], np.array([0.3, 0.5, 0.6, 0.7, 0.4, 0.5], np.float32)), (styles[2], None)]
    here = styled_garments("top", jobs, anny_body, template, backend="anny", workers=1)
    spread = styled_garments("top", jobs, anny_body, template, backend="anny", workers=2)
    assert here.shape == (3, len(template.vertices), 3) and here.dtype == np.float32
    assert here.tobytes() == spread.tobytes()
    assert not np.array_equal(here[0], here[2]), "two styles make two garments"
    assert worker_count(7, cpus=16) == 1 and worker_count(500, cpus=16) == 16 and worker_count(40, cpus=16) == 5


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
    from simulate.body.anny_backend import AnnyBody, anny_on
    from simulate.body import load_body_model

    gd._CONTEXTS.clear()  # a context keeps its garments and drapes; bodies keep their blended shapes
    for body in {id(b): b for b in (anny_on("cpu"), load_body_model("anny"))}.values():
        body.__dict__.pop("_rest_cache", None)
    with monkeypatch.context() as patch:
        if reference:  # anny's whole rest model, one shard writer
            patch.setattr(AnnyBody, "_rest_torch", _reference_rest)
            patch.setattr(background, "lane_count", lambda mode, cpus=None: 1)
        else:  # two shard writers (threads on the CPU); garments by workers: tested above
            patch.setattr(background, "lane_count", lambda mode, cpus=None: 2)
        gd.generate(SPEC, out, progress=False, log=lambda m: None)
    gd._CONTEXTS.clear()
    manifest = json.loads((out / "manifest.json").read_text())
    return sorted((s["task_id"], s["sha256"]) for s in manifest["shards"])


def test_a_tiny_motion_dataset_is_the_bytes_the_straightforward_paths_write(tmp_path, monkeypatch):
    reference = _generate(tmp_path / "reference", monkeypatch, reference=True)
    fast = _generate(tmp_path / "fast", monkeypatch, reference=False)
    assert len(reference) == 2 and fast == reference
    # the shards hold motion frames (not empty files that would trivially agree)
    from data_manifest.reader import DatasetReader

    with DatasetReader(tmp_path / "fast") as reader:
        arrays = reader.load_task(reference[0][0])
    assert arrays["posed_vertices"].shape[0] >= 1 and "velocities" in arrays
