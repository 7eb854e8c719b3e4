"""Side by side with Newton (pip `newton`, extra `peers`): SolverVBD and SolverXPBD against our
XPBD (Gauss-Seidel and Jacobi) on the identical cloth, body and stopping rule.

Scene: the benchmark cape (pinned behind the neck of the default body in a non-trivial pose,
swinging down onto the back; --scene shawl for the square cloth dropped over the shoulders;
capsule stand-in without simulate.body), --worlds copies in one model.
Identical for every solver: geometry, areal density, gravity (-9.81 y), contact distance
(collider thickness + half fabric thickness), Coulomb friction, velocity damping (fabric +
--damping, applied to Newton's velocities by a kernel after every substep) and the stopping
rule (max particle speed < --tolerance for --patience consecutive frames, at most
--max-frames frames).  Materials are matched to first order, since the energies differ:
Newton's isotropic membrane gets tri_ke = tri_ka = 3 Y / 8 (2-D Young's modulus Y), its
XPBD springs spring_ke = Y / 3 (edge share of a right-triangle grid), bending edge_ke = 3 B / h
(our dihedral energy per edge of length h); our shear is orthotropic (much softer), Newton's is not.

Because the energies differ, each solver's error is measured against its own tight reference
(--ref-substeps x --ref-iterations, run to --ref-tolerance); the summary reports, per solver,
the least wall time of a sweep configuration whose mean error is <= --target-error-mm, and how
far each reference is from ours.  One JSON line per run, a summary line per solver.

    python bench/bench_sim_newton.py --device cuda:0 --resolution 135 --worlds 1     # cape, 10k vertices
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def damp_and_measure(qd: wp.array(dtype=wp.vec3), factor: float, max_speed: wp.array(dtype=float)):
    """Scale velocities by ``factor`` and keep the largest speed [m/s] (NaN counts as huge)."""
    i = wp.tid()
    v = qd[i] * factor
    qd[i] = v
    s = wp.length(v)
    if not wp.isfinite(s):
        s = 1.0e30
    wp.atomic_max(max_speed, 0, s)


def cloth_mesh_arguments(vertices: np.ndarray, faces: np.ndarray, fabric, particle_radius: float,
                         springs: bool = False) -> dict:
    """Keywords of Newton's ``ModelBuilder.add_cloth_mesh`` for our ``fabric`` on the cloth
    ``vertices`` (V, 3) [m] (rest and start) / ``faces`` (F, 3), matched to first order (module
    docstring): isotropic membrane tri_ke = tri_ka = 3 Y / 8, or with ``springs`` (SolverXPBD)
    spring_ke = Y / 3; bending edge_ke = 3 B / h (h: the mean edge length); no element damping
    (damping is a velocity scale after every substep, as ours)."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int32)
    edge = float(np.mean(np.linalg.norm(v[f[:, 1]] - v[f[:, 0]], axis=1)))
    young = fabric.stretch_stiffness
    out = dict(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
               vertices=[wp.vec3(*p) for p in v], indices=f.reshape(-1).tolist(),
               density=fabric.density, edge_ke=3.0 * fabric.bending_stiffness / edge, edge_kd=0.0,
               particle_radius=float(particle_radius))
    if springs:
        out.update(tri_ke=0.0, tri_ka=0.0, tri_kd=0.0, add_springs=True, spring_ke=young / 3.0, spring_kd=0.0)
    else:
        out.update(tri_ke=3.0 * young / 8.0, tri_ka=3.0 * young / 8.0, tri_kd=0.0)
    return out


class NewtonRun:
    """Newton model of the scene with our damping and stopping rule around its solver."""

    def __init__(self, newton, scene: dict, fabric, args, solver: str, substeps: int, iterations: int,
                 worlds: int) -> None:
        self.device = wp.get_device(args.device)
        cloth_v = scene["cloth_vertices"].astype(np.float32)
        sub = newton.ModelBuilder(up_axis=newton.Axis.Y)
        cfg = sub.default_shape_cfg.copy()
        cfg.mu = fabric.friction
        mesh = newton.Mesh(scene["body_vertices"].astype(np.float32), scene["body_faces"].astype(np.int32).reshape(-1),
                           compute_inertia=False)
        sub.add_shape_mesh(body=-1, mesh=mesh, cfg=cfg)
        sub.add_cloth_mesh(**cloth_mesh_arguments(cloth_v, scene["cloth_faces"], fabric,
                                                  args.thickness + 0.5 * fabric.thickness,
                                                  springs=solver != "newton_vbd"))
        for i in scene.get("pinned", []):
            sub.particle_mass[int(i)] = 0.0  # cloth particles come first in `sub`; mass 0 pins them
        builder = newton.ModelBuilder(up_axis=newton.Axis.Y)
        builder.replicate(sub, worlds, spacing=(4.0, 0.0, 0.0))
        if solver == "newton_vbd":
            builder.color(include_bending=True)
        self.model = builder.finalize(device=self.device)
        self.model.soft_contact_ke = 1.0e3
        self.model.soft_contact_kd = 1.0
        self.model.soft_contact_mu = fabric.friction
        if solver == "newton_vbd":
            self.solver = newton.solvers.SolverVBD(self.model, iterations=iterations)
        else:
            # Newton's XPBD sums spring corrections (atomics) and scales them by soft_body_relaxation;
            # at realistic (light) cloth density the default 0.9 overshoots, so it is a flag.
            self.solver = newton.solvers.SolverXPBD(self.model, iterations=iterations,
                                                    soft_body_relaxation=args.newton_xpbd_relaxation)
        self.pipeline = newton.CollisionPipeline(self.model, soft_contact_gap=0.01)
        self.contacts = self.pipeline.contacts()
        self.state_0 = self.model.state()
        self.state_1 = self.model.state()
        self.control = self.model.control()
        self.substeps = substeps
        self.dt = args.frame_dt / substeps
        self.factor = max(0.0, 1.0 - (fabric.damping + args.damping) * self.dt)
        self.max_speed = wp.zeros(1, dtype=float, device=self.device)
        self.graph = None
        self.particles_per_world = len(cloth_v)
        # replicate() places worlds around the origin: remember world 0's shift to undo it.
        start = self.state_0.particle_q.numpy()[: len(cloth_v)]
        self.world0_shift = (start - cloth_v).mean(axis=0)

    def _frame(self) -> None:
        for _ in range(self.substeps):
            self.state_0.clear_forces()
            self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.dt)
            self.state_0, self.state_1 = self.state_1, self.state_0
            self.max_speed.zero_()
            wp.launch(damp_and_measure, dim=self.model.particle_count,
                      inputs=[self.state_0.particle_qd, self.factor, self.max_speed], device=self.device)
        if self.substeps % 2 == 1:
            wp.copy(self.state_1.particle_q, self.state_0.particle_q)
            wp.copy(self.state_1.particle_qd, self.state_0.particle_qd)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def step_frame(self) -> float:
        """One frame; returns the max particle speed [m/s] after it."""
        if self.device.is_cuda:
            if self.graph is None:
                self._frame()
                with wp.ScopedCapture(device=self.device) as capture:
                    self._frame()
                self.graph = capture.graph
            else:
                wp.capture_launch(self.graph)
        else:
            self._frame()
        return float(self.max_speed.numpy()[0])

    def relax(self, tolerance: float, patience: int, max_frames: int, checkpoint_every: int = 0
              ) -> tuple[int, str, float, list]:
        """Steps until the stopping rule holds; returns :func:`timed_frames`' (frames, status, wall, checkpoints)."""
        calm = 0

        def step() -> str | None:
            nonlocal calm
            speed = self.step_frame()
            if not np.isfinite(speed) or speed > 50.0:
                return "EXPLODED"
            calm = calm + 1 if speed < tolerance else 0
            return "CONVERGED" if calm >= patience else None

        return timed_frames(step, self.positions, max_frames, checkpoint_every)

    def positions(self) -> np.ndarray:
        """World 0's cloth positions [m] in the scene's frame (its particles come first)."""
        return self.state_0.particle_q.numpy()[: self.particles_per_world] - self.world0_shift


def timed_frames(step, positions, max_frames: int, checkpoint_every: int = 0) -> tuple[int, str, float, list]:
    """Calls ``step()`` (one frame; returns a final status name, or None to go on) at most
    ``max_frames`` times.  Returns (frames, status, stepping wall [s], checkpoints): with
    ``checkpoint_every`` > 0, ``positions()`` (world 0) is copied out every that many frames as
    (stepping seconds so far, frame, positions), the copies not timed; "MAX_STEPS" if no status came."""
    wall, checkpoints = 0.0, []
    for frame in range(1, max_frames + 1):
        t0 = time.perf_counter()
        status = step()  # both simulators read their stopping metrics back: synchronizes
        wall += time.perf_counter() - t0
        if status is not None:
            return frame, status, wall, checkpoints
        if checkpoint_every and frame % checkpoint_every == 0:
            checkpoints.append((wall, frame, positions()))
    return max_frames, "MAX_STEPS", wall, checkpoints


def run_ours(scene: dict, args, solver: str, substeps: int, iterations: int, tolerance: float, max_frames: int,
             worlds: int, checkpoint_every: int = 0):
    """Our simulator to rest; returns (world 0 positions, stepping wall [s], frames, world 0's status,
    checkpoints) as :func:`timed_frames`."""
    from simulate.cloth.fabric import resolve_fabric
    from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus
    from simulate.scenes import batched_drape

    # Newton's cloth is isotropic (one Young's modulus, NewtonRun): ours takes the warp stiffness
    # across the weft too, so both simulate the same material.
    fabric = dataclasses.replace(resolve_fabric(args.fabric), weft_stiffness=None)
    model, collider = batched_drape(scene, worlds, args.device, fabric=fabric, thickness=args.thickness)
    settings = SimSettings(frame_dt=args.frame_dt, substeps=substeps, iterations=iterations,
                           xpbd_mode="jacobi" if solver == "ours_xpbd_jacobi" else "gauss_seidel",
                           xpbd_bending_mode="jacobi" if solver == "ours_xpbd_gs_jb" else None,
                           damping=args.damping,
                           tolerance=tolerance, patience=args.patience, max_frames=max_frames,
                           explosion_stretch=3.0, outlier_fraction=0.0)  # the settings of its figures
    sim = QuasiStaticSimulator(model, collider, settings=settings, solver="vbd" if solver == "ours_vbd" else "xpbd")
    wp.synchronize_device(model.device)

    def step() -> str | None:
        status = sim.step_frame()
        return None if (status == WorldStatus.RUNNING).any() else WorldStatus(status[0]).name

    frames, status, wall, checkpoints = timed_frames(step, lambda: sim.world_positions(0), max_frames,
                                                     checkpoint_every)
    if sim.status[0] != WorldStatus.RUNNING:  # world 0 may have stopped while others ran to max_frames
        status = WorldStatus(sim.status[0]).name
    return sim.world_positions(0), wall, frames, status, checkpoints


def run_newton(newton, scene: dict, fabric, args, solver: str, substeps: int, iterations: int, tolerance: float,
               max_frames: int, worlds: int, checkpoint_every: int = 0):
    run = NewtonRun(newton, scene, fabric, args, solver, substeps, iterations, worlds)
    wp.synchronize_device(run.device)
    frames, status, wall, checkpoints = run.relax(tolerance, args.patience, max_frames, checkpoint_every)
    return run.positions(), wall, frames, status, checkpoints


def settled_point(row: dict, settle: float = 1.05) -> tuple[float, float, int]:
    """(wall [s], mean error [mm], frame) at which a peer run first came within ``settle`` x its
    final error: the time it needed to reach the error it ends at, whether or not its stopping rule
    ever held (Newton's VBD keeps moving at ~0.01 m/s and runs to --max-frames)."""
    final = row["mean_err_mm"]
    for wall, frame, err in row.get("checkpoints", []):
        if err <= settle * final:
            return wall, final, frame
    return row["wall_s"], final, row["frames"]


def equal_error_speedup(ours_rows: list[dict], peer_rows: list[dict]) -> dict | None:
    """Time ratio peer / ours at equal error, per peer configuration and at the peer's most favourable.

    Every non-exploded run is reduced to its settled point (:func:`settled_point`: the time it
    first came within 5 % of the error it ends at).  For each peer run, our fastest run whose final
    mean error is no larger gives ``speedup`` (settled time against settled time, the same rule for
    both) and ``speedup_to_rest`` (against our time until our stopping rule held: what a quasi-static
    pipeline pays to know it is at rest).  Errors are each against the solver's own tight reference
    (the energies differ).  Returns {"speedup", "speedup_to_rest" (smallest over peer configs),
    "per_config": [...]}, or None when no peer run is matched by one of ours.
    """
    ours_settled = [(settled_point(r), r) for r in ours_rows if r["status"] != "EXPLODED"]
    per_config = []
    for row in peer_rows:
        if row["status"] == "EXPLODED":
            continue
        wall, err, frame = settled_point(row)
        matches = [(p, r) for p, r in ours_settled if p[1] <= err]
        if not matches:
            continue
        (o_wall, o_err, o_frame), ours = min(matches, key=lambda m: m[0][0])
        entry = {"peer_config": f"{row['substeps']}x{row['iterations']}", "peer_settled_frame": frame,
                 "peer_wall_s": round(wall, 4), "peer_mean_err_mm": err,
                 "ours_config": f"{ours['solver']} {ours['substeps']}x{ours['iterations']}",
                 "ours_settled_frame": o_frame, "ours_wall_s": round(o_wall, 4), "ours_mean_err_mm": o_err,
                 "speedup": round(wall / max(o_wall, 1e-12), 2)}
        at_rest = [r for p, r in matches if r["status"] == "CONVERGED"]
        if at_rest:
            fastest = min(at_rest, key=lambda r: r["wall_s"])
            entry.update({"ours_to_rest_config": f"{fastest['solver']} {fastest['substeps']}x{fastest['iterations']}",
                          "ours_to_rest_wall_s": fastest["wall_s"],
                          "speedup_to_rest": round(wall / max(fastest["wall_s"], 1e-12), 2)})
        per_config.append(entry)
    if not per_config:
        return None
    rest = [c["speedup_to_rest"] for c in per_config if "speedup_to_rest" in c]
    return {"speedup": min(c["speedup"] for c in per_config), "speedup_to_rest": min(rest) if rest else None,
            "per_config": per_config}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0" if wp.get_cuda_device_count() else "cpu")
    parser.add_argument("--scene", default="cape", choices=["cape", "shawl", "tshirt"],
                        help="tshirt: the dataset's t-shirt (--resolution vertices) from its rest geometry on the "
                             "neutral body in the canonical pose")
    parser.add_argument("--resolution", type=int, default=135,
                        help="cape: vertices along its length (135 -> 10k); shawl: per side (100 -> 10k)")
    parser.add_argument("--worlds", type=int, default=1)
    parser.add_argument("--body", default="default", choices=["default", "capsule"])
    parser.add_argument("--fabric", default="cotton")
    parser.add_argument("--solvers", nargs="+",
                        default=["ours_xpbd_gs", "ours_xpbd_gs_jb", "ours_xpbd_jacobi", "newton_vbd",
                                 "newton_xpbd"],
                        choices=["ours_vbd", "ours_xpbd_gs", "ours_xpbd_gs_jb", "ours_xpbd_jacobi", "newton_vbd",
                                 "newton_xpbd"],
                        help="ours_xpbd_gs_jb: Gauss-Seidel triangles, Jacobi bending (2 launches per iteration "
                             "instead of one per bending colour)")
    parser.add_argument("--substeps", type=int, nargs="+", default=[5, 10])
    parser.add_argument("--iterations", type=int, nargs="+", default=[5, 10])
    parser.add_argument("--ref-substeps", type=int, default=20)
    parser.add_argument("--ref-iterations", type=int, default=20)
    parser.add_argument("--ref-tolerance", type=float, default=0.003)
    parser.add_argument("--ref-max-frames", type=int, default=1000)
    parser.add_argument("--frame-dt", type=float, default=1.0 / 60.0)
    parser.add_argument("--tolerance", type=float, default=0.01)
    parser.add_argument("--patience", type=int, default=5)
    parser.add_argument("--max-frames", type=int, default=600)
    parser.add_argument("--damping", type=float, default=5.0)
    parser.add_argument("--thickness", type=float, default=2.0e-3, help="body contact thickness [m]")
    parser.add_argument("--target-error-mm", type=float, default=10.0)
    parser.add_argument("--checkpoint-every", type=int, default=25,
                        help="measure world 0's error every this many frames, in every sweep run (time to reach an error "
                             "even when its stopping rule never holds); 0 = off")
    parser.add_argument("--newton-xpbd-relaxation", type=float, default=0.9,
                        help="Newton SolverXPBD soft_body_relaxation (its default 0.9)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    from simulate.cloth.fabric import resolve_fabric
    from simulate.scenes import cape_scene, shawl_scene

    out = open(args.out, "a") if args.out else None

    def emit(record: dict) -> None:
        line = json.dumps(record)
        print(line, flush=True)
        if out is not None:
            out.write(line + "\n")
            out.flush()

    try:
        import newton
    except ImportError as exc:
        newton = None
        emit({"bench": "sim_newton", "skipped": "newton", "reason": f"import newton failed: {exc}; "
              "install the 'peers' extra (pip install -e .[peers])"})
    fabric = resolve_fabric(args.fabric)
    if args.scene == "tshirt":
        from bench_solver_front import tshirt_on_body

        rest, faces, _, body_v, body_f = tshirt_on_body(args.resolution)
        scene = {"cloth_vertices": rest, "cloth_faces": faces, "body_vertices": body_v, "body_faces": body_f,
                 "body_kind": "anny"}
    else:
        scene = (cape_scene if args.scene == "cape" else shawl_scene)(args.resolution, body=args.body)
    base = {"bench": "sim_newton", "device": str(wp.get_device(args.device)), "worlds": args.worlds,
            "vertices": int(len(scene["cloth_vertices"])), "body": scene["body_kind"], "scene": args.scene,
            "fabric": fabric.name,
            "tolerance": args.tolerance, "patience": args.patience}
    references = {}
    summary = {}
    ours_rows: list[dict] = []
    peer_rows: dict[str, list] = {}
    for solver in args.solvers:
        if solver.startswith("newton") and newton is None:
            continue

        def run(substeps: int, iterations: int, tolerance: float, max_frames: int, worlds: int, checkpoints: int = 0):
            if solver.startswith("ours"):
                return run_ours(scene, args, solver, substeps, iterations, tolerance, max_frames, worlds, checkpoints)
            return run_newton(newton, scene, fabric, args, solver, substeps, iterations, tolerance, max_frames, worlds,
                              checkpoints)

        try:
            run(1, 1, args.tolerance, 2, args.worlds)  # warm-up: compile kernels (not timed)
            # worlds are identical copies: one world is the reference of all
            ref_q, ref_wall, ref_frames, ref_status, _ = run(args.ref_substeps, args.ref_iterations,
                                                             args.ref_tolerance, args.ref_max_frames, 1)
        except Exception as exc:  # a peer's API drift must not hide the other solvers' numbers
            emit({**base, "solver": solver, "error": f"{type(exc).__name__}: {exc}"})
            continue
        references[solver] = ref_q
        emit({**base, "solver": solver, "config": "reference", "worlds": 1, "substeps": args.ref_substeps,
              "iterations": args.ref_iterations, "frames": ref_frames, "status": ref_status,
              "wall_s": round(ref_wall, 4)})
        best = None
        for substeps in args.substeps:
            for iterations in args.iterations:
                q, wall, frames, status, checkpoints = run(substeps, iterations, args.tolerance, args.max_frames,
                                                           args.worlds, args.checkpoint_every)
                err = np.linalg.norm(q - ref_q, axis=1) * 1e3
                row = {**base, "solver": solver, "config": "sweep", "substeps": substeps, "iterations": iterations,
                       "frames": frames, "status": status, "wall_s": round(wall, 4),
                       "ms_per_frame": round(1e3 * wall / max(frames, 1), 4),
                       "ms_per_world_frame": round(1e3 * wall / max(frames, 1) / args.worlds, 4),
                       "mean_err_mm": round(float(err.mean()), 3), "max_err_mm": round(float(err.max()), 3)}
                if checkpoints:
                    row["checkpoints"] = [[round(t, 4), f, round(float(np.linalg.norm(x - ref_q, axis=1).mean() * 1e3), 3)]
                                          for t, f, x in checkpoints]
                emit(row)
                if solver.startswith("ours"):
                    ours_rows.append(row)
                else:
                    peer_rows.setdefault(solver, []).append(row)
                if status == "CONVERGED" and row["mean_err_mm"] <= args.target_error_mm and (
                        best is None or wall < best["wall_s"]):
                    best = row
        summary[solver] = best
    ours = references.get("ours_xpbd_gs", references.get("ours_vbd"))
    for solver, best in summary.items():
        record = {**base, "solver": solver, "config": "summary", "target_error_mm": args.target_error_mm,
                  "best_wall_s": None if best is None else best["wall_s"],
                  "best_config": None if best is None else f"{best['substeps']}x{best['iterations']}",
                  "best_ms_per_frame": None if best is None else best["ms_per_frame"]}
        if ours is not None and solver in references:
            gap = np.linalg.norm(references[solver] - ours, axis=1) * 1e3
            record["reference_vs_ours_mean_mm"] = round(float(gap.mean()), 3)
        if solver in peer_rows:
            record["equal_error"] = equal_error_speedup(ours_rows, peer_rows[solver])
        emit(record)
    if out is not None:
        out.close()


if __name__ == "__main__":
    main()
