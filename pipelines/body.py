"""``drape body``: pose and shape a body model and write it as OBJ/PLY (+ PNG preview)."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pipelines.errors import UsageError, check_output_file, check_torch_device


def _floats(text: str, field: str, count: int | None = None) -> np.ndarray:
    """Numbers separated by commas or spaces; ``count`` of them when given. Raises naming ``field``."""
    try:
        values = np.array([float(x) for x in text.replace(",", " ").split()], dtype=np.float32)
    except ValueError:
        raise UsageError(f"{field} must be numbers separated by commas or spaces (got {text!r})") from None
    if not np.isfinite(values).all():
        raise UsageError(f"{field} must be finite numbers (got {text!r})")
    if count is not None and values.size != count:
        raise UsageError(f"{field} must have {count} numbers (got {values.size}: {text!r})")
    return values


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "body", help="pose and shape a body, write OBJ/PLY and a PNG preview",
        description="Poses and shapes a body model (anny by default) and writes the mesh. "
        "Shape values follow the backend's shape_names (anny: gender age muscle weight height proportions, each 0..1). "
        "Joint rotations are axis-angle [rad] in the body frame (y up, facing +z, left +x).",
    )
    p.add_argument("--backend", default="anny", choices=["anny", "smpl"], help="body model backend (default: anny)")
    p.add_argument("--model-path", default=None, help="SMPL/SMPL-H/SMPL-X model file (.npz/.pkl) for --backend smpl")
    p.add_argument("--shape", default=None, help="shape values, e.g. '0.5,0.5,0.5,0.5,0.9,0.5' (default: neutral)")
    p.add_argument("--set", dest="shape_set", action="append", default=[], metavar="NAME=VALUE",
                   help="set one shape parameter by name, e.g. --set height=0.9 (repeatable)")
    p.add_argument("--pose", default=None, help="60 numbers: axis-angle of the 20 posable joints (default: canonical pose)")
    p.add_argument("--joint", action="append", default=[], metavar="NAME=RX,RY,RZ",
                   help="rotate one joint, e.g. --joint left_shoulder=0,0,1.2 (repeatable)")
    p.add_argument("--out", default="body.obj", help="output mesh (.obj or .ply)")
    p.add_argument("--preview", default=None, help="also write a PNG preview here")
    p.add_argument("--device", default="cpu", help="torch device for the body model (cpu, cuda:0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import trimesh

    from simulate.body import POSE_JOINTS, load_body_model

    out = check_output_file(args.out, "--out", suffixes=(".obj", ".ply"))
    if args.preview:
        check_output_file(args.preview, "--preview", suffixes=(".png",))
    check_torch_device(args.device)
    if args.backend == "smpl" and not args.model_path:
        raise UsageError("--backend smpl needs --model-path (an SMPL/SMPL-H/SMPL-X .npz or .pkl file)")
    if args.model_path and not Path(args.model_path).is_file():
        raise UsageError(f"--model-path {args.model_path!r} does not exist")
    t0 = time.perf_counter()
    body = load_body_model(args.backend, path=args.model_path, device=args.device)
    load_s = time.perf_counter() - t0
    names = list(body.shape_names)
    shape = body.shape_default.copy() if args.shape is None else _floats(args.shape, "--shape", len(names))
    for item in args.shape_set:
        name, sep, value = item.partition("=")
        if not sep:
            raise UsageError(f"--set {item!r} must be NAME=VALUE, e.g. height=0.9 (names: {', '.join(names)})")
        if name not in names:
            from pipelines.spec import nearest_name

            raise UsageError(f"--set {item!r}: unknown shape parameter {name!r}{nearest_name(name, names)}; "
                             f"expected one of {', '.join(names)}")
        shape[names.index(name)] = _floats(value, f"--set {name}", 1)[0]
    lo, hi = body.shape_ranges[:, 0], body.shape_ranges[:, 1]
    if ((shape < lo) | (shape > hi)).any():
        bad = int(np.nonzero((shape < lo) | (shape > hi))[0][0])
        raise UsageError(f"shape parameter {names[bad]}={shape[bad]:g} is outside its range [{lo[bad]:g}, {hi[bad]:g}]")
    pose = body.canonical_pose.copy() if args.pose is None else _floats(args.pose, "--pose", len(POSE_JOINTS) * 3)
    if args.joint:
        pose = pose.reshape(len(POSE_JOINTS), 3)
        for item in args.joint:
            name, sep, value = item.partition("=")
            if not sep:
                raise UsageError(f"--joint {item!r} must be NAME=RX,RY,RZ, e.g. left_shoulder=0,0,1.2")
            if name not in POSE_JOINTS:
                from pipelines.spec import nearest_name

                raise UsageError(f"--joint {item!r}: unknown joint name {name!r}{nearest_name(name, POSE_JOINTS)}; "
                                 f"expected one of {', '.join(POSE_JOINTS)}")
            pose[POSE_JOINTS.index(name)] = _floats(value, f"--joint {name}", 3)
        pose = pose.reshape(-1)
    t1 = time.perf_counter()
    posed = body.pose(shape, pose)
    pose_s = time.perf_counter() - t1
    trimesh.Trimesh(posed.vertices[0], body.faces, process=False).export(out)
    summary = {"backend": body.name, "vertices": body.vertex_count, "faces": int(len(body.faces)), "joints": body.joint_count,
               "shape": dict(zip(body.shape_names, map(float, shape))), "load_s": round(load_s, 3),
               "pose_s": round(pose_s, 4), "height_m": float(np.ptp(posed.vertices[0][:, 1])), "out": str(out)}
    if args.preview:
        from simulate.viz import MeshLayer, render_png

        render_png(args.preview, [MeshLayer(posed.vertices[0], body.faces)], titles=[f"{body.name} body"])
        summary["preview"] = args.preview
    print(json.dumps(summary, indent=2))
    return 0
