"""Time to rest and crossings against Newton's ``SolverVBD`` with self-contact, on the scene of
``bench_self_contact.py``: the t-shirt's canonical drape, both shoulders lowered to ``--angle`` rad
(slerp'ed, ``--step`` rad per frame) and held until the stopping rule holds.

    python bench/bench_self_contact_newton.py [--resolution 1800] [--device cpu] [--runs vbd-sc,xpbd-sc,newton-vbd-sc]

Runs: ``vbd-sc`` / ``xpbd-sc`` (ours, through ``run_sequences`` with the shipped stepping, as
``bench_self_contact.py`` runs them) and ``newton-vbd-sc`` (Newton's ``SolverVBD``,
``particle_enable_self_contact``; pip ``newton``, the ``peers`` extra). Newton starts from our VBD
canonical drape, settles on the canonical body (not timed: this also compiles its kernels, as our
canonical drape and settle do ours), then goes through the same slerp'ed bodies, one frame each,
and holds the lowered pose. Matched: garment rest geometry and start, body mesh per frame (moved
linearly across each frame's substeps, the mesh's velocities set for friction), frame length,
substeps x iterations (VBD 20 x 3), gravity, areal density, velocity damping (fabric + 20/s after
every substep), body friction, contact distances, self-contact distance, and the stopping rule (our
``measure_particles`` kernel: every particle but 2 % slower than 0.05 m/s or in a limit cycle of 8
frames, 3 frames in a row, at least ``--min-hold-frames`` and at most ``--max-hold-frames``
frames). What cannot be matched: docs/newton-self-contact.md.

One JSON line per run: ``time_to_rest_s`` (wall seconds of the lowering and the hold; ours: the
frames after the settle, posing of the bodies included; Newton: its frames, the bodies posed
beforehand), ``frames_to_rest`` (lowering frames + hold frames), the hold's status, and by our
``QualityMeter`` on the held frame: crossing garment edges (``self_intersections``, exact
edge-triangle test), intersection ``contours``, ``penetration_fraction`` and
``distorted_fraction`` (area ratio outside [0.25, 2]). A Newton run that cannot run (not installed,
or failing on this device) prints a line with ``skipped`` and the reason instead.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

from bench_self_contact import arms_lowered_scene, canonical_drape, parse_stepping, run_settings
from simulate.poses import interpolate_sequence
from simulate.quasi_static import WorldStatus
from simulate.sequence import SequenceTask, run_sequences
from simulate.solvers import common_kernels as ck

wp.set_module_options({"enable_backward": False})

NEWTON_RUNS = ("newton-vbd-sc", "newton-vbd")
"""Newton runs: SolverVBD with and without self-contact."""


@wp.kernel
def lerp_points(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), t: float, out: wp.array(dtype=wp.vec3)):
    """``out = a + t (b - a)`` per point."""
    i = wp.tid()
    out[i] = a[i] + t * (b[i] - a[i])


@wp.kernel
def frame_velocity(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), inv_dt: float,
                   out: wp.array(dtype=wp.vec3)):
    """``out = (b - a) / dt`` per point [m/s]: a body vertex moving from ``a`` to ``b`` in a frame."""
    i = wp.tid()
    out[i] = (b[i] - a[i]) * inv_dt


@wp.kernel
def scale_velocities(qd: wp.array(dtype=wp.vec3), factor: float):
    """Velocities [m/s] times ``factor`` (our velocity damping, after each substep)."""
    i = wp.tid()
    qd[i] = qd[i] * factor


class RestRule:
    """Our stopping rule (``QuasiStaticSimulator``: ``measure_particles`` with its limit-cycle
    history, ``outlier_fraction``, ``patience``, explosion speed) on another simulator's particle
    positions and velocities (one world)."""

    def __init__(self, sim, particle_count: int, device) -> None:
        self.sim = sim
        self.device = device
        self.window = sim.limit_cycle_window if sim.limit_cycle_window > 1 else 0
        self.world = wp.zeros(particle_count, dtype=wp.int32, device=device)
        self.active = wp.ones(1, dtype=wp.int32, device=device)
        self.history = wp.full((max(self.window, 1), particle_count), wp.vec3(1.0e6, 1.0e6, 1.0e6), dtype=wp.vec3,
                               device=device)
        self.slot = wp.zeros(1, dtype=wp.int32, device=device)
        self.speed = wp.zeros(1, dtype=float, device=device)
        self.bad = wp.zeros(1, dtype=wp.int32, device=device)
        self.fast = wp.zeros(1, dtype=wp.int32, device=device)
        self.allowed_fast = np.floor(sim.outlier_fraction * particle_count)
        self.calm = 0

    def restart(self) -> None:
        """A new target: calm frames count from zero (``QuasiStaticSimulator.restart``)."""
        self.calm = 0

    def frame(self, q: wp.array, qd: wp.array) -> WorldStatus:
        """Measures a finished frame; RUNNING, CONVERGED or EXPLODED (MAX_STEPS is the caller's)."""
        s = self.sim
        for a in (self.speed, self.bad, self.fast):
            a.zero_()
        step = float(s.tolerance) * float(s.frame_dt)
        wp.launch(ck.measure_particles, dim=len(self.world),
                  inputs=[self.world, self.active, qd, q, float(s.tolerance), self.history, self.slot, self.window, step,
                          self.window * step], outputs=[self.speed, self.bad, self.fast], device=self.device)
        if self.window:
            wp.launch(ck.advance_history_slot, dim=1, inputs=[self.window, self.slot], device=self.device)
        speed, bad, fast = float(self.speed.numpy()[0]), int(self.bad.numpy()[0]), int(self.fast.numpy()[0])
        if bad or speed > s.explosion_speed:
            return WorldStatus.EXPLODED
        self.calm = self.calm + 1 if fast <= self.allowed_fast else 0
        return WorldStatus.CONVERGED if self.calm >= s.patience else WorldStatus.RUNNING


class NewtonSelfContactRun:
    """Newton model of the scene: the garment as cloth, the body as one static mesh shape whose
    vertices move each substep, SolverVBD (with self-contact unless ``self_contact`` is False),
    our damping and stopping rule around it."""

    def __init__(self, newton, scene, settings, start: np.ndarray, bodies: np.ndarray, args,
                 self_contact: bool = True) -> None:
        from bench_sim_newton import cloth_mesh_arguments

        from simulate.cloth.fabric import resolve_fabric
        from simulate.contact.self_contact import SelfContact

        self.device = wp.get_device(args.device)
        sim = settings.sim
        fabric = resolve_fabric("cotton")  # SequenceTask's default fabric
        mu = fabric.friction if settings.friction != 0.0 else 0.0
        self.body_faces = np.asarray(scene.body_faces, np.int32)
        builder = newton.ModelBuilder(up_axis=newton.Axis.Y)
        cfg = builder.default_shape_cfg.copy()
        cfg.mu = mu
        mesh = newton.Mesh(np.asarray(bodies[0], np.float32), self.body_faces.reshape(-1), compute_inertia=False)
        builder.add_shape_mesh(body=-1, mesh=mesh, cfg=cfg)
        builder.add_cloth_mesh(**cloth_mesh_arguments(scene.template.vertices, scene.template.faces, fabric,
                                                      settings.contact_thickness + 0.5 * fabric.thickness))
        builder.color(include_bending=True)
        self.model = builder.finalize(device=self.device)
        # the body moves: the shape's broad-phase box must hold it in every pose (Newton computes it once)
        lo, hi = bodies.reshape(-1, 3).min(axis=0) - 0.05, bodies.reshape(-1, 3).max(axis=0) + 0.05
        self.model.shape_collision_aabb_lower.assign(np.asarray([lo], np.float32))
        self.model.shape_collision_aabb_upper.assign(np.asarray([hi], np.float32))
        self.model.soft_contact_ke = args.newton_contact_ke
        self.model.soft_contact_kd = 0.0
        self.model.soft_contact_mu = mu
        thickness = max(2.0e-3, fabric.thickness)  # SelfContact's default distance
        self.self_contact_distance = thickness
        options = {}
        if self_contact:
            options = dict(particle_enable_self_contact=True, particle_self_contact_margin=thickness,
                           particle_self_contact_gap=SelfContact.__init__.__kwdefaults__["margin"])
        self.solver = newton.solvers.SolverVBD(self.model, iterations=sim.iterations, **options)
        self.pipeline = newton.CollisionPipeline(self.model, soft_contact_gap=0.01)
        self.contacts = self.pipeline.contacts()
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        self.state_0.particle_q.assign(np.asarray(start, np.float32))
        self.state_0.particle_qd.zero_()
        self.body_mesh = mesh.mesh  # the wp.Mesh the model's shape points to
        self.body_from = wp.array(np.asarray(bodies[0], np.float32), dtype=wp.vec3, device=self.device)
        self.body_to = wp.clone(self.body_from)
        self.body_mesh.velocities.zero_()
        self.substeps = int(sim.substeps)
        self.dt = sim.frame_dt / self.substeps
        self.frame_dt = sim.frame_dt
        self.factor = max(0.0, 1.0 - (fabric.damping + sim.damping) * self.dt)
        self.rule = RestRule(sim, self.model.particle_count, self.device)
        self.use_graph = not args.newton_eager
        self.graph = None
        self.graph_error = None

    def set_body_target(self, vertices: np.ndarray) -> None:
        """The body at the end of the next frame [m] (Vb, 3); the mesh's velocities carry the frame's motion."""
        wp.copy(self.body_from, self.body_to)
        self.body_to.assign(np.asarray(vertices, np.float32))
        wp.launch(frame_velocity, dim=len(self.body_to), inputs=[self.body_from, self.body_to, 1.0 / self.frame_dt],
                  outputs=[self.body_mesh.velocities], device=self.device)

    def _substeps(self) -> None:
        """The frame's substeps: body moved to (s + 1) / substeps of its motion and refit, Newton's
        collision pass, a SolverVBD step, our damping (graph-capturable: no allocation)."""
        for s in range(self.substeps):
            wp.launch(lerp_points, dim=len(self.body_to), inputs=[self.body_from, self.body_to, (s + 1) / self.substeps],
                      outputs=[self.body_mesh.points], device=self.device)
            self.body_mesh.refit()
            self.state_0.clear_forces()
            self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.dt)
            self.state_0, self.state_1 = self.state_1, self.state_0
            wp.launch(scale_velocities, dim=self.model.particle_count, inputs=[self.state_0.particle_qd, self.factor],
                      device=self.device)
        if self.substeps % 2 == 1:  # end in the buffer the frame started from, so a replayed graph chains
            wp.copy(self.state_1.particle_q, self.state_0.particle_q)
            wp.copy(self.state_1.particle_qd, self.state_0.particle_qd)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def step_frame(self) -> WorldStatus:
        """One frame (the body moved linearly over its substeps); the stopping rule's verdict. On
        CUDA the substeps are captured once as a graph and replayed (as our simulator's frames; Newton's
        examples capture theirs), unless ``use_graph`` is off or the capture fails (then eager)."""
        if self.device.is_cuda and self.use_graph:
            if self.graph is None:
                self._substeps()  # eager first frame: every kernel compiled and loaded before capture
                states = (self.state_0, self.state_1)
                try:
                    with wp.ScopedCapture(device=self.device) as capture:
                        self._substeps()
                    self.graph = capture.graph
                except Exception as exc:  # keep stepping eagerly, and say so in the run's line
                    self.state_0, self.state_1 = states
                    self.use_graph = False
                    self.graph_error = f"{type(exc).__name__}: {exc}"
                return self.rule.frame(self.state_0.particle_q, self.state_0.particle_qd)
            wp.capture_launch(self.graph)
        else:
            self._substeps()
        return self.rule.frame(self.state_0.particle_q, self.state_0.particle_qd)

    def positions(self) -> np.ndarray:
        """Garment positions [m] (V, 3) (a copy)."""
        return self.state_0.particle_q.numpy().copy()


def hold_to_rest(step_frame, restart, min_hold: int, max_hold: int) -> tuple[int, WorldStatus]:
    """Steps a held target until the stopping rule holds, as ``run_sequences`` holds a target:
    at least ``min_hold`` frames (a world at rest before that keeps holding, its calm frames
    counted afresh), at most ``max_hold`` (then MAX_STEPS). Returns (frames, status)."""
    restart()
    for held in range(1, max_hold + 1):
        status = step_frame()
        if status == WorldStatus.EXPLODED or (status == WorldStatus.CONVERGED and held >= min_hold):
            return held, status
        if status == WorldStatus.CONVERGED:
            restart()
    return max_hold, WorldStatus.MAX_STEPS


def run_ours(scene, run: str, args) -> dict:
    """One of our runs through ``run_sequences`` (shape transition, settle, lowering, hold), timed
    from the end of the settle to the end of the hold (the frames' kinds from its statistics)."""
    settings = run_settings(run, max_frames=args.max_hold_frames, min_hold_frames=args.min_hold_frames,
                            step=args.step, friction=args.friction, stepping=args.stepping)
    start, drape_s = canonical_drape(scene, settings, args.device)
    task = SequenceTask(rest_vertices=scene.template.vertices, start_vertices=start,
                        shape=np.asarray(scene.body.shape_default, np.float32), poses=scene.lowered[None])
    stats: dict = {}
    marks = []  # per loop pass: (time, settle frames, transition frames, hold frames, body-model seconds)

    def progress(_finished: int) -> None:
        marks.append((time.perf_counter(), stats["settle_world_frames"], stats["transition_world_frames"],
                      stats["hold_world_frames"], stats["body_model_s"]))

    frames = []
    run_sequences(scene.body, scene.template.faces, [task], settings=settings, on_frame=frames.append,
                  on_progress=progress, stats=stats, material_uv=scene.template.face_uv,
                  **scene.sim_arguments(args.device))
    settle_end = next(m for m in marks if m[1] == marks[-1][1])
    hold_end = next(m for m in marks if m[3] == marks[-1][3])
    frame = frames[-1]
    return {"start": start, "drape_s": drape_s, "positions": frame.positions, "body": frame.body_vertices,
            "status": WorldStatus(int(frame.status)).name, "lowering_frames": hold_end[2] - settle_end[2],
            "hold_frames": int(frame.frames), "time_to_rest_s": hold_end[0] - settle_end[0],
            "body_posing_s": hold_end[4] - settle_end[4]}


def run_newton(newton, scene, run: str, args, start: np.ndarray) -> dict:
    """Newton's SolverVBD from ``start`` (our VBD canonical drape): settle on the canonical body
    (not timed), then the slerp'ed bodies one frame each and the hold, timed."""
    settings = run_settings("vbd-sc", max_frames=args.max_hold_frames, min_hold_frames=args.min_hold_frames,
                            step=args.step, friction=args.friction, stepping=args.stepping)
    route, _ = interpolate_sequence(scene.lowered[None], scene.canonical, args.step)
    poses = np.concatenate([scene.canonical[None], route]).astype(np.float32)
    shapes = np.tile(np.asarray(scene.body.shape_default, np.float32), (len(poses), 1))
    bodies = np.asarray(scene.body.pose(shapes, poses).vertices, np.float32).reshape(len(poses), -1, 3)
    sim = NewtonSelfContactRun(newton, scene, settings, start, bodies, args, self_contact=run == "newton-vbd-sc")
    t0 = time.perf_counter()
    settle_frames, settle_status = hold_to_rest(sim.step_frame, sim.rule.restart, args.min_hold_frames, 80)
    wp.synchronize_device(sim.device)
    settle_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    status = WorldStatus.RUNNING
    for body in bodies[1:-1]:
        sim.set_body_target(body)
        sim.rule.restart()
        if sim.step_frame() == WorldStatus.EXPLODED:
            status = WorldStatus.EXPLODED
            break
    held = 0
    if status != WorldStatus.EXPLODED:
        sim.set_body_target(bodies[-1])
        held, status = hold_to_rest(sim.step_frame, sim.rule.restart, args.min_hold_frames, args.max_hold_frames)
    wp.synchronize_device(sim.device)
    return {"start": start, "positions": sim.positions(), "body": bodies[-1], "status": status.name,
            "lowering_frames": len(bodies) - 2, "hold_frames": held, "time_to_rest_s": time.perf_counter() - t0,
            "settle_frames": settle_frames, "settle_status": settle_status.name, "settle_s": settle_s,
            "self_contact_distance_m": sim.self_contact_distance, "contact_ke": args.newton_contact_ke,
            "newton": newton.__version__, "newton_cuda_graph": sim.graph is not None,
            **({"newton_graph_error": sim.graph_error} if sim.graph_error else {})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=1800, help="garment vertices (about; 7700 for production)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda:N")
    parser.add_argument("--angle", type=float, default=1.0, help="shoulder rotation toward the torso [rad]")
    parser.add_argument("--step", type=float, default=0.05, help="largest joint turn per frame [rad]")
    parser.add_argument("--min-hold-frames", type=int, default=2, help="frames the lowered pose is held at least")
    parser.add_argument("--max-hold-frames", type=int, default=60,
                        help="frames after which a hold still moving ends as MAX_STEPS")
    parser.add_argument("--friction", type=float, default=None,
                        help="0: body friction off (default: the fabric's coefficient)")
    parser.add_argument("--stepping", default=None, metavar="SxI",
                        help="substeps x iterations of every run, e.g. 10x3 (default: each solver's shipped stepping, "
                             "Newton's VBD at ours)")
    parser.add_argument("--newton-contact-ke", type=float, default=1.0e4,
                        help="Newton's soft_contact_ke [N/m] (body and self-contact alike; ours: 1e4 for self-contact)")
    parser.add_argument("--newton-eager", action="store_true",
                        help="CUDA: step Newton eagerly instead of replaying its frame as a CUDA graph")
    parser.add_argument("--runs", default="vbd-sc,xpbd-sc,newton-vbd-sc",
                        help="comma-separated: vbd-sc, xpbd-sc (ours, any of bench_self_contact's), newton-vbd-sc, "
                             "newton-vbd (Newton without self-contact)")
    parser.add_argument("--out", default=None, help="also append the JSON lines to this file")
    args = parser.parse_args()
    args.stepping = parse_stepping(args.stepping, parser)
    runs = args.runs.split(",")
    for run in runs:
        if run not in NEWTON_RUNS:
            try:
                run_settings(run, max_frames=1, min_hold_frames=1, step=args.step, friction=args.friction)
            except ValueError as exc:
                parser.error(f"--runs: {exc}, or one of {', '.join(NEWTON_RUNS)}")
    if args.min_hold_frames < 1 or args.max_hold_frames < args.min_hold_frames:
        parser.error(f"--min-hold-frames must be >= 1 and <= --max-hold-frames (got {args.min_hold_frames}, "
                     f"{args.max_hold_frames})")
    if args.device.startswith("cuda") and not wp.get_cuda_device_count():
        parser.error(f"--device {args.device}: no CUDA device here (expected cpu or cuda:N)")

    def emit(record: dict) -> None:
        line = json.dumps(record)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")

    newton, newton_missing = None, None
    if any(r in NEWTON_RUNS for r in runs):
        try:
            import newton
        except ImportError as exc:
            newton_missing = f"import newton failed ({exc}); pip install 'newton>=1.8' (the peers extra)"
    scene = arms_lowered_scene(args.resolution, args.angle)
    meter = scene.meter(args.device)
    base = {"bench": "self_contact_newton", "resolution": args.resolution, "vertices": len(scene.template.vertices),
            "device": args.device, "angle_rad": args.angle, "step_rad": args.step,
            "stepping": list(args.stepping) if args.stepping else "shipped"}
    vbd_start = None
    for run in runs:
        if run in NEWTON_RUNS:
            if newton_missing:
                emit({**base, "run": run, "skipped": newton_missing})
                continue
            if vbd_start is None:
                vbd_start, _ = canonical_drape(scene, run_settings("vbd-sc", max_frames=args.max_hold_frames,
                                                                   min_hold_frames=args.min_hold_frames,
                                                                   step=args.step, friction=args.friction,
                                                                   stepping=args.stepping), args.device)
            try:
                out = run_newton(newton, scene, run, args, vbd_start)
            except Exception as exc:  # e.g. a kernel Newton does not build for this device
                emit({**base, "run": run, "skipped": f"Newton failed on {args.device}: {type(exc).__name__}: {exc}"})
                continue
        else:
            out = run_ours(scene, run, args)
            if run == "vbd-sc":
                vbd_start = out["start"]
        start_q = meter.measure(out.pop("start"), scene.rest_body)
        held = meter.measure(out.pop("positions"), out.pop("body"), area_bounds=(0.25, 2.0))
        frames = out["lowering_frames"] + out["hold_frames"]
        emit({**base, "run": run, "frames_to_rest": frames, **{k: (round(v, 3) if isinstance(v, float) else v)
                                                               for k, v in out.items()},
              "ms_per_frame": round(1e3 * out["time_to_rest_s"] / max(frames, 1), 2),
              "drape_self_intersections": start_q["self_intersections"],
              "self_intersections": held["self_intersections"], "contours": held["self_intersection_contours"],
              "penetration_fraction": round(held["penetration_fraction"], 5),
              "distorted_fraction": round(held["distorted_fraction"], 5)})


if __name__ == "__main__":
    main()
