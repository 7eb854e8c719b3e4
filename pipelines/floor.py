"""``drape report floor --data DIR --out OUT``: the error floor of a dataset itself.

Two figures a learner cannot be expected to beat, printed beside the learners by
``drape evaluate --floor OUT/floor.json``:

- **history** (the drape's dependence on the path that led to it): the same garment (style),
  body (shape) and target pose reached along two different pose sequences, relaxed by the
  dataset's own simulator and settings (spec in the manifest). Sequence A is the dataset's
  own: the ``prefix`` target poses that precede the probe pose in the task's visiting order,
  then the probe. Sequence B replaces those predecessors by the ``prefix`` poses of the same
  task farthest from the probe (largest joint-angle distance). The figure is the mean
  per-vertex distance [mm] between the two final drapes, posed and unposed (inverse
  skinning, as the learners' targets). A quasi-static learner sees (style, shape, pose) only,
  so it cannot tell the two apart: half of the distance (the mean of the two drapes is
  equidistant) is an estimate of what history alone adds to any learner's error. The
  convergence tolerance of the hold is part of it, as it is part of the data.
- **single pair** (TailorNet section 6.1): one MLP of pose per training style-shape pair,
  trained on that pair's ``train_train`` frames and evaluated on its ``train_test`` frames
  (:mod:`learn.tailornet.single_pair`): the error of a model that never has to generalise
  over style or shape.

A command rather than a bench script: its JSON is an input of ``drape evaluate`` and belongs
to the dataset, not to a machine's timing.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class Probe:
    """One history probe: a style on a shape reaching ``sequence_a[-1]`` (= ``sequence_b[-1]``).

    style_index: index into the context's styles; shape: body shape (S,); sequence_a,
    sequence_b: target poses (n, P) in visiting order, the last one shared; task_id, key: where
    the probe pose comes from in the dataset's plan.
    """

    style_index: int
    shape: np.ndarray
    sequence_a: np.ndarray
    sequence_b: np.ndarray
    task_id: str = ""
    key: int = -1
    garment_index: int = -1  # the task's garment (rest geometry, canonical drape); -1: the style's
    fabric: str | None = None  # the task's fabric; None: the spec's
    start_shape: np.ndarray | None = None  # the task's start shape (tightness); None: the neutral shape


def _joint_angle_distance(poses: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Sum over joints of the axis-angle difference's norm [rad], (N,), poses (N, P), pose (P,)."""
    diff = (np.asarray(poses, np.float64) - np.asarray(pose, np.float64)[None]).reshape(len(poses), -1, 3)
    return np.linalg.norm(diff, axis=-1).sum(axis=1)


def plan_probes(tasks: list, *, split: str = "train_train", pairs: int = 4, targets: int = 4,
                prefix: int = 1) -> list[Probe]:
    """Probes on the first ``pairs`` tasks of ``split`` (one per style-shape pair) at ``targets``
    evenly spaced target poses each (keys >= ``prefix``); see the module docstring for A and B.
    ``tasks``: the dataset plan's tasks (``pipelines.dataset_plan.Task``)."""
    for name, value, minimum in (("pairs", pairs, 1), ("targets", targets, 1), ("prefix", prefix, 1)):
        if int(value) != value or value < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    chosen, seen = [], set()
    for task in tasks:
        key = (int(task.style_index), np.asarray(task.shape, np.float32).tobytes())
        if task.split == split and key not in seen and len(task.poses) > prefix + 1:
            seen.add(key)
            chosen.append(task)
        if len(chosen) == pairs:
            break
    if not chosen:
        raise ValueError(f"no task of split {split!r} has more than {prefix + 1} target poses to probe")
    probes = []
    for task in chosen:
        poses = np.asarray(task.poses, np.float32)
        keys = np.unique(np.linspace(prefix, len(poses) - 1, targets).round().astype(int))
        for key in keys:
            others = np.setdiff1d(np.arange(len(poses)), np.arange(key - prefix, key + 1))
            farthest = others[np.argsort(-_joint_angle_distance(poses[others], poses[key]), kind="stable")[:prefix]]
            if farthest.size < prefix:
                continue
            probes.append(Probe(int(task.style_index), np.asarray(task.shape, np.float32),
                                poses[key - prefix:key + 1], np.concatenate([poses[farthest[::-1]], poses[key:key + 1]]),
                                task_id=str(task.task_id), key=int(key),
                                garment_index=int(getattr(task, "garment_index", -1)), fabric=getattr(task, "fabric", None),
                                start_shape=getattr(task, "start_shape", None)))
    return probes


def _final_frames(ctx, probes: list[Probe], which: str, settings) -> list:
    """The recorded frame of each probe's last target along sequence ``which`` ("a" or "b"); all
    probes run as worlds of one batch, so A and B batches have the same company."""
    import torch

    from simulate.sequence import SequenceTask, run_sequences

    def garment(p: Probe) -> int:
        return p.style_index if p.garment_index < 0 else p.garment_index

    tasks = [SequenceTask(rest_vertices=ctx.style_rest[garment(p)], start_vertices=ctx.style_start[garment(p)],
                          shape=p.shape, poses=getattr(p, f"sequence_{which}"),
                          fabric=ctx.spec["garment"]["fabric"] if p.fabric is None else p.fabric, start_shape=p.start_shape)
             for p in probes]
    last = {}

    def on_frame(frame) -> bool:
        if frame.key == len(tasks[frame.task].poses) - 1:
            last[frame.task] = frame
        return True

    with torch.no_grad():
        run_sequences(ctx.body, ctx.template.faces, tasks, body_faces=ctx.body_faces,
                      body_face_groups=ctx.body_face_groups, body_part=ctx.body_part, settings=settings,
                      device=ctx.device, on_frame=on_frame, material_uv=ctx.template.face_uv,
                      attached=ctx.template.attachment)
    return [last[i] for i in range(len(tasks))]


def history_floor(ctx, probes: list[Probe], *, settings=None) -> dict[str, Any]:
    """Distances between the drapes of each probe's two sequences, simulated with ``ctx``
    (``pipelines.generate_dataset.build_context``) and ``settings`` (default: the spec's).

    Returns ``probes`` (per probe: task_id, key, posed_mm, unposed_mm, statuses), the means
    over the probes whose both drapes are finite and not exploded (``posed_mm``,
    ``unposed_mm``; and ``converged_*`` over those whose both holds converged) and the counts.
    """
    from simulate.quasi_static import WorldStatus

    from pipelines.generate_dataset import Unskinner, sequence_settings

    if not probes:
        raise ValueError("history_floor needs at least one probe")
    settings = settings or sequence_settings(ctx.spec)
    frames_a = _final_frames(ctx, probes, "a", settings)
    frames_b = _final_frames(ctx, probes, "b", settings)
    unskin = Unskinner(ctx.template.skinning_weights, ctx.device)
    rows, used, converged = [], [], []
    for i, (probe, a, b) in enumerate(zip(probes, frames_a, frames_b)):
        ok = (np.isfinite(a.positions).all() and np.isfinite(b.positions).all()
              and WorldStatus.EXPLODED not in (a.status, b.status))
        row = {"task_id": probe.task_id, "key": probe.key, "status_a": WorldStatus(a.status).name,
               "status_b": WorldStatus(b.status).name, "hold_frames_a": int(a.frames), "hold_frames_b": int(b.frames)}
        if ok:
            unposed = unskin(np.stack([a.positions, b.positions]), np.stack([a.skinning_transforms, b.skinning_transforms]))
            row["posed_mm"] = float(np.linalg.norm(np.asarray(a.positions, np.float64) - b.positions, axis=-1).mean() * 1e3)
            row["unposed_mm"] = float(np.linalg.norm(unposed[0] - unposed[1], axis=-1).mean() * 1e3)
            used.append(i)
            if a.status == b.status == WorldStatus.CONVERGED:
                converged.append(i)
        rows.append(row)
    result: dict[str, Any] = {"probes": rows, "probe_count": len(probes), "used": len(used),
                              "converged_both": len(converged)}
    for label, subset in (("", used), ("converged_", converged)):
        for metric in ("posed_mm", "unposed_mm"):
            values = [rows[i][metric] for i in subset]
            result[f"{label}{metric}"] = float(np.mean(values)) if values else None
    return result


def _context(spec: dict, data: Path, out: Path, device: str | None):
    """The generate-dataset context (body, template, canonical drapes) of ``spec``; the canonical
    drapes are read from the dataset's cache when it has them, else computed and cached in ``out``."""
    from pipelines.generate_dataset import build_context
    from pipelines.spec import spec_hash

    cached = data / "cache" / f"garments-{spec_hash(spec)[:16]}.npz"
    return build_context(spec, data if cached.is_file() else out, device=device, log=lambda m: None)


def floor(data: str | Path, out: str | Path, *, device: str | None = None, history: bool = True,
          single_pair: bool = True, pairs: int = 4, targets: int = 4, prefix: int = 1,
          single_pair_epochs: int | None = None, train_device: str = "cpu", seed: int = 0,
          progress: bool = False, log=print) -> dict[str, Any]:
    """Library form of ``drape report floor``; writes ``out/floor.json`` and returns it."""
    from data_manifest.reader import DatasetReader

    from pipelines.errors import check_output_dir
    from pipelines.spec import validate_spec, without_library_settings

    data, out = Path(data), check_output_dir(out, "--out")
    reader = DatasetReader(data)
    report: dict[str, Any] = {"data": str(data.resolve()), "dataset_manifest": reader.manifest.name}
    if history:
        t0 = time.perf_counter()
        spec = validate_spec(without_library_settings(json.loads(json.dumps(reader.manifest.spec))))
        ctx = _context(spec, data, out, device)
        probes = plan_probes(ctx.plan.tasks, pairs=pairs, targets=targets, prefix=prefix)
        report["history"] = history_floor(ctx, probes)
        report["history"].update(prefix=prefix, device=ctx.device, seconds=round(time.perf_counter() - t0, 2))
        h = report["history"]
        log(f"history: {h['used']} of {h['probe_count']} probes, mean distance between the two drapes "
            f"{_mm(h['unposed_mm'])} unposed, {_mm(h['posed_mm'])} posed ({h['converged_both']} with both holds converged: "
            f"{_mm(h['converged_unposed_mm'])} unposed)")
    if single_pair:
        from learn.tailornet.single_pair import single_pair_floor

        t0 = time.perf_counter()
        report["single_pair"] = single_pair_floor(reader, data, device=train_device, epochs=single_pair_epochs,
                                                  run_dir=out / "single_pair", seed=seed, progress=progress)
        report["single_pair"]["seconds"] = round(time.perf_counter() - t0, 2)
        s = report["single_pair"]
        log(f"single pair: {s['pairs']} pairs, train_test error {_mm(s['test_error_mm'])} "
            f"(train_train {_mm(s['train_error_mm'])}, worst pair {_mm(s['worst_pair_test_error_mm'])})")
    tmp = out / "floor.json.tmp"
    tmp.write_text(json.dumps(report, indent=2))
    tmp.replace(out / "floor.json")
    log(f"report: {out / 'floor.json'}")
    return report


def _mm(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f} mm"


def run_floor_command(args: argparse.Namespace) -> int:
    from pipelines.errors import UsageError, check_number, check_torch_device

    for name in ("pairs", "targets", "prefix"):
        check_number(getattr(args, name), f"--{name}", minimum=1, integer=True)
    if args.epochs is not None:
        check_number(args.epochs, "--epochs", minimum=1, integer=True)
    check_torch_device(args.train_device, "--train-device")
    if args.skip_history and args.skip_single_pair:
        raise UsageError("--skip-history and --skip-single-pair together leave nothing to measure")
    floor(args.data, args.out, device=None if args.device == "auto" else args.device, history=not args.skip_history,
          single_pair=not args.skip_single_pair, pairs=args.pairs, targets=args.targets, prefix=args.prefix,
          single_pair_epochs=args.epochs, train_device=args.train_device, seed=args.seed,
          progress=not args.no_progress)
    return 0


def register_report(reports: argparse._SubParsersAction) -> None:
    """``drape report floor`` (hooked into ``drape report``'s subcommands)."""
    f = reports.add_parser("floor", help="the dataset's own error floor: history dependence and single-pair MLPs",
                           description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    f.add_argument("--data", required=True, help="dataset directory (from drape generate-dataset)")
    f.add_argument("--out", required=True, help="output folder (floor.json; single_pair/ checkpoints)")
    f.add_argument("--device", default=None,
                   help="simulation device (auto, cpu, cuda:N; default: the dataset spec's simulation.device)")
    f.add_argument("--train-device", default="cpu", help="torch device training the single-pair MLPs")
    f.add_argument("--pairs", type=int, default=4, help="style-shape pairs probed for history (default 4)")
    f.add_argument("--targets", type=int, default=4, help="target poses probed per pair (default 4)")
    f.add_argument("--prefix", type=int, default=1, help="preceding target poses that differ between the two "
                                                         "sequences (default 1)")
    f.add_argument("--epochs", type=int, default=None, help="single-pair MLP epochs (default: the HF stage's, 800)")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--skip-history", action="store_true", help="no simulation, only the single-pair error")
    f.add_argument("--skip-single-pair", action="store_true", help="no training, only the history figure")
    f.add_argument("--no-progress", action="store_true")
    f.set_defaults(func=run_floor_command)
