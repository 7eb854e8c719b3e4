"""The self-intersection metric: exact edge-triangle crossing counts and intersection contours."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.scenes import grid_cloth
from simulate.quality import QualityMeter, unique_edges

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def _brute_force_crossings(x: np.ndarray, faces: np.ndarray) -> int:
    """Every (edge, triangle) pair without a shared vertex, tested by the segment's crossing point
    with the triangle's plane and its barycentric coordinates (float64; no BVH, no orientations)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return _brute_force(x.astype(np.float64), faces)


def _brute_force(x: np.ndarray, faces: np.ndarray) -> int:
    edges = unique_edges(faces)
    p, q = x[edges[:, 0]][:, None], x[edges[:, 1]][:, None]  # (E, 1, 3)
    a, b, c = (x[faces[:, k]][None] for k in range(3))  # (1, F, 3)
    n = np.cross(b - a, c - a)
    dp = np.einsum("efk,efk->ef", np.broadcast_to(n, (len(edges),) + n.shape[1:]), p - a)
    dq = np.einsum("efk,efk->ef", np.broadcast_to(n, (len(edges),) + n.shape[1:]), q - a)
    crosses = dp * dq < 0.0
    t = dp / (dp - dq)
    hit = p + t[..., None] * (q - p)
    nn = np.einsum("efk,efk->ef", np.broadcast_to(n, hit.shape), np.broadcast_to(n, hit.shape))
    w_a = np.einsum("efk,efk->ef", np.cross(c - b, hit - b), np.broadcast_to(n, hit.shape)) / nn
    w_b = np.einsum("efk,efk->ef", np.cross(a - c, hit - c), np.broadcast_to(n, hit.shape)) / nn
    inside = (w_a >= 0.0) & (w_b >= 0.0) & (1.0 - w_a - w_b >= 0.0)
    shared = (edges[:, None, :, None] == faces[None, :, None, :]).any(axis=(2, 3))
    return int((crosses & inside & ~shared).sum())


def _sheets(*grids):
    """One mesh of several grid sheets (vertices, faces)."""
    verts, faces, off = [], [], 0
    for v, f in grids:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    return np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int32)


@pytest.mark.parametrize("device", DEVICES)
def test_crossing_count_equals_brute_force(device) -> None:
    rng = np.random.default_rng(3)
    v, f = grid_cloth(9, 9, 0.3, 0.3, plane="xz")
    frames = []
    for k in range(4):  # crumpled: the sheet folds through itself
        bump = rng.normal(scale=0.06 * k, size=v.shape)
        frames.append((v + bump).astype(np.float32))
    meter = QualityMeter(f, v, f[:1], 3, device=device)
    counts = meter.self_intersection_counts(np.stack(frames))
    expected = [_brute_force_crossings(x, f) for x in frames]
    assert expected[0] == 0 and max(expected) > 20
    assert counts.tolist() == expected


@pytest.mark.parametrize("device", DEVICES)
def test_contours_count_the_intersection_curves(device) -> None:
    floor = grid_cloth(11, 11, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    wall_a = grid_cloth(7, 7, 0.2, 0.2, plane="xy", origin=(-0.1, 0.0967, 0.0317))
    wall_b = grid_cloth(7, 7, 0.2, 0.2, plane="xy", origin=(-0.1, 0.1089, -0.0713))
    apart = grid_cloth(7, 7, 0.2, 0.2, plane="xy", origin=(-0.1, 0.25, 0.0317))
    # a closed tube standing through the floor: its crossing is one closed loop
    theta = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    ring = np.stack([0.05 * np.cos(theta) + 0.013, np.zeros_like(theta), 0.05 * np.sin(theta) - 0.007], 1)
    tube_v = np.concatenate([ring + [0.0, y, 0.0] for y in np.linspace(-0.1137, 0.0863, 6)])
    tube_f = []
    for r in range(5):
        for i in range(16):
            a, b = r * 16 + i, r * 16 + (i + 1) % 16
            tube_f += [[a, b, a + 16], [b, b + 16, a + 16]]
    tube = (tube_v, np.array(tube_f))
    cases = {"one wall": (_sheets(floor, wall_a), 1), "two walls": (_sheets(floor, wall_a, wall_b), 2),
             "apart": (_sheets(floor, apart), 0), "tube": (_sheets(floor, tube), 1)}
    for name, ((v, f), contours) in cases.items():
        meter = QualityMeter(f, v, f[:1], 3, device=device)
        got = meter.self_intersection_contours(v[None])[0]
        assert got == contours, f"{name}: {got} contours, expected {contours}"
        count = meter.self_intersection_counts(v[None])[0]
        assert count == _brute_force_crossings(v, f), name
        assert (count > 0) == (contours > 0), name
    # measure_batch reports both
    (v, f), _ = cases["two walls"]
    meter = QualityMeter(f, v, f[:1], 3, device=device)
    m = meter.measure_batch(np.stack([v, v + 0.0]), np.zeros((2, 3, 3), np.float32))
    assert m[0]["self_intersection_contours"] == 2.0 and m[0]["self_intersections"] > 0
