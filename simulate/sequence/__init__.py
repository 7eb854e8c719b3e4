"""Quasi-static sequence driver (seed 000 section 5.3, seed 004 section 3.3).

Each task is one garment style on one body shape visiting a list of target poses.
A world starts on the neutral body (or the task's ``start_shape``: shape + tightness, the
shape its garment is sized for) in the canonical pose, the body shape is blended
to the task's shape over ``shape_transition_frames`` frames and the garment relaxed,
then the body visits the target poses in the given order; slerp'ed poses are
inserted where any joint would turn more than ``interpolation_threshold`` in one
frame (one frame each), and every target pose is held until the world converges
(or hits ``max_relax_frames``), when the frame is handed to ``on_frame`` (or, with the
other worlds' frames that finished with it, to ``on_frames``). A motion task (``SequenceTask.motion_steps``)
instead steps through its poses at a fixed frame rate, each recorded after a fixed number of
frames without waiting for rest (``schedule.motion_entries``). A world whose
frames ``on_frame`` rejects (``restart_after_rejects``), or that keeps exploding, goes back home
(its drape at the end of the settle) and heads for its next target from the canonical pose.

Many tasks run as parallel worlds of one simulator. Worlds follow their own
schedules; a world whose current entry is done moves on without waiting for the
others, and a world whose schedule is finished is frozen. Nothing couples worlds but
the float rounding of the batched body model (a body posed in another company can differ by
an ulp, and a hold may then stop a frame earlier or later), so callers that need bitwise
reproducible frames keep each task's batch the same (generate-dataset does).

Modules: ``settings`` (task, settings, recorded frame), ``schedule`` (a world's entries, their
re-planning and the plan cache), ``routing`` (which task each world runs and where it goes after a
hold, a rejection or an explosion; saved states), ``posing`` (bodies posed ahead in batches),
``streams`` (CUDA streams of the frame loop), ``stats`` (the run's statistics), ``loop`` (the frame
loop, ``run_sequences``), ``drape`` (relaxing garments on static bodies).
"""
from simulate.sequence.drape import drape_static
from simulate.sequence.loop import run_sequences
from simulate.sequence.routing import SavedState, allocate_worlds, world_groups
from simulate.sequence.schedule import KEY, RECORD, SETTLE, TRANSITION
from simulate.sequence.settings import RecordedFrame, SequenceSettings, SequenceTask
from simulate.sequence.stats import SequenceStats

__all__ = ["run_sequences", "drape_static", "SequenceTask", "SequenceSettings", "RecordedFrame", "SequenceStats",
           "SavedState", "world_groups", "allocate_worlds", "KEY", "RECORD", "SETTLE", "TRANSITION"]
