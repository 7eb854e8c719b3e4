"""Body friction against Coulomb's law: a 10 cm cloth patch on an incline of angle theta with
friction coefficient mu stays put where tan(theta) < mu and slides s = g (sin theta - mu cos theta)
t^2 / 2 where tan(theta) > mu (no damping).

XPBD cancels the slip of each substep up to mu times the normal push at the position level, which
is exact for a patch moving as one body at any stiffness.  VBD puts friction as a force into each
vertex's Newton step (``simulate.solvers.vbd.kernels.friction_terms``); its local steps carry a
rigid motion of a stiff patch slowly (the elastic Hessian dwarfs m / dt^2), so the sliding
distance is checked on a soft patch, where the local step is the whole step, and on cotton only
that the slope is not held (a slip budget in a free particle's displacement units would hold it)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from simulate.cloth import ClothBuilder, Features
from simulate.cloth.fabric import FABRICS
from simulate.contact import BodyCollider
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth
from unit_sim import unit_settings

GRAVITY = 9.81
MU = 0.5
FRAME_DT = 1.0 / 45.0
STEPPING = {"xpbd": dict(substeps=15, iterations=5), "vbd": dict(substeps=10, iterations=3)}
"""Each solver's stepping as the dataset runs it (XPBD: the library default; VBD: the point of its
substeps front that meets the hanging-strip bar, docs/benchmarks.md)."""
RTOL_SLIDE = 0.05
SOFT = dict(stretch_stiffness=1.0, shear_stiffness=0.1, weft_stiffness=None)
"""A patch whose elastic Hessian is below a vertex's m / dt^2 [N/m]."""


def slide_on_incline(solver: str, theta_deg: float, *, frames: int = 27, damping: float = 0.0,
                     **fabric_fields) -> float:
    """Distance [m] a cotton patch (9 x 9 vertices, 10 x 10 cm, mu = 0.5) released at rest on an
    incline of ``theta_deg`` degrees moves along the slope in ``frames`` frames of 1/45 s."""
    theta = np.radians(theta_deg)
    turn = trimesh.transformations.rotation_matrix(theta, (0.0, 0.0, 1.0))
    slab = trimesh.creation.box(extents=(2.0, 0.2, 2.0))
    slab.apply_translation((0.0, -0.1, 0.0))  # top face at y = 0 before the turn
    slab.apply_transform(turn)
    fabric = dataclasses.replace(FABRICS["cotton"], friction=MU, damping=0.0, **fabric_fields)
    collider = BodyCollider(np.asarray(slab.vertices, np.float32), np.asarray(slab.faces, np.int32), device="cpu")
    lift = collider.thickness + fabric.thickness / 2.0 + 1.0e-4  # released just outside its contact distance
    verts, faces = grid_cloth(9, 9, 0.1, 0.1, plane="xz", origin=(-0.05, lift, -0.05))
    verts = (np.asarray(verts, np.float64) @ turn[:3, :3].T).astype(np.float32)
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric=fabric)
    model = builder.finalize("cpu", features=Features(friction=True))
    sim = QuasiStaticSimulator(model, collider, solver=solver, settings=unit_settings(
        frame_dt=FRAME_DT, damping=damping, **STEPPING[solver]))
    start = sim.positions().mean(axis=0)
    for _ in range(frames):
        sim.step_frame()
    down_slope = np.array([-np.cos(theta), -np.sin(theta), 0.0])
    return float((sim.positions().mean(axis=0) - start) @ down_slope)


def coulomb_slide(theta_deg: float, frames: int = 27) -> float:
    """g (sin theta - mu cos theta) t^2 / 2 [m], 0 where friction holds."""
    theta = np.radians(theta_deg)
    t = frames * FRAME_DT
    return max(GRAVITY * (np.sin(theta) - MU * np.cos(theta)), 0.0) * t * t / 2.0


@pytest.mark.parametrize("solver,fabric", [("xpbd", "cotton"), ("xpbd", "soft"), ("vbd", "soft")])
@pytest.mark.parametrize("theta", [20.0, 32.0, 40.0])
def test_patch_on_incline_follows_coulomb(solver: str, fabric: str, theta: float) -> None:
    """Below the friction angle (26.6 degrees) the patch stays within 1 mm; above it, it slides
    Coulomb's distance within 5 %."""
    moved = slide_on_incline(solver, theta, **(SOFT if fabric == "soft" else {}))
    expected = coulomb_slide(theta)
    if expected == 0.0:
        assert abs(moved) < 1.0e-3, f"{solver}, {fabric}, {theta} deg: slid {moved * 1e3:.2f} mm, friction holds"
    else:
        assert abs(moved - expected) <= RTOL_SLIDE * expected, (
            f"{solver}, {fabric}, {theta} deg: slid {moved * 1e3:.1f} mm, Coulomb {expected * 1e3:.1f} mm")


def test_vbd_does_not_hold_cotton_beyond_the_friction_angle() -> None:
    """Cotton at production stiffness on a 40 degree slope with mu = 0.5 slides (its tangential
    load is 1.7 mu N); on a 20 degree slope, damped as the dataset steps, it stays."""
    steep = slide_on_incline("vbd", 40.0)
    assert steep > 0.01, f"cotton on 40 degrees moved {steep * 1e3:.2f} mm in 0.6 s: friction holds it"
    gentle = slide_on_incline("vbd", 20.0, frames=90, damping=20.0)
    assert abs(gentle) < 1.0e-3, f"cotton on 20 degrees moved {gentle * 1e3:.2f} mm in 2 s, friction holds"
