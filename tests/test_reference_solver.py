"""Physics checks of the converged reference solver (simulate/solvers/reference): analytic oracles
(hanging strip, elastic catenary), its energy against finite differences and the production
solvers' forces, and drapes on a sphere (with stick friction and frictionless)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.optimize import brentq

from simulate.cloth import ClothBuilder, Features
from simulate.cloth.fabric import FABRICS
from simulate.quasi_static import QuasiStaticSimulator, WorldStatus
from simulate.scenes import grid_cloth, hanging_strip, icosphere
from simulate.contact import BodyCollider
from simulate.solvers.reference import solve_equilibrium, world_energy
from unit_sim import unit_settings

wp.config.log_level = wp.LOG_WARNING
wp.init()

GRAVITY = 9.81
RTOL_STRIP = 0.01
"""Hanging strip: relative error of the bottom extension against rho g L^2 / (2 Y)."""
RTOL_CATENARY = 0.005
"""Elastic catenary: relative error of the mid-span sag (the lumped-mass chain of 80 segments
differs from the continuous catenary by O(1/80^2))."""
ATOL_PENETRATION_M = 1.0e-5
"""No particle may be closer to the body than its contact distance minus this [m] (0.01 mm)."""
CONTACT_THICKNESS = 2.0e-3
"""Collider thickness of the drapes [m] (BodyCollider's default)."""


def _no_bending(name: str):
    return dataclasses.replace(FABRICS[name], bending_stiffness=0.0)


def _body_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Float64 distance [m] of points to a convex body mesh, negative inside; outward normals (N, 3).

    Brute force over all faces (trimesh), independent of the solver's BVH query."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, distance, _ = trimesh.proximity.closest_point_naive(mesh, points)
    inside = np.all(np.einsum("fj,ifj->if", mesh.face_normals, points[:, None, :] - vertices[faces[:, 0]][None]) < 0.0,
                    axis=1)
    normal = (points - closest) / np.maximum(distance, 1e-300)[:, None]
    return np.where(inside, -distance, distance), np.where(inside[:, None], -normal, normal)


@pytest.mark.parametrize("fabric", ["cotton", "denim"])
@pytest.mark.parametrize("rows", [20, 40, 80])
def test_hanging_strip_extension(fabric: str, rows: int) -> None:
    """A 1 m x 5 cm strip pinned at its top edge stretches by rho g L^2 / (2 Y) under its own weight.

    The strip carries at height s the weight below it, so the strain is rho g (L - s) / Y (Poisson
    0, as the triangle energy) and integrates to rho g L^2 / (2 Y); with lumped masses (half rows at
    the ends) the sum over segments gives the same number at any resolution (80 rows: 1.25 cm
    edges, the production edge length)."""
    fab = _no_bending(fabric)
    length = 1.0
    verts, model = hanging_strip(rows, fab, length=length)
    x, result = solve_equilibrium(model, 0, verts)
    assert result.converged and result.residual <= result.tol_force, result
    extension = (verts[-2:, 1] - x[-2:, 1]).mean()
    expected = fab.density * GRAVITY * length ** 2 / (2.0 * fab.stretch_stiffness)
    assert abs(extension - expected) <= RTOL_STRIP * expected, (
        f"{fabric}, {rows} rows: extension {extension * 1e3:.6f} mm vs rho g L^2/(2Y) = {expected * 1e3:.6f} mm")


def test_elastic_catenary_sag() -> None:
    """A 1 m x 5 cm cotton strip pinned at both ends 1 m apart (taut at rest) sags by stretching:
    the elastic catenary (Irvine) with weight w = rho g W per unstretched length and axial
    stiffness EA = Y W, at mid-span s in [0, L/2]:
    x(s) = H/w asinh(w s / H) + H s / EA, y(s) = H/w (sqrt(1 + (w s / H)^2) - 1) + w s^2 / (2 EA),
    with the horizontal tension H fixed by x(L/2) = L/2."""
    fab = _no_bending("cotton")
    length, width, rows = 1.0, 0.05, 80
    nx = rows + 1
    verts, faces = grid_cloth(nx, 2, length, width, plane="xz", origin=(0.0, 1.0, 0.0))
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric=fab, pinned=[0, rows, nx, nx + rows])
    model = builder.finalize("cpu", features=Features(body_contact=False, bending=False))
    start = verts.copy()
    s = verts[:, 0] / length
    start[:, 1] -= 0.04 * s * (1.0 - s)  # a 1 cm sag: the flat strip has no transverse stiffness
    x, result = solve_equilibrium(model, 0, start)
    assert result.converged and result.residual <= result.tol_force, result
    w = fab.density * GRAVITY * width
    ea = fab.stretch_stiffness * width
    half = length / 2.0
    tension = brentq(lambda h: h / w * np.arcsinh(w * half / h) + h * half / ea - half, 1e-6, 1e6)
    sag = tension / w * (np.sqrt(1.0 + (w * half / tension) ** 2) - 1.0) + w * half ** 2 / (2.0 * ea)
    mid = (verts[[rows // 2, nx + rows // 2], 1] - x[[rows // 2, nx + rows // 2], 1]).mean()
    assert abs(mid - sag) <= RTOL_CATENARY * sag, f"mid-span sag {mid * 1e3:.4f} mm vs catenary {sag * 1e3:.4f} mm"


def _two_world_model():
    """World 0: a denim patch; world 1: a bent cotton patch with a pinned and two attached vertices."""
    verts, faces = grid_cloth(5, 4, 0.2, 0.15, plane="xz")
    rng = np.random.default_rng(0)
    builder = ClothBuilder()
    builder.add_garment(verts + 0.01 * rng.standard_normal(verts.shape), faces, fabric="denim")
    builder.add_garment(verts, faces, fabric="cotton", pinned=[0], attached=[3, 7])
    model = builder.finalize("cpu", features=Features(body_contact=False))
    positions = [verts + 0.01 * rng.standard_normal(verts.shape) for _ in range(2)]
    return model, positions


@pytest.mark.parametrize("world", [0, 1])
def test_energy_gradient_matches_finite_differences(world: int) -> None:
    """world_energy's gradient (stretch, shear, bending, gravity, attachments) is the derivative of
    its energy: central differences with a 1e-6 m step agree to 1e-8 of the largest component."""
    model, positions = _two_world_model()
    x = positions[world]
    energy, grad = world_energy(model, world, x)
    step = 1.0e-6
    numeric = np.zeros_like(x)
    for i in range(len(x)):
        for axis in range(3):
            plus, minus = x.copy(), x.copy()
            plus[i, axis] += step
            minus[i, axis] -= step
            numeric[i, axis] = (world_energy(model, world, plus)[0] - world_energy(model, world, minus)[0]) / (2 * step)
    assert np.isfinite(energy)
    assert np.abs(numeric - grad).max() <= 1e-8 * np.abs(grad).max(), np.abs(numeric - grad).max()


def test_gradient_matches_production_forces() -> None:
    """The elastic part of world_energy's gradient is minus the forces of the production kernels
    (mass-spring triangle and bending forces, float32) in every world."""
    from simulate.solvers.mass_spring import kernels

    model, positions = _two_world_model()
    x = np.concatenate(positions).astype(np.float32)
    xw = wp.array(x, dtype=wp.vec3, device="cpu")
    slots = wp.zeros(3 * model.tri_count + 4 * model.bend_count, dtype=wp.vec3, device="cpu")
    wp.launch(kernels.eval_triangle_forces, dim=model.tri_count, device="cpu",
              inputs=[model.tri_indices, model.tri_dm_inv, model.tri_compliance, xw], outputs=[slots])
    wp.launch(kernels.eval_bending_forces, dim=model.bend_count, device="cpu",
              inputs=[3 * model.tri_count, model.bend_indices, model.bend_rest_angle, model.bend_compliance, xw],
              outputs=[slots])
    force = np.zeros((model.particle_count, 3))
    np.add.at(force, np.concatenate([model.tri_indices_np.reshape(-1), model.bend_indices_np.reshape(-1)]),
              slots.numpy())
    control = model.control()
    control.release_attachments()  # attachment springs are no slot force of these kernels
    for world in range(model.world_count):
        sl = model.world_slice(world)
        _, grad = world_energy(model, world, x[sl].astype(np.float64), control=control)
        elastic = grad + model.particle_mass_np[sl, None] * np.asarray(model.gravity)
        assert np.abs(force[sl] + elastic).max() <= 1e-5 * np.abs(elastic).max(), world


def test_drape_on_sphere_sticks_without_penetration() -> None:
    """A cloth dropped on a sphere by the production XPBD driver, then solved to equilibrium with
    stick friction: converged, residual below tolerance, nobody closer than the contact distance
    minus 0.01 mm (float64 distance, brute force), the particles in contact held."""
    verts, faces = grid_cloth(17, 17, 0.8, 0.8, plane="xz", origin=(-0.4, 0.3, -0.4))
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton")
    model = builder.finalize("cpu")
    sphere_v, sphere_f = icosphere(0.25, subdivisions=3)
    collider = BodyCollider(sphere_v, sphere_f, device="cpu", thickness=CONTACT_THICKNESS)
    settings = unit_settings(substeps=5, iterations=5, damping=2.0, tolerance=0.02, max_frames=400)
    sim = QuasiStaticSimulator(model, collider, settings=settings)
    assert sim.relax()[0] == WorldStatus.CONVERGED
    start = sim.positions().astype(np.float64)
    x, result = solve_equilibrium(model, 0, start, body_vertices=sphere_v, body_faces=sphere_f,
                                  contact_thickness=CONTACT_THICKNESS)
    assert result.converged and result.residual <= result.tol_force, result
    assert result.residual_history[-1] == result.residual
    reach = CONTACT_THICKNESS + 0.5 * FABRICS["cotton"].thickness
    distance, _ = _body_distance(sphere_v, sphere_f, x)
    assert distance.min() >= reach - ATOL_PENETRATION_M, f"{(reach - distance.min()) * 1e3:.4f} mm too close"
    assert result.max_compression <= 1.0e-6
    assert result.contact_count > 10 and result.stick_count > 10
    assert 0 <= result.friction_violations <= result.stick_count
    assert 0.0 <= result.friction_violation_share <= 1.0
    # The stick springs hold the contact particles near where XPBD left them.
    assert np.abs(x - start).max() < 0.05


def test_frictionless_curtain_on_sphere_balances_normal_forces() -> None:
    """A curtain pinned along its top edge hangs over a sphere (frictionless): converged; the model's
    own force (elastic + gravity, world_energy) vanishes away from the body and is along the outward
    normal, pressing inward, where the curtain touches it; nobody penetrates."""
    n = 21
    verts, faces = grid_cloth(n, n, 0.4, 0.4, plane="xy", origin=(-0.2, 0.5, 0.0))
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(n))
    model = builder.finalize("cpu")
    radius, centre = 0.1, np.array([0.0, 0.25, -0.06])
    sphere_v, sphere_f = icosphere(radius, subdivisions=3, center=tuple(centre))
    reach = CONTACT_THICKNESS + 0.5 * FABRICS["cotton"].thickness
    # Start outside the body: particles in front of the sphere pushed out onto a sphere of radius
    # radius + reach (outside the faceted icosphere by at least the contact distance).
    start = verts.copy()
    dxy2 = np.sum((verts[:, :2] - centre[:2]) ** 2, axis=1)
    covered = dxy2 < (radius + reach) ** 2
    start[covered, 2] = centre[2] + np.sqrt((radius + reach) ** 2 - dxy2[covered]) + 1e-4
    x, result = solve_equilibrium(model, 0, start, body_vertices=sphere_v, body_faces=sphere_f,
                                  contact_thickness=CONTACT_THICKNESS, friction="none")
    assert result.converged and result.residual <= result.tol_force, result
    assert result.stick_count == 0 and result.friction_violations == 0
    distance, normal = _body_distance(sphere_v, sphere_f, x)
    assert distance.min() >= reach - ATOL_PENETRATION_M, f"{(reach - distance.min()) * 1e3:.4f} mm too close"
    _, grad = world_energy(model, 0, x)
    free = model.particle_inv_mass_np > 0
    touching = free & (distance < reach + 1e-6)
    assert touching.sum() >= 1, "the curtain does not touch the sphere"
    tol = 10.0 * result.tol_force  # the residual plus the float32 rounding of the planes' search
    assert np.linalg.norm(grad[free & ~touching], axis=1).max() <= tol
    g_n = np.einsum("ij,ij->i", grad[touching], normal[touching])
    tangential = grad[touching] - g_n[:, None] * normal[touching]
    assert np.linalg.norm(tangential, axis=1).max() <= tol, "a frictionless contact carries tangential force"
    assert g_n.min() >= -tol, "a contact pulls the curtain onto the body"
