"""Report scenes and a batched driver: canonical drape -> pose path -> rest, one world per case.

A :class:`Scene` is one cloth (rest vertices, faces) on one body whose vertices come from
``(shape, pose)`` through :meth:`Scene.body_vertices`:

* ``body="anny"`` (default): the project's default body; the cloth is a garment from
  :mod:`simulate.garment` (``tshirt``, ``shirt``, ``pants``, ``shorts``, ``skirt``) or a
  ``shawl`` (a flat rectangle dropped over the shoulders, head included in the collider so it
  cannot fall through the neck opening).
* ``body="capsule"``: a horizontal capsule (a towel bar) with a small towel over it, for CI on
  CPU: the anny body costs about 0.1 s per frame on 2 CPU cores (14k-face BVH refit per
  substep), the capsule a few ms. Its ``pose`` is read as the pelvis axis-angle (the bar is
  rotated about its centre) and ``shape[0]`` in [0, 1] scales its radius by 0.8 ... 1.2.

:func:`run_worlds` simulates many cases at once as worlds of one
:class:`~simulate.quasi_static.QuasiStaticSimulator`: each world starts from its start
positions on the first body of its path, moves one frame per path entry (the body is
interpolated per substep inside the frame) and then relaxes on the last body until it converges,
hits the frame budget or explodes. Worlds can differ in fabric, path and path length; the solver
and time step are shared. :func:`frame_metrics` gives the per-world stretch and penetration.

Frame: metres, y up, facing +z, left +x.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import warp as wp

from simulate.cloth import ClothBuilder, Fabric, Features
from simulate.cloth.fabric import resolve_fabric
from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus
from simulate.contact import BodyCollider

__all__ = [
    "Scene", "SceneRun", "build_scene", "named_pose", "pose_path", "run_worlds", "edge_stretch", "frame_metrics",
    "ACCURACY_POSES", "EXTREME_POSES", "GARMENT_CONTACT_PARTS", "SCENE_GARMENTS", "round_float16",
]

#: Body parts each cloth can touch (the rest is culled from the collider). Garment types use the
#: garment layer's table (``simulate.garment.drape.COLLISION_PARTS``: tops keep the legs and head
#: so hems and necklines never meet an open cut of the torso mesh); the shawl keeps the head so it
#: cannot fall through the torso's open neck.
GARMENT_CONTACT_PARTS: dict[str, tuple[str, ...]] = {
    "tshirt": ("torso", "arms", "legs", "head"), "shirt": ("torso", "arms", "legs", "head"),
    "pants": ("torso", "legs", "feet"), "shorts": ("torso", "legs"), "skirt": ("torso", "legs"),
    "shawl": ("torso", "arms", "head"),
}
SCENE_GARMENTS: tuple[str, ...] = tuple(GARMENT_CONTACT_PARTS)

#: Poses of the accuracy report, {name: {joint: axis-angle [rad]}} (body frame: x left, y up,
#: z forward; raising the left arm sideways is +z at left_shoulder). "canonical" is the drape pose.
ACCURACY_POSES: dict[str, dict[str, tuple[float, float, float]]] = {
    "canonical": {},
    "arms-up": {"left_shoulder": (0.0, 0.0, 1.2), "right_shoulder": (0.0, 0.0, -1.2)},
    "arms-forward": {"left_shoulder": (0.0, -0.8, 0.5), "right_shoulder": (0.0, 0.8, -0.5),
                     "left_elbow": (0.0, -0.6, 0.0), "right_elbow": (0.0, 0.6, 0.0)},
    "twist": {"spine1": (0.0, 0.2, 0.0), "spine2": (0.0, 0.2, 0.0), "spine3": (0.0, 0.2, 0.0)},
    "lean": {"spine1": (0.3, 0.0, 0.1), "spine2": (0.25, 0.0, 0.1), "spine3": (0.15, 0.0, 0.05)},
    "tilt": {"pelvis": (0.0, 0.0, 0.2)},
}

#: Extreme poses of the stability report, at or near :data:`simulate.body.JOINT_LIMITS`.
EXTREME_POSES: dict[str, dict[str, tuple[float, float, float]]] = {
    "arms-overhead": {"left_shoulder": (0.0, 0.0, 1.9), "right_shoulder": (0.0, 0.0, -1.9),
                      "left_collar": (0.0, 0.0, 0.4), "right_collar": (0.0, 0.0, -0.4)},
    "deep-squat": {"left_hip": (-1.6, 0.0, 0.3), "right_hip": (-1.6, 0.0, -0.3), "left_knee": (2.3, 0.0, 0.0),
                   "right_knee": (2.3, 0.0, 0.0), "left_ankle": (-0.6, 0.0, 0.0), "right_ankle": (-0.6, 0.0, 0.0),
                   "spine1": (0.5, 0.0, 0.0), "spine2": (0.3, 0.0, 0.0)},
    "arms-crossed": {"left_shoulder": (0.0, -1.0, 0.6), "right_shoulder": (0.0, 1.0, -0.6),
                     "left_elbow": (0.0, -2.0, 0.0), "right_elbow": (0.0, 2.0, 0.0)},
    "twisted-spine": {"spine1": (0.0, 0.3, 0.0), "spine2": (0.0, 0.3, 0.0), "spine3": (0.0, 0.3, 0.0),
                      "neck": (0.0, 0.5, 0.0)},
}


def named_pose(name: str) -> np.ndarray:
    """The (60,) axis-angle pose [rad] of an accuracy or extreme pose name; ValueError if unknown."""
    from simulate.body import POSE_JOINTS

    table = {**ACCURACY_POSES, **EXTREME_POSES}
    if name not in table:
        raise ValueError(f"pose name must be one of {', '.join(table)} (got {name!r})")
    pose = np.zeros((len(POSE_JOINTS), 3), np.float32)
    for joint, value in table[name].items():
        pose[POSE_JOINTS.index(joint)] = value
    return pose.reshape(-1)


def pose_path(start: np.ndarray, end: np.ndarray, *, steps: int) -> np.ndarray:
    """``steps`` + 1 poses from ``start`` to ``end`` (per-joint slerp), shape (steps + 1, 60)."""
    from simulate.poses import slerp_poses

    if int(steps) != steps or steps < 0:
        raise ValueError(f"steps must be an integer >= 0 (got {steps!r})")
    return slerp_poses(start, end, np.arange(steps + 1) / max(int(steps), 1))


def round_float16(positions: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Positions [m] (..., V, 3) after a float16 round trip relative to ``origin`` (..., 3), as PC16 stores them."""
    origin = np.asarray(origin, np.float64)[..., None, :]
    return (np.asarray(positions, np.float64) - origin).astype(np.float16).astype(np.float64) + origin


@dataclass
class Scene:
    """One cloth on one body model (see the module docstring).

    Attributes:
        name: e.g. "tshirt@anny".
        garment: cloth name ("tshirt", ..., "shawl", "towel").
        body_kind: "anny" or "capsule".
        rest_vertices: cloth rest geometry [m], shape (V, 3).
        start_vertices: cloth positions before the canonical drape [m], shape (V, 3).
        faces: cloth triangles, shape (F, 3).
        body_faces: body triangles the cloth can touch, shape (Fb, 3) (indices into the body's vertices).
        body_vertex_count: vertices of the body mesh, Vb.
        canonical_pose: (60,); neutral_shape: (S,); shape_ranges: (S, 2); shape_names: S names.
        material_uv: pattern UVs per face corner, shape (F, 3, 2) (the garment template's
            ``face_uv``: the warp runs up each panel), or None (shawl, towel: the builder's
            grain axis, +y, x where the cloth is horizontal).
    """

    name: str
    garment: str
    body_kind: str
    rest_vertices: np.ndarray
    start_vertices: np.ndarray
    faces: np.ndarray
    body_faces: np.ndarray
    body_vertex_count: int
    canonical_pose: np.ndarray
    neutral_shape: np.ndarray
    shape_ranges: np.ndarray
    shape_names: list[str]
    _pose_fn: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] = field(repr=False)
    material_uv: np.ndarray | None = field(default=None, repr=False)

    @property
    def vertex_count(self) -> int:
        return int(len(self.rest_vertices))

    def body_vertices(self, shapes: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posed body vertices [m] (N, Vb, 3) and roots (pelvis) [m] (N, 3) for shapes (N, S), poses (N, 60)."""
        shapes = np.asarray(shapes, np.float32).reshape(-1, len(self.neutral_shape))
        poses = np.asarray(poses, np.float32).reshape(-1, 60)
        if len(shapes) != len(poses):
            raise ValueError(f"shapes ({len(shapes)}) and poses ({len(poses)}) must have the same count")
        return self._pose_fn(shapes, poses)

    def path_bodies(self, shape: np.ndarray, poses: np.ndarray, *, shape_from: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        """Bodies along a pose path (T, 60) with the shape blended from ``shape_from`` (default ``shape``) over it.

        Returns:
            vertices (T, Vb, 3) [m] and roots (T, 3) [m].
        """
        poses = np.asarray(poses, np.float32).reshape(-1, 60)
        t = np.linspace(0.0, 1.0, len(poses))[:, None] if len(poses) > 1 else np.ones((1, 1))
        a = np.asarray(shape if shape_from is None else shape_from, np.float32)
        shapes = a[None] * (1.0 - t) + np.asarray(shape, np.float32)[None] * t
        return self.body_vertices(shapes, poses)


def _anny_pose_fn(body) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    def pose(shapes: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        verts, roots = [], []
        for i in range(0, len(shapes), 16):  # bounded memory for long paths
            posed = body.pose(shapes[i:i + 16], poses[i:i + 16])
            verts.append(np.asarray(posed.vertices, np.float32))
            roots.append(np.asarray(posed.joints, np.float32)[:, 0])
        return np.concatenate(verts), np.concatenate(roots)
    return pose


def _capsule_scene(resolution: int) -> Scene:
    from simulate.scenes import capsule_body, grid_cloth

    # A bar along x at height 1 m: trimesh capsules stand along y in capsule_body; lay it down.
    cv, cf = capsule_body(height=0.5, radius=0.06, center=(0.0, 0.0, 0.0), count=(12, 12))
    cv = cv[:, [1, 0, 2]] * np.array([1.0, 1.0, 1.0])
    cf = cf[:, [0, 2, 1]]  # swapping two axes mirrors the mesh: restore outward winding
    centre = np.array([0.0, 1.0, 0.0])
    n = max(3, int(round(np.sqrt(resolution / 2.0))))
    verts, faces = grid_cloth(2 * n, n, 0.6, 0.3, plane="xz", origin=(-0.3, 1.0 + 0.06 + 0.02, -0.15))

    def pose(shapes: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from scipy.spatial.transform import Rotation

        out = np.empty((len(shapes), len(cv), 3), np.float32)
        for i, (s, p) in enumerate(zip(shapes, poses)):
            radial = cv.copy()
            radial[:, 1:] *= 0.8 + 0.4 * float(np.clip(s[0], 0.0, 1.0))
            out[i] = Rotation.from_rotvec(p[:3]).apply(radial) + centre
        return out, np.tile(centre, (len(shapes), 1)).astype(np.float32)

    return Scene(name="towel@capsule", garment="towel", body_kind="capsule", rest_vertices=verts, start_vertices=verts,
                 faces=faces, body_faces=cf.astype(np.int64), body_vertex_count=len(cv),
                 canonical_pose=np.zeros(60, np.float32), neutral_shape=np.full(1, 0.5, np.float32),
                 shape_ranges=np.array([[0.0, 1.0]], np.float32), shape_names=["radius"], _pose_fn=pose)


def build_scene(garment: str = "tshirt", *, body: str = "anny", resolution: int | None = None,
                device: str = "cpu") -> Scene:
    """Builds a report scene.

    Args:
        garment: one of :data:`SCENE_GARMENTS` on ``body="anny"``; ignored for ``body="capsule"`` (a towel).
        body: "anny" (the default body model) or "capsule" (CI stand-in).
        resolution: target cloth vertex count (garments: nearest subdivision level, see
            ``simulate.garment.templates.make_template``; shawl/towel: grid size). Default: garment 2000, shawl 600,
            towel 60.
        device: Warp device for the garment's canonical drape (garments start from
            ``simulate.garment.drape.drape_canonical``; the shawl and towel start flat).
    """
    if body == "capsule":
        return _capsule_scene(60 if resolution is None else int(resolution))
    if body != "anny":
        raise ValueError(f"body must be 'anny' or 'capsule' (got {body!r})")
    if garment not in GARMENT_CONTACT_PARTS:
        raise ValueError(f"garment must be one of {', '.join(SCENE_GARMENTS)} (got {garment!r})")
    if resolution is not None and (int(resolution) != resolution or resolution < 16):
        raise ValueError(f"resolution must be an integer vertex count >= 16 (got {resolution!r})")
    from simulate.body import load_body_model

    model = load_body_model("anny")
    parts = GARMENT_CONTACT_PARTS[garment]
    if garment != "shawl":
        from simulate.garment.drape import COLLISION_PARTS

        parts = COLLISION_PARTS[garment]  # the garment layer's table wins if it changes
    body_faces = np.asarray(model.part_faces(list(parts)), np.int64)
    canonical = np.asarray(model.canonical_pose, np.float32)
    neutral = np.asarray(model.shape_default, np.float32)
    if garment == "shawl":
        from simulate.scenes import grid_cloth

        bv = np.asarray(model.pose(neutral[None], canonical[None]).vertices[0])
        torso = np.unique(model.part_faces(["torso"]))
        top = float(bv[torso, 1].max())
        # The neck: torso vertices within 3 cm of its top; the shawl gets a hole the head passes
        # through (a poncho), else its middle starts inside the head and gets trapped in the neck.
        neck = bv[torso[bv[torso, 1] > top - 0.03]]
        centre = neck[:, [0, 2]].mean(axis=0)
        hole = float(np.linalg.norm(neck[:, [0, 2]] - centre, axis=1).max()) + 0.03
        count = 600 if resolution is None else int(resolution)
        ny = max(5, int(round(np.sqrt(count / 2.0))))
        verts, faces = grid_cloth(2 * ny, ny, 0.9, 0.45, plane="xz",
                                  origin=(centre[0] - 0.45, top + 0.02, centre[1] - 0.225))
        mid = verts[faces].mean(axis=1)
        faces = faces[np.linalg.norm(mid[:, [0, 2]] - centre, axis=1) > hole]
        used, faces = np.unique(faces, return_inverse=True)
        faces = faces.reshape(-1, 3)
        rest = start = verts[used]
        material_uv = None
    else:
        from simulate.garment.templates import generate_garment
        from simulate.garment.templates import make_template

        from simulate.garment.drape import drape_canonical

        template = make_template(garment, model, resolution=2000 if resolution is None else int(resolution))
        rest = np.asarray(generate_garment(garment, None, model, template=template), np.float64)
        faces = np.asarray(template.faces, np.int64)
        material_uv = np.asarray(template.face_uv, np.float64)
        # The garment layer's own canonical drape (as the dataset pipeline starts from it).
        draped = drape_canonical([(template, rest)], model, neutral, device=device)
        if draped.status[0] == "EXPLODED" or not np.isfinite(draped.vertices[0]).all():
            raise ValueError(f"the canonical drape of garment {garment!r} exploded (simulate.garment.drape); "
                             "the scene cannot be built")
        start = np.asarray(draped.vertices[0], np.float64)
    return Scene(name=f"{garment}@anny", garment=garment, body_kind="anny", rest_vertices=np.asarray(rest, np.float64),
                 start_vertices=np.asarray(start, np.float64), faces=faces, body_faces=body_faces,
                 body_vertex_count=int(model.vertex_count), canonical_pose=canonical, neutral_shape=neutral,
                 shape_ranges=np.asarray(model.shape_ranges, np.float32), shape_names=list(model.shape_names),
                 _pose_fn=_anny_pose_fn(model), material_uv=material_uv)


@dataclass
class SceneRun:
    """Result of :func:`run_worlds` (W worlds).

    Attributes:
        positions: final cloth positions [m], (W, V, 3).
        status: WorldStatus per world, (W,).
        frames: frames each world was stepped (path + relaxation), (W,).
        wall_s: wall time of the stepping [s] (device synchronized; model build excluded).
        substeps: substeps per frame used; dt: substep [s].
    """

    positions: np.ndarray
    status: np.ndarray
    frames: np.ndarray
    wall_s: float
    substeps: int
    dt: float


def run_worlds(
    scene: Scene,
    *,
    start: np.ndarray,
    paths: Sequence[np.ndarray],
    fabrics: Sequence[Fabric | str],
    settings: SimSettings,
    solver: str = "xpbd",
    device: str = "cpu",
    contact_thickness: float = 0.004,
    friction: bool = True,
) -> SceneRun:
    """Moves every world's body along its path (one frame per entry after the first) and relaxes at the end.

    Args:
        scene: the scene (cloth topology and rest geometry shared by all worlds).
        start: cloth positions at the first body of each path [m], (W, V, 3) or (V, 3) for all.
        paths: per world, body vertices along its path [m], (T_w, Vb, 3) with T_w >= 1.
        fabrics: per world fabric (preset name or Fabric).
        settings: time stepping and convergence; ``max_frames`` bounds the relaxation at the end.
        solver: "xpbd" or "mass_spring".
        device: Warp device.
        contact_thickness: body contact distance [m]; friction: Coulomb friction on/off.
    """
    w_count = len(paths)
    if w_count < 1 or len(fabrics) != w_count:
        raise ValueError(f"paths ({w_count}) and fabrics ({len(fabrics)}) must be non-empty and of equal length")
    start = np.asarray(start, np.float32)
    if start.ndim == 2:
        start = np.broadcast_to(start, (w_count,) + start.shape)
    if start.shape != (w_count, scene.vertex_count, 3):
        raise ValueError(f"start must have shape ({w_count}, {scene.vertex_count}, 3) (got {start.shape})")
    paths = [np.asarray(p, np.float32) for p in paths]
    for w, p in enumerate(paths):
        if p.ndim != 3 or p.shape[0] < 1 or p.shape[1:] != (scene.body_vertex_count, 3):
            raise ValueError(f"paths[{w}] must have shape (T >= 1, {scene.body_vertex_count}, 3) (got {p.shape})")
    builder = ClothBuilder()
    for fab in fabrics:
        builder.add_garment(scene.rest_vertices, scene.faces, fabric=resolve_fabric(fab), material_uv=scene.material_uv)
    model = builder.finalize(device, features=Features(friction=bool(friction)))
    collider = BodyCollider(np.stack([p[0] for p in paths]), scene.body_faces, device=device, thickness=contact_thickness)
    sim = QuasiStaticSimulator(model, collider, solver=solver, settings=dataclasses.replace(settings))
    q = np.concatenate([start[w] for w in range(w_count)])
    sim.set_positions(q)
    last = np.array([len(p) - 1 for p in paths])
    ptr = np.minimum(1, last)
    frames = np.zeros(w_count, np.int64)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    collider.set_target(np.stack([paths[w][ptr[w]] for w in range(w_count)]))
    sim.restart()
    while True:
        running = sim.status == WorldStatus.RUNNING
        if not running.any():
            break
        status = sim.step_frame()
        frames[running] += 1
        # A world on its path moves on every frame (unless it exploded); at its last entry it relaxes.
        moving = (ptr < last) & (status != WorldStatus.EXPLODED) & running
        if moving.any():
            ptr[moving] += 1
            collider.set_target(np.stack([paths[w][ptr[w]] for w in range(w_count)]))
            sim.restart(moving)
    positions = sim.positions()
    wp.synchronize_device(device)
    wall = time.perf_counter() - t0
    pos = np.stack([positions[model.world_slice(w)] for w in range(w_count)]).astype(np.float64)
    return SceneRun(positions=pos, status=sim.status.copy(), frames=frames, wall_s=wall, substeps=sim.substeps, dt=sim.dt)


def edge_stretch(positions: np.ndarray, rest_vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edge length ratios |e| / |e_rest| [-]: (max, mean) per world for positions (W, V, 3) -> ((W,), (W,))."""
    from simulate.quality import unique_edges

    e = unique_edges(np.asarray(faces))
    rest = np.linalg.norm(rest_vertices[e[:, 1]] - rest_vertices[e[:, 0]], axis=-1)
    x = np.asarray(positions, np.float64)
    ratio = np.linalg.norm(x[:, e[:, 1]] - x[:, e[:, 0]], axis=-1) / np.maximum(rest, 1e-12)
    return ratio.max(axis=1), ratio.mean(axis=1)


def frame_metrics(scene: Scene, positions: np.ndarray, bodies: np.ndarray, *, device: str = "cpu") -> list[dict[str, float]]:
    """Per world: stretch (max/mean edge ratio) and penetration (QualityMeter) of the final frames.

    Args:
        positions: cloth [m], (W, V, 3); bodies: the final bodies [m], (W, Vb, 3).
    Returns:
        W dicts: finite, stretch_max, stretch_mean, penetration_max_mm, penetration_fraction.
    """
    from simulate.quality import QualityMeter

    meter = QualityMeter(scene.faces, scene.rest_vertices, scene.body_faces, scene.body_vertex_count, device=device)
    smax, smean = edge_stretch(np.nan_to_num(positions, nan=0.0, posinf=0.0, neginf=0.0), scene.rest_vertices, scene.faces)
    out = []
    for w in range(len(positions)):
        m = meter.measure(positions[w], bodies[w], self_intersection=False)
        finite = bool(m["finite"])
        out.append({
            "finite": finite,
            "stretch_max": float(smax[w]) if finite else float("nan"),
            "stretch_mean": float(smean[w]) if finite else float("nan"),
            "penetration_max_mm": 1e3 * m["penetration_max_m"],
            "penetration_fraction": m["penetration_fraction"],
        })
    return out
