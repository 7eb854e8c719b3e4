"""CLOTH3D-style datasets (seed 004, Sec. 3.2-3.3): every garment type of one multi-type spec as
its own dataset, fabrics drawn per style and stored, tightness drawn per pair (the garment sized
for shape + tau, the body blending from there to the shape in the driver), motion sequences, and
the shipped specs."""
from __future__ import annotations

import json

import numpy as np
import pytest

CLOTH3D_TYPES = ["top", "tshirt", "dress", "jumpsuit", "skirt", "pants"]
FABRICS = ["cotton", "silk", "denim", "leather"]
TIGHTNESS = [[0.03, 0.05], [0.3, 0.4]]  # looser only: every garment is sized larger than its body
FRAMES = 3
MULTI_SPEC = {
    "name": "c3-tiny",
    "seed": 1,
    "garment": {"type": CLOTH3D_TYPES, "resolution": 100, "fabric": FABRICS, "tightness": TIGHTNESS},
    "styles": {"train": 2, "test": 1, "limb_profiles": True},
    "shapes": {"train": 1, "test": 1},
    "pairs": {"train": 1, "test": 0},
    "poses": {"source": "motion"},
    "motion": {"kinds": ["arm_raise"], "fps": 30, "frames": FRAMES},
    "simulation": {"device": "cpu", "worlds": 1, "iterations": 3, "substeps": 3, "tolerance": 0.1,
                   "max_relax_frames": 15, "interpolation_threshold": 0.5, "frame_dt": 1.0 / 60.0},
    # 100-vertex garments fold coarsely: the run is about the wiring, not the drape's fidelity, so
    # only exploded frames are dropped and every type keeps its frames
    "filters": {"max_self_intersections": 100_000, "max_distorted_fraction": 1.0, "max_penetration_fraction": 1.0},
    "audit": {"samples": 0},
}
TASK = "train_train-p000-m00"


@pytest.fixture(scope="module")
def multi_dataset(tmp_path_factory):
    from pipelines.generate_dataset import generate

    out = tmp_path_factory.mktemp("cloth3d")
    manifests = generate(MULTI_SPEC, out, progress=False, log=lambda m: None)
    return out, manifests


def _type_context(out, gtype):
    from pipelines.generate_dataset import build_context
    from pipelines.spec import type_specs, validate_spec

    sub = dict(type_specs(validate_spec(MULTI_SPEC)))[gtype]
    return build_context(sub, out / gtype)  # the run's context (cached in this process)


def test_each_cloth3d_type_becomes_a_valid_motion_dataset_listed_in_datasets_json(multi_dataset):
    from data_manifest.reader import DatasetReader
    from data_manifest.validate import validate_dataset
    from simulate.garment.style import OPTIONAL_STYLE_SPECS, STYLE_SPECS

    out, manifests = multi_dataset
    index = json.loads((out / "datasets.json").read_text())
    assert index["format"] == "drape-datasets" and index["name"] == "c3-tiny"
    assert [d["type"] for d in index["datasets"]] == CLOTH3D_TYPES and all(d["complete"] for d in index["datasets"])
    assert sorted(manifests) == sorted(CLOTH3D_TYPES)
    for gtype in CLOTH3D_TYPES:
        assert validate_dataset(out / gtype).ok, gtype
        manifest = json.loads((out / gtype / "manifest.json").read_text())
        assert manifest["name"] == f"c3-tiny-{gtype}" and manifest["spec"]["garment"]["type"] == gtype
        assert [s["task_id"] for s in manifest["shards"]] == [TASK]
        entry = next(d for d in index["datasets"] if d["type"] == gtype)
        assert entry["path"] == gtype and entry["frames_kept"] == manifest["totals"]["frames_kept"]
        with DatasetReader(out / gtype) as reader:
            arrays = reader.load_task(TASK)
            dropped = reader.dropped_frames("train_train")
        # every motion frame is recorded, in order, with its velocities
        assert arrays["frame_index"].tolist() == list(range(FRAMES)) and len(dropped["frame_index"]) == 0, gtype
        assert arrays["velocities"].shape == arrays["posed_vertices"].shape
        np.testing.assert_array_equal(arrays["pose"], _type_context(out, gtype).plan.tasks[0].poses)
        # styles of the types with an optional width profile carry it (limb_profiles), others not
        width = len(STYLE_SPECS[gtype]) + len(OPTIONAL_STYLE_SPECS.get(gtype, {}))
        ctx = _type_context(out, gtype)
        assert ctx.plan.style_vectors.shape[1] == width, gtype
    assert all(m.totals["frames_kept"] == FRAMES for m in manifests.values())


def test_fabrics_are_drawn_per_style_from_the_list_and_stored(multi_dataset):
    from data_manifest.reader import DatasetReader

    out, _ = multi_dataset
    drawn = []
    for gtype in CLOTH3D_TYPES:
        ctx = _type_context(out, gtype)
        fabrics = ctx.plan.fabrics
        assert len(fabrics) == len(ctx.plan.styles) == 3 and set(fabrics) <= set(FABRICS)
        if gtype in ("top", "tshirt"):  # upper-body garments are cotton or silk (seed 004)
            assert set(fabrics) <= {"cotton", "silk"}, fabrics
            assert ctx.spec["garment"]["fabric"] == ["cotton", "silk"]
        task = ctx.plan.tasks[0]
        with DatasetReader(out / gtype) as reader:
            assert reader.task_info(TASK)["fabric"] == task.fabric == fabrics[task.style_index]
        drawn += fabrics
    assert len(set(drawn)) >= 3, f"18 draws from four fabrics gave {set(drawn)}"
    # the draw follows the seed: a second plan gives the same fabrics, another seed others
    from pipelines.dataset_plan import plan_dataset
    from pipelines.spec import type_specs, validate_spec

    ctx = _type_context(out, "dress")
    sub = dict(type_specs(validate_spec(MULTI_SPEC)))["dress"]
    assert plan_dataset(sub, ctx.body).fabrics == ctx.plan.fabrics
    others = [plan_dataset({**sub, "seed": s}, ctx.body).fabrics for s in range(2, 6)]
    assert any(f != ctx.plan.fabrics for f in others)


def test_tightness_sizes_each_pair_s_garment_larger_and_is_stored(multi_dataset):
    from data_manifest.reader import DatasetReader
    from simulate.garment.templates import generate_garment
    from simulate.garment.tightness import sized_shape

    out, _ = multi_dataset
    for gtype in CLOTH3D_TYPES:
        ctx = _type_context(out, gtype)
        task = ctx.plan.tasks[0]
        tau = ctx.plan.tightness[task.pair]
        assert TIGHTNESS[0][0] <= tau[0] <= TIGHTNESS[0][1] and TIGHTNESS[1][0] <= tau[1] <= TIGHTNESS[1][1]
        np.testing.assert_allclose(task.start_shape, sized_shape(ctx.body, task.shape, tau))
        with DatasetReader(out / gtype) as reader:
            arrays = reader.load_task(TASK)
            item = reader.get("train_train", 0) if reader.num_frames("train_train") else None
        assert arrays["tightness"].shape == (FRAMES, 2) and arrays["sized_shape"].shape == arrays["shape"].shape
        np.testing.assert_allclose(arrays["tightness"], np.tile(tau, (FRAMES, 1)), rtol=1e-6)
        np.testing.assert_allclose(arrays["sized_shape"][0], task.start_shape, rtol=1e-6)
        np.testing.assert_allclose(arrays["shape"][0], task.shape, rtol=1e-6)  # the frames are on the shape
        assert item["fabric"] == task.fabric and item["tightness"].shape == (2,)
        if gtype not in ("top", "skirt"):  # (the rest geometry of one embedded and one ring-grid type)
            continue
        # the garment's rest geometry is that of the style on shape + tau: wider than on the shape
        rest = ctx.style_rest[task.garment_index]
        on_beta = generate_garment(gtype, ctx.plan.styles[task.style_index], ctx.body, template=ctx.template,
                                   shape=task.shape)

        def girth(v):  # mean horizontal distance from the garment's vertical axis [m]
            return float(np.linalg.norm(v[:, [0, 2]] - v[:, [0, 2]].mean(0), axis=1).mean())

        assert girth(rest) > girth(on_beta) + 0.002, (gtype, girth(rest), girth(on_beta))


class _PoseSpy:
    """A body model whose posing records the shapes it is asked for (the driver's bodies)."""

    def __init__(self, body):
        self._body, self.shapes = body, []

    def __getattr__(self, name):
        return getattr(self._body, name)

    def on_device(self, device):
        inner, spy = self._body.on_device(device), self

        class Poser:
            def __getattr__(self, name):
                return getattr(inner, name)

            def pose_torch(self, shapes, poses):
                spy.shapes.append(np.array(shapes, np.float32, copy=True))
                return inner.pose_torch(shapes, poses)

        return Poser()


def test_the_driver_starts_on_shape_plus_tightness_and_blends_to_the_shape(multi_dataset):
    import torch

    from simulate.garment.tightness import shape_blend
    from simulate.sequence import SequenceTask, run_sequences

    out, _ = multi_dataset
    ctx = _type_context(out, "skirt")
    t = ctx.plan.tasks[0]
    task = SequenceTask(rest_vertices=ctx.style_rest[t.garment_index], start_vertices=ctx.style_start[t.garment_index],
                        shape=t.shape, poses=t.poses[:1], fabric=t.fabric, start_shape=t.start_shape,
                        motion_steps=t.motion_steps)
    spy = _PoseSpy(ctx.body)
    frames = []
    from pipelines.generate_dataset import sequence_settings

    settings = sequence_settings(ctx.spec)
    with torch.no_grad():
        run_sequences(spy, ctx.template.faces, [task], body_faces=ctx.body_faces, settings=settings, device="cpu",
                      on_frame=frames.append, material_uv=ctx.template.face_uv)
    posed = np.concatenate(spy.shapes)
    # the start body is shape + tau (the garment's canonical drape was made on it), not the neutral shape
    np.testing.assert_allclose(spy.shapes[0][0], t.start_shape, atol=1e-6)
    assert not np.allclose(t.start_shape, ctx.body.shape_default)
    # then the transition's bodies: start + (shape - start) k / n, k = 1..n, ending on the shape
    n = settings.shape_transition_frames
    blend = shape_blend(t.start_shape, t.shape, n)
    first = [int(np.argmin(np.abs(posed - b).max(1))) for b in blend]
    assert all(np.abs(posed[i] - b).max() < 1e-5 for i, b in zip(first, blend)) and first == sorted(first)
    # the recorded frame is on the shape itself
    assert len(frames) == 1
    rest_on_shape = np.asarray(ctx.body.pose(t.shape[None], ctx.body.canonical_pose[None]).rest_vertices)[0]
    np.testing.assert_allclose(frames[0].rest_body_vertices, rest_on_shape, atol=1e-5)


def test_a_multi_type_spec_is_checked_and_split_per_type():
    from pipelines.spec import SpecError, type_specs, validate_spec

    spec = validate_spec(MULTI_SPEC)
    parts = type_specs(spec)
    assert [t for t, _ in parts] == CLOTH3D_TYPES
    for gtype, sub in parts:
        assert sub["garment"]["type"] == gtype and sub["name"] == f"c3-tiny-{gtype}" and sub["seed"] == 1
        assert sub["garment"]["fabric"] == (["cotton", "silk"] if gtype in ("top", "tshirt") else FABRICS)
    single = validate_spec({**MULTI_SPEC, "garment": {**MULTI_SPEC["garment"], "type": "dress"}})
    assert type_specs(single) == [("dress", single)]
    for garment, styles, expected in (
            ({"type": ["top", "cape"]}, None, "spec.garment.type[1] must be one of"),
            ({"type": ["top", "top"]}, None, "spec.garment.type must be a list without repeated types"),
            ({"type": []}, None, "spec.garment.type must be one of tshirt"),
            ({"type": ["top", "skirt"], "fabric": ["denim"]}, None,
             "spec.garment.fabric must be a list naming cotton or silk for the upper-body types"),
            ({"type": ["top", "skirt"]}, {"train": [{"length": 0.5}]}, "spec.styles.train must be a count >= 1 when"),
            ({"type": "pants"}, {"limb_profiles": "yes"}, "spec.styles.limb_profiles must be true or false")):
        raw = {"name": "t", "garment": garment, **({"styles": styles} if styles else {})}
        with pytest.raises(SpecError) as info:
            validate_spec(raw)
        assert expected in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_style_vectors_carry_the_width_profile_only_where_styles_use_it():
    from simulate.garment.style import StyleParams, sample_styles

    plain = StyleParams("tshirt", {"length": 0.5})
    assert len(plain.as_array()) == 4 and not plain.uses_optional()
    profiled = StyleParams("tshirt", {"widen": 0.03})
    assert profiled.uses_optional() and len(profiled.as_array()) == 4
    assert profiled.as_array(optional=True)[4:] == [0.0, 1.0, 0.03]  # taper, widen_at defaults, widen given
    assert len(StyleParams("jumpsuit", {}).as_array(optional=True)) == len(StyleParams("jumpsuit", {}).as_array())
    # sampled styles without the profile keep their vectors
    assert [s.as_array() for s in sample_styles("pants", 3, seed=4)] == \
        [s.as_array(optional=False) for s in sample_styles("pants", 3, seed=4)]


def test_every_shipped_spec_validates():
    from pathlib import Path

    from simulate.poses import default_pose_joints
    from pipelines.spec import load_spec, type_specs

    names = sorted(p.stem for p in (Path(__file__).parents[1] / "pipelines" / "configs").glob("*.yaml"))
    assert {"quickstart", "tailornet-tshirt", "tailornet-shirt", "tailornet-pants", "tailornet-skirt",
            "cloth3d-mini", "cloth3d"} <= set(names)
    specs = {n: load_spec(n) for n in names}
    for gtype in ("shirt", "pants", "skirt"):
        spec = specs[f"tailornet-{gtype}"]
        assert spec["garment"]["type"] == gtype and spec["poses"]["joints"] == default_pose_joints(gtype)
        assert spec["shapes"]["train"] == "tailornet9" and spec["pairs"]["train"] == 9
        tshirt = specs["tailornet-tshirt"]
        assert spec["simulation"] == tshirt["simulation"] and spec["filters"] == tshirt["filters"]
        frames = 9 * (2600 + 179) + 4 * (spec["splits"]["test_train"] + spec["splits"]["test_test"])
        assert frames == 25_675  # the count the spec's comment states
    for name in ("cloth3d-mini", "cloth3d"):
        spec = specs[name]
        assert spec["garment"]["type"] == CLOTH3D_TYPES and spec["poses"]["source"] == "motion"
        assert spec["garment"]["fabric"] == FABRICS and spec["garment"]["tightness"] is not None
        assert len(type_specs(spec)) == 6
    full = specs["cloth3d"]
    sequences = 6 * (full["pairs"]["train"] + full["pairs"]["test"]) * full["motion"]["per_pair"]
    assert sequences == 3_000 and sequences * full["motion"]["frames"] == 180_000  # the comment's counts


def test_validate_and_info_take_a_multi_type_run_and_a_rerun_resumes_it(multi_dataset, capsys):
    from data_manifest.cli import main
    from pipelines.generate_dataset import generate

    out, manifests = multi_dataset
    hashes = {t: [s["sha256"] for s in m.shards] for t, m in manifests.items()}
    assert main(["dataset", "validate", str(out), "--no-checksum"]) == 0
    text = capsys.readouterr().out
    assert all(f"== {t}: {out / t}" in text for t in CLOTH3D_TYPES), text
    assert main(["dataset", "info", str(out)]) == 0
    assert "== dress" in capsys.readouterr().out
    logs = []
    again = generate(MULTI_SPEC, out, progress=False, log=logs.append)  # every type complete: nothing simulated
    assert {t: [s["sha256"] for s in m.shards] for t, m in again.items()} == hashes
    assert not any(line.startswith("simulating") and "0 tasks" not in line for line in logs), logs
