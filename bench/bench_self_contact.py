"""Self-contact where an arm presses the sleeve onto the torso: the t-shirt's canonical drape, then
both arms lowered from the canonical pose to ``--angle`` rad (slerp'ed, ``--step`` rad per frame)
and held to rest, for each solver / self-contact setting in one run on one device.

    python bench/bench_self_contact.py [--resolution 1800] [--device cpu] [--runs vbd-sc,xpbd-sc,vbd,xpbd]

Prints one JSON line per run: crossing garment edges (``self_intersections``) and intersection
contours after the canonical drape and after the hold, the penetration and distorted-triangle
shares of the held frame (the dataset's filters: seed 001 D.6 area bounds), its status and hold
frames, and the wall time of the sequence. Runs: ``<solver>[-sc|-scb][-untangle]`` with the solver's
shipped stepping (VBD 20 x 3, XPBD 15 x 5, frames of 1/45 s, damping 20/s, primary collision
bodies); ``-sc``: self-contact; ``-scb``: XPBD self-contact with the displacement bounds
(``SimSettings.self_contact_bounds``); ``-untangle``: intersection contour minimization after
every substep.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from simulate.body import load_body_model
from simulate.body.collision_parts import collision_parts
from simulate.garment.drape import COLLISION_PARTS
from simulate.garment.templates import make_template
from simulate.quality import QualityMeter
from simulate.quasi_static import SimSettings
from simulate.sequence import SequenceSettings, SequenceTask, drape_static, run_sequences

STEPPING = {"vbd": (20, 3), "xpbd": (15, 5)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=1800)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--angle", type=float, default=1.0, help="shoulder rotation toward the torso [rad]")
    parser.add_argument("--step", type=float, default=0.05, help="largest joint turn per frame [rad]")
    parser.add_argument("--hold-frames", type=int, default=30)
    parser.add_argument("--friction", type=float, default=None,
                        help="0: body friction off (default: each fabric's coefficient)")
    parser.add_argument("--runs", default="vbd-sc,xpbd-sc")
    parser.add_argument("--save", default=None, metavar="DIR",
                        help="write each run's held garment and body (RUN.npz: garment, body, faces, area ratios)")
    args = parser.parse_args()

    body = load_body_model("anny")
    template = make_template("tshirt", body, resolution=args.resolution)
    body_faces = body.part_faces(COLLISION_PARTS["tshirt"])
    parts = collision_parts(body, "tshirt", body_faces)
    canonical = np.asarray(body.canonical_pose, np.float32)
    rest_body = np.asarray(body.pose(body.shape_default, canonical).vertices).reshape(-1, 3)
    garment_part = parts.garment_vertex_parts(template.vertices, rest_body)
    lowered = canonical + body.pose_from_dict({"left_shoulder": [0.0, 0.0, -args.angle],
                                               "right_shoulder": [0.0, 0.0, args.angle]})
    meter = QualityMeter(template.faces, template.vertices, body_faces, len(rest_body), device=args.device,
                         body_face_groups=parts.face_groups, garment_part=garment_part)
    for run in args.runs.split(","):
        solver, *flags = run.split("-")
        if solver not in STEPPING or not set(flags) <= {"sc", "scb", "untangle"}:
            parser.error(f"--runs: {run!r} is not <solver>[-sc|-scb][-untangle] with a solver of {sorted(STEPPING)}")
        substeps, iterations = STEPPING[solver]
        sim = SimSettings(frame_dt=1.0 / 45.0, substeps=substeps, iterations=iterations, damping=20.0, tolerance=0.05,
                          outlier_fraction=0.02, max_frames=args.hold_frames, limit_cycle_window=8,
                          untangle="untangle" in flags, self_contact_bounds="scb" in flags)
        settings = SequenceSettings(sim=sim, solver=solver, self_contact=bool({"sc", "scb"} & set(flags)),
                                    shape_transition_frames=1,
                                    interpolation_threshold=args.step, min_hold_frames=args.hold_frames,
                                    friction=args.friction)
        common = dict(body_faces=body_faces, body_face_groups=parts.face_groups, body_part=garment_part,
                      device=args.device)
        t0 = time.perf_counter()
        start, _ = drape_static(body, template.faces, template.vertices[None], shapes=body.shape_default[None],
                                poses=canonical[None], settings=settings, max_frames=80, material_uv=template.face_uv,
                                **common)
        drape_s = time.perf_counter() - t0
        task = SequenceTask(rest_vertices=template.vertices, start_vertices=start[0],
                            shape=np.asarray(body.shape_default, np.float32), poses=lowered[None])
        frames = []
        t0 = time.perf_counter()
        run_sequences(body, template.faces, [task], settings=settings, on_frame=frames.append,
                      material_uv=template.face_uv, **common)
        hold_s = time.perf_counter() - t0
        frame = frames[-1]
        start_q = meter.measure(start[0], rest_body)
        held = meter.measure(frame.positions, frame.body_vertices, area_bounds=(0.25, 2.0))
        if args.save:
            from pathlib import Path

            from simulate.quality import triangle_areas

            Path(args.save).mkdir(parents=True, exist_ok=True)
            ratio = triangle_areas(frame.positions, template.faces) / triangle_areas(template.vertices, template.faces)
            np.savez(Path(args.save) / f"{run}.npz", garment=frame.positions, body=frame.body_vertices,
                     faces=template.faces, body_faces=body_faces, area_ratio=ratio, garment_part=garment_part)
        print(json.dumps({
            "run": run, "friction": args.friction, "resolution": args.resolution, "vertices": len(template.vertices), "device": args.device,
            "angle_rad": args.angle, "drape_self_intersections": start_q["self_intersections"],
            "drape_contours": start_q["self_intersection_contours"], "self_intersections": held["self_intersections"],
            "contours": held["self_intersection_contours"], "penetration_fraction": held["penetration_fraction"],
            "distorted_fraction": held["distorted_fraction"], "status": int(frame.status), "hold_frames": frame.frames,
            "drape_s": round(drape_s, 2), "sequence_s": round(hold_s, 2)}), flush=True)


if __name__ == "__main__":
    main()
