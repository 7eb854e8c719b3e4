"""Per-dataset audit: how far are the production frames from the static equilibrium of their model?

A seeded random sample of kept frames is re-solved with the converged reference solver
(:func:`simulate.solvers.reference.solve_equilibrium`: Newton in float64 on the CPU, judged by its
force residual) on the frame's own model and body: the garment's style rest geometry built as the
production solver builds it (``ClothBuilder`` with the template's ``material_uv`` and the spec's
``garment.fabric``), the body posed with the frame's shape and pose (``simulate.sequence.drape_static``
poses it the same way) and culled to the garment's collision parts, and the simulation's collider
thickness ``SequenceSettings.contact_thickness``. Newton starts from the frame's recorded positions.

Contact uses ``friction="stick"``: the particles touching the body in the recorded frame (within
0.1 mm of their contact plane) are held at their recorded positions tangentially to the body and
may only move along its normal, the rest move freely. The reference is then the equilibrium nearest
the recorded contact state: a production frame that came to rest with a different sliding history
is not penalized for where its contacts are, only for the forces left unbalanced around them.
``friction_violation_share`` says for how many of those held particles that grip would need more
than the fabric's Coulomb friction (mu times the normal force): where it is large, the recorded
contact state itself is not one friction could hold. Self-contact is not part of the reference
energy, so frames whose layers press on each other are measured without that force.

Per frame: ``max_mm`` / ``mean_mm``, the max and mean vertex distance between the recorded and the
equilibrium positions [mm]; the reference's ``residual_n`` (max per-particle force left [N]) against
``tol_force_n``, its Newton ``iterations``, ``converged`` and ``friction_violation_share``.
The cost is bounded by ``audit.max_iterations`` Newton iterations per frame (one sparse
factorization each, ~0.5 s for a 7k-vertex t-shirt on one CPU core, plus element work of similar
cost; a 1.8k-vertex t-shirt frame simulated by XPBD at 8 iterations took 60 iterations, 19 s on
one CPU core, the penalty's stiffening near convergence included); frames whose reference does
not converge within it are listed with ``converged: false`` and left out of the ``max_mm`` /
``mean_mm`` distributions (median, p90, max over the converged frames) and counted in ``not_converged``.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["AUDIT_FRICTION", "reference_model", "solve_reference", "frame_record", "summarize_frames", "audit_dataset"]

AUDIT_FRICTION = "stick"
"""Contact model of the audit's reference (see the module docstring)."""


def reference_model(rest_vertices: np.ndarray, faces: np.ndarray, *, fabric: Any, material_uv: np.ndarray | None,
                    body_part: np.ndarray | None = None):
    """A one-world CPU :class:`~simulate.cloth.model.ClothModel` of a garment, built as the production
    solver builds it (``simulate.sequence.drape_static``).

    Args:
        rest_vertices: rest geometry [m], (V, 3); faces: (F, 3).
        fabric: a Fabric or preset name; material_uv: pattern UVs per face corner (F, 3, 2) or None.
        body_part: primary collision part per vertex (V,) or None (``simulate.body.collision_parts``).
    """
    from simulate.cloth import ClothBuilder, Features

    builder = ClothBuilder()
    builder.add_garment(np.asarray(rest_vertices, np.float64), np.asarray(faces), fabric=fabric, material_uv=material_uv,
                        body_part=body_part)
    return builder.finalize("cpu", features=Features())


def solve_reference(model, start: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray, *,
                    contact_thickness: float, max_iterations: int, world: int = 0,
                    body_face_groups: list[np.ndarray] | None = None):
    """The audit's reference of one frame: the static equilibrium of ``model``'s world nearest ``start``
    with stick contact on the body.

    Args:
        model: e.g. :func:`reference_model`; start: recorded positions [m], (V, 3).
        body_vertices: the posed body [m], (Vb, 3); body_faces: the faces the garment can touch, (Fb, 3).
        contact_thickness: collider thickness [m] (``SequenceSettings.contact_thickness``).
        max_iterations: Newton iterations at most.
        body_face_groups: primary collision bodies (rows of ``body_faces`` per part; the model's
            ``particle_body_part`` picks one per particle), or None.
    Returns:
        (positions [m] (V, 3) float64, :class:`~simulate.solvers.reference.ReferenceResult`).
    """
    from simulate.solvers.reference import solve_equilibrium

    return solve_equilibrium(model, world, np.asarray(start, np.float64), body_vertices=np.asarray(body_vertices, np.float64),
                             body_faces=np.asarray(body_faces), body_face_groups=body_face_groups,
                             contact_thickness=float(contact_thickness),
                             friction=AUDIT_FRICTION, max_iterations=int(max_iterations))


def reference_job(job: tuple) -> tuple[np.ndarray, Any]:
    """One audited frame from plain arrays (a process pool's unit of work): builds the frame's
    one-world CPU model (:func:`reference_model`) and solves it (:func:`solve_reference`).

    ``job`` = (rest_vertices (V, 3), faces (F, 3), fabric, material_uv (F, 3, 2) or None, start (V, 3),
    body_vertices (Vb, 3), body_faces (Fb, 3), contact_thickness [m], max_iterations[, body_face_groups,
    body_part]) (the last two: primary collision bodies, or absent)."""
    rest, faces, fabric, uv, start, body, body_faces, thickness, max_iterations, *parts = job
    groups, part = parts if parts else (None, None)
    model = reference_model(rest, faces, fabric=fabric, material_uv=uv, body_part=part)
    return solve_reference(model, start, body, body_faces, contact_thickness=thickness, max_iterations=max_iterations,
                           body_face_groups=groups)


def solve_references(jobs: list[tuple], *, workers: int) -> list[tuple[np.ndarray, Any]]:
    """:func:`reference_job` for every job, in order; with ``workers`` > 1 in that many spawned
    processes (each frame's Newton solve is single-threaded and independent of the others, so
    the result is the same either way; a 7k-vertex frame takes minutes of one core)."""
    if workers <= 1 or len(jobs) <= 1:
        return [reference_job(job) for job in jobs]
    import concurrent.futures
    import multiprocessing

    with concurrent.futures.ProcessPoolExecutor(max_workers=min(workers, len(jobs)),
                                                mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(reference_job, jobs))


def audit_workers() -> int:
    """Processes the audit solves its frames in: the machine's cores less one for the writer and
    the host, one on machines of 2 cores or fewer (the spawn start-up would cost more than it saves)."""
    cores = os.cpu_count() or 1
    return 1 if cores <= 2 else cores - 1


def frame_record(recorded: np.ndarray, reference: np.ndarray, result) -> dict[str, Any]:
    """Distances [mm] between a recorded frame (V, 3) [m] and its reference (V, 3) [m], and the
    reference's convergence: {max_mm, mean_mm, residual_n, tol_force_n, iterations, converged,
    friction_violation_share, stick_count, seconds}."""
    dist_mm = 1e3 * np.linalg.norm(np.asarray(reference, np.float64) - np.asarray(recorded, np.float64), axis=-1)
    return {"max_mm": float(dist_mm.max()), "mean_mm": float(dist_mm.mean()), "residual_n": float(result.residual),
            "tol_force_n": float(result.tol_force), "iterations": int(result.iterations), "converged": bool(result.converged),
            "friction_violation_share": float(result.friction_violation_share), "stick_count": int(result.stick_count),
            "seconds": round(float(result.seconds), 3)}


def _spread(values: list[float]) -> dict[str, float]:
    v = np.asarray(values, np.float64)
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max())}


def summarize_frames(records: list[dict[str, Any]]) -> dict[str, Any]:
    """The audit's distributions over frame records (:func:`frame_record`): ``max_mm`` and ``mean_mm``
    (median, p90, max) over the frames whose reference converged (absent when none did), ``converged`` /
    ``not_converged`` counts, and the reference's ``residual_n``, ``iterations`` and
    ``friction_violation_share`` (median, p90, max) over all frames."""
    good = [r for r in records if r["converged"]]
    out: dict[str, Any] = {"converged": len(good), "not_converged": len(records) - len(good)}
    if good:
        out["max_mm"] = _spread([r["max_mm"] for r in good])
        out["mean_mm"] = _spread([r["mean_mm"] for r in good])
    if records:
        for key in ("residual_n", "iterations", "friction_violation_share"):
            out[key] = _spread([r[key] for r in records])
    return out


def audit_dataset(ctx, out_dir: Path, manifest, *, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Re-solves ``spec.audit.samples`` kept frames of the dataset in ``out_dir`` with the reference (module
    docstring) and returns the manifest's ``audit`` block: ``reference`` ("equilibrium"), ``friction``,
    ``samples``, ``max_iterations``, ``contact_thickness_m``, ``frames`` (one :func:`frame_record` each, with
    split, index and task_id) and :func:`summarize_frames`'s distributions, ``seconds`` (wall time)."""
    from data_manifest.reader import DatasetReader

    spec = ctx.spec
    t0 = time.perf_counter()
    reader = DatasetReader(out_dir)
    candidates = [(split, i) for split in reader.splits for i in range(reader.num_frames(split))]
    want = min(int(spec["audit"]["samples"]), len(candidates))
    if want == 0:
        reader.close()
        return {"samples": 0, "note": "no kept frames to audit"}
    rng = np.random.default_rng([int(spec["seed"]), 71])
    picks = [candidates[i] for i in sorted(rng.choice(len(candidates), want, replace=False))]
    frames = [reader.get(split, i) for split, i in picks]
    reader.close()
    tasks = ctx.tasks
    max_iterations = int(spec["audit"]["max_iterations"])
    from simulate.sequence import SequenceSettings

    thickness = float(SequenceSettings().contact_thickness)  # the collider thickness the frames were simulated with
    bodies = np.asarray(ctx.body.pose(np.stack([f["shape"] for f in frames]), np.stack([f["pose"] for f in frames])).vertices)
    jobs = [(np.asarray(ctx.style_rest[tasks[f["task_id"]].garment_index]), np.asarray(ctx.template.faces),
             tasks[f["task_id"]].fabric,
             ctx.template.face_uv, np.asarray(f["posed_vertices"]), np.asarray(body), np.asarray(ctx.body_faces),
             thickness, max_iterations, ctx.body_face_groups, ctx.body_part) for f, body in zip(frames, bodies)]
    solved = solve_references(jobs, workers=audit_workers())
    records = [{"split": split, "index": int(index), "task_id": f["task_id"], **frame_record(f["posed_vertices"], x, result)}
               for (split, index), f, (x, result) in zip(picks, frames, solved)]
    result = {"reference": "equilibrium", "friction": AUDIT_FRICTION, "samples": want, "max_iterations": max_iterations,
              "contact_thickness_m": thickness, "frames": records, **summarize_frames(records),
              "seconds": round(time.perf_counter() - t0, 3)}
    if "max_mm" in result:
        log(f"audit: {want} kept frames against their static equilibrium (stick contact): {result['converged']} converged, "
            f"vertex error median of max {result['max_mm']['median']:.2f} mm, median of mean "
            f"{result['mean_mm']['median']:.2f} mm ({result['seconds']:.1f} s)")
    else:
        log(f"audit: {want} kept frames, no reference converged within {max_iterations} Newton iterations "
            f"(residual median {result['residual_n']['median']:.3g} N; {result['seconds']:.1f} s)")
    return result
