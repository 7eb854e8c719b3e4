"""Poses drawn across the joint limits, each reached from the canonical drape: the share that comes
to rest with no garment edge through the garment, per solver / self-contact setting, in one run on
one device.

    python bench/bench_uniform_poses.py [--poses 40] [--resolution 1800] [--device cpu]
                                        [--runs xpbd-sc,xpbd-sc-untangle,vbd-sc,vbd-sc-ball]
                                        [--garment pants] [--stepping 10x3] [--poses-per-task 8]

Poses: the dataset's sampler (``simulate.poses.PoseSampler``: the garment type's joints (upper body
for tops, lower for bottoms, ``simulate.poses.default_pose_joints``), limb joints
uniform within ``JOINT_LIMITS``, spine and neck half-normal about the centre line) with the
dataset's pruning of poses whose body intersects itself, seeded. Each pose is one task of
``run_sequences`` (``--poses-per-task N``: N consecutive poses a task, visited in order, as a
dataset's worlds go from target to target) from the garment's canonical drape on the neutral anny body, bottoms held at
their waistband (greedy slerp from the canonical pose, ``interpolation_threshold`` 0.05 rad per
frame, then held to rest), all tasks
as worlds of one simulator. Runs are ``bench_self_contact.run_settings``'s: ``<solver>[-sc|-scb]
[-untangle]`` (``-untangle``: the library's untangling, every 5th substep).

Prints one JSON line per run: crossings of the canonical drape, poses, at rest (status CONVERGED), at rest with 0 crossings (the
target share), frames with crossings and the largest count, distorted and penetrating frames by the
dataset's thresholds (more than 1 % of triangles outside area ratios [0.25, 2]; vertices deeper
than 1 mm), and the wall time of the sequences.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from bench_self_contact import arms_lowered_scene, canonical_drape, parse_stepping, run_settings
from simulate.garment.drape import COLLISION_PARTS
from simulate.poses import GARMENT_POSE_JOINTS, PoseSampler, default_pose_joints, sample_poses
from simulate.quasi_static import WorldStatus
from simulate.sequence import SequenceTask, run_sequences


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=40)
    parser.add_argument("--resolution", type=int, default=1800)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-frames", type=int, default=60, help="hold budget per pose [frames]")
    parser.add_argument("--runs", default="xpbd-sc,xpbd-sc-untangle")
    parser.add_argument("--garment", default="tshirt", choices=sorted(COLLISION_PARTS),
                        help="the garment type (its poses move the type's joints)")
    parser.add_argument("--poses-per-task", type=int, default=1,
                        help="poses a task visits in turn from the canonical drape (1: each pose on its own)")
    parser.add_argument("--stepping", default=None, metavar="SUBSTEPSxITERATIONS",
                        help="every run's stepping, e.g. 10x3 (default: each solver's shipped stepping)")
    args = parser.parse_args()
    if args.poses < 1:
        parser.error(f"--poses must be >= 1 (got {args.poses})")
    if args.poses_per_task < 1:
        parser.error(f"--poses-per-task must be >= 1 (got {args.poses_per_task})")
    stepping = parse_stepping(args.stepping, parser)
    for run in args.runs.split(","):
        try:
            run_settings(run, max_frames=1, min_hold_frames=1, step=0.05, friction=None, stepping=stepping)
        except ValueError as exc:
            parser.error(f"--runs: {exc}")

    scene = arms_lowered_scene(args.resolution, 0.0, args.garment)
    body, template = scene.body, scene.template
    shape = np.asarray(body.shape_default, np.float32)
    sampler = PoseSampler(joints=GARMENT_POSE_JOINTS[default_pose_joints(args.garment)], base_pose=scene.canonical)
    poses, _ = sample_poses(body, shape, args.poses, sampler, np.random.default_rng(args.seed))
    meter = scene.meter(args.device)
    for run in args.runs.split(","):
        settings = run_settings(run, max_frames=args.max_frames, min_hold_frames=1, step=0.05, friction=None,
                                stepping=stepping)
        start, _ = canonical_drape(scene, settings, args.device)
        start_crossings = int(meter.self_intersections(start))
        k = args.poses_per_task
        tasks = [SequenceTask(rest_vertices=template.vertices, start_vertices=start, shape=shape, poses=poses[i:i + k])
                 for i in range(0, len(poses), k)]
        frames = []
        t0 = time.perf_counter()
        run_sequences(body, template.faces, tasks, settings=settings, on_frame=frames.append,
                      material_uv=template.face_uv, worlds=len(tasks), **scene.sim_arguments(args.device))
        seconds = time.perf_counter() - t0
        frames.sort(key=lambda f: (f.task, f.key))
        quality = meter.measure_batch(np.stack([f.positions for f in frames]),
                                      np.stack([f.body_vertices for f in frames]), area_bounds=(0.25, 2.0))
        crossings = np.array([q["self_intersections"] for q in quality])
        rest = np.array([f.status == WorldStatus.CONVERGED for f in frames])
        print(json.dumps({
            "run": run, "garment": args.garment, "stepping": [settings.sim.substeps, settings.sim.iterations],
            "poses": len(frames), "poses_per_task": args.poses_per_task, "resolution": args.resolution, "vertices": len(template.vertices),
            "device": args.device, "seed": args.seed, "drape_self_intersections": start_crossings,
            "at_rest": int(rest.sum()),
            "at_rest_without_crossings": int((rest & (crossings == 0)).sum()),
            "share_at_rest_without_crossings": round(float((rest & (crossings == 0)).mean()), 3),
            "frames_with_crossings": int((crossings > 0).sum()), "most_crossings": int(crossings.max()),
            "distorted_frames": int(sum(q["distorted_fraction"] > 0.01 for q in quality)),
            "penetrating_frames": int(sum(q["penetration_fraction"] > 0.0 for q in quality)),
            "sequences_s": round(seconds, 2)}), flush=True)


if __name__ == "__main__":
    main()
