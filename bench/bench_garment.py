"""Garment layer timings: template build, style generation, UV rasterize/sample and
batched canonical draping (worlds x vertices); prints one JSON line per measurement.

    python bench/bench_garment.py [--types tshirt skirt] [--resolution N] [--worlds 1 4]
                                  [--device cpu] [--max-frames 300]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    from simulate.garment.style import GARMENT_TYPES

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--types", nargs="+", default=list(GARMENT_TYPES), choices=GARMENT_TYPES)
    parser.add_argument("--resolution", type=int, default=None, help="target vertex count (default per type)")
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--max-frames", type=int, default=300)
    parser.add_argument("--uv-size", type=int, default=256)
    parser.add_argument("--no-drape", action="store_true")
    args = parser.parse_args()

    from simulate.body import load_body_model
    from simulate.garment import uv
    from simulate.garment.drape import drape_canonical
    from simulate.garment.style import sample_styles
    from simulate.garment.templates import apply_style, make_template

    body = load_body_model("anny")
    for gt in args.types:
        kwargs = {} if args.resolution is None else {"resolution": args.resolution}
        t0 = time.perf_counter()
        tpl = make_template(gt, body, **kwargs)
        build_s = time.perf_counter() - t0
        styles = sample_styles(gt, max(args.worlds), seed=0)
        t0 = time.perf_counter()
        garments = [apply_style(tpl, s, body) for s in styles]
        style_s = (time.perf_counter() - t0) / len(styles)
        values = np.stack(garments)  # (N, V, 3)
        uv.rasterize(values[:1], tpl, size=args.uv_size)  # builds the cached pixel map
        t0 = time.perf_counter()
        images, _ = uv.rasterize(values, tpl, size=args.uv_size)
        raster_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        uv.sample(images, tpl)
        sample_s = time.perf_counter() - t0
        print(json.dumps({"bench": "garment_template", "type": gt, "vertices": tpl.vertex_count,
                          "faces": int(len(tpl.faces)), "build_s": round(build_s, 3), "style_s": round(style_s, 3),
                          "rasterize_s_per_item": round(raster_s / len(values), 5),
                          "sample_s_per_item": round(sample_s / len(values), 5), "uv_size": args.uv_size}), flush=True)
        if args.no_drape:
            continue
        for worlds in args.worlds:
            pairs = [(tpl, g) for g in garments[:worlds]]
            result = drape_canonical(pairs, body, body.shape_default, device=args.device, max_frames=args.max_frames)
            frames = int(result.frames.max())
            print(json.dumps({"bench": "garment_drape", "type": gt, "device": args.device, "worlds": worlds,
                              "vertices_per_world": tpl.vertex_count, "seconds": round(result.seconds, 3),
                              "frames": frames, "ms_per_frame": round(1e3 * result.seconds / max(frames, 1), 2),
                              "statuses": result.status,
                              "max_penetration_mm": round(1e3 * float(result.max_penetration_m.max()), 3)}),
                  flush=True)


if __name__ == "__main__":
    main()
