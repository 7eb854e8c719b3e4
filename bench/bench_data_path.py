"""Shards to training tensors: the serial path (one reader, per-shard CPU smoothing of a
re-read shard) against ``DrapeDataset`` (process-parallel reads, batched smoothing on
``--device``), both with an empty low-frequency cache, then ``DrapeDataset`` from its cache.

    python bench/bench_data_path.py DATASET [--split train_train] [--device cuda] [--workers N]
    python bench/bench_data_path.py OUT --synthetic SHARDS FRAMES   # writes a 7,744-vertex tube dataset first
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np


def _write_shard(root: str, task_id: str, frames: int, seed: int) -> dict:
    from data_manifest.shard import ShardWriter, shard_path
    from data_manifest.synthetic import SHAPE_SIZE, STYLE_SIZE, synthetic_frame, tube_template

    template = tube_template(rings=88, segments=88)
    rng = np.random.default_rng(seed)
    task = {"task_id": task_id, "garment": "tube", "splits": ["train"], "seed": seed,
            "shape": rng.normal(size=SHAPE_SIZE), "style": rng.normal(size=STYLE_SIZE)}
    with ShardWriter(shard_path(root, task_id), template=template, task=task) as writer:
        for frame in range(frames):
            writer.write_frame(**synthetic_frame(template, rng, translation_m=np.array([0.0, 1.0, 0.0])),
                               frame_index=frame)
    return writer.record


def write_synthetic(root: Path, shards: int, frames: int) -> None:
    """A ``train`` split of ``shards`` x ``frames`` frames on a 7,744-vertex tube, shards written in parallel."""
    from data_manifest.manifest import Manifest, collect_provenance
    from data_manifest.schema import template_sha256
    from data_manifest.synthetic import tube_template

    template = tube_template(rings=88, segments=88)
    ids = [f"train-{k:04d}" for k in range(shards)]
    manifest = Manifest.create(root, name="bench", spec={"name": "bench"}, template_sha256=template_sha256(template),
                               precision="float32", provenance=collect_provenance(device="cpu", seeds={"spec": 0}),
                               splits={"train": ids})
    with ProcessPoolExecutor() as pool:
        for record in pool.map(_write_shard, [str(root)] * shards, ids, [frames] * shards, range(shards)):
            manifest.add_shard(record)
    manifest.finish()
    manifest.save()


def serial_load(root: Path, split: str, cache: Path) -> float:
    """The serial path: ``load_split`` then each shard re-read and smoothed on the CPU."""
    import torch

    from data_manifest.reader import DatasetReader
    from learn.common.smoothing import LaplacianSmoother, split_frequencies
    from learn.data import ITERATIONS, SMOOTHNESS

    t0 = time.perf_counter()
    reader = DatasetReader(root)
    arrays = reader.load_split(split)
    smoother = LaplacianSmoother(reader.template["faces"], arrays["unposed_displacements"].shape[1],
                                 smoothness=SMOOTHNESS, iterations=ITERATIONS)
    lows = []
    for entry in reader.shard_entries:
        if split in entry["splits"] and entry["frame_count"]:
            d = reader.load_task(entry["task_id"])["unposed_displacements"]
            lows.append(split_frequencies(torch.from_numpy(d), smoother)[0].numpy())
    np.concatenate(lows)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data")
    parser.add_argument("--split", default="train")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--synthetic", type=int, nargs=2, metavar=("SHARDS", "FRAMES"))
    parser.add_argument("--skip-serial", action="store_true")
    args = parser.parse_args()
    root = Path(args.data)
    import torch

    from learn.data import DrapeDataset

    if args.synthetic:
        t0 = time.perf_counter()
        write_synthetic(root, *args.synthetic)
        print(f"wrote {args.synthetic[0]} x {args.synthetic[1]} frames in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    DrapeDataset(root, args.split, frequencies=False, workers=args.workers)  # digests cached, files in page cache
    print(f"first read, hashing every shard: {time.perf_counter() - t0:.1f} s", flush=True)
    result = {"data": str(root), "split": args.split, "device": args.device, "workers": args.workers,
              "cpu_threads": torch.get_num_threads()}
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_serial:
            result["serial_s"] = round(serial_load(root, args.split, Path(tmp) / "serial"), 2)
        cache = Path(tmp) / "new"
        for label in ("parallel_fresh_s", "parallel_cached_s"):
            if args.device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            ds = DrapeDataset(root, args.split, device=args.device, workers=args.workers, cache_dir=cache)
            result[label] = round(time.perf_counter() - t0, 2)
        result["frames"] = len(ds)
        result["vertices"] = int(ds.displacements.shape[1])
        shutil.rmtree(cache, ignore_errors=True)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
