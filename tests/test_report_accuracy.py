"""CI version of ``drape report accuracy``: a towel on a capsule on CPU (and CUDA where present).

Checks that the error against the tight reference falls as XPBD iterations rise, that the float16
storage row adds no more than the float16 rounding bound, and the report's bookkeeping."""
from __future__ import annotations

import math

import pytest
import warp as wp

from simulate.reports.accuracy import (DEFAULT_SETTING, REFERENCE_SETTINGS, Resume, Setting, format_table, run_accuracy,
                                      summarize, sweep_settings)
from simulate.reports.scenes import build_scene

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])

ITERATIONS = (2, 4, 8)
MONOTONE_RTOL = 0.05
"""Error may rise by at most this fraction from one iteration count to the next (solver noise) [-]."""
MONOTONE_ATOL_MM = 0.05
"""... plus this absolute slack [mm]."""
FLOAT16_BOUND_MM = 0.49
"""float16 round trip of positions within 2 m of the origin: at most 2**-11 m [mm]."""


@pytest.fixture(scope="module")
def scene():
    return build_scene(body="capsule", resolution=60)


@pytest.mark.parametrize("device", DEVICES)
def test_error_falls_as_iterations_rise(scene, device: str) -> None:
    sweep = [Setting("xpbd", "gauss_seidel", 4, i, 0.01) for i in ITERATIONS]
    sweep.append(Setting("xpbd", "gauss_seidel", 4, ITERATIONS[-1], 0.01, "float16"))
    default = sweep[1]
    streamed: list[dict] = []
    report = run_accuracy(scene, poses=["canonical"], settings=sweep, reference=REFERENCE_SETTINGS["ci"], default=default,
                          device=device, max_frames=200, reference_max_frames=400,
                          drape_setting=Setting("xpbd", "gauss_seidel", 4, 2, 0.02), on_row=streamed.append)
    rows = {r["label"]: r for r in report["rows"]}
    # rows are handed out as soon as they are measured (a sweep cut short keeps them): reference first
    assert streamed[0] == {"reference": report["reference"]} and streamed[1:] == report["rows"]
    print(format_table(report))
    assert report["reference"]["status"] == ["CONVERGED"], f"reference did not converge: {report['reference']}"
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
        assert {s.group for s in settings} == {"xpbd-gs", "xpbd-jac", "mass-spring"}
        assert {s.precision for s in settings} == {"float32", "float16"}
    with pytest.raises(ValueError, match="sweep"):
        sweep_settings("huge")
    with pytest.raises(ValueError, match="solver"):
        Setting(solver="newton")
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
