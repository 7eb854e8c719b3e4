"""The dataset audit's reference (pipelines/audit.py) on a towel draped over the CI capsule: the
reference is the static equilibrium of the frame's model (its forces balance away from the body),
a frame displaced by a known amount is reported with that error, and frames whose reference does
not converge are counted, not measured."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pipelines.audit import frame_record, reference_model, solve_reference, summarize_frames
from simulate.cloth.fabric import FABRICS
from simulate.quasi_static import WorldStatus
from simulate.reports.scenes import build_scene, run_worlds
from simulate.solvers.reference import world_energy
from unit_sim import unit_settings

CONTACT_THICKNESS = 0.004
"""Collider thickness of the drape and of the reference [m] (the production spec's)."""
OFF_BODY_MARGIN = 1.0e-3
"""Particles farther than their contact distance plus this from the body carry no contact force [m]."""
DISPLACEMENT_MM = 2.0
"""Known displacement of the perturbed frame's off-body particles [mm]."""
RETURN_ATOL_MM = 1.0e-4
"""The displaced frame's reference lies within this of the undisplaced frame's reference [mm] (0.1 um)."""
REST_ATOL_MM = 1.0e-2
"""A frame at rest moves less than this when re-solved [mm]: contacts within the stick threshold
(0.1 mm) of their plane are held or released by where they start, which moves the rest state by
micrometres."""


@pytest.fixture(scope="module")
def frame():
    """A towel draped on the capsule by XPBD (the recorded frame), its model and body, and its reference."""
    scene = build_scene(body="capsule", resolution=60)
    body = scene.body_vertices(scene.neutral_shape[None], scene.canonical_pose[None])[0]
    run = run_worlds(scene, start=scene.start_vertices, paths=[body], fabrics=["cotton"],
                     settings=unit_settings(frame_dt=1 / 45, substeps=4, iterations=8, tolerance=0.01, max_frames=300,
                                          damping=20.0),
                     contact_thickness=CONTACT_THICKNESS)
    assert run.status[0] == WorldStatus.CONVERGED, run
    model = reference_model(scene.rest_vertices, scene.faces, fabric="cotton", material_uv=scene.material_uv)
    recorded = run.positions[0]
    x, result = solve_reference(model, recorded, body[0], scene.body_faces, contact_thickness=CONTACT_THICKNESS,
                                max_iterations=60)
    mesh = trimesh.Trimesh(body[0], scene.body_faces, process=False)
    reach = CONTACT_THICKNESS + 0.5 * FABRICS["cotton"].thickness + OFF_BODY_MARGIN
    off_body = trimesh.proximity.closest_point_naive(mesh, x)[1] > reach
    return dict(scene=scene, body=body[0], model=model, recorded=recorded, x=x, result=result, off_body=off_body)


def test_reference_is_the_equilibrium_of_the_frame(frame) -> None:
    """Newton converged to its force tolerance, and away from the body (where no contact force acts)
    the model's elastic + gravity forces balance at the reference, by an energy gradient computed
    without the solver's contact terms; at the recorded XPBD frame they do not (the reference moved)."""
    x, result, off = frame["x"], frame["result"], frame["off_body"]
    assert result.converged and result.residual <= result.tol_force, result
    assert off.sum() >= 10, "too few off-body particles to test"
    _, grad = world_energy(frame["model"], 0, x)
    force = np.linalg.norm(grad, axis=1)[off]
    assert force.max() <= result.tol_force, f"unbalanced force {force.max():.3g} N off the body (tol {result.tol_force:.3g} N)"
    _, grad0 = world_energy(frame["model"], 0, frame["recorded"])
    assert np.linalg.norm(grad0, axis=1)[off].max() > 1e3 * result.tol_force, "the recorded frame was already at rest"
    rec = frame_record(frame["recorded"], x, result)
    dist = 1e3 * np.linalg.norm(x - frame["recorded"], axis=1)
    assert rec["max_mm"] == pytest.approx(dist.max()) and rec["mean_mm"] == pytest.approx(dist.mean()) and rec["max_mm"] > 0
    assert rec["residual_n"] == result.residual and rec["converged"] is True and rec["iterations"] == result.iterations
    assert 0.0 <= rec["friction_violation_share"] <= 1.0 and rec["stick_count"] > 0


def test_a_frame_displaced_by_a_known_amount_reports_that_error(frame) -> None:
    """A frame at rest (the reference of the reference: the contacts it holds are those of its own
    start) with its off-body particles moved 2 mm sideways: the reference brings them back to where the
    undisplaced frame's reference has them (the contacts, held by stick, are where they were), so the
    audit reports 2 mm max and 2 mm times the moved share as mean."""
    scene, off = frame["scene"], frame["off_body"]

    def solve(start):
        return solve_reference(frame["model"], start, frame["body"], scene.body_faces, contact_thickness=CONTACT_THICKNESS,
                               max_iterations=60)

    rest, _ = solve(frame["x"])
    expected, _ = solve(rest)
    assert 1e3 * np.abs(expected - rest).max() <= REST_ATOL_MM, "the frame is not at rest"
    perturbed = rest.copy()
    perturbed[off, 2] += 1e-3 * DISPLACEMENT_MM
    back, result = solve(perturbed)
    assert result.converged, result
    assert 1e3 * np.abs(back - expected).max() <= RETURN_ATOL_MM, (
        f"the displaced frame's reference is {1e3 * np.abs(back - expected).max():.5f} mm from the frame's")
    rec = frame_record(perturbed, back, result)
    assert rec["max_mm"] == pytest.approx(DISPLACEMENT_MM, abs=REST_ATOL_MM)
    assert rec["mean_mm"] == pytest.approx(DISPLACEMENT_MM * off.mean(), abs=REST_ATOL_MM)


def test_unconverged_references_are_counted_not_measured(frame) -> None:
    """A reference cut at one Newton iteration from the flat start is reported converged false; the
    distributions then cover only the converged frames and the count says how many were left out."""
    scene = frame["scene"]
    x, cut = solve_reference(frame["model"], scene.start_vertices, frame["body"], scene.body_faces,
                             contact_thickness=CONTACT_THICKNESS, max_iterations=1)
    assert not cut.converged and cut.iterations == 1
    good = frame_record(frame["recorded"], frame["x"], frame["result"])
    bad = frame_record(scene.start_vertices, x, cut)
    assert bad["converged"] is False
    summary = summarize_frames([good, bad])
    assert (summary["converged"], summary["not_converged"]) == (1, 1)
    assert summary["max_mm"] == {"median": good["max_mm"], "p90": good["max_mm"], "max": good["max_mm"]}
    assert summary["mean_mm"]["max"] == good["mean_mm"]
    assert summary["residual_n"]["max"] == max(good["residual_n"], bad["residual_n"]), "reference stats cover all frames"
    none = summarize_frames([bad])
    assert "max_mm" not in none and "mean_mm" not in none and none["not_converged"] == 1


def test_audit_frames_solved_in_processes_equal_serial() -> None:
    """The audit's frames solved in a process pool are the serial solves, frame for frame, bit for bit."""
    from pipelines.audit import solve_references
    from simulate.scenes import grid_cloth, icosphere

    verts, faces = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.15, 0.255, -0.15))
    sphere_v, sphere_f = icosphere(0.25, subdivisions=2)
    jobs = [(verts, faces, "cotton", None, verts + [0.0, dy, 0.0], sphere_v, sphere_f, 2.0e-3, 40)
            for dy in (0.0, 0.002)]
    serial = solve_references(jobs, workers=1)
    pooled = solve_references(jobs, workers=2)
    for (xs, rs), (xp, rp) in zip(serial, pooled):
        assert np.array_equal(xs, xp), f"pool and serial solves differ by {np.abs(xs - xp).max():.3g} m"
        assert rs.iterations == rp.iterations and rs.residual == rp.residual
