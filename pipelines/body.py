"""``drape body``: pose and shape a body model and write it as OBJ/PLY (+ PNG preview)."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def _floats(text: str, field: str) -> np.ndarray:
    try:
        return np.array([float(x) for x in text.replace(",", " ").split()], dtype=np.float32)
    except ValueError as exc:
        raise ValueError(f"--{field} must be numbers separated by commas or spaces, got {text!r}") from exc


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

    t0 = time.perf_counter()
    body = load_body_model(args.backend, path=args.model_path, device=args.device)
    load_s = time.perf_counter() - t0
    shape = body.shape_default.copy() if args.shape is None else _floats(args.shape, "shape")
    for item in args.shape_set:
        name, _, value = item.partition("=")
        if name not in body.shape_names:
            raise ValueError(f"--set {item!r}: unknown shape parameter {name!r}; expected one of {', '.join(body.shape_names)}")
        shape[body.shape_names.index(name)] = float(value)
    lo, hi = body.shape_ranges[:, 0], body.shape_ranges[:, 1]
    if shape.shape == lo.shape and ((shape < lo) | (shape > hi)).any():
        bad = int(np.nonzero((shape < lo) | (shape > hi))[0][0])
        raise ValueError(f"shape parameter {body.shape_names[bad]}={shape[bad]:g} is outside its range [{lo[bad]:g}, {hi[bad]:g}]")
    pose = body.canonical_pose.copy() if args.pose is None else _floats(args.pose, "pose")
    if args.joint:
        pose = pose.reshape(len(POSE_JOINTS), 3)
        for item in args.joint:
            name, _, value = item.partition("=")
            body.pose_from_dict({name: [0, 0, 0]})  # raises on an unknown joint name
            pose[POSE_JOINTS.index(name)] = _floats(value, "joint")
        pose = pose.reshape(-1)
    t1 = time.perf_counter()
    posed = body.pose(shape, pose)
    pose_s = time.perf_counter() - t1
    out = Path(args.out)
    if out.suffix.lower() not in (".obj", ".ply"):
        raise ValueError(f"--out must end in .obj or .ply, got {out.name!r}")
    out.parent.mkdir(parents=True, exist_ok=True)
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
