"""Pareto front and error-vs-time plot of the reports (simulate.reports.pareto)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from simulate.reports.pareto import NEAR_FRONT_TIME_FACTOR, front_time_at_error, pareto_front, plot_error_vs_time


def _pts(pairs):
    return [{"label": f"p{i}", "ms_per_frame": t, "error_mm": e} for i, (t, e) in enumerate(pairs)]


def _front_naive(points) -> list[int]:
    """O(n^2) twin: a point is on the front when no other point dominates it (first of exact ties kept)."""
    keep = []
    for i, p in enumerate(points):
        t, e = p["ms_per_frame"], p["error_mm"]
        if not (math.isfinite(t) and math.isfinite(e) and t > 0 and e >= 0):
            continue
        dominated = False
        for j, q in enumerate(points):
            u, f = q["ms_per_frame"], q["error_mm"]
            if j == i or not (math.isfinite(u) and math.isfinite(f) and u > 0 and f >= 0):
                continue
            if (u <= t and f <= e and (u < t or f < e)) or (u == t and f == e and j < i):
                dominated = True
                break
        if not dominated:
            keep.append(i)
    return sorted(keep, key=lambda i: points[i]["ms_per_frame"])


def test_front_of_a_known_set() -> None:
    pts = _pts([(1.0, 10.0), (2.0, 5.0), (3.0, 6.0), (4.0, 1.0), (0.5, 20.0), (5.0, 1.0)])
    assert pareto_front(pts) == [4, 0, 1, 3], "p2 is dominated by p1, p5 by p3 (same error, slower)"


def test_failed_and_exact_points() -> None:
    pts = _pts([(1.0, float("inf")), (float("nan"), 1.0), (2.0, 3.0), (3.0, 0.0), (0.0, 1.0), (3.0, 0.0)])
    assert pareto_front(pts) == [2, 3], "inf/NaN/zero-time points are excluded; of exact ties the first is kept"


def test_front_matches_naive_twin_on_random_points() -> None:
    rng = np.random.default_rng(0)
    for trial in range(20):
        n = int(rng.integers(1, 40))
        times = rng.choice([0.5, 1.0, 2.0, 4.0, 8.0], size=n) if trial % 2 else rng.lognormal(size=n)
        errors = rng.choice([0.1, 1.0, 10.0], size=n) if trial % 3 == 0 else rng.lognormal(size=n)
        pts = _pts(zip(times.tolist(), errors.tolist()))
        assert pareto_front(pts) == _front_naive(pts), f"trial {trial}: front differs from the naive twin"


def test_front_time_at_error() -> None:
    pts = _pts([(1.0, 10.0), (2.0, 5.0), (4.0, 1.0)])
    assert front_time_at_error(pts, 6.0) == 2.0
    assert front_time_at_error(pts, 1.0) == 4.0
    assert math.isinf(front_time_at_error(pts, 0.5))
    assert NEAR_FRONT_TIME_FACTOR > 1.0


def test_missing_or_bad_keys_raise() -> None:
    with pytest.raises(ValueError, match="error_mm"):
        pareto_front([{"label": "a", "ms_per_frame": 1.0}])
    with pytest.raises(ValueError, match="ms_per_frame"):
        pareto_front([{"label": "a", "ms_per_frame": "fast", "error_mm": 1.0}])


def test_plot_writes_png_with_highlight_and_extra_points(tmp_path) -> None:
    pts = _pts([(1.0, 10.0), (2.0, 5.0), (3.0, 6.0), (4.0, 0.0), (2.5, float("inf"))])
    for p, g in zip(pts, ["xpbd-gs", "xpbd-gs", "xpbd-jac", "mass-spring", "xpbd-jac"]):
        p["group"] = g
    out = plot_error_vs_time(pts, tmp_path / "sub" / "pareto.png", highlight="p1",
                             extra_points=[{"label": "tailornet", "ms_per_frame": 0.3, "error_mm": 11.0}])
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, f"{out} is not a plausible PNG ({len(data)} bytes)"
    with pytest.raises(ValueError, match="highlight"):
        plot_error_vs_time(pts, tmp_path / "x.png", highlight="nope")
    with pytest.raises(ValueError, match="error_mm"):
        plot_error_vs_time(pts, tmp_path / "y.png", extra_points=[{"label": "l", "ms_per_frame": 1.0}])


def test_rows_read_back_from_accuracy_json_plot(tmp_path) -> None:
    """accuracy.json stores failed settings' errors as the strings "inf"/"nan" (standard JSON); they still plot."""
    import json

    from pipelines.report import _clean

    rows = _pts([(1.0, 2.0), (2.0, float("inf")), (3.0, 0.5)])
    back = json.loads(json.dumps(_clean(rows)))
    assert back[1]["error_mm"] == "inf"
    assert pareto_front(back) == [0, 2]
    out = plot_error_vs_time(back, tmp_path / "p.png", highlight="p1", error_key="error_mm",
                             extra_points=[{"label": "learner", "ms_per_frame": 0.5, "error_mm": 3.0}])
    assert out.is_file()
