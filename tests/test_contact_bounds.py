"""Cloth self-contact with displacement bounds (SolverVBD, SolverXPBD): no new intersection, whatever the speed."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth
from simulate.quality import QualityMeter
from simulate.solvers.vbd.kernels import edge_edge_contact, vertex_triangle_contact
from unit_sim import unit_settings

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def _layers():
    lower_v, lower_f = grid_cloth(9, 9, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    upper_v, upper_f = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.16, 0.03, -0.14))
    return lower_v, np.vstack([lower_v, upper_v]), np.vstack([lower_f, upper_f + len(lower_v)])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bounds", [True, False], ids=["bounds", "no-bounds"])
@pytest.mark.parametrize("solver", ["vbd", "xpbd"])
def test_fast_layer_does_not_pass_through(device: str, bounds: bool, solver: str) -> None:
    """A layer thrown at 6 m/s onto a pinned one, 3 cm below: a substep carries it 2 cm, past the
    penalty's reach; the bounds hold it to a fraction of the distance it was searched at, so it
    lands and never crosses (crossings counted every frame); with the penalty alone it passes."""
    lower_v, verts, faces = _layers()
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)))
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver=solver, settings=unit_settings(substeps=5, iterations=5, damping=2.0,
                                                                                frame_dt=1.0 / 60.0),
                               solver_options={"self_contact_options": {"bounds": bounds}})
    v0 = np.zeros((len(verts), 3), np.float32)
    v0[len(lower_v):, 1] = -6.0
    sim.state_0.particle_qd.assign(v0)
    meter = QualityMeter(faces, verts, faces[:1], 3, device=device)
    crossings = []
    for _ in range(20):
        sim.step_frame()
        crossings.append(meter.self_intersections(sim.positions()))
    upper = sim.positions()[len(lower_v):]
    if bounds:
        assert max(crossings) == 0, f"crossings per frame: {crossings}"
        assert upper[:, 1].min() > 0.0 and upper[:, 1].max() < 0.02, upper[:, 1].min()
    else:
        assert upper[:, 1].min() < -0.05, "the scene must be fast enough to pass without the bounds"


@pytest.mark.parametrize("device", DEVICES)
def test_world_without_self_contact_is_unaffected(device: str) -> None:
    """A world whose self-contact is switched off beside one with it steps bit for bit as the same
    world in a model without self-contact."""
    lower_v, verts, faces = _layers()
    runs = {}
    for on in (True, False):
        builder = ClothBuilder()
        for _ in range(2 if on else 1):
            builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)))
        model = builder.finalize(device, features=Features(self_contact=on, body_contact=False))
        sim = QuasiStaticSimulator(model, None, solver="vbd", settings=unit_settings(substeps=4, iterations=3))
        if on:
            sim.control.set_self_contact(np.array([True, False]))
        for _ in range(8):
            sim.step_frame()
        runs[on] = sim.positions().reshape(model.world_count, len(verts), 3)
    np.testing.assert_array_equal(runs[True][1], runs[False][0])
    assert not np.array_equal(runs[True][0], runs[False][0]), "self-contact changed nothing in its own world"


@pytest.mark.parametrize("device", DEVICES)
def test_free_layers_bounce_off_each_other_without_crossing(device: str) -> None:
    """Two free layers flying at each other without gravity or damping, bounds off: the pair
    energies alone stop them at the contact distance and send them apart, none crossing."""
    lower_v, lower_f = grid_cloth(6, 6, 0.1, 0.1, plane="xz", origin=(-0.05, 0.0, -0.05))
    upper_v, upper_f = grid_cloth(6, 6, 0.1, 0.1, plane="xz", origin=(-0.047, 0.012, -0.052))
    verts = np.vstack([lower_v, upper_v])
    faces = np.vstack([lower_f, upper_f + len(lower_v)])
    builder = ClothBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_garment(verts, faces, fabric="cotton")
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver="vbd", settings=unit_settings(substeps=10, iterations=5, damping=0.0,
                                                                               frame_dt=1.0 / 60.0),
                               solver_options={"self_contact_options": {"bounds": False}})
    n = len(lower_v)
    v0 = np.zeros((len(verts), 3), np.float32)
    v0[:n, 1] = 0.25
    v0[n:, 1] = -0.25
    sim.state_0.particle_qd.assign(v0)
    meter = QualityMeter(faces, verts, faces[:1], 3, device=device)
    crossings, gaps = [], []
    for _ in range(12):
        sim.step_frame()
        x = sim.positions()
        crossings.append(meter.self_intersections(x))
        gaps.append(float(x[n:, 1].mean() - x[:n, 1].mean()))
    assert max(crossings) == 0, f"crossings per frame: {crossings}"
    assert min(gaps) < 0.004, f"the layers never met: mean gaps {gaps}"
    v = sim.state_0.particle_qd.numpy()[:len(verts)]
    assert v[n:, 1].mean() > 0.1 and v[:n, 1].mean() < -0.1, "the layers must have bounced off each other"


@wp.kernel
def _pair_terms(x: wp.array(dtype=wp.vec3), radius: float, stiffness: float, edge: int,
                force: wp.array(dtype=wp.vec3)):
    k = wp.tid()
    if edge == 0:
        role = k - 1  # particle 0 is the point, 1..3 the triangle's corners
        f, h = vertex_triangle_contact(x[0] - x[k], x[1] - x[k], x[2] - x[k], x[3] - x[k], role, radius, stiffness)
        force[k] = f
    else:
        end = k % 2
        if k < 2:
            f, h = edge_edge_contact(x[0] - x[k], x[1] - x[k], x[2] - x[k], x[3] - x[k], end, radius, stiffness)
        else:
            f, h = edge_edge_contact(x[2] - x[k], x[3] - x[k], x[0] - x[k], x[1] - x[k], end, radius, stiffness)
        force[k] = f


def _pair_energy(x: np.ndarray, radius: float, stiffness: float, edge: bool) -> float:
    if edge:
        s = np.linspace(0.0, 1.0, 301)
        a = x[0] + (x[1] - x[0]) * s[:, None]
        b = x[2] + (x[3] - x[2]) * s[:, None]
        d = np.linalg.norm(a[:, None] - b[None], axis=2).min()
    else:
        u, v = np.meshgrid(np.linspace(0, 1, 241), np.linspace(0, 1, 241))
        keep = (u + v) <= 1.0
        pts = x[1] + (x[2] - x[1]) * u[keep][:, None] + (x[3] - x[1]) * v[keep][:, None]
        d = np.linalg.norm(pts - x[0], axis=1).min()
    return 0.5 * stiffness * max(radius - d, 0.0) ** 2


@pytest.mark.parametrize("edge", [False, True], ids=["vertex-triangle", "edge-edge"])
def test_contact_pair_forces_are_the_energy_gradient_and_sum_to_zero(edge: bool) -> None:
    """Each pair's force on each of its four particles is minus the gradient of its contact energy
    (central differences of a brute-force distance), and the four forces cancel: the pair pushes
    both sides, equal and opposite."""
    rng = np.random.default_rng(3)
    radius, stiffness = 0.004, 1.0e4
    tested = 0
    while tested < 6:
        x = rng.normal(scale=0.004, size=(4, 3)).astype(np.float32)
        if _pair_energy(x, radius, stiffness, edge) < 1.0e-6:
            continue
        out = wp.zeros(4, dtype=wp.vec3, device="cpu")
        wp.launch(_pair_terms, dim=4, inputs=[wp.array(x, dtype=wp.vec3, device="cpu"), radius, stiffness, int(edge)],
                  outputs=[out], device="cpu")
        forces = out.numpy()
        np.testing.assert_allclose(forces.sum(axis=0), 0.0, atol=1.0e-3 * np.abs(forces).max())
        h = 2.0e-5
        for k in range(4):
            grad = np.zeros(3)
            for c in range(3):
                xp = x.astype(np.float64).copy()
                xm = xp.copy()
                xp[k, c] += h
                xm[k, c] -= h
                grad[c] = (_pair_energy(xp, radius, stiffness, edge) - _pair_energy(xm, radius, stiffness, edge)) / (2 * h)
            np.testing.assert_allclose(forces[k], -grad, atol=0.05 * np.abs(forces).max() + 1e-4)
        tested += 1
