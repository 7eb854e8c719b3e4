"""TailorNet training and evaluation speed: seconds per epoch of every stage, the projected time
of the paper's epochs (lf 100, hf 800, shape_style 400, baseline 100), and the evaluation time
of the test frames, printed as one JSON line.

    python bench/bench_train.py DATASET [--device cuda] [--epochs 3] [--mixed-precision] [--no-cuda-graphs]
    python bench/bench_train.py --synthetic 30581 7744 [--test-frames 6900] [--device cuda]

``DATASET``: a drape generate-dataset directory (train_train trains; the test splits are
evaluated with the body model, as ``drape evaluate`` does). ``--synthetic FRAMES VERTICES``: no
dataset; random low-rank displacements on a square grid garment over ``--pairs`` style-shape
pairs (the shipped t-shirt spec: 30,581 frames, 7,744 vertices, 20 pairs), evaluated unposed
and posed against a sphere body (identity skinning), so the collision and post-process costs
are measured too. The first epoch of a stage (allocation, kernel selection) is excluded from its
median when more than one ran.
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

PAPER_EPOCHS = {"shape_style": 400, "lf": 100, "hf": 800, "baseline": 100}


def synthetic_frames(frames: int, vertices: int, *, pairs: int = 20, pose_size: int = 60, seed: int = 0):
    """(FrameArrays with low_frequency filled, faces): displacements [m] = a smooth low-rank
    function of (pose, shape, style) plus a per-pair pose-dependent ripple."""
    from learn.common.mesh import grid_mesh
    from learn.tailornet.train import FrameArrays

    side = int(round(np.sqrt(vertices)))
    grid, faces = grid_mesh(side, side, spacing=0.6 / side)
    rng = np.random.default_rng(seed)
    pair_id = np.sort(rng.integers(0, pairs, size=frames))
    shapes, styles = rng.normal(size=(pairs, 6)).astype(np.float32), rng.normal(size=(pairs, 4)).astype(np.float32)
    pose = rng.uniform(-0.6, 0.6, size=(frames, pose_size)).astype(np.float32)
    features = np.tanh(np.concatenate([pose[:, :16], shapes[pair_id], styles[pair_id]], axis=1))  # (N, 26)
    x, y = grid[:, 0] / grid[:, 0].max(), grid[:, 1] / grid[:, 1].max()
    smooth = np.stack([np.sin(np.pi * (i % 4 + 1) * x) * np.cos(np.pi * (i // 4 % 3 + 1) * y) for i in range(26)])
    coefficients = rng.normal(scale=0.004, size=(26, 3))
    # sum_f features[n, f] smooth[f, v] coefficients[f, c], one matrix product per axis (a three-operand einsum
    # of the t-shirt's size runs for minutes)
    low = np.stack([(features * coefficients[:, c]) @ smooth for c in range(3)], axis=-1).astype(np.float32)
    ripple = np.sin(40.0 * x)[None, :, None] * (0.002 * np.tanh(pose[:, :1]) * (1 + pair_id[:, None] / pairs))[:, :, None]
    displacements = (low + ripple * np.array([0.0, 0.0, 1.0], np.float32)).astype(np.float32)
    data = FrameArrays(pose=pose, shape=shapes[pair_id], style=styles[pair_id], displacements=displacements,
                       pair_id=pair_id.astype(np.int64), low_frequency=low,
                       posed_vertices=(grid[None] + displacements).astype(np.float32))
    return data, faces, grid.astype(np.float32)


def _synthetic_posing(grid: np.ndarray, faces: np.ndarray):
    import torch
    import trimesh

    from learn.tailornet.evaluate import PosingContext

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.25)  # 10k vertices, about anny's 14k
    body = torch.as_tensor(np.asarray(sphere.vertices) + np.array([0.3, 0.3, -0.24]), dtype=torch.float32)
    under = torch.as_tensor(grid)
    return PosingContext(unposed_body=lambda shape: under.to(shape.device).expand(shape.shape[0], -1, -1),
                         garment_poser=lambda unposed, pose, shape: unposed,
                         posed_body=lambda pose, shape: body.to(pose.device).expand(pose.shape[0], -1, -1),
                         body_faces=np.asarray(sphere.faces), garment_faces=faces)


def _dataset(root: Path, device: str):
    from data_manifest.reader import DatasetReader
    from learn.common.skinning import garment_posing_functions
    from learn.data import DrapeDataset
    from learn.tailornet.evaluate import PosingContext
    from learn.tailornet.train import frame_arrays_from_dataset, garment_pose_indices
    from simulate.body import load_body_model

    reader = DatasetReader(root)
    template = reader.template
    body_spec = reader.manifest.spec.get("body", {"backend": "anny", "path": None})
    body = load_body_model(body_spec.get("backend", "anny"), path=body_spec.get("path"))
    t0 = time.perf_counter()
    train = frame_arrays_from_dataset(DrapeDataset(root, "train_train", device=device))
    tests = {s: frame_arrays_from_dataset(DrapeDataset(root, s, frequencies=False))
             for s in ("train_test", "test_train", "test_test") if s in reader.splits and reader.num_frames(s)}
    load_s = time.perf_counter() - t0
    posing = PosingContext(*garment_posing_functions(body, template["body_vertex_index"], template["skinning_weights"],
                                                     rest_vertices=template["rest_vertices"]), body.faces, template["faces"])
    indices = garment_pose_indices(template["skinning_weights"], body.pose_size, parents=body.joint_parents,
                                   posable_joints=body.pose_joint_indices)
    return train, tests, template["faces"], posing, indices, load_s


def _epoch_seconds(run_dir: Path, stage: str) -> list[float]:
    with (run_dir / f"{stage}_loss.csv").open() as handle:
        return [float(row["seconds"]) for row in csv.DictReader(handle)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", nargs="?", help="dataset directory (omit with --synthetic)")
    parser.add_argument("--synthetic", type=int, nargs=2, metavar=("FRAMES", "VERTICES"))
    parser.add_argument("--test-frames", type=int, default=6900, help="synthetic test frames (default 6,900: the "
                                                                       "spec's three test splits)")
    parser.add_argument("--pairs", type=int, default=20, help="synthetic style-shape pairs (default 20)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--epochs", type=int, default=3, help="epochs timed per stage (default 3)")
    parser.add_argument("--mixed-precision", action="store_true", help="bf16 autocast (model.mixed_precision)")
    parser.add_argument("--no-cuda-graphs", action="store_true",
                        help="eager steps instead of steps replayed as CUDA graphs (model.cuda_graphs: false)")
    parser.add_argument("--no-evaluate", action="store_true")
    parser.add_argument("--stages", default=None,
                        help="comma-separated stages to train (default all): run one process per group of stages "
                             "side by side on one GPU to time the stage-parallel run (torchrun with several "
                             "processes per GPU); implies --no-evaluate")
    parser.add_argument("--postprocess-frames", type=int, default=32)
    parser.add_argument("--postprocess-workers", type=int, default=None)
    args = parser.parse_args()
    if (args.data is None) == (args.synthetic is None):
        parser.error("give a dataset directory or --synthetic FRAMES VERTICES")
    chosen = list(PAPER_EPOCHS) if args.stages is None else [s.strip() for s in args.stages.split(",") if s.strip()]
    unknown = sorted(set(chosen) - set(PAPER_EPOCHS))
    if unknown or not chosen:
        parser.error(f"--stages {args.stages!r}: expected a comma-separated subset of {', '.join(PAPER_EPOCHS)}")
    if args.stages is not None:
        args.no_evaluate = True
    import torch

    from learn.tailornet.evaluate import evaluate_models
    from learn.tailornet.train import fit_baseline, fit_tailornet
    from pipelines.evaluate import default_postprocess_workers

    result: dict = {"device": args.device, "epochs_timed": args.epochs, "mixed_precision": args.mixed_precision,
                    "cuda_graphs": not args.no_cuda_graphs,
                    "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None}
    if args.synthetic:
        t0 = time.perf_counter()
        data, faces, grid = synthetic_frames(args.synthetic[0] + args.test_frames, args.synthetic[1], pairs=args.pairs)
        order = np.random.default_rng(1).permutation(data.frame_count)
        train, test = data.subset(np.sort(order[:args.synthetic[0]])), data.subset(np.sort(order[args.synthetic[0]:]))
        tests, pose_indices = {"test": test}, np.arange(data.pose.shape[1])
        posing = None if args.no_evaluate else _synthetic_posing(grid, faces)  # trimesh: only to evaluate
        result.update(data="synthetic", synthetic_s=round(time.perf_counter() - t0, 2))
    else:
        train, tests, faces, posing, pose_indices, load_s = _dataset(Path(args.data), args.device)
        result.update(data=str(args.data), load_s=round(load_s, 2))
    result.update(train_frames=train.frame_count, vertices=train.vertex_count, pairs=int(np.unique(train.pair_id).size),
                  test_frames={s: d.frame_count for s, d in tests.items()})
    hyper = {stage: {"epochs": args.epochs} for stage in PAPER_EPOCHS}
    hyper["model"] = {"checkpoint_interval_s": 1e9, "mixed_precision": args.mixed_precision,
                      "cuda_graphs": not args.no_cuda_graphs,
                      "prototype_count": min(20, result["pairs"]), "shape_components": train.shape.shape[1],
                      "style_components": train.style.shape[1]}
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp)
        t0 = time.perf_counter()
        tn_stages = [s for s in chosen if s != "baseline"]
        tailornet = baseline = None
        if tn_stages:
            tailornet = fit_tailornet(train, faces, run_dir=run_dir, pose_indices=pose_indices, hyperparameters=hyper,
                                      device=args.device, progress=False, stages=tn_stages)
        if "baseline" in chosen:
            baseline = fit_baseline(train, faces, run_dir=run_dir, pose_indices=pose_indices, hyperparameters=hyper,
                                    device=args.device, progress=False)
        result["fit_s"] = round(time.perf_counter() - t0, 2)
        stages = {}
        for stage, paper in PAPER_EPOCHS.items():
            if stage not in chosen:
                continue
            seconds = _epoch_seconds(run_dir, stage)
            epoch = statistics.median(seconds[1:] if len(seconds) > 1 else seconds)
            stages[stage] = {"epoch_s": round(epoch, 4), "first_epoch_s": round(seconds[0], 4), "paper_epochs": paper,
                             "projected_s": round(epoch * paper, 1)}
        result["stages"] = stages
        result["projected_paper_total_s"] = round(sum(s["projected_s"] for s in stages.values()), 1)
    if not args.no_evaluate:
        workers = args.postprocess_workers or default_postprocess_workers()
        t0 = time.perf_counter()
        report = evaluate_models({"tailornet": tailornet, "baseline": baseline}, tests, posing=posing,
                                 postprocess_frames=args.postprocess_frames, device=args.device,
                                 timing_devices=(args.device,), postprocess_workers=workers)
        result["evaluation"] = {"seconds": round(time.perf_counter() - t0, 2), "postprocess_workers": workers,
                                "postprocess_frames": args.postprocess_frames,
                                "unposed_error_mm": {s: {m: round(r["unposed_error_mm"], 3) for m, r in per.items()}
                                                     for s, per in report["splits"].items()}}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
