"""A world's schedule: the bodies it visits, one entry per frame or hold, and its re-planning.

A schedule is a tuple ``(shapes (M, S), poses (M, 60), kinds (M,), keys (M,))``: entry ``j`` puts
the body at shape ``shapes[j]`` and pose ``poses[j]``; its kind says whether the world steps one
frame there (TRANSITION: not recorded; RECORD: recorded as frame ``keys[j]`` of a motion, at rest
or not) or holds it until converged (SETTLE: not recorded; KEY: recorded as target ``keys[j]`` of
the task); ``keys`` is -1 for the kinds not recorded.

A task with ``motion_steps`` n >= 1 is a motion (``SequenceTask``): after the settle its body
turns from the start pose to the motion's first pose by slerp (steps of at most the interpolation
threshold, the last one recorded as frame 0), then moves through the motion at its frame rate: n - 1
slerp'ed simulator frames between consecutive motion poses, then the pose itself, recorded
(``motion_entries``).
"""
from __future__ import annotations

import numpy as np

from simulate.poses import interpolate_segments, interpolate_sequence, segment_key_index, slerp_segments
from simulate.sequence.settings import SequenceSettings, SequenceTask

# Entry kinds of a world's schedule.
TRANSITION = 0  # one frame toward an intermediate body (shape blend or slerp'ed pose)
SETTLE = 1  # hold until converged, not recorded (after the shape transition)
KEY = 2  # hold until converged, then record
RECORD = 3  # one frame toward a motion pose, then record (at the motion's frame rate)

Schedule = tuple  # (shapes (M, S) float32, poses (M, 60) float32, kinds (M,), keys (M,))


def build_schedule(task: SequenceTask, canonical_pose: np.ndarray, neutral_shape: np.ndarray, s: SequenceSettings,
                   first_key: int = 0) -> Schedule:
    """The schedule of one world from the canonical drape: shape transition (from
    ``task.start_shape``, or ``neutral_shape`` when it is None), settle, then the target poses
    from ``first_key`` on."""
    n = s.shape_transition_frames
    start = neutral_shape if task.start_shape is None else np.asarray(task.start_shape, np.float32)
    shapes = [transition_shapes(start, task.shape, n), task.shape[None]]
    poses = [np.tile(canonical_pose, (n, 1)), canonical_pose[None]]
    kinds = [np.full(n, TRANSITION), np.array([SETTLE])]
    keys = [np.full(n, -1), np.array([-1])]
    if task.motion_steps:
        visit = motion_entries(task, canonical_pose, s.interpolation_threshold)
    else:
        visit = visit_entries(task, first_key, canonical_pose, s.interpolation_threshold)
    out = [np.concatenate([*part, v]) for part, v in zip((shapes, poses, kinds, keys), visit)]
    return out[0].astype(np.float32), out[1].astype(np.float32), out[2], out[3]


def transition_shapes(start: np.ndarray, shape: np.ndarray, n: int) -> np.ndarray:
    """The bodies of a shape transition: ``start`` (S,) blended linearly to ``shape`` (S,) over ``n``
    frames, (n, S) float32, the last one ``shape`` (the schedule's first entries; a caller that
    blends these bodies ahead of the run gets the very shapes the run poses)."""
    blend = (np.arange(1, n + 1) / n)[:, None]
    return (np.asarray(start)[None] * (1 - blend) + np.asarray(shape)[None] * blend).astype(np.float32)


def visit_entries(task: SequenceTask, first_key: int, start_pose: np.ndarray, threshold: float,
                  stop: int | None = None) -> Schedule:
    """Schedule entries visiting ``task.poses[first_key:stop]`` from ``start_pose``, slerp'ed
    poses inserted where a joint would turn more than ``threshold`` [rad] in one frame."""
    seq, key_index = interpolate_sequence(task.poses[first_key:stop], start_pose, threshold)
    return entries(task, seq, key_index, first_key)


def motion_entries(task: SequenceTask, start_pose: np.ndarray, threshold: float) -> Schedule:
    """Schedule entries of motion task ``task`` (``motion_steps`` n >= 1) from ``start_pose``: slerp'ed
    poses to the motion's first pose, each joint turning at most ``threshold`` [rad] per frame (the
    first pose itself RECORD as frame 0), then per later motion pose k its n - 1 slerp'ed
    TRANSITION poses from pose k - 1 (fractions 1/n .. (n-1)/n) and pose k, RECORD as frame k."""
    poses = np.asarray(task.poses, np.float32)
    n = int(task.motion_steps)
    lead, _ = interpolate_segments(np.asarray(start_pose, np.float32).reshape(1, -1), poses[:1], threshold)
    count = len(poses) - 1
    if count and n > 1:
        segment = np.repeat(np.arange(count), n - 1)
        fractions = np.tile(np.arange(1, n) / n, count)
        between = slerp_segments(poses[:-1], poses[1:], segment, fractions).reshape(count, n - 1, -1)
        rest = np.concatenate([between, poses[1:, None]], axis=1).reshape(count * n, -1)
    else:
        rest = poses[1:]
    seq = np.concatenate([lead, rest]).astype(np.float32)
    recorded = np.zeros(len(seq), dtype=bool)
    recorded[len(lead) - 1::n] = True  # the first pose, then every n-th entry: a motion pose
    keys = np.full(len(seq), -1, dtype=np.int64)
    keys[recorded] = np.arange(len(poses))
    return (np.tile(task.shape, (len(seq), 1)).astype(np.float32), seq,
            np.where(recorded, RECORD, TRANSITION), keys)


def entries(task: SequenceTask, seq: np.ndarray, key_index: np.ndarray, first_key: int = 0) -> Schedule:
    """Schedule entries of the poses ``seq`` (M, 60) on the task's shape: target ``key_index +
    first_key`` where ``key_index >= 0``, a slerp'ed transition pose elsewhere."""
    return (np.tile(task.shape, (len(seq), 1)).astype(np.float32), seq.astype(np.float32),
            np.where(key_index >= 0, KEY, TRANSITION), np.where(key_index >= 0, key_index + first_key, -1))


def reroute(task: SequenceTask, schedule: Schedule, next_key: int, start_pose: np.ndarray, threshold: float,
            route: np.ndarray | None = None) -> Schedule:
    """``schedule`` re-planned from ``start_pose``: slerp'ed poses to target ``next_key``, then the
    entries that already follow that target (interpolation is sequential, so they are what a full
    re-plan gives, at a fraction of its cost). ``route``: the poses from ``start_pose`` to the
    target, ending with it, when already known (M, 60)."""
    _, _, kinds, keys = schedule
    j = int(np.nonzero((kinds == KEY) & (keys == next_key))[0][0])
    if route is None:
        head = visit_entries(task, next_key, start_pose, threshold, stop=next_key + 1)
    else:  # the route's last pose is the target
        head = entries(task, np.asarray(route, np.float32), np.arange(len(route)) - (len(route) - 1), next_key)
    return tuple(np.concatenate([h.astype(old.dtype), old[j + 1:]]) for h, old in zip(head, schedule))


def plans_from(tasks: list[SequenceTask], start_poses: list[np.ndarray],
               threshold: float) -> list[tuple[Schedule, list[np.ndarray]]]:
    """Per task, from its start pose: the schedule visiting all its targets (``visit_entries``
    from the first) and, for every target, the slerp'ed poses from the start pose to it, ending
    with it (the route ``reroute`` inserts), all segments of all tasks interpolated in one batched
    call (each segment is interpolated on its own, so a task's plan does not depend on the others
    in the call; one call per task costs ~10-80 ms on a GPU)."""
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
        visit = entries(t, poses[a:b], segment_key_index(segment[a:b] - first))
        first += n
        out.append((visit, [poses[a:b] for a, b in zip(bounds[first:first + n], bounds[first + 1:first + n + 1])]))
        first += n
    return out


class PlanCache:
    """Plans (``plans_from``) by (task, start pose), made in batches and dropped when the task is
    done: worlds change tasks and go home thousands of times in a dataset, each trip needing the
    task's schedule and routes from the home pose."""

    def __init__(self, tasks: list[SequenceTask], threshold: float) -> None:
        self.tasks, self.threshold = tasks, threshold
        self.plans: dict[tuple[int, bytes], tuple] = {}
        self.calls = 0  # batched plan calls made

    def get(self, task: int, pose: np.ndarray, also: list[int]) -> tuple[Schedule, list[np.ndarray]]:
        """Task ``task``'s plan from ``pose`` (60,). A missing plan is made in one batched call with
        those of the tasks in ``also`` (the tasks likely to need one from the same pose next) that
        lack one."""
        pose = np.asarray(pose, np.float32)
        key = (int(task), pose.tobytes())
        if key not in self.plans and self.tasks[int(task)].motion_steps:  # no routes: a motion is not re-entered
            self.plans[key] = (motion_entries(self.tasks[int(task)], pose, self.threshold), [])
            self.calls += 1
        if key not in self.plans:
            batch = [u for u in dict.fromkeys([int(task)] + [int(u) for u in also])
                     if (u, key[1]) not in self.plans and not self.tasks[u].motion_steps]
            for u, plan in zip(batch, plans_from([self.tasks[u] for u in batch], [pose] * len(batch), self.threshold)):
                self.plans[(u, key[1])] = plan
            self.calls += 1
        return self.plans[key]

    def drop(self, task: int) -> None:
        """Forgets task ``task``'s plans (it is done)."""
        for key in [k for k in self.plans if k[0] == task]:
            del self.plans[key]
