"""``drape train LEARNER --data DIR --out RUN``: train a learner on a dataset's train split.

For ``tailornet`` this trains g (style-shape -> canonical garment), the low-frequency
MLP, the K high-frequency prototype MLPs (stacked) and the baseline MLP, each stage
resumable from its checkpoint in RUN (rerun the same command to continue), with losses
in ``RUN/<stage>_loss.csv`` and a progress bar. RUN also gets ``template.npz`` (the
garment template the model predicts) and ``run.json`` (dataset, hashes, settings).
Several GPUs: launch with ``torchrun --nproc-per-node N -m pipelines.cli train ... --device cuda``
(each process takes ``cuda:LOCAL_RANK``; docs/scale-out.md). For ``tailornet`` the stages are
spread over the ranks (the K prototypes are independent networks, so stage parallelism scales
better here than data parallelism on one small MLP) and rank 0 assembles the model; every other
learner trains data-parallel (:mod:`learn.distributed`: each global batch dealt out over the
ranks, gradients summed, rank 0 writing checkpoints), and a run resumes on any process count.

``collision_aware`` (seed 002; docs/learners/collision_aware.md) trains its diffused body fields,
the canonical body's SDF, the canonical projection of the training frames (cached per shard under
``DATA/cache/canonical``), the garment VAE and the latent regressor, each stage resumable too; the
regressor is a GRU over each sequence on a motion dataset (``poses.source: motion``), an MLP
otherwise (``--regressor auto|gru|mlp``).
``uvimage`` and ``uvimage_pca`` (seed 001; docs/learners/uvimage.md) train one stage each, named
after the learner.
``gcvae`` (seed 004; docs/learners/gcvae.md) trains on a static set from ``drape static-set``
instead of a dataset (its registry ``data`` is ``static_set``): one resumable stage ``train``
(checkpoint ``RUN/gcvae.pt``, per-epoch loss terms and validation error in ``RUN/gcvae_terms.csv``),
the best validation epoch in ``RUN/gcvae_model.pt``. Given a motion dataset (``poses.source:
motion``, or a directory with ``datasets.json``) it trains the dynamic variant (``--dynamic``
says so explicitly; learn/gcvae/dynamic_set.py).

``--data-mode`` (memory, stream, auto: docs/streaming.md) says whether the training split is loaded
whole or read shard by shard in DataLoader workers every epoch; ``auto`` streams when the split's
per-vertex arrays exceed half the available memory.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from typing import Any

import numpy as np
import yaml

from pipelines.errors import UsageError, check_number, check_output_dir, check_torch_device, one_line

TRAIN_SPLITS = ("train_train", "train")


def _check_config(hyper: Any, path: Path, learner: str = "tailornet") -> dict:
    """Stage names, keys and value types of a --config file against the learner's defaults
    (TailorNet's stages for tailornet and baseline; a mapping of mappings for the other learners,
    whose merge checks their keys and values, ``learn.common.hyperparameters``); raises naming the
    file and the field path (e.g. ``lf.lr``)."""
    from learn.tailornet.train import DEFAULT_HYPERPARAMETERS

    from pipelines.spec import nearest_name

    stages = sorted(DEFAULT_HYPERPARAMETERS)
    if not isinstance(hyper, dict):
        raise UsageError(f"--config {path} must map stage names to settings (got {type(hyper).__name__})")
    if learner not in ("tailornet", "baseline"):
        for stage, values in hyper.items():
            if not isinstance(values, dict):
                raise UsageError(f"--config {path}: {stage} must be a mapping of settings (got {values!r})")
        return hyper
    for stage, values in hyper.items():
        if stage not in DEFAULT_HYPERPARAMETERS:
            raise UsageError(f"--config {path}: {stage!r} is not a training stage{nearest_name(stage, stages)}; "
                             f"expected one of {', '.join(stages)}")
        if not isinstance(values, dict):
            raise UsageError(f"--config {path}: {stage} must be a mapping of settings such as lr, epochs (got {values!r})")
        known = DEFAULT_HYPERPARAMETERS[stage]
        for key, value in values.items():
            if key not in known:
                raise UsageError(f"--config {path}: {stage}.{key} is not a setting{nearest_name(key, list(known))}; "
                                 f"expected one of {', '.join(sorted(known))}")
            default = known[key]
            where = f"--config {path}: {stage}.{key}"
            if isinstance(value, str) and isinstance(default, (int, float)) and not isinstance(default, bool):
                try:  # YAML reads 1e-3 (no dot) as text
                    value = values[key] = float(value)
                except ValueError:
                    pass
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise UsageError(f"{where} must be true or false (got {value!r})")
            elif isinstance(default, int):
                minimum = 0 if key in ("epochs", "smoothing_iterations", "canonical_repeat") else 1
                check_number(value, where, minimum=minimum, integer=True)
            elif isinstance(default, float):
                minimum = 0.0
                check_number(value, where, minimum=minimum, above=key in ("lr", "sigma"),
                             maximum=1.0 if key == "dropout" else None)
    return hyper


def _overrides(args: argparse.Namespace, stages: tuple[str, ...]) -> dict:
    """Hyper-parameters from ``--config``, ``--epochs`` (set for each of ``stages``, the
    learner's registry ``stages``) and ``--prototypes`` (tailornet only)."""
    hyper: dict = {}
    if args.config:
        path = Path(args.config)
        if not path.is_file():
            raise UsageError(f"--config: hyper-parameter file not found: {path}")
        try:
            hyper = yaml.safe_load(path.read_text(encoding="utf-8"))
        except UnicodeDecodeError:
            raise UsageError(f"--config {path} is not a YAML text file") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
            raise UsageError(f"--config {path} is not valid YAML{where}: "
                             f"{getattr(exc, 'problem', None) or one_line(str(exc))}") from None
        hyper = _check_config({} if hyper is None else hyper, path, args.learner)
    if args.epochs is not None:
        check_number(args.epochs, "--epochs", minimum=1, integer=True)
        for stage in stages:
            hyper.setdefault(stage, {})["epochs"] = int(args.epochs)
    if getattr(args, "regressor", None) is not None:
        if args.learner != "collision_aware":
            raise UsageError(f"--regressor applies to collision_aware only, not {args.learner}")
        hyper.setdefault("regressor", {})["kind"] = args.regressor
    if args.prototypes is not None:
        check_number(args.prototypes, "--prototypes", minimum=1, integer=True)
        if args.learner != "tailornet":
            raise UsageError(f"--prototypes applies to tailornet only, not {args.learner}")
        hyper.setdefault("model", {})["prototype_count"] = int(args.prototypes)
    return hyper


def train(learner: str, data: str | Path, out: str | Path, *, device: str = "cpu", epochs: int | None = None,
          config: str | None = None, prototypes: int | None = None, seed: int = 0, progress: bool = True,
          data_mode: str = "auto", regressor: str | None = None, dynamic: bool = False) -> Path:
    """Library form of the command; returns the run directory."""
    args = argparse.Namespace(learner=learner, data=str(data), out=str(out), device=device, epochs=epochs, config=config,
                              prototypes=prototypes, seed=seed, no_progress=not progress, data_mode=data_mode,
                              regressor=regressor, dynamic=dynamic)
    run(args)
    return Path(out)


def run(args: argparse.Namespace) -> int:
    from learn import distributed
    from learn.registry import get_learner

    from learn.streamed_split import DATA_MODES

    entry = get_learner(args.learner)
    args.learner = entry.name
    check_torch_device(args.device)
    mode = getattr(args, "data_mode", "auto")
    if mode not in DATA_MODES:
        raise UsageError(f"--data-mode {mode!r} is not a data mode; expected one of {', '.join(DATA_MODES)}")
    if mode == "stream" and (entry.data != "dataset" or not entry.streams):
        raise UsageError(f"--data-mode stream: {entry.name} trains from memory only "
                         + ("(a static set is one file, read whole)" if entry.data != "dataset" else
                            "(it projects every training frame to its canonical space and trains on the projections "
                            "held together); use --data-mode memory"))
    try:  # under torchrun: join the process group, one device per rank
        args.device = distributed.init(args.device, data_parallel=entry.name != "tailornet")
    except ValueError as error:
        raise UsageError(str(error)) from None
    try:
        status = _run(args, entry)
    except BaseException:
        distributed.finish(wait=False)  # the other ranks may be inside a collective: no barrier
        raise
    distributed.finish()
    return status


def _run(args: argparse.Namespace, entry) -> int:
    from data_manifest.reader import DatasetReader
    from learn.data import DrapeDataset
    from learn.tailornet.train import (DEFAULT_HYPERPARAMETERS, dataset_fingerprint, fit_tailornet_process,
                                       frame_arrays_from_dataset, garment_pose_indices)
    from simulate.body import load_body_model

    check_number(args.seed, "--seed", minimum=0, integer=True)
    hyper = _overrides(args, entry.stages)
    if Path(args.out).resolve() == Path(args.data).resolve():
        raise UsageError(f"--out {args.out!r} is the dataset directory; give the run its own directory")
    if getattr(args, "dynamic", False) and entry.data != "static_set":
        raise UsageError(f"--dynamic applies to gcvae only, not {args.learner}")
    out = check_output_dir(args.out, "--out")
    if entry.data == "static_set":
        return _train_on_static_set(entry, args, hyper, out)
    reader = DatasetReader(args.data)
    split = next((s for s in TRAIN_SPLITS if s in reader.splits and reader.num_frames(s) > 0), None)
    if split is None:
        raise ValueError(f"dataset {args.data} has no frames in a training split ({', '.join(TRAIN_SPLITS)}); "
                         f"its splits: {', '.join(f'{s} ({reader.num_frames(s)})' for s in reader.splits)}")
    template = reader.template
    spec = reader.manifest.spec
    body_spec = spec.get("body", {"backend": "anny", "path": None})
    body = load_body_model(body_spec.get("backend", "anny"), path=body_spec.get("path"))
    model_hyper = {**DEFAULT_HYPERPARAMETERS["model"], **hyper.get("model", {})}
    # model.pose_mask false feeds every pose entry (the pose-input masking ablation)
    pose_indices = (garment_pose_indices(template["skinning_weights"], body.pose_size, parents=body.joint_parents,
                                         posable_joints=body.pose_joint_indices,
                                         min_weight_sum=float(model_hyper["min_joint_weight_sum"]))
                    if model_hyper["pose_mask"] else np.arange(body.pose_size))
    fingerprint = dataset_fingerprint(args.data, template)
    t0 = time.perf_counter()
    mode = _data_mode(getattr(args, "data_mode", "auto"), reader, split, entry)
    if mode == "stream":
        from learn import distributed
        from learn.streamed_split import StreamedSplit

        dataset = None
        reader.close()  # the template's shard: no HDF5 handle is open when a loader forks its workers
        data = StreamedSplit(args.data, split)
        if args.learner == "tailornet":  # the whole-split pre-pass: every shard's low-frequency part, cached
            data.prepare_low_frequency(args.device, rank=distributed.rank(), world_size=distributed.world_size())
            distributed.barrier()
    else:
        dataset = DrapeDataset(args.data, split, frequencies=args.learner == "tailornet", device=args.device,
                               posed=entry.posed)
        data = frame_arrays_from_dataset(dataset)
    pairs = int(np.unique(data.pair_id).size)
    read_s = time.perf_counter() - t0
    print(f"read {split}: {data.frame_count} frames of {pairs} pairs in {read_s:.1f} s ({mode})")
    canonical = load_canonical_split(reader, args.data, args.learner, model_hyper, streamed=mode == "stream")
    hyper.setdefault("model", {})
    # TailorNet keeps the first 2 components of PCA shape/style spaces; our shape is anny's
    # phenotype vector and our style the CLOTH3D-like parameters, where no prefix is "the most
    # important", so every component is an input unless the config says otherwise.
    if args.learner in ("tailornet", "baseline"):
        hyper["model"].setdefault("shape_components", int(data.shape.shape[1]))
        hyper["model"].setdefault("style_components", int(data.style.shape[1]))
    if args.learner == "tailornet":
        requested = int(hyper["model"].get("prototype_count", 20))
        if requested > pairs:
            print(f"note: {requested} prototypes requested but the training split has {pairs} style-shape pairs; using {pairs}")
            hyper["model"]["prototype_count"] = pairs
    rank, world = int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))
    if rank == 0:
        np.savez(out / "template.npz", **template)
    common = dict(run_dir=out, pose_indices=pose_indices, canonical_pose=body.canonical_pose, hyperparameters=hyper,
                  fingerprint=fingerprint, device=args.device, seed=args.seed, progress=not args.no_progress)
    if args.learner == "tailornet":
        # the stages (hf possibly in parts of its prototypes) spread over the processes; rank 0 assembles
        fit_tailornet_process(data, template["faces"], rank=rank, world_size=world, canonical=canonical, **common)
    else:
        extra = {} if entry.context is None else entry.context(
            reader=reader, dataset=dataset, body=body, body_spec={"backend": body.name, "path": body_spec.get("path")},
            template=template)
        if canonical is not None:
            extra["canonical"] = canonical
        entry.fit(data, template["faces"], **common, **extra)
    if rank == 0:
        info = {"learner": args.learner, "data": str(Path(args.data).resolve()), "train_split": split, "data_mode": mode,
                "frames": data.frame_count,
                "pairs": pairs, "dataset_manifest_sha256": fingerprint.dataset_manifest_sha256,
                "template_sha256": fingerprint.template_sha256, "hyperparameters": hyper, "device": args.device,
                "seed": args.seed, "seconds": round(time.perf_counter() - t0, 2), "read_seconds": round(read_s, 2),
                "body": {"backend": body.name, "path": body_spec.get("path")}}
        (out / "run.json").write_text(json.dumps(info, indent=2, default=str))
        print(f"trained {args.learner} on {data.frame_count} frames of {split} ({pairs} pairs) in {info['seconds']} s -> {out}")
    return 0


def load_canonical_split(reader, data: str | os.PathLike, learner: str, model_hyper: dict, *,
                         streamed: bool = False):
    """The dataset's ``canonical`` split (every style-shape combination in the canonical pose,
    ``splits.canonical``) as FrameArrays for TailorNet and the baseline, with a line saying what
    they do with it; None for other learners, without the split, or with
    ``model.use_canonical_split`` false. ``streamed``: the training split is streamed, so LF and
    the baseline train on its own frames only."""
    from learn.data import DrapeDataset
    from learn.tailornet.train import frame_arrays_from_dataset
    from pipelines.dataset_plan import CANONICAL_SPLIT

    if learner not in ("tailornet", "baseline") or not model_hyper["use_canonical_split"] \
            or CANONICAL_SPLIT not in reader.splits or reader.num_frames(CANONICAL_SPLIT) == 0:
        return None
    loaded = DrapeDataset(data, CANONICAL_SPLIT, frequencies=False)
    canonical = frame_arrays_from_dataset(loaded)
    loaded.reader.close()  # no HDF5 handle open when a loader forks its workers
    repeat = int(model_hyper["canonical_repeat"])
    uses = ["g and the prototype choice learn from them"] if learner == "tailornet" else []
    uses.append(f"{'LF' if learner == 'tailornet' else 'the baseline'} trains on them "
                + ("not (a streamed split)" if streamed else
                   f"{repeat} times (model.canonical_repeat)" if repeat else "not (model.canonical_repeat 0)"))
    print(f"canonical split: {canonical.frame_count} style-shape combinations in the canonical pose "
          f"({'; '.join(uses)})")
    return canonical


def _data_mode(mode: str, reader, split: str, entry) -> str:
    """``memory`` or ``stream`` for ``--data-mode`` ``mode``: ``auto`` streams when the in-memory
    split (:func:`learn.streamed_split.split_bytes`) would exceed
    :data:`learn.streamed_split.MEMORY_SHARE` of the available memory, for learners that stream."""
    from learn.streamed_split import MEMORY_SHARE, available_memory_bytes, choose_data_mode, split_bytes

    if mode != "auto":
        return mode
    need, available = split_bytes(reader, split), available_memory_bytes()
    chosen = choose_data_mode(mode, need, available)
    if chosen == "stream" and not entry.streams:
        print(f"note: split {split} takes {need / 2**30:.1f} GiB in memory, over {MEMORY_SHARE:.0%} of the "
              f"{available / 2**30:.1f} GiB available, but {entry.name} trains from memory only")
        return "memory"
    return chosen


def _train_on_static_set(entry, args: argparse.Namespace, hyper: dict, out: Path) -> int:
    """``drape train`` of a learner whose registry ``data`` is ``static_set`` (gcvae): fits it on
    the ``drape static-set`` directory ``--data`` (or, the dynamic variant, on the frames of the
    motion dataset ``--data``) and writes ``run.json``."""
    from learn.gcvae.dynamic_set import DynamicSet, is_motion_source
    from learn.gcvae.hyperparameters import merged
    from learn.gcvae.static_set import StaticSet

    if is_motion_source(args.data):
        try:
            settings = merged(hyper)
        except ValueError as error:
            raise UsageError(f"--config {args.config}: {error}") from None
        data = DynamicSet(args.data, frames=settings["dynamic"]["frames"],
                          frame_stride=settings["dynamic"]["frame_stride"], representation=settings["representation"])
        for skipped in data.skipped:
            print(f"note: skipped {skipped['type']} {skipped['task_id']}: its garment is not on the body "
                  f"(registration {skipped['registration_mm']:.1f} mm)")
    elif getattr(args, "dynamic", False):
        raise UsageError(f"--dynamic needs a motion dataset (a drape generate-dataset directory with poses.source: "
                         f"motion, or one with datasets.json); --data {args.data} is not one (a static set trains the "
                         f"static gcvae: drop --dynamic)")
    else:
        data = StaticSet(args.data)
    t0 = time.perf_counter()
    model = entry.fit(data, run_dir=out, hyperparameters=hyper, device=args.device, seed=args.seed,
                      progress=not args.no_progress)
    train_samples, validation_samples = model.split_sizes
    from learn import distributed

    if not distributed.is_main():
        return 0
    info = {"learner": args.learner, "data": str(Path(data.path).resolve()), "samples": len(data),
            "train_samples": train_samples, "validation_samples": validation_samples, "types": data.types,
            "best_epoch": model.best_epoch, "hyperparameters": model.hyperparameters, "device": args.device,
            "seed": args.seed, "seconds": round(time.perf_counter() - t0, 2),
            "registration_mm": data.registration_table(), "dynamic": getattr(model, "dynamic", None)}
    (out / "run.json").write_text(json.dumps(info, indent=2, default=str))
    print(f"trained {args.learner} on {train_samples} samples, validated on {validation_samples} "
          f"({', '.join(data.types)}) in {info['seconds']} s, best epoch {model.best_epoch} -> {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a learner (tailornet, baseline, uvimage, uvimage_pca, collision_aware, gcvae) "
                       "on a dataset", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    # not argparse choices: the registry imports torch, and `drape --help` stays light
    p.add_argument("learner", help="what to train, a name in learn/registry.py: tailornet (also trains the baseline), "
                                   "baseline, uvimage, uvimage_pca (seed 001), collision_aware or collision-aware (seed 002), "
                                   "gcvae (seed 004)")
    p.add_argument("--data", required=True,
                   help="dataset directory (from drape generate-dataset; for gcvae: from drape static-set, or a "
                        "motion dataset for the dynamic variant)")
    p.add_argument("--out", required=True, help="run directory (checkpoints, logs, model)")
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    p.add_argument("--epochs", type=int, default=None, help="epochs for every stage (default: the paper's per stage)")
    p.add_argument("--prototypes", type=int, default=None, help="number K of high-frequency prototypes (default 20)")
    p.add_argument("--config", default=None, help="YAML of per-stage overrides, e.g. {lf: {lr: 1e-4}, model: {sigma: 0.01}}; "
                   "gcvae: per section of learn/gcvae/hyperparameters.py, e.g. {train: {lr: 5e-4}}")
    p.add_argument("--regressor", choices=("auto", "gru", "mlp"), default=None,
                   help="collision_aware: the latent regressor, gru (motion datasets) or mlp; auto (default) picks "
                        "gru for a motion dataset (poses.source: motion), mlp otherwise")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--data-mode", default="auto", metavar="MODE",
                   help="how the training split reaches the epoch loops: memory (loaded whole), stream (read shard by "
                        "shard in DataLoader workers, for datasets larger than memory; docs/streaming.md) or auto "
                        "(default: stream when the split's per-vertex arrays exceed half the available memory)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--dynamic", action="store_true",
                   help="gcvae: the dynamic variant on a motion dataset's frames (automatic when --data is a motion "
                        "dataset; sizes in the config section dynamic: frames, frame_stride, channel_factor)")
    p.set_defaults(func=run)
