"""World routing: which task each world runs, where it is in its schedule, and where it goes
after a hold, a rejected frame, an explosion or the end of its task.

Worlds take tasks one after another: tasks that can share a world (``world_groups``) form a
group, each group gets worlds in proportion to its target poses (``allocate_worlds``), and a
world that finishes a task takes its group's next one from its home drape (the settled canonical
drape on the group's shape), or, once its group has none left, the next task of the group with
the most target poses waiting per busy world (``SequenceSettings.cross_group_tasks``).
"""
from __future__ import annotations

import hashlib
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from simulate.body.kinematics import to_device_async
from simulate.contact import BodyCollider
from simulate.quasi_static import QuasiStaticSimulator, WorldStatus
from simulate.sequence.schedule import KEY, RECORD, SETTLE, TRANSITION, PlanCache, Schedule, build_schedule, reroute
from simulate.sequence.settings import RecordedFrame, SequenceSettings, SequenceTask
from simulate.sequence.stats import SequenceStats


@dataclass
class SavedState:
    """A world's garment and body, kept to put the world back there (``Worlds.put_back``).

    Attributes:
        positions: garment vertices [m], (V, 3).
        vertices, skin, rest: posed body [m] (Vb, 3), skinning transforms (J, 4, 4) and shaped
            unposed body [m] (Vb, 3), torch tensors on the body's device.
        pose: the body pose (60,) the world heads on from; None for the canonical start drape
            (from which a world follows a fresh schedule).
        placed: the collider's compacted body and the positions on the simulator's device, made
            at the first trip back and reused by every later one (a home state serves thousands).
    """

    positions: np.ndarray
    vertices: torch.Tensor
    skin: torch.Tensor
    rest: torch.Tensor
    pose: np.ndarray | None = None
    placed: tuple | None = None


def world_groups(tasks: list[SequenceTask]) -> list[int]:
    """Group index of each task: tasks with the same cloth rest geometry, start drape, body shape,
    start shape (``SequenceTask.start_shape``: their home drapes come from the same transition) and
    fabric can follow each other in one world (numbered in order of first appearance)."""
    seen: dict[bytes, int] = {}
    groups = []
    for t in tasks:
        h = hashlib.sha1()
        for a in (t.rest_vertices, t.start_vertices, t.shape):
            arr = np.ascontiguousarray(a, dtype=np.float32)
            h.update(str(arr.shape).encode())
            h.update(arr.tobytes())
        h.update(repr(t.fabric).encode())
        if t.start_shape is not None:
            h.update(b"start_shape" + np.ascontiguousarray(t.start_shape, dtype=np.float32).tobytes())
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


@dataclass
class Assignment:
    """Which task each world starts with and which tasks wait.

    Attributes:
        first: task of each world, (W,) (with a world per task, world w runs task w).
        group: group of each world, (W,).
        queues: each group's tasks not yet started, in the given order.
        source: per group, the first world of that group: it keeps the group's garment while the
            group has tasks queued (a world switching groups copies it from there).
    """

    first: np.ndarray
    group: np.ndarray
    queues: list[deque]
    source: dict[int, int]


def assign_worlds(tasks: list[SequenceTask], worlds: int | None) -> Assignment:
    """Worlds go to the first tasks of each group in the given order (``allocate_worlds`` decides
    how many per group; ``worlds`` None: one per task); the rest wait in their group's queue."""
    group_of_task = world_groups(tasks)
    n_groups = max(group_of_task, default=-1) + 1
    members = [[i for i, g in enumerate(group_of_task) if g == k] for k in range(n_groups)]
    share = allocate_worlds([sum(len(tasks[i].poses) for i in m) for m in members], [len(m) for m in members],
                            len(tasks) if worlds is None else int(worlds))
    quota, first = list(share), []
    queues: list[deque] = [deque() for _ in members]
    for i, g in enumerate(group_of_task):
        if quota[g] > 0:
            quota[g] -= 1
            first.append(i)
        else:
            queues[g].append(i)
    group = np.array([group_of_task[i] for i in first], dtype=np.int64)
    return Assignment(np.array(first, dtype=np.int64), group, queues,
                      {int(g): w for w, g in reversed(list(enumerate(group)))})


class Worlds:
    """Every world's task, schedule, place in it and saved states, and the moves between them.

    Per world (W,): ``cur`` (task), ``group``, ``ptr`` (current schedule entry), ``held`` (frames
    at the current entry), ``done`` (no task left: frozen), ``changed`` (needs the body of its
    current entry and a restart before the next frame), ``streak`` (explosions in a row),
    ``rejects`` (rejected target frames in a row); ``last_good`` (state at the last finished hold),
    ``home`` (settled canonical drape on the task's shape).
    """

    def __init__(self, tasks: list[SequenceTask], assignment: Assignment, schedules: list[Schedule],
                 settings: SequenceSettings, *, sim: QuasiStaticSimulator, collider: BodyCollider, start: dict[bytes, tuple],
                 body_now: dict[str, torch.Tensor],
                 canonical: np.ndarray, neutral: np.ndarray, torch_device: str, stats: SequenceStats,
                 deliver: Callable[[list[RecordedFrame]], list[bool]]) -> None:
        """
        Args:
            schedules: each world's schedule for its first task (``build_schedule``).
            start: the start bodies (canonical pose) by start shape bytes (``loop.starting_bodies``):
                (vertices (Vb, 3), skin (J, 4, 4), rest (Vb, 3)) tensors for every task's start shape.
            body_now: each world's current body, {"vertices": (W, Vb, 3), "skin": (W, J, 4, 4),
                "rest": (W, Vb, 3)} tensors on ``torch_device``, updated in place.
            deliver: hands frames over, returns True where accepted.
        """
        self.tasks, self.settings, self.sim, self.collider = tasks, settings, sim, collider
        self.start, self.body_now, self.canonical, self.neutral = start, body_now, canonical, neutral
        self.torch_device, self.stats, self.deliver = torch_device, stats, deliver
        self.cur, self.group, self.queues, self.group_source = (
            assignment.first.copy(), assignment.group.copy(), assignment.queues, assignment.source)
        self.n_groups = len(assignment.queues)
        self.group_home: dict[int, SavedState] = {}  # each group's settled canonical drape, from its first settle
        w_count = len(self.cur)
        self.schedules: list[Schedule] = list(schedules)
        self.ptr = np.zeros(w_count, dtype=np.int64)
        self.held = np.zeros(w_count, dtype=np.int64)
        self.done = np.zeros(w_count, dtype=bool)
        self.changed = np.ones(w_count, dtype=bool)
        self.streak = np.zeros(w_count, dtype=np.int64)
        self.rejects = np.zeros(w_count, dtype=np.int64)
        self.last_good: list[SavedState | None] = [None] * w_count
        self.home: list[SavedState | None] = [None] * w_count
        self.plans = PlanCache(tasks, settings.interpolation_threshold)

    def __len__(self) -> int:
        return len(self.cur)

    def kind(self, w: int) -> int:
        """Kind of world ``w``'s current schedule entry (TRANSITION, SETTLE, KEY or RECORD)."""
        return self.schedules[w][2][self.ptr[w]]

    # ----------------------------------------------------------------- frames
    def frames_of(self, worlds: list[int], keys: list[int], positions: np.ndarray,
                  statuses: list[int], velocities: np.ndarray | None = None) -> list[RecordedFrame]:
        """Frames of ``worlds`` at their current bodies, positions (n, V, 3) [m] (and velocities (n, V, 3)
        [m/s] of motion frames): each body tensor leaves the device once for all of them (indexing
        copies, so the next frames cannot alias them)."""
        idx_t = to_device_async(np.asarray(worlds, np.int64), self.torch_device)
        body = {name: self.body_now[name][idx_t].cpu().numpy() for name in ("vertices", "skin", "rest")}
        return [RecordedFrame(int(self.cur[w]), int(k), positions[j], int(st), int(self.held[w]), body["vertices"][j],
                              body["skin"][j], body["rest"][j], None if velocities is None else velocities[j])
                for j, (w, k, st) in enumerate(zip(worlds, keys, statuses))]

    def frame_of(self, w: int, key: int, positions: np.ndarray, st: int) -> RecordedFrame:
        return self.frames_of([w], [key], positions[None], [st])[0]

    # ----------------------------------------------------------------- moves
    def advance(self, w: int) -> None:
        """World ``w`` moves on to its next schedule entry (or to its next task)."""
        self.ptr[w] += 1
        self.held[w] = 0
        if self.ptr[w] >= len(self.schedules[w][2]):
            self.finish(w)
        else:
            self.changed[w] = True

    def put_back(self, w: int, state: SavedState) -> None:
        """Puts world ``w``'s body and garment back at a saved state (held from frame 0 again).
        The state's body and garment go to the device once, at its first trip back, and stay
        there; later trips are device-side copies."""
        for name in ("vertices", "skin", "rest"):
            self.body_now[name][w] = getattr(state, name)
        if state.placed is None:
            state.placed = (self.collider.compact_world(state.vertices), self.sim.device_positions(state.positions))
        self.collider.place_world(w, state.placed[0])
        self.sim.revive(w, state.placed[1])
        self.held[w] = 0

    def canonical_start(self, w: int, t: int) -> SavedState:
        """Task ``t``'s start drape on its start body (its ``start_shape``, else the neutral shape;
        canonical pose), to put world ``w`` back at."""
        task = self.tasks[t]
        shape = self.neutral if task.start_shape is None else np.asarray(task.start_shape, np.float32)
        vertices, skin, rest = self.start[np.asarray(shape, np.float32).tobytes()]
        return SavedState(np.asarray(task.start_vertices, np.float32), vertices, skin, rest)

    def plan_of(self, w: int, t: int) -> tuple:
        """Task ``t``'s plan (schedule, routes) from world ``w``'s home pose; a missing one is made
        with those of every busy world's task and every group's next task."""
        calls = self.plans.calls
        also = [int(self.cur[v]) for v in range(len(self)) if not self.done[v]] + [int(q[0]) for q in self.queues if q]
        plan = self.plans.get(t, self.home[w].pose, also)
        self.stats.plan_calls += self.plans.calls - calls
        return plan

    def restart_from(self, w: int, state: SavedState, next_key: int, route: np.ndarray | None = None) -> None:
        """Puts world ``w`` back at a saved ``state``, heading for target ``next_key`` from its pose
        (the caller knows that target exists); ``route``: the slerp'ed poses there, when known."""
        self.put_back(w, state)
        self.last_good[w] = state
        self.schedules[w] = reroute(self.tasks[self.cur[w]], self.schedules[w], next_key, state.pose,
                                    self.settings.interpolation_threshold, route=route)
        self.ptr[w] = 0
        self.changed[w] = True

    def go_home(self, w: int, next_key: int) -> None:
        """Puts world ``w`` back at its home state, heading for target ``next_key`` from the
        canonical pose along the route planned with its task's plan."""
        self.restart_from(w, self.home[w], next_key, route=self.plan_of(w, self.cur[w])[1][next_key])

    def busiest_group(self) -> int | None:
        """The group with the most target poses queued per busy world, among those whose home
        drape is known (None: no task waits anywhere, or cross-group tasks are off)."""
        if not self.settings.cross_group_tasks:
            return None
        busy = np.bincount(self.group[~self.done], minlength=self.n_groups)
        waiting = [(sum(len(self.tasks[i].poses) for i in self.queues[k]) / max(int(busy[k]), 1), -k)
                   for k in range(self.n_groups) if self.queues[k] and k in self.group_home]
        return -max(waiting)[1] if waiting else None

    def finish(self, w: int) -> None:
        """World ``w`` is through its task: it takes its group's next task, or another group's
        (``SequenceSettings.cross_group_tasks``), or is done."""
        if not self.queues[self.group[w]]:
            k = self.busiest_group()
            if k is None:
                self.done[w] = True
                if self.sim.status[w] == WorldStatus.RUNNING:  # a motion ends on a frame, not a hold: freeze it
                    self.sim.status[w] = WorldStatus.CONVERGED
                return
            self.sim.adopt_garment(w, self.group_source[k])  # a world that holds group k's garment
            self.group[w] = k
            self.home[w] = self.group_home[k]
            self.stats.group_switches += 1
        before = self.cur[w]
        t = self.cur[w] = self.queues[self.group[w]].popleft()
        self.stats.task_switches += 1
        self.streak[w] = self.rejects[w] = 0
        self.plans.drop(int(before))
        if self.home[w] is not None:  # from the settled drape: a slerp from the canonical pose to the first target
            self.put_back(w, self.home[w])
            self.last_good[w] = self.home[w]
            self.schedules[w] = self.plan_of(w, t)[0]
        else:  # never settled (exploded on the way): from the canonical drape, as at the start
            self.put_back(w, self.canonical_start(w, t))
            self.last_good[w] = None
            self.schedules[w] = build_schedule(self.tasks[t], self.canonical, self.neutral, self.settings)
        self.ptr[w] = 0
        self.changed[w] = True

    # ----------------------------------------------------------------- after a frame
    def explode(self, w: int, st: int) -> int:
        """Hands the failed target pose(s) of exploded world ``w`` over and, when it can, puts the
        world back at its last good state heading for the next target (or, after
        ``restart_after_explosions`` explosions in a row or before any good state, back at home or
        the canonical drape). Returns the number of target poses handed over."""
        s = self.settings
        _, _, kinds_w, keys_w = self.schedules[w]
        failed = np.nonzero(kinds_w[self.ptr[w]:] == KEY)[0]
        can_restart = s.restart_after_explosions > 0
        motion = bool(self.tasks[self.cur[w]].motion_steps)
        if motion or not (s.recover_explosions and (self.last_good[w] is not None or can_restart) and len(failed)):
            # no good state to go back to (a motion has none): hand over every remaining target as failed
            handed = 0
            for j in range(self.ptr[w], len(kinds_w)):
                if kinds_w[j] in (KEY, RECORD):
                    self.deliver([self.frame_of(w, keys_w[j], self.sim.world_positions(w), st)])
                    handed += 1
            self.finish(w)
            return handed
        # lose only the target being approached or held, then resume from the last good state
        j = self.ptr[w] + int(failed[0])
        self.deliver([self.frame_of(w, keys_w[j], self.sim.world_positions(w), st)])
        self.stats.recoveries += 1
        self.streak[w] += 1
        next_key = int(keys_w[j]) + 1
        over = self.last_good[w] is None or (can_restart and s.restart_after_explosions <= self.streak[w])
        task = self.tasks[self.cur[w]]
        if over and self.home[w] is not None and next_key < len(task.poses):  # start over from home
            self.streak[w] = 0
            self.stats.restarts += 1
            self.go_home(w, next_key)
            return 1
        if over:  # the last good state keeps leading into explosions: start over
            self.streak[w] = 0
            good = self.canonical_start(w, int(self.cur[w]))
        else:
            good = self.last_good[w]
        self.put_back(w, good)
        if next_key >= len(task.poses):
            self.sim.status[w] = WorldStatus.CONVERGED  # frozen again: nothing left of this task
            self.finish(w)
            return 1
        if over:
            self.stats.restarts += 1
            self.schedules[w] = build_schedule(task, self.canonical, self.neutral, s, first_key=next_key)
        else:
            self.schedules[w] = reroute(task, self.schedules[w], next_key, good.pose, s.interpolation_threshold)
        self.ptr[w] = 0
        self.changed[w] = True
        return 1

    def end_holds(self, ready: list[int], positions: np.ndarray, status: np.ndarray,
                  velocities: np.ndarray | None = None) -> list[tuple[int | None, RecordedFrame]]:
        """Worlds ``ready`` ended a hold (settle or target pose) or a motion frame (RECORD) with
        ``positions`` (n, V, 3) [m], ``velocities`` (n, V, 3) [m/s] (given when any is a motion frame)
        and ``status`` (the frame's WorldStatus values, (W,)): their states are kept (last good, home),
        settled worlds and motion worlds move on, and the (world, frame) of every target hold is
        returned, its world frozen until the frame is handed over; a motion frame comes as (None,
        frame): its world has moved on already (nothing to route by the answer)."""
        s = self.settings
        keyed, moving = [], []
        for j, w in enumerate(ready):
            _, poses_w, kinds_w, _ = self.schedules[w]
            kind = kinds_w[self.ptr[w]]
            if kind == RECORD:
                moving.append(j)
                continue
            if s.recover_explosions or kind == SETTLE:
                state = SavedState(positions[j].copy(), self.body_now["vertices"][w].clone(),
                                   self.body_now["skin"][w].clone(), self.body_now["rest"][w].clone(),
                                   pose=poses_w[self.ptr[w]])
                if s.recover_explosions:
                    self.last_good[w] = state
                if kind == SETTLE:
                    self.home[w] = state
                    self.group_home.setdefault(int(self.group[w]), state)
            if kind == KEY:
                keyed.append(j)
            else:
                self.advance(w)
        if not keyed and not moving:
            return []
        rows = keyed + moving
        worlds_k = [ready[j] for j in rows]
        f0 = time.perf_counter()
        frames = self.frames_of(worlds_k, [self.schedules[w][3][self.ptr[w]] for w in worlds_k], positions[rows],
                                [int(status[w]) for w in worlds_k], None if velocities is None else velocities[rows])
        self.stats.record_frames_s += time.perf_counter() - f0
        for frame in frames[:len(keyed)]:
            frame.velocities = None  # a held target's velocities are those of a garment at rest
        for j in moving:  # on to the next motion frame (or task) now: the answer changes nothing
            self.advance(ready[j])
        return [(w if r < len(keyed) else None, frame) for r, (w, frame) in enumerate(zip(worlds_k, frames))]

    def route(self, worlds: list[int | None], verdicts: list[bool]) -> None:
        """Worlds whose target frames were handed over move on by the answers: home after
        ``restart_after_rejects`` rejections in a row or after every target
        (``targets_from_home``), else to their next entry (None: a motion
        frame, whose world has moved on already)."""
        s = self.settings
        for w, accepted in zip(worlds, verdicts):
            if w is None:  # a motion frame: its world moved on when it was recorded
                continue
            self.streak[w] = 0
            self.rejects[w] = 0 if accepted else self.rejects[w] + 1
            next_key = int(self.schedules[w][3][self.ptr[w]]) + 1
            more = self.home[w] is not None and next_key < len(self.tasks[self.cur[w]].poses)
            if s.restart_after_rejects > 0 and self.rejects[w] >= s.restart_after_rejects and more:
                self.rejects[w] = 0
                self.stats.restarts_after_rejects += 1
                self.go_home(w, next_key)
            elif s.targets_from_home and more:
                self.stats.targets_from_home += 1
                self.go_home(w, next_key)
            else:
                self.advance(w)
