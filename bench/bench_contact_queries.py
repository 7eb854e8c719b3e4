"""Contact queries at dataset scale: BVH build options against the cost of one detection pass.

Builds the dataset's t-shirt (``--resolution`` vertices) on the default body in ``--worlds``
worlds (as ``bench_sim_throughput.py --scene tshirt``), then for each BVH option (constructor x
leaf size) rebuilds the self-contact cloth mesh and the body mesh and times, per launch, a refit
and a detection pass (self-contact: nearest other-layer triangle per particle, AABB query; body:
nearest body point per particle). The candidates each option finds are compared with the first
option's (a different BVH must not change the nearest triangle). One JSON line per option.

    python bench/bench_contact_queries.py --device cuda:0 --worlds 240 --resolution 7700
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp


def _time(fn, repeats: int, device) -> float:
    """Mean wall time of ``fn`` [ms] over ``repeats`` calls after one warm-up call."""
    fn()
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    wp.synchronize_device(device)
    return 1e3 * (time.perf_counter() - t0) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0" if wp.get_cuda_device_count() else "cpu")
    parser.add_argument("--worlds", type=int, default=240)
    parser.add_argument("--resolution", type=int, default=7700)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--options", nargs="+", default=["default:4", "lbvh:1", "lbvh:2", "sah:1", "sah:4", "median:1"],
                        help="constructor:leaf_size pairs ('default' = Warp's choice for the device)")
    parser.add_argument("--out", default=None, help="also append JSON lines to this file")
    args = parser.parse_args()

    from bench_sim_throughput import tshirt_scene

    from simulate.cloth import Features
    from simulate.scenes import batched_drape
    from simulate.contact.self_contact import SelfContact
    from simulate.solvers import make_solver

    scene = tshirt_scene(args.resolution, args.device)
    model, collider = batched_drape(scene, args.worlds, args.device, features=Features(self_contact=True))
    solver = make_solver("xpbd", model, body_contact=True)
    control = model.control()
    control.collider = collider
    x = model.state().particle_q
    sc = SelfContact(model)
    body_points = collider.mesh.points
    device = str(wp.get_device(args.device))
    out = open(args.out, "a") if args.out else None
    reference = None
    for option in args.options:
        name, leaf = option.split(":")
        kwargs = {"bvh_leaf_size": int(leaf)}
        if name != "default":
            kwargs["bvh_constructor"] = name
        t0 = time.perf_counter()
        sc.mesh = wp.Mesh(points=sc.points, indices=wp.array(model.tri_indices_np.reshape(-1), dtype=wp.int32,
                                                              device=model.device), **kwargs)
        collider.mesh = wp.Mesh(points=body_points, indices=collider.mesh_indices, **kwargs)
        build_s = time.perf_counter() - t0
        record = {"bench": "contact_queries", "device": device, "worlds": args.worlds,
                  "vertices_per_world": model.particle_count // args.worlds, "constructor": name, "leaf_size": int(leaf),
                  "build_s": round(build_s, 3),
                  "self_refit_ms": round(_time(sc.mesh.refit, args.repeats, model.device), 3),
                  "self_detect_ms": round(_time(lambda: sc.detect(x, control.world_active), args.repeats, model.device), 3),
                  "body_refit_ms": round(_time(collider.mesh.refit, args.repeats, model.device), 3),
                  "body_detect_ms": round(_time(lambda: solver.detect_contacts(x, control), args.repeats, model.device), 3)}
        found = (sc.candidate.numpy().copy(), solver.contact_active.numpy().copy(), solver.contact_offset.numpy().copy())
        if reference is None:
            reference = found
        record["self_candidates"] = int((found[0] >= 0).sum())
        record["self_candidates_differing"] = int((found[0] != reference[0]).sum())
        record["body_contacts"] = int(found[1].sum())
        record["body_contacts_differing"] = int(((found[1] != reference[1])
                                                  | (np.abs(found[2] - reference[2]) > 1e-6)).sum())
        line = json.dumps(record)
        print(line, flush=True)
        if out is not None:
            out.write(line + "\n")
            out.flush()
    if out is not None:
        out.close()


if __name__ == "__main__":
    main()
