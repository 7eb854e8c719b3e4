"""UV charts: panels inside [0, 1]^2, no flipped or overlapping triangles, low
distortion; rasterize -> sample reproduces smooth per-vertex data."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.garment import mesh_ops, uv
from simulate.garment.templates import make_template, template_surface

TEST_RESOLUTION = 500
#: Mean |log area ratio| of UV vs 3D triangles (after global scale) must stay below this.
MAX_AREA_DISTORTION = 0.15
#: rasterize(positions) -> sample must reproduce positions within this [m] (mean / max).
ATOL_ROUNDTRIP_MEAN_M = 1.0e-3
ATOL_ROUNDTRIP_MAX_M = 1.0e-2
TYPES = ("tshirt", "pants", "skirt")


@pytest.fixture(scope="module")
def templates(anny_body):
    return {t: make_template(t, anny_body, resolution=TEST_RESOLUTION) for t in TYPES}


@pytest.mark.parametrize("garment_type", TYPES)
def test_charts_valid(templates, anny_body, garment_type):
    tpl = templates[garment_type]
    fuv = tpl.face_uv.astype(np.float64)
    assert fuv.min() >= 0.0 and fuv.max() <= 1.0, f"UVs outside [0,1]^2: [{fuv.min()}, {fuv.max()}]"
    assert set(np.unique(tpl.face_panel)) == set(range(len(tpl.panel_names))) and len(tpl.panel_names) in (2, 4)
    area = uv.signed_areas(fuv, None)
    for p in range(len(tpl.panel_names)):
        sel = tpl.face_panel == p
        assert (area[sel] > 0).all(), f"{garment_type} panel {p}: {(area[sel] <= 0).sum()} flipped triangles"
        sub, used = mesh_ops.remove_unused_vertices(tpl.faces[sel], tpl.vertex_count)
        assert len(np.unique(mesh_ops.face_components(sub))) == 1, f"panel {p} is not one piece"
        edges, _ = mesh_ops.unique_edges(sub)
        assert len(used) - len(edges) + len(sub) == 1, f"{garment_type} panel {p} is not a disk (Euler characteristic)"
    # Per-vertex main-chart UV equals one of the vertex's corner UVs.
    first = np.zeros(tpl.vertex_count, dtype=bool)
    match = np.all(np.isclose(fuv, tpl.uv[tpl.faces]), axis=-1)
    first[tpl.faces[match]] = True
    assert first.all(), "per-vertex uv is not one of the vertex's corner uvs"
    dist = uv.uv_distortion(tpl, template_surface(tpl, anny_body))
    assert dist["flipped_fraction"] == 0.0
    assert dist["area_log_mean"] < MAX_AREA_DISTORTION, f"area distortion {dist['area_log_mean']:.3f}"


@pytest.mark.parametrize("garment_type", TYPES)
def test_no_overlap_coverage_count(templates, garment_type):
    _, _, count = uv.pixel_map(templates[garment_type].face_uv, 512)
    assert count.max() <= 1, f"{garment_type}: {(count > 1).sum()} pixel centres lie inside 2+ triangles (overlap)"
    assert (count > 0).mean() > 0.2, "charts cover too little of the atlas"


def test_pixel_map_detects_overlap(templates):
    tpl = templates["skirt"]
    doubled = np.concatenate([tpl.face_uv, tpl.face_uv[:10]])
    _, _, count = uv.pixel_map(doubled, 512)
    assert count.max() >= 2, "the coverage-count test cannot see overlapping triangles"


@pytest.mark.parametrize("garment_type", TYPES)
def test_rasterize_sample_roundtrip(templates, garment_type):
    tpl = templates[garment_type]
    values = np.stack([tpl.vertices, 2.0 * tpl.vertices], axis=0)  # (2, V, 3)
    images, mask = uv.rasterize(values, tpl, size=256, padding=4)
    assert images.shape == (2, 3, 256, 256) and mask.shape == (256, 256) and mask.any()
    back = uv.sample(images, tpl)
    assert back.shape == (2, tpl.vertex_count, 3)
    err = np.linalg.norm(back[0] - tpl.vertices, axis=1)
    assert err.mean() < ATOL_ROUNDTRIP_MEAN_M and err.max() < ATOL_ROUNDTRIP_MAX_M, \
        f"{garment_type}: round trip error mean {err.mean() * 1e3:.2f} mm, max {err.max() * 1e3:.2f} mm"
    assert np.allclose(back[1], 2.0 * back[0], atol=1e-5), "rasterization is not linear in the values"
    single, _ = uv.rasterize(tpl.vertices, tpl, size=64)
    assert single.shape == (1, 3, 64, 64)


def test_rasterize_bad_input(templates):
    tpl = templates["skirt"]
    with pytest.raises(ValueError, match="values must have shape"):
        uv.rasterize(np.zeros((tpl.vertex_count + 1, 3)), tpl)
    with pytest.raises(ValueError, match="images must have shape"):
        uv.sample(np.zeros((1, 3, 8, 9)), tpl)


def test_subdivided_template_keeps_the_pattern(anny_body, templates):
    fine = make_template("pants", anny_body, resolution=5000)
    coarse = templates["pants"]
    assert fine.vertex_count > 3 * coarse.vertex_count and fine.panel_names == coarse.panel_names
    area = uv.signed_areas(fine.face_uv.astype(np.float64), None)
    assert (area > 0).all(), f"{(area <= 0).sum()} flipped triangles after subdivision"
    _, _, count = uv.pixel_map(fine.face_uv, 512)
    assert count.max() <= 1, "subdivided charts overlap"
    _, _, coarse_count = uv.pixel_map(coarse.face_uv, 512)
    assert abs((count > 0).sum() - (coarse_count > 0).sum()) < 0.02 * (coarse_count > 0).sum(), "pattern changed"
