"""Garment templates: manifold meshes with the expected named boundary loops, the body
correspondence I, skinning weights, fixed topology across styles, save/load + hash."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.garment import mesh_ops
from simulate.garment.style import STYLE_SPECS, TAILORNET_TYPES, StyleParams
from simulate.garment.templates import BOUNDARY_NAMES, GarmentTemplate, apply_style, body_joints, make_template

#: The single-piece types these assertions are written for (the top, dress and jumpsuit:
#: tests/test_garment_cloth3d.py).
GARMENT_TYPES = TAILORNET_TYPES
#: Low resolution (subdivision level 0 / a small skirt grid) keeps the tests fast.
TEST_RESOLUTION = 500
#: Max distance from a garment vertex to its body vertex I beyond looseness + flare [m]
#: (the body's own edge length around the garment is up to ~4 cm).
I_DISTANCE_TOLERANCE_M = 0.045
ATOL_WEIGHT_SUM = 1e-4


@pytest.fixture(scope="module")
def templates(anny_body):
    return {t: make_template(t, anny_body, resolution=TEST_RESOLUTION) for t in GARMENT_TYPES}


@pytest.mark.parametrize("garment_type", GARMENT_TYPES)
def test_template_is_manifold_with_named_loops(templates, garment_type):
    tpl = templates[garment_type]
    ok, reason = mesh_ops.is_manifold(tpl.faces, tpl.vertex_count)
    assert ok, f"{garment_type}: {reason}"
    _, counts = mesh_ops.edge_face_counts(tpl.faces)
    assert set(np.unique(counts)) <= {1, 2}, f"{garment_type}: edges used by {set(np.unique(counts))} faces"
    loops = mesh_ops.boundary_loops(tpl.faces)
    assert len(loops) == len(BOUNDARY_NAMES[garment_type]), f"{garment_type}: {len(loops)} loops"
    assert tpl.boundary_names == list(BOUNDARY_NAMES[garment_type])
    assert sorted(map(len, loops)) == sorted(map(len, tpl.boundary_loops)), "stored loops differ from the mesh's"
    assert np.unique(tpl.faces).size == tpl.vertex_count, f"{garment_type}: unreferenced vertices"
    centre = {n: tpl.vertices[tpl.boundary(n)].mean(0) for n in tpl.boundary_names}
    if garment_type in ("tshirt", "shirt"):
        assert centre["neck"][1] > centre["hem"][1], "neck loop is not above the hem"
        assert centre["left_sleeve"][0] > 0 > centre["right_sleeve"][0], "sleeves are on the wrong sides (left is +x)"
    elif garment_type in ("pants", "shorts"):
        assert centre["waist"][1] > max(centre["left_hem"][1], centre["right_hem"][1])
        assert centre["left_hem"][0] > 0 > centre["right_hem"][0]
    else:
        assert centre["waist"][1] > centre["hem"][1]


@pytest.mark.parametrize("garment_type", GARMENT_TYPES)
def test_body_correspondence_and_skinning(templates, anny_body, garment_type):
    tpl = templates[garment_type]
    w = tpl.skinning_weights
    assert w.shape == (tpl.vertex_count, anny_body.joint_count)
    assert (w >= 0).all() and np.allclose(w.sum(1), 1.0, atol=ATOL_WEIGHT_SUM), "skinning weights not convex"
    if garment_type == "skirt":
        assert (tpl.body_vertex_index == -1).all(), "the skirt does not follow body topology: I must be -1"
        assert len(tpl.attachment) > 0
        return
    body_v, _ = body_joints(anny_body, anny_body.shape_default)
    idx = tpl.body_vertex_index
    assert idx.min() >= 0 and idx.max() < anny_body.vertex_count, "I points outside the body"
    # I belongs to the longest cut (shorter styles slide rows away from their I vertex).
    longest = StyleParams(garment_type, {k: 1.0 for k in STYLE_SPECS[garment_type] if k.endswith("length")})
    verts = apply_style(tpl, longest, anny_body)
    limit = longest["looseness"] + longest["width_profile"] + I_DISTANCE_TOLERANCE_M
    dist = np.linalg.norm(verts - body_v[idx], axis=1)
    assert dist.max() < limit, f"{garment_type}: vertex {dist.argmax()} is {dist.max():.3f} m from its body vertex (limit {limit:.3f})"
    if garment_type in ("pants", "shorts"):
        waist = tpl.vertices[tpl.boundary("waist")][:, 1].mean()
        assert len(tpl.attachment) > 0 and (tpl.vertices[tpl.attachment, 1] > waist - 0.05).all(), "attachment is not a waistband"


@pytest.mark.parametrize("garment_type", GARMENT_TYPES)
def test_styles_keep_topology_and_move_hems(templates, anny_body, garment_type):
    tpl = templates[garment_type]
    spec = STYLE_SPECS[garment_type]
    length = "length" if "length" in spec else "leg_length"
    short = apply_style(tpl, StyleParams(garment_type, {length: 0.0}), anny_body)
    long = apply_style(tpl, StyleParams(garment_type, {length: 1.0}), anny_body)
    assert short.shape == long.shape == tpl.vertices.shape and np.isfinite(short).all()
    hem = "hem" if garment_type in ("tshirt", "shirt", "skirt") else "left_hem"
    assert short[tpl.boundary(hem), 1].mean() > long[tpl.boundary(hem), 1].mean() + 0.02, f"{length}=0 hem not shorter"
    if "sleeve_length" in spec:
        a = apply_style(tpl, StyleParams(garment_type, {"sleeve_length": 0.0}), anny_body)
        b = apply_style(tpl, StyleParams(garment_type, {"sleeve_length": 1.0}), anny_body)
        assert a[tpl.boundary("left_sleeve"), 0].mean() < b[tpl.boundary("left_sleeve"), 0].mean() - 0.02
    loose = apply_style(tpl, StyleParams(garment_type, {"looseness": spec["looseness"][1]}), anny_body)
    tight = apply_style(tpl, StyleParams(garment_type, {"looseness": spec["looseness"][0]}), anny_body)
    body_v, _ = body_joints(anny_body, anny_body.shape_default)
    centre = body_v.mean(0)
    spread = lambda v: np.linalg.norm((v - centre)[:, [0, 2]], axis=1).mean()  # noqa: E731
    assert spread(loose) > spread(tight) + 0.01, "looser style is not wider"


def test_other_shape_follows_the_body(templates, anny_body):
    tpl = templates["tshirt"]
    tall = np.array(anny_body.shape_default, dtype=np.float32)
    tall[anny_body.shape_names.index("height")] = 0.9
    v = apply_style(tpl, StyleParams("tshirt", {}), anny_body, shape=tall)
    _, joints = body_joints(anny_body, tall)
    _, neutral = body_joints(anny_body, anny_body.shape_default)
    shift = joints["neck"][1] - neutral["neck"][1]
    assert shift > 0.02
    assert abs(v[tpl.boundary("neck"), 1].mean() - tpl.vertices[tpl.boundary("neck"), 1].mean() - shift) < 0.02


def test_save_load_and_hash(templates, tmp_path):
    tpl = templates["shorts"]
    path = tpl.save(tmp_path / "shorts.npz")
    back = GarmentTemplate.load(path)
    assert back.content_hash() == tpl.content_hash()
    assert np.array_equal(back.faces, tpl.faces) and back.boundary_names == tpl.boundary_names
    assert all(np.array_equal(a, b) for a, b in zip(back.boundary_loops, tpl.boundary_loops))
    back.vertices = back.vertices.copy()
    back.vertices[0, 0] += 1e-3
    assert back.content_hash() != tpl.content_hash(), "hash ignores vertex positions"
    with pytest.raises(FileNotFoundError, match="does not exist"):
        GarmentTemplate.load(tmp_path / "missing.npz")


def test_bad_inputs(anny_body):
    with pytest.raises(ValueError, match="tshirt, shirt, pants, shorts, skirt, top, dress, jumpsuit"):
        make_template("gown", anny_body)
    with pytest.raises(ValueError, match="resolution"):
        make_template("skirt", anny_body, resolution=3)


def test_templates_are_deterministic(templates, anny_body):
    for garment_type in ("skirt", "shorts"):
        again = make_template(garment_type, anny_body, resolution=TEST_RESOLUTION)
        assert again.content_hash() == templates[garment_type].content_hash(), f"{garment_type} differs between builds"


def _grid_faces(rows: int, cols: int, *, wrap: bool) -> np.ndarray:
    """Two triangles per quad of a (rows, cols) vertex grid, row-major; columns wrap around if ``wrap``."""
    faces = []
    for r in range(rows - 1):
        for c in range(cols if wrap else cols - 1):
            a, b = r * cols + c, r * cols + (c + 1) % cols
            faces += [(a, a + cols, b), (b, a + cols, b + cols)]
    return np.asarray(faces, dtype=np.int64)


def test_slide_spaces_rows_evenly_in_arc_length():
    """A tube with a bulge (like the buttocks below the lumbar curve): sliding the hem halfway
    up keeps every column's rows evenly compressed along the surface. Sliding by height alone
    squeezes the rows that land on the bulge's flanks to 0.3x their old spacing."""
    from simulate.garment.templates import _slide

    rows, cols = 41, 48
    y = np.linspace(0.0, -0.4, rows)  # u = 0 at the top, 1 at the hem
    theta = np.linspace(-np.pi, np.pi, cols, endpoint=False)
    radius = 0.12 + 0.06 * np.exp(-((y + 0.3) / 0.04) ** 2)
    pts = np.stack([np.outer(radius, np.sin(theta)), np.repeat(y[:, None], cols, 1),
                    np.outer(radius, np.cos(theta))], -1).reshape(-1, 3)
    u = -pts[:, 1] / 0.4
    chain = [np.zeros(3), np.array([0.0, -0.4, 0.0])]
    out, u_new = _slide(pts, np.ones(len(pts)), u, chain, 0.0, 1.0, 0.5, length=0.4)
    assert np.isfinite(out).all() and u_new.max() < 0.5 + 1e-6
    before = np.linalg.norm(np.diff(pts.reshape(rows, cols, 3), axis=0), axis=2)
    after = np.linalg.norm(np.diff(out.reshape(rows, cols, 3), axis=0), axis=2)
    ratio = after / before
    assert 0.4 < ratio.min() and ratio.max() < 0.6, (ratio.min(), ratio.max())
    # the moved vertices stay on the tube (radius at their new height)
    r_new = np.linalg.norm(out[:, [0, 2]], axis=1)
    assert np.abs(r_new - np.interp(-out[:, 1], -y, radius)).max() < 0.004


def test_unfold_offset_removes_folds_of_a_loose_offset_over_a_groove():
    """Offsetting a 1.5 cm wide, 1 cm deep groove by 3 cm along its normals crosses the
    offset rows over each other (flipped faces); unfold_offset leaves none flipped and no
    face under 10 % of its surface area, and does not touch the flat parts."""
    from simulate.garment.templates import unfold_offset

    rows, cols = 40, 30
    x = np.linspace(-0.1, 0.1, rows)
    z = np.linspace(0.0, 0.1, cols)
    xx, zz = np.meshgrid(x, z, indexing="ij")
    surface = np.stack([xx, -0.01 * np.exp(-(xx / 0.015) ** 2), zz], -1).reshape(-1, 3)
    faces = _grid_faces(rows, cols, wrap=False)[:, ::-1]  # normals up, into the groove's open side
    normals = mesh_ops.smooth_normals(surface, faces, iterations=1)
    assert normals[:, 1].min() > 0
    offset = surface + 0.03 * normals
    n0 = mesh_ops.face_normals(surface, faces)
    flipped = lambda v: int((np.einsum("ij,ij->i", mesh_ops.face_normals(v, faces), n0) < 0).sum())  # noqa: E731
    assert flipped(offset) > 0, "test setup: the offset should fold"
    out = unfold_offset(offset, surface, faces)
    assert flipped(out) == 0
    area = lambda v: np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)  # noqa: E731
    assert (area(out) / area(surface)).min() > 0.1
    flat = np.abs(surface[:, 0]) > 0.07
    np.testing.assert_allclose(out[flat], offset[flat], atol=1e-9)


def test_closest_point_query_matches_brute_force_over_every_triangle():
    """The BVH query's closest points, faces and signed distances against checking every triangle
    (points near, far from and inside a bumpy closed surface, where a nearest-centroid shortcut fails)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    rng = np.random.default_rng(4)
    verts = sphere.vertices * (1.0 + 0.3 * rng.random((len(sphere.vertices), 1)))  # uneven triangles
    faces = np.asarray(sphere.faces)
    points = rng.normal(size=(300, 3)) * rng.choice([0.05, 0.3, 1.0], size=(300, 1))
    closest, face, bary, signed = mesh_ops.ClosestPointQuery(verts, faces).query(points)
    tri = verts[faces]  # (F, 3, 3)
    q, _ = mesh_ops.closest_points_on_triangles(points[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    dist = np.linalg.norm(q - points[:, None], axis=-1)  # (N, F)
    best = dist.min(axis=1)
    np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), best, rtol=0, atol=1e-6)
    np.testing.assert_allclose(dist[np.arange(len(points)), face], best, rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.einsum("nk,nkd->nd", bary, tri[face]), closest, rtol=0, atol=1e-9)
    # inside: winding number 1 (solid angles of the triangles seen from the point, Van Oosterom-Strackee)
    a, b, c = (tri[None, :, k] - points[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    num = np.einsum("nfd,nfd->nf", a, np.cross(b, c))
    den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
    inside = np.abs((2.0 * np.arctan2(num, den)).sum(axis=1) / (4.0 * np.pi)) > 0.5
    far = best > 1e-3
    assert ((signed < 0) == inside)[far].all(), "the sign follows the closest face's normal: negative inside"
    with pytest.raises(ValueError, match="farther than max_distance"):
        mesh_ops.ClosestPointQuery(verts, faces, max_distance=0.01).query(np.array([[5.0, 0.0, 0.0]]))
