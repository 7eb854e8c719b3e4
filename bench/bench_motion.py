"""Motion-sequence dataset throughput: one garment type of a motion spec (``poses.source:
motion``, e.g. cloth3d) through generate-dataset on one device, with where the time went.

    python bench/bench_motion.py --spec cloth3d --type top --device cuda:0 --out /tmp/bm
    python bench/bench_motion.py --spec cloth3d-mini --type top --pairs 16 --test-pairs 1 --worlds 17 --device cpu

Prints one JSON line: the garment preparation (styled garments and their canonical drapes,
``prepare_s``, from the run's log), the simulation's seconds and kept frames, kept frames per
second over the simulation and over the whole run, the frame loop's phases (``run_sequences``
statistics plus the recording callback's ``record_meter_s`` / ``record_unskin_s`` /
``record_submit_s``) and ``shards_sha256``: the sha256 of the sorted list of (task, shard sha256),
which is the same for two runs exactly when their shards are byte for byte the same (compare a
change against its base on the same device with it).
"""
from __future__ import annotations

import argparse
import copy
import hashlib
import json
import re
import shutil
import sys
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spec", default="cloth3d", help="shipped spec name or a spec file")
    parser.add_argument("--type", default=None, help="the garment type of a multi-type spec (default: its first)")
    parser.add_argument("--pairs", type=int, default=None, help="train pairs (default: the spec's); styles and shapes follow")
    parser.add_argument("--test-pairs", type=int, default=None, help="test pairs (default: the spec's)")
    parser.add_argument("--frames", type=int, default=None, help="motion.frames (default: the spec's)")
    parser.add_argument("--worlds", type=int, default=None)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--device", default=None)
    parser.add_argument("--audit-samples", type=int, default=0, help="audit.samples (default 0: no audit)")
    parser.add_argument("--out", default="/tmp/bench_motion")
    parser.add_argument("--keep", action="store_true", help="keep the output directory")
    parser.add_argument("--heartbeat", type=float, default=30.0)
    parser.add_argument("--sample-stacks", default=None, metavar="JSON",
                        help="diagnostic: where the main thread's wall time went (bench_dataset.StackSampler)")
    parser.add_argument("--sample-interval", type=float, default=0.005)
    args = parser.parse_args()

    from pipelines.generate_dataset import generate
    from pipelines.spec import load_spec, type_specs, validate_spec

    full = load_spec(args.spec)  # a path, or a shipped spec's name
    types = dict(type_specs(full))
    gtype = args.type or next(iter(types))
    if gtype not in types:
        raise SystemExit(f"--type: expected one of {', '.join(types)} (got {gtype!r})")
    spec = copy.deepcopy(types[gtype])
    spec["name"] = f"{spec['name']}-bench"
    for key, value in (("train", args.pairs), ("test", args.test_pairs)):
        if value is not None:
            for section in ("pairs", "styles", "shapes"):
                spec[section][key] = value
    if args.frames is not None:
        spec["motion"]["frames"] = args.frames
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_dataset import StackSampler, override_run_options

    override_run_options(spec, args)
    spec["audit"]["samples"] = args.audit_samples
    spec = validate_spec(spec)
    sampler = None
    if args.sample_stacks:
        sampler = StackSampler(args.sample_stacks, args.sample_interval)
        sampler.start()
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    prepare = {}

    def log(message: str) -> None:  # stderr: stdout stays one JSON line
        found = re.match(r"prepared (\d+) garment drapes .* in ([0-9.]+) s", message)
        if found:
            prepare.update(garments=int(found.group(1)), seconds=float(found.group(2)))
        print(f"[{time.perf_counter() - t0:7.1f} s] {message}", file=sys.stderr, flush=True)

    manifest = generate(spec, out, progress=False, log=log, heartbeat_s=args.heartbeat)
    wall = time.perf_counter() - t0
    if sampler is not None:
        sampler.write()
    sim = manifest.audit.get("simulation", {})
    kept = int(manifest.totals["frames_kept"])
    shards = sorted((s["task_id"], s["sha256"]) for s in manifest.shards)
    seconds = float(sim.get("seconds", wall))
    print(json.dumps({
        "bench": "motion", "spec": args.spec, "type": gtype, "device": sim.get("device"),
        "worlds": spec["simulation"]["worlds"], "resolution": spec["garment"]["resolution"],
        "tasks": len(shards), "target_frames": sim.get("target_frames"), "kept_frames": kept,
        "dropped": manifest.totals["frames_dropped"], "prepare_s": prepare.get("seconds"),
        "simulation_s": seconds, "wall_s": round(wall, 2),
        "kept_frames_per_s_simulation": round(kept / max(seconds, 1e-9), 2),
        "kept_frames_per_s_wall": round(kept / max(wall, 1e-9), 2),
        "phases": sim.get("phases"),
        "shards_sha256": hashlib.sha256(json.dumps(shards).encode()).hexdigest(),
    }), flush=True)
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
