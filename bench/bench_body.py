"""Body-model load time, memory and pose-evaluation time; prints one JSON line per measurement.

The ``body_skin_product`` line times LBS's per-vertex 3x3 product both ways on the same posed
batch: ``kinematics.apply_linear`` (what posing uses) against ``(m @ v[..., None])[..., 0]``
(cuBLAS strided-batched gemv, at most 65,535 products a launch on CUDA).

    python bench/bench_body.py [--backend anny] [--batches 1 256] [--device cpu] [--repeats 5]
"""
from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--backend", default="anny")
    parser.add_argument("--model-path", default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 256])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    import torch

    from simulate.body import kinematics as kin
    from simulate.body import load_body_model

    t0 = time.perf_counter()
    body = load_body_model(args.backend, path=args.model_path, device=args.device)
    load_s = time.perf_counter() - t0
    print(json.dumps({"bench": "body_load", "backend": body.name, "device": args.device, "load_s": round(load_s, 3),
                      "vertices": body.vertex_count, "faces": int(len(body.faces)), "joints": body.joint_count,
                      "max_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                      "torch_threads": torch.get_num_threads()}))
    rng = np.random.default_rng(0)
    for batch in args.batches:
        shape = rng.uniform(0.2, 0.8, (batch, body.shape_size)).astype(np.float32)
        pose = rng.normal(0, 0.2, (batch, body.pose_size)).astype(np.float32)
        with torch.no_grad():
            pose_s = _median_time(lambda: body.pose_torch(shape, pose), args)
        print(json.dumps({"bench": "body_pose", "backend": body.name, "device": args.device, "batch": batch,
                          "median_ms": round(1e3 * pose_s, 3), "per_body_ms": round(1e3 * pose_s / batch, 4)}))
        with torch.no_grad():
            posed = body.pose_torch(shape, pose)
            blended = kin.blend_transforms(posed.skinning_weights.to(posed.vertices), posed.skinning_transforms)
            linear, points = blended[..., :3, :3], posed.rest_vertices.expand(batch, -1, -1)
            products = {"elementwise_ms": lambda: kin.apply_linear(linear, points),
                        "matmul_ms": lambda: (linear @ points[..., None])[..., 0]}
            row = {name: round(1e3 * _median_time(fn, args), 3) for name, fn in products.items()}
        print(json.dumps({"bench": "body_skin_product", "backend": body.name, "device": args.device, "batch": batch,
                          "points": int(points.shape[0] * points.shape[1]), **row,
                          "matmul_over_elementwise": round(row["matmul_ms"] / max(row["elementwise_ms"], 1e-6), 2)}))


def _median_time(fn, args) -> float:
    """Median wall time [s] of ``fn()`` over ``args.repeats`` runs after one warm-up (synchronised on CUDA)."""
    import torch

    fn()
    times = []
    for _ in range(args.repeats):
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        fn()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


if __name__ == "__main__":
    main()
