"""CI version of ``drape report accuracy``: a towel on a capsule on CPU (and CUDA where present).

Checks that the reference is the static equilibrium of the model (forces balance off the body; the
tight XPBD run that starts it is measured against it like any setting), that the error against it
falls as XPBD iterations rise, that the float16 storage row adds no more than the float16 rounding
bound, and the report's bookkeeping."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
import warp as wp

from simulate.cloth import ClothBuilder, Features
from simulate.cloth.fabric import FABRICS
from simulate.reports.accuracy import (CONTACT_THICKNESS, DEFAULT_SETTING, REFERENCE_SETTINGS, Resume, Setting,
                                      format_table, run_accuracy, summarize, sweep_settings)
from simulate.reports.scenes import build_scene, named_pose
from simulate.solvers.reference import world_energy

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])

ITERATIONS = (2, 4, 8)
MONOTONE_RTOL = 0.05
"""Error may rise by at most this fraction from one iteration count to the next (solver noise) [-]."""
MONOTONE_ATOL_MM = 0.05
"""... plus this absolute slack [mm]."""
FLOAT16_BOUND_MM = 0.49
"""float16 round trip of positions within 2 m of the origin: at most 2**-11 m [mm]."""
STRIP_RTOL = 1.0e-3
"""The reference's hanging-strip extension against rho g L^2 / (2 Y) [-] (measured: 1e-6)."""
OFF_BODY_MARGIN = 1.0e-3
"""Particles farther than their contact distance plus this from the body carry no contact force [m]."""


@pytest.fixture(scope="module")
def scene():
    return build_scene(body="capsule", resolution=60)


def test_reference_is_the_equilibrium_not_the_tight_run(scene) -> None:
    """The reference of the tilted bar: Newton converged, and off the body (no contact force there) the
    model's elastic + gravity forces balance at the reference positions by an energy gradient computed
    without the solver's contact terms, while at the tight XPBD run that starts it they do not; that
    run, swept as a setting, is measured against the equilibrium (its error is its distance to it, not
    0). The hanging strip's extension is within 0.1 % of the analytic one."""
    tight = REFERENCE_SETTINGS["ci"]
    saved: list = []
    runs: dict = {}
    report = run_accuracy(scene, poses=["tilt"], settings=[tight], reference=tight, default=tight, device="cpu",
                          max_frames=400, reference_max_frames=400, drape_setting=Setting("xpbd", "gauss_seidel", 4, 2, 0.02),
                          on_reference=lambda *a: saved.append(a), on_progress=runs.__setitem__)
    ref = report["reference"]
    assert ref["kind"] == "equilibrium" and ref["friction"] == "stick" and ref["start"]["status"] == ["CONVERGED"], ref
    assert ref["converged"] == [True] and ref["residual_n"][0] <= ref["tol_force_n"][0], ref
    assert report["reference_strip_error"] == ref["strip"]["relative_error"] <= STRIP_RTOL, ref["strip"]
    assert ref["strip"]["converged"] and ref["strip"]["rows"] == 80
    row = report["rows"][0]
    assert row["error_max_mm"] == pytest.approx(ref["start_error_max_mm"][0], rel=1e-9) and row["error_max_mm"] > 0.01, (row, ref)
    assert row["error_mean_mm"] == pytest.approx(ref["start_error_mean_mm"][0], rel=1e-9)
    positions = saved[0][1][0]
    builder = ClothBuilder()
    builder.add_garment(scene.rest_vertices, scene.faces, fabric="cotton", material_uv=scene.material_uv)
    model = builder.finalize("cpu", features=Features())
    body = scene.body_vertices(scene.neutral_shape[None], named_pose("tilt")[None])[0][0]
    mesh = trimesh.Trimesh(body, scene.body_faces, process=False)
    off = trimesh.proximity.closest_point_naive(mesh, positions)[1] > (
        CONTACT_THICKNESS + 0.5 * FABRICS["cotton"].thickness + OFF_BODY_MARGIN)
    assert off.sum() >= 10, "too few off-body particles to test"
    force = np.linalg.norm(world_energy(model, 0, positions)[1], axis=1)[off]
    assert force.max() <= ref["tol_force_n"][0], f"unbalanced force {force.max():.3g} N off the body at the reference"
    start = runs[f"{tight.label} (reference start)"].positions[0]
    assert np.linalg.norm(world_energy(model, 0, start)[1], axis=1)[off].max() > 1e3 * ref["tol_force_n"][0], (
        "the tight XPBD run is at rest already: the test cannot tell it from the equilibrium")
    assert 1e3 * np.linalg.norm(start - positions, axis=1).max() == pytest.approx(ref["start_error_max_mm"][0])


@pytest.mark.parametrize("device", DEVICES)
def test_error_falls_as_iterations_rise(scene, device: str) -> None:
    sweep = [Setting("xpbd", "gauss_seidel", 4, i, 0.01) for i in ITERATIONS]
    sweep.append(Setting("xpbd", "gauss_seidel", 4, ITERATIONS[-1], 0.01, "float16"))
    default = sweep[1]
    streamed: list[dict] = []
    report = run_accuracy(scene, poses=["tilt"], settings=sweep, reference=REFERENCE_SETTINGS["ci"], default=default,
                          device=device, max_frames=200, reference_max_frames=400,
                          drape_setting=Setting("xpbd", "gauss_seidel", 4, 2, 0.02), on_row=streamed.append)
    rows = {r["label"]: r for r in report["rows"]}
    # rows are handed out as soon as they are measured (a sweep cut short keeps them): reference first
    assert streamed[0] == {"reference": report["reference"]} and streamed[1:] == report["rows"]
    print(format_table(report))
    ref = report["reference"]
    assert ref["converged"] == [True] and ref["residual_n"][0] <= ref["tol_force_n"][0], f"reference did not converge: {ref}"
    errors = [rows[s.label] for s in sweep[:len(ITERATIONS)]]
    for key in ("error_max_mm", "error_mean_mm"):
        vals = [r[key] for r in errors]
        assert all(math.isfinite(v) for v in vals), f"{key} not finite: {vals}"
        for a, b, i in zip(vals, vals[1:], ITERATIONS[1:]):
            assert b <= a * (1 + MONOTONE_RTOL) + MONOTONE_ATOL_MM, f"{key} rose at {i} iterations: {vals} mm"
        assert vals[-1] < vals[0], f"{key} did not fall from {ITERATIONS[0]} to {ITERATIONS[-1]} iterations: {vals}"
    f32, f16 = rows[sweep[2].label], rows[sweep[3].label]
    assert f16["ms_per_frame"] == f32["ms_per_frame"], "float16 row must reuse the float32 simulation"
    assert abs(f16["error_max_mm"] - f32["error_max_mm"]) <= FLOAT16_BOUND_MM, (
        f"float16 rounding changed the max error by {abs(f16['error_max_mm'] - f32['error_max_mm']):.3f} mm")
    for r in report["rows"]:
        assert r["converged"] == 1.0 and r["exploded"] == 0, f"{r['label']}: converged {r['converged']}, exploded {r['exploded']}"
        assert r["stretch_max"] < 1.1 and r["penetration_max_mm"] < 5.0, f"{r['label']}: {r}"
        assert r["ms_per_frame"] > 0.0
    assert report["front"], "the Pareto front is empty"
    assert report["default"] == default.label
    assert report["default_on_front"] == (default.label in report["front"])
    assert report["front_mean"] and report["default_on_front_mean"] == (default.label in report["front_mean"])
    # the fastest setting is on both fronts (nothing is faster)
    fastest = min(report["rows"], key=lambda r: r["ms_per_frame"])["label"]
    assert fastest in report["front"] and fastest in report["front_mean"]
    table = format_table(report)
    assert all(s.label in table for s in sweep), "table misses a setting"


def test_sweeps_hold_the_default_once_and_reject_bad_names() -> None:
    for size in ("small", "full"):
        settings = sweep_settings(size)
        labels = [s.label for s in settings]
        assert labels[0] == DEFAULT_SETTING.label == "xpbd-gs s15 i5 tol0.05 f32" and len(set(labels)) == len(labels), f"{size}: {labels}"
        assert {s.group for s in settings} == {"xpbd-gs", "xpbd-jac", "vbd", "mass-spring"}
        assert {s.precision for s in settings} == {"float32", "float16"}
        vbd = [s for s in settings if s.solver == "vbd"]
        assert len({s.simulation_key() for s in vbd}) == len(vbd) >= 3, "VBD rows must differ in substeps/sweeps/tolerance"
        assert all(s.substeps >= 15 for s in vbd), "VBD needs >= 15 substeps per 1/45 s frame"
    with pytest.raises(ValueError, match="sweep"):
        sweep_settings("huge")
    with pytest.raises(ValueError, match="solver"):
        Setting(solver="newton")
    with pytest.raises(ValueError, match="substeps"):
        Setting(solver="vbd", substeps=None)
    assert Setting("vbd", substeps=20, iterations=3).label == "vbd s20 i3 tol0.01 f32"
    assert Setting("vbd", substeps=20, iterations=3).simulation_key() != Setting("vbd", substeps=20, iterations=5).simulation_key()
    with pytest.raises(ValueError, match="precision"):
        Setting(precision="bfloat16")


def test_default_must_be_in_the_sweep(scene) -> None:
    with pytest.raises(ValueError, match="default"):
        run_accuracy(scene, poses=["tilt"], settings=[Setting(iterations=3)], reference=REFERENCE_SETTINGS["ci"])
    with pytest.raises(ValueError, match="pose"):
        run_accuracy(scene, poses=["moonwalk"], settings=[DEFAULT_SETTING], reference=REFERENCE_SETTINGS["ci"])


def test_resume_skips_the_reference_and_finished_rows(scene) -> None:
    """A sweep cut short resumes: the saved reference is not solved again, finished rows are reused,
    and the missing rows (a float32 setting and its float16 variant) come out as in the full run."""
    sweep = [Setting("xpbd", "gauss_seidel", 4, 2, 0.01), Setting("xpbd", "gauss_seidel", 4, 4, 0.01),
             Setting("xpbd", "gauss_seidel", 4, 4, 0.01, "float16")]
    kw = dict(poses=["canonical"], settings=sweep, reference=REFERENCE_SETTINGS["ci"], default=sweep[0], device="cpu",
              max_frames=200, reference_max_frames=400, drape_setting=Setting("xpbd", "gauss_seidel", 4, 2, 0.02))
    saved: list = []
    streamed: list[dict] = []
    full = run_accuracy(scene, on_reference=lambda *a: saved.append(a), on_row=streamed.append, **kw)
    # precision variants are measured right after their simulation
    assert [r["label"] for r in streamed[1:]] == [s.label for s in sweep]
    summary, positions, status = saved[0]
    assert summary == full["reference"] and positions.shape == (1, scene.vertex_count, 3) and len(status) == 1
    first = full["rows"][0]
    sims: list[str] = []
    again: list[dict] = []
    resumed = run_accuracy(scene, resume=Resume(reference=summary, reference_positions=positions, reference_status=status,
                                                rows={first["label"]: first}),
                           on_progress=lambda label, run: sims.append(label), on_row=again.append, **kw)
    assert not any("reference" in s for s in sims), f"the reference was solved again: {sims}"
    assert sims == ["canonical drape", sweep[1].label], sims
    assert resumed["resumed_rows"] == 1 and full["resumed_rows"] == 0
    assert [r["label"] for r in again] == [sweep[1].label, sweep[2].label], "reused rows must not be streamed again"
    assert resumed["rows"][0] is first
    for a, b in zip(full["rows"][1:], resumed["rows"][1:]):
        assert a["error_max_mm"] == b["error_max_mm"] and a["error_mean_mm"] == b["error_mean_mm"], (a, b)
    assert resumed["front"] == summarize(resumed["rows"], sweep[0].label)["front"]
    with pytest.raises(ValueError, match="saved reference"):
        run_accuracy(scene, resume=Resume(summary, positions[:, :3], status, {}), **kw)
