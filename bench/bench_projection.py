"""collision_aware's canonical projection: milliseconds per Adam step at several batch sizes, and
the projection time of a whole training split they imply, printed as one JSON line.

    python bench/bench_projection.py [--device cuda] [--vertices 7744] [--batches 64,128,256]
        [--shards 1740] [--frames-per-shard 30] [--gpus 1] [--sdf grid|mlp]

A step is one evaluation of the objective (reconstruction, Green-Lagrange strain, collision) and
its backward pass over B frames of V garment vertices, with the default fields network and SDF
(learn/collision_aware/train.py; ``--sdf mlp``: the SDF network instead of the grid). Its cost depends on B, V and the networks' sizes, not on their
weights or the garment's shape, so the garment is a grid of V vertices wrapped around the
canonical torso and the networks are untrained. A split of S shards of F frames, projected in
batches of B shards over G GPUs, takes ceil(S / G / B) x F x (steps + fixed-point iterations)
steps per GPU; ``projected_split_s`` is that times the measured step (the fixed-point iterations
are counted as full steps, an upper bound). The shipped t-shirt spec's training split: ~1,740
shards of up to 30 frames, 7,744 vertices.
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import torch


def wrapped_grid(body, vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A grid garment of ~``vertices`` vertices on a cylinder 3 cm outside the canonical torso
    [m] (V, 3), with its faces (F, 3)."""
    from learn.collision_aware.fields import canonical_body
    from learn.common.mesh import grid_mesh

    rest = canonical_body(body)
    torso = rest[body.part_vertex_mask(["torso"])]
    center = torso.mean(0)
    radius = float(np.percentile(np.linalg.norm((torso - center)[:, [0, 2]], axis=1), 90)) + 0.03
    side = int(round(math.sqrt(vertices)))
    grid, faces = grid_mesh(side, side, spacing=1.0 / (side - 1))
    angle, height = 2 * np.pi * grid[:, 0] * (side - 1) / side, grid[:, 1]
    y0, y1 = np.percentile(torso[:, 1], [10, 90])
    points = np.stack([center[0] + radius * np.cos(angle), y0 + (y1 - y0) * height, center[2] + radius * np.sin(angle)], 1)
    return points.astype(np.float32), faces


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--vertices", type=int, default=7744)
    parser.add_argument("--batches", default="64,128,256", help="batch sizes B (shards per batch), comma separated")
    parser.add_argument("--steps", type=int, default=10, help="timed steps per batch size (after 3 warm-up steps)")
    parser.add_argument("--shards", type=int, default=1740, help="training shards of the split to project")
    parser.add_argument("--frames-per-shard", type=int, default=30)
    parser.add_argument("--gpus", type=int, default=1, help="processes the split's shards are dealt over")
    parser.add_argument("--sdf", choices=("grid", "mlp"), default="grid", help="the body SDF's kind (sdf.kind)")
    args = parser.parse_args(argv)

    from learn.collision_aware.canonicalize import ProjectionSettings, projection_terms, triangle_reference
    from learn.collision_aware.fields import canonical_body, new_diffused_body, shape_basis
    from learn.collision_aware.sdf import grid_sdf, new_body_sdf
    from learn.collision_aware.train import DEFAULT_HYPERPARAMETERS
    from simulate.body import load_body_model

    body = load_body_model("anny")
    hf, hs = DEFAULT_HYPERPARAMETERS["fields"], DEFAULT_HYPERPARAMETERS["sdf"]
    torch.manual_seed(0)
    fields = new_diffused_body(body, hidden_size=hf["hidden_size"], layers=hf["layers"], frequencies=hf["frequencies"],
                               shape_basis=hf["shape_basis"], shape_hidden_size=hf["shape_hidden_size"],
                               shape_layers=hf["shape_layers"], shape_frequencies=hf["shape_frequencies"])
    if fields.basis_size:  # the default basis field: its basis from random shapes (the networks stay untrained)
        ranges = np.asarray(body.shape_ranges, np.float64)
        shapes = np.random.default_rng(0).uniform(ranges[:, 0], ranges[:, 1], (hf["shapes"], len(ranges)))
        rest = canonical_body(body)
        fields.set_shape_basis(*shape_basis(body.rest(shapes.astype(np.float32))[0] - rest, fields.basis_size), rest)
    fields = fields.to(args.device).requires_grad_(False)
    if args.sdf == "grid":
        sdf = grid_sdf(canonical_body(body), body.faces, voxel_m=hs["voxel_m"], margin_m=hs["margin_m"],
                       warp_device=args.device if args.device.startswith("cuda") else "cpu")
    else:
        sdf = new_body_sdf(canonical_body(body), hidden_size=hs["hidden_size"], layers=hs["layers"],
                           frequencies=hs["frequencies"])
    sdf = sdf.to(args.device).requires_grad_(False)
    garment, faces = wrapped_grid(body, args.vertices)
    faces_t = torch.as_tensor(faces, dtype=torch.int64, device=args.device)
    settings = ProjectionSettings()
    body_on = body.on_device(args.device)
    rows = []
    for batch in [int(b) for b in args.batches.split(",")]:
        rng = np.random.default_rng(batch)
        shape = torch.as_tensor(np.repeat(np.asarray(body.shape_default, np.float32)[None], batch, 0), device=args.device)
        pose = torch.as_tensor(0.2 * rng.standard_normal((batch, body.pose_size)), dtype=torch.float32, device=args.device)
        with torch.no_grad():
            transforms = body_on.pose_torch(shape, pose).skinning_transforms.to(args.device)
        target = torch.as_tensor(garment, device=args.device)[None].repeat(batch, 1, 1)
        reference = triangle_reference(target, faces_t)
        x = target.clone().requires_grad_(True)
        optimizer = torch.optim.Adam([x], lr=settings.lr)

        def step() -> None:
            terms = projection_terms(x, target, shape, transforms, fields, sdf, faces_t, reference, settings)
            optimizer.zero_grad(set_to_none=True)
            terms["objective"].sum().backward()
            optimizer.step()

        for _ in range(3):
            step()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        t0 = time.perf_counter()
        for _ in range(args.steps):
            step()
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        ms = 1e3 * (time.perf_counter() - t0) / args.steps
        per_gpu = math.ceil(args.shards / args.gpus)
        steps = math.ceil(per_gpu / batch) * args.frames_per_shard * (settings.steps + settings.fixed_point_iterations)
        rows.append({"batch_sequences": batch, "ms_per_step": round(ms, 2),
                     "us_per_frame_step": round(1e3 * ms / batch, 2),
                     "peak_memory_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2)
                     if args.device.startswith("cuda") else None,
                     "projected_split_s": round(steps * ms / 1e3, 1)})
    print(json.dumps({"device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
                      "vertices": int(garment.shape[0]), "faces": int(faces.shape[0]), "shards": args.shards,
                      "frames_per_shard": args.frames_per_shard, "gpus": args.gpus,
                      "sdf": args.sdf, "steps_per_frame": settings.steps, "fixed_point_iterations": settings.fixed_point_iterations,
                      "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
