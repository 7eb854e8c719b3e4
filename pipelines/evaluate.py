"""``drape evaluate RUN --data DIR``: predicted against simulated drapes.

For every test split (train_test, test_train, test_test) and every model in RUN
(each learner of learn/registry.py trained on datasets whose model file is there: tailornet,
baseline, uvimage, uvimage_pca, collision_aware): mean per-vertex error in mm on unposed displacements
(as TailorNet reports) and on posed vertices, the normal error (1 - cos of predicted and
simulated vertex normals, seed 001), the collision rate (share of garment vertices
deeper than 1 mm inside the body along the nearest face normal) without and with the
Laplacian-preserving post-process, and inference ms/frame at batch 1 and batched on
the CPU and on the GPU when there is one. The simulator's amortized ms per kept frame
comes from the dataset's manifest; the speed-up is their ratio. Writes
``RUN/evaluation/evaluation.json``, ``error_vs_time.png`` (learners and the simulator in
one picture; the simulator's settings sweep is added when ``--accuracy-report`` points
at a ``drape report accuracy`` JSON) and a few renders of predicted vs simulated drapes
coloured by per-vertex error.

A run of a learner trained on a static set (registry ``data`` ``static_set``: gcvae,
``RUN/gcvae_model.pt``) is evaluated on a ``drape static-set`` directory instead: surface error,
normal angle, mask IoU and KL per garment type on its test and train splits
(learn/gcvae/evaluate.py), in ``RUN/evaluation/evaluation.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

TEST_SPLITS = ("train_test", "test_train", "test_test")


def _load_models(run_dir: Path, fingerprint, device: str, data: str = "dataset") -> dict:
    """{name: model} of the learners trained on ``data`` (a registry ``data`` kind) whose model
    file is in ``run_dir``; raises naming the file when one is unreadable, or when there is none."""
    from learn.registry import LEARNERS

    models = {}
    learners = {name: entry for name, entry in LEARNERS.items() if entry.data == data}
    for name, entry in learners.items():
        file = run_dir / entry.model_file
        if file.is_file():
            try:
                models[name] = entry.load(file, fingerprint=fingerprint, require_same_manifest=False, device=device)
            except Exception as exc:  # torch.load raises pickle, runtime and zip errors on a damaged file
                from learn.tailornet.train import DatasetMismatchError

                if isinstance(exc, DatasetMismatchError):
                    raise
                raise ValueError(f"{str(file)!r} is not a readable {name} checkpoint ({type(exc).__name__}: "
                                 f"{' '.join(str(exc).split())[:200]}); rerun drape train") from None
    if not models:
        files = ", ".join(entry.model_file for entry in learners.values())
        raise FileNotFoundError(f"no trained model in {run_dir} (expected one of {files}; run drape train first)")
    return models


def _canonical_collisions(results: dict, model, run_dir: Path, splits: dict, device: str) -> None:
    """Adds ``canonical_collision_rate`` to collision_aware's metrics of every split: its
    predicted canonical garments' vertices inside the canonical body by more than the collision
    threshold, by the run's ``sdf.pt`` (none without it). Set against ``collision_rate`` it says
    whether collisions come from the generative space or from the posing."""
    from learn.collision_aware.sdf import load_run_sdf
    from learn.tailornet.evaluate import sequence_root

    sdf = load_run_sdf(run_dir, device)
    if sdf is None:
        return
    for split, frames in splits.items():
        results["splits"][split]["collision_aware"]["canonical_collision_rate"] = model.canonical_collision_rate(
            sdf, frames.pose, frames.shape, frames.style, sequence=frames.sequence, frame_index=frames.frame_index,
            root=sequence_root(frames), device=device)


def simulator_ms_per_frame(manifest) -> float | None:
    """Amortized simulation wall time per kept frame [ms] recorded by generate-dataset."""
    sim = (manifest.audit or {}).get("simulation") if manifest.audit else None
    if not sim or not sim.get("kept_frames"):
        return None
    return 1e3 * float(sim["seconds"]) / float(sim["kept_frames"])


def missing_simulator_time(manifest) -> str | None:
    """Why the manifest gives no simulator time per kept frame (None when it does)."""
    sim = (manifest.audit or {}).get("simulation") if manifest.audit else None
    if not sim:
        return ("the dataset's manifest records no simulation time: generate-dataset stopped before "
                "it finished (rerun the same command to complete it)")
    if not sim.get("kept_frames"):
        return "the dataset kept no frames, so there is no time per kept frame"
    return None


def default_postprocess_workers() -> int:
    """Processes for the post-process: half the usable CPUs, at most 16, 1 below 8 CPUs (a
    worker's start costs seconds, worth it only where many frames share many cores)."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 1 if cpus < 8 else min(16, cpus // 2)


def floor_rows(floor: dict) -> list[tuple[str, str, float]]:
    """(split, label, mm) rows of a ``drape report floor`` JSON for the evaluation table: the
    history distance between two drapes halved (their mean is that far from each), and the
    single-pair error on train_test."""
    rows = []
    history = floor.get("history") or {}
    if history.get("unposed_mm") is not None:
        rows.append(("all", "floor:history", 0.5 * float(history["unposed_mm"])))
    single = floor.get("single_pair") or {}
    if single.get("test_error_mm") is not None:
        rows.append(("train_test", "floor:1-pair", float(single["test_error_mm"])))
    return rows


def evaluate(run_dir: str | Path, data: str | Path, *, device: str = "cpu", out: str | Path | None = None,
             postprocess_frames: int | None = 32, renders: int = 3, accuracy_report: str | None = None,
             postprocess_workers: int | None = None, floor: str | None = None, analysis: bool = False,
             log=print) -> dict:
    import torch

    from data_manifest.reader import DatasetReader
    from learn.common.skinning import garment_posing_functions
    from learn.data import DrapeDataset
    from learn.tailornet.evaluate import PosingContext, evaluate_models, predict_vertices
    from learn.tailornet.plots import plot_error_vs_runtime, render_prediction
    from learn.tailornet.train import dataset_fingerprint, frame_arrays_from_dataset
    from simulate.body import load_body_model

    from pipelines.errors import UsageError, check_number, check_output_dir, check_torch_device

    run_dir, data = Path(run_dir), Path(data)
    if not run_dir.is_dir():
        raise UsageError(f"RUN {str(run_dir)!r} is not a directory (a run directory from drape train)")
    check_torch_device(device)
    if postprocess_frames is not None:
        check_number(postprocess_frames, "--postprocess-frames", minimum=0, integer=True)
    check_number(renders, "--renders", minimum=0, integer=True)
    if floor and not Path(floor).is_file():
        raise UsageError(f"--floor {floor!r} does not exist (a floor.json from drape report floor)")
    if postprocess_workers is None:
        postprocess_workers = default_postprocess_workers()
    check_number(postprocess_workers, "--postprocess-workers", minimum=1, integer=True)
    if accuracy_report and not Path(accuracy_report).is_file():
        raise UsageError(f"--accuracy-report {accuracy_report!r} does not exist (an accuracy.json from drape report accuracy)")
    reader = DatasetReader(data)
    out = check_output_dir(Path(out) if out else run_dir / "evaluation", "--out")
    template = reader.template
    fingerprint = dataset_fingerprint(data, template)
    models = _load_models(run_dir, fingerprint, device)
    info = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").is_file() else {}
    body_spec = info.get("body", {"backend": "anny", "path": None})
    body = load_body_model(body_spec.get("backend", "anny"), path=body_spec.get("path"))
    posing = PosingContext(*garment_posing_functions(body, template["body_vertex_index"], template["skinning_weights"],
                                                     rest_vertices=template["rest_vertices"]), body.faces, template["faces"])
    splits = {s: frame_arrays_from_dataset(DrapeDataset(data, s, frequencies=False))
              for s in TEST_SPLITS if s in reader.splits and reader.num_frames(s) > 0}
    if not splits:
        raise ValueError(f"dataset {data} has no frames in any test split ({', '.join(TEST_SPLITS)})")
    timing_devices = ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",)
    t0 = time.perf_counter()
    results = evaluate_models(models, splits, posing=posing, postprocess=True, postprocess_frames=postprocess_frames,
                              device=device, timing_devices=timing_devices, timing_batch_sizes=(1, 32),
                              postprocess_workers=postprocess_workers)
    if "collision_aware" in models:
        _canonical_collisions(results, models["collision_aware"], run_dir, splits, device)
    results["evaluation_seconds"] = round(time.perf_counter() - t0, 2)
    if floor:
        results["floor"] = json.loads(Path(floor).read_text())
    if analysis:
        from learn.tailornet.analysis import error_analysis

        train_split = next((s for s in ("train_train", "train") if s in reader.splits and reader.num_frames(s) > 0), None)
        if train_split is None:
            raise ValueError(f"--analysis needs the dataset's training split (train_train), {data} has none")
        train_frames = frame_arrays_from_dataset(DrapeDataset(data, train_split, frequencies=False))
        results["analysis"] = error_analysis(models, train_frames, splits, device=device)
    sim_ms = simulator_ms_per_frame(reader.manifest)
    results["simulator"] = {"ms_per_kept_frame": sim_ms, "device": reader.manifest.provenance.get("device"),
                            "audit_mean_mm": (reader.manifest.audit or {}).get("mean_mm")}
    speedups = {}
    for name, per_dev in results["timing"].items():
        for dev, t in per_dev.items():
            ms = t.get("ms_per_frame_batch_32")
            if sim_ms and ms:
                speedups[f"{name}@{dev}"] = sim_ms / ms
    results["speedup_over_simulator"] = speedups
    if sim_ms is None:
        results["simulator"]["missing"] = missing_simulator_time(reader.manifest)
    results["seconds"] = round(time.perf_counter() - t0, 2)
    (out / "evaluation.json").write_text(json.dumps(results, indent=2, default=float))

    points = []
    first = next(iter(splits))
    for name, per_dev in results["timing"].items():
        err = results["splits"][first][name]["unposed_error_mm"]
        for dev, t in per_dev.items():
            for key, label in (("ms_per_frame_batch_1", "batch 1"), ("ms_per_frame_batch_32", "batch 32")):
                if t.get(key):
                    points.append({"label": f"{name} {dev} {label}", "ms_per_frame": float(t[key]), "error_mm": float(err)})
    if sim_ms:
        audit = (reader.manifest.audit or {}).get("mean_mm", {})
        points.append({"label": "simulator (dataset settings)", "ms_per_frame": sim_ms,
                       "error_mm": float(audit.get("median", 0.0)) or 1e-3})
    if accuracy_report and Path(accuracy_report).is_file():
        from simulate.reports.pareto import plot_error_vs_time

        acc = json.loads(Path(accuracy_report).read_text())
        sim_points = [p for p in acc.get("points", acc.get("settings", [])) if "ms_per_frame" in p and "error_mm" in p]
        plot_error_vs_time(sim_points, out / "error_vs_time.png", extra_points=points,
                           title="learners vs simulator settings")
    else:
        plot_error_vs_runtime(points, out / "error_vs_time.png",
                              title=f"error ({first}, unposed mean per vertex) vs time per frame")
    split_for_renders = "test_test" if "test_test" in splits else first
    frames = splits[split_for_renders]
    name = "tailornet" if "tailornet" in models else next(iter(models))
    for k, i in enumerate(np.linspace(0, frames.frame_count - 1, min(renders, frames.frame_count)).astype(int)):
        rows = np.array([i])
        if getattr(models[name], "recurrent", False) and frames.sequence is not None:
            # frame i at the end of its sequence's frames up to it, run in order (their steps taken as
            # one frame each and the root as still: a picture, the metrics above run the sequences exactly)
            same = np.flatnonzero((frames.sequence == frames.sequence[i]) & (frames.frame_index <= frames.frame_index[i]))
            rows = same[np.argsort(frames.frame_index[same], kind="stable")]
        pred = predict_vertices(models[name], frames.pose[rows], frames.shape[rows], frames.style[rows], posing=posing,
                                device=device)[-1]
        body_v = body.pose(frames.shape[i], frames.pose[i]).vertices[0]
        render_prediction(pred, frames.posed_vertices[i], template["faces"], out / f"render_{split_for_renders}_{k}.png",
                          body_vertices=body_v, body_faces=body.faces, title=f"{name}, {split_for_renders} frame {i}")
    table = [f"{'split':<12}{'model':<13}{'unposed mm':>11}{'posed mm':>10}{'normal':>8}{'coll %':>8}{'coll pp %':>10}"]
    for split, per_model in results["splits"].items():
        for m, r in per_model.items():
            table.append(f"{split:<12}{m:<13}{r['unposed_error_mm']:>11.2f}{r.get('posed_error_mm', float('nan')):>10.2f}"
                         f"{r.get('normal_error', float('nan')):>8.4f}"
                         f"{100 * r.get('collision_rate', float('nan')):>8.2f}{100 * r.get('collision_rate_postprocessed', float('nan')):>10.2f}")
    for split, label, mm in floor_rows(results.get("floor", {})):
        table.append(f"{split:<12}{label:<13}{mm:>11.2f}")
    canonical = {split: r["collision_aware"]["canonical_collision_rate"] for split, r in results["splits"].items()
                 if "canonical_collision_rate" in r.get("collision_aware", {})}
    if canonical:
        table.append("collision_aware, predicted canonical garments inside the canonical body (before posing): "
                     + ", ".join(f"{split} {100 * rate:.2f} %" for split, rate in canonical.items()))
    log("\n".join(table))
    if "analysis" in results:
        from learn.tailornet.analysis import format_analysis

        log(format_analysis(results["analysis"]))
    if speedups:
        log("speed-up over the simulator: " + ", ".join(f"{k} {v:.0f}x" for k, v in speedups.items()))
    elif sim_ms is None:
        log(f"speed-up over the simulator: not available, {results['simulator']['missing']}")
    phases = results.get("phase_seconds", {})
    log(f"evaluation: {results['evaluation_seconds']:.1f} s (the splits {phases.get('splits', 0.0):.1f} s, of it the "
        f"post-process {phases.get('postprocess', 0.0):.1f} s; inference timing {phases.get('timing', 0.0):.1f} s)")
    log(f"report: {out / 'evaluation.json'}  plot: {out / 'error_vs_time.png'}")
    return results


def evaluate_static_set(run_dir: str | Path, data: str | Path, *, device: str = "cpu", out: str | Path | None = None,
                        log=print) -> dict:
    """``drape evaluate`` of a run trained on a static set (gcvae): per-type surface error [mm],
    normal angle [rad], mask IoU and KL on the set's test and train splits, the set's
    registration error beside them (a dynamic gcvae run: on the frames of the motion dataset
    ``data``, beside the seed's Table 4); writes ``evaluation.json`` into ``out`` (default
    ``RUN/evaluation``) and returns the report."""
    from learn.gcvae.dynamic_set import DynamicSet, is_motion_source
    from learn.gcvae.evaluate import evaluate_set, format_dynamic_table, format_table
    from learn.gcvae.static_set import StaticSet
    from learn.gcvae.train import set_fingerprint
    from learn.tailornet.train import load_checkpoint

    from pipelines.errors import UsageError, check_output_dir, check_torch_device

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UsageError(f"RUN {str(run_dir)!r} is not a directory (a run directory from drape train)")
    check_torch_device(device)
    model_file = run_dir / "gcvae_model.pt"
    saved = load_checkpoint(model_file, map_location="cpu") if model_file.is_file() else {}
    dynamic = saved.get("dynamic")
    if dynamic and not is_motion_source(data):
        raise UsageError(f"RUN {str(run_dir)!r} holds a dynamic gcvae; --data {data} must be a motion dataset "
                         f"(a drape generate-dataset directory with poses.source: motion)")
    if not dynamic and is_motion_source(data):
        raise UsageError(f"RUN {str(run_dir)!r} holds a static gcvae; --data {data} is a motion dataset (evaluate a "
                         f"run of drape train gcvae --dynamic on it, or give a drape static-set directory)")
    if dynamic:
        static_set = DynamicSet(data, frames=dynamic["frames"], frame_stride=dynamic["frame_stride"],
                                representation=(saved.get("hyperparameters") or {}).get("representation"))
    else:
        static_set = StaticSet(data)
    out = check_output_dir(Path(out) if out else run_dir / "evaluation", "--out")
    name, model = next(iter(_load_models(run_dir, set_fingerprint(static_set), device, data="static_set").items()))
    trained_types = [str(t) for t in model.graph["types"]]
    if trained_types != static_set.types:
        log(f"note: the run was trained on types {trained_types}, the set has {static_set.types}")
    splits = tuple(s for s in ("test", "train") if len(static_set.indices(s)))
    report = evaluate_set(model, static_set, splits=splits, device=device)
    report["learner"] = name
    report["best_epoch"] = getattr(model, "best_epoch", None)
    if dynamic:
        report["dynamic"] = dynamic
        report["skipped"] = static_set.skipped
    (out / "evaluation.json").write_text(json.dumps(report, indent=2))
    log(format_dynamic_table(report, dynamic["frames"]) if dynamic else format_table(report))
    log(f"report: {out / 'evaluation.json'}")
    return report


def run(args: argparse.Namespace) -> int:
    from learn.registry import LEARNERS

    if any(entry.data == "static_set" and (Path(args.run) / entry.model_file).is_file() for entry in LEARNERS.values()):
        evaluate_static_set(args.run, args.data, device=args.device, out=args.out)
        return 0
    evaluate(args.run, args.data, device=args.device, out=args.out, postprocess_frames=args.postprocess_frames,
             renders=args.renders, accuracy_report=args.accuracy_report, postprocess_workers=args.postprocess_workers,
             floor=args.floor, analysis=args.analysis)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="errors, collisions and timings of a trained run on a dataset's test splits",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="run directory from drape train")
    p.add_argument("--data", required=True, help="dataset directory (same template as the run; "
                                                 "for a gcvae run: a drape static-set directory)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=None, help="report directory (default RUN/evaluation)")
    p.add_argument("--postprocess-frames", type=int, default=32, help="frames per split to post-process (slow part)")
    p.add_argument("--renders", type=int, default=3, help="predicted-vs-simulated renders to write")
    p.add_argument("--postprocess-workers", type=int, default=None,
                   help="processes for the post-process (default: half the CPUs up to 16; 1 below 8 CPUs)")
    p.add_argument("--floor", default=None, help="floor.json from drape report floor (printed beside the learners)")
    p.add_argument("--analysis", action="store_true",
                   help="error analysis: train vs test error, error per pair and against the distance to the nearest "
                        "training pose (adds 'analysis' to evaluation.json)")
    p.add_argument("--accuracy-report", default=None, help="accuracy.json from drape report accuracy (adds the simulator sweep)")
    p.set_defaults(func=run)
