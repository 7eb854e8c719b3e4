"""Quasi-static sequence driver (seed 000 section 5.3, seed 004 section 3.3).

Each task is one garment style on one body shape visiting a list of target poses.
A world starts on the neutral body in the canonical pose, the body shape is blended
to the task's shape over ``shape_transition_frames`` frames and the garment relaxed,
then the body visits the target poses in the given order; slerp'ed poses are
inserted where any joint would turn more than ``interpolation_threshold`` in one
frame (one frame each), and every target pose is held until the world converges
(or hits ``max_relax_frames``), when the frame is handed to ``on_frame`` (or, with the
other worlds' frames that finished with it, to ``on_frames``). A world whose
frames ``on_frame`` rejects (``restart_after_rejects``), or that keeps exploding, goes back home
(its drape at the end of the settle) and heads for its next target from the canonical pose; with
``restart_to="last_kept"`` a rejecting world goes back to its last accepted frame instead.

Many tasks run as parallel worlds of one simulator. Worlds follow their own
schedules; a world whose current entry is done moves on without waiting for the
others, and a world whose schedule is finished is frozen. Nothing couples worlds but
the float rounding of the batched body model (a body posed in another company can differ by
an ulp, and a hold may then stop a frame earlier or later), so callers that need bitwise
reproducible frames keep each task's batch the same (generate-dataset does).
"""
from __future__ import annotations

import hashlib
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from simulate.body.base import BodyModel, PosedBody
from simulate.body.kinematics import to_device_async
from simulate.cloth import ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus
from simulate.contact import BodyCollider
from simulate.poses import interpolate_segments, interpolate_sequence, segment_key_index

SELF_CONTACT_DURING = ("all", "transitions", "holds")  # SequenceSettings.self_contact_during

# Entry kinds of a world's schedule.
TRANSITION = 0  # one frame toward an intermediate body (shape blend or slerp'ed pose)
SETTLE = 1  # hold until converged, not recorded (after the shape transition)
KEY = 2  # hold until converged, then record

#: Where a world goes after rejected frames (``SequenceSettings.restart_to``).
RESTART_TO = ("home", "last_kept")


@dataclass
class SequenceTask:
    """One garment on one body shape through a pose list.

    Attributes:
        rest_vertices: cloth rest geometry (edge lengths, areas) [m], shape (V, 3).
        start_vertices: initial positions on the neutral body, canonical pose [m], (V, 3).
        shape: body shape, (S,).
        poses: target poses in visiting order, (N, 60).
        fabric: fabric preset name or Fabric.
    """

    rest_vertices: np.ndarray
    start_vertices: np.ndarray
    shape: np.ndarray
    poses: np.ndarray
    fabric: object = "cotton"


@dataclass
class SequenceSettings:
    """Stepping of the sequence (see the module docstring)."""

    sim: SimSettings = field(default_factory=SimSettings)
    solver: str = "xpbd"
    shape_transition_frames: int = 10
    interpolation_threshold: float = 0.1
    min_hold_frames: int = 2
    contact_thickness: float = 0.004
    friction: float | None = None
    self_contact: bool = False
    self_contact_during: str = "all"
    """With ``self_contact``: "all" frames; only "transitions" (a world searches for self-contacts
    while its body moves between poses: shape blends, slerp'ed poses, routes home; its holds relax
    without); or only "holds" (target poses and the settles, not the moves). On a CPU slice (7.7k
    t-shirt, 60 targets) self-contact on all frames halved the self-intersection drops (24 -> 12)
    and "transitions" left them at 24: the layers cross while a pose is held."""
    recover_explosions: bool = True
    """A world that explodes loses only the target pose it was heading to: its last good state
    (garment and body at the previous finished hold) is put back and the world goes on to the
    next target, slerp'ed afresh from there. Off: the rest of its schedule is handed over as failed."""
    restart_after_explosions: int = 2
    """After this many explosions of a world in a row (its last good state led into an explosion
    again), the world starts over from the canonical drape (shape transition, settle, then the
    next target) instead of the last good state. A CPU slice of the TailorNet spec (7.7k t-shirt,
    30-pose tasks) lost 14 targets in a row in one world, each retried from the same state; on a
    1.8k slice (3+1 pairs, 231 targets, CPU) 2 instead of never cut explosions from 22 to 7 and
    raised the kept frames from 40 to 57 at the same simulation time. 0 = never. A world that has
    come home (see ``restart_after_rejects``) starts over from there instead."""
    restart_after_rejects: int = 0
    """After this many target frames in a row that ``on_frame`` rejects (returns ``False``: the
    frame failed the dataset's filters), the world goes home: back to its settled canonical drape
    on the task's shape (kept when the settle hold ended), from where it heads for its next target
    along a slerp from the canonical pose. Without it a tangle is carried along the rest of the
    sequence: on the H200 full-width run of the TailorNet spec (7.7k t-shirt, 30-pose tasks) the
    first target of each world kept 64 % of its frames, targets 20-29 kept 12 %; self-intersection
    and distortion grew with the position in the sequence, not with any joint angle. 0 = never."""
    restart_to: str = "home"
    """Where a world goes after ``restart_after_rejects`` rejected frames: "home" (its settled
    canonical drape, then a slerp from the canonical pose) or "last_kept" (the garment and body of
    its last accepted target frame, then a slerp from that pose: a shorter way to the next target,
    from a state that passed the filters; home while the world has accepted none). At full width
    on the H200 (TailorNet spec, 6,700 targets) "last_kept" kept 40.5 % of the targets against
    47.2 % for "home", and saved only 0.6 of 12.8 moving frames per target: a frame that passed
    the filters can still carry the start of a tangle."""
    home_between_targets: bool = False
    """Every world goes home (its settled canonical drape) after each target frame, accepted or
    not, and heads for its next target from the canonical pose: each target is reached along a
    slerp from the canonical pose instead of from the previous target (no tangle is carried from
    one target to the next, at the price of longer moves)."""
    body_lookahead: int = 8
    """Schedule entries per world posed ahead; whenever a world runs out, every world short of
    entries is topped up in the same batched body-model call (an H200 run of 240 worlds made 555
    calls in 876 frames instead of one per frame). Memory: world_count x lookahead posed bodies
    (~0.34 MB each for anny)."""

    cross_group_tasks: bool = True
    """A world whose group (``world_groups``) has no task left takes the next task of the group
    with the most target poses waiting per busy world: that group's garment (rest shape, fabric:
    ``QuasiStaticSimulator.adopt_garment``), shape and settled home drape are swapped in, and the
    task runs as it would in a world of its own group (tested bit for bit). Without it a group's
    worlds wait idle once its tasks run out while others still queue (the full TailorNet spec
    on an H200: the last ~5 % of its targets took ~120 s of the 513 with ~9 worlds busy)."""
    concurrent_streams: bool = True
    """On CUDA, frames step on a stream of their own while the host hands the previous frame's
    target frames over (``on_frames``) and poses the next bodies beside them (see ``run_sequences``).
    Off: every launch goes to the device's stream, in the same order, so the results are the same
    bit for bit (a check for the streams' synchronisation); only slower."""

    def __post_init__(self) -> None:
        if self.restart_to not in RESTART_TO:
            raise ValueError(f"SequenceSettings.restart_to must be one of {', '.join(RESTART_TO)} (got {self.restart_to!r})")
        if self.self_contact_during not in SELF_CONTACT_DURING:
            raise ValueError(f"SequenceSettings.self_contact_during must be one of {', '.join(SELF_CONTACT_DURING)} "
                             f"(got {self.self_contact_during!r})")


@dataclass
class RecordedFrame:
    """What ``on_frame`` receives for a target pose that finished relaxing.

    Attributes:
        task: index of the task in the batch.
        key: index of the target pose in the task's pose list.
        positions: garment vertices [m], (V, 3).
        status: WorldStatus of the world (CONVERGED, MAX_STEPS or EXPLODED).
        frames: frames the pose was held.
        body_vertices: posed body [m], (Vb, 3).
        skinning_transforms: (J, 4, 4); rest_vertices: shaped unposed body (Vb, 3).
    """

    task: int
    key: int
    positions: np.ndarray
    status: int
    frames: int
    body_vertices: np.ndarray
    skinning_transforms: np.ndarray
    rest_body_vertices: np.ndarray


def _schedule(task: SequenceTask, canonical_pose: np.ndarray, neutral_shape: np.ndarray, s: SequenceSettings,
              first_key: int = 0):
    """(shapes (M,S), poses (M,60), kinds (M,), key index (M,)) of one world: from the canonical
    drape, shape transition, settle, then the target poses from ``first_key`` on."""
    n = s.shape_transition_frames
    blend = (np.arange(1, n + 1) / n)[:, None]
    shapes = [neutral_shape[None] * (1 - blend) + task.shape[None] * blend, task.shape[None]]
    poses = [np.tile(canonical_pose, (n, 1)), canonical_pose[None]]
    kinds = [np.full(n, TRANSITION), np.array([SETTLE])]
    keys = [np.full(n, -1), np.array([-1])]
    visit = _visit_entries(task, first_key, canonical_pose, s.interpolation_threshold)
    out = [np.concatenate([*part, v]) for part, v in zip((shapes, poses, kinds, keys), visit)]
    return out[0].astype(np.float32), out[1].astype(np.float32), out[2], out[3]


def _visit_entries(task: SequenceTask, first_key: int, start_pose: np.ndarray, threshold: float,
                   stop: int | None = None):
    """Schedule entries visiting ``task.poses[first_key:stop]`` from ``start_pose``: (shapes (M,S),
    poses (M,60), kinds (M,), key index into ``task.poses`` (M,), -1 for slerp'ed poses)."""
    seq, key_index = interpolate_sequence(task.poses[first_key:stop], start_pose, threshold)
    return _entries(task, seq, key_index, first_key)


def _entries(task: SequenceTask, seq: np.ndarray, key_index: np.ndarray, first_key: int = 0):
    """Schedule entries of the poses ``seq`` (M, 60) on the task's shape: target ``key_index +
    first_key`` where ``key_index >= 0``, a slerp'ed transition pose elsewhere."""
    return (np.tile(task.shape, (len(seq), 1)).astype(np.float32), seq.astype(np.float32),
            np.where(key_index >= 0, KEY, TRANSITION), np.where(key_index >= 0, key_index + first_key, -1))


def _reroute(task: SequenceTask, schedule, next_key: int, start_pose: np.ndarray, threshold: float,
             route: np.ndarray | None = None):
    """``schedule`` re-planned from ``start_pose``: slerp'ed poses to target ``next_key``, then the
    entries that already follow that target (interpolation is sequential, so they are what a full
    re-plan gives; re-planning a 30-pose task from scratch took ~18 ms, this ~0.5 ms). ``route``:
    the poses from ``start_pose`` to the target, ending with it, when already known (M, 60)."""
    _, _, kinds, keys = schedule
    j = int(np.nonzero((kinds == KEY) & (keys == next_key))[0][0])
    if route is None:
        head = _visit_entries(task, next_key, start_pose, threshold, stop=next_key + 1)
    else:  # the route's last pose is the target
        head = _entries(task, np.asarray(route, np.float32), np.arange(len(route)) - (len(route) - 1), next_key)
    return tuple(np.concatenate([h.astype(old.dtype), old[j + 1:]]) for h, old in zip(head, schedule))


def _plans_from(tasks: list[SequenceTask], start_poses: list[np.ndarray],
                threshold: float) -> list[tuple[tuple, list[np.ndarray]]]:
    """Per task, from its start pose: the schedule visiting all its targets (``_visit_entries``
    from the first) and, for every target, the slerp'ed poses from the start pose to it, ending
    with it (the route ``_reroute`` inserts), all segments of all tasks interpolated in one batched
    call (one call per task cost ~10-80 ms on the device machine; each segment is interpolated on
    its own, so a task's plan does not depend on the others in the call)."""
    if not tasks:
        return []
    starts, ends = [], []
    for t, p in zip(tasks, start_poses):
        start = np.asarray(p, np.float32).reshape(1, -1)
        keys = np.asarray(t.poses, np.float32)
        starts += [np.concatenate([start, keys[:-1]]), np.broadcast_to(start, keys.shape)]  # visit; routes
        ends += [keys, keys]
    starts, ends = np.concatenate(starts), np.concatenate(ends)
    poses, segment = interpolate_segments(starts, ends, threshold)
    bounds = np.searchsorted(segment, np.arange(len(ends) + 1))
    out, first = [], 0
    for t in tasks:
        n = len(t.poses)
        a, b = bounds[first], bounds[first + n]
        visit = _entries(t, poses[a:b], segment_key_index(segment[a:b] - first))
        first += n
        out.append((visit, [poses[a:b] for a, b in zip(bounds[first:first + n], bounds[first + 1:first + n + 1])]))
        first += n
    return out


def world_groups(tasks: list[SequenceTask]) -> list[int]:
    """Group index of each task: tasks with the same cloth rest geometry, start drape, body shape
    and fabric can follow each other in one world (numbered in order of first appearance)."""
    seen: dict[bytes, int] = {}
    groups = []
    for t in tasks:
        h = hashlib.sha1()
        for a in (t.rest_vertices, t.start_vertices, t.shape):
            arr = np.ascontiguousarray(a, dtype=np.float32)
            h.update(str(arr.shape).encode())
            h.update(arr.tobytes())
        h.update(repr(t.fabric).encode())
        groups.append(seen.setdefault(h.digest(), len(seen)))
    return groups


def allocate_worlds(group_poses: list[int], group_tasks: list[int], worlds: int) -> list[int]:
    """Worlds per group: one each, then one at a time to the group with the most target poses per
    world (D'Hondt), never more than a group has tasks.

    Args:
        group_poses: target poses of each group's tasks together.
        group_tasks: tasks in each group.
        worlds: worlds to share out (at least one per group).
    Returns:
        worlds per group; the sum is ``min(worlds, sum(group_tasks))``.
    """
    if worlds < len(group_poses):
        raise ValueError(f"worlds ({worlds}) must be at least the number of task groups ({len(group_poses)}): "
                         "tasks of different garments or shapes cannot share a world")
    share = [1] * len(group_poses)
    for _ in range(min(worlds, sum(group_tasks)) - len(share)):
        g = max((g for g in range(len(share)) if share[g] < group_tasks[g]),
                key=lambda g: (group_poses[g] / share[g], -g))
        share[g] += 1
    return share


class _PosedAhead:
    """Posed bodies of each world's next ``depth`` schedule entries, filled in one batched
    body-model call for all worlds that ran past theirs.

    Buffers on the body's torch device: vertices (W, depth, Vb, 3) [m], skin (W, depth, J, 4, 4),
    rest (W, depth, Vb, 3) [m]. A world's buffer belongs to one schedule object; a new schedule
    (after an explosion recovery) refills it.
    """

    def __init__(self, pose_fn: Callable[[np.ndarray, np.ndarray], PosedBody], template: PosedBody,
                 world_count: int, depth: int):
        if depth < 1:
            raise ValueError(f"body_lookahead must be >= 1 (got {depth!r})")
        self.pose_fn, self.depth = pose_fn, int(depth)
        self.buffers = {name: getattr(template, attr).new_zeros((world_count, self.depth, *getattr(template, attr).shape[1:]))
                        for name, attr in (("vertices", "vertices"), ("skin", "skinning_transforms"),
                                           ("rest", "rest_vertices"))}
        self.first = np.full(world_count, -1, dtype=np.int64)  # schedule index of slot 0
        self.count = np.zeros(world_count, dtype=np.int64)
        self.owner: list[object] = [None] * world_count  # the schedule the slots were posed for
        self.calls = 0
        self.bodies = 0  # bodies posed
        self.model_s = 0.0  # wall seconds in the body model

    def get(self, idx: np.ndarray, schedules: list, ptr: np.ndarray, active: np.ndarray) -> dict[str, torch.Tensor]:
        """Posed bodies of entry ``ptr[w]`` of ``schedules[w]`` for each world in ``idx``:
        {"vertices": (n, Vb, 3), "skin": (n, J, 4, 4), "rest": (n, Vb, 3)}.

        When a world in ``idx`` has run past its buffer, every ``active`` world with less than
        half a buffer left ahead is refilled in the same call: worlds advance at their own pace,
        so refilling only the one that ran out would call the body model almost every frame."""
        stale = self._stale(idx, schedules, ptr)
        if stale:
            self._fill(sorted(set(stale) | set(self._low(schedules, ptr, active))), schedules, ptr)
        device = self.buffers["vertices"].device
        w_t = to_device_async(np.asarray(idx, np.int64), device)
        slot_t = to_device_async(ptr[idx] - self.first[idx], device)
        return {name: buf[w_t, slot_t] for name, buf in self.buffers.items()}

    def prefetch(self, schedules: list, ptr: np.ndarray, active: np.ndarray) -> None:
        """Fills, in one body-model call, the buffer of every ``active`` world that holds none of
        its current entries (a new schedule, or run past) or less than half a buffer ahead, so the
        next ``get`` finds them posed (the frame loop calls this while a frame is in flight)."""
        worlds = set(self._stale(np.nonzero(active)[0], schedules, ptr)) | set(self._low(schedules, ptr, active))
        if worlds:
            self._fill(sorted(worlds), schedules, ptr)

    def _stale(self, worlds, schedules: list, ptr: np.ndarray) -> list[int]:
        """Worlds of ``worlds`` whose buffer holds no body for their current entry (a new schedule,
        or run past)."""
        return [int(w) for w in worlds if self.owner[w] is not schedules[w]
                or not self.first[w] <= ptr[w] < self.first[w] + self.count[w]]

    def _low(self, schedules: list, ptr: np.ndarray, active: np.ndarray) -> list[int]:
        """``active`` worlds with less than half a buffer posed ahead and more of the schedule to pose."""
        left = self.first + self.count - ptr  # buffered entries from ptr on
        return [int(w) for w in np.nonzero(active & (left < (self.depth + 1) // 2))[0]
                if self.owner[w] is schedules[w] and self.first[w] + self.count[w] < len(schedules[w][0])]

    def _fill(self, worlds: list[int], schedules: list, ptr: np.ndarray) -> None:
        spans = [(w, int(ptr[w]), min(int(ptr[w]) + self.depth, len(schedules[w][0]))) for w in worlds]
        shapes = np.concatenate([schedules[w][0][a:b] for w, a, b in spans])
        poses = np.concatenate([schedules[w][1][a:b] for w, a, b in spans])
        t0 = time.perf_counter()
        posed = self.pose_fn(shapes, poses)
        self.model_s += time.perf_counter() - t0
        self.calls += 1
        self.bodies += len(shapes)
        w_idx = np.concatenate([np.full(b - a, w) for w, a, b in spans])
        slot = np.concatenate([np.arange(b - a) for _, a, b in spans])
        device = self.buffers["vertices"].device
        w_t, slot_t = to_device_async(w_idx, device), to_device_async(slot, device)  # no wait for the posing just queued
        for name, value in (("vertices", posed.vertices), ("skin", posed.skinning_transforms), ("rest", posed.rest_vertices)):
            self.buffers[name][w_t, slot_t] = value
        for w, a, b in spans:
            self.first[w], self.count[w], self.owner[w] = a, b - a, schedules[w]


class _FrameStreams:
    """Where the frame loop's device work goes. On CUDA the simulator's frames run on a stream of
    their own that does not synchronize with the CUDA default stream, which torch uses (body
    posing, inverse skinning): host work between frames then runs beside a frame in flight
    instead of waiting behind it, and ``delivering`` puts the frame callback's Warp work (the
    quality filters) on the stream that was current when the loop began, which does not wait for
    the frame either. Everything that touches the simulator's or the collider's state stays on the
    stepping stream, so it is ordered after the frame in flight. On the CPU both contexts do nothing
    (Warp's CPU launches run to completion)."""

    def __init__(self, device: str, *, enabled: bool = True) -> None:
        import warp as wp

        self._wp = wp
        dev = wp.get_device(device)
        self.enabled = bool(enabled and dev.is_cuda and torch.cuda.is_available())
        if self.enabled:
            self._torch_stream = torch.cuda.Stream(device=torch.device("cuda", dev.ordinal))  # non-blocking
            self.step_stream = wp.stream_from_torch(self._torch_stream)
            self.deliver_stream = dev.stream

    @contextmanager
    def stepping(self):
        """The frame loop: the stepping stream is current (it first waits for the work queued
        before on the device's stream) and, on leaving, the host waits for it."""
        if not self.enabled:
            yield
            return
        wp = self._wp
        with wp.ScopedStream(self.step_stream):
            try:
                yield
            finally:
                wp.synchronize_stream(self.step_stream)

    @contextmanager
    def delivering(self):
        """Frame callbacks: Warp work goes to the delivery stream, not behind the frame in flight
        (the callback gets host arrays; nothing of it depends on the stepping stream)."""
        if not self.enabled:
            yield
            return
        with self._wp.ScopedStream(self.deliver_stream, sync_enter=False):
            yield


def run_sequences(
    body: BodyModel,
    faces: np.ndarray,
    tasks: list[SequenceTask],
    *,
    body_faces: np.ndarray,
    settings: SequenceSettings,
    device: str,
    on_frame: Callable[[RecordedFrame], object] | None = None,
    on_frames: Callable[[list[RecordedFrame]], list] | None = None,
    on_progress: Callable[[int], None] | None = None,
    stats: dict[str, float] | None = None,
    worlds: int | None = None,
    material_uv: np.ndarray | None = None,
) -> dict[str, float]:
    """Simulates every task's sequence in the worlds of one batched simulator.

    With ``worlds`` below the task count, worlds take tasks one after another: tasks that can share
    a world (the same cloth rest geometry, start drape, shape and fabric, see ``world_groups``)
    form a group, each group gets worlds in proportion to its target poses (``allocate_worlds``),
    and a world that finishes a task takes its group's next one (in the given order) from its home
    drape, the settled canonical drape on the group's shape; once its group has none left, it takes
    the next task of the group with the most target poses waiting per busy world, that group's
    garment and home drape swapped in (``SequenceSettings.cross_group_tasks``). Worlds whose tasks end at different
    times would otherwise sit idle while the last ones finish, and a frame of a few busy worlds
    costs most of a full one (7.7k t-shirts on an H100: 23 ms per frame for 30 worlds, 38 ms for
    240). Which world takes which task depends only on the batch, so the result is reproducible.

    Target frames are handed over one simulator frame after their hold ended: while the device steps
    the next frame, ``on_frames`` measures and writes them and the host routes their worlds on (home
    after a rejection, next target, next task) and poses the bodies coming up. Their worlds sit that
    frame out, frozen, so each world passes through the same states as if frames were handed over
    between simulator frames. On CUDA the frames step on a non-blocking stream of their own
    (``SequenceSettings.concurrent_streams``): on the full TailorNet spec (H100, 256 worlds) the
    steady rate went from 99 to 137 target poses/s, where the host work between frames had been
    half of the loop.

    Args:
        body: body model (its canonical pose and neutral shape start every world).
        faces: garment triangles shared by all tasks, (F, 3).
        tasks: the batch.
        body_faces: the body faces the garment can touch (culled), (Fb, 3).
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
    Returns:
        statistics: frames simulated, world_frames (frames summed over the worlds still
            busy: the work a perfectly packed batch would do) and their split into
            transition_world_frames (shape blends, slerp'ed poses, routes home), hold_world_frames
            (holding target poses) and settle_world_frames (settling after the shape blend), wall seconds in the simulation /
            body / record / explosion-recovery phases and in the whole loop (loop_s; the rest is
            bookkeeping and ``on_progress``; on CUDA the device steps a frame while the host delivers
            the last one's target frames and poses bodies, so sim_s is only the launch and the wait
            left after that work (sim_launch_s: the launch alone), and body_s / record_s include work
            done beside a frame in flight), before the loop (setup_s: visiting orders and routes
            setup_schedules_s, the batched cloth model setup_model_s, start bodies, collider and
            simulator setup_simulator_s), explosion recoveries, batched body-model calls
            (body_calls) with the bodies they posed (bodies_posed) and their wall time (body_model_s),
            parts of the record phase (record_copy_s: positions off the device, record_frames_s: the
            frames' bodies off the device, record_deliver_s: ``on_frames``/``on_frame``,
            record_route_s: routing the delivered frames' worlds on or home; the rest keeps the
            states of holds that ended), parts of the body phase (body_target_s: the collider's
            targets, body_prefetch_s: posing ahead beside a frame in flight), explosions by cause (exploded_non_finite / _speed / _stretch) (``stats``
            itself when given), and on CUDA element_data_copies: the copies of garment data the
            sweep reads (the batch's distinct garments, see ``shared_element_data``); task_switches
            (a world taking a queued task) and group_switches (of them, tasks of another group).
    """
    if (on_frame is None) == (on_frames is None):
        raise ValueError("run_sequences needs exactly one of on_frame and on_frames")
    if worlds is not None and (int(worlds) != worlds or worlds < 1):
        raise ValueError(f"worlds must be an integer >= 1 (got {worlds!r})")
    t_setup = time.perf_counter()
    group_of_task = world_groups(tasks)
    n_groups = max(group_of_task, default=-1) + 1
    members = [[i for i, g in enumerate(group_of_task) if g == k] for k in range(n_groups)]
    share = allocate_worlds([sum(len(tasks[i].poses) for i in m) for m in members], [len(m) for m in members],
                            len(tasks) if worlds is None else int(worlds))
    # worlds go to the first tasks of each group in the given order (with a world per task, world w
    # runs task w); the rest wait in their group's queue
    quota, first = list(share), []
    queues: list[deque] = [deque() for _ in members]  # each group's tasks not yet started, in the given order
    for i, g in enumerate(group_of_task):
        if quota[g] > 0:
            quota[g] -= 1
            first.append(i)
        else:
            queues[g].append(i)
    cur = np.array(first, dtype=np.int64)  # task each world runs
    group = np.array([group_of_task[i] for i in first], dtype=np.int64)  # group of each world
    # the first world of each group: it keeps the group's garment while the group has tasks queued
    group_source = {int(g): w for w, g in reversed(list(enumerate(group)))}
    group_home: dict[int, dict] = {}  # each group's settled canonical drape, from its first settle
    w_count = len(cur)
    neutral = np.asarray(body.shape_default, np.float32)
    canonical = np.asarray(body.canonical_pose, np.float32)
    schedules = [_schedule(tasks[t], canonical, neutral, settings) for t in cur]
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

    builder = ClothBuilder()
    for t in cur:
        builder.add_garment(tasks[t].rest_vertices, faces, fabric=tasks[t].fabric, material_uv=material_uv)
    features = Features(self_contact=settings.self_contact, friction=settings.friction != 0.0)
    model = builder.finalize(device, features=features)
    t_model = time.perf_counter()
    start = pose_bodies(np.tile(neutral, (w_count, 1)), np.tile(canonical, (w_count, 1)))
    collider = BodyCollider(start.vertices.cpu().numpy(), body_faces, device=device, thickness=settings.contact_thickness)
    sim_settings = SimSettings(**{**settings.sim.__dict__})
    sim = QuasiStaticSimulator(model, collider, solver=settings.solver, settings=sim_settings)
    for w, t in enumerate(cur):
        sim.set_positions(np.asarray(tasks[t].start_vertices, np.float32), world=w)

    ptr = np.zeros(w_count, dtype=np.int64)
    held = np.zeros(w_count, dtype=np.int64)
    done = np.zeros(w_count, dtype=bool)
    # current body per world, (W, Vb, 3) / (W, J, 4, 4) / (W, Vb, 3) tensors on torch_device
    body_now: dict[str, torch.Tensor] = {
        "vertices": start.vertices.clone(), "skin": start.skinning_transforms.clone(), "rest": start.rest_vertices.clone()}

    def frames_of(worlds: list[int], keys: list[int], positions: np.ndarray, statuses: list[int]) -> list[RecordedFrame]:
        """Frames of ``worlds`` at their current bodies, positions (n, V, 3) [m]: each body tensor
        leaves the device once for all of them (indexing copies, so the next frames cannot alias them)."""
        idx_t = to_device_async(np.asarray(worlds, np.int64), torch_device)
        body = {name: body_now[name][idx_t].cpu().numpy() for name in ("vertices", "skin", "rest")}
        return [RecordedFrame(int(cur[w]), int(k), positions[j], int(st), int(held[w]), body["vertices"][j], body["skin"][j],
                              body["rest"][j]) for j, (w, k, st) in enumerate(zip(worlds, keys, statuses))]

    def frame_of(w: int, key: int, positions: np.ndarray, st: int) -> RecordedFrame:
        return frames_of([w], [key], positions[None], [st])[0]

    def deliver(frames: list[RecordedFrame]) -> list[bool]:
        """Hands frames over (one ``on_frames`` call, or ``on_frame`` per frame); True where accepted."""
        with streams.delivering():  # the callback's device work does not wait for a frame in flight
            if on_frames is None:
                return [on_frame(f) is not False for f in frames]
            answers = list(on_frames(frames))
        if len(answers) != len(frames):
            raise ValueError(f"on_frames must return one answer per frame ({len(frames)}), got {len(answers)}")
        return [a is not False for a in answers]

    def advance(w: int) -> None:
        """World ``w`` moves on to its next schedule entry (or is done)."""
        ptr[w] += 1
        held[w] = 0
        if ptr[w] >= len(schedules[w][2]):
            finish(w)
        else:
            changed[w] = True

    def busiest_group() -> int | None:
        """The group with the most target poses queued per busy world, among those whose home
        drape is known (None: no task waits anywhere, or cross-group tasks are off)."""
        if not settings.cross_group_tasks:
            return None
        busy = np.bincount(group[~done], minlength=n_groups)
        waiting = [(sum(len(tasks[i].poses) for i in queues[k]) / max(int(busy[k]), 1), -k)
                   for k in range(n_groups) if queues[k] and k in group_home]
        return -max(waiting)[1] if waiting else None

    def finish(w: int) -> None:
        """World ``w`` is through its task: it takes its group's next task, or another group's
        (``SequenceSettings.cross_group_tasks``), or is done."""
        if not queues[group[w]]:
            k = busiest_group()
            if k is None:
                done[w] = True
                return
            sim.adopt_garment(w, group_source[k])  # a world that holds group k's garment
            group[w] = k
            home[w] = group_home[k]
            stats["group_switches"] += 1
        cur_before = cur[w]
        t = cur[w] = queues[group[w]].popleft()
        stats["task_switches"] += 1
        streak[w] = rejects[w] = 0
        last_kept[w] = None
        drop_plans(int(cur_before))
        if home[w] is not None:  # from the settled drape: a slerp from the canonical pose to the first target
            put_back(w, home[w])
            last_good[w] = home[w]
            schedules[w] = plan_of(w, t)[0]
        else:  # never settled (exploded on the way): from the canonical drape, as at the start
            put_back(w, {"positions": np.asarray(tasks[t].start_vertices, np.float32), "vertices": start.vertices[w],
                         "skin": start.skinning_transforms[w], "rest": start.rest_vertices[w]})
            last_good[w] = None
            schedules[w] = _schedule(tasks[t], canonical, neutral, settings)
        ptr[w] = 0
        changed[w] = True

    ahead = _PosedAhead(pose_bodies, start, w_count, settings.body_lookahead)
    streams = _FrameStreams(device, enabled=settings.concurrent_streams)
    stats = {} if stats is None else stats
    for k in ("frames", "world_frames", "transition_world_frames", "hold_world_frames", "settle_world_frames",
              "sim_s", "sim_launch_s", "body_s", "record_s", "recover_s", "loop_s", "recoveries", "body_calls", "bodies_posed", "body_model_s",
              "record_copy_s", "record_frames_s", "record_deliver_s", "record_route_s", "body_target_s",
              "body_prefetch_s", "plan_calls", "setup_s", "group_switches", "homecomings",
              "setup_schedules_s", "setup_model_s", "setup_simulator_s", "task_switches"):
        stats.setdefault(k, 0)
    t_ready = time.perf_counter()
    stats["setup_schedules_s"] += t_schedules - t_setup
    stats["setup_model_s"] += t_model - t_schedules
    stats["setup_simulator_s"] += t_ready - t_model
    stats["setup_s"] += t_ready - t_setup
    copies = getattr(sim.solver, "element_data_copies", None)  # worlds repeating a garment read one copy
    if copies is not None:
        stats["element_data_copies"] = max(stats.get("element_data_copies", 0), copies)
    causes_before = {f"exploded_{k}": stats.get(f"exploded_{k}", 0) for k in sim.explosion_causes}
    last_good: list[dict | None] = [None] * w_count
    streak = np.zeros(w_count, dtype=np.int64)  # explosions in a row per world
    changed = np.ones(w_count, dtype=bool)
    stats.setdefault("restarts", 0)
    stats.setdefault("restarts_after_rejects", 0)
    home: list[dict | None] = [None] * w_count  # settled canonical drape on the task's shape
    rejects = np.zeros(w_count, dtype=np.int64)  # rejected target frames in a row per world

    def put_back(w: int, state: dict) -> None:
        """Puts world ``w``'s body and garment back at a saved state (held from frame 0 again).
        The state's body and garment go to the device once, at its first trip back, and stay
        there: a home state serves thousands of trips, each then only device-side copies."""
        for name in ("vertices", "skin", "rest"):
            body_now[name][w] = state[name]
        if "placed" not in state:
            state["placed"] = (collider.compact_world(state["vertices"]), sim.device_positions(state["positions"]))
        collider.place_world(w, state["placed"][0])
        sim.revive(w, state["placed"][1])
        held[w] = 0

    # (task, home pose) -> (schedule visiting the task's targets, routes to each target), both from
    # the home pose: planned in batches, dropped when the task is done
    plans: dict[tuple[int, bytes], tuple] = {}

    def plan_of(w: int, t: int) -> tuple:
        """Task ``t``'s plan from world ``w``'s home pose. A missing plan is made in one batched call
        with those of every busy world's task and every group's next task that lack one (worlds
        change tasks and go home thousands of times; one call per task cost ~10-80 ms)."""
        pose = np.asarray(home[w]["pose"], np.float32)
        key = (int(t), pose.tobytes())
        if key not in plans:
            wanted = [int(t)] + [int(cur[v]) for v in range(w_count) if not done[v]] + [int(q[0]) for q in queues if q]
            batch = [u for u in dict.fromkeys(wanted) if (u, key[1]) not in plans]
            for u, plan in zip(batch, _plans_from([tasks[u] for u in batch], [pose] * len(batch),
                                                   settings.interpolation_threshold)):
                plans[(u, key[1])] = plan
            stats["plan_calls"] += 1
        return plans[key]

    def drop_plans(t: int) -> None:
        for key in [k for k in plans if k[0] == t]:
            del plans[key]
    last_kept: list[dict | None] = [None] * w_count  # state at the last accepted target frame
    stats.setdefault("restarts_to_last_kept", 0)

    restart_to_kept = settings.restart_to == "last_kept"

    def restart_from(w: int, state: dict, next_key: int, route: np.ndarray | None = None) -> None:
        """Puts world ``w`` back at a saved ``state``, heading for target ``next_key`` from its pose
        (the caller knows that target exists); ``route``: the slerp'ed poses there, when known."""
        put_back(w, state)
        last_good[w] = state
        schedules[w] = _reroute(tasks[cur[w]], schedules[w], next_key, state["pose"], settings.interpolation_threshold,
                                route=route)
        ptr[w] = 0
        changed[w] = True

    def go_home(w: int, next_key: int) -> None:
        """Puts world ``w`` back at its home state, heading for target ``next_key`` from the
        canonical pose along the route planned with its task's plan (``plan_of``)."""
        restart_from(w, home[w], next_key, route=plan_of(w, cur[w])[1][next_key])

    def handle_explosion(w: int, st: int) -> int:
        """Hands the failed target pose(s) of exploded world ``w`` to ``on_frame`` and, when it
        can, puts the world back at its last good state heading for the next target (or, after
        ``restart_after_explosions`` explosions in a row or before any good state, back at the
        canonical drape). Returns the number of target poses handed over."""
        _, _, kinds_w, keys_w = schedules[w]
        failed = np.nonzero(kinds_w[ptr[w]:] == KEY)[0]
        can_restart = settings.restart_after_explosions > 0
        if settings.recover_explosions and (last_good[w] is not None or can_restart) and len(failed):
            # lose only the target being approached or held, then resume from the last good state
            j = ptr[w] + int(failed[0])
            deliver([frame_of(w, keys_w[j], sim.world_positions(w), st)])
            stats["recoveries"] += 1
            streak[w] += 1
            next_key = int(keys_w[j]) + 1
            over = last_good[w] is None or (can_restart and settings.restart_after_explosions <= streak[w])
            task = tasks[cur[w]]
            if over and home[w] is not None and next_key < len(task.poses):  # start over from home
                streak[w] = 0
                stats["restarts"] += 1
                go_home(w, next_key)
                return 1
            if over:  # the last good state keeps leading into explosions: start over
                streak[w] = 0
                good = {"positions": np.asarray(task.start_vertices, np.float32), "vertices": start.vertices[w],
                        "skin": start.skinning_transforms[w], "rest": start.rest_vertices[w]}
            else:
                good = last_good[w]
            put_back(w, good)
            if next_key >= len(task.poses):
                sim.status[w] = WorldStatus.CONVERGED  # frozen again: nothing left of this task
                finish(w)
                return 1
            if over:
                stats["restarts"] += 1
                schedules[w] = _schedule(task, canonical, neutral, settings, first_key=next_key)
            else:
                schedules[w] = _reroute(task, schedules[w], next_key, good["pose"], settings.interpolation_threshold)
            ptr[w] = 0
            changed[w] = True
            return 1
        # no good state to go back to: hand over every remaining target pose as failed
        handed = 0
        for j in range(ptr[w], len(kinds_w)):
            if kinds_w[j] == KEY:
                deliver([frame_of(w, keys_w[j], sim.world_positions(w), st)])
                handed += 1
        finish(w)
        return handed

    # Two frames' work at once: while the device steps frame k+1, the host hands over the target
    # frames whose holds ended in frame k (``on_frames``: filters, inverse skinning, shard writes),
    # acts on the answers (route home, next target, next task) and poses the bodies the worlds need
    # next. A world whose frame is being handed over sits that frame out, frozen (its state does not
    # change), so every world goes through the same states as when frames were handed over between
    # frames; only the simulator frame each state is reached in differs.
    pending: list[tuple[int, RecordedFrame]] = []  # (world, frame) of target holds that ended

    def deliver_pending() -> int:
        """Hands the pending frames over (one ``on_frames`` call) and routes their worlds on by
        the answers; returns the number of target poses finished."""
        worlds = [w for w, _ in pending]
        f1 = time.perf_counter()
        verdicts = deliver([f for _, f in pending])
        f2 = time.perf_counter()
        stats["record_deliver_s"] += f2 - f1
        pending.clear()
        for w, accepted in zip(worlds, verdicts):
            streak[w] = 0
            rejects[w] = 0 if accepted else rejects[w] + 1
            if accepted and restart_to_kept:
                last_kept[w] = last_good[w]  # the state saved for this hold
            next_key = int(schedules[w][3][ptr[w]]) + 1
            if (settings.restart_after_rejects > 0 and rejects[w] >= settings.restart_after_rejects
                    and home[w] is not None and next_key < len(tasks[cur[w]].poses)):
                rejects[w] = 0
                stats["restarts_after_rejects"] += 1
                if restart_to_kept and last_kept[w] is not None:
                    stats["restarts_to_last_kept"] += 1
                    restart_from(w, last_kept[w], next_key)
                else:
                    go_home(w, next_key)
            elif settings.home_between_targets and home[w] is not None and next_key < len(tasks[cur[w]].poses):
                stats["homecomings"] += 1
                go_home(w, next_key)
            else:
                advance(w)
        stats["record_route_s"] += time.perf_counter() - f2
        return len(worlds)

    def pose_ahead(idx: np.ndarray | None) -> dict[str, torch.Tensor] | None:
        """Bodies of the worlds in ``idx`` at their current entries (None: only tops up the
        buffers of every world that needs it, ahead of the next frame)."""
        calls, bodies, model_s = ahead.calls, ahead.bodies, ahead.model_s
        if idx is None:
            ahead.prefetch(schedules, ptr, ~done)
            posed = None
        else:
            posed = ahead.get(idx, schedules, ptr, ~done)
        stats["body_calls"] += ahead.calls - calls
        stats["bodies_posed"] += ahead.bodies - bodies
        stats["body_model_s"] += ahead.model_s - model_s
        return posed

    # self-contact in some worlds only: the entry kind whose worlds have it on, the others off
    contact_kind = {"transitions": True, "holds": False}.get(settings.self_contact_during) if settings.self_contact else None
    with streams.stepping():
        while not done.all() or pending:
            t0 = time.perf_counter()
            if changed.any():
                idx = np.nonzero(changed)[0]
                posed = pose_ahead(idx)
                idx_t = to_device_async(idx, torch_device)
                for name in ("vertices", "skin", "rest"):
                    body_now[name][idx_t] = posed[name]
                b0 = time.perf_counter()
                collider.set_target(body_now["vertices"])
                stats["body_target_s"] += time.perf_counter() - b0
                sim.restart(changed & ~done)
                changed[:] = False
            ran = sim.status == WorldStatus.RUNNING  # the worlds this frame advances
            if contact_kind is not None:
                sim.control.set_self_contact(np.fromiter(
                    (not done[w] and (schedules[w][2][ptr[w]] == TRANSITION) == contact_kind for w in range(w_count)),
                    dtype=bool, count=w_count))
            if not ran.any() and not pending:
                raise RuntimeError("run_sequences stalled: no world is running and no frame is pending "
                                   f"({int((~done).sum())} worlds not done)")
            t1 = time.perf_counter()
            stats["body_s"] += t1 - t0
            if ran.any():
                sim.launch_frame()
            t2 = time.perf_counter()
            finished_keys = 0
            if pending:  # beside the frame in flight
                finished_keys += deliver_pending()
                t3 = time.perf_counter()
                stats["record_s"] += t3 - t2
                pose_ahead(None)  # the worlds routed on need their next bodies: posed now, not before the next launch
                stats["body_prefetch_s"] += time.perf_counter() - t3
                stats["body_s"] += time.perf_counter() - t3
            if ran.any():
                t4 = time.perf_counter()
                status = sim.finish_frame()
                stats["sim_s"] += time.perf_counter() - t4 + (t2 - t1)
                stats["sim_launch_s"] += t2 - t1
                stats["frames"] += 1
                stats["world_frames"] += int(ran.sum())
                held[ran] += 1
                busy = np.nonzero(ran)[0]
                kinds_now = np.fromiter((schedules[w][2][ptr[w]] for w in busy), dtype=np.int64, count=len(busy))
                for name, kind in (("transition_world_frames", TRANSITION), ("hold_world_frames", KEY),
                                   ("settle_world_frames", SETTLE)):
                    stats[name] += int((kinds_now == kind).sum())
                ready = []  # worlds whose hold (settle or target pose) ended this frame
                for w in busy:
                    kind = schedules[w][2][ptr[w]]
                    st = int(status[w])
                    if st == WorldStatus.EXPLODED:
                        q0 = time.perf_counter()
                        finished_keys += handle_explosion(w, st)
                        stats["recover_s"] += time.perf_counter() - q0
                        continue
                    if kind == TRANSITION:
                        advance(w)
                        continue
                    if st in (WorldStatus.CONVERGED, WorldStatus.MAX_STEPS):
                        if held[w] >= settings.min_hold_frames:
                            ready.append(w)
                        else:
                            sim.restart([w])  # keep holding the pose
                if ready:
                    # the worlds that finished together leave the device together and are handed over
                    # in one call, beside the next frame
                    r0 = time.perf_counter()
                    positions = sim.worlds_positions(ready)
                    stats["record_copy_s"] += time.perf_counter() - r0
                    keyed = []
                    for j, w in enumerate(ready):
                        _, poses_w, kinds_w, _ = schedules[w]
                        kind = kinds_w[ptr[w]]
                        if settings.recover_explosions or kind == SETTLE or restart_to_kept:
                            state = {"positions": positions[j].copy(), "pose": poses_w[ptr[w]],
                                     "vertices": body_now["vertices"][w].clone(), "skin": body_now["skin"][w].clone(),
                                     "rest": body_now["rest"][w].clone()}
                            if settings.recover_explosions or restart_to_kept:
                                last_good[w] = state
                            if kind == SETTLE:
                                home[w] = state
                                group_home.setdefault(int(group[w]), state)
                        if kind == KEY:
                            keyed.append(j)
                        else:
                            advance(w)
                    if keyed:
                        worlds_k = [ready[j] for j in keyed]
                        f0 = time.perf_counter()
                        frames = frames_of(worlds_k, [schedules[w][3][ptr[w]] for w in worlds_k], positions[keyed],
                                           [int(status[w]) for w in worlds_k])
                        stats["record_frames_s"] += time.perf_counter() - f0
                        pending.extend(zip(worlds_k, frames))  # frozen (converged) until handed over
                    stats["record_s"] += time.perf_counter() - r0
            if on_progress is not None:  # every frame (also with 0), so heartbeats can fire during long holds
                on_progress(finished_keys)
            stats["loop_s"] += time.perf_counter() - t0
            for k, n in sim.explosion_causes.items():
                stats[f"exploded_{k}"] = causes_before[f"exploded_{k}"] + n
    return stats


def drape_static(
    body: BodyModel,
    faces: np.ndarray,
    rest_vertices: np.ndarray,
    *,
    shapes: np.ndarray,
    poses: np.ndarray,
    body_faces: np.ndarray,
    settings: SequenceSettings,
    device: str,
    fabric: object = "cotton",
    start_vertices: np.ndarray | None = None,
    max_frames: int | None = None,
    material_uv: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Relaxes W garments on W static bodies (one world each) until they come to rest.

    Args:
        rest_vertices: cloth rest geometry per world [m], (W, V, 3) (also the start unless given).
        shapes: (W, S) body shapes; poses: (W, 60) body poses.
        start_vertices: initial positions [m], (W, V, 3) (default: ``rest_vertices``).
        max_frames: frame budget (default ``settings.sim.max_frames``).
        material_uv: pattern UVs per face corner, (F, 3, 2) (a template's ``face_uv``; see
            ``ClothBuilder.add_garment``); None: the builder's grain axis (+y).
    Returns:
        (positions (W, V, 3) [m], status (W,) WorldStatus values).
    """
    rest_vertices = np.asarray(rest_vertices, np.float32)
    w_count = len(rest_vertices)
    torch_device = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
    with torch.no_grad():
        posed = body.on_device(torch_device).pose_torch(torch.as_tensor(np.asarray(shapes, np.float32), device=torch_device),
                                torch.as_tensor(np.asarray(poses, np.float32), device=torch_device))
    body_vertices = posed.vertices.cpu().numpy()
    builder = ClothBuilder()
    for w in range(w_count):
        builder.add_garment(rest_vertices[w], faces, fabric=fabric, material_uv=material_uv)
    model = builder.finalize(device, features=Features(self_contact=settings.self_contact, friction=settings.friction != 0.0))
    collider = BodyCollider(body_vertices, body_faces, device=device, thickness=settings.contact_thickness)
    budget = settings.sim.max_frames if max_frames is None else int(max_frames)
    sim = QuasiStaticSimulator(model, collider, solver=settings.solver,
                               settings=SimSettings(**{**settings.sim.__dict__, "max_frames": budget}))
    if start_vertices is not None:
        for w in range(w_count):
            sim.set_positions(np.asarray(start_vertices[w], np.float32), world=w)
    status = sim.relax(budget)
    positions = sim.positions()
    return np.stack([positions[model.world_slice(w)] for w in range(w_count)]), status
