"""The dataset filters' cost: ``QualityMeter.measure_batch`` on n frames of a garment at once, as
``generate-dataset`` measures the frames that finish together. Prints one JSON line per (n, body
mode): seconds per call and per frame, alone on the device (no simulator frame beside it).

On one H100 the whole t-shirt spec spent 27 ms of each 125 ms simulator frame in the meter
(``record_meter_s`` over ``frames``, docs/scale-out.md): this says how much of that the meter
costs by itself, and how the cost grows with n.

    python bench/bench_quality_meter.py [--device cuda:0] [--frames 1 8 32] [--resolution 7700] [--repeats 10]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np


def build(device: str, resolution: int, primary_bodies: bool):
    """The t-shirt on anny's canonical body, and a meter for it (per-part distances when
    ``primary_bodies``), as ``generate-dataset`` builds them."""
    from simulate.body import load_body_model
    from simulate.body.collision_parts import collision_parts
    from simulate.garment.drape import COLLISION_PARTS
    from simulate.garment.templates import make_template
    from simulate.quality import QualityMeter

    body = load_body_model("anny")
    template = make_template("tshirt", body, resolution=resolution)
    body_faces = body.part_faces(COLLISION_PARTS["tshirt"])
    canonical = np.asarray(body.pose(body.shape_default, body.canonical_pose).vertices, np.float32).reshape(-1, 3)
    kwargs = {}
    if primary_bodies:
        parts = collision_parts(body, "tshirt", body_faces)
        kwargs = {"body_face_groups": parts.face_groups,
                  "garment_part": parts.garment_vertex_parts(template.vertices, canonical)}
    meter = QualityMeter(template.faces, template.vertices, body_faces, body.vertex_count, device=device, **kwargs)
    return meter, np.asarray(template.vertices, np.float32), canonical


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--resolution", type=int, default=7700)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    if min(args.frames) < 1 or args.repeats < 1:
        parser.error(f"--frames and --repeats must be >= 1 (got {args.frames}, {args.repeats})")
    import warp as wp

    wp.config.quiet = True
    rng = np.random.default_rng(0)
    for primary in (False, True):
        meter, garment, body = build(args.device, args.resolution, primary)
        for n in args.frames:
            # the rest garment with sub-millimetre noise, so no two frames are the same
            x = garment[None] + rng.normal(scale=2e-4, size=(n, *garment.shape)).astype(np.float32)
            b = np.broadcast_to(body, (n, *body.shape))
            meter.measure_batch(x, b)  # slots, buffers and kernels made once
            wp.synchronize_device(args.device)
            started = time.perf_counter()
            for _ in range(args.repeats):
                metrics = meter.measure_batch(x, b)
            seconds = (time.perf_counter() - started) / args.repeats
            print(json.dumps({"bench": "quality_meter", "device": args.device, "vertices": int(len(garment)),
                              "primary_bodies": primary, "frames": n, "s_per_call": round(seconds, 5),
                              "ms_per_frame": round(1e3 * seconds / n, 3),
                              "self_intersections_frame0": metrics[0]["self_intersections"]}), flush=True)


if __name__ == "__main__":
    main()
