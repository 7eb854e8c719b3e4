"""Error against run time of the simulator's settings (``drape report accuracy``).

Protocol: the scene's cloth is draped once on the canonical body with the reference settings
(the *canonical drape*). For each report pose the body then moves from the canonical pose to the
pose along a slerp path of one frame per 0.1 rad of the largest joint change (the dataset
pipeline's interpolation threshold) and the cloth relaxes until it converges; all poses run
together as worlds of one simulator. Every setting runs the same protocol; the *reference* runs
it with a very tight tolerance and many iterations. Per setting:

* ``ms_per_frame``: wall time [ms] of the whole protocol (path frames + relaxation, device
  synchronized, kernels compiled beforehand) divided by the number of poses: the cost of one
  converged frame as a dataset pays it;
* ``error_max_mm`` / ``error_mean_mm``: max and mean vertex distance to the reference [mm]
  over all poses (``error_mm`` = ``error_max_mm`` is the value on the Pareto plot);
* stretch (max / mean edge length ratio), penetration (deepest vertex [mm], share of vertices
  deeper than 1 mm: :class:`simulate.quality.QualityMeter`), converged share, frames.

Float precision: a ``float16`` row is the same simulation with positions rounded to float16
relative to the pelvis (the dataset's PC16 storage), so its error adds the rounding error.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from simulate.cloth.quasi_static import SimSettings, WorldStatus
from simulate.reports.pareto import NEAR_FRONT_ERROR_SLACK, NEAR_FRONT_TIME_FACTOR, front_time_at_error, pareto_front
from simulate.reports.scenes import Scene, SceneRun, frame_metrics, named_pose, pose_path, round_float16, run_worlds

__all__ = ["Setting", "DEFAULT_SETTING", "PRODUCTION_BASE", "REFERENCE_SETTINGS", "SWEEPS", "sweep_settings", "run_accuracy",
           "Resume", "summarize", "format_table", "PATH_STEP_RAD"]

PATH_STEP_RAD = 0.1
"""Largest per-joint rotation between consecutive frames of a pose path [rad] (the dataset's
``simulation.interpolation_threshold`` default)."""

_MODE_SHORT = {"gauss_seidel": "gs", "jacobi": "jac"}


@dataclass(frozen=True)
class Setting:
    """One simulator setting of the sweep.

    Attributes:
        solver: "xpbd" or "mass_spring".
        mode: XPBD sweep, "gauss_seidel" or "jacobi" (ignored by mass-spring).
        substeps: substeps per 1/60 s frame; None = the solver's choice (mass-spring: stable step).
        iterations: XPBD iterations per substep (ignored by mass-spring).
        tolerance: convergence tolerance, max particle speed [m/s].
        precision: "float32" or "float16" (storage rounding relative to the pelvis).
    """

    solver: str = "xpbd"
    mode: str = "gauss_seidel"
    substeps: int | None = 10
    iterations: int = 10
    tolerance: float = 0.01
    precision: str = "float32"

    def __post_init__(self) -> None:
        if self.solver not in ("xpbd", "mass_spring"):
            raise ValueError(f"Setting.solver must be 'xpbd' or 'mass_spring' (got {self.solver!r})")
        if self.mode not in _MODE_SHORT:
            raise ValueError(f"Setting.mode must be 'gauss_seidel' or 'jacobi' (got {self.mode!r})")
        if self.precision not in ("float32", "float16"):
            raise ValueError(f"Setting.precision must be 'float32' or 'float16' (got {self.precision!r})")

    @property
    def group(self) -> str:
        """Solver family for plot colours: "xpbd-gs", "xpbd-jac" or "mass-spring"."""
        return "mass-spring" if self.solver == "mass_spring" else f"xpbd-{_MODE_SHORT[self.mode]}"

    @property
    def label(self) -> str:
        """Short unique name, e.g. "xpbd-gs s10 i10 tol0.01 f32"."""
        sub = "auto" if self.substeps is None else str(self.substeps)
        its = "" if self.solver == "mass_spring" else f" i{self.iterations}"
        return f"{self.group} s{sub}{its} tol{self.tolerance:g} {'f16' if self.precision == 'float16' else 'f32'}"

    def sim_settings(self, *, max_frames: int, base: SimSettings | None = None,
                     explosion_stretch: float | None = None) -> SimSettings:
        """SimSettings of this setting: ``base`` (default :data:`PRODUCTION_BASE`) with this setting's swept
        fields; ``explosion_stretch`` overrides the base's when given."""
        extra = {} if explosion_stretch is None else {"explosion_stretch": float(explosion_stretch)}
        return dataclasses.replace(PRODUCTION_BASE if base is None else base, substeps=self.substeps,
                                   iterations=self.iterations, xpbd_mode=self.mode, tolerance=self.tolerance,
                                   max_frames=int(max_frames), **extra)

    def simulation_key(self) -> tuple:
        """Settings that change the simulation (precision does not)."""
        return (self.solver, self.mode if self.solver == "xpbd" else "-", self.substeps,
                self.iterations if self.solver == "xpbd" else 0, self.tolerance)


DEFAULT_SETTING = Setting("xpbd", "gauss_seidel", 15, 5, 0.05, "float32")
"""The production default (pipelines/configs/tailornet-tshirt.yaml ``simulation`` block)."""

PRODUCTION_BASE = SimSettings(frame_dt=0.0222222, damping=20.0, explosion_stretch=50.0, outlier_fraction=0.02, patience=3)
"""The production spec's settings that the sweep does not vary (tailornet-tshirt.yaml with the spec
defaults: frames of 1/45 s, velocity damping 20/s, explosion at 50x triangle stretch, 2 % outlier
vertices, 3 calm frames); every setting, the reference included, runs on top of these, so the report measures the
solver the datasets are made with. (The simulator's own defaults flag a transient 3x stretch where
the cloth first meets the body as an explosion: on the 1.8k-vertex t-shirt 3 of the 4 report poses
"exploded" within 11 frames that way, and all 4 converge without penetration when it is not.)"""

REFERENCE_SETTINGS: dict[str, Setting] = {
    "ci": Setting("xpbd", "gauss_seidel", 4, 32, 1e-3),
    "small": Setting("xpbd", "gauss_seidel", 20, 50, 1e-4),
    "full": Setting("xpbd", "gauss_seidel", 40, 100, 1e-4),
}
"""Reference solve per sweep size: Gauss-Seidel XPBD, many substeps and iterations, a tolerance
100x or more below the default's, with the base's outlier share (with none, the 1.8k-vertex t-shirt
never came to rest at 1e-4 m/s: all 4 poses ran 400 frames on CPU, the armpit vertices jitter at
that level; those positions differ from the production default's by 5-8 mm mean, 16-38 mm max)."""


def sweep_settings(size: str, *, default: Setting = DEFAULT_SETTING) -> list[Setting]:
    """The settings of a sweep size ("small" or "full"), the default first, no duplicates."""
    gs, jac = "gauss_seidel", "jacobi"
    if size == "small":
        grid = [Setting("xpbd", gs, s, i, 0.01) for s, i in ((5, 5), (5, 10), (10, 5), (20, 10), (10, 20), (20, 20))]
        grid += [Setting("xpbd", gs, 10, 10, t) for t in (0.05, 0.01, 0.002)]
        grid += [Setting("xpbd", jac, 10, i, 0.01) for i in (10, 20)]
        grid += [Setting("mass_spring", gs, None, 1, 0.01)]
        grid += [dataclasses.replace(default, precision="float16")]
    elif size == "full":
        grid = [Setting("xpbd", gs, s, i, 0.01) for s in (5, 10, 20, 40) for i in (5, 10, 20, 40)]
        grid += [Setting("xpbd", gs, s, i, t) for s, i in ((10, 10), (20, 20)) for t in (0.05, 0.02, 0.005, 0.002, 0.001)]
        grid += [Setting("xpbd", jac, s, i, 0.01) for s in (10, 20) for i in (10, 20, 40)]
        grid += [Setting("mass_spring", gs, None, 1, t) for t in (0.01, 0.002)]
        grid += [dataclasses.replace(g, precision="float16") for g in list(grid) if g.group == "xpbd-gs"]
    else:
        raise ValueError(f"sweep must be 'small' or 'full' (got {size!r})")
    out: list[Setting] = [default]
    for g in grid:
        if g not in out:
            out.append(g)
    return out


SWEEPS = ("small", "full")


@dataclass
class Resume:
    """What an earlier run of the same sweep measured before it was cut short
    (``drape report accuracy --resume``): its reference and its finished rows.

    Attributes:
        reference: the reference summary (``report["reference"]``).
        reference_positions: the reference's final cloth positions of every requested pose [m], (W, V, 3).
        reference_status: its per-pose :class:`WorldStatus` values, (W,).
        rows: finished rows by setting label.
    """

    reference: dict[str, Any]
    reference_positions: np.ndarray
    reference_status: np.ndarray
    rows: dict[str, dict[str, Any]]


def summarize(rows: Sequence[dict[str, Any]], default_label: str) -> dict[str, Any]:
    """Pareto bookkeeping of a list of rows, for the max error (``error_mm``) and for the mean error:
    {"front", "default_on_front", "default_time_ratio", "default_near_front", "front_mean",
    "default_on_front_mean", "default_time_ratio_mean", "default_near_front_mean",
    "near_front_time_factor", "near_front_error_slack"}.

    ``default_time_ratio``: the default's time over the time of the fastest front setting whose error
    is at most the default's (plus :data:`NEAR_FRONT_ERROR_SLACK`); "near" means at most
    :data:`NEAR_FRONT_TIME_FACTOR`. The max error is one vertex of one pose (on the 1.8k t-shirt it is
    not monotone in the iteration count: 36.6 mm at s5 i20, 72.3 mm at s5 i40 on an H200), so the
    mean error's front is reported beside it."""
    labels = [r["label"] for r in rows]
    if default_label not in labels:
        raise ValueError(f"the default setting {default_label!r} has no row")
    d = rows[labels.index(default_label)]
    out: dict[str, Any] = {}
    for suffix, key in (("", "error_mm"), ("_mean", "error_mean_mm")):
        front = pareto_front(rows, error_key=key)
        t_front = front_time_at_error(rows, d[key] * (1.0 + NEAR_FRONT_ERROR_SLACK), error_key=key)
        ratio = d["ms_per_frame"] / t_front if math.isfinite(t_front) and t_front > 0 else float("inf")
        out.update({f"front{suffix}": [labels[i] for i in front],
                    f"default_on_front{suffix}": labels.index(default_label) in front,
                    f"default_time_ratio{suffix}": ratio,
                    f"default_near_front{suffix}": bool(ratio <= NEAR_FRONT_TIME_FACTOR)})
    out.update(near_front_time_factor=NEAR_FRONT_TIME_FACTOR, near_front_error_slack=NEAR_FRONT_ERROR_SLACK)
    return out


def _path_steps(pose: np.ndarray, canonical: np.ndarray) -> int:
    from simulate.poses import joint_angle_change

    return int(math.ceil(float(joint_angle_change(canonical, pose).max()) / PATH_STEP_RAD - 1e-9))


def run_accuracy(
    scene: Scene,
    *,
    poses: Sequence[str],
    settings: Sequence[Setting],
    reference: Setting,
    default: Setting = DEFAULT_SETTING,
    device: str = "cpu",
    fabric: str = "cotton",
    max_frames: int = 600,
    reference_max_frames: int = 3000,
    drape_setting: Setting | None = None,
    base: SimSettings | None = None,
    explosion_stretch: float | None = None,
    on_progress: Callable[[str, Any], None] | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
    on_reference: Callable[[dict[str, Any], np.ndarray, np.ndarray], None] | None = None,
    resume: Resume | None = None,
) -> dict[str, Any]:
    """Runs the accuracy protocol (module docstring) and returns the report as a JSON-ready dict.

    Args:
        scene: report scene.
        poses: pose names (``simulate.reports.scenes.ACCURACY_POSES`` or ``EXTREME_POSES``); one world each.
        settings: the sweep (precision variants share one simulation).
        reference: the tight reference setting.
        default: the production default (must be among ``settings``).
        max_frames: relaxation frame budget per setting; reference_max_frames: the reference's.
        drape_setting: setting of the canonical drape, the common start of all runs (default: ``default``;
            every run, the reference included, then relaxes each pose with its own setting).
        base: the settings not swept (damping, explosion limits, outlier share, patience), default
            :data:`PRODUCTION_BASE`.
        explosion_stretch: triangle stretch ratio that marks a world EXPLODED, for every run (None: the base's).
        on_progress: called with a setting label and its :class:`~simulate.reports.scenes.SceneRun` after each
            simulation (progress bars, per-setting log lines).
        on_row: called with the reference's summary and then with each finished row, as soon as it is
            measured (the CLI appends them to a JSON-lines file, so a sweep cut short keeps its rows).
            Settings that share a simulation (precision variants) are measured one after the other.
        on_reference: called with the reference's summary, final positions (W, V, 3) and statuses (W,)
            once it is solved (the CLI saves them, so ``--resume`` can skip it).
        resume: an earlier run's reference and rows: the reference is not solved again and settings
            whose rows are all there are not simulated again (neither is passed to ``on_row``).
    Returns:
        {"scene", "device", "poses", "poses_dropped" (reference exploded), "reference", "rows", "default",
        "resumed_rows", and :func:`summarize`'s fronts and ratios} (see the module docstring for row fields).
    """
    if not poses:
        raise ValueError("poses must name at least one pose")
    if default not in settings:
        raise ValueError(f"the default setting {default.label!r} must be part of the sweep")
    canonical = scene.canonical_pose
    pose_vecs = [named_pose(p) for p in poses]
    shape = scene.neutral_shape
    paths, roots, finals = [], [], []
    for vec in pose_vecs:
        body, root = scene.path_bodies(shape, pose_path(canonical, vec, steps=_path_steps(vec, canonical)))
        paths.append(body)
        roots.append(root[-1])
        finals.append(body[-1])
    finals_arr = np.stack(finals)
    roots_arr = np.stack(roots)
    canon_body, _ = scene.body_vertices(shape[None], canonical[None])
    w = len(poses)

    def simulate(s: Setting, frames: int, start: np.ndarray, use_paths: list[np.ndarray]):
        return run_worlds(scene, start=start, paths=use_paths, fabrics=[fabric] * len(use_paths),
                          settings=s.sim_settings(max_frames=frames, base=base, explosion_stretch=explosion_stretch),
                          solver=s.solver, device=device)

    # Compile and load every kernel variant before anything is timed.
    for key in sorted({(s.solver, s.mode) for s in [*settings, reference]}):
        simulate(Setting(key[0], key[1], 1, 1, 0.01), 1, scene.start_vertices, [canon_body])
    drape_setting = default if drape_setting is None else drape_setting
    drape = simulate(drape_setting, reference_max_frames, scene.start_vertices, [canon_body])
    if drape.status[0] == WorldStatus.EXPLODED or not np.isfinite(drape.positions).all():
        raise ValueError(f"the canonical drape of {scene.name} exploded ({drape_setting.label}, after "
                         f"{int(drape.frames[0])} frames); this scene cannot serve as an accuracy reference")
    start = drape.positions[0]
    if on_progress:
        on_progress("canonical drape", drape)
    if resume is None:
        ref = simulate(reference, reference_max_frames, start, paths)
        if on_progress:
            on_progress(reference.label + " (reference)", ref)
    else:
        if resume.reference_positions.shape != (w, scene.vertex_count, 3) or len(resume.reference_status) != w:
            raise ValueError(f"resume: the saved reference has positions {resume.reference_positions.shape} and "
                             f"{len(resume.reference_status)} statuses; expected ({w}, {scene.vertex_count}, 3) and {w}")
        # only positions and status are read from a resumed reference (its summary comes saved)
        ref = SceneRun(positions=np.asarray(resume.reference_positions, np.float32),
                       status=np.asarray(resume.reference_status), frames=np.zeros(w, np.int64), wall_s=0.0,
                       substeps=0, dt=0.0)
    ref_all_positions, ref_all_status = ref.positions, ref.status
    # A pose whose reference exploded has no reference: drop it (worlds are independent, so the
    # other worlds' reference results stand) and say so in the report.
    keep = (ref.status != WorldStatus.EXPLODED) & np.isfinite(ref.positions).all(axis=(1, 2))
    dropped = [p for p, k in zip(poses, keep) if not k]
    if not keep.any():
        raise ValueError(f"the reference ({reference.label}) exploded in every pose ({', '.join(poses)}) of {scene.name}")
    if dropped:
        idx = np.nonzero(keep)[0]
        poses = [poses[i] for i in idx]
        paths = [paths[i] for i in idx]
        finals_arr, roots_arr = finals_arr[idx], roots_arr[idx]
        ref = dataclasses.replace(ref, positions=ref.positions[idx], status=ref.status[idx], frames=ref.frames[idx])
        w = len(poses)
    if resume is None:
        ref_metrics = frame_metrics(scene, ref.positions, finals_arr, device=device)
        reference_out = {
            "setting": dataclasses.asdict(reference), "label": reference.label, "wall_s": ref.wall_s,
            "ms_per_frame": 1e3 * ref.wall_s / w, "status": [WorldStatus(int(s)).name for s in ref.status],
            "frames": ref.frames.tolist(), "stretch_max": max(m["stretch_max"] for m in ref_metrics),
            "penetration_max_mm": max(m["penetration_max_mm"] for m in ref_metrics),
            "canonical_drape_setting": drape_setting.label,
            "canonical_drape_status": WorldStatus(int(drape.status[0])).name, "canonical_drape_frames": int(drape.frames[0]),
        }
        if on_row:
            on_row({"reference": reference_out})
        if on_reference:
            on_reference(reference_out, ref_all_positions, ref_all_status)
    else:
        reference_out = resume.reference
    done = dict(resume.rows) if resume is not None else {}
    # Simulations in the order their first setting appears; the settings sharing one (precision
    # variants) are measured right after it, so a sweep cut short loses no row it has paid for.
    by_key: dict[tuple, list[int]] = {}
    for i, s in enumerate(settings):
        by_key.setdefault(s.simulation_key(), []).append(i)
    rows_at: dict[int, dict[str, Any]] = {}
    resumed = 0
    for key, idxs in by_key.items():
        missing = [i for i in idxs if settings[i].label not in done]
        for i in idxs:
            if i not in missing:
                rows_at[i] = done[settings[i].label]
                resumed += 1
        if not missing:
            continue
        run = simulate(settings[missing[0]], max_frames, start, paths)
        if on_progress:
            on_progress(settings[missing[0]].label, run)
        for i in missing:
            rows_at[i] = _measure_row(scene, settings[i], run, ref.positions, finals_arr, roots_arr, w, device)
            if on_row:
                on_row(rows_at[i])
    rows = [rows_at[i] for i in range(len(settings))]
    return {
        "scene": {"name": scene.name, "garment": scene.garment, "body": scene.body_kind,
                  "vertices": scene.vertex_count, "faces": int(len(scene.faces)), "fabric": fabric},
        "device": str(device),
        "base_settings": dataclasses.asdict(default.sim_settings(max_frames=max_frames, base=base,
                                                                  explosion_stretch=explosion_stretch)),
        "poses": [{"name": p, "path_frames": int(len(b) - 1)} for p, b in zip(poses, paths)],
        "poses_dropped": dropped,
        "reference": reference_out,
        "rows": rows,
        "default": default.label,
        **summarize(rows, default.label),
        "resumed_rows": resumed,
    }


def _measure_row(scene: Scene, s: Setting, run: Any, ref_positions: np.ndarray, finals: np.ndarray, roots: np.ndarray,
                 w: int, device: str) -> dict[str, Any]:
    """One report row: a setting's simulation (float16 variants rounded) against the reference."""
    x = run.positions if s.precision == "float32" else round_float16(run.positions, roots)
    metrics = frame_metrics(scene, x, finals, device=device)
    finite = np.isfinite(x).all(axis=(1, 2))
    exploded = (run.status == WorldStatus.EXPLODED) | ~finite
    dist_mm = 1e3 * np.linalg.norm(x - ref_positions, axis=-1)  # (W, V)
    failed = bool(exploded.any())
    return {
        "label": s.label, "group": s.group, **dataclasses.asdict(s),
        "ms_per_frame": 1e3 * run.wall_s / w,
        "error_max_mm": float("inf") if failed else float(dist_mm.max()),
        "error_mean_mm": float("inf") if failed else float(dist_mm.mean()),
        "error_mm": float("inf") if failed else float(dist_mm.max()),
        "error_max_mm_per_pose": [float(d.max()) if f else float("inf") for d, f in zip(dist_mm, ~exploded)],
        "stretch_max": float(np.nanmax([m["stretch_max"] for m in metrics])) if not failed else float("nan"),
        "stretch_mean": float(np.nanmean([m["stretch_mean"] for m in metrics])) if not failed else float("nan"),
        "penetration_max_mm": float(max(m["penetration_max_mm"] for m in metrics)) if not failed else float("nan"),
        "penetration_fraction": float(np.mean([m["penetration_fraction"] for m in metrics])) if not failed else float("nan"),
        "converged": float(np.mean(run.status == WorldStatus.CONVERGED)),
        "exploded": int(exploded.sum()),
        "frames_mean": float(run.frames.mean()),
        "substeps_used": int(run.substeps),
    }


def format_table(report: dict[str, Any]) -> str:
    """Plain-text table of the report rows (front points marked '*', the default '<')."""
    front = set(report["front"])
    front_mean = set(report.get("front_mean", ()))
    head = (f"{'setting':<34}{'ms/frame':>10}{'err max':>9}{'err mean':>9}{'stretch':>9}{'pen mm':>8}"
            f"{'conv':>6}{'frames':>8}")
    lines = [head, f"{'':<34}{'[ms]':>10}{'[mm]':>9}{'[mm]':>9}{'max':>9}{'max':>8}{'[%]':>6}{'mean':>8}", "-" * len(head)]
    for r in report["rows"]:
        mark = (("*" if r["label"] in front else " ") + ("+" if r["label"] in front_mean else " ")
                + ("<" if r["label"] == report["default"] else " "))
        lines.append(f"{mark}{r['label']:<31}{r['ms_per_frame']:>10.1f}{r['error_max_mm']:>9.2f}{r['error_mean_mm']:>9.3f}"
                     f"{r['stretch_max']:>9.4f}{r['penetration_max_mm']:>8.2f}{100 * r['converged']:>6.0f}"
                     f"{r['frames_mean']:>8.1f}")
    ref = report["reference"]
    lines.append(f"reference {ref['label']}: {ref['ms_per_frame']:.1f} ms/frame, status {', '.join(ref['status'])}")
    lines.append("* = on the Pareto front of max error vs time, + = on the mean error's, < = production default")
    return "\n".join(lines)
