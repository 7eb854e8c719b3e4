"""``drape train LEARNER --data DIR --out RUN``: train a learner on a dataset's train split.

For ``tailornet`` this trains g (style-shape -> canonical garment), the low-frequency
MLP, the K high-frequency prototype MLPs (stacked) and the baseline MLP, each stage
resumable from its checkpoint in RUN (rerun the same command to continue), with losses
in ``RUN/<stage>_loss.csv`` and a progress bar. RUN also gets ``template.npz`` (the
garment template the model predicts) and ``run.json`` (dataset, hashes, settings).
Several GPUs: launch with ``torchrun --nproc-per-node N -m pipelines.cli train ...``;
stages are spread over the ranks (the K prototypes are independent networks, so
stage parallelism scales better here than data-parallel DDP on one small MLP) and
rank 0 assembles the model.

``gcvae`` trains on a static set from ``drape static-set`` (learn/gcvae/train.py: checkpoint,
per-epoch loss terms, the best validation epoch in ``RUN/gcvae_model.pt``).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import yaml

TRAIN_SPLITS = ("train_train", "train")


def _overrides(args: argparse.Namespace) -> dict:
    hyper: dict = {}
    if args.config:
        path = Path(args.config)
        if not path.is_file():
            raise FileNotFoundError(f"--config: hyper-parameter file not found: {path}")
        hyper = yaml.safe_load(path.read_text()) or {}
        if not isinstance(hyper, dict):
            raise ValueError(f"--config {path} must map stage names (lf, hf, shape_style, baseline, model) to settings")
    if args.epochs is not None:
        if args.epochs < 1:
            raise ValueError(f"--epochs must be >= 1 (got {args.epochs})")
        for stage in ("lf", "hf", "shape_style", "baseline"):
            hyper.setdefault(stage, {})["epochs"] = int(args.epochs)
    if args.prototypes is not None:
        hyper.setdefault("model", {})["prototype_count"] = int(args.prototypes)
    return hyper


def train(learner: str, data: str | Path, out: str | Path, *, device: str = "cpu", epochs: int | None = None,
          config: str | None = None, prototypes: int | None = None, seed: int = 0, progress: bool = True) -> Path:
    """Library form of the command; returns the run directory."""
    args = argparse.Namespace(learner=learner, data=str(data), out=str(out), device=device, epochs=epochs, config=config,
                              prototypes=prototypes, seed=seed, no_progress=not progress)
    run(args)
    return Path(out)


def run(args: argparse.Namespace) -> int:
    from data_manifest.reader import DatasetReader
    from learn.data import DrapeDataset
    from learn.tailornet.train import (dataset_fingerprint, fit_baseline, fit_tailornet, frame_arrays_from_dataset,
                                       garment_pose_indices, stages_for_rank)
    from simulate.body import load_body_model

    from learn.registry import get_learner

    entry = get_learner(args.learner)
    if entry.train_command is not None:
        return entry.train_command(args)
    reader = DatasetReader(args.data)
    split = next((s for s in TRAIN_SPLITS if s in reader.splits and reader.num_frames(s) > 0), None)
    if split is None:
        raise ValueError(f"dataset {args.data} has no frames in a training split ({', '.join(TRAIN_SPLITS)}); "
                         f"its splits: {', '.join(f'{s} ({reader.num_frames(s)})' for s in reader.splits)}")
    hyper = _overrides(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    template = reader.template
    spec = reader.manifest.spec
    body_spec = spec.get("body", {"backend": "anny", "path": None})
    body = load_body_model(body_spec.get("backend", "anny"), path=body_spec.get("path"))
    pose_indices = garment_pose_indices(template["skinning_weights"], body.pose_size, parents=body.joint_parents,
                                        posable_joints=body.pose_joint_indices)
    fingerprint = dataset_fingerprint(args.data, template)
    t0 = time.perf_counter()
    data = frame_arrays_from_dataset(DrapeDataset(args.data, split))
    pairs = int(np.unique(data.pair_id).size)
    hyper.setdefault("model", {})
    # TailorNet keeps the first 2 components of PCA shape/style spaces; our shape is anny's
    # phenotype vector and our style the CLOTH3D-like parameters, where no prefix is "the most
    # important", so every component is an input unless the config says otherwise.
    hyper["model"].setdefault("shape_components", int(data.shape.shape[1]))
    hyper["model"].setdefault("style_components", int(data.style.shape[1]))
    if args.learner == "tailornet":
        requested = int(hyper["model"].get("prototype_count", 20))
        if requested > pairs:
            print(f"note: {requested} prototypes requested but the training split has {pairs} style-shape pairs; using {pairs}")
            hyper["model"]["prototype_count"] = pairs
    np.savez(out / "template.npz", **template)
    rank, world = int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1))
    common = dict(run_dir=out, pose_indices=pose_indices, canonical_pose=body.canonical_pose, hyperparameters=hyper,
                  fingerprint=fingerprint, device=args.device, seed=args.seed, progress=not args.no_progress)
    if args.learner == "tailornet":
        stages = stages_for_rank(rank, world) if world > 1 else None
        tn_stages = None if stages is None else [s for s in stages if s != "baseline"]
        if tn_stages is None or tn_stages or rank == 0:
            fit_tailornet(data, template["faces"], stages=tn_stages, wait_timeout_s=3600.0 if world > 1 else 0.0, **common)
        if stages is None or "baseline" in stages:
            fit_baseline(data, template["faces"], **common)
    else:
        fit_baseline(data, template["faces"], **common)
    if rank == 0:
        info = {"learner": args.learner, "data": str(Path(args.data).resolve()), "train_split": split, "frames": data.frame_count,
                "pairs": pairs, "dataset_manifest_sha256": fingerprint.dataset_manifest_sha256,
                "template_sha256": fingerprint.template_sha256, "hyperparameters": hyper, "device": args.device,
                "seed": args.seed, "seconds": round(time.perf_counter() - t0, 2),
                "body": {"backend": body.name, "path": body_spec.get("path")}}
        (out / "run.json").write_text(json.dumps(info, indent=2, default=str))
        print(f"trained {args.learner} on {data.frame_count} frames of {split} ({pairs} pairs) in {info['seconds']} s -> {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a learner (tailornet, baseline, gcvae) on a dataset",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("learner", choices=["tailornet", "baseline", "gcvae"],
                   help="what to train (tailornet also trains the baseline)")
    p.add_argument("--data", required=True,
                   help="dataset directory (from drape generate-dataset; for gcvae: from drape static-set)")
    p.add_argument("--out", required=True, help="run directory (checkpoints, logs, model)")
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:1)")
    p.add_argument("--epochs", type=int, default=None, help="epochs for every stage (default: the paper's per stage)")
    p.add_argument("--prototypes", type=int, default=None, help="number K of high-frequency prototypes (default 20)")
    p.add_argument("--config", default=None, help="YAML of per-stage overrides, e.g. {lf: {lr: 1e-4}, model: {sigma: 0.01}}; "
                   "gcvae: per section of learn/gcvae/hyperparameters.py, e.g. {train: {lr: 5e-4}}")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)
