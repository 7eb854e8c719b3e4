"""``drape generate-dataset``: spec -> filtered, sharded HDF5 dataset + manifest.

Stages: validate the spec; plan styles, shapes, pairs, poses and tasks
(:mod:`pipelines.dataset_plan`); prepare the garment template and each garment's
canonical drape (one per style, or with a tightness range one per style-shape pair sized
for shape + tau; cached under ``OUT/cache``); simulate the pending tasks in batches
of ``simulation.worlds`` worlds (:func:`simulate.sequence.run_sequences`) on the
local device or on a Ray cluster; filter every frame and write one shard per task
(temporary name, renamed when complete); list each finished shard in the manifest
at once (so a kill loses at most the shards in flight); audit a sample of kept
frames against a much tighter solve; print a summary table. With ``poses.source:
motion`` each task is a motion recorded frame by frame at a fixed rate, with the
garment's velocities and the body's root joint per frame (docs/motion.md). A spec with a
list of garment types runs each type as a dataset of its own (:func:`generate_types`).
"""
from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipelines.spec import load_spec, spec_hash, validate_spec

CANONICAL_DRAPE_FRAMES = 300
"""Frame budget of each style's canonical drape (the start of its sequences) at least; a spec's
``max_relax_frames`` bounds a pose hold, and a short hold budget (e.g. TailorNet's fixed 2-frame
holds) must not leave the start drapes unrelaxed."""

#: Frame drop reasons, in the order they are tested (a frame is counted once).
DROP_REASONS = ("nan", "not_converged", "off_body", "distortion", "penetration", "self_intersection")


def resolve_device(device: str, option: str = "simulation.device") -> str:
    """"auto" -> "cuda:0" when Warp sees a GPU, else "cpu"; "cuda" -> "cuda:0". Raises ValueError
    naming ``option`` for a malformed device or a CUDA device this machine does not have."""
    import warp as wp

    if not isinstance(device, str) or not (device in ("auto", "cpu", "cuda") or (
            device.startswith("cuda:") and device[5:].isdigit())):
        raise ValueError(f"{option} must be auto, cpu, cuda or cuda:N (got {device!r})")
    if device == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    count = wp.get_cuda_device_count() if device.startswith("cuda") else 0
    if device.startswith("cuda") and count == 0:
        raise ValueError(f"{option} is {device!r} but Warp finds no CUDA device; use auto or cpu")
    if device.startswith("cuda:") and int(device[5:]) >= count:
        raise ValueError(f"{option} is {device!r} but Warp finds {count} CUDA device(s) (cuda:0..cuda:{count - 1})")
    return "cuda:0" if device == "cuda" else device


def status_drop_reason(finite: bool, status: int, filters: dict[str, Any]) -> str | None:
    """The filters that need no geometry: "nan" (exploded or non-finite), "not_converged"."""
    from simulate.quasi_static import WorldStatus

    if status == WorldStatus.EXPLODED or not finite:
        return "nan"
    if filters["require_converged"] and status != WorldStatus.CONVERGED:
        return "not_converged"
    return None


def drop_reason(metrics: dict[str, float], status: int, filters: dict[str, Any]) -> str | None:
    """The first filter a frame fails (see :data:`DROP_REASONS`), or None to keep it."""
    reason = status_drop_reason(bool(metrics["finite"]), status, filters)
    if reason is not None:
        return reason
    if metrics["off_body_fraction"] > filters["max_off_body_fraction"]:
        return "off_body"
    if metrics["distorted_fraction"] > filters["max_distorted_fraction"]:
        return "distortion"
    if metrics["penetration_fraction"] > filters["max_penetration_fraction"]:
        return "penetration"
    if metrics["self_intersections"] > filters["max_self_intersections"]:
        return "self_intersection"
    return None


@dataclass
class Context:
    """Everything a worker needs, built once per process from the spec."""

    spec: dict
    device: str
    body: Any
    template: Any  # GarmentTemplate
    template_dict: dict
    body_faces: np.ndarray
    plan: Any
    # per garment of the plan (Plan.garments, Task.garment_index: a style, or with tightness a style
    # sized for a pair's shape + tau):
    style_rest: np.ndarray  # (n_garments, V, 3) cloth rest geometry
    style_start: np.ndarray  # (n_garments, V, 3) canonical drape (canonical pose, on the shape it is sized for)
    phases: dict = None  # summed run_sequences statistics of the batches simulated in this process
    body_face_groups: list | None = None  # primary collision bodies: rows of body_faces per part
    body_part: np.ndarray | None = None  # (V,) primary collision part per garment vertex

    @property
    def tasks(self) -> dict:
        return {t.task_id: t for t in self.plan.tasks}

    @property
    def prepared(self) -> dict:
        """What another process of the same spec takes instead of building it again
        (``build_context(..., prepared=)``): the plan and the garment template."""
        return {"plan": self.plan, "template": self.template}


_CONTEXTS: dict[str, Context] = {}

def sequence_settings(spec: dict):
    """The spec's ``simulation`` section as SequenceSettings; what it does not set is the library's default."""
    from simulate.quasi_static import SimSettings
    from simulate.sequence import SequenceSettings

    s = spec["simulation"]
    sim = SimSettings(frame_dt=float(s["frame_dt"]), substeps=int(s["substeps"]), iterations=int(s["iterations"]),
                      tolerance=float(s["tolerance"]), max_frames=int(s["max_relax_frames"]))
    return SequenceSettings(sim=sim, solver=s["solver"], interpolation_threshold=float(s["interpolation_threshold"]),
                            self_contact=bool(s["contact"]["self_contact"]),
                            targets_from_home=bool(s.get("targets_from_home", False)))


def build_context(spec: dict, out_dir: Path, *, device: str | None = None, log: Callable[[str], None] = print,
                  prepared: dict | None = None) -> Context:
    """Loads the body, plans the dataset and prepares (or loads cached) garments. ``prepared``:
    the ``plan`` and ``template`` another process built from the same spec (a Ray worker gets the
    driver's instead of planning again: ~8 s of a t-shirt spec's worker start on a CPU core)."""
    key = spec_hash(spec) + str(device)
    if key in _CONTEXTS:
        return _CONTEXTS[key]
    from simulate.body import load_body_model
    from simulate.garment.drape import COLLISION_PARTS
    from simulate.garment.templates import make_template
    from simulate.sequence import drape_static

    from pipelines.dataset_plan import plan_dataset
    from pipelines.styled_garments import styled_garments

    device = resolve_device(device or spec["simulation"]["device"])
    body = load_body_model(spec["body"]["backend"], path=spec["body"]["path"])
    gtype = spec["garment"]["type"]
    plan = prepared["plan"] if prepared else plan_dataset(spec, body)
    cache = out_dir / "cache" / f"garments-{spec_hash(spec)[:16]}.npz"
    template = prepared["template"] if prepared else make_template(gtype, body, resolution=int(spec["garment"]["resolution"]))
    # one table for every driver: tops keep legs and head so hems and collars never meet an open
    # cut of the culled body (points beyond a cut get flipped contact normals and explode)
    body_faces = body.part_faces(COLLISION_PARTS[gtype])
    face_groups = garment_part = None
    if spec["simulation"]["contact"]["primary_bodies"]:
        from simulate.body.collision_parts import collision_parts

        parts = collision_parts(body, gtype, body_faces)
        face_groups = parts.face_groups
        canonical = np.asarray(body.pose(body.shape_default, body.canonical_pose).vertices).reshape(-1, 3)
        garment_part = parts.garment_vertex_parts(template.vertices, canonical)
    if cache.is_file():
        with np.load(cache) as z:
            style_rest, style_start = z["style_rest"], z["style_start"]
    else:
        t0 = time.perf_counter()
        style_rest = styled_garments(gtype, [(plan.styles[si], shape) for si, shape in plan.garments], body, template,
                                     backend=spec["body"]["backend"], body_path=spec["body"]["path"],
                                     meanwhile=lambda: keep_schedule_bodies(body, plan.tasks, spec, device))
        t_styled = time.perf_counter()
        drape_shapes = np.stack([body.shape_default if shape is None else shape for _, shape in plan.garments])
        fabrics = [plan.fabrics[si] for si, _ in plan.garments]
        # the canonical drape starts from the pattern: it gets its own frame budget, not a pose hold's,
        # and self-contact with the solvers that have it (without it 7 of the TailorNet spec's 40
        # drapes started with > 60 garment edges through the garment)
        seq = sequence_settings(spec)
        if seq.solver in ("vbd", "xpbd"):
            seq = dataclasses.replace(seq, self_contact=True)
        # every garment in one batch, each on the shape it is sized for, in its fabric
        style_start, status = drape_static(body, template.faces, style_rest, shapes=drape_shapes,
                                           poses=np.tile(body.canonical_pose, (len(style_rest), 1)), body_faces=body_faces,
                                           body_face_groups=face_groups, body_part=garment_part,
                                           settings=seq, device=device, fabric=fabrics,
                                           max_frames=max(seq.sim.max_frames, CANONICAL_DRAPE_FRAMES),
                                           material_uv=template.face_uv, attached=template.attachment)
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_suffix(".tmp.npz")
        try:
            np.savez(tmp, style_rest=style_rest, style_start=style_start.astype(np.float32), status=status)
            os.replace(tmp, cache)
        except BaseException:  # a full disk or a signal: no partial cache file stays behind
            tmp.unlink(missing_ok=True)
            raise
        log(f"prepared {len(style_rest)} garment drapes on the canonical body in {time.perf_counter() - t0:.1f} s "
            f"(garments {t_styled - t0:.1f} s, drapes {time.perf_counter() - t_styled:.1f} s; statuses "
            f"{np.bincount(status, minlength=4).tolist()} running/converged/max-steps/exploded)")
    template_dict = {"faces": template.faces, "rest_vertices": template.vertices, "skinning_weights": template.skinning_weights,
                     "body_vertex_index": template.body_vertex_index, "uv": template.uv}
    ctx = Context(spec, device, body, template, template_dict, body_faces, plan, style_rest, style_start,
                  body_face_groups=face_groups, body_part=garment_part)
    _CONTEXTS[key] = ctx
    return ctx


def keep_schedule_bodies(body: Any, tasks: list, spec: dict, device: str) -> int:
    """Blends, on the simulation's device, the rest body of every shape the tasks' schedules pose
    first (start shape, shape transition, shape; ``simulate.sequence.schedule``) and keeps them
    (``BodyModel.keep_rest``): one blend per shape, each alone, as posing would blend them between
    frames (5,500 for a cloth3d type). Returns the number blended."""
    import torch

    from simulate.sequence.schedule import transition_shapes

    n = sequence_settings(spec).shape_transition_frames
    neutral = np.asarray(body.shape_default, np.float32)
    shapes = []
    for t in tasks:
        start = neutral if t.start_shape is None else np.asarray(t.start_shape, np.float32)
        shapes += [start[None], transition_shapes(start, t.shape, n)]
    torch_device = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
    with torch.no_grad():
        return body.on_device(torch_device).keep_rest(np.concatenate(shapes)) if shapes else 0


class Unskinner:
    """Inverse skinning of garment frames (TailorNet Eq. 5's W^-1) in float64, batched, on the
    CUDA device when the simulation runs there (torch on the CPU otherwise)."""

    def __init__(self, weights: np.ndarray, device: str) -> None:
        import torch

        self.torch_device = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
        self.weights = torch.as_tensor(np.asarray(weights, np.float64), device=self.torch_device)

    def __call__(self, positions: np.ndarray, transforms: np.ndarray) -> np.ndarray:
        """positions (n, V, 3) [m], skinning transforms (n, J, 4, 4) -> unposed (n, V, 3) [m], float64."""
        import torch

        from simulate.body import inverse_lbs_torch

        x = torch.as_tensor(np.asarray(positions, np.float64), device=self.torch_device)
        t = torch.as_tensor(np.asarray(transforms, np.float64), device=self.torch_device)
        return inverse_lbs_torch(x, self.weights, t).cpu().numpy()


def plan_batches(tasks: list, worlds: int, batches: int = 1) -> list[list[str]]:
    """Task ids of each batch, pair by pair: at most ``worlds`` style-shape pairs per batch, at least
    ``batches`` batches (``simulation.batches``: one per GPU of a Ray run), tasks longest first. A
    batch's worlds are shared out among its pairs in proportion to their target poses, and a world
    that finishes a task takes its pair's next one (``run_sequences``), so the worlds of a batch stay
    busy until its end instead of waiting for its longest task. With ``batches`` > 1 and no more
    pairs than ``worlds``, every pair's tasks are dealt over all the batches, longest first, each to
    the batch with the fewest target poses so far (ties: the lowest batch), so every batch holds
    about the same share of every pair: pairs differ in cost (style, shape), and batches of whole
    pairs with equal target counts returned at 289 to 395 s on 4 GPUs. With more pairs than
    ``worlds``, pairs stay whole and are dealt out largest first the same way.

    Batches are a function of the spec alone: a resumed or distributed run simulates every task in
    the same company as an uninterrupted one, so its frames are bitwise identical. A batch with any
    unfinished task runs again whole; finished shards are not rewritten."""
    ordered = sorted(tasks, key=lambda t: (-len(t.poses), t.task_id))
    pairs: dict[tuple, list] = {}
    for t in ordered:  # a pair: one garment on one shape (the tasks that can share a world)
        pairs.setdefault((int(t.garment_index), np.asarray(t.shape, np.float32).tobytes()), []).append(t)
    groups = list(pairs.values())
    if not groups:
        return []
    if int(batches) <= 1:  # the batches the worlds need: consecutive runs of pairs
        return [[t.task_id for g in groups[i:i + worlds] for t in g] for i in range(0, len(groups), worlds)]
    if len(groups) <= int(worlds):  # every batch may hold every pair: deal the tasks
        count = min(int(batches), len(ordered))
        load, members = [0] * count, [[] for _ in range(count)]
        position = {t.task_id: k for k, t in enumerate(t for g in groups for t in g)}
        for t in ordered:
            b = min(range(count), key=lambda b: (load[b], b))
            load[b] += len(t.poses)
            members[b].append(t.task_id)
        return [sorted(m, key=position.__getitem__) for m in members if m]
    count = min(len(groups), max(int(batches), -(-len(groups) // int(worlds))))
    sizes = [sum(len(t.poses) for t in g) for g in groups]
    load, members = [0] * count, [[] for _ in range(count)]
    for i in sorted(range(len(groups)), key=lambda i: (-sizes[i], i)):
        b = min((b for b in range(count) if len(members[b]) < worlds), key=lambda b: (load[b], b))
        load[b] += sizes[i]
        members[b].append(i)
    return [[t.task_id for i in sorted(m) for t in groups[i]] for m in members]


def simulate_batch(ctx: Context, out_dir: Path, task_ids: list[str], *, on_shard: Callable[[Any], None] | None = None,
                   on_progress: Callable[[int], None] | None = None, skip: set[str] | frozenset = frozenset()) -> list[dict]:
    """Simulates a batch of tasks as parallel worlds and writes their shards.

    Tasks in ``skip`` are simulated (so the batch is the same as in an uninterrupted
    run) but their finished shards are not rewritten. Returns the manifest records of
    the shards written (also passed to ``on_shard`` as soon as each shard is complete).
    """
    import torch

    from data_manifest.background import WriterLanes, lane_count, resolve_mode
    from data_manifest.shard import ShardWriterSet
    from simulate.quality import QualityMeter
    from simulate.sequence import SequenceTask, run_sequences

    spec = ctx.spec
    tasks = [ctx.tasks[t] for t in task_ids]
    tmpl = ctx.template
    if ctx.body_face_groups is None:
        meter = QualityMeter(tmpl.faces, tmpl.vertices, ctx.body.faces, ctx.body.vertex_count, device=ctx.device)
    else:  # penetration as the simulation's contact sees it: each vertex against its own body part
        meter = QualityMeter(tmpl.faces, tmpl.vertices, ctx.body_faces, ctx.body.vertex_count, device=ctx.device,
                             body_face_groups=ctx.body_face_groups, garment_part=ctx.body_part)
    index = tmpl.body_vertex_index
    on_body = index >= 0
    records = []
    remaining = [len(t.poses) for t in tasks]
    motion = spec["poses"]["source"] == "motion"
    roots = root_joints(ctx.body, [t.shape for t in tasks]) if motion else None  # (n, 3) rest root joint per task
    started_at = time.time()
    # shards are written, closed and hashed by workers of their own while the simulation goes on
    # (processes on CUDA: see data_manifest.background), each owning the shard writers of its lane
    # (task index modulo the workers)
    in_daemon = multiprocessing.current_process().daemon  # e.g. a Pool worker: it may not start processes
    mode = resolve_mode("process" if str(ctx.device).startswith("cuda") and not in_daemon else "thread")
    background = WriterLanes(lane_count(mode), mode=mode)
    shards = "shards"  # the ShardWriterSet's key on the worker
    background.create(shards, ShardWriterSet, out_dir, ctx.template_dict, precision=spec["output"]["precision"],
                      compression=spec["output"]["compression"])
    written: dict[int, bool] = {}  # task index -> its shard is written here (False: finished in an earlier run)

    def writes(i: int) -> bool:
        """Whether task ``i``'s shard is written in this run; opens it on the worker at its first frame."""
        if i not in written:
            t = tasks[i]
            written[i] = t.task_id not in skip
            if written[i]:
                about = {"task_id": t.task_id, "garment": spec["garment"]["type"], "splits": [t.split], "seed": int(spec["seed"]),
                         "shape": t.shape, "style": t.style_vector, "pair": int(t.pair), "style_index": int(t.style_index),
                         "fabric": t.fabric}
                if t.tightness is not None:  # the garment is sized for sized_shape = shape + tightness (clipped)
                    about.update(tightness=t.tightness, sized_shape=t.start_shape)
                if t.motion_steps:  # the motion and its frame rate: frames are 1 / fps apart
                    about.update(motion=t.motion, fps=float(spec["motion"]["fps"]))
                background.lane(i).call(shards, ShardWriterSet.open, i, about)
        return written[i]
    # a motion frame is recorded after its frames whether or not the garment is at rest: the
    # convergence filter is for held targets
    filters = dict(spec["filters"], require_converged=False) if motion else spec["filters"]
    weights = tmpl.skinning_weights
    from simulate.quality import triangle_areas

    rest_areas = {k: triangle_areas(ctx.style_rest[k], tmpl.faces) for k in {t.garment_index for t in tasks}}
    unskin = Unskinner(weights, ctx.device)

    def record_frames(frames: list) -> list[bool]:
        """Filters and writes target frames that finished together (one per world); returns
        which were kept. The geometric metrics and the inverse skinning of all of them run as
        one batch each, on the simulation device."""
        reasons: dict[int, str | None] = {}
        metrics: dict[int, dict] = {}
        for i, frame in enumerate(frames):
            if writes(frame.task):  # else finished in an earlier run
                # the status filters first: a frame they drop needs no geometric metrics
                reasons[i] = status_drop_reason(bool(np.isfinite(frame.positions).all()), frame.status, filters)
        measured = [i for i, r in reasons.items() if r is None]
        t_meter = time.perf_counter()
        if measured:
            batch = meter.measure_batch(
                np.stack([frames[i].positions for i in measured]), np.stack([frames[i].body_vertices for i in measured]),
                collision_depth=filters["collision_depth"],
                rest_areas=np.stack([rest_areas[tasks[frames[i].task].garment_index] for i in measured]),
                area_bounds=(1.0 - filters["max_area_shrink"], 1.0 + filters["max_area_growth"]))
            for i, m in zip(measured, batch):
                metrics[i] = m
                reasons[i] = drop_reason(m, frames[i].status, filters)
        keep = [i for i in measured if reasons[i] is None]
        t_unskin = time.perf_counter()
        unposed = unskin(np.stack([frames[i].positions for i in keep]),
                         np.stack([frames[i].skinning_transforms for i in keep])) if keep else None
        unposed_row = {i: r for r, i in enumerate(keep)}
        t_submit = time.perf_counter()
        for i, reason in reasons.items():
            frame = frames[i]
            t = tasks[frame.task]
            lane = background.lane(frame.task)
            if reason is None:
                base = np.where(on_body[:, None], frame.rest_body_vertices[np.maximum(index, 0)], tmpl.vertices)
                row = dict(metrics[i], status=float(frame.status), frames=float(frame.frames))
                # frame_index: position in the visiting order; pose_id: index into the split's pose set
                # (a motion's frame number); motion frames add velocities and the root joint
                moving = {} if frame.velocities is None else {
                    "velocities": frame.velocities, "root_joint": root_position(frame, roots[frame.task], ctx.body)}
                # the positions travel as simulated (float32: half the bytes to pickle); the writer
                # widens them to float64 itself, exactly
                lane.call(shards, ShardWriterSet.write_frame, frame.task, frame.positions, unposed[unposed_row[i]] - base,
                          t.poses[frame.key], row, frame_index=int(frame.key),
                          pose_id=np.array([t.pose_ids[frame.key]], np.float32), **moving)
            else:
                lane.call(shards, ShardWriterSet.record_dropped, frame.task, reason, frame_index=int(frame.key),
                          pose=t.poses[frame.key])
            remaining[frame.task] -= 1
            if remaining[frame.task] == 0:
                lane.call_collect(shards, ShardWriterSet.close, frame.task, started_at=started_at)
        list_finished(background.completed())
        phases = ctx.phases
        for key, seconds in (("record_meter_s", t_unskin - t_meter), ("record_unskin_s", t_submit - t_unskin),
                             ("record_submit_s", time.perf_counter() - t_submit)):
            phases[key] = phases.get(key, 0.0) + seconds
        return [reasons.get(i) is None for i in range(len(frames))]

    def list_finished(finished: list) -> None:
        for record in finished:
            records.append(record)
            if on_shard is not None:
                on_shard(record)

    seq_tasks = [SequenceTask(rest_vertices=ctx.style_rest[t.garment_index], start_vertices=ctx.style_start[t.garment_index],
                              shape=t.shape, poses=t.poses, fabric=t.fabric, start_shape=t.start_shape,
                              motion_steps=t.motion_steps)
                 for t in tasks]
    settings = sequence_settings(spec)
    if motion and spec["motion"]["damping"] is not None:  # the sequences' damping; the canonical drapes keep theirs
        settings = dataclasses.replace(settings, sim=dataclasses.replace(settings.sim, damping=float(spec["motion"]["damping"])))
    try:
        with torch.no_grad():
            if ctx.phases is None:
                ctx.phases = {}
            # adds to ctx.phases as it goes, so heartbeats can show where the time goes
            run_sequences(ctx.body, tmpl.faces, seq_tasks, body_faces=ctx.body_faces, body_face_groups=ctx.body_face_groups,
                          body_part=ctx.body_part, settings=settings,
                          device=ctx.device, on_frames=record_frames, on_progress=on_progress, stats=ctx.phases,
                          worlds=int(spec["simulation"]["worlds"]), material_uv=tmpl.face_uv,
                          attached=tmpl.attachment)
        list_finished(background.close())
        ctx.phases["writer_busy_s"] = ctx.phases.get("writer_busy_s", 0.0) + background.busy_s
    except BaseException:
        background.close(raise_error=False, cleanup=ShardWriterSet.abort)  # no temporary file stays behind
        raise
    return [r if isinstance(r, dict) else r.to_dict() if hasattr(r, "to_dict") else r for r in records]


def root_joints(body: Any, shapes: list) -> np.ndarray:
    """The root joint (pelvis) of the shaped, unposed body of each shape [m], (n, 3)."""
    posed = body.pose(np.asarray(shapes, np.float32), np.tile(np.asarray(body.canonical_pose, np.float32), (len(shapes), 1)))
    return np.asarray(posed.rest_joints[:, int(body.pose_joint_indices[0])], np.float64)


def root_position(frame: Any, rest_root: np.ndarray, body: Any) -> np.ndarray:
    """The root joint of a recorded frame's posed body in world space [m], (3,): its skinning
    transform (rest to posed) applied to the rest root joint ``rest_root`` (3,)."""
    t = np.asarray(frame.skinning_transforms[int(body.pose_joint_indices[0])], np.float64)
    return t[:3, :3] @ rest_root + t[:3, 3]


def _phase_split(phases: dict) -> str:
    """'stepping / bodies / recording / recoveries / other' seconds of run_sequences statistics
    (other: the rest of the frame loop, bookkeeping and progress callbacks)."""
    named = [float(phases.get(k, 0.0)) for k in ("sim_s", "body_s", "record_s", "recover_s")]
    other = max(float(phases.get("loop_s", 0.0)) - sum(named), 0.0)
    return " / ".join(f"{v:.1f}" for v in (*named, other))


def _summary_table(manifest, seconds: float, frames_simulated_keys: int) -> str:
    totals = manifest.totals
    kept = int(totals.get("frames_kept", 0))
    dropped = totals.get("frames_dropped", {}) or {}
    lines = ["", f"dataset {manifest.name}: {len(manifest.shards)} shards",
             f"  {'frames kept':<26}{kept:>6}"]
    for reason in DROP_REASONS:
        lines.append(f"  {'dropped: ' + reason:<26}{int(dropped.get(reason, 0)):>6}")
    if seconds > 0:
        lines.append(f"  {'this run':<22}{seconds:>9.1f} s   {frames_simulated_keys / seconds:8.2f} target frames/s")
    ray = ((manifest.audit or {}).get("simulation") or {}).get("ray")
    if ray:
        lines.append(f"  {'Ray workers':<26}{int(ray['workers']):>6}  (on {int(ray['nodes'])} node(s), {int(ray['gpus'])} GPU(s); "
                     f"{int(ray['batches_rerun'])} batch(es) re-run after a worker died)")
        if ray.get("batch_done_s"):
            lines.append(f"  {'Ray timeline':<22}first target pose at {ray.get('first_target_s')} s; batches returned at "
                         + ", ".join(f"{t:.0f}" for t in ray["batch_done_s"]) + " s")
    phases = ((manifest.audit or {}).get("simulation") or {}).get("phases")
    if phases and seconds > 0:
        lines.append(f"  stepping / bodies / recording / recoveries / other  {_phase_split(phases)} s over "
                     f"{int(phases.get('frames', 0))} simulator frames")
        if float(phases.get("sim_device_s", 0.0)) > 0:  # CUDA: how much of the loop the frames keep the device busy
            lines.append(f"  {'frames on the device':<26}{float(phases['sim_device_s']):>6.1f} s of the loop's "
                         f"{float(phases.get('loop_s', 0.0)):.1f} s (the rest: host work the device waits for)")
        if int(phases.get("self_contact_substeps", 0)) > 0:  # VBD's pair lists: searched or refreshed
            share = int(phases.get("self_contact_searches", 0)) / int(phases["self_contact_substeps"])
            lines.append(f"  {'self-contact searches':<26}{100.0 * share:>6.1f} % of the world-substeps "
                         f"(the rest refreshed their pair lists)")
        lines.append("  set-up: orders and routes / cloth model / bodies and simulator  "
                     + " / ".join(f"{float(phases.get(k, 0.0)):.1f}" for k in
                                  ("setup_schedules_s", "setup_model_s", "setup_simulator_s")) + " s")
        lines.append(f"  {'  explosions recovered':<26}{int(phases.get('recoveries', 0)):>6}")
        lines.append(f"  {'    of them restarted':<26}{int(phases.get('restarts', 0)):>6}  (from the canonical drape)")
        lines.append(f"  {'  restarts after rejects':<26}{int(phases.get('restarts_after_rejects', 0)):>6}  "
                     f"(worlds sent back to the canonical drape after dropped frames)")
        if int(phases.get("targets_from_home", 0)):
            lines.append(f"  {'  targets from home':<26}{int(phases['targets_from_home']):>6}  "
                         f"(worlds sent back after kept frames, simulation.targets_from_home)")
        lines.append(f"  {'  tasks of other pairs':<26}{int(phases.get('group_switches', 0)):>6}  "
                     f"(worlds that took a task of another style-shape pair, cross_group_tasks)")
    return "\n".join(lines)


def generate(spec_or_path: dict | str | Path, out_dir: str | Path, **options: Any) -> Any:
    """Runs (or resumes) a dataset generation; returns the finished Manifest.

    Checks the spec, ``device`` and ``out_dir`` (a writable directory) before any work, then holds
    ``out_dir``'s writer lock (:mod:`data_manifest.lock`) for the run: a second run on the same
    directory raises DatasetLockedError naming the first. A full disk raises
    :class:`DiskFullError` naming the path, the space needed and the space free. ``options``: see
    :func:`_generate_locked`."""
    from data_manifest.lock import DatasetLock

    from pipelines.errors import check_output_dir

    spec = validate_spec(dict(spec_or_path)) if isinstance(spec_or_path, dict) else load_spec(spec_or_path)
    if spec["poses"]["source"] == "motion":  # motion files are read (and checked) before any work
        from pipelines.dataset_plan import load_motions

        load_motions(spec)
    if options.get("device") is not None:
        resolve_device(options["device"], option="--device")
    out_dir = check_output_dir(out_dir, "--out")
    if isinstance(spec["garment"]["type"], list):
        return generate_types(spec, out_dir, **options)
    lock = DatasetLock(out_dir).acquire()
    try:
        if lock.took_over is not None:
            options.get("log", print)(f"took over the writer lock of an ended run ({lock.took_over.describe()})")
        return _generate_locked(spec, out_dir, **options)
    except Exception as error:  # h5py reports a full disk as OSError or RuntimeError
        from pipelines.errors import is_disk_full

        if is_disk_full(error) and not isinstance(error, DiskFullError):
            raise DiskFullError.at(out_dir, error) from error
        raise
    finally:
        lock.release()


DATASETS_NAME = "datasets.json"
"""The index of a multi-type run: ``OUT/datasets.json`` lists the per-type datasets ``OUT/<type>/``."""
DATASETS_FORMAT = "drape-datasets"


def generate_types(spec: dict, out_dir: Path, **options: Any) -> dict[str, Any]:
    """A spec whose ``garment.type`` is a list: one ordinary dataset per type in ``out_dir/<type>/``
    (:func:`pipelines.spec.type_specs`: the spec with that type, each with its manifest and shards,
    resumable as a single-type run), one after another, and ``out_dir/datasets.json`` listing them
    (rewritten, whole, as each finishes). Holds ``out_dir``'s writer lock for the run; returns the
    finished Manifest per type."""
    import json

    from data_manifest.lock import DatasetLock

    from pipelines.spec import type_specs

    log = options.get("log", print)
    parts = type_specs(spec)
    lock = DatasetLock(out_dir).acquire()
    manifests: dict[str, Any] = {}
    try:
        if lock.took_over is not None:
            log(f"took over the writer lock of an ended run ({lock.took_over.describe()})")

        def write_index() -> None:
            entries = []
            for gtype, sub in parts:
                m = manifests.get(gtype)
                entry = {"type": gtype, "name": sub["name"], "path": gtype, "complete": m is not None}
                if m is not None:
                    entry.update(shards=len(m.shards), frames_kept=int(m.totals.get("frames_kept", 0)))
                entries.append(entry)
            index = {"format": DATASETS_FORMAT, "name": spec["name"], "spec_sha256": spec_hash(spec), "spec": spec,
                     "datasets": entries}
            tmp = out_dir / f".{DATASETS_NAME}.{os.getpid()}.tmp"
            try:
                tmp.write_text(json.dumps(index, indent=2, default=str) + "\n")
                os.replace(tmp, out_dir / DATASETS_NAME)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise

        write_index()
        for k, (gtype, sub) in enumerate(parts):
            log(f"== {spec['name']}: garment type {gtype} ({k + 1} of {len(parts)}) -> {out_dir / gtype}")
            manifests[gtype] = generate(sub, out_dir / gtype, **options)
            write_index()
    finally:
        lock.release()
    total = sum(int(m.totals.get("frames_kept", 0)) for m in manifests.values())
    log(f"{spec['name']}: {len(manifests)} datasets, {total} frames kept: "
        + ", ".join(f"{t} {int(m.totals.get('frames_kept', 0))}" for t, m in manifests.items())
        + f"; index {out_dir / DATASETS_NAME}")
    return manifests


class DiskFullError(OSError):
    """The dataset's file system filled up; the message names the path and the space free.
    Complete shards are kept; the shard being written is removed (rerun to resume)."""

    @classmethod
    def at(cls, out_dir: Path, error: BaseException) -> "DiskFullError":
        from pipelines.errors import free_bytes, human_bytes

        where = getattr(error, "filename", None)
        if not where:  # h5py names the file only in its message
            import re

            found = re.search(r"filename = '([^']+)'", str(error))
            where = found.group(1) if found else out_dir
        free = free_bytes(out_dir)
        reason = getattr(error, "strerror", None)
        if not reason:
            import re

            found = re.search(r"error message = '([^']+)'", str(error))
            reason = found.group(1) if found else str(error).splitlines()[0][:200]
        return cls(f"the disk of {str(out_dir)!r} is full: writing {str(where)!r} failed ({reason}; "
                   f"{human_bytes(free or 0)} free); complete shards are kept, the one being written is "
                   f"removed: free some space and rerun the same command to resume")


def estimated_bytes(tasks: list, template_dict: dict, precision: str) -> int:
    """Lower estimate of the bytes the shards of ``tasks`` take [B]: every target pose kept,
    posed and unposed positions (and a motion's velocities) compressed to half their size (gzip keeps ~85 % of them on the
    t-shirt), the template to a tenth (its skinning weights are mostly zero)."""
    vertices = int(np.asarray(template_dict["rest_vertices"]).shape[0])
    per_value = 2 if precision == "float16" else 4
    frames = sum(len(t.poses) * (3 if getattr(t, "motion_steps", 0) else 2) for t in tasks)  # motions: + velocities
    template = sum(np.asarray(v).nbytes for v in template_dict.values() if v is not None)
    return int(frames * vertices * 3 * per_value * 0.5 + len(tasks) * template * 0.1)


def _generate_locked(spec_or_path: dict | str | Path, out_dir: str | Path, *, executor: str = "local",
                     device: str | None = None, ray_address: str | None = None, ray_cpus: int | None = None,
                     progress: bool = True,
                     log: Callable[[str], None] = print, heartbeat_s: float = 30.0,
                     on_heartbeat: Callable[[dict], None] | None = None, save_every_s: float = 10.0,
                     max_batches: int | None = None) -> Any:
    """Runs (or resumes) a dataset generation in ``out_dir`` (whose writer lock the caller holds);
    returns the finished Manifest.

    Without ``progress`` bars, a line of progress is logged at most every ``heartbeat_s`` seconds.
    ``on_heartbeat`` (local executor, with or without bars) gets the same numbers as a dict at each
    heartbeat: seconds since simulation began, target poses done and total, shards written, frames
    kept and dropped by reason over the shards listed so far (kept_in_shards, dropped_in_shards),
    and the simulator's running counts (frames, world_frames, sim_s, body_s, record_s, recoveries).
    The manifest is saved after each batch and, within a batch, at most every ``save_every_s`` seconds
    as shards finish (0: after every shard). ``ray_address``: the Ray cluster of ``executor="ray"``
    (default: a Ray started for this run with ``ray_cpus`` CPUs, default all); heartbeats and the
    summary then add up every worker's batches (:mod:`pipelines.executors`). ``max_batches``: simulate
    only the first this many of the batches left, then stop as a killed run would (the manifest lists
    their shards and the same command without it resumes the rest); benchmarks time one GPU on part
    of a plan with it."""
    from data_manifest.manifest import Manifest, collect_provenance
    from data_manifest.schema import template_sha256
    from data_manifest.shard import remove_orphan_temporaries

    from pipelines.executors import EXECUTORS, run_local, run_ray

    if executor not in EXECUTORS:
        raise ValueError(f"--executor must be one of {', '.join(EXECUTORS)} (got {executor!r})")
    if max_batches is not None and (not isinstance(max_batches, int) or isinstance(max_batches, bool) or max_batches < 1):
        raise ValueError(f"max_batches must be an integer >= 1 or None (got {max_batches!r})")
    spec = validate_spec(dict(spec_or_path)) if isinstance(spec_or_path, dict) else load_spec(spec_or_path)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    ctx = build_context(spec, out_dir, device=device, log=log)
    splits: dict[str, list[str]] = {}
    for t in ctx.plan.tasks:
        splits.setdefault(t.split, []).append(t.task_id)
    provenance = collect_provenance(device=ctx.device, seeds={"spec": int(spec["seed"])}, command=" ".join(sys.argv))
    manifest = Manifest.load_or_create(out_dir, name=spec["name"], spec=spec, template_sha256=template_sha256(ctx.template_dict),
                                       precision=spec["output"]["precision"], provenance=provenance, splits=splits)
    remove_orphan_temporaries(out_dir)
    worlds = int(spec["simulation"]["worlds"])
    all_batches = plan_batches(ctx.plan.tasks, worlds, int(spec["simulation"]["batches"]))
    done = {t.task_id for t in ctx.plan.tasks if manifest.is_complete(t.task_id)}
    batches = [b for b in all_batches if not set(b) <= done][:max_batches]
    pending = [ctx.tasks[t] for b in batches for t in b if t not in done]
    if done:
        log(f"resuming: {len(done)} of {len(ctx.plan.tasks)} shards already complete")
    # which sampled poses were pruned before simulation, and why, for the record
    plan = ctx.plan
    pruned_tmp = out_dir / "pruned_poses.npz.tmp"
    try:
        with open(pruned_tmp, "wb") as fh:
            np.savez(fh, poses=plan.pruned_poses, reason=plan.pruned_reasons)
        os.replace(pruned_tmp, out_dir / "pruned_poses.npz")
    except BaseException:
        pruned_tmp.unlink(missing_ok=True)
        raise
    if len(plan.pruned_reasons):
        why, counts = np.unique(plan.pruned_reasons, return_counts=True)
        log("pruned sampled poses before simulation: " + ", ".join(f"{c} {w}" for w, c in zip(why, counts))
            + f" (poses.min_clearance {spec['poses']['min_clearance']}; {out_dir / 'pruned_poses.npz'})")
    total_keys = sum(len(t.poses) for t in pending)
    from pipelines.errors import free_bytes, human_bytes

    needed, free = estimated_bytes(pending, ctx.template_dict, spec["output"]["precision"]), free_bytes(out_dir)
    if free is not None and needed > free:
        raise DiskFullError(f"not enough free space in {str(out_dir)!r}: the {len(pending)} shards to write need about "
                            f"{human_bytes(needed)} (a low estimate), {human_bytes(free)} are free; free some space "
                            f"or choose another --out")
    from tqdm import tqdm

    bar = tqdm(total=total_keys, desc=f"{spec['name']}: target poses", unit="frame", disable=not progress, file=sys.stderr)

    kept_this_run = [0]

    saved = {"at": time.perf_counter()}

    def save_manifest() -> None:
        manifest.save()
        saved["at"] = time.perf_counter()

    def on_shard(record) -> None:
        kept_this_run[0] += int(record["frame_count"] if isinstance(record, dict) else record.frame_count)
        manifest.add_shard(record)
        # the manifest is rewritten whole: once per shard made the run quadratic in the shard count
        # (24 ms per save at 140 shards on the device host). A shard that is complete but not yet
        # listed is simply written again by a resumed run (its batch is simulated again anyway).
        if time.perf_counter() - saved["at"] >= save_every_s:
            save_manifest()
        bar.set_postfix(shards=f"{len(manifest.shards)}/{len(ctx.plan.tasks)}", refresh=False)

    log(f"simulating {len(pending)} tasks ({total_keys} target poses) in {len(batches)} batch(es) of at most "
        f"{worlds} worlds on {ctx.device}")
    beat = {"done": 0, "calls": 0, "last": time.perf_counter()}

    from pipelines.errors import raise_if_interrupted

    def on_progress(count: int) -> None:
        raise_if_interrupted()  # a Ctrl-C or SIGTERM whose exception a finalizer swallowed
        bar.update(count)
        beat["done"] += count
        beat["calls"] += 1  # local executor: one call per simulator frame; Ray: per poll of the workers
        heartbeat()

    def add_phases(phases: dict) -> None:
        """Sums a Ray batch's run_sequences statistics into the run's (the local executor adds to ctx.phases itself)."""
        for key, value in phases.items():
            ctx.phases[key] = ctx.phases.get(key, 0.0) + float(value)

    def after_batch() -> None:
        save_manifest()
        heartbeat(force=True)  # the batch's last shards are listed only now (their writes finish in the background)

    def heartbeat(force: bool = False) -> None:
        now = time.perf_counter()
        if force or now - beat["last"] >= heartbeat_s:
            # headless runs (logs of cluster or device jobs) still say how far they are
            beat["last"] = now
            elapsed = now - t_sim
            ph = dict(ctx.phases or {})  # Ray: the batches finished so far
            if on_heartbeat is not None:
                totals = manifest.totals
                on_heartbeat({"elapsed_s": elapsed, "targets_done": beat["done"], "targets_total": total_keys,
                              "shards": len(manifest.shards), "tasks": len(ctx.plan.tasks),
                              "kept_in_shards": totals["frames_kept"], "dropped_in_shards": totals["frames_dropped"], **ph})
            if progress:
                return
            line = (f"  {elapsed:7.1f} s: {beat['done']}/{total_keys} target poses "
                    f"({beat['done'] / max(elapsed, 1e-9):.1f}/s), {len(manifest.shards)}/{len(ctx.plan.tasks)} shards")
            if ph.get("frames"):
                line += (f", {int(ph['frames'])} simulator frames ({int(ph['world_frames'])} world-frames, "
                         f"{ph['world_frames'] / max(beat['done'], 1):.1f} per target: moving / holding / settling "
                         + " / ".join(f"{ph.get(k + '_world_frames', 0) / max(beat['done'], 1):.1f}"
                                      for k in ("transition", "hold", "settle"))
                         + "); stepping / bodies / recording / "
                         f"recoveries / other {_phase_split(ph)} s, {int(ph.get('recoveries', 0))} recoveries "
                         f"({int(ph.get('restarts', 0))} restarts; explosions "
                         f"non-finite / speed / stretch {int(ph.get('exploded_non_finite', 0))} / "
                         f"{int(ph.get('exploded_speed', 0))} / {int(ph.get('exploded_stretch', 0))}), "
                         f"{int(ph.get('restarts_after_rejects', 0))} restarts after rejects, "
                         f"{int(ph.get('group_switches', 0))} tasks of other pairs, "
                         f"{int(ph.get('body_calls', 0))} body-model calls")
            log(line)

    t_sim = time.perf_counter()
    ctx.phases = {}
    cluster = None
    if executor == "local":
        run_local(ctx, out_dir, batches, simulate_batch=simulate_batch, on_shard=on_shard, on_progress=on_progress,
                  on_batch=after_batch, skip=done)
    else:
        cluster = run_ray(spec, out_dir, batches, build_context=build_context, simulate_batch=simulate_batch,
                          device=ctx.device, on_shard=on_shard, on_progress=on_progress, on_batch=after_batch,
                          on_phases=add_phases, address=ray_address, num_cpus=ray_cpus, skip=done, log=log,
                          prepared=ctx.prepared)
    bar.close()
    sim_seconds = time.perf_counter() - t_sim
    audit = dict(manifest.audit or {})
    if pending:
        # amortized simulation cost of this run (what drape evaluate compares learners with)
        audit["simulation"] = {"seconds": round(sim_seconds, 3), "target_frames": int(total_keys),
                               "kept_frames": int(kept_this_run[0]), "device": ctx.device,
                               "worlds": int(spec["simulation"]["worlds"])}
        if cluster is not None:  # where the batches ran: worker processes, nodes, GPUs, batches re-run
            audit["simulation"]["ray"] = cluster
        if ctx.phases:
            # where the simulation time went (frames: simulator frames; *_s: seconds stepping,
            # posing bodies, recording frames; recoveries: explosions survived)
            audit["simulation"]["phases"] = {k: round(float(v), 3) for k, v in ctx.phases.items()}
        manifest.audit = audit
        if int(spec["audit"]["samples"]) > 0:
            save_manifest()  # a kill during the audit keeps the simulation's record
    # the audit block: after new shards, or where a run was stopped before its audit ended
    if int(spec["audit"]["samples"]) > 0 and (pending or "samples" not in audit):
        from pipelines.audit import audit_dataset

        simulation = audit.pop("simulation", None)
        audit.update(audit_dataset(ctx, out_dir, manifest, log=log))
        if simulation is not None:
            audit["simulation"] = simulation
        manifest.audit = audit
    manifest.finish()
    manifest.save()
    log(_summary_table(manifest, sim_seconds, total_keys))
    log(f"  {'total wall time':<22}{time.perf_counter() - t0:>9.1f} s\n  manifest: {out_dir / 'manifest.json'}")
    return manifest


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("generate-dataset", help="simulate a dataset spec into sharded HDF5 + manifest",
                       description="Runs (or resumes) a dataset spec: plans styles/shapes/poses, simulates every "
                       "style-shape pair through its poses, filters frames and writes one HDF5 shard per task. "
                       "Rerunning the same command skips finished shards. A spec with a list of garment types "
                       "writes one dataset per type, OUT/<type>/, listed in OUT/datasets.json.")
    p.add_argument("spec", help="spec YAML path, or the name of a shipped spec (quickstart, tailornet-tshirt, "
                   "tailornet-shirt, tailornet-pants, tailornet-skirt, cloth3d-mini, cloth3d)")
    p.add_argument("--out", required=True, help="dataset directory")
    p.add_argument("--executor", default="local", choices=["local", "ray"], help="where batches run (default local)")
    p.add_argument("--device", default=None, help="override simulation.device (auto, cpu, cuda:0)")
    p.add_argument("--ray-address", default=None, help="Ray cluster address, e.g. 10.0.0.1:6379 or auto (default: "
                   "start a Ray on this host for the run); one batch per GPU, see docs/scale-out.md")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=lambda a: (generate(a.spec, a.out, executor=a.executor, device=a.device, ray_address=a.ray_address,
                                            progress=not a.no_progress), 0)[1])
