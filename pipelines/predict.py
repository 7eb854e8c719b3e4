"""``drape predict RUN --pose ... --shape ... --style ... --out mesh.obj``: one garment
from a trained model, posed on its body (or unposed with ``--unposed``).

A collision-aware run with the recurrent regressor (trained on a motion dataset) also takes a
motion: ``--pose`` a .npy of shape (F, 60), frames at the training data's fps. The sequence runs
through in order (the regressor's state carried from frame to frame) and frame k is written to
``<out stem>_<k:04d><suffix>``."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pipelines.errors import UsageError, check_output_file, check_torch_device, one_line


def _vector(text: str | None, size: int, field: str, default: np.ndarray,
            ranges: np.ndarray | None = None, names: list[str] | None = None) -> np.ndarray:
    """Numbers from a comma list or a .npy file: ``size`` finite values, each within ``ranges``
    (rows [lo, hi]) when given; raises naming the option ``--field``."""
    if text is None:
        return np.asarray(default, np.float32)
    path = Path(text)
    if path.suffix == ".npy":
        if not path.is_file():
            raise UsageError(f"--{field} {text!r}: no such .npy file")
        try:
            v = np.load(path, allow_pickle=False).astype(np.float32).reshape(-1)
        except (OSError, ValueError) as exc:
            raise UsageError(f"--{field} {text!r} is not a readable .npy array of numbers ({exc})") from None
    else:
        try:
            v = np.array([float(x) for x in text.replace(",", " ").split()], np.float32)
        except ValueError:
            raise UsageError(f"--{field} must be numbers separated by commas (or a .npy file), got {text!r}") from None
    if v.size != size:
        raise UsageError(f"--{field} must have {size} values, got {v.size}")
    if not np.isfinite(v).all():
        raise UsageError(f"--{field} must be finite numbers (got {text!r})")
    if ranges is not None:
        bad = np.nonzero((v < ranges[:, 0]) | (v > ranges[:, 1]))[0]
        if len(bad):
            i = int(bad[0])
            name = names[i] if names else f"value {i}"
            raise UsageError(f"--{field}: {name}={v[i]:g} is outside its range [{ranges[i, 0]:g}, {ranges[i, 1]:g}]")
    return v


def _pose_frames(text: str | None, size: int, default: np.ndarray) -> np.ndarray:
    """Poses (F, size): a .npy of shape (F, size) with F > 1 (a motion), else one pose (:func:`_vector`)."""
    if text is not None and Path(text).suffix == ".npy" and Path(text).is_file():
        try:
            v = np.load(text, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise UsageError(f"--pose {text!r} is not a readable .npy array of numbers ({exc})") from None
        if v.ndim == 2 and v.shape[0] > 1 and v.shape[1] == size:
            if not np.isfinite(v).all():
                raise UsageError(f"--pose must be finite numbers (got non-finite values in {text!r})")
            return v.astype(np.float32)
    return _vector(text, size, "pose", default)[None]


def run(args: argparse.Namespace) -> int:
    import trimesh

    from learn.common.skinning import garment_posing_functions
    from learn.registry import LEARNERS, get_learner
    from learn.tailornet.evaluate import PosingContext, predict_vertices
    from simulate.body import load_body_model

    entry = get_learner(args.learner)
    if entry.data != "dataset":
        drapers = ", ".join(name for name, e in LEARNERS.items() if e.data == "dataset")
        raise UsageError(f"--learner {args.learner} is trained on a {entry.data.replace('_', ' ')} and predicts no drape; "
                         f"expected one of {drapers} (draw {args.learner} garments with drape sample RUN)")
    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise UsageError(f"RUN {str(run_dir)!r} is not a directory (a run directory from drape train)")
    out = check_output_file(args.out, "--out", suffixes=(".obj", ".ply"))
    check_torch_device(args.device)
    file = run_dir / entry.model_file
    if not file.is_file():
        raise FileNotFoundError(f"no {args.learner} model in {run_dir} (expected {file.name}; run drape train first)")
    if not (run_dir / "template.npz").is_file():
        raise FileNotFoundError(f"{run_dir} has no template.npz (written by drape train)")
    try:
        with np.load(run_dir / "template.npz", allow_pickle=False) as z:
            template = {k: z[k] for k in z.files}
        info = json.loads((run_dir / "run.json").read_text()) if (run_dir / "run.json").is_file() else {}
    except (OSError, ValueError, EOFError) as exc:
        raise UsageError(f"RUN {str(run_dir)!r}: template.npz or run.json is unreadable ({one_line(str(exc))}); "
                         f"rerun drape train") from None
    body_spec = info.get("body", {"backend": "anny", "path": None})
    body = load_body_model(body_spec.get("backend", "anny"), path=body_spec.get("path"))
    # the body's inputs are checked before the model is loaded
    pose = _pose_frames(args.pose, body.pose_size, body.canonical_pose)  # (F, P)
    shape = _vector(args.shape, body.shape_size, "shape", body.shape_default, ranges=body.shape_ranges,
                    names=list(body.shape_names))
    try:
        model = entry.load(file, device=args.device)
    except Exception as exc:  # torch.load raises pickle, runtime and zip errors on a damaged file
        from learn.tailornet.train import DatasetMismatchError

        if isinstance(exc, DatasetMismatchError):
            raise
        raise UsageError(f"{str(file)!r} is not a readable {args.learner} checkpoint ({type(exc).__name__}: "
                         f"{one_line(str(exc))[:200]}); rerun drape train") from None
    if pose.shape[0] > 1 and not getattr(model, "recurrent", False):
        raise UsageError(f"--pose {args.pose!r} holds {pose.shape[0]} frames; a pose sequence needs a collision_aware "
                         f"run with the recurrent regressor (trained on a motion dataset), give one pose of "
                         f"{body.pose_size} values")
    cfg = getattr(model, "config", {}) or {}
    style_size = int(cfg.get("low_frequency", cfg).get("style_components", 0))
    style = _vector(args.style, style_size, "style", np.zeros(style_size)) if args.style is not None else None
    if style is None:
        raise ValueError(f"--style is required: {style_size} style values (the dataset's style vector)")
    posing = None if args.unposed else PosingContext(
        *garment_posing_functions(body, template["body_vertex_index"], template["skinning_weights"],
                                  rest_vertices=template["rest_vertices"]), body.faces, template["faces"])
    frames = pose.shape[0]
    vertices = predict_vertices(model, pose, np.tile(shape, (frames, 1)), np.tile(style, (frames, 1)), posing=posing,
                                postprocess=args.postprocess, device=args.device)  # (F, V, 3), one sequence
    outs = [out] if frames == 1 else [out.with_name(f"{out.stem}_{k:04d}{out.suffix}") for k in range(frames)]
    for k, path in enumerate(outs):
        trimesh.Trimesh(vertices[k], template["faces"], process=False).export(path)
        if args.with_body and not args.unposed:
            posed = body.pose(shape, pose[k])
            trimesh.Trimesh(posed.vertices[0], body.faces, process=False).export(
                path.with_name(path.stem + "_body" + path.suffix))
    print(json.dumps({"out": str(out) if frames == 1 else [str(p) for p in outs], "vertices": int(vertices.shape[1]),
                      "learner": args.learner, "posed": not args.unposed}))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("predict", help="predict one garment with a trained model and write OBJ/PLY",
                       description=__doc__)
    p.add_argument("run", help="run directory from drape train")
    p.add_argument("--pose", default=None, help="60 axis-angle values or a .npy (default: canonical pose); for a "
                                               "recurrent collision_aware run also a .npy motion (F, 60)")
    p.add_argument("--shape", default=None, help="body shape values (default: neutral)")
    p.add_argument("--style", required=True, help="style vector (as stored in the dataset's shards)")
    p.add_argument("--learner", default="tailornet", help="a learner of learn/registry.py trained into RUN (tailornet, "
                                                          "baseline, uvimage, uvimage_pca, collision_aware or collision-aware)")
    p.add_argument("--out", required=True, help="output mesh (.obj or .ply)")
    p.add_argument("--unposed", action="store_true", help="write the unposed displacement garment instead")
    p.add_argument("--postprocess", action="store_true", help="push vertices inside the body out (Laplacian-preserving)")
    p.add_argument("--with-body", action="store_true", help="also write the posed body next to the garment")
    p.add_argument("--device", default="cpu")
    p.set_defaults(func=run)
