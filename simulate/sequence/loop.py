"""The frame loop: ``run_sequences`` steps every world through its schedule, frame by frame."""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from simulate.body.base import BodyModel, PosedBody
from simulate.body.kinematics import to_device_async
from simulate.cloth import ClothBuilder, Features
from simulate.contact import BodyCollider
from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus
from simulate.sequence.posing import PosedAhead
from simulate.sequence.routing import Worlds, assign_worlds
from simulate.sequence.schedule import KEY, RECORD, SETTLE, TRANSITION, build_schedule
from simulate.sequence.settings import RecordedFrame, SequenceSettings, SequenceTask
from simulate.sequence.stats import SequenceStats
from simulate.sequence.streams import FrameStreams


def run_sequences(
    body: BodyModel,
    faces: np.ndarray,
    tasks: list[SequenceTask],
    *,
    body_faces: np.ndarray,
    body_face_groups: list[np.ndarray] | None = None,
    body_part: np.ndarray | None = None,
    settings: SequenceSettings,
    device: str,
    on_frame: Callable[[RecordedFrame], object] | None = None,
    on_frames: Callable[[list[RecordedFrame]], list] | None = None,
    on_progress: Callable[[int], None] | None = None,
    stats: dict[str, float] | None = None,
    worlds: int | None = None,
    material_uv: np.ndarray | None = None,
    attached: np.ndarray | None = None,
) -> dict[str, float]:
    """Simulates every task's sequence in the worlds of one batched simulator.

    With ``worlds`` below the task count, worlds take tasks one after another: tasks that can share
    a world (the same cloth rest geometry, start drape, shape and fabric, see ``world_groups``)
    form a group, each group gets worlds in proportion to its target poses (``allocate_worlds``),
    and a world that finishes a task takes its group's next one (in the given order) from its home
    drape, the settled canonical drape on the group's shape; once its group has none left, it takes
    the next task of the group with the most target poses waiting per busy world, that group's
    garment and home drape swapped in (``SequenceSettings.cross_group_tasks``). Worlds whose tasks
    end at different times would otherwise sit idle while the last ones finish, and a frame of a
    few busy worlds costs most of a full one. Which world takes which task depends only on the
    batch, so the result is reproducible.

    Target frames are handed over one simulator frame after their hold ended: while the device steps
    the next frame, ``on_frames`` measures and writes them and the host routes their worlds on (home
    after a rejection, next target, next task) and poses the bodies coming up. Their worlds sit that
    frame out, frozen, so each world passes through the same states as if frames were handed over
    between simulator frames. On CUDA the frames step on a non-blocking stream of their own
    (``SequenceSettings.concurrent_streams``), so the host work runs beside the device's.
    A motion frame (``SequenceTask.motion_steps``) is handed over the same way, but its world does
    not sit out: it steps on towards the next motion frame at once (the answer does not route it).

    Args:
        body: body model (its canonical pose and neutral shape start every world whose task has no
            ``start_shape``; a task with one starts on that shape).
        faces: garment triangles shared by all tasks, (F, 3).
        tasks: the batch.
        body_faces: the body faces the garment can touch (culled), (Fb, 3).
        body_face_groups, body_part: primary collision bodies (``simulate.body.collision_parts``):
            per part the rows of ``body_faces`` in its mesh, and each garment vertex's part (V,);
            None: every vertex meets all of ``body_faces``.
        settings: sequence settings.
        device: Warp device ("cpu", "cuda:0"); the body is posed with torch on it too.
        on_frame: called once per (task, target pose) in visiting order per task; returning
            ``False`` rejects the frame (see ``SequenceSettings.restart_after_rejects``), any other
            value accepts it.
        on_frames: instead of ``on_frame``: called with the list of frames that finished in the same
            simulator frame (one per world; an exploded world's failed targets come in lists of
            their own), returning one answer per frame. Their positions and bodies left the device
            in one copy each, and the caller can measure them together. The frames and answers are
            those ``on_frame`` would get; only the grouping differs.
        on_progress: called after each frame with the number of target poses it finished (often 0).
        stats: a dict to add the statistics to as they accrue (heartbeats of long runs read it; a
            dict that already holds counts, e.g. of earlier batches, keeps adding).
        worlds: worlds of the simulator (default: one per task); at least the number of task groups.
        material_uv: pattern UVs per face corner shared by all tasks, (F, 3, 2) (a template's
            ``face_uv``): the cloth's warp runs up each panel (``ClothBuilder.add_garment``);
            None: the builder's grain axis (+y).
        attached: vertex indices shared by all tasks held to the body by soft springs (a template's
            ``attachment``: the waistband of pants, shorts and skirts; ``attachment_targets``),
            so a garment that only the waist holds up does not slide off a moving body; None or
            empty: none.
    Returns:
        statistics (``stats`` itself when given): the fields of ``SequenceStats`` (frames, world
        frames by entry kind, wall seconds by phase, recoveries and restarts, body-model calls,
        task switches), explosions by cause (exploded_non_finite / _speed / _stretch) and on CUDA
        element_data_copies: the copies of garment data the sweep reads (the batch's distinct
        garments, see ``shared_element_data``). On CUDA the device steps a frame while the host
        delivers the last one's target frames and poses bodies, so sim_s is only the launch and
        the wait left after that work, and body_s / record_s include work done beside a frame in flight.
    """
    if (on_frame is None) == (on_frames is None):
        raise ValueError("run_sequences needs exactly one of on_frame and on_frames")
    if worlds is not None and (int(worlds) != worlds or worlds < 1):
        raise ValueError(f"worlds must be an integer >= 1 (got {worlds!r})")
    run = SequenceStats()
    t_setup = time.perf_counter()
    assignment = assign_worlds(tasks, worlds)
    w_count = len(assignment.first)
    neutral = np.asarray(body.shape_default, np.float32)
    canonical = np.asarray(body.canonical_pose, np.float32)
    schedules = [build_schedule(tasks[t], canonical, neutral, settings) for t in assignment.first]
    t_schedules = time.perf_counter()
    torch_device = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
    poser = body.on_device(torch_device)  # posing on the CPU would cost ~4 ms per body in a GPU run

    def pose_bodies(shapes: np.ndarray, poses: np.ndarray) -> PosedBody:
        """Posed bodies as torch tensors on ``torch_device`` (they stay there: on CUDA the
        collider takes them without a host round trip). The host arrays go in as they are: the
        body model checks them and tells the shapes apart on the host, and the posing is queued
        on the GPU without the host waiting for it."""
        with torch.no_grad():
            return poser.pose_torch(np.asarray(shapes, np.float32), np.asarray(poses, np.float32))

    held = None if attached is None or len(attached) == 0 else np.asarray(attached, np.int64)
    builder = ClothBuilder()
    for t in assignment.first:
        builder.add_garment(tasks[t].rest_vertices, faces, fabric=tasks[t].fabric, material_uv=material_uv,
                            body_part=body_part, attached=held)
    model = builder.finalize(device, features=Features(self_contact=settings.self_contact,
                                                       friction=settings.friction != 0.0))
    t_model = time.perf_counter()
    # each world starts on its first task's start shape (the neutral one, or shape + tightness) in the
    # canonical pose; the start bodies of tasks worlds take later are posed here too (start_bodies)
    start_shapes = np.stack([neutral if tasks[t].start_shape is None else np.asarray(tasks[t].start_shape, np.float32)
                             for t in assignment.first])
    start = pose_bodies(start_shapes, np.tile(canonical, (w_count, 1)))
    start_bodies = starting_bodies(tasks, start, start_shapes, neutral, canonical, pose_bodies)
    collider = BodyCollider(start.vertices.cpu().numpy(), body_faces, device=device, thickness=settings.contact_thickness,
                            face_groups=body_face_groups)
    sim = QuasiStaticSimulator(model, collider, solver=settings.solver, settings=SimSettings(**{**settings.sim.__dict__}))
    for w, t in enumerate(assignment.first):
        sim.set_positions(np.asarray(tasks[t].start_vertices, np.float32), world=w)
    # current body per world, (W, Vb, 3) / (W, J, 4, 4) / (W, Vb, 3) tensors on torch_device
    body_now = {"vertices": start.vertices.clone(), "skin": start.skinning_transforms.clone(),
                "rest": start.rest_vertices.clone()}
    ahead = PosedAhead(pose_bodies, start, w_count, settings.body_lookahead)
    anchors = None if held is None else attachment_anchors(tasks, held, start_bodies, neutral)
    streams = FrameStreams(device, enabled=settings.concurrent_streams)

    def deliver(frames: list[RecordedFrame]) -> list[bool]:
        """Hands frames over (one ``on_frames`` call, or ``on_frame`` per frame); True where accepted."""
        with streams.delivering():  # the callback's device work does not wait for a frame in flight
            if on_frames is None:
                return [on_frame(f) is not False for f in frames]
            answers = list(on_frames(frames))
        if len(answers) != len(frames):
            raise ValueError(f"on_frames must return one answer per frame ({len(frames)}), got {len(answers)}")
        return [a is not False for a in answers]

    ws = Worlds(tasks, assignment, schedules, settings, sim=sim, collider=collider, start=start_bodies, body_now=body_now,
                canonical=canonical, neutral=neutral, torch_device=torch_device, stats=run, deliver=deliver)
    stats = {} if stats is None else stats
    base = run.start(stats)
    t_ready = time.perf_counter()
    run.setup_schedules_s += t_schedules - t_setup
    run.setup_model_s += t_model - t_schedules
    run.setup_simulator_s += t_ready - t_model
    run.setup_s += t_ready - t_setup
    copies = getattr(sim.solver, "element_data_copies", None)  # worlds repeating a garment read one copy
    if copies is not None:
        stats["element_data_copies"] = max(stats.get("element_data_copies", 0), copies)
    causes_before = {f"exploded_{k}": stats.get(f"exploded_{k}", 0) for k in sim.explosion_causes}

    def pose_ahead(idx: np.ndarray | None) -> dict[str, torch.Tensor] | None:
        """Bodies of the worlds in ``idx`` at their current entries (None: only tops up the
        buffers of every world that needs it, ahead of the next frame)."""
        calls, bodies, model_s = ahead.calls, ahead.bodies, ahead.model_s
        if idx is None:
            ahead.prefetch(ws.schedules, ws.ptr, ~ws.done)
            posed = None
        else:
            posed = ahead.get(idx, ws.schedules, ws.ptr, ~ws.done)
        run.body_calls += ahead.calls - calls
        run.bodies_posed += ahead.bodies - bodies
        run.body_model_s += ahead.model_s - model_s
        return posed

    def move_bodies() -> None:
        """The worlds that changed entry get their bodies as the collider's targets and run again."""
        idx = np.nonzero(ws.changed)[0]
        posed = pose_ahead(idx)
        idx_t = to_device_async(idx, torch_device)
        for name in ("vertices", "skin", "rest"):
            body_now[name][idx_t] = posed[name]
        b0 = time.perf_counter()
        collider.set_target(body_now["vertices"])
        if anchors is not None:
            set_attachment_targets(sim.control, anchors, body_now["vertices"], ws.cur)
        run.body_target_s += time.perf_counter() - b0
        sim.restart(ws.changed & ~ws.done)
        ws.changed[:] = False

    # Two frames' work at once: while the device steps frame k+1, the host hands over the target
    # frames whose holds ended in frame k (``on_frames``: filters, inverse skinning, shard writes),
    # acts on the answers (route home, next target, next task) and poses the bodies the worlds need
    # next. A world whose frame is being handed over sits that frame out, frozen (its state does not
    # change), so every world goes through the same states as when frames were handed over between
    # frames; only the simulator frame each state is reached in differs.
    pending: list[tuple[int | None, RecordedFrame]] = []  # (world, frame) of target holds that ended; None: a motion frame

    def hand_over() -> int:
        """Hands the pending frames over (one ``on_frames`` call) and routes their worlds on by
        the answers; returns the number of target poses finished."""
        handed = [w for w, _ in pending]
        f1 = time.perf_counter()
        verdicts = deliver([f for _, f in pending])
        f2 = time.perf_counter()
        run.record_deliver_s += f2 - f1
        pending.clear()
        ws.route(handed, verdicts)
        run.record_route_s += time.perf_counter() - f2
        return len(handed)

    def end_frame(ran: np.ndarray, status: np.ndarray) -> int:
        """Acts on the frame's statuses: exploded worlds recover, transitions move on, ended holds
        keep their states and queue their target frames; returns the target poses finished."""
        busy = np.nonzero(ran)[0]
        kinds_now = np.fromiter((ws.kind(w) for w in busy), dtype=np.int64, count=len(busy))
        run.transition_world_frames += int((kinds_now == TRANSITION).sum())
        run.hold_world_frames += int((kinds_now == KEY).sum())
        run.settle_world_frames += int((kinds_now == SETTLE).sum())
        run.motion_world_frames += int((kinds_now == RECORD).sum())
        finished, ready = 0, []  # ready: worlds whose hold (settle or target pose) ended this frame
        for w in busy:
            st = int(status[w])
            if st == WorldStatus.EXPLODED:
                q0 = time.perf_counter()
                finished += ws.explode(w, st)
                run.recover_s += time.perf_counter() - q0
            elif ws.kind(w) == TRANSITION:
                ws.advance(w)
            elif ws.kind(w) == RECORD:  # a motion frame: recorded after its one frame, at rest or not
                ready.append(w)
            elif st in (WorldStatus.CONVERGED, WorldStatus.MAX_STEPS):
                if ws.held[w] >= settings.min_hold_frames:
                    ready.append(w)
                else:
                    sim.restart([w])  # keep holding the pose
        if ready:  # they leave the device together and are handed over in one call, beside the next frame
            r0 = time.perf_counter()
            positions = sim.worlds_positions(ready)
            moving = any(ws.kind(w) == RECORD for w in ready)
            velocities = sim.worlds_velocities(ready) if moving else None
            run.record_copy_s += time.perf_counter() - r0
            # held targets stay frozen (converged) until handed over; motion worlds move on at once
            pending.extend(ws.end_holds(ready, positions, status, velocities))
            run.record_s += time.perf_counter() - r0
        return finished

    with streams.stepping():
        while not ws.done.all() or pending:
            t0 = time.perf_counter()
            if ws.changed.any():
                move_bodies()
            ran = sim.status == WorldStatus.RUNNING  # the worlds this frame advances
            if not ran.any() and not pending:
                raise RuntimeError("run_sequences stalled: no world is running and no frame is pending "
                                   f"({int((~ws.done).sum())} worlds not done)")
            t1 = time.perf_counter()
            run.body_s += t1 - t0
            if ran.any():
                sim.launch_frame()
            t2 = time.perf_counter()
            finished = 0
            if pending:  # beside the frame in flight
                finished += hand_over()
                t3 = time.perf_counter()
                run.record_s += t3 - t2
                pose_ahead(None)  # the worlds routed on need their next bodies: posed now, not before the next launch
                run.body_prefetch_s += time.perf_counter() - t3
                run.body_s += time.perf_counter() - t3
            if ran.any():
                t4 = time.perf_counter()
                status = sim.finish_frame()
                run.sim_s += time.perf_counter() - t4 + (t2 - t1)
                run.sim_device_s += sim.last_frame_device_s
                run.sim_launch_s += t2 - t1
                run.frames += 1
                run.world_frames += int(ran.sum())
                ws.held[ran] += 1
                finished += end_frame(ran, status)
            run.publish(stats, base)
            if on_progress is not None:  # every frame (also with 0), so heartbeats can fire during long holds
                on_progress(finished)
            run.loop_s += time.perf_counter() - t0
            run.publish(stats, base)
            for k, n in sim.explosion_causes.items():
                stats[f"exploded_{k}"] = causes_before[f"exploded_{k}"] + n
    contact = getattr(sim.solver, "self_contact", None)
    if getattr(contact, "search_counts", None) is not None:
        run.self_contact_substeps, run.self_contact_searches = (int(n) for n in contact.search_counts.numpy().sum(axis=0))
    run.publish(stats, base)
    return stats


def attachment_anchors(tasks: list[SequenceTask], attached: np.ndarray, start_bodies: dict[bytes, tuple],
                       neutral: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each task's attached vertices hang on the body: the nearest body vertex to each
    attached rest vertex on the task's start body (its start shape in the canonical pose, the
    body the garment is sized for) and the offset from it [m]. Returns (anchor (T, A) int64,
    offset (T, A, 3) float32) on the start bodies' device."""
    anchor, offset = [], []
    for t in tasks:
        shape = neutral if t.start_shape is None else np.asarray(t.start_shape, np.float32)
        body = start_bodies[shape.tobytes()][0]
        points = torch.as_tensor(np.asarray(t.rest_vertices, np.float32)[attached], device=body.device)
        k = torch.cdist(points, body.to(points.dtype)).argmin(dim=1)
        anchor.append(k)
        offset.append(points - body[k].to(points.dtype))
    return torch.stack(anchor), torch.stack(offset)


def set_attachment_targets(control, anchors: tuple[torch.Tensor, torch.Tensor], bodies: torch.Tensor,
                           current: np.ndarray) -> None:
    """Every world's attachment targets [m]: its current task's anchor vertices on its body
    ``bodies`` (W, Vb, 3) plus their offsets (``attachment_anchors``); ``current``: each world's
    task (W,). The targets move with the body each time the driver moves it, so the garment is
    held where it was sized to sit."""
    anchor, offset = anchors
    cur = torch.as_tensor(np.asarray(current, np.int64), device=anchor.device)
    idx = anchor[cur]  # (W, A)
    targets = torch.gather(bodies, 1, idx[..., None].expand(-1, -1, 3)).float() + offset[cur]
    control.set_attachment_targets(targets.reshape(-1, 3), check_finite=False)  # posed bodies: no device sync


def starting_bodies(tasks: list[SequenceTask], start: PosedBody, start_shapes: np.ndarray, neutral: np.ndarray,
                    canonical: np.ndarray, pose_bodies: Callable[[np.ndarray, np.ndarray], PosedBody]) -> dict[bytes, tuple]:
    """Each task's start body, by its start shape's bytes: (vertices (Vb, 3), skinning transforms
    (J, 4, 4), rest vertices (Vb, 3)) tensors, the shape (``SequenceTask.start_shape``, or the
    neutral one) in the canonical pose. The worlds' own start bodies ``start`` (posed from
    ``start_shapes``, (W, S)) serve their shapes; the start shapes of tasks no world starts with
    are posed in one more call."""
    bodies: dict[bytes, tuple] = {}
    for w, shape in enumerate(start_shapes):
        bodies.setdefault(np.asarray(shape, np.float32).tobytes(),
                          (start.vertices[w], start.skinning_transforms[w], start.rest_vertices[w]))
    missing = {}
    for t in tasks:
        shape = neutral if t.start_shape is None else np.asarray(t.start_shape, np.float32)
        if shape.tobytes() not in bodies:
            missing.setdefault(shape.tobytes(), shape)
    if missing:
        shapes = np.stack(list(missing.values()))
        posed = pose_bodies(shapes, np.tile(canonical, (len(shapes), 1)))
        for j, key in enumerate(missing):
            bodies[key] = (posed.vertices[j], posed.skinning_transforms[j], posed.rest_vertices[j])
    return bodies
