"""Quasi-static cloth throughput as the number of batched worlds grows (1 -> 512).

Each world is the benchmark drape (a resolution^2-vertex square cloth falling onto the default
body in a non-trivial pose; capsule stand-in without simulate.body), the cloth shifted by a
seeded random offset per world.  For every world count: build, warm up (compile + CUDA graph
capture), then time --frames frames with convergence switched off (raw throughput), and with
--relax also time a full relaxation with the stopping rule (amortized cost of a converged drape).
One JSON line per world count.

    python bench/bench_sim_throughput.py --device cuda:0 --worlds 1 4 16 64 256 512 --resolution 100
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import warp as wp

BENCH_SETTINGS = dict(damping=5.0, explosion_stretch=3.0, patience=5, outlier_fraction=0.0, limit_cycle_window=0,
                      frame_dt=1.0 / 60.0)
"""The settings this benchmark's figures in docs/benchmarks.md are measured at (light damping, a
3x stretch limit, the fastest particle decides convergence, frames of 1/60 s)."""


def tshirt_scene(resolution: int, device: str) -> dict:
    """The dataset's t-shirt (``resolution`` vertices) on the default body in the canonical pose, as a
    :func:`simulate.scenes.shawl_scene`-style dict (cloth at its rest geometry on the body)."""
    from simulate.reports.scenes import build_scene

    sc = build_scene("tshirt", body="anny", resolution=resolution, device=device)
    body, _ = sc.body_vertices(sc.neutral_shape[None], sc.canonical_pose[None])
    return {"cloth_vertices": sc.rest_vertices, "cloth_faces": sc.faces, "cloth_uv": sc.material_uv,
            "body_vertices": body[0], "body_faces": sc.body_faces, "body_kind": "anny"}


def kernel_profile(sim, frames: int) -> dict:
    """GPU time per frame by kernel name over ``frames`` eager frames (Warp's CUDA activity timing).

    Returns ``gpu_ms_per_frame`` (sum of kernel times), ``launches_per_frame``,
    ``eager_wall_ms_per_frame`` and ``kernels``: [{name, ms_per_frame, launches_per_frame, share}],
    most expensive first.  The gap between the graph's wall time and the kernel sum is launch
    and dependency overhead.
    """
    sim.step_frame()  # warm: kernels compiled, buffers touched
    wp.synchronize_device(sim.model.device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_KERNEL_BUILTIN)
    t0 = time.perf_counter()
    for _ in range(frames):
        sim.step_frame()
    wp.synchronize_device(sim.model.device)
    wall = time.perf_counter() - t0
    results = wp.timing_end()
    totals: dict[str, list[float]] = {}
    for r in results:
        name = str(r.name).split(" ")[-1]
        entry = totals.setdefault(name, [0.0, 0])
        entry[0] += float(r.elapsed)
        entry[1] += 1
    gpu = sum(v[0] for v in totals.values())
    kernels = [{"name": k, "ms_per_frame": round(v[0] / frames, 4), "launches_per_frame": round(v[1] / frames, 1),
                "share": round(v[0] / max(gpu, 1e-12), 4)} for k, v in sorted(totals.items(), key=lambda kv: -kv[1][0])]
    return {"frames": frames, "gpu_ms_per_frame": round(gpu / frames, 4),
            "launches_per_frame": round(sum(v[1] for v in totals.values()) / frames, 1),
            "eager_wall_ms_per_frame": round(1e3 * wall / frames, 4), "kernels": kernels}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0" if wp.get_cuda_device_count() else "cpu")
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 4, 16, 64, 256, 512])
    parser.add_argument("--scene", default="shawl", choices=["shawl", "cape", "tshirt"],
                        help="tshirt: the dataset garment on the default body in the canonical pose, --resolution "
                             "vertices (e.g. 7700 as in tailornet-tshirt.yaml): the pipeline's stepping cost alone")
    parser.add_argument("--resolution", type=int, default=100,
                        help="shawl: vertices per side (100 -> 10k); cape: along its length (135 -> 10k)")
    parser.add_argument("--body", default="default", choices=["default", "capsule"])
    parser.add_argument("--solver", default="xpbd", choices=["xpbd", "vbd", "mass_spring"])
    parser.add_argument("--mode", default="gauss_seidel", choices=["gauss_seidel", "jacobi"])
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--gs-sweep", default="world_blocks", choices=["world_blocks", "colour_launches"],
                        help="XPBD Gauss-Seidel launches: a block per world, or a launch per colour")
    parser.add_argument("--gs-block-dim", type=int, default=256, help="threads per world block (world_blocks)")
    parser.add_argument("--vbd-block-dim", type=int, default=None,
                        help="VBD: threads per world block (SolverVBD's block_dim; default its own)")
    parser.add_argument("--vbd-shared", default="auto", choices=["auto", "on", "off"],
                        help="VBD: each world's positions in a shared-memory tile (SolverVBD's shared)")
    parser.add_argument("--bending-mode", default=None, choices=["gauss_seidel", "jacobi"],
                        help="XPBD bending sweep (default: same as --mode)")
    parser.add_argument("--self-contact", action="store_true", help="cloth self-contact on (Features.self_contact)")
    parser.add_argument("--self-contact-detect-every", type=int, default=1,
                        help="search cloth-cloth pairs every N substeps (SimSettings.self_contact_detect_every)")
    parser.add_argument("--self-contact-search-every", type=int, default=1,
                        help="VBD self-contact: BVH searches on every N-th self-contact substep, the pair lists "
                             "refreshed in between (SimSettings.self_contact_search_every)")
    parser.add_argument("--self-contact-skin", type=float, default=0.0,
                        help="VBD self-contact: extra list distance of the searches [m] (SimSettings.self_contact_skin)")
    parser.add_argument("--ball-bounds", action="store_true",
                        help="VBD self-contact: ball displacement bounds instead of the directional ones "
                             "(SimSettings.self_contact_directional_bounds=False)")
    parser.add_argument("--contact-detect-every", type=int, default=1,
                        help="query the body every N substeps (SimSettings.body_contact_detect_every)")
    parser.add_argument("--frames", type=int, default=20, help="timed frames for raw throughput")
    parser.add_argument("--relax", action="store_true", help="also time relaxation to rest")
    parser.add_argument("--tolerance", type=float, default=0.01)
    parser.add_argument("--max-frames", type=int, default=600)
    parser.add_argument("--profile", action="store_true",
                        help="CUDA only: also run --profile-frames frames without graph capture under Warp's kernel "
                             "timing and print one sim_profile line per world count (GPU ms per frame by kernel)")
    parser.add_argument("--profile-frames", type=int, default=3)
    parser.add_argument("--garments", type=int, default=0,
                        help="K > 0: K garments of distinct rest shapes over the worlds (a dataset batch has 40 styles); "
                             "0: every world the same")
    parser.add_argument("--no-share-element-data", action="store_true",
                        help="each world's tiled sweep reads its own copy of the element data even where worlds "
                             "repeat a garment (the A/B of SolverXPBD's share_element_data)")
    parser.add_argument("--out", default=None, help="also append JSON lines to this file")
    args = parser.parse_args()

    from simulate.cloth import Features
    from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus
    from simulate.scenes import batched_drape, cape_scene, shawl_scene

    out = open(args.out, "a") if args.out else None
    if args.scene == "tshirt":
        scene = tshirt_scene(args.resolution, args.device)
    else:
        scene = (cape_scene if args.scene == "cape" else shawl_scene)(args.resolution, body=args.body)
    vertices = len(scene["cloth_vertices"])
    device = str(wp.get_device(args.device))
    for worlds in args.worlds:
        t_build = time.perf_counter()
        # the t-shirt is fitted to the body: a sideways shift would push it into the torso (worlds
        # then explode and freeze, and the bench times fewer live worlds than it reports)
        jitter = 0.0 if args.scene == "tshirt" else 0.02
        model, collider = batched_drape(scene, worlds, args.device, jitter=jitter, seed=worlds,
                                        features=Features(self_contact=args.self_contact), garments=args.garments)
        build_s = time.perf_counter() - t_build
        solver_options = {"share_element_data": False} if args.no_share_element_data and args.solver == "xpbd" else None
        if args.solver == "vbd":
            solver_options = {"shared": {"auto": None, "on": True, "off": False}[args.vbd_shared]}
            if args.vbd_block_dim is not None:
                solver_options["block_dim"] = args.vbd_block_dim
        substeps = None if args.solver == "mass_spring" else args.substeps
        # Raw throughput: a tolerance no world reaches, so every world is stepped every frame.
        raw = SimSettings(substeps=substeps, iterations=args.iterations, xpbd_mode=args.mode, tolerance=1e-12,
                          xpbd_bending_mode=args.bending_mode,
                          gs_sweep=args.gs_sweep, gs_block_dim=args.gs_block_dim,
                          body_contact_detect_every=args.contact_detect_every,
                          self_contact_directional_bounds=not args.ball_bounds,
                          self_contact_detect_every=args.self_contact_detect_every,
                          self_contact_search_every=args.self_contact_search_every,
                          self_contact_skin=args.self_contact_skin,
                          max_frames=10 ** 9, **BENCH_SETTINGS)
        sim = QuasiStaticSimulator(model, collider, solver=args.solver, settings=raw,
                                   solver_options=solver_options)
        sim.step_frame()  # compile + first frame
        sim.step_frame()  # graph capture (CUDA) or second eager frame
        wp.synchronize_device(model.device)
        t0 = time.perf_counter()
        for _ in range(args.frames):
            sim.step_frame()
        wp.synchronize_device(model.device)
        wall = time.perf_counter() - t0
        iters = sim.substeps * (args.iterations if args.solver in ("xpbd", "vbd") else 1)
        record = {
            "bench": "sim_throughput", "device": device, "solver": args.solver,
            "mode": args.mode if args.solver == "xpbd" else None, "worlds": worlds, "vertices_per_world": vertices,
            "body": scene["body_kind"], "scene": args.scene, "substeps": sim.substeps, "iterations": args.iterations,
            "bending_mode": args.bending_mode or args.mode,
            "gs_sweep": args.gs_sweep, "gs_block_dim": args.gs_block_dim,
            "contact_detect_every": args.contact_detect_every,
            "self_contact": args.self_contact, "ball_bounds": args.ball_bounds,
            "self_contact_detect_every": args.self_contact_detect_every,
            "self_contact_search_every": args.self_contact_search_every, "self_contact_skin": args.self_contact_skin,
            "vbd_block_dim": getattr(sim.solver, "block_dim", None) if args.solver == "vbd" else None,
            "vbd_shared": getattr(sim.solver, "shared", None), "garments": args.garments,
            "element_data_copies": getattr(sim.solver, "element_data_copies", None),
            "build_s": round(build_s, 3), "frames": args.frames, "wall_s": round(wall, 4),
            "ms_per_frame": round(1e3 * wall / args.frames, 4),
            "world_frames_per_s": round(worlds * args.frames / wall, 2),
            "amortized_ms_per_world_frame": round(1e3 * wall / (args.frames * worlds), 4),
            "vertex_iterations_per_s": float(f"{worlds * vertices * iters * args.frames / wall:.4g}"),
            "exploded": int(np.sum(sim.status == WorldStatus.EXPLODED)),
        }
        if args.relax:
            collider.set_pose(scene["body_vertices"])
            settings = SimSettings(substeps=substeps, iterations=args.iterations, xpbd_mode=args.mode,
                                   xpbd_bending_mode=args.bending_mode,
                                   gs_sweep=args.gs_sweep, gs_block_dim=args.gs_block_dim,
                                   body_contact_detect_every=args.contact_detect_every, tolerance=args.tolerance,
                                   self_contact_directional_bounds=not args.ball_bounds,
                                   self_contact_detect_every=args.self_contact_detect_every,
                                   self_contact_search_every=args.self_contact_search_every,
                                   self_contact_skin=args.self_contact_skin,
                                   max_frames=args.max_frames, **BENCH_SETTINGS)
            sim = QuasiStaticSimulator(model, collider, solver=args.solver, settings=settings,
                                       solver_options=solver_options)
            wp.synchronize_device(model.device)
            t0 = time.perf_counter()
            status = sim.relax()
            wp.synchronize_device(model.device)
            relax_s = time.perf_counter() - t0
            record.update({
                "relax_s": round(relax_s, 4), "relax_frames": int(sim.frame_count),
                "world_frames_to_rest_median": int(np.median(sim.world_frames)),
                "converged": int(np.sum(status == WorldStatus.CONVERGED)),
                "max_steps": int(np.sum(status == WorldStatus.MAX_STEPS)),
                "exploded_relax": int(np.sum(status == WorldStatus.EXPLODED)),
                "amortized_s_per_converged_drape": round(relax_s / worlds, 5),
                "amortized_ms_per_frame_to_rest": round(1e3 * relax_s / max(1, int(np.sum(sim.world_frames))), 4),
            })
        records = [record]
        if args.profile and wp.get_device(args.device).is_cuda:
            eager = dataclasses.replace(raw, use_cuda_graph=False)
            sim = QuasiStaticSimulator(model, collider, solver=args.solver, settings=eager,
                                       solver_options=solver_options)
            records.append({"bench": "sim_profile", "device": device, "worlds": worlds, "scene": args.scene,
                            "vertices_per_world": vertices, "substeps": sim.substeps, "iterations": args.iterations,
                            "mode": args.mode, "self_contact": args.self_contact, "ball_bounds": args.ball_bounds,
                            "self_contact_search_every": args.self_contact_search_every,
                            "self_contact_skin": args.self_contact_skin,
                            "graph_ms_per_frame": record["ms_per_frame"],
                            **kernel_profile(sim, args.profile_frames)})
        for rec in records:
            line = json.dumps(rec)
            print(line, flush=True)
            if out is not None:
                out.write(line + "\n")
                out.flush()
        del sim, model, collider
    if out is not None:
        out.close()


if __name__ == "__main__":
    main()
