"""CLOTH3D-style garments (seed 004): rest shapes of sampled styles of every type without
flipped or collapsed triangles, the sewn dress and jumpsuit, tightness, fabrics, spec fields."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.garment import mesh_ops
from simulate.garment.style import GARMENT_TYPES, StyleParams, sample_styles
from simulate.garment.templates import BOUNDARY_NAMES, apply_style, make_template

#: Low resolution (subdivision level 0 / small grids) keeps the tests fast.
TEST_RESOLUTION = 500
#: A triangle is collapsed when its area is below this share of the mesh's median face area.
COLLAPSED_AREA_FRACTION = 0.01
#: A triangle is flipped when its normal points more than 120 degrees away from the area-weighted
#: mean normal of its edge-adjacent faces (cosine below this): an inverted triangle points ~180
#: degrees away. Sharp creases stay below it (the shorts' slide folds ~102 degrees at the shortest
#: legs with 4 cm looseness and flare).
FLIPPED_COSINE = -0.5
STYLES_PER_TYPE = 2


@pytest.fixture(scope="module")
def templates(anny_body):
    return {t: make_template(t, anny_body, resolution=TEST_RESOLUTION) for t in GARMENT_TYPES}


def _face_quality(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """(smallest face area / median face area, smallest cosine between a face normal and the mean
    normal of its edge-adjacent faces)."""
    v = np.asarray(vertices, np.float64)
    cross = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    area = np.linalg.norm(cross, axis=1)
    unit = cross / np.maximum(area, 1e-30)[:, None]
    _, fe = mesh_ops.unique_edges(faces)
    flat = fe.ravel()
    order = np.argsort(flat, kind="stable")
    same = flat[order][1:] == flat[order][:-1]
    fa, fb = order[:-1][same] // 3, order[1:][same] // 3
    around = np.zeros_like(cross)
    np.add.at(around, fa, cross[fb])
    np.add.at(around, fb, cross[fa])
    around /= np.maximum(np.linalg.norm(around, axis=1), 1e-30)[:, None]
    return float(area.min() / np.median(area)), float((unit * around).sum(1).min())


@pytest.mark.parametrize("garment_type", GARMENT_TYPES)
def test_sampled_rest_shapes_have_no_flipped_or_collapsed_triangles(templates, anny_body, garment_type):
    tpl = templates[garment_type]
    styles = sample_styles(garment_type, STYLES_PER_TYPE, seed=7, optional=True)
    for style in styles:
        v = apply_style(tpl, style, anny_body)
        assert v.shape == (tpl.vertex_count, 3) and np.isfinite(v).all()
        area_ratio, cosine = _face_quality(v, tpl.faces)
        assert area_ratio > COLLAPSED_AREA_FRACTION, f"{garment_type} {style.values}: collapsed face ({area_ratio:.4f})"
        assert cosine > FLIPPED_COSINE, f"{garment_type} {style.values}: flipped face (cosine {cosine:.3f})"


@pytest.mark.parametrize("garment_type", ["top", "dress", "jumpsuit"])
def test_new_types_manifold_oriented_with_named_loops(templates, garment_type):
    tpl = templates[garment_type]
    ok, reason = mesh_ops.is_manifold(tpl.faces, tpl.vertex_count)
    assert ok, reason
    assert mesh_ops.oriented_consistently(tpl.faces), "faces are not consistently oriented"
    assert len(np.unique(mesh_ops.face_components(tpl.faces))) == 1, "more than one connected component"
    assert tpl.boundary_names == list(BOUNDARY_NAMES[garment_type])
    assert len(mesh_ops.boundary_loops(tpl.faces)) == len(BOUNDARY_NAMES[garment_type])
    centre = {n: tpl.vertices[tpl.boundary(n)].mean(0) for n in tpl.boundary_names}
    assert centre["left_armhole"][0] > 0 > centre["right_armhole"][0]
    assert set(np.unique(tpl.vertex_panel)) == set(range(len(tpl.panel_names))), "a panel has no vertex"
    # outward: the signed volume of the garment closed by fans over its loops is positive
    assert np.isfinite(tpl.face_uv).all() and (tpl.face_uv >= 0).all() and (tpl.face_uv <= 1).all()


@pytest.mark.parametrize("garment_type", ["dress", "jumpsuit"])
def test_sewn_seam_is_matched_and_manifold(templates, anny_body, garment_type):
    tpl = templates[garment_type]
    seam, piece, faces = tpl.seam, tpl.piece, tpl.faces
    assert len(seam) >= 8 and (piece[seam] == 0).all() and (piece == 1).any()
    lower = (piece[faces] == 1).any(1)
    pairs = np.stack([seam, np.roll(seam, -1)], 1)
    edges, counts = mesh_ops.edge_face_counts(faces)
    lookup = {tuple(e): c for e, c in zip(edges.tolist(), counts.tolist())}
    for a, b in pairs.tolist():
        key = (min(a, b), max(a, b))
        assert lookup.get(key) == 2, f"seam edge {key} is in {lookup.get(key)} faces, expected 2"
        touching = np.nonzero((faces == a).any(1) & (faces == b).any(1))[0]
        assert sorted(lower[touching].tolist()) == [False, True], "a seam edge must join an upper and a lower face"
    # no duplicate seam vertices: no other vertex sits on a seam vertex
    v = apply_style(tpl, StyleParams(garment_type, {}), anny_body)
    d = np.linalg.norm(v[seam][:, None] - v[None], axis=2)
    d[np.arange(len(seam)), seam] = np.inf
    assert d.min() > 1e-4, f"a vertex duplicates a seam vertex ({d.min():.2e} m apart)"


def test_sew_loops_aligns_reversed_loops_and_refuses_mismatch():
    # two rings of a cylinder: a above (rows 0-1), b below (rows 1-2), b's loop given reversed and shifted
    cols = 6
    ang = 2 * np.pi * np.arange(cols) / cols

    def ring(y):
        return np.stack([np.sin(ang), np.full(cols, y), np.cos(ang)], 1)

    def band(top, bottom):
        a, b = np.arange(cols), (np.arange(cols) + 1) % cols
        return np.concatenate([np.stack([a, a + cols, b], 1), np.stack([b, a + cols, b + cols], 1)])

    va, fa = np.concatenate([ring(1.0), ring(0.0)]), band(0, 1)
    vb, fb = np.concatenate([ring(0.0), ring(-1.0)]), band(0, 1)[:, ::-1]  # opposite orientation
    loop_a = np.arange(cols, 2 * cols)
    loop_b = np.roll(np.arange(cols)[::-1], 2)
    v, f, index_b = mesh_ops.sew_loops(va, fa, loop_a, vb, fb, loop_b, tolerance=1e-9)
    assert len(v) == 3 * cols and len(f) == len(fa) + len(fb)
    assert np.allclose(v[index_b], vb), "b's vertices moved"
    assert mesh_ops.is_manifold(f, len(v))[0] and mesh_ops.oriented_consistently(f)
    assert len(mesh_ops.boundary_loops(f)) == 2
    with pytest.raises(ValueError, match="do not match"):
        mesh_ops.sew_loops(va, fa, loop_a, vb + [0.0, 0.01, 0.0], fb, loop_b, tolerance=1e-3)
    with pytest.raises(ValueError, match="same length"):
        mesh_ops.sew_loops(va, fa, loop_a, vb, fb, loop_b[:-1], tolerance=1e-3)


def test_width_profile_tapers_and_widens(templates, anny_body):
    tpl = templates["jumpsuit"]
    base = {"leg_length": 1.0, "looseness": 0.03}
    hem = tpl.boundary("left_hem")
    plain = apply_style(tpl, StyleParams("jumpsuit", base), anny_body)
    tapered = apply_style(tpl, StyleParams("jumpsuit", {**base, "taper": 0.6}), anny_body)
    widened = apply_style(tpl, StyleParams("jumpsuit", {**base, "widen_at": 0.3, "widen": 0.06}), anny_body)

    def radius(v):
        p = v[hem]
        return float(np.linalg.norm((p - p.mean(0))[:, [0, 2]], axis=1).mean())

    assert radius(tapered) < radius(plain) - 0.005 < radius(widened) - 0.02


def test_tightness_sizes_garment_larger_and_blends_to_beta(templates, anny_body):
    from simulate.garment.tightness import shape_blend, sized_shape, tightness_offsets
    from simulate.sequence.schedule import build_schedule
    from simulate.sequence.settings import SequenceSettings, SequenceTask

    beta = anny_body.shape_default.copy()
    loose = sized_shape(anny_body, beta, [0.0, 0.4])
    tight = sized_shape(anny_body, beta, [0.0, -0.1])
    assert np.allclose(tightness_offsets(anny_body, 0.1)[[4, 3]], 0.1)
    tpl = templates["top"]
    style = StyleParams("top", {})

    def girth(shape):  # perimeter of the hem loop around the hips [m]
        p = apply_style(tpl, style, anny_body, shape=shape)[tpl.boundary("hem")][:, [0, 2]]
        return float(np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1).sum())

    assert girth(loose) > girth(beta) + 0.005 > girth(tight) + 0.005
    frames = shape_blend(loose, beta, 10)
    assert frames.shape == (10, anny_body.shape_size)
    assert np.allclose(frames[-1], beta) and np.allclose(frames[0], loose + (beta - loose) / 10)
    steps = np.diff(np.concatenate([loose[None], frames]), axis=0)
    assert np.allclose(steps, steps[0], atol=1e-6), "the blend is not linear"
    # the sequence driver's schedule starts its shape transition on the task's start_shape
    s = SequenceSettings(shape_transition_frames=10)
    poses = np.tile(anny_body.canonical_pose, (1, 1))
    task = SequenceTask(np.zeros((3, 3)), np.zeros((3, 3)), beta, poses, start_shape=loose)
    shapes = build_schedule(task, anny_body.canonical_pose, anny_body.shape_default, s)[0]
    assert np.allclose(shapes[:10], frames, atol=1e-6) and np.allclose(shapes[10], beta)
    plain = SequenceTask(np.zeros((3, 3)), np.zeros((3, 3)), loose, poses)
    shapes = build_schedule(plain, anny_body.canonical_pose, anny_body.shape_default, s)[0]
    assert np.allclose(shapes[:10], shape_blend(anny_body.shape_default, loose, 10), atol=1e-6)


def test_fabric_sampling_keeps_tops_to_cotton_and_silk():
    from simulate.cloth.fabric import FABRICS
    from simulate.garment.cloth3d import CLOTH3D, sample_fabrics

    assert set(CLOTH3D.fabrics) <= set(FABRICS)
    for gtype in ("tshirt", "shirt", "top"):
        assert set(sample_fabrics(gtype, 200, seed=1)) == {"cotton", "silk"}
    assert set(sample_fabrics("jumpsuit", 200, seed=1)) == set(CLOTH3D.fabrics)
    assert sample_fabrics("dress", 5, seed=3) == sample_fabrics("dress", 5, seed=3)
    with pytest.raises(ValueError, match="cotton or silk"):
        sample_fabrics("top", 1, fabrics=["denim", "leather"])


def _spec(**garment):
    return {"name": "t", "garment": {"type": "dress", **garment}}


def test_spec_accepts_new_types_fabric_lists_and_tightness():
    from pipelines.spec import spec_hash, validate_spec

    for gtype in ("top", "dress", "jumpsuit"):
        assert validate_spec({"name": "t", "garment": {"type": gtype}})["garment"]["type"] == gtype
    spec = validate_spec(_spec(fabric=["denim", "leather"], tightness=[[-0.02, 0.05], [-0.1, 0.4]]))
    assert spec["garment"]["fabric"] == ["denim", "leather"]
    assert validate_spec(_spec(tightness=[0.0, 0.2]))["garment"]["tightness"] == [0.0, 0.2]
    # an absent tightness stays out of the resolved spec: existing specs keep their hashes
    assert "tightness" not in validate_spec(_spec())["garment"]
    assert spec_hash(validate_spec(_spec())) == spec_hash(validate_spec(_spec()))


@pytest.mark.parametrize("garment, field, expected", [
    ({"type": "top", "fabric": ["cotton", "denim"]}, "spec.garment.fabric[1]", "cotton or silk for a top"),
    ({"type": "jumpsuit", "fabric": ["cotton", "velvet"]}, "spec.garment.fabric[1]", "one of cotton"),
    ({"type": "dress", "fabric": []}, "spec.garment.fabric", "non-empty list"),
    ({"type": "dress", "fabric": ["silk", "silk"]}, "spec.garment.fabric", "without repeated"),
    ({"type": "dress", "tightness": [0.3, 0.1]}, "spec.garment.tightness", "lo <= hi"),
    ({"type": "dress", "tightness": [0.0, 0.9]}, "spec.garment.tightness", "<= 0.5"),
    ({"type": "dress", "tightness": "loose"}, "spec.garment.tightness", "null, a range"),
    ({"type": "gown"}, "spec.garment.type", "jumpsuit"),
])
def test_spec_rejects_bad_garment_fields(garment, field, expected):
    from pipelines.spec import SpecError, validate_spec

    with pytest.raises(SpecError) as info:
        validate_spec({"name": "t", "garment": garment})
    message = str(info.value)
    assert field in message and expected in message and "\n" not in message, message
