"""``drape garment`` (generate, drape and export one garment on its body, + PNG preview)
and ``drape style-space`` (TailorNet style PCA + prototypes in one command)."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from simulate.garment.style import GARMENT_TYPES


def _floats(text: str, field: str) -> np.ndarray:
    try:
        return np.array([float(x) for x in text.replace(",", " ").split()], dtype=np.float32)
    except ValueError as exc:
        raise ValueError(f"--{field} must be numbers separated by commas or spaces, got {text!r}") from exc


def _shape(body, text: str | None) -> np.ndarray:
    if text is None:
        return body.shape_default.copy()
    shape = _floats(text, "shape")
    if shape.shape != (body.shape_size,):
        raise ValueError(f"--shape must have {body.shape_size} values ({', '.join(body.shape_names)}), got {len(shape)}")
    lo, hi = body.shape_ranges[:, 0], body.shape_ranges[:, 1]
    if ((shape < lo) | (shape > hi)).any():
        i = int(np.nonzero((shape < lo) | (shape > hi))[0][0])
        raise ValueError(f"--shape {body.shape_names[i]}={shape[i]:g} is outside [{lo[i]:g}, {hi[i]:g}]")
    return shape


def _parser(sub: argparse._SubParsersAction, name: str, help_text: str, description: str) -> argparse.ArgumentParser:
    """The subparser ``name``: a placeholder already added (lazy CLI) is filled in, else a new one."""
    if name in sub.choices:
        parser = sub.choices[name]
        parser.description = description
        return parser
    return sub.add_parser(name, help=help_text, description=description)


def register(sub: argparse._SubParsersAction) -> None:
    """Adds ``garment`` and ``style-space`` (filling in placeholders of those names)."""
    p = _parser(sub, "garment", "generate a garment style, drape it on a body, write OBJ/PLY + PNG",
                "Generates a garment of a type and style on the canonical body of a shape, drapes "
                "it quasi-statically with the cloth simulator and writes garment and body meshes.")
    p.add_argument("--type", dest="garment_type", required=True, choices=GARMENT_TYPES)
    p.add_argument("--style", default=None, help="NAME=VALUE,... e.g. length=0.6,looseness=0.02 (default: type defaults)")
    p.add_argument("--shape", default=None, help="body shape values (anny: gender age muscle weight height proportions)")
    p.add_argument("--resolution", type=int, default=None, help="target vertex count (default per type)")
    p.add_argument("--out", default="garment.obj", help="garment mesh (.obj or .ply); the body goes to <stem>_body<ext>")
    p.add_argument("--preview", default=None, help="PNG preview of garment and body")
    p.add_argument("--no-drape", action="store_true", help="write the generated rest garment without simulating")
    p.add_argument("--fabric", default="cotton")
    p.add_argument("--max-frames", type=int, default=400)
    p.add_argument("--device", default="cpu", help="Warp device (cpu, cuda:0)")
    p.set_defaults(func=run_garment)

    s = _parser(sub, "style-space", "build a garment style PCA space and choose prototypes",
                "TailorNet Sec. 4.2/4.4: drape sampled styles, PCA, resample, PCA again; then drape "
                "style-shape pairs on the 9 training shapes and greedily choose prototypes.")
    s.add_argument("--type", dest="garment_type", required=True, choices=GARMENT_TYPES)
    s.add_argument("--samples", type=int, default=20)
    s.add_argument("--rounds", type=int, default=2)
    s.add_argument("--components", type=int, default=2)
    s.add_argument("--resolution", type=int, default=None)
    s.add_argument("--prototype-styles", type=int, default=3, help="styles (gamma samples) per training shape")
    s.add_argument("--prototypes", type=int, default=20, help="K prototypes (capped at the pair count)")
    s.add_argument("--max-frames", type=int, default=300)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--device", default="cpu")
    s.add_argument("--out", required=True, help="output directory")
    s.set_defaults(func=run_style_space)


#: Body faces closer than this to the garment, on its inner side, are hidden in previews [m].
PREVIEW_HIDE_DISTANCE_M = 0.015


def visible_body_faces(body_vertices: np.ndarray, body_faces: np.ndarray, garment_vertices: np.ndarray,
                       garment_faces: np.ndarray) -> np.ndarray:
    """Body faces (F', 3) not covered by the garment: the painter's-algorithm preview
    would otherwise show body triangles through cloth resting millimetres above them."""
    from scipy.spatial import cKDTree

    from simulate.body.mesh_utils import vertex_normals

    points = np.asarray(body_vertices)
    dist, nearest = cKDTree(garment_vertices).query(points)
    normals = vertex_normals(garment_vertices, garment_faces)
    inner = ((points - garment_vertices[nearest]) * normals[nearest]).sum(1) < 0
    covered = (dist < PREVIEW_HIDE_DISTANCE_M) & inner  # per body vertex
    return body_faces[~covered[body_faces].all(1)]


def _write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    import trimesh

    trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False).export(path)


def run_garment(args: argparse.Namespace) -> int:
    from simulate.body import load_body_model
    from simulate.garment.style import StyleParams
    from simulate.garment.templates import apply_style, make_template

    from pipelines.errors import check_output_file

    out = check_output_file(args.out, "--out", suffixes=(".obj", ".ply"))
    if args.preview:
        check_output_file(args.preview, "--preview", suffixes=(".png",))
    body = load_body_model("anny")
    shape = _shape(body, args.shape)
    style = StyleParams.parse(args.garment_type, args.style)
    t0 = time.perf_counter()
    kwargs = {} if args.resolution is None else {"resolution": args.resolution}
    template = make_template(args.garment_type, body, **kwargs)
    vertices = apply_style(template, style, body, shape=shape)
    summary = {"type": args.garment_type, "style": style.values, "shape": dict(zip(body.shape_names, map(float, shape))),
               "vertices": template.vertex_count, "faces": int(len(template.faces)),
               "template_sha256": template.content_hash(), "generate_s": round(time.perf_counter() - t0, 3)}
    if not args.no_drape:
        from simulate.garment.drape import drape_canonical

        result = drape_canonical([(template, vertices)], body, shape, fabric=args.fabric, device=args.device,
                                 max_frames=args.max_frames)
        vertices = result.vertices[0]
        summary.update({"status": result.status[0], "frames": int(result.frames[0]), "drape_s": round(result.seconds, 3),
                        "max_penetration_mm": round(1e3 * float(result.max_penetration_m[0]), 3),
                        "penetrating_fraction": float(result.penetrating_fraction[0])})
    body_v = body.pose(shape, body.canonical_pose).vertices[0]
    out.parent.mkdir(parents=True, exist_ok=True)
    _write_mesh(out, vertices, template.faces)
    body_path = out.with_name(f"{out.stem}_body{out.suffix}")
    _write_mesh(body_path, body_v, body.faces)
    summary.update({"out": str(out), "body_out": str(body_path)})
    if args.preview:
        from simulate.viz import MeshLayer, render_png

        render_png(args.preview, [MeshLayer(body_v, visible_body_faces(body_v, body.faces, vertices, template.faces)),
                                  MeshLayer(vertices, template.faces, color=(0.25, 0.45, 0.8))],
                   titles=[f"{args.garment_type} on {body.name}"])
        summary["preview"] = args.preview
    print(json.dumps(summary, indent=2))
    return 0


def run_style_space(args: argparse.Namespace) -> int:
    import sys

    from simulate.body import load_body_model
    from simulate.garment.drape import drape_canonical
    from simulate.garment.shapes import training_shapes
    from simulate.garment.style_space import build_style_space, outside_body, select_prototypes
    from simulate.garment.templates import apply_style, make_template

    from pipelines.errors import check_output_dir

    out = check_output_dir(args.out, "--out")
    body = load_body_model("anny")
    kwargs = {} if args.resolution is None else {"resolution": args.resolution}
    template = make_template(args.garment_type, body, **kwargs)
    template.save(out / "template.npz")
    opts = {"max_frames": args.max_frames}
    t0 = time.perf_counter()
    space, _ = build_style_space(template, body, samples=args.samples, rounds=args.rounds, components=args.components,
                                 seed=args.seed, device=args.device, drape_options=opts,
                                 progress=lambda h: print(json.dumps({"round": h}), file=sys.stderr))
    space.save(out / "style_space.npz")
    # Style-shape pairs: gamma samples on each of the 9 training shapes, draped there.
    shapes, shape_params = training_shapes(body)
    rng = np.random.default_rng(args.seed + 1)
    gammas = np.concatenate([np.zeros((1, space.size)),
                             rng.normal(size=(max(args.prototype_styles - 1, 0), space.size)) * np.sqrt(space.variances)])
    pairs, pair_shapes, pair_gamma = [], [], []
    for shape in shapes:
        shape_v = body.pose(shape, body.canonical_pose).vertices[0]
        for g in gammas:
            disp = space.gamma_to_garment(g)[0] - space.reference
            if template.follows_body_topology:
                garment = shape_v[template.body_vertex_index] + disp
            else:  # skirt: regenerate the default style on this shape, plus the style offset
                garment = apply_style(template, template_style(template), body, shape=shape) + (
                    disp - space.mean)
            pairs.append((template, outside_body(template, garment, body, shape=shape)))
            pair_shapes.append(shape)
            pair_gamma.append(g)
    result = drape_canonical(pairs, body, np.stack(pair_shapes), device=args.device, **opts)
    # Exploded drapes are not garments: they take no part in the prototype choice.
    kept = np.array([i for i, st in enumerate(result.status) if st != "EXPLODED"], dtype=np.int64)
    if len(kept) == 0:
        raise RuntimeError(f"every style-shape drape exploded (statuses {result.status})")
    disp = []
    for i in kept:
        tpl, v, shape = pairs[i][0], result.vertices[i], pair_shapes[i]
        ref = (body.pose(shape, body.canonical_pose).vertices[0][tpl.body_vertex_index]
               if tpl.follows_body_topology else np.zeros_like(v))
        disp.append(v - ref)
    disp = np.stack(disp)
    k = min(args.prototypes, len(disp))
    choice = select_prototypes(disp, k)
    np.savez_compressed(out / "prototypes.npz", indices=kept[choice.indices], mean_error_mm=choice.mean_error_mm,
                        max_error_mm=choice.max_error_mm, pair_index=kept, shapes=np.stack(pair_shapes)[kept],
                        gammas=np.stack(pair_gamma)[kept], displacements=disp.astype(np.float32))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=100)
    ks = np.arange(1, k + 1)
    ax.plot(ks, choice.mean_error_mm, "o-", label="mean over pairs")
    ax.plot(ks, choice.max_error_mm, "s--", label="worst pair")
    ax.set_xlabel("prototypes K")
    ax.set_ylabel("convex-fit error [mm per vertex]")
    ax.set_title(f"{args.garment_type}: prototype approximation error")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "prototype_error.png")
    plt.close(fig)
    _plot_components(out / "style_components.png", space, template, body)
    summary = {"type": args.garment_type, "vertices": template.vertex_count, "template_sha256": template.content_hash(),
               "style_space": str(out / "style_space.npz"), "variances_m2": [float(v) for v in space.variances],
               "rounds": space.history, "shape_parameters": shape_params, "pairs": len(disp),
               "pair_status": result.status, "pairs_kept": int(len(kept)),
               "prototype_indices": [int(i) for i in kept[choice.indices]],
               "mean_error_mm": [round(float(e), 3) for e in choice.mean_error_mm],
               "plot": str(out / "prototype_error.png"), "components_plot": str(out / "style_components.png"), "seconds": round(time.perf_counter() - t0, 2)}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


def _plot_components(path: Path, space, template, body) -> None:
    """TailorNet Fig. 3: each style component at -1.5, 0, +1.5 standard deviations."""
    from simulate.viz import MeshLayer, render_png

    body_v = body.pose(body.shape_default, body.canonical_pose).vertices[0]
    panels, titles = [], []
    for k in range(min(space.size, 2)):
        for z in (-1.5, 0.0, 1.5):
            gamma = np.zeros(space.size)
            gamma[k] = z * np.sqrt(space.variances[k])
            garment = space.gamma_to_garment(gamma)[0]
            panels.append([MeshLayer(body_v, visible_body_faces(body_v, body.faces, garment, template.faces)),
                           MeshLayer(garment, template.faces, color=(0.25, 0.45, 0.8))])
            titles.append(f"gamma{k + 1} {z:+.1f} sd")
    render_png(path, panels, views=(0.0,), titles=titles, size_px=500)


def template_style(template):
    from simulate.garment.style import StyleParams

    return StyleParams(template.garment_type, template.default_style)
