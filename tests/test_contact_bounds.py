"""Cloth self-contact with displacement bounds (SolverVBD): no new intersection, whatever the speed."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth
from simulate.quality import QualityMeter
from unit_sim import unit_settings

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def _layers():
    lower_v, lower_f = grid_cloth(9, 9, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    upper_v, upper_f = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.16, 0.03, -0.14))
    return lower_v, np.vstack([lower_v, upper_v]), np.vstack([lower_f, upper_f + len(lower_v)])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bounds", [True, False], ids=["bounds", "no-bounds"])
def test_fast_layer_does_not_pass_through(device: str, bounds: bool) -> None:
    """A layer thrown at 6 m/s onto a pinned one, 3 cm below: a substep carries it 2 cm, past the
    penalty's reach; the bounds hold it to a fraction of the distance it was searched at, so it
    lands and never crosses (crossings counted every frame); with the penalty alone it passes."""
    lower_v, verts, faces = _layers()
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)))
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver="vbd", settings=unit_settings(substeps=5, iterations=5, damping=2.0,
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
