"""Frame metrics against direct computations on simple shapes."""
from __future__ import annotations

import numpy as np
import trimesh

from simulate.quality import QualityMeter, triangle_areas, unique_edges


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
