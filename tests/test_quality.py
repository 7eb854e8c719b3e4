"""Frame metrics against direct computations on simple shapes."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

from simulate.quality import QualityMeter, triangle_areas, unique_edges

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def _grid(n=8, size=0.4, z=0.0):
    u, v = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n))
    verts = np.stack([u.ravel(), v.ravel(), np.full(n * n, z)], 1)
    idx = np.arange(n * n).reshape(n, n)
    faces = np.concatenate([np.stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel()], 1),
                            np.stack([idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()], 1)])
    return verts, faces


def test_penetration_matches_sphere_distance():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    verts, faces = _grid()
    meter = QualityMeter(faces, verts, sphere.faces, len(sphere.vertices))
    points = verts.copy()
    points[:, 2] = 0.25  # grid at z=0.25: central vertices inside the sphere
    d = meter.signed_distance(points, sphere.vertices)
    exact = np.linalg.norm(points, axis=1) - 0.3
    np.testing.assert_allclose(d, exact, atol=2e-3, err_msg="signed distance vs analytic sphere distance")
    m = meter.measure(points, sphere.vertices, self_intersection=False)
    assert abs(m["penetration_fraction"] - (exact < -1e-3).mean()) < 0.05
    assert abs(m["penetration_max_m"] - max(0, -exact.min())) < 3e-3


def test_area_ratios_and_self_intersection():
    verts, faces = _grid()
    meter = QualityMeter(faces, verts, faces, len(verts))
    m = meter.measure(verts * np.array([2.0, 1.0, 1.0]), verts - [0, 0, 1], self_intersection=True)
    assert abs(m["area_ratio_min"] - 2.0) < 1e-6 and abs(m["area_ratio_max"] - 2.0) < 1e-6
    assert m["self_intersections"] == 0
    # two sheets in one mesh: a vertical sheet through the horizontal one intersects it
    vertical = verts[:, [2, 0, 1]] + np.array([0.013, 0.0, 0.0])  # plane x = 0.013, spanning z in [-0.2, 0.2]
    both_faces = np.concatenate([faces, faces + len(verts)])
    two = QualityMeter(both_faces, np.concatenate([verts, vertical]), faces, len(verts))
    assert two.self_intersections(np.concatenate([verts, vertical])) > 0
    lifted = vertical + np.array([0.0, 0.0, 0.25])  # now entirely above the horizontal sheet
    assert two.self_intersections(np.concatenate([verts, lifted])) == 0
    nan = verts.copy()
    nan[0, 0] = np.nan
    assert meter.measure(nan, verts)["finite"] == 0.0


def test_helpers():
    verts, faces = _grid(n=3, size=2.0)
    assert np.isclose(triangle_areas(verts, faces).sum(), 4.0)
    assert len(unique_edges(faces)) == 16


@pytest.mark.parametrize("device", DEVICES)
def test_a_batch_of_frames_measures_each_frame_as_if_it_were_alone(device):
    """measure_batch packs frames one after another, one body and one rest-area row per frame: each
    frame's metrics must be the ones it gets alone (wrong offsets, mesh slots or per-frame sums would
    mix frames), and a non-finite frame must not disturb the others."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    verts, faces = _grid()
    vertical = verts[:, [2, 0, 1]] + np.array([0.013, 0.0, 0.0])
    both_faces = np.concatenate([faces, faces + len(verts)])
    rest = np.concatenate([verts, vertical + [0.0, 0.0, 0.25]])
    crossing = np.concatenate([verts, vertical]) + [0.0, 0.0, 0.25]  # the sheets pierce each other, inside the sphere
    apart = rest * np.array([2.0, 1.0, 1.0])  # no piercing; the flat sheet twice its rest area, the upright one as it was
    nan = rest.copy()
    nan[3, 1] = np.nan
    frames = np.stack([crossing, apart, nan, crossing])
    bodies = np.stack([sphere.vertices, sphere.vertices + [0.0, 0.0, 5.0], sphere.vertices, sphere.vertices + [0.0, 0.0, 0.3]])
    rest_rows = np.stack([triangle_areas(rest, both_faces), triangle_areas(rest, both_faces),
                          triangle_areas(rest, both_faces), 0.5 * triangle_areas(rest, both_faces)])
    meter = QualityMeter(both_faces, rest, sphere.faces, len(sphere.vertices), device=device)
    batch = meter.measure_batch(frames, bodies, rest_areas=rest_rows)
    for i in range(len(frames)):
        alone = QualityMeter(both_faces, rest, sphere.faces, len(sphere.vertices), device=device).measure(
            frames[i], bodies[i], rest_areas=rest_rows[i])
        assert batch[i].keys() == alone.keys()
        for k in alone:
            assert batch[i][k] == alone[k] or (np.isnan(alone[k]) and np.isnan(batch[i][k])), (i, k, batch[i][k], alone[k])
    # and the values are the right ones, not just the same ones (areas in float64 of the float32
    # positions the device holds, as the simulator's are)
    ratio = triangle_areas(crossing.astype(np.float32).astype(np.float64), both_faces) / rest_rows[0]
    assert abs(batch[0]["area_ratio_min"] - ratio.min()) < 1e-12 and abs(batch[0]["area_ratio_max"] - ratio.max()) < 1e-12
    assert abs(batch[3]["area_ratio_min"] - 2.0 * batch[0]["area_ratio_min"]) < 1e-12
    assert batch[0]["self_intersections"] > 0 and batch[1]["self_intersections"] == 0 and batch[3]["self_intersections"] > 0
    assert abs(batch[1]["area_ratio_max"] - 2.0) < 1e-6 and abs(batch[1]["area_ratio_min"] - 1.0) < 1e-6 and batch[1]["penetration_fraction"] == 0.0
    assert batch[2]["finite"] == 0.0 and batch[2]["self_intersections"] == -1.0
    inside = (np.linalg.norm(crossing, axis=1) - 0.3 < -2e-3).mean()
    assert abs(batch[0]["penetration_fraction"] - inside) < 0.05 and batch[0]["penetration_fraction"] > 0.2
    # shape errors name the argument and the expected shape
    with pytest.raises(ValueError, match=r"body_vertices must have shape \(4, "):
        meter.measure_batch(frames, bodies[:3])
    with pytest.raises(ValueError, match=r"rest_areas must have shape"):
        meter.measure_batch(frames, bodies, rest_areas=rest_rows[:2])


def test_a_garment_that_fell_off_the_body_is_dropped_as_off_body() -> None:
    """A sheet lying on a sphere has no vertex 0.5 m or more from it; the same sheet 1 m below
    (a garment that slid off) has all of them, and the dataset's default filters drop that frame
    for ``off_body`` before any other geometric reason."""
    from pipelines.generate_dataset import drop_reason
    from pipelines.spec import DEFAULTS
    from simulate.quasi_static import WorldStatus
    from simulate.scenes import grid_cloth, icosphere

    sphere_v, sphere_f = icosphere(0.2, subdivisions=2)
    sheet_v, sheet_f = grid_cloth(6, 6, 0.2, 0.2, plane="xz", origin=(-0.1, 0.21, -0.1))
    meter = QualityMeter(sheet_f, sheet_v, sphere_f, len(sphere_v))
    on, off = meter.measure_batch(np.stack([sheet_v, sheet_v - np.array([0.0, 1.0, 0.0], np.float32)]),
                                  np.stack([sphere_v, sphere_v]))
    assert on["off_body_fraction"] == 0.0 and off["off_body_fraction"] == 1.0
    filters = DEFAULTS["filters"]
    assert drop_reason(on, WorldStatus.CONVERGED, filters) is None
    assert drop_reason(off, WorldStatus.CONVERGED, filters) == "off_body"
