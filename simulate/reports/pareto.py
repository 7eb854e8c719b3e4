"""Pareto front of (time, error) points and the error-vs-time plot.

A point is a mapping with at least ``label`` (str), ``ms_per_frame`` (wall time per converged
frame [ms], > 0) and ``error_mm`` (error against the reference [mm], >= 0); other keys are kept
(``group`` picks the marker colour, e.g. the solver). Points whose time or error is not finite
(an exploded setting) are never on the front and are drawn as crosses at the top of the plot.

``drape evaluate`` adds a learner to the simulator's picture with ``extra_points``::

    plot_error_vs_time(points, "accuracy_pareto.png", highlight="xpbd-gs s10 i10 tol0.01 f32",
                       extra_points=[{"label": "tailornet", "ms_per_frame": 1.3, "error_mm": 11.2}])
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

from simulate.reports.labels import place_labels

__all__ = ["pareto_front", "front_time_at_error", "plot_error_vs_time", "NEAR_FRONT_TIME_FACTOR",
           "NEAR_FRONT_ERROR_SLACK"]

NEAR_FRONT_TIME_FACTOR = 1.5
"""A setting is "near the front" when it takes at most this factor times the time of the fastest
front point that is at least as accurate [-]."""

NEAR_FRONT_ERROR_SLACK = 0.02
"""Front points within this relative error of the setting count as "as accurate" [-]: errors that
differ by run-to-run noise (e.g. a float16 twin, or a looser tolerance stopping at the same drape)
must not decide the comparison."""


def _value(point: Mapping[str, Any], key: str, index: int) -> float:
    if key not in point:
        raise ValueError(f"points[{index}] has no {key!r} (keys: {sorted(point)}); expected label, ms_per_frame, error_mm")
    try:
        return float(point[key])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"points[{index}][{key!r}] must be a number (got {point[key]!r})") from exc


def _finite(t: float, e: float) -> bool:
    return math.isfinite(t) and math.isfinite(e) and t > 0.0 and e >= 0.0


def pareto_front(points: Sequence[Mapping[str, Any]], *, time_key: str = "ms_per_frame",
                 error_key: str = "error_mm") -> list[int]:
    """Indices of the non-dominated points, sorted by increasing time.

    A point dominates another when it is no slower and no less accurate and strictly better in
    one of the two. Ties (equal time and error) keep the first index. Points with a non-finite or
    non-positive time, or a non-finite or negative error, are excluded.

    Args:
        points: mappings with ``time_key`` [ms] and ``error_key`` [mm].
    Returns:
        indices into ``points``.
    """
    vals = [(_value(p, time_key, i), _value(p, error_key, i)) for i, p in enumerate(points)]
    order = sorted((i for i, (t, e) in enumerate(vals) if _finite(t, e)), key=lambda i: (vals[i][0], vals[i][1], i))
    front: list[int] = []
    best_error = math.inf
    for i in order:
        t, e = vals[i]
        if e < best_error:
            front.append(i)
            best_error = e
    return front


def front_time_at_error(points: Sequence[Mapping[str, Any]], error_mm: float, *, time_key: str = "ms_per_frame",
                        error_key: str = "error_mm") -> float:
    """Time [ms] of the fastest front point whose error is <= ``error_mm`` (inf if none)."""
    best = math.inf
    for i in pareto_front(points, time_key=time_key, error_key=error_key):
        if float(points[i][error_key]) <= error_mm:
            best = min(best, float(points[i][time_key]))
    return best


_GROUP_COLOURS = ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"]


def plot_error_vs_time(
    points: Sequence[Mapping[str, Any]],
    out_png: str | Path,
    *,
    highlight: str | None = None,
    extra_points: Sequence[Mapping[str, Any]] = (),
    title: str | None = None,
    time_key: str = "ms_per_frame",
    error_key: str = "error_mm",
    annotate: bool = True,
    ylabel: str = "max vertex error against the reference [mm]",
) -> Path:
    """Log-log error-vs-time scatter with the Pareto front drawn as a step line.

    Args:
        points: simulator settings (see the module docstring); ``group`` (optional) colours them.
        out_png: output PNG path (parent folders are created).
        highlight: label of the point to mark (the production default): a red ring and its label.
        extra_points: further points drawn as stars with their labels (a learner from
            ``drape evaluate``); they are not part of the simulator's front.
        title: plot title.
        annotate: write every point's label next to it.
        ylabel: y axis label (say which error ``error_key`` holds).
    Returns:
        the PNG path.
    Raises:
        ValueError if a point lacks a key or ``highlight`` names no point.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [str(p.get("label", i)) for i, p in enumerate(points)]
    if highlight is not None and highlight not in labels:
        raise ValueError(f"highlight {highlight!r} is not the label of any point (labels: {labels})")
    vals = [(_value(p, time_key, i), _value(p, error_key, i)) for i, p in enumerate(points)]
    extra = [(_value(p, time_key, i), _value(p, error_key, i), str(p.get("label", f"extra {i}")))
             for i, p in enumerate(extra_points)]
    good = [v for v in vals if _finite(*v)] + [(t, e) for t, e, _ in extra if _finite(t, e)]
    floor = min([e for _, e in good if e > 0.0], default=1e-3) * 0.5  # where an exact (0 mm) point is drawn
    top = max([e for _, e in good], default=1.0) * 3.0
    fig, ax = plt.subplots(figsize=(8.0, 5.5), dpi=120)
    groups: dict[str, str] = {}
    labelled: set[str] = set()
    to_label: list[tuple[float, float, str]] = []  # (time, error, text): placed after the layout
    for i, (p, (t, e)) in enumerate(zip(points, vals)):
        group = str(p.get("group", "settings"))
        colour = groups.setdefault(group, _GROUP_COLOURS[len(groups) % len(_GROUP_COLOURS)])
        if _finite(t, e):
            ax.scatter([t], [max(e, floor)], color=colour, s=22, zorder=3, label=None if group in labelled else group)
            labelled.add(group)
            if annotate:
                to_label.append((t, max(e, floor), labels[i]))
        elif math.isfinite(t) and t > 0.0:
            ax.scatter([t], [top], color=colour, marker="x", s=30, zorder=3)
            if annotate:
                to_label.append((t, top, labels[i] + " (failed)"))
    front = pareto_front(points, time_key=time_key, error_key=error_key)
    if front:
        ft = [vals[i][0] for i in front]
        fe = [max(vals[i][1], floor) for i in front]
        ax.step(ft, fe, where="post", color="black", lw=1.2, zorder=2, label="Pareto front")
        ax.scatter(ft, fe, facecolors="none", edgecolors="black", s=60, zorder=4)
    if highlight is not None:
        t, e = vals[labels.index(highlight)]
        y = max(e, floor) if _finite(t, e) else top
        ax.scatter([t], [y], facecolors="none", edgecolors="red", s=180, linewidths=2.0, zorder=5,
                   label=f"default: {highlight}")
    for t, e, label in extra:
        if _finite(t, e):
            ax.scatter([t], [max(e, floor)], marker="*", s=160, color="crimson", zorder=6, label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per converged frame [ms]")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.set_title(title or "error against run time")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    # after the layout, in window coordinates: the learners' stars first (larger), then the settings
    place_labels(ax, [(t, max(e, floor)) for t, e, _ in extra if _finite(t, e)],
                 [label for t, e, label in extra if _finite(t, e)], fontsize=8, color="crimson")
    place_labels(ax, [(t, e) for t, e, _ in to_label], [text for *_, text in to_label], fontsize=5.5)
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
