"""Per-dataset audit: how close are the production frames to converged physics?

A seeded random sample of kept frames is re-simulated from the recorded garment on
the same body (shape, pose) with a tolerance ``audit.tolerance_factor`` times the
production one, twice the iterations and a larger frame budget; the distance between
the production and the tight result is the frame's error. The distribution (mm) and
the time spent go into the manifest's ``audit`` block.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

AUDIT_MIN_FRAMES = 240
"""Frame budget of the audit's tight re-solve at least (4x the spec's hold budget otherwise): with
short holds (e.g. 2 frames) a 4x budget would stop the reference before it is at rest."""


def audit_dataset(ctx, out_dir: Path, manifest, *, log: Callable[[str], None] = print) -> dict[str, Any]:
    from data_manifest.reader import DatasetReader
    from simulate.sequence import drape_static

    from pipelines.generate_dataset import sequence_settings

    spec = ctx.spec
    t0 = time.perf_counter()
    reader = DatasetReader(out_dir)
    candidates = [(split, i) for split in reader.splits for i in range(reader.num_frames(split))]
    want = min(int(spec["audit"]["samples"]), len(candidates))
    if want == 0:
        return {"samples": 0, "note": "no kept frames to audit"}
    rng = np.random.default_rng([int(spec["seed"]), 71])
    picks = [candidates[i] for i in sorted(rng.choice(len(candidates), want, replace=False))]
    frames = [reader.get(split, i) for split, i in picks]
    tasks = ctx.tasks
    rest = np.stack([ctx.style_rest[tasks[f["task_id"]].style_index] for f in frames])
    start = np.stack([f["posed_vertices"] for f in frames])
    base = sequence_settings(spec)
    tight = dataclasses.replace(base, sim=dataclasses.replace(
        base.sim, tolerance=base.sim.tolerance * float(spec["audit"]["tolerance_factor"]),
        iterations=2 * base.sim.iterations, max_frames=max(4 * base.sim.max_frames, AUDIT_MIN_FRAMES)))
    positions, status = drape_static(ctx.body, ctx.template.faces, rest, shapes=np.stack([f["shape"] for f in frames]),
                                     poses=np.stack([f["pose"] for f in frames]), body_faces=ctx.body_faces,
                                     settings=tight, device=ctx.device, fabric=spec["garment"]["fabric"],
                                     start_vertices=start, material_uv=ctx.template.face_uv)
    dist_mm = 1e3 * np.linalg.norm(positions - start, axis=-1)  # (N, V)
    per_max, per_mean = dist_mm.max(1), dist_mm.mean(1)
    reader.close()
    result = {
        "samples": want,
        "tolerance_mps": tight.sim.tolerance,
        "iterations": tight.sim.iterations,
        "frames": [{"split": s, "index": int(i), "task_id": f["task_id"], "max_mm": float(a), "mean_mm": float(b),
                    "status": int(st)} for (s, i), f, a, b, st in zip(picks, frames, per_max, per_mean, status)],
        "max_mm": {"median": float(np.median(per_max)), "p90": float(np.percentile(per_max, 90)), "max": float(per_max.max())},
        "mean_mm": {"median": float(np.median(per_mean)), "p90": float(np.percentile(per_mean, 90)), "max": float(per_mean.max())},
        "seconds": round(time.perf_counter() - t0, 3),
    }
    log(f"audit: {want} kept frames re-solved at {tight.sim.tolerance:g} m/s: vertex error median of max "
        f"{result['max_mm']['median']:.2f} mm, median of mean {result['mean_mm']['median']:.2f} mm ({result['seconds']:.1f} s)")
    return result
