"""Error against run time of the simulator's settings (``drape report accuracy``).

Protocol: the scene's cloth is draped once on the canonical body (the *canonical drape*, with
``drape_setting``). For each report pose the body then moves from the canonical pose to the pose
along a slerp path of one frame per 0.1 rad of the largest joint change (the dataset pipeline's
interpolation threshold) and the cloth relaxes until it converges; all poses run together as worlds
of one simulator. Every setting runs the same protocol.

The *reference* of a pose is the static equilibrium of the model's own energy on the pose's body
(:func:`simulate.solvers.reference.solve_equilibrium`: Newton in float64 on the CPU, converged to a
force residual of 1e-6 of the lightest particle's weight, at least 1e-8 N), started from the pose's
result of the tightest XPBD run (``reference``: many substeps and iterations, a tolerance 100x below
the default's) with ``friction="stick"``: the particles touching the body there stay where they touch
it (they may only move along its normal) and everything else settles. So every setting is measured
against the exact rest state of the energy it integrates, for the contact state the tight run arrived
at, and not against another iterative solve that stops at a speed threshold. Friction makes rest
states a continuum (cloth on a tilted bar can rest anywhere it stops sliding): a setting whose
contacts come to rest elsewhere than the tight run's is measured by that distance too (on the CI
capsule's "tilt" pose, 50 vertices, the VBD rows rest 7 mm from the reference started by the "small"
XPBD setting and 74 mm from the one started by the "ci" setting; the XPBD rows within 8 mm of both).

The report's ``reference`` block gives each pose's residual [N] against its tolerance, the Newton
iterations, the share of held particles whose grip exceeds Coulomb friction, and how far the tight
XPBD start was from the equilibrium; ``reference_strip_error`` is the same solver's relative error on
a hanging strip with an analytic answer (:func:`strip_error`), the accuracy the reference itself is
known to have.

Per setting:

* ``ms_per_frame``: wall time [ms] of the whole protocol (path frames + relaxation, device
  synchronized, kernels compiled beforehand) divided by the number of poses: the cost of one
  converged frame as a dataset pays it;
* ``error_max_mm`` / ``error_mean_mm``: max and mean vertex distance to the reference equilibrium
  [mm] over all poses (``error_mm`` = ``error_max_mm`` is the value on the Pareto plot);
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

from simulate.quasi_static import SimSettings, WorldStatus
from simulate.reports.pareto import NEAR_FRONT_ERROR_SLACK, NEAR_FRONT_TIME_FACTOR, front_time_at_error, pareto_front
from simulate.reports.scenes import Scene, SceneRun, frame_metrics, named_pose, pose_path, round_float16, run_worlds

__all__ = ["Setting", "DEFAULT_SETTING", "PRODUCTION_BASE", "REFERENCE_SETTINGS", "SWEEPS", "SOLVERS", "sweep_settings",
           "run_accuracy", "Resume", "summarize", "format_table", "strip_error", "PATH_STEP_RAD", "CONTACT_THICKNESS",
           "REFERENCE_FRICTION", "STRIP_ROWS"]

PATH_STEP_RAD = 0.1
"""Largest per-joint rotation between consecutive frames of a pose path [rad] (the dataset's
``simulation.interpolation_threshold`` default)."""

CONTACT_THICKNESS = 0.004
"""Collider thickness of every run and of the reference equilibrium [m] (the production
``SequenceSettings.contact_thickness``)."""
REFERENCE_FRICTION = "stick"
"""Contact model of the reference equilibrium (see the module docstring)."""
STRIP_ROWS = 80
"""Rows of the hanging strip of :func:`strip_error` (1.25 cm edges on a 1 m strip: the production edge length)."""
SOLVERS = ("xpbd", "vbd", "mass_spring")
"""Solvers a :class:`Setting` can name."""

_MODE_SHORT = {"gauss_seidel": "gs", "jacobi": "jac"}


@dataclass(frozen=True)
class Setting:
    """One simulator setting of the sweep.

    Attributes:
        solver: "xpbd", "vbd" or "mass_spring".
        mode: XPBD sweep, "gauss_seidel" or "jacobi" (ignored by VBD and mass-spring).
        substeps: substeps per frame (1/45 s in :data:`PRODUCTION_BASE`); None = the solver's choice
            (mass-spring: its stable step; not allowed for VBD, which needs >= 15 per 1/45 s frame
            to gain no energy).
        iterations: XPBD iterations or VBD sweeps per substep (ignored by mass-spring).
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
        if self.solver not in SOLVERS:
            raise ValueError(f"Setting.solver must be one of {', '.join(SOLVERS)} (got {self.solver!r})")
        if self.solver == "vbd" and self.substeps is None:
            raise ValueError("Setting.substeps must be a number for solver 'vbd' (it has no stable-step choice)")
        if self.mode not in _MODE_SHORT:
            raise ValueError(f"Setting.mode must be 'gauss_seidel' or 'jacobi' (got {self.mode!r})")
        if self.precision not in ("float32", "float16"):
            raise ValueError(f"Setting.precision must be 'float32' or 'float16' (got {self.precision!r})")

    @property
    def group(self) -> str:
        """Solver family for plot colours: "xpbd-gs", "xpbd-jac", "vbd" or "mass-spring"."""
        if self.solver == "xpbd":
            return f"xpbd-{_MODE_SHORT[self.mode]}"
        return "mass-spring" if self.solver == "mass_spring" else self.solver

    @property
    def label(self) -> str:
        """Short unique name, e.g. "xpbd-gs s10 i10 tol0.01 f32", "vbd s20 i3 tol0.01 f32"."""
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
                0 if self.solver == "mass_spring" else self.iterations, self.tolerance)


DEFAULT_SETTING = Setting("xpbd", "gauss_seidel", 15, 5, 0.05, "float32")
"""The production default: the library's stepping, which pipelines/configs/tailornet-tshirt.yaml runs with."""

PRODUCTION_BASE = SimSettings()
"""The settings the sweep does not vary: the library's defaults, which are the production settings
(frames of 1/45 s, velocity damping 20/s, explosion at 50x triangle stretch, 2 % outlier vertices,
3 calm frames, ...); every setting, the reference included, runs on top of these, so the report
measures the solver the datasets are made with. (A 3x stretch limit flags the transient stretch where
the cloth first meets the body as an explosion: on the 1.8k-vertex t-shirt 3 of the 4 report poses
"exploded" within 11 frames that way, and all 4 converge without penetration when it is not.)"""

REFERENCE_SETTINGS: dict[str, Setting] = {
    "ci": Setting("xpbd", "gauss_seidel", 4, 32, 1e-3),
    "small": Setting("xpbd", "gauss_seidel", 20, 50, 1e-4),
    "full": Setting("xpbd", "gauss_seidel", 40, 100, 1e-4),
}
"""Start of the reference per sweep size: Gauss-Seidel XPBD with many substeps and iterations and a
tolerance 100x or more below the default's (with the base's outlier share; with none, the 1.8k-vertex
t-shirt never came to rest at 1e-4 m/s on CPU, its armpit vertices jitter at that level). Its
result fixes each pose's contact state; the reference is the equilibrium Newton finds from there."""


def sweep_settings(size: str, *, default: Setting = DEFAULT_SETTING) -> list[Setting]:
    """The settings of a sweep size ("small" or "full"), the default first, no duplicates: XPBD
    (Gauss-Seidel and Jacobi), VBD (>= 15 substeps per 1/45 s frame) and mass-spring rows."""
    gs, jac = "gauss_seidel", "jacobi"
    if size == "small":
        grid = [Setting("xpbd", gs, s, i, 0.01) for s, i in ((5, 5), (5, 10), (10, 5), (20, 10), (10, 20), (20, 20))]
        grid += [Setting("xpbd", gs, 10, 10, t) for t in (0.05, 0.01, 0.002)]
        grid += [Setting("xpbd", jac, 10, i, 0.01) for i in (10, 20)]
        grid += [Setting("vbd", gs, s, i, 0.01) for s, i in ((15, 5), (20, 3), (30, 5))]
        grid += [Setting("mass_spring", gs, None, 1, 0.01)]
        grid += [dataclasses.replace(default, precision="float16")]
    elif size == "full":
        grid = [Setting("xpbd", gs, s, i, 0.01) for s in (5, 10, 20, 40) for i in (5, 10, 20, 40)]
        grid += [Setting("xpbd", gs, s, i, t) for s, i in ((10, 10), (20, 20)) for t in (0.05, 0.02, 0.005, 0.002, 0.001)]
        grid += [Setting("xpbd", jac, s, i, 0.01) for s in (10, 20) for i in (10, 20, 40)]
        grid += [Setting("vbd", gs, s, i, 0.01) for s in (15, 20, 30, 40) for i in (2, 3, 5, 10)]
        grid += [Setting("vbd", gs, 20, 3, t) for t in (0.05, 0.02, 0.005, 0.002)]
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
        reference_positions: the reference equilibrium of every requested pose [m], (W, V, 3) (a pose
            whose XPBD start exploded keeps that start's positions; it is dropped again).
        reference_status: the XPBD start's per-pose :class:`WorldStatus` values, (W,).
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


def strip_error(fabric: str = "cotton", *, rows: int = STRIP_ROWS) -> dict[str, Any]:
    """The reference solver on a problem with an analytic answer: a 1 m x 5 cm strip of ``fabric``
    (bending off) pinned at its top edge stretches under its own weight by rho g L^2 / (2 Y) (strain
    rho g (L - s) / Y at height s; Poisson 0, as the triangle energy; exact for lumped masses at any
    row count).

    Returns:
        {"fabric", "rows", "extension_mm" (mean drop of the bottom edge), "analytic_mm",
        "relative_error" (|extension - analytic| / analytic [-]), "residual_n", "tol_force_n", "converged"}.
    """
    from simulate.cloth.fabric import resolve_fabric
    from simulate.scenes import hanging_strip
    from simulate.solvers.reference import solve_equilibrium

    fab = dataclasses.replace(resolve_fabric(fabric), bending_stiffness=0.0)
    length = 1.0
    verts, model = hanging_strip(rows, fab, length=length)
    x, result = solve_equilibrium(model, 0, verts)
    extension = float((verts[-2:, 1] - x[-2:, 1]).mean())
    analytic = fab.density * float(np.linalg.norm(model.gravity)) * length ** 2 / (2.0 * fab.stretch_stiffness)
    return {"fabric": fab.name, "rows": int(rows),
            "extension_mm": 1e3 * extension, "analytic_mm": 1e3 * analytic,
            "relative_error": abs(extension - analytic) / analytic, "residual_n": float(result.residual),
            "tol_force_n": float(result.tol_force), "converged": bool(result.converged)}


def _equilibria(scene: Scene, fabric: str, starts: np.ndarray, bodies: np.ndarray, max_iterations: int
                ) -> tuple[np.ndarray, list[Any]]:
    """The reference equilibrium of each pose (module docstring): positions [m] (W, V, 3) float64 and
    one :class:`~simulate.solvers.reference.ReferenceResult` per pose, from ``starts`` (W, V, 3) [m] on
    ``bodies`` (W, Vb, 3) [m]."""
    from simulate.cloth import ClothBuilder, Features
    from simulate.cloth.fabric import resolve_fabric
    from simulate.solvers.reference import solve_equilibrium

    builder = ClothBuilder()
    for _ in range(len(starts)):
        builder.add_garment(scene.rest_vertices, scene.faces, fabric=resolve_fabric(fabric), material_uv=scene.material_uv)
    model = builder.finalize("cpu", features=Features())
    out, results = np.empty((len(starts), scene.vertex_count, 3)), []
    for w in range(len(starts)):
        out[w], result = solve_equilibrium(model, w, starts[w], body_vertices=np.asarray(bodies[w], np.float64),
                                           body_faces=scene.body_faces, contact_thickness=CONTACT_THICKNESS,
                                           friction=REFERENCE_FRICTION, max_iterations=max_iterations)
        results.append(result)
    return out, results


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
    reference_max_iterations: int = 200,
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
        reference: the tight XPBD setting whose result starts the reference equilibrium.
        default: the production default (must be among ``settings``).
        max_frames: relaxation frame budget per setting; reference_max_frames: the reference start's.
        reference_max_iterations: Newton iterations per pose at most for the reference equilibrium
            (a pose that does not converge is kept and reported with ``converged`` false).
        drape_setting: setting of the canonical drape, the common start of all runs (default: ``default``;
            every run, the reference included, then relaxes each pose with its own setting).
        base: the settings not swept (damping, explosion limits, outlier share, patience), default
            :data:`PRODUCTION_BASE`.
        explosion_stretch: triangle stretch ratio that marks a world EXPLODED, for every run (None: the base's).
        on_progress: called with a setting label and its :class:`~simulate.reports.scenes.SceneRun` after each
            simulation (progress bars, per-setting log lines); for the reference equilibrium the run's
            ``frames`` are Newton iterations, ``wall_s`` the Newton time and ``status`` CONVERGED or MAX_STEPS.
        on_row: called with the reference's summary and then with each finished row, as soon as it is
            measured (the CLI appends them to a JSON-lines file, so a sweep cut short keeps its rows).
            Settings that share a simulation (precision variants) are measured one after the other.
        on_reference: called with the reference's summary, equilibrium positions (W, V, 3) and the XPBD
            start's statuses (W,) once it is solved (the CLI saves them, so ``--resume`` can skip it).
        resume: an earlier run's reference and rows: the reference is not solved again and settings
            whose rows are all there are not simulated again (neither is passed to ``on_row``).
    Returns:
        {"scene", "device", "poses", "poses_dropped" (reference start exploded), "reference",
        "reference_strip_error", "rows", "default", "resumed_rows", and :func:`summarize`'s fronts and
        ratios} (see the module docstring for the row and reference fields).
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
                          solver=s.solver, device=device, contact_thickness=CONTACT_THICKNESS)

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
            on_progress(reference.label + " (reference start)", ref)
    else:
        if resume.reference_positions.shape != (w, scene.vertex_count, 3) or len(resume.reference_status) != w:
            raise ValueError(f"resume: the saved reference has positions {resume.reference_positions.shape} and "
                             f"{len(resume.reference_status)} statuses; expected ({w}, {scene.vertex_count}, 3) and {w}")
        # only positions and status are read from a resumed reference (its summary comes saved)
        ref = SceneRun(positions=np.asarray(resume.reference_positions, np.float64),
                       status=np.asarray(resume.reference_status), frames=np.zeros(w, np.int64), wall_s=0.0,
                       substeps=0, dt=0.0)
    ref_all_start, ref_all_status = ref.positions, ref.status
    # A pose whose reference start exploded has no reference: drop it (worlds are independent, so the
    # other worlds' results stand) and say so in the report.
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
        eq_positions, eq_results = _equilibria(scene, fabric, ref.positions, finals_arr, reference_max_iterations)
        newton_s = float(sum(r.seconds for r in eq_results))
        if on_progress:
            on_progress("equilibrium (reference)", SceneRun(
                positions=eq_positions, frames=np.array([r.iterations for r in eq_results], np.int64), wall_s=newton_s,
                status=np.array([WorldStatus.CONVERGED if r.converged else WorldStatus.MAX_STEPS for r in eq_results]),
                substeps=0, dt=0.0))
        start_mm = 1e3 * np.linalg.norm(ref.positions - eq_positions, axis=-1)  # (W, V)
        ref_metrics = frame_metrics(scene, eq_positions, finals_arr, device=device)
        reference_out = {
            "kind": "equilibrium", "friction": REFERENCE_FRICTION, "label": f"equilibrium from {reference.label}",
            "converged": [bool(r.converged) for r in eq_results],
            "residual_n": [float(r.residual) for r in eq_results], "tol_force_n": [float(r.tol_force) for r in eq_results],
            "iterations": [int(r.iterations) for r in eq_results], "newton_s": newton_s,
            "friction_violation_share": [float(r.friction_violation_share) for r in eq_results],
            "stick_count": [int(r.stick_count) for r in eq_results],
            "max_iterations": int(reference_max_iterations),
            "start_error_max_mm": [float(d.max()) for d in start_mm],
            "start_error_mean_mm": [float(d.mean()) for d in start_mm],
            "stretch_max": max(m["stretch_max"] for m in ref_metrics),
            "penetration_max_mm": max(m["penetration_max_mm"] for m in ref_metrics),
            "start": {"setting": dataclasses.asdict(reference), "label": reference.label, "wall_s": ref.wall_s,
                      "ms_per_frame": 1e3 * ref.wall_s / w, "status": [WorldStatus(int(s)).name for s in ref.status],
                      "frames": ref.frames.tolist()},
            "strip": strip_error(fabric),
            "canonical_drape_setting": drape_setting.label,
            "canonical_drape_status": WorldStatus(int(drape.status[0])).name, "canonical_drape_frames": int(drape.frames[0]),
        }
        ref = dataclasses.replace(ref, positions=eq_positions)
        ref_all_positions = np.array(ref_all_start, np.float64)
        ref_all_positions[keep] = eq_positions
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
        "reference_strip_error": reference_out.get("strip", {}).get("relative_error", float("nan")),
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
    conv = ref.get("converged", [])
    lines.append(f"reference: {ref['label']} ({ref.get('friction', '?')} contact), converged {sum(conv)}/{len(conv)} poses, "
                 f"residual max {max(ref.get('residual_n', [float('nan')])):.2g} N (tolerance "
                 f"{min(ref.get('tol_force_n', [float('nan')])):.2g} N), {max(ref.get('iterations', [0]))} Newton iterations "
                 f"at most; its start was {max(ref.get('start_error_max_mm', [float('nan')])):.2f} mm (max) from it; "
                 f"hanging-strip error {100 * report.get('reference_strip_error', float('nan')):.4f} %")
    lines.append("* = on the Pareto front of max error vs time, + = on the mean error's, < = production default")
    return "\n".join(lines)
