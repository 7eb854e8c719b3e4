"""Self-contact where an arm presses the sleeve onto the torso: the t-shirt's canonical drape, then
both arms lowered from the canonical pose to ``--angle`` rad (slerp'ed, ``--step`` rad per frame)
and held to rest, for each solver / self-contact setting in one run on one device.

    python bench/bench_self_contact.py [--resolution 1800] [--device cpu] [--runs vbd-sc,xpbd-sc,vbd,xpbd] [--stepping 10x3]
                                       [--to-rest --hold-frames 60]

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
from dataclasses import dataclass

import numpy as np

from simulate.body import load_body_model
from simulate.body.collision_parts import collision_parts
from simulate.garment.drape import COLLISION_PARTS
from simulate.garment.templates import make_template
from simulate.quality import QualityMeter
from simulate.quasi_static import SimSettings
from simulate.sequence import SequenceSettings, SequenceTask, drape_static, run_sequences

STEPPING = {"vbd": (20, 3), "xpbd": (15, 5)}


@dataclass
class ArmsLoweredScene:
    """A garment (the t-shirt unless stated) on the neutral anny body and the lowered pose its arms
    turn to.

    Attributes:
        body: the anny body model; template: the garment's template (rest ``vertices`` (V, 3) [m],
        ``faces`` (F, 3), ``face_uv``, ``attachment``: a bottom's waistband vertices or None);
        body_faces: the body faces the garment meets (Fb, 3);
        parts: its primary collision bodies; garment_part: each garment vertex's part (V,);
        canonical / lowered: the canonical pose and the pose with both shoulders turned to the
        torso (60,); rest_body: the body in the canonical pose [m] (Vb, 3).
    """

    body: object
    template: object
    body_faces: np.ndarray
    parts: object
    garment_part: np.ndarray
    canonical: np.ndarray
    lowered: np.ndarray
    rest_body: np.ndarray

    def meter(self, device: str) -> QualityMeter:
        """The dataset's quality meter on this scene (exact crossings, penetration, distortion)."""
        return QualityMeter(self.template.faces, self.template.vertices, self.body_faces, len(self.rest_body),
                            device=device, body_face_groups=self.parts.face_groups, garment_part=self.garment_part)

    def sim_arguments(self, device: str) -> dict:
        """The body and collision-part keywords ``drape_static`` and ``run_sequences`` take."""
        return dict(body_faces=self.body_faces, body_face_groups=self.parts.face_groups, body_part=self.garment_part,
                    device=device, attached=getattr(self.template, "attachment", None))


def arms_lowered_scene(resolution: int, angle: float, garment: str = "tshirt") -> ArmsLoweredScene:
    """The scene at ``resolution`` garment vertices (approximate), shoulders turned by ``angle`` [rad];
    ``garment``: the template type."""
    body = load_body_model("anny")
    template = make_template(garment, body, resolution=resolution)
    body_faces = body.part_faces(COLLISION_PARTS[garment])
    parts = collision_parts(body, garment, body_faces)
    canonical = np.asarray(body.canonical_pose, np.float32)
    rest_body = np.asarray(body.pose(body.shape_default, canonical).vertices).reshape(-1, 3)
    garment_part = parts.garment_vertex_parts(template.vertices, rest_body)
    lowered = canonical + body.pose_from_dict({"left_shoulder": [0.0, 0.0, -angle],
                                               "right_shoulder": [0.0, 0.0, angle]})
    return ArmsLoweredScene(body, template, body_faces, parts, garment_part, canonical, lowered, rest_body)


def run_settings(run: str, *, max_frames: int, min_hold_frames: int, step: float,
                 friction: float | None, stepping: tuple[int, int] | None = None) -> SequenceSettings:
    """Sequence settings of run ``<solver>[-sc|-scb][-untangle][-ball]`` (scb: XPBD with the
    displacement bounds; untangle: intersection contour minimization after every substep; ball:
    VBD's bounds as balls, not directional): the solver's
    shipped stepping, frames of 1/45 s, damping 20/s, holds of at least ``min_hold_frames`` and
    at most ``max_frames`` frames, joints turning ``step`` [rad] per frame; ``stepping``
    (substeps, iterations) replaces the solver's shipped stepping."""
    solver, *flags = run.split("-")
    if solver not in STEPPING or not set(flags) <= {"sc", "scb", "untangle", "ball"} or {"sc", "scb"} <= set(flags):
        raise ValueError(f"run must be <solver>[-sc|-scb][-untangle][-ball] with solver in {sorted(STEPPING)} "
                         f"(got {run!r})")
    substeps, iterations = stepping or STEPPING[solver]
    sim = SimSettings(frame_dt=1.0 / 45.0, substeps=substeps, iterations=iterations, damping=20.0, tolerance=0.05,
                      outlier_fraction=0.02, max_frames=max_frames, limit_cycle_window=8,
                      self_contact_bounds="scb" in flags, untangle="untangle" in flags,
                      self_contact_directional_bounds="ball" not in flags)
    return SequenceSettings(sim=sim, solver=solver, self_contact=bool({"sc", "scb"} & set(flags)),
                            shape_transition_frames=1, interpolation_threshold=step, min_hold_frames=min_hold_frames,
                            friction=friction)


def parse_stepping(value: str | None, parser: argparse.ArgumentParser) -> tuple[int, int] | None:
    """``--stepping SUBSTEPSxITERATIONS`` as (substeps, iterations); None stays None (each solver's
    shipped stepping); anything else exits 2 naming the option."""
    if value is None:
        return None
    try:
        stepping = tuple(int(v) for v in value.lower().split("x"))
        if len(stepping) != 2 or min(stepping) < 1:
            raise ValueError
    except ValueError:
        parser.error(f"--stepping: expected SUBSTEPSxITERATIONS with both >= 1, e.g. 10x3 (got {value!r})")
    return stepping


def canonical_drape(scene: ArmsLoweredScene, settings: SequenceSettings, device: str) -> tuple[np.ndarray, float]:
    """The t-shirt relaxed on the canonical body with ``settings`` (at most 80 frames): ((V, 3) [m], wall [s])."""
    t0 = time.perf_counter()
    start, _ = drape_static(scene.body, scene.template.faces, scene.template.vertices[None],
                            shapes=scene.body.shape_default[None], poses=scene.canonical[None], settings=settings,
                            max_frames=80, material_uv=scene.template.face_uv, **scene.sim_arguments(device))
    return start[0], time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=1800)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--angle", type=float, default=1.0, help="shoulder rotation toward the torso [rad]")
    parser.add_argument("--step", type=float, default=0.05, help="largest joint turn per frame [rad]")
    parser.add_argument("--hold-frames", type=int, default=30)
    parser.add_argument("--to-rest", action="store_true",
                        help="end the hold at rest (at least 2 frames, at most --hold-frames); hold_frames then "
                             "says how many frames the garment took to come to rest")
    parser.add_argument("--friction", type=float, default=None,
                        help="0: body friction off (default: each fabric's coefficient)")
    parser.add_argument("--runs", default="vbd-sc,xpbd-sc")
    parser.add_argument("--stepping", default=None, metavar="SUBSTEPSxITERATIONS",
                        help="every run's stepping, e.g. 10x3 (default: each solver's shipped stepping)")
    parser.add_argument("--save", default=None, metavar="DIR",
                        help="write each run's held garment and body (RUN.npz: garment, body, faces, area ratios)")
    args = parser.parse_args()
    stepping = parse_stepping(args.stepping, parser)
    for run in args.runs.split(","):
        try:
            run_settings(run, max_frames=1, min_hold_frames=1, step=args.step, friction=args.friction,
                         stepping=stepping)
        except ValueError as exc:
            parser.error(f"--runs: {exc}")

    scene = arms_lowered_scene(args.resolution, args.angle)
    template, body = scene.template, scene.body
    meter = scene.meter(args.device)
    for run in args.runs.split(","):
        settings = run_settings(run, max_frames=args.hold_frames, min_hold_frames=2 if args.to_rest else args.hold_frames,
                                step=args.step,
                                friction=args.friction, stepping=stepping)
        start, drape_s = canonical_drape(scene, settings, args.device)
        task = SequenceTask(rest_vertices=template.vertices, start_vertices=start,
                            shape=np.asarray(body.shape_default, np.float32), poses=scene.lowered[None])
        frames = []
        t0 = time.perf_counter()
        run_sequences(body, template.faces, [task], settings=settings, on_frame=frames.append,
                      material_uv=template.face_uv, **scene.sim_arguments(args.device))
        hold_s = time.perf_counter() - t0
        frame = frames[-1]
        start_q = meter.measure(start, scene.rest_body)
        held = meter.measure(frame.positions, frame.body_vertices, area_bounds=(0.25, 2.0))
        if args.save:
            from pathlib import Path

            from simulate.quality import triangle_areas

            Path(args.save).mkdir(parents=True, exist_ok=True)
            ratio = triangle_areas(frame.positions, template.faces) / triangle_areas(template.vertices, template.faces)
            np.savez(Path(args.save) / f"{run}.npz", garment=frame.positions, body=frame.body_vertices,
                     faces=template.faces, body_faces=scene.body_faces, area_ratio=ratio,
                     garment_part=scene.garment_part)
        print(json.dumps({
            "run": run, "friction": args.friction, "stepping": [settings.sim.substeps, settings.sim.iterations],
            "resolution": args.resolution, "vertices": len(template.vertices), "device": args.device,
            "angle_rad": args.angle, "drape_self_intersections": start_q["self_intersections"],
            "drape_contours": start_q["self_intersection_contours"], "self_intersections": held["self_intersections"],
            "contours": held["self_intersection_contours"], "penetration_fraction": held["penetration_fraction"],
            "distorted_fraction": held["distorted_fraction"], "status": int(frame.status), "hold_frames": frame.frames,
            "drape_s": round(drape_s, 2), "sequence_s": round(hold_s, 2)}), flush=True)


if __name__ == "__main__":
    main()
