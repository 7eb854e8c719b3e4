"""What the sequence driver takes and hands back: a task, its settings, a recorded frame."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simulate.quasi_static import SimSettings


@dataclass
class SequenceTask:
    """One garment on one body shape through a pose list.

    Attributes:
        rest_vertices: cloth rest geometry (edge lengths, areas) [m], shape (V, 3).
        start_vertices: initial positions on the start body (``start_shape``, else the neutral
            shape), canonical pose [m], (V, 3).
        shape: body shape, (S,).
        poses: target poses in visiting order, (N, 60); for a motion, its frames in order.
        fabric: fabric preset name or Fabric.
        start_shape: body shape the shape transition starts from, (S,); None: the neutral shape.
            A garment of tightness tau starts on beta + tau (``simulate.garment.tightness``).
        motion_steps: 0: ``poses`` are targets, each held until the world converges. n >= 1:
            ``poses`` are a motion's frames, n simulator frames apart (the motion's frame time is
            n x ``SimSettings.frame_dt``): each is recorded after its n-th frame, at rest or not,
            with the garment's velocities (see ``simulate.sequence.schedule``). A motion world
            that explodes hands its remaining frames over as failed (no recovery: a motion's
            state cannot be put back mid-way), and rejected frames do not send it home.
    """

    rest_vertices: np.ndarray
    start_vertices: np.ndarray
    shape: np.ndarray
    poses: np.ndarray
    fabric: object = "cotton"
    start_shape: np.ndarray | None = None
    motion_steps: int = 0


@dataclass
class SequenceSettings:
    """Stepping of the sequence (see the ``simulate.sequence`` docstring)."""

    sim: SimSettings = field(default_factory=SimSettings)
    solver: str = "xpbd"
    shape_transition_frames: int = 10
    """Frames over which the body shape is blended from the task's start shape (the neutral shape
    unless ``SequenceTask.start_shape`` is set) to the task's."""
    interpolation_threshold: float = 0.1
    """Largest turn of any joint in one frame [rad]; slerp'ed poses are inserted between targets
    farther apart."""
    min_hold_frames: int = 2
    """Frames a target pose (or the settle) is held at least, converged or not."""
    contact_thickness: float = 0.004
    """Distance the cloth keeps from the body surface [m]."""
    friction: float | None = None
    """Body friction: 0 turns it off; any other value (or None) keeps it on, with each fabric's
    coefficient (``Fabric.friction``)."""
    self_contact: bool = False
    """Cloth self-contact (search and response) on."""
    recover_explosions: bool = True
    """A world that explodes loses only the target pose it was heading to: its last good state
    (garment and body at the previous finished hold) is put back and the world goes on to the
    next target, slerp'ed afresh from there. Off: the rest of its schedule is handed over as failed."""
    restart_after_explosions: int = 2
    """After this many explosions of a world in a row (its last good state led into an explosion
    again), the world starts over from the canonical drape (shape transition, settle, then the
    next target) instead of the last good state: a state that led into an explosion tends to lead
    into the next one too. 0 = never. A world that has come home (see ``restart_after_rejects``)
    starts over from there instead."""
    restart_after_rejects: int = 1
    """After this many target frames in a row that ``on_frame`` rejects (returns ``False``: the
    frame failed the dataset's filters), the world goes home: back to its settled canonical drape
    on the task's shape (kept when the settle hold ended), from where it heads for its next target
    along a slerp from the canonical pose. Without it a tangle is carried along the rest of the
    sequence (self-intersection and distortion grow with the position in the sequence, not with
    any joint angle). 1: home after every rejected frame. 0 = never."""
    targets_from_home: bool = False
    """Every target pose of a task is reached from home (the settled canonical drape on the task's
    shape, along a slerp from the canonical pose), as after a rejected frame, not from the pose
    before it: a target's rest then does not depend on the poses before it. Rests reached along
    two different sequences lie 15-18 mm apart on average (``drape report floor``, XPBD and VBD
    alike), which no quasi-static learner can fit; from home, ~25 % more world-frames per
    target (longer transitions; docs/benchmarks.md)."""
    body_lookahead: int = 8
    """Schedule entries per world posed ahead; whenever a world runs out, every world short of
    entries is topped up in the same batched body-model call (one call per frame costs more than
    the frame on a GPU). Memory: world_count x lookahead posed bodies (~0.34 MB each for anny)."""
    cross_group_tasks: bool = True
    """A world whose group (``world_groups``) has no task left takes the next task of the group
    with the most target poses waiting per busy world: that group's garment (rest shape, fabric:
    ``QuasiStaticSimulator.adopt_garment``), shape and settled home drape are swapped in, and the
    task runs as it would in a world of its own group (tested bit for bit). Without it a group's
    worlds wait idle once its tasks run out while others still queue."""
    concurrent_streams: bool = True
    """On CUDA, frames step on a stream of their own while the host hands the previous frame's
    target frames over (``on_frames``) and poses the next bodies beside them (see ``run_sequences``).
    Off: every launch goes to the device's stream, in the same order, so the results are the same
    bit for bit (a check for the streams' synchronisation); only slower."""


@dataclass
class RecordedFrame:
    """What ``on_frame`` receives for a target pose that finished relaxing, or a motion frame.

    Attributes:
        task: index of the task in the batch.
        key: index of the target pose (motion frame) in the task's pose list.
        positions: garment vertices [m], (V, 3).
        status: WorldStatus of the world (CONVERGED, MAX_STEPS or EXPLODED; a motion frame also
            RUNNING: it is recorded whether or not the garment is at rest).
        frames: frames the pose was held (a motion frame: 1).
        body_vertices: posed body [m], (Vb, 3).
        skinning_transforms: (J, 4, 4); rest_vertices: shaped unposed body (Vb, 3).
        velocities: garment vertex velocities [m/s] at the frame's end, (V, 3), for motion frames
            (None for held targets and failed frames).
    """

    task: int
    key: int
    positions: np.ndarray
    status: int
    frames: int
    body_vertices: np.ndarray
    skinning_transforms: np.ndarray
    rest_body_vertices: np.ndarray
    velocities: np.ndarray | None = None
