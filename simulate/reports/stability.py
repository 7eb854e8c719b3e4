"""Stiff and extreme cases (``drape report stability``).

Each *cell* of the matrix is one case run from the scene's canonical drape (computed once with
the report's settings): the body goes along a slerp pose path (one frame per 0.1 rad of the
largest joint change, or the given number of frames for fast transitions) with its shape blended
from neutral over the same frames, and the cloth then relaxes with the report's settings
(XPBD Gauss-Seidel, frames of 1/60 s in 10 substeps x 10 iterations, the body queried every substep,
tolerance 0.01 m/s, damping 5/s) unless the cell changes them. Families (``value`` is what the cell changes):

==============  ===========================================================================
family          cells
==============  ===========================================================================
stretch         cotton with its stretch stiffness scaled (0.1x ... 1000x: soft to nearly inextensible)
bending         cotton with its bending stiffness scaled (0.01x ... 10000x)
timestep        substep dt 1x, 2x, 5x, 10x the default 1/600 s (10, 5, 2, 1 substeps per frame)
fabric          silk, cotton, denim, leather (light to heavy)
pose            arms overhead, deep squat, arms crossed, twisted spine (at/near the joint limits)
shape           each shape parameter at the low and high end of its range (neutral elsewhere)
transition      a large pose change (arms up 1.2 rad, arms overhead) in 1 or 2 frames
==============  ===========================================================================

A cell *passes* when its world did not explode (no NaN, no speed above 50 m/s, no triangle
stretched beyond ``SimSettings.explosion_stretch``, 3x unless given), converged within :data:`MAX_RELAX_FRAMES` frames, its longest edge is at most
:data:`STRETCH_LIMIT` times its rest length, and its deepest vertex is at most
:data:`PENETRATION_LIMIT_MM` inside the body with at most :data:`PENETRATION_FRACTION_LIMIT` of the
vertices deeper than 1 mm (the dataset filter). :data:`SUPPORTED` says which cells the project
supports per scene (the README repeats it); :func:`failing_supported` lists supported cells that failed.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from simulate.cloth import FABRICS, Fabric
from simulate.quasi_static import SimSettings, WorldStatus
from simulate.reports.scenes import Scene, frame_metrics, named_pose, pose_path, run_worlds

__all__ = ["Case", "stability_cases", "run_stability", "supported_cells", "CUDA_EXCEPTIONS", "failing_supported", "unexpected_passes", "plot_heatmap",
           "format_table", "SUPPORTED", "STRETCH_LIMIT", "PENETRATION_LIMIT_MM", "PENETRATION_FRACTION_LIMIT",
           "MAX_RELAX_FRAMES", "DEFAULT_SCENE"]

STRETCH_LIMIT = 1.25
"""Largest accepted edge length ratio at rest [-] (25 % elongation)."""
PENETRATION_LIMIT_MM = 5.0
"""Deepest accepted vertex inside the body [mm]."""
PENETRATION_FRACTION_LIMIT = 0.01
"""Largest accepted share of vertices deeper than 1 mm [-] (the dataset's filter)."""
MAX_RELAX_FRAMES = 300
"""Frames a cell may take to converge at its final pose (5 s of simulated time)."""
PATH_STEP_RAD = 0.1
"""Largest per-joint rotation per path frame [rad] outside the transition family."""

DEFAULT_SCENE = "shawl@anny"
"""Scene of ``drape report stability`` by default (see the README's Reports section for why)."""

_BASE = SimSettings(frame_dt=1.0 / 60.0, substeps=10, iterations=10, xpbd_mode="gauss_seidel", tolerance=0.01, patience=3,
                    max_frames=MAX_RELAX_FRAMES, damping=5.0, explosion_stretch=3.0, outlier_fraction=0.0,
                    limit_cycle_window=0, body_contact_detect_every=1)
"""The cells' settings: a light damping and a tight explosion limit, so that a cell shows the
solver's own stability rather than what strong damping hides; convergence by the fastest particle
alone, and the body queried on every substep."""


@dataclass(frozen=True)
class Case:
    """One cell: what the body does and which material / time step the cloth has.

    Attributes:
        family, value: cell id parts (``cell`` = "family/value").
        fabric: the cloth's Fabric.
        pose: target pose (60,) [rad]; shape: target shape (S,).
        steps: frames of the path from the canonical pose/neutral shape to the target (0 = none).
        substeps: substeps per 1/60 s frame.
    """

    family: str
    value: str
    fabric: Fabric
    pose: tuple
    shape: tuple
    steps: int
    substeps: int = 10

    @property
    def cell(self) -> str:
        return f"{self.family}/{self.value}"


def _scaled(field: str, scale: float) -> Fabric:
    cotton = FABRICS["cotton"]
    fields = {field: getattr(cotton, field) * scale}
    if field == "stretch_stiffness" and cotton.weft_stiffness is not None:  # warp and weft scale together
        fields["weft_stiffness"] = cotton.weft_stiffness * scale
    return dataclasses.replace(cotton, name=f"cotton {field} x{scale:g}", **fields)


def _steps(pose: np.ndarray, start: np.ndarray) -> int:
    from simulate.poses import joint_angle_change

    return int(math.ceil(float(joint_angle_change(start, pose).max()) / PATH_STEP_RAD - 1e-9))


def stability_cases(scene: Scene, size: str) -> list[Case]:
    """The cells for ``size`` "ci" (capsule scene, 4 cells), "small" or "full" (anny scenes)."""
    canon = np.asarray(scene.canonical_pose, np.float32)
    neutral = np.asarray(scene.neutral_shape, np.float32)
    cotton = FABRICS["cotton"]

    def case(family: str, value: str, *, fabric: Fabric = cotton, pose: np.ndarray | None = None,
             shape: np.ndarray | None = None, steps: int | None = None, substeps: int = 10) -> Case:
        p = canon if pose is None else np.asarray(pose, np.float32)
        s = neutral if shape is None else np.asarray(shape, np.float32)
        n = _steps(p, canon) if steps is None else steps
        if shape is not None:
            n = max(n, 10)  # the dataset's shape_transition_frames
        return Case(family, value, fabric, tuple(map(float, p)), tuple(map(float, s)), int(n), int(substeps))

    if size == "ci":
        tilt = named_pose("tilt")
        return [case("stretch", "x1000", fabric=_scaled("stretch_stiffness", 1000.0)),
                case("fabric", "silk", fabric=FABRICS["silk"]),
                case("timestep", "x5", substeps=2),
                case("transition", "tilt-1-frame", pose=tilt, steps=1)]
    if size not in ("small", "full"):
        raise ValueError(f"size must be 'ci', 'small' or 'full' (got {size!r})")
    if scene.body_kind != "anny":
        raise ValueError(f"size {size!r} needs an anny scene (got {scene.name}); use size 'ci' on the capsule")
    full = size == "full"
    stretch = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0) if full else (0.1, 1.0, 100.0, 1000.0)
    bending = (0.01, 0.1, 1.0, 10.0, 100.0, 1000.0, 10000.0) if full else (0.01, 100.0, 10000.0)
    substeps = (10, 5, 3, 2, 1) if full else (10, 5, 2, 1)
    cases = [case("stretch", f"x{k:g}", fabric=_scaled("stretch_stiffness", k)) for k in stretch]
    cases += [case("bending", f"x{k:g}", fabric=_scaled("bending_stiffness", k)) for k in bending]
    arms_up = named_pose("arms-up")
    cases += [case("timestep", f"x{10 / s:g}", pose=arms_up, substeps=s) for s in substeps]
    cases += [case("fabric", name, fabric=FABRICS[name], pose=arms_up) for name in ("silk", "cotton", "denim", "leather")]
    cases += [case("pose", name, pose=named_pose(name)) for name in ("arms-overhead", "deep-squat", "arms-crossed",
                                                                   "twisted-spine")]
    names = list(scene.shape_names) if full else list(scene.shape_names)[:3]
    for i, name in enumerate(names):
        for end, label in ((0, "min"), (1, "max")):
            s = neutral.copy()
            s[i] = scene.shape_ranges[i, end]
            cases.append(case("shape", f"{name}-{label}", shape=s))
    cases += [case("transition", f"arms-up-{n}-frame", pose=arms_up, steps=n) for n in (1, 2)]
    if full:
        cases += [case("transition", f"{p}-1-frame", pose=named_pose(p), steps=1) for p in ("arms-overhead", "twisted-spine")]
    return cases


def run_stability(
    scene: Scene,
    cases: Sequence[Case],
    *,
    device: str = "cpu",
    max_frames: int = MAX_RELAX_FRAMES,
    explosion_stretch: float | None = None,
    on_progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Runs every cell (cells with the same substeps run together as worlds) and judges it.

    ``explosion_stretch`` (None: 3x) is the triangle stretch ratio that marks a
    world EXPLODED.

    Returns:
        {"scene", "device", "criteria", "canonical_drape", "cells": [per-cell dict], "wall_s"};
        each cell: cell, family, value, supported, exploded, finite, converged, status, frames,
        stretch_max, penetration_max_mm, penetration_fraction, passed, reasons (why it failed),
        batch_wall_s / batch_cells (the batch it ran in), ms_per_frame (batch wall / batch frames).
    """
    t_all = time.perf_counter()
    base = _BASE if explosion_stretch is None else dataclasses.replace(_BASE, explosion_stretch=float(explosion_stretch))
    canon_body, _ = scene.body_vertices(scene.neutral_shape[None], scene.canonical_pose[None])
    drape = run_worlds(scene, start=scene.start_vertices, paths=[canon_body], fabrics=["cotton"],
                       settings=dataclasses.replace(base, max_frames=max(max_frames, 600)), device=device)
    drape_status = WorldStatus(int(drape.status[0])).name
    start = drape.positions[0] if np.isfinite(drape.positions).all() else scene.start_vertices
    supported = supported_cells(scene.name, device)
    cells: list[dict[str, Any] | None] = [None] * len(cases)
    for sub in sorted({c.substeps for c in cases}, reverse=True):
        idx = [i for i, c in enumerate(cases) if c.substeps == sub]
        paths, finals = [], []
        for i in idx:
            c = cases[i]
            poses = pose_path(scene.canonical_pose, np.asarray(c.pose, np.float32), steps=c.steps)
            body, _ = scene.path_bodies(np.asarray(c.shape, np.float32), poses, shape_from=scene.neutral_shape)
            paths.append(body)
            finals.append(body[-1])
        run = run_worlds(scene, start=start, paths=paths, fabrics=[cases[i].fabric for i in idx],
                         settings=dataclasses.replace(base, substeps=sub, max_frames=max_frames), device=device)
        metrics = frame_metrics(scene, run.positions, np.stack(finals), device=device)
        for j, i in enumerate(idx):
            c, m = cases[i], metrics[j]
            status = WorldStatus(int(run.status[j]))
            exploded = status == WorldStatus.EXPLODED or not m["finite"]
            reasons = []
            if exploded:
                reasons.append("exploded")
            else:
                if status != WorldStatus.CONVERGED:
                    reasons.append(f"not converged in {max_frames} frames")
                if m["stretch_max"] > STRETCH_LIMIT:
                    reasons.append(f"stretch {m['stretch_max']:.3f} > {STRETCH_LIMIT}")
                if m["penetration_max_mm"] > PENETRATION_LIMIT_MM:
                    reasons.append(f"penetration {m['penetration_max_mm']:.1f} mm > {PENETRATION_LIMIT_MM} mm")
                if m["penetration_fraction"] > PENETRATION_FRACTION_LIMIT:
                    reasons.append(f"{100 * m['penetration_fraction']:.1f} % vertices > 1 mm deep")
            cells[i] = {
                "cell": c.cell, "family": c.family, "value": c.value, "supported": supported.get(c.cell, (False, ""))[0],
                "declared": c.cell in supported, "note": supported.get(c.cell, (False, "not declared"))[1],
                "fabric": c.fabric.name, "substeps": c.substeps, "dt_s": float(run.dt), "path_frames": c.steps,
                "exploded": bool(exploded), "finite": bool(m["finite"]), "converged": status == WorldStatus.CONVERGED,
                "status": status.name, "frames": int(run.frames[j]),
                "stretch_max": m["stretch_max"], "penetration_max_mm": m["penetration_max_mm"],
                "penetration_fraction": m["penetration_fraction"],
                "passed": not reasons, "reasons": reasons,
                "batch_wall_s": run.wall_s, "batch_cells": len(idx),
                "ms_per_frame": 1e3 * run.wall_s / max(int(run.frames.max()), 1),
            }
        if on_progress:
            on_progress(len(idx))
    return {
        "scene": {"name": scene.name, "garment": scene.garment, "body": scene.body_kind, "vertices": scene.vertex_count},
        "device": str(device),
        "criteria": {"stretch_limit": STRETCH_LIMIT, "penetration_limit_mm": PENETRATION_LIMIT_MM,
                     "penetration_fraction_limit": PENETRATION_FRACTION_LIMIT, "max_relax_frames": max_frames,
                     "base_settings": dataclasses.asdict(base)},
        "canonical_drape": {"status": drape_status, "frames": int(drape.frames[0])},
        "cells": cells,
        "wall_s": time.perf_counter() - t_all,
    }


def supported_cells(scene_name: str, device: str) -> dict[str, tuple[bool, str]]:
    """The SUPPORTED table of a scene on a device: on CUDA the :data:`CUDA_EXCEPTIONS` are unsupported."""
    table = dict(SUPPORTED.get(scene_name, {}))
    if str(device).startswith("cuda"):
        for cell, note in CUDA_EXCEPTIONS.get(scene_name, {}).items():
            table[cell] = (False, "on CUDA: " + note)
    return table


def failing_supported(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Cells declared supported that failed."""
    return [c for c in report["cells"] if c["supported"] and not c["passed"]]


def unexpected_passes(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Cells declared unsupported (or not declared) that passed (flaky cells, or a stale SUPPORTED entry)."""
    return [c for c in report["cells"] if not c["supported"] and c["passed"]]


def format_table(report: dict[str, Any]) -> str:
    """Plain-text table: one line per cell."""
    head = (f"{'cell':<28}{'sup':>4}{'pass':>6}{'status':>11}{'frames':>7}{'stretch':>9}{'pen mm':>8}{'pen %':>7}"
            f"{'ms/fr':>8}  why")
    lines = [head, "-" * (len(head) + 10)]
    for c in report["cells"]:
        lines.append(f"{c['cell']:<28}{'yes' if c['supported'] else 'no':>4}{'ok' if c['passed'] else 'FAIL':>6}"
                     f"{c['status']:>11}{c['frames']:>7}{c['stretch_max']:>9.3f}{c['penetration_max_mm']:>8.2f}"
                     f"{100 * c['penetration_fraction']:>7.2f}{c['ms_per_frame']:>8.1f}  {'; '.join(c['reasons'])}")
    return "\n".join(lines)


def plot_heatmap(report: dict[str, Any], out_png: str | Path) -> Path:
    """Heat map: rows = cells (family/value), columns = explosion, convergence, stretch, penetration,
    pass; each square green (within its limit) or red, annotated with the measured value; rows of
    unsupported cells are labelled "(unsupported)"."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cells = report["cells"]
    cols = ["exploded", "converged", "stretch max", "penetration [mm]", "pen > 1 mm [%]", "passed"]
    ok = np.zeros((len(cells), len(cols)))
    text = []
    for r, c in enumerate(cells):
        vals = [not c["exploded"], c["converged"], c["stretch_max"] <= STRETCH_LIMIT,
                c["penetration_max_mm"] <= PENETRATION_LIMIT_MM, c["penetration_fraction"] <= PENETRATION_FRACTION_LIMIT,
                c["passed"]]
        ok[r] = [1.0 if v else 0.0 for v in vals]
        text.append(["yes" if c["exploded"] else "no", f"{c['frames']}" if c["converged"] else c["status"].lower(),
                     f"{c['stretch_max']:.3f}", f"{c['penetration_max_mm']:.1f}", f"{100 * c['penetration_fraction']:.1f}",
                     "pass" if c["passed"] else "FAIL"])
    fig, ax = plt.subplots(figsize=(9.0, 0.28 * len(cells) + 1.6), dpi=110)
    ax.imshow(ok, cmap=ListedColormap(["#e06666", "#93c47d"]), vmin=0, vmax=1, aspect="auto")
    for r in range(len(cells)):
        for k in range(len(cols)):
            ax.text(k, r, text[r][k], ha="center", va="center", fontsize=6.5)
    ax.set_xticks(range(len(cols)), cols, fontsize=7.5)
    ax.set_yticks(range(len(cells)), [c["cell"] + ("" if c["supported"] else "  (unsupported)") for c in cells],
                  fontsize=7)
    ax.xaxis.tick_top()
    ax.set_title(f"stability matrix: {report['scene']['name']} on {report['device']}", fontsize=9, pad=24)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


# Declared support per scene: cell -> (supported, why / note). Filled from measured runs (see the
# README's Reports section); a cell that is not listed counts as unsupported.
_OK = (True, "")
_FLAKY = "passes or fails depending on the run (world index in the batch changes float rounding and the " \
         "frictional sliding amplifies it): "
SUPPORTED: dict[str, dict[str, tuple[bool, str]]] = {
    # Measured on CPU (2 cores), shawl of 282 vertices, small and full matrices (see the README).
    "shawl@anny": {
        **{f"stretch/x{k:g}": _OK for k in (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)},
        **{f"bending/x{k:g}": _OK for k in (0.01, 0.1, 1.0, 10.0, 100.0, 1000.0, 10000.0)},
        "timestep/x1": _OK, "timestep/x2": _OK, "timestep/x3.33333": _OK,
        "timestep/x5": (True, "marginal: max edge ratio 1.24 against the 1.25 limit (2 substeps per frame)"),
        "timestep/x10": (False, "1 substep per 1/60 s frame: 10 Gauss-Seidel iterations leave cotton stretched "
                                "1.86-1.97x where the shawl hangs over the arms; use >= 2 substeps per frame"),
        **{f"fabric/{n}": _OK for n in ("silk", "cotton", "denim", "leather")},
        "pose/arms-overhead": (False, _FLAKY + "the shawl keeps sliding on the raised shoulders, converged after 121 "
                                               "frames in one run and still moving after 300 in another"),
        **{f"pose/{n}": _OK for n in ("deep-squat", "arms-crossed", "twisted-spine")},
        **{f"shape/{n}-{e}": _OK for n in ("gender", "muscle", "weight", "proportions") for e in ("min", "max")},
        "shape/age-min": (False, "the body shrinks to anny's youngest (child) end in 10 frames: the adult-sized cloth "
                                 "slides off the shoulders (no convergence in 300 frames; in one run trapped inside "
                                 "the arms, 73 mm deep); cloth must be generated for the target shape"),
        "shape/age-max": (True, "stretch 1.11-1.22 of the 1.25 limit"),
        "shape/height-min": _OK,
        "shape/height-max": (False, "tallest body: the cloth is held 1.32x stretched over the shoulders at rest"),
        "transition/arms-up-1-frame": (True, "1.2 rad in one frame: passed both measured runs"),
        "transition/arms-up-2-frame": (False, _FLAKY + "the shawl edge is caught under the rising arm (1.39x "
                                                       "stretched at rest in one run, 1.05x in another)"),
        "transition/arms-overhead-1-frame": (False, "1.9 rad in one frame: the arm sweeps through the cloth (2.3x "
                                                    "stretch, 16 mm deep, still moving after 300 frames); keep the "
                                                    "dataset's 0.1 rad/frame interpolation"),
        "transition/twisted-spine-1-frame": (False, "0.3 rad per spine joint in one frame: the shawl is still sliding "
                                                    "after 300 frames"),
    },
    "towel@capsule": {
        "stretch/x1000": (True, ""),
        "fabric/silk": (True, ""),
        "timestep/x5": (True, ""),
        "transition/tilt-1-frame": (True, ""),
    },
}

_MARGINAL = "marginal: the shawl's longest edge sits at 1.247x in the canonical drape, so the 1.25 bound " \
            "decides on one edge; "
CUDA_EXCEPTIONS: dict[str, dict[str, str]] = {
    # Cells supported on CPU that fail on an H200 (small and full matrix): float rounding differs
    # from the CPU's and frictional sliding amplifies it.
    "shawl@anny": {
        "bending/x10": _MARGINAL + "1.255 (full matrix)",
        "bending/x1000": _MARGINAL + "1.261 (full matrix)",
        "bending/x10000": "the stiffest bending holds the shawl 1.50x stretched over the arms (both GPU runs)",
        "timestep/x5": "2 substeps per frame: still sliding after 300 frames, 1.36x stretched (both GPU runs)",
        "fabric/denim": _MARGINAL + "1.27 (both GPU runs)",
        "fabric/leather": _MARGINAL + "1.28 (both GPU runs)",
        "pose/twisted-spine": _MARGINAL + "1.28 (both GPU runs)",
        "shape/gender-min": _MARGINAL + "1.28 (both GPU runs)",
        "shape/age-max": _MARGINAL + "1.28 (small matrix), 1.234 (full matrix)",
    },
}
"""Cells of :data:`SUPPORTED` that are not supported on CUDA devices, with the measured reason."""
