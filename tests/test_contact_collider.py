"""BodyCollider: signed distance, face culling, per-world cells, interpolation, friction transport."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from simulate.cloth import FABRICS, ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth, icosphere
from simulate.contact import BodyCollider
from unit_sim import unit_settings

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
RADIUS = 0.3


@pytest.mark.parametrize("device", DEVICES)
def test_signed_distance_matches_sphere(device: str) -> None:
    verts, faces = icosphere(RADIUS, subdivisions=4)
    collider = BodyCollider(verts, faces, device=device)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = rng.uniform(0.2, 0.4, size=200)
    pts = dirs * radii[:, None]
    sd = collider.signed_distance(pts, np.zeros(200, dtype=np.int32))
    # Facet error of a level-4 icosphere (edges span ~0.07 rad): face centres sit up to ~1.1e-3 R inside.
    tol = RADIUS * 1.5e-3
    assert np.abs(sd - (radii - RADIUS)).max() < tol, f"max |sd - analytic| {np.abs(sd - (radii - RADIUS)).max()}"
    assert np.all(np.sign(sd) == np.sign(radii - RADIUS)), "inside/outside sign wrong"


def test_face_subset_drops_unreferenced_vertices_and_checks_shapes() -> None:
    verts, faces = icosphere(RADIUS, subdivisions=2)
    upper = faces[verts[faces].mean(axis=1)[:, 1] > 0.0]  # cull: keep the upper half
    collider = BodyCollider(verts, upper, device="cpu", world_count=2)
    assert collider.vertex_count == len(np.unique(upper)) < len(verts)
    assert np.array_equal(verts[collider.vertex_map][collider.faces], verts[upper])
    collider.set_target(np.stack([verts, verts + 0.1]))  # full source vertex array per world
    with pytest.raises(ValueError, match=r"body vertices must have shape \(2, 162 or"):
        collider.set_target(verts[:10])
    with pytest.raises(ValueError, match="faces index range"):
        BodyCollider(verts, faces + 1000, device="cpu")
    with pytest.raises(ValueError, match="thickness must be a finite number >= 0"):
        BodyCollider(verts, faces, device="cpu", thickness=-1.0)


def test_worlds_only_see_their_own_body_and_interpolation() -> None:
    verts, faces = icosphere(RADIUS, subdivisions=3)
    per_world = np.stack([verts, verts + np.array([0.0, 1.0, 0.0])])  # world 1's sphere is 1 m higher
    collider = BodyCollider(per_world, faces, device="cpu")
    probe = np.array([[0.0, 0.1, 0.0], [0.0, 0.0, 0.0], [0.0, 1.1, 0.0]])
    sd = collider.signed_distance(probe, np.array([0, 1, 1], dtype=np.int32), max_dist=2.0)
    assert sd[0] < -0.19 and sd[2] < -0.19, f"probes should be inside their own sphere: {sd}"
    assert abs(sd[1] - 0.7) < 5e-3, f"world 1 sees only its own sphere: {sd[1]} vs 0.7"
    # Half-way through a frame the mesh is at the average pose (plus the world's cell offset).
    collider.set_target(per_world + np.array([0.2, 0.0, 0.0]))
    collider.update(0.5)
    pts = collider.mesh.points.numpy().reshape(2, -1, 3) - collider.world_offset_np[:, None, :]
    assert np.allclose(pts, per_world[:, collider.vertex_map] + np.array([0.1, 0.0, 0.0]), atol=1e-5)
    collider.finish_frame()
    assert np.allclose(collider.pose_start.numpy(), collider.pose_end.numpy())


@pytest.mark.parametrize("friction", [True, False])
def test_moving_body_carries_cloth_by_friction_and_does_not_tunnel(friction: bool) -> None:
    """A sphere carrying a small cloth patch moves 10 cm sideways and 10 cm up in 10 frames:
    with friction the cloth rides along, without it the cloth stays (up to sliding off);
    in both cases it never ends up inside the sphere."""
    verts, faces = icosphere(RADIUS, subdivisions=3)
    cloth_v, cloth_f = grid_cloth(5, 5, 0.1, 0.1, plane="xz", origin=(-0.05, RADIUS + 0.003, -0.05))
    builder = ClothBuilder()
    builder.add_garment(cloth_v, cloth_f, fabric=dataclasses.replace(FABRICS["denim"], friction=0.8))
    model = builder.finalize("cpu", features=Features(friction=friction))
    collider = BodyCollider(verts, faces, device="cpu")
    sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=5, iterations=5, damping=2.0))
    for _ in range(20):
        sim.step_frame()
    x0 = sim.positions()[:, 0].mean()
    for k in range(1, 11):
        sim.set_body_target(verts + np.array([0.01 * k, 0.01 * k, 0.0]))
        sim.step_frame()
    q = sim.positions()
    moved = q[:, 0].mean() - x0
    if friction:
        assert moved > 0.07, f"cloth moved {moved * 1e3:.1f} mm with the sphere's 100 mm (friction on)"
    else:
        assert moved < 0.05, f"cloth moved {moved * 1e3:.1f} mm without friction"
    sd = collider.signed_distance(q, np.zeros(len(q), dtype=np.int32))
    assert sd.min() > -1e-3, f"cloth vertex {-sd.min() * 1e3:.2f} mm inside the moving sphere"


def test_place_world_moves_only_that_world():
    from simulate.contact import BodyCollider

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(3, 10, 3)).astype(np.float32)
    faces = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7], [7, 8, 9]])
    col = BodyCollider(verts, faces, device="cpu")
    new = rng.normal(size=(10, 3)).astype(np.float32)
    col.place_world(1, new)
    for arr in (col.pose_start, col.pose_end):
        got = arr.numpy().reshape(3, -1, 3)
        np.testing.assert_array_equal(got[1], new[col.vertex_map])
        np.testing.assert_array_equal(got[0], verts[0][col.vertex_map])
        np.testing.assert_array_equal(got[2], verts[2][col.vertex_map])
    with pytest.raises(ValueError, match="world"):
        col.place_world(3, new)
    with pytest.raises(ValueError, match="shape"):
        col.place_world(0, new[:4])
    # a body put back many times goes to the device once: the same placement from its array
    placed = col.compact_world(new + 1.0)
    col.place_world(2, placed)
    np.testing.assert_array_equal(col.pose_end.numpy().reshape(3, -1, 3)[2], (new + 1.0)[col.vertex_map])
    with pytest.raises(ValueError, match=rf"vec3f \({col.vertex_count},\) on cpu \(got vec3f \(4,\)"):
        col.place_world(0, placed[:4])
