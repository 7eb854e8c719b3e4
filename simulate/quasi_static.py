"""Quasi-static driver: steps all worlds frame by frame until each one comes to rest.

Per frame, for every substep ``s`` the body mesh is moved to fraction ``(s + 1) / substeps`` of
its motion from the previous to the target pose (one refit for all worlds), then the solver
advances one substep.  After the frame a per-world check decides:

* EXPLODED: a non-finite position/velocity, a speed above ``explosion_speed`` or a stretch
  ratio above ``explosion_stretch``; the world is frozen (no longer integrated) and the
  others continue untouched (no kernel mixes worlds).
* CONVERGED: every particle but at most ``outlier_fraction`` of the world's slower than
  ``tolerance`` (or, with ``limit_cycle_window``, circling in a small limit cycle) for
  ``patience`` consecutive frames; frozen.
* MAX_STEPS: still moving after ``max_frames`` frames; frozen.

On CUDA the whole frame (substeps, body refits, metrics) is captured once as a CUDA graph and
replayed.  On CPU, Warp's graph capture records kernel launches and memsets but executes a
``wp.Mesh.refit`` immediately instead of recording it, so a whole frame cannot be captured;
there the solver substep (both buffer parities) and the metrics are captured as CPU graphs
(replay costs ~3 us per launch against ~20 us for an eager ``wp.launch``) and the body
interpolation + refit run eagerly between them.  With self-contact on (its BVH refit sits
inside the substep) CPU runs are fully eager.
"""

from __future__ import annotations

import dataclasses
import enum
import warnings

import numpy as np
import warp as wp

from simulate.cloth.model import ClothModel
from simulate.contact.body_collider import BodyCollider
from simulate.solvers import common_kernels as ck
from simulate.solvers import make_solver
from simulate.solvers.xpbd.solver_xpbd import GS_SWEEPS

__all__ = ["QuasiStaticSimulator", "SimSettings", "WorldStatus"]

_FAR = wp.vec3(1.0e6, 1.0e6, 1.0e6)  # [m] a history position no particle is near


class WorldStatus(enum.IntEnum):
    """Per-world outcome of quasi-static stepping."""

    RUNNING = 0
    CONVERGED = 1
    MAX_STEPS = 2
    EXPLODED = 3


@dataclasses.dataclass
class SimSettings:
    """Time stepping and convergence settings (SI units).

    The defaults are the settings ``drape generate-dataset`` runs with unless a spec changes
    them (``pipelines.spec.DEFAULTS``; tested to agree)."""

    frame_dt: float = 1.0 / 45.0
    """Frame duration [s]; the body moves from its previous to its target pose in one frame.
    1/45 s: holds come to rest in fewer frames than at 1/60 s (docs/benchmarks.md)."""
    substeps: int | None = 15
    """Substeps per frame; None = solver's choice (mass-spring: from its stable time step)."""
    iterations: int = 5
    """XPBD iterations per substep.  15 x 5: smaller substeps with fewer iterations reach the
    accuracy of 10 x 10 for less sweep work (``drape report accuracy``)."""
    xpbd_mode: str = "gauss_seidel"
    """XPBD sweep: "gauss_seidel" (graph colouring) or "jacobi"."""
    xpbd_bending_mode: str | None = None
    """XPBD bending sweep ("gauss_seidel" or "jacobi"); None = same as ``xpbd_mode``.  Jacobi
    bending under Gauss-Seidel triangles needs 2 launches per iteration instead of one per
    bending colour (launch-bound single-world GPU runs), at slightly higher error."""
    gs_sweep: str = "world_blocks"
    """How XPBD launches its Gauss-Seidel colours: "world_blocks" (one launch per iteration, one
    thread block per world, a barrier between colours) or "colour_launches" (one launch per
    colour).  Same result; see ``SolverXPBD``."""
    gs_block_dim: int = 256
    """Threads per world block of the "world_blocks" sweep (CUDA)."""
    damping: float = 20.0
    """Velocity damping rate [1/s] added to each fabric's damping.  Quasi-static relaxation only
    needs the rest state, so this is strong (velocities decay e-fold in 0.05 s): a 10k-vertex
    shawl on the body settles in ~200 frames at 5/s against >600 at 1/s."""
    tolerance: float = 0.05
    """Convergence: max particle speed [m/s] ..."""
    patience: int = 3
    """... below tolerance for this many consecutive frames."""
    outlier_fraction: float = 0.02
    """Fraction of a world's particles allowed to stay at or above ``tolerance`` when it is
    declared converged.  0 = the max speed decides.  A few particles caught where two body
    surfaces interpenetrate (armpit, a lowered arm against the torso) can jitter forever;
    with 0.02 the rest of the garment still counts as at rest (the dataset filters then
    judge those particles through penetration)."""
    limit_cycle_window: int = 8
    """Frames of position history kept to recognize limit cycles (0 or 1 = off).  With N > 1 a
    particle also counts as at rest when it is back within ``tolerance * frame_dt`` of where it
    was 2..N frames ago and no further than ``N * tolerance * frame_dt`` from any of those
    positions: contacts that alternate between two planes (armpits, a cuff against the torso)
    keep a few particles in a small periodic orbit (period 2 to 7 frames seen) whose speed never
    drops below the tolerance, though the garment does not move on.  8 covers the periods seen.
    Memory: N positions per particle."""
    self_contact_detect_every: int = 1
    """Self-contact (XPBD, when the model's features have it): find candidate triangles on
    every this-many-th substep of a frame and reuse them in between (see SelfContact)."""
    self_contact_bounds: bool = False
    """Self-contact (XPBD): keep each particle within its displacement bound between searches
    (``SelfContact``'s module docstring), so no new crossing forms; VBD always keeps to them.
    Off: where the body presses two layers together the bounds pin them and triangles stretch
    (a 480-target t-shirt slice kept 21.5 % against 58.5 %, at 8x the cost per world-frame;
    docs/benchmarks.md, "XPBD with the displacement bounds")."""
    self_contact_directional_bounds: bool = True
    """Self-contact (VBD): each particle's displacement bound is a half-space along the direction
    away from its nearest pair plus a ball (``SelfContact``'s module docstring), instead of a ball
    of 0.45 its nearest pair distance: layers pressed together by the body may part and slide
    along each other instead of being pinned, and still never cross (docs/benchmarks.md,
    "Directional displacement bounds")."""
    self_contact_search_every: int = 1
    """Self-contact (VBD): every world searches its pair lists with the BVHs on every this-many-th
    self-contact substep of a frame; in between only worlds that moved farther than half
    ``self_contact_skin`` since their last search do, and the others refresh their lists
    (distances and bounds of the listed pairs, the rest bounded by their distance at the search
    less the world's displacement since; ``SelfContact``'s module docstring)."""
    self_contact_skin: float = 0.0
    """Self-contact (VBD): extra distance [m] the searches list pairs at, so pairs that close
    before the next search are already listed (``SelfContact``'s ``skin``)."""
    self_contact_rest_exclusion: float | None = None
    """Self-contact: particle-triangle pairs closer than this in the rest geometry are never
    contacts [m] (None = SelfContact's default, twice the contact reach)."""
    untangle: bool = True
    """XPBD and VBD on a model with self-contact: one step of intersection contour minimization
    on every ``untangle_every``-th substep, undoing cloth that passes through itself
    (``simulate.contact.untangle``), in worlds whose self-contact is on
    (``ClothControl.world_self_contact``). On a 480-target t-shirt slice (one H100) it keeps
    61.7 % of the targets against 58.5 % without, at 0.45 against 0.41 ms per world-frame
    (every substep: 66.5 % at 0.60 ms; docs/benchmarks.md, "Untangling in datasets"). A model
    without self-contact compiles none of its kernels (a solver's ``untangle`` option applies
    it there)."""
    untangle_every: int = 5
    """With ``untangle``: its step on every this-many-th substep of a frame, as the body queries
    (``body_contact_detect_every``); the search for crossings is most of its cost."""
    body_contact_detect_every: int = 5
    """Query the body for contact planes on substeps 0, N, 2N, ... of each frame; in between the
    planes move with the body (which moves linearly within a frame), and the body mesh is moved
    and refitted only for the substeps that query it.  1 = every substep.  The planes are tangent
    planes, so a particle sliding by s along a surface of radius R meets its carried plane
    s^2 / (2R) off the surface (0.02 mm for 1 mm on a 3 cm arm); a particle that was farther than
    the collider's thickness + margin (2 cm) at the last query finds no plane until the next one.
    5 (with 15 substeps: queries on substeps 0, 5 and 10) runs faster than 1 at about the same
    kept share and error."""
    max_frames: int = 60
    """Frames after which a still-moving world is marked MAX_STEPS.  Converged t-shirt holds take
    10-33 frames at the other defaults; a longer budget only adds frames."""
    explosion_speed: float = 50.0
    """A particle faster than this [m/s] marks its world EXPLODED."""
    explosion_stretch: float = 50.0
    """A triangle stretched beyond this ratio [-] marks its world EXPLODED: real blow-ups (a few
    triangles at a garment's first contact reach 10-30x transiently at 7.7k vertices, and the
    dataset's distortion filter judges the kept frames)."""
    use_cuda_graph: bool = True
    """Capture and replay the frame as a CUDA graph on CUDA devices."""
    use_cpu_graph: bool = True
    """Capture and replay substeps as CPU graphs on the CPU (see the module docstring)."""

    def __post_init__(self) -> None:
        checks = {
            "frame_dt": self.frame_dt > 0.0,
            "substeps": self.substeps is None or (int(self.substeps) == self.substeps and self.substeps >= 1),
            "iterations": int(self.iterations) == self.iterations and self.iterations >= 1,
            "damping": self.damping >= 0.0,
            "tolerance": self.tolerance > 0.0,
            "patience": int(self.patience) == self.patience and self.patience >= 1,
            "max_frames": int(self.max_frames) == self.max_frames and self.max_frames >= 1,
            "self_contact_detect_every": int(self.self_contact_detect_every) == self.self_contact_detect_every
            and self.self_contact_detect_every >= 1,
            "self_contact_search_every": int(self.self_contact_search_every) == self.self_contact_search_every
            and self.self_contact_search_every >= 1,
            "self_contact_skin": np.isfinite(self.self_contact_skin) and self.self_contact_skin >= 0.0,
            "self_contact_rest_exclusion": self.self_contact_rest_exclusion is None
            or (np.isfinite(self.self_contact_rest_exclusion) and self.self_contact_rest_exclusion >= 0.0),
            "untangle": isinstance(self.untangle, bool),
            "self_contact_directional_bounds": isinstance(self.self_contact_directional_bounds, bool),
            "untangle_every": int(self.untangle_every) == self.untangle_every and self.untangle_every >= 1,
            "body_contact_detect_every": int(self.body_contact_detect_every) == self.body_contact_detect_every
            and self.body_contact_detect_every >= 1,
            "limit_cycle_window": int(self.limit_cycle_window) == self.limit_cycle_window and self.limit_cycle_window >= 0,
            "explosion_speed": self.explosion_speed > 0.0,
            "explosion_stretch": self.explosion_stretch > 1.0,
            "gs_sweep": self.gs_sweep in GS_SWEEPS,
            "gs_block_dim": int(self.gs_block_dim) == self.gs_block_dim and 32 <= self.gs_block_dim <= 1024
            and self.gs_block_dim % 32 == 0,
            "outlier_fraction": 0.0 <= self.outlier_fraction < 1.0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"SimSettings.{name} is invalid (got {getattr(self, name)!r}); see its docstring")


class QuasiStaticSimulator:
    """Relaxes every world of a ClothModel on its body, with per-world status and freezing."""

    def __init__(
        self,
        model: ClothModel,
        collider: BodyCollider | None,
        *,
        solver: str = "xpbd",
        settings: SimSettings | None = None,
        solver_options: dict | None = None,
    ) -> None:
        """
        Args:
            model: cloth model (one garment per world).
            collider: body collider with ``model.world_count`` worlds, or None (no body).
            solver: "vbd", "xpbd" or "mass_spring".
            settings: stepping and convergence settings.
            solver_options: extra keyword options for the solver class.
        """
        self.model = model
        self.settings = settings or SimSettings()
        s = self.settings
        if collider is not None and collider.world_count != model.world_count:
            raise ValueError(f"collider has {collider.world_count} worlds but the model has {model.world_count}")
        if collider is not None and collider.device != model.device:
            raise ValueError(f"collider is on {collider.device} but the model is on {model.device}")
        self.collider = collider
        body_contact = bool(model.features.body_contact and collider is not None)
        opts = dict(solver_options or {})
        opts.setdefault("body_contact", body_contact)
        opts.setdefault("extra_damping", s.damping)
        opts.setdefault("contact_detect_every", int(s.body_contact_detect_every))
        if solver in ("xpbd", "vbd"):
            untangle = s.untangle and model.features.self_contact
            opts.setdefault("untangle", {"every": int(s.untangle_every)} if untangle else False)
        if solver == "xpbd":
            opts.setdefault("iterations", s.iterations)
            opts.setdefault("mode", s.xpbd_mode)
            opts.setdefault("bending_mode", s.xpbd_bending_mode)
            opts.setdefault("gs_sweep", s.gs_sweep)
            opts.setdefault("gs_block_dim", s.gs_block_dim)
            opts.setdefault("self_contact_options", {"detect_every": int(s.self_contact_detect_every),
                                                     "rest_exclusion": s.self_contact_rest_exclusion,
                                                     "bounds": bool(s.self_contact_bounds)})
        elif solver == "vbd":
            opts.setdefault("iterations", s.iterations)
            opts.setdefault("self_contact_options", {"detect_every": int(s.self_contact_detect_every),
                                                     "rest_exclusion": s.self_contact_rest_exclusion,
                                                     "directional_bounds": bool(s.self_contact_directional_bounds),
                                                     "search_every": int(s.self_contact_search_every),
                                                     "skin": float(s.self_contact_skin)})
        self.solver = make_solver(solver, model, **opts)
        if s.substeps is None:
            self.substeps = int(self.solver.substeps_for(s.frame_dt)) if hasattr(self.solver, "substeps_for") else 10
        else:
            self.substeps = int(s.substeps)
        self.dt = s.frame_dt / self.substeps
        """Substep length [s]."""
        if collider is not None:
            collider.motion_scale = 1.0 / self.substeps
        self.state_0 = model.state()
        self.state_1 = model.state()
        self.control = model.control()
        w = model.world_count
        dev = model.device
        self.world_max_speed = wp.zeros(w, dtype=float, device=dev)
        self.world_bad = wp.zeros(w, dtype=wp.int32, device=dev)
        self.world_max_stretch = wp.zeros(w, dtype=float, device=dev)
        self.world_fast_count = wp.zeros(w, dtype=wp.int32, device=dev)
        window = int(s.limit_cycle_window)
        self._window = window if window > 1 else 0
        # positions of the last ``window`` frames (ring; far away until written, so no cycle is
        # recognized before a world has ``window`` frames of its own history)
        self._position_history = wp.full((max(self._window, 1), max(model.particle_count, 1)), _FAR,
                                         dtype=wp.vec3, device=dev)
        self._history_slot = wp.zeros(1, dtype=wp.int32, device=dev)
        self._allowed_fast = np.floor(s.outlier_fraction * np.asarray(model.world_particle_count, np.float64))
        self.status = np.full(w, WorldStatus.RUNNING, dtype=np.int8)
        """Per-world WorldStatus values, shape (world_count,)."""
        self.world_frames = np.zeros(w, dtype=np.int64)
        """Frames each world has been stepped since its last target, shape (world_count,)."""
        self._calm = np.zeros(w, dtype=np.int64)
        self.explosion_causes = {"non_finite": 0, "speed": 0, "stretch": 0}
        """Explosions so far by the first test they failed: a non-finite position or velocity, a
        speed above ``explosion_speed``, a stretch ratio above ``explosion_stretch``."""
        self._history: list[np.ndarray] = []
        self._active_host = np.ones(w, dtype=np.int32)
        self.frame_count = 0
        self._graph = None
        self._use_graph = bool(s.use_cuda_graph and wp.get_device(dev).is_cuda)
        self._use_cpu_graph = bool(s.use_cpu_graph and wp.get_device(dev).is_cpu
                                   and getattr(self.solver, "self_contact", None) is None
                                   and self.solver.contact_detect_every == 1)
        self._cpu_graphs: tuple | None = None
        self._launched_running: np.ndarray | None = None
        self.device_frame_s = 0.0
        """The frames' own time on the device [s], summed: from each frame's start on its stream to
        its end, timed by CUDA events (0 on the CPU). Against the wall time per frame it says how
        much of a loop the host adds (``last_frame_device_s``: the last frame's)."""
        self.last_frame_device_s = 0.0
        self._frame_events = ((wp.Event(dev, enable_timing=True), wp.Event(dev, enable_timing=True))
                              if wp.get_device(dev).is_cuda else None)

    # ----------------------------------------------------------------- stepping
    def _simulate_frame(self, *, cpu_graphs: tuple | None = None) -> None:
        """Substeps of one frame plus the metric kernels (graph-capturable: no allocation).

        With ``cpu_graphs`` = (substep 0->1, substep 1->0, metrics) the solver launches are
        replayed from CPU graphs and only the body update runs eagerly.
        """
        for sub in range(self.substeps):
            if self.collider is not None and self.solver.queries_body(sub):  # the body is needed only there
                self.collider.update((sub + 1) / self.substeps)
            if cpu_graphs is None:
                self.solver.step(self.state_0, self.state_1, self.control, self.collider, self.dt, substep=sub)
            else:
                wp.capture_launch(cpu_graphs[sub % 2])
            self.state_0, self.state_1 = self.state_1, self.state_0
        if self.substeps % 2 == 1:
            # Keep the frame's result in the buffer it started from, so a replayed graph chains.
            self.state_1.assign(self.state_0)
            self.state_0, self.state_1 = self.state_1, self.state_0
        if self.collider is not None:
            if not self.solver.queries_body(self.substeps - 1):  # the body ends the frame at its target pose
                self.collider.update(1.0)
            self.collider.finish_frame()
        if cpu_graphs is None:
            self._measure()
        else:
            wp.capture_launch(cpu_graphs[2])

    def _measure(self) -> None:
        m = self.model
        self.world_max_speed.zero_()
        self.world_bad.zero_()
        self.world_max_stretch.zero_()
        self.world_fast_count.zero_()
        s = self.settings
        step = float(s.tolerance) * float(s.frame_dt)  # [m] moved in a frame at the tolerance speed
        wp.launch(ck.measure_particles, dim=m.particle_count,
                  inputs=[m.particle_world, self.control.world_active, self.state_0.particle_qd,
                          self.state_0.particle_q, float(s.tolerance), self._position_history, self._history_slot,
                          self._window, step, self._window * step],
                  outputs=[self.world_max_speed, self.world_bad, self.world_fast_count], device=m.device)
        if self._window:
            wp.launch(ck.advance_history_slot, dim=1, inputs=[self._window, self._history_slot], device=m.device)
        wp.launch(ck.measure_triangles, dim=m.tri_count,
                  inputs=[m.tri_indices, m.tri_dm_inv, m.tri_world, self.control.world_active,
                          self.state_0.particle_q],
                  outputs=[self.world_max_stretch], device=m.device)

    def _capture_cpu_graphs(self) -> tuple:
        dev = self.model.device
        graphs = []
        for src, dst in ((self.state_0, self.state_1), (self.state_1, self.state_0)):
            with wp.ScopedCapture(device=dev) as capture:
                self.solver.step(src, dst, self.control, self.collider, self.dt)  # (no self-contact here: substep unused)
            graphs.append(capture.graph)
        with wp.ScopedCapture(device=dev) as capture:
            self._measure()
        graphs.append(capture.graph)
        return tuple(graphs)

    def _sync_active(self) -> None:
        active = (self.status == WorldStatus.RUNNING).astype(np.int32)
        if not np.array_equal(active, self._active_host):
            self.control.world_active.assign(active)
            self._active_host = active

    def step_frame(self) -> np.ndarray:
        """Advance every RUNNING world by one frame; returns the per-world status array."""
        self.launch_frame()
        return self.finish_frame()

    def launch_frame(self) -> None:
        """Queues one frame of every RUNNING world on the device's current stream and returns
        without waiting for it (on CUDA; on the CPU the frame runs here). ``finish_frame`` waits
        for it and updates the statuses. In between, host work goes on beside the device: the
        worlds that did not run (``launched_running`` False) may be revived or restarted, and
        device work queued on the same stream runs after the frame."""
        if self._launched_running is not None:
            raise RuntimeError("launch_frame called twice without finish_frame")
        self._sync_active()
        self._launched_running = self.status == WorldStatus.RUNNING
        if self._frame_events is not None:
            wp.record_event(self._frame_events[0])
        self._queue_frame()
        if self._frame_events is not None:
            wp.record_event(self._frame_events[1])

    def _queue_frame(self) -> None:
        """The frame's work, by CUDA graph, CPU graphs or eagerly (``launch_frame``)."""
        if self._use_graph:
            if self._graph is None:
                # The first frame runs eagerly so every kernel is compiled and loaded before capture.
                self._simulate_frame()
                states = (self.state_0, self.state_1)
                try:
                    with wp.ScopedCapture(device=self.model.device) as capture:
                        self._simulate_frame()
                    self._graph = capture.graph
                    # Capture recorded but did not execute the second frame's work.
                except Exception as exc:  # keep simulating eagerly rather than fail a long job
                    self.state_0, self.state_1 = states
                    self._use_graph = False
                    warnings.warn(f"CUDA graph capture failed ({type(exc).__name__}: {exc}); running eagerly",
                                  RuntimeWarning, stacklevel=2)
            else:
                wp.capture_launch(self._graph)
        elif self._use_cpu_graph:
            if self._cpu_graphs is None:
                self._simulate_frame()  # eager first frame compiles and loads every kernel
                self._cpu_graphs = self._capture_cpu_graphs()
            else:
                self._simulate_frame(cpu_graphs=self._cpu_graphs)
        else:
            self._simulate_frame()

    @property
    def launched_running(self) -> np.ndarray | None:
        """Worlds the frame in flight advances, (world_count,) bool; None when no frame is in flight."""
        return self._launched_running

    def finish_frame(self) -> np.ndarray:
        """Waits for the frame queued by ``launch_frame`` and returns the per-world status array.
        Only the worlds that ran in it change status; a world revived or restarted meanwhile keeps
        what that gave it."""
        running = self._launched_running
        if running is None:
            raise RuntimeError("finish_frame called without launch_frame")
        self._launched_running = None
        self.frame_count += 1
        speed = self.world_max_speed.numpy()
        bad = self.world_bad.numpy()
        stretch = self.world_max_stretch.numpy()
        fast = self.world_fast_count.numpy()
        if self._frame_events is not None:  # the reads above waited for the frame: no wait here
            self.last_frame_device_s = wp.get_event_elapsed_time(*self._frame_events) / 1000.0
            self.device_frame_s += self.last_frame_device_s
        s = self.settings
        residual = np.where(running, speed, np.nan)
        self._history.append(residual)
        self.world_frames[running] += 1
        non_finite, too_fast = running & (bad != 0), running & (speed > s.explosion_speed)
        exploded = non_finite | too_fast | (running & (stretch > s.explosion_stretch))
        self.explosion_causes["non_finite"] += int(non_finite.sum())
        self.explosion_causes["speed"] += int((too_fast & ~non_finite).sum())
        self.explosion_causes["stretch"] += int((exploded & ~too_fast & ~non_finite).sum())
        calm = running & ~exploded & (fast <= self._allowed_fast)
        self._calm = np.where(calm, self._calm + 1, np.where(running, 0, self._calm))
        self.status[exploded] = WorldStatus.EXPLODED
        self.status[running & ~exploded & (self._calm >= s.patience)] = WorldStatus.CONVERGED
        timeout = (self.status == WorldStatus.RUNNING) & (self.world_frames >= s.max_frames)
        self.status[timeout] = WorldStatus.MAX_STEPS
        return self.status.copy()

    def relax(self, max_frames: int | None = None) -> np.ndarray:
        """Step until no world is RUNNING (or ``max_frames`` frames this call; the rest get MAX_STEPS).

        Returns:
            per-world WorldStatus values, shape (world_count,).
        """
        budget = self.settings.max_frames if max_frames is None else int(max_frames)
        if budget < 1:
            raise ValueError(f"max_frames must be >= 1 (got {max_frames!r})")
        for _ in range(budget):
            if not (self.status == WorldStatus.RUNNING).any():
                break
            self.step_frame()
        self.status[self.status == WorldStatus.RUNNING] = WorldStatus.MAX_STEPS
        return self.status.copy()

    # ----------------------------------------------------------------- poses and state
    def set_body_target(self, vertices: np.ndarray, *, reset_velocities: bool = False) -> None:
        """Body pose at the end of the next frame [m] (W, Vb, 3); non-exploded worlds run again."""
        if self.collider is None:
            raise ValueError("set_body_target needs a collider (the simulator was built with collider=None)")
        self.collider.set_target(vertices)
        self.restart(reset_velocities=reset_velocities)

    def restart(self, worlds: np.ndarray | list[int] | None = None, *, reset_velocities: bool = False) -> None:
        """Mark worlds RUNNING again (frame and calm counters reset); exploded worlds stay frozen.

        Args:
            worlds: world indices or a (world_count,) bool mask; None = all worlds.
            reset_velocities: zero the velocities of the restarted worlds' particles.
        """
        count = self.model.world_count
        if worlds is None:
            mask = np.ones(count, dtype=bool)
        else:
            arr = np.asarray(worlds)
            if arr.dtype == bool:
                if arr.shape != (count,):
                    raise ValueError(f"worlds mask must have shape ({count},) (got {arr.shape})")
                mask = arr.copy()
            else:
                idx = arr.astype(np.int64).reshape(-1)
                if idx.size and (idx.min() < 0 or idx.max() >= count):
                    raise ValueError(f"worlds must be indices in [0, {count}) (got {idx.tolist()})")
                mask = np.zeros(count, dtype=bool)
                mask[idx] = True
        mask &= self.status != WorldStatus.EXPLODED
        self.status[mask] = WorldStatus.RUNNING
        self.world_frames[mask] = 0
        self._calm[mask] = 0
        if reset_velocities and mask.any():
            qd = self.velocities()
            qd[mask[self.model.particle_world_np]] = 0.0
            self.state_0.particle_qd.assign(qd)

    def revive(self, world: int, positions: np.ndarray | wp.array) -> None:
        """Restart one world (exploded or not) from ``positions`` [m], (V_w, 3) or a
        ``device_positions`` array, at rest.

        Used to recover a world that exploded: put back its last good state and go on.
        """
        self.set_positions(positions, world=world)
        self.status[world] = WorldStatus.RUNNING
        self.world_frames[world] = 0
        self._calm[world] = 0

    def adopt_garment(self, world: int, source: int) -> None:
        """World ``world`` takes world ``source``'s garment (rest shape, fabric; same triangles,
        see ``ClothModel.copy_world_garment``), in place on the device; put its positions there
        with ``revive`` after. A batch's world can then run another garment's tasks."""
        self.model.copy_world_garment(world, source)
        self.solver.garment_changed(world, source)

    def positions(self) -> np.ndarray:
        """Particle positions [m] of all worlds, shape (particle_count, 3) (a copy, also on CPU,
        where Warp's ``numpy()`` would alias the simulation state)."""
        return self.state_0.particle_q.numpy().copy()

    def velocities(self) -> np.ndarray:
        """Particle velocities [m/s], shape (particle_count, 3) (a copy)."""
        return self.state_0.particle_qd.numpy().copy()

    def world_positions(self, world: int) -> np.ndarray:
        """Positions [m] of one world's particles, shape (V_w, 3) (a copy; only this world's
        particles leave the device)."""
        sl = self.model.world_slice(world)
        return self.state_0.particle_q[sl.start:sl.stop].numpy().copy()

    def worlds_positions(self, worlds) -> np.ndarray:
        """Positions [m] of several worlds with the same particle count, shape (n, V_w, 3): they are
        gathered on the device and leave it in one copy (one wait for the device instead of n)."""
        return self._gather(self.state_0.particle_q, worlds)

    def worlds_velocities(self, worlds) -> np.ndarray:
        """Velocities [m/s] of several worlds with the same particle count, shape (n, V_w, 3), gathered
        like ``worlds_positions``."""
        return self._gather(self.state_0.particle_qd, worlds)

    def _gather(self, array: wp.array, worlds) -> np.ndarray:
        """Rows of the per-particle vec3 ``array`` of several worlds with the same particle count, (n, V_w, 3)."""
        slices = [self.model.world_slice(int(w)) for w in worlds]
        sizes = sorted({sl.stop - sl.start for sl in slices})
        if len(sizes) > 1:
            raise ValueError(f"worlds must have the same particle count to be gathered together (got counts {sizes})")
        v = sizes[0] if sizes else 0
        gathered = wp.empty(len(slices) * v, dtype=wp.vec3, device=self.model.device)
        for i, sl in enumerate(slices):
            wp.copy(gathered, array, dest_offset=i * v, src_offset=sl.start, count=v)
        return gathered.numpy().reshape(len(slices), v, 3)

    def device_positions(self, positions: np.ndarray) -> wp.array:
        """Positions [m], (N, 3), checked (finite) and copied once to the model's device as a
        (N,) vec3 array that ``set_positions``/``revive`` take without a host round trip."""
        pos = np.asarray(positions, dtype=np.float32)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"positions must have shape (N, 3) (got {pos.shape})")
        if not np.all(np.isfinite(pos)):
            raise ValueError("positions must be finite (got NaN or inf)")
        return wp.array(pos, dtype=wp.vec3, device=self.model.device)

    def set_positions(self, positions: np.ndarray | wp.array, *, world: int | None = None) -> None:
        """Set positions [m] (all worlds (particle_count, 3), or one world's (V_w, 3), or a
        ``device_positions`` array of that length); zeroes their velocities.

        The positions are copied into place on the device: for one world, the other worlds'
        particles do not leave it (a 256-world t-shirt batch holds 1.8 M particles)."""
        sl = slice(0, self.model.particle_count) if world is None else self.model.world_slice(world)
        start, n = sl.start, sl.stop - sl.start
        dev = self.model.device
        if isinstance(positions, wp.array):
            if positions.dtype != wp.vec3 or positions.shape != (n,) or positions.device != dev:
                raise ValueError(f"a positions array must be device_positions': {wp.vec3.__name__} ({n},) on {dev} "
                                 f"(got {positions.dtype.__name__} {positions.shape} on {positions.device})")
            src = positions
        else:
            pos = np.asarray(positions, dtype=np.float32)
            if pos.shape != (n, 3):
                raise ValueError(f"positions must have shape {(n, 3)} (got {pos.shape})")
            src = self.device_positions(pos)
        wp.copy(self.state_0.particle_q, src, dest_offset=start, count=n)
        self.state_0.particle_qd[start:start + n].zero_()
        self.solver.positions_set(start, n)
        if self._window:  # the old history is not this state's: forget it
            self._position_history[:, start:start + n].fill_(_FAR)

    @property
    def residual_history(self) -> np.ndarray:
        """Max particle speed [m/s] per frame and world (NaN where the world was frozen), (frames, W)."""
        if not self._history:
            return np.zeros((0, self.model.world_count), dtype=np.float32)
        return np.stack(self._history)
