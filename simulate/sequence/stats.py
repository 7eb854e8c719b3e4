"""Counts and wall times of a ``run_sequences`` call (see its docstring for what each one is)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass
class SequenceStats:
    """Statistics of one ``run_sequences`` call, counted from zero; ``publish`` adds them to a
    caller's dict (which may hold counts of earlier calls). Seconds are wall seconds."""

    frames: int = 0  # simulator frames
    world_frames: int = 0  # frames summed over the worlds that ran in them
    transition_world_frames: int = 0  # of them on transition entries (shape blends, slerp'ed poses, routes home)
    hold_world_frames: int = 0  # ... holding target poses
    settle_world_frames: int = 0  # ... settling after the shape blend
    motion_world_frames: int = 0  # ... stepping to a motion frame and recording it
    sim_s: float = 0  # stepping: launch plus the wait left after the host work beside the frame
    sim_launch_s: float = 0  # the launch alone
    sim_device_s: float = 0  # the frames' own device time (CUDA events; 0 on the CPU): the rest of loop_s is the host's
    body_s: float = 0  # posing bodies, moving the collider's targets
    record_s: float = 0  # copying, handing over and routing target frames
    recover_s: float = 0  # explosion recoveries
    loop_s: float = 0  # the whole frame loop
    recoveries: int = 0  # explosions recovered from
    body_calls: int = 0  # batched body-model calls
    bodies_posed: int = 0  # bodies they posed
    body_model_s: float = 0  # in the body model
    record_copy_s: float = 0  # positions off the device
    record_frames_s: float = 0  # the frames' bodies off the device
    record_deliver_s: float = 0  # in ``on_frames`` / ``on_frame``
    record_route_s: float = 0  # routing the delivered frames' worlds on or home
    body_target_s: float = 0  # the collider's targets
    body_prefetch_s: float = 0  # posing ahead beside a frame in flight
    plan_calls: int = 0  # batched plan calls (``PlanCache``)
    setup_s: float = 0  # before the loop: the three below
    group_switches: int = 0  # task switches to a task of another group
    setup_schedules_s: float = 0  # visiting orders and routes
    setup_model_s: float = 0  # the batched cloth model
    setup_simulator_s: float = 0  # start bodies, collider and simulator
    task_switches: int = 0  # a world taking a queued task
    restarts: int = 0  # explosion recoveries that started over from home or the canonical drape
    restarts_after_rejects: int = 0  # worlds sent back after ``restart_after_rejects`` rejected frames
    targets_from_home: int = 0  # worlds sent home after a kept target (``targets_from_home``)
    self_contact_substeps: int = 0  # world-substeps whose self-contact pair lists were searched or refreshed (VBD)
    self_contact_searches: int = 0  # ... of them with a BVH search (the others refreshed their lists)

    def start(self, into: dict) -> dict:
        """Lists every statistic in ``into`` (0 where absent) and returns a copy of it: the ``base``
        of ``publish``."""
        for f in dataclasses.fields(self):
            into.setdefault(f.name, 0)
        return dict(into)

    def publish(self, into: dict, base: dict) -> None:
        """``into[name] = base[name] + value`` for every statistic (``base``: the counts ``into``
        held before this call)."""
        for f in dataclasses.fields(self):
            into[f.name] = base.get(f.name, 0) + getattr(self, f.name)

