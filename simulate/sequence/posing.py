"""Bodies posed ahead: each world's next schedule entries, posed in one batched body-model call
for all worlds that need them (one call per world and frame would cost more than the frame)."""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

from simulate.body.base import PosedBody
from simulate.body.kinematics import to_device_async


class PosedAhead:
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
