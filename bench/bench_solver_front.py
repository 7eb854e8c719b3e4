"""Solver settings side by side on the dataset's t-shirt: time to rest against thread strain and error.

Scene: the t-shirt template at --resolution vertices, cut at its default style, falls from its rest
geometry onto the default body in the canonical pose (the canonical drape every dataset sequence
starts from), cotton, --worlds copies in one model (one launch advances all of them), stepped as
the TailorNet spec steps (1/45 s frames, damping 20/s, body queries every 5th substep, 2 % outlier
vertices, limit cycles of 8 frames) until the stopping rule (max speed < tolerance for 3 frames)
or --max-frames.  For every setting (solver, substeps, iterations, tolerance):

* ``wall_s``: wall time of the relaxation, device synchronized, kernels compiled and the frame's
  CUDA graph captured beforehand (a warm-up relaxation of 2 frames); ``ms_per_world_frame``;
* ``frames``: frames to rest (max over worlds: the batch waits for its slowest world);
* thread strain: per triangle |f1| - 1 and |f2| - 1 (stretch along warp and weft) over all worlds,
  99th percentile and max;
* ``positions.npz`` (in --out-dir): world 0's final positions of every setting, keyed by the
  setting's label, so that the error against the converged reference
  (``simulate.solvers.reference``, float64 Newton) can be computed afterwards on any machine:
  ``python bench/bench_solver_front.py --reference OUT_DIR`` adds ``error_mean_mm`` /
  ``error_max_mm`` and writes ``front.png`` (error against time).

One JSON line per setting.

    python bench/bench_solver_front.py --device cuda:0 --worlds 256 --resolution 7700 --out-dir /tmp/front
    python bench/bench_solver_front.py --reference /tmp/front
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import warp as wp

SETTINGS = [
    ("xpbd", 15, 5, 0.05), ("xpbd", 15, 5, 0.01), ("xpbd", 30, 10, 0.01),
    ("vbd", 20, 3, 0.05), ("vbd", 20, 3, 0.02), ("vbd", 20, 3, 0.01), ("vbd", 15, 5, 0.02), ("vbd", 10, 8, 0.02),
    ("vbd", 30, 2, 0.02), ("vbd", 10, 5, 0.02), ("vbd", 40, 5, 0.002),
]
"""(solver, substeps per frame, iterations per substep, tolerance [m/s])."""
CONTACT_THICKNESS = 2.0e-3
"""BodyCollider's default contact thickness [m] (the reference adds half the fabric thickness per
particle, as the collider does)."""


def tshirt_on_body(resolution: int):
    """(rest vertices (V, 3) [m], faces (F, 3), face UVs (F, 3, 2) or None, body vertices (Vb, 3),
    body faces) of the t-shirt at its default style on the neutral body in the canonical pose."""
    from simulate.body import load_body_model
    from simulate.garment.drape import COLLISION_PARTS
    from simulate.garment.templates import generate_garment
    from simulate.garment.templates import make_template

    body = load_body_model("anny")
    template = make_template("tshirt", body, resolution=resolution)
    rest = np.asarray(generate_garment("tshirt", None, body, template=template), np.float64)
    body_v = np.asarray(body.pose(body.shape_default[None], body.canonical_pose[None]).vertices[0], np.float64)
    body_f = np.asarray(body.part_faces(list(COLLISION_PARTS["tshirt"])), np.int64)
    uv = getattr(template, "face_uv", None)
    return rest, np.asarray(template.faces, np.int64), uv, body_v, body_f


def thread_strain(model, positions: np.ndarray, world: int | None = None) -> np.ndarray:
    """|f1| - 1 and |f2| - 1 of every triangle (of ``world``, or of all worlds) [-], (2 T,), the
    stretch along the two material directions of ``tri_dm_inv``."""
    mask = slice(None) if world is None else model.tri_world.numpy()[:model.tri_count] == world
    dm = model.tri_dm_inv.numpy()[:model.tri_count][mask].astype(np.float64)
    x = positions[model.tri_indices_np[mask]]
    e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    f1 = e1 * dm[:, 0, 0, None] + e2 * dm[:, 1, 0, None]
    f2 = e1 * dm[:, 0, 1, None] + e2 * dm[:, 1, 1, None]
    return np.concatenate([np.linalg.norm(f1, axis=1), np.linalg.norm(f2, axis=1)]) - 1.0


def build(scene, worlds: int, device: str, material_uv: bool):
    from simulate.cloth import ClothBuilder, Features
    from simulate.contact import BodyCollider

    rest, faces, uv, body_v, body_f = scene
    builder = ClothBuilder()
    for _ in range(worlds):
        kwargs = {"material_uv": uv} if (material_uv and uv is not None) else {}
        builder.add_garment(rest, faces, fabric="cotton", **kwargs)
    model = builder.finalize(device, features=Features())
    collider = BodyCollider(np.repeat(body_v[None], worlds, axis=0), body_f, device=device)
    return model, collider


def run_setting(scene, built, args, solver: str, substeps: int, iterations: int, tolerance: float) -> dict:
    """One setting on the built model and collider (shared by every setting: both are read-only
    to the simulator, which keeps its own states)."""
    from simulate.quasi_static import QuasiStaticSimulator, SimSettings

    model, collider = built

    def simulator(max_frames: int):
        settings = SimSettings(frame_dt=1.0 / 45.0, substeps=substeps, iterations=iterations, damping=20.0,
                               tolerance=tolerance, patience=3, outlier_fraction=0.02, limit_cycle_window=8,
                               body_contact_detect_every=5, max_frames=max_frames, explosion_stretch=50.0)
        return model, QuasiStaticSimulator(model, collider, solver=solver, settings=settings)

    _, warm = simulator(2)
    warm.relax()
    wp.synchronize_device(args.device)
    model, sim = simulator(args.max_frames)
    wp.synchronize_device(args.device)
    t0 = time.perf_counter()
    status = sim.relax()
    wp.synchronize_device(args.device)
    wall = time.perf_counter() - t0
    q = sim.positions().astype(np.float64)
    strain = thread_strain(model, q)
    frames = int(len(sim.residual_history))
    label = f"{solver}_{substeps}x{iterations}_tol{tolerance:g}"
    row = {"setting": label, "solver": solver, "substeps": substeps, "iterations": iterations, "tolerance": tolerance,
           "worlds": args.worlds, "vertices": int(model.world_particle_count[0]), "device": str(args.device),
           "wall_s": round(wall, 3), "frames": frames,
           "ms_per_world_frame": round(1e3 * wall / max(frames, 1) / args.worlds, 4),
           "converged_share": float(np.mean(status == 1)),
           "strain_p99": float(np.percentile(strain, 99)), "strain_max": float(strain.max()),
           "strain_p99_world0": float(np.percentile(thread_strain(model, q, 0), 99))}
    if args.out_dir:  # world 0's final positions, every setting in one file
        path = Path(args.out_dir) / "positions.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        saved = dict(np.load(path)) if path.is_file() else {}
        saved[label] = q[:int(model.world_particle_count[0])]
        np.savez(path, **saved)
    return row


def add_reference(out_dir: Path, resolution: int, material_uv: bool) -> None:
    """Errors of every saved setting against the converged reference of world 0, started from the
    most converged saved state; rewrites ``front.jsonl`` with ``error_*_mm`` and plots ``front.png``."""
    from simulate.solvers.reference import solve_equilibrium

    rows = [json.loads(line) for line in (out_dir / "front.jsonl").read_text().splitlines() if line.strip()]
    scene = tshirt_on_body(resolution)
    model, _ = build(scene, 1, "cpu", material_uv)
    saved = dict(np.load(out_dir / "positions.npz"))
    start_row = min(rows, key=lambda r: (r["solver"] != "vbd", r["tolerance"], -r["substeps"] * r["iterations"]))
    start = saved[start_row["setting"]]
    t0 = time.perf_counter()
    ref, info = solve_equilibrium(model, 0, start, body_vertices=scene[3], body_faces=scene[4],
                                  contact_thickness=CONTACT_THICKNESS)
    summary = {k: v for k, v in dataclasses.asdict(info).items() if k != "residual_history"}
    print(json.dumps({"reference": summary, "start": start_row["setting"], "seconds": round(time.perf_counter() - t0, 1)}))
    np.savez(out_dir / "reference.npz", positions=ref)
    for r in rows:
        q = saved[r["setting"]]
        d = 1e3 * np.linalg.norm(q - ref, axis=1)
        r["error_mean_mm"], r["error_max_mm"] = float(d.mean()), float(d.max())
        print(json.dumps(r))
    (out_dir / "front.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for solver, marker in (("xpbd", "s"), ("vbd", "o")):
        sel = [r for r in rows if r["solver"] == solver]
        ax.scatter([r["wall_s"] for r in sel], [r["error_mean_mm"] for r in sel], marker=marker, label=solver)
        for r in sel:
            ax.annotate(r["setting"].split("_", 1)[1], (r["wall_s"], r["error_mean_mm"]), fontsize=6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"wall time to rest, {rows[0]['worlds']} worlds [s]")
    ax.set_ylabel("mean vertex error vs converged reference [mm]")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out_dir / "front.png", dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0" if wp.get_cuda_device_count() else "cpu")
    parser.add_argument("--worlds", type=int, default=256)
    parser.add_argument("--resolution", type=int, default=7700)
    parser.add_argument("--max-frames", type=int, default=300)
    parser.add_argument("--settings", nargs="*", default=None,
                        help="subset as solver:substeps:iterations:tolerance (default: the built-in list)")
    parser.add_argument("--no-material-uv", dest="material_uv", action="store_false",
                        help="grain from the builder's fallback axis instead of the template's UV panels")
    parser.add_argument("--out-dir", default=None, help="folder for front.jsonl and world 0's final positions")
    parser.add_argument("--reference", default=None, metavar="OUT_DIR",
                        help="add errors against the converged reference to OUT_DIR/front.jsonl (CPU)")
    args = parser.parse_args()
    if args.reference:
        add_reference(Path(args.reference), args.resolution, args.material_uv)
        return
    settings = SETTINGS
    if args.settings:
        settings = [(s.split(":")[0], int(s.split(":")[1]), int(s.split(":")[2]), float(s.split(":")[3]))
                    for s in args.settings]
    scene = tshirt_on_body(args.resolution)
    built = build(scene, args.worlds, args.device, args.material_uv)
    for solver, substeps, iterations, tolerance in settings:
        row = run_setting(scene, built, args, solver, substeps, iterations, tolerance)
        print(json.dumps(row), flush=True)
        if args.out_dir:
            with open(Path(args.out_dir) / "front.jsonl", "a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
