"""Small procedural meshes for tests, examples and benchmarks (grid cloth, tube, sphere, capsule)."""

from __future__ import annotations

import numpy as np
import trimesh

__all__ = ["grid_cloth", "hanging_strip", "tube_cloth", "icosphere", "capsule_body"]


def grid_cloth(nx: int, ny: int, size_x: float, size_y: float, *, plane: str = "xz",
               origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Regular triangulated rectangle with ``nx`` x ``ny`` vertices.

    Each quad is split into two triangles whose first edge runs along the first axis. The
    triangles' material frames come from the builder's grain (``ClothBuilder.add_garment``:
    default +y projected into each triangle, x where a triangle is horizontal): on an "xz" grid
    the warp is the first axis (x), on an "xy" grid it is the second axis (vertical, pointing
    up). Pass ``grain_axis`` or ``material_uv`` to the builder to cut the cloth another way.

    Args:
        nx, ny: vertices along the first and second axis (>= 2).
        size_x, size_y: side lengths [m].
        plane: "xz" (horizontal; first axis x, second axis z) or "xy" (vertical; first axis x,
            second axis -y, so row 0 is the top).
        origin: position of vertex (0, 0) [m].
    Returns:
        vertices (nx * ny, 3) float64 [m] (index ``j * nx + i``), faces (2 (nx-1)(ny-1), 3) int64.
    """
    if nx < 2 or ny < 2:
        raise ValueError(f"grid_cloth needs nx, ny >= 2 (got {nx}, {ny})")
    u = np.linspace(0.0, size_x, nx)
    v = np.linspace(0.0, size_y, ny)
    uu, vv = np.meshgrid(u, v)  # (ny, nx)
    verts = np.zeros((ny * nx, 3))
    if plane == "xz":
        verts[:, 0], verts[:, 2] = uu.ravel(), vv.ravel()
    elif plane == "xy":
        verts[:, 0], verts[:, 1] = uu.ravel(), -vv.ravel()
    else:
        raise ValueError(f"plane must be 'xz' or 'xy' (got {plane!r})")
    verts += np.asarray(origin, dtype=np.float64)
    j, i = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    p00 = (j * nx + i).ravel()
    p01 = p00 + 1
    p10 = p00 + nx
    p11 = p10 + 1
    faces = np.concatenate([np.stack([p00, p01, p11], 1), np.stack([p11, p10, p00], 1)])
    return verts, faces


def hanging_strip(rows: int, fabric, device: str = "cpu", *, length: float = 1.0, width: float = 0.05,
                  roll: int = 0):
    """The hanging-strip oracle's scene: a vertical strip of ``rows`` rows (two vertices across),
    its top edge pinned at y = 1 m, stretch and shear only (no body, no bending). Under its own
    weight its bottom sinks by rho g L^2 / (2 Y) (lumped masses give the continuous answer).

    Args:
        rows: rows of triangles pairs along the length; fabric: a Fabric or preset name.
        length, width: strip size [m]; roll: each face's corners rolled by this many places.
    Returns:
        (rest vertices (2 (rows + 1), 3) [m], one-world ClothModel on ``device``).
    """
    from simulate.cloth import ClothBuilder, Features

    verts, faces = grid_cloth(2, rows + 1, width, length, plane="xy", origin=(0.0, 1.0, 0.0))
    builder = ClothBuilder()
    builder.add_garment(verts, np.roll(faces, roll, axis=1), fabric=fabric, pinned=[0, 1])
    return verts, builder.finalize(device, features=Features(body_contact=False, bending=False))


def tube_cloth(n_around: int, n_along: int, radius: float, length: float, *,
               center: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Open cylinder along y (a skirt- or sleeve-like tube), top ring at ``center`` y + length / 2.

    Returns:
        vertices (n_around * n_along, 3) [m] (ring ``j`` = rows from the top), faces int64.
    """
    if n_around < 3 or n_along < 2:
        raise ValueError(f"tube_cloth needs n_around >= 3 and n_along >= 2 (got {n_around}, {n_along})")
    theta = np.linspace(0.0, 2.0 * np.pi, n_around, endpoint=False)
    y = np.linspace(length / 2.0, -length / 2.0, n_along)
    tt, yy = np.meshgrid(theta, y)
    verts = np.stack([radius * np.cos(tt).ravel(), yy.ravel(), radius * np.sin(tt).ravel()], 1)
    verts += np.asarray(center, dtype=np.float64)
    j, i = np.meshgrid(np.arange(n_along - 1), np.arange(n_around), indexing="ij")
    p00 = (j * n_around + i).ravel()
    p01 = (j * n_around + (i + 1) % n_around).ravel()
    p10 = p00 + n_around
    p11 = p01 + n_around
    faces = np.concatenate([np.stack([p00, p01, p11], 1), np.stack([p11, p10, p00], 1)])
    return verts, faces


def icosphere(radius: float, *, subdivisions: int = 3,
              center: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Closed sphere mesh (trimesh icosphere) [m]; returns vertices (V, 3), faces (F, 3)."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(mesh.vertices) + np.asarray(center), np.asarray(mesh.faces, dtype=np.int64)


def capsule_body(*, height: float = 1.2, radius: float = 0.15, center: tuple[float, float, float] = (0.0, 1.0, 0.0),
                 count: tuple[int, int] = (24, 24)) -> tuple[np.ndarray, np.ndarray]:
    """A closed capsule standing along y: a torso-like stand-in for a body [m]."""
    mesh = trimesh.creation.capsule(height=height, radius=radius, count=list(count))
    # trimesh capsules run along z; stand it up along y.
    verts = np.asarray(mesh.vertices)[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0])
    faces = np.asarray(mesh.faces, dtype=np.int64)
    return verts + np.asarray(center), faces


def default_body(parts: tuple[str, ...] | None = ("torso", "arms", "legs"), *,
                 pose: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """The project's default body (anny via ``simulate.body``) in its canonical pose, culled to ``parts``.

    Falls back to :func:`capsule_body` (kind "capsule") when ``simulate.body.load_body_model`` is
    not importable.

    Args:
        parts: body parts to keep (see ``simulate.body.PARTS``); None keeps the whole body.
        pose: pose vector (60,) for the body model; None = its canonical pose.
    Returns:
        vertices (V, 3) [m], faces (F, 3) (a subset of the body's faces; unreferenced vertices
        are left in, BodyCollider drops them), and the kind ("anny" or "capsule").
    """
    try:
        from simulate.body import load_body_model
    except ImportError:
        verts, faces = capsule_body()
        return verts, faces, "capsule"
    body = load_body_model("anny")
    pose_vec = body.canonical_pose if pose is None else np.asarray(pose, dtype=np.float32)
    posed = body.pose(body.shape_default[None], pose_vec[None])
    faces = body.faces if parts is None else body.part_faces(list(parts))
    return np.asarray(posed.vertices[0], dtype=np.float64), np.asarray(faces, dtype=np.int64), "anny"


BENCH_POSE = {
    "left_shoulder": (0.0, 0.0, 0.5),   # left arm raised sideways
    "right_shoulder": (-0.6, 0.0, 0.0),  # right arm swung forward
    "right_elbow": (0.0, 0.9, 0.0),      # and bent
    "spine2": (0.0, 0.25, 0.0),          # torso twisted
    "left_hip": (-0.4, 0.0, 0.0),        # left leg forward
}
"""Axis-angle offsets [rad] added to the canonical pose for the benchmark drape."""


def shawl_scene(resolution: int = 100, *, size: float = 1.4, body: str = "default",
                parts: tuple[str, ...] = ("torso", "arms", "head", "legs", "hands")) -> dict:
    """Benchmark scene: a square cloth of ``resolution`` x ``resolution`` vertices held flat 2 cm above
    the head of the default body in a non-trivial pose (:data:`BENCH_POSE`), culled to ``parts``.

    Args:
        resolution: vertices per side (100 gives a 10k-vertex cloth).
        size: cloth side length [m].
        body: "default" (anny via simulate.body, capsule if unavailable) or "capsule".
        parts: body parts kept in the collider (feet dropped by default).  The hands are kept: the
            shawl's edge reaches them in this pose, and at an open wrist cut it passed inside the
            forearm and was flung out (every 10k-vertex world EXPLODED at frame 27-36).
    Returns:
        dict with cloth_vertices (V, 3), cloth_faces (F, 3), body_vertices (Vb, 3),
        body_faces (Fb, 3) [m], and body_kind ("anny" or "capsule").
    """
    kind = "capsule"
    if body == "default":
        try:
            from simulate.body import POSE_JOINTS, load_body_model
        except ImportError:
            POSE_JOINTS = None
        if POSE_JOINTS is not None:
            model = load_body_model("anny")
            pose = np.asarray(model.canonical_pose, dtype=np.float32).reshape(-1, 3).copy()
            for joint, rot in BENCH_POSE.items():
                pose[POSE_JOINTS.index(joint)] += np.asarray(rot, dtype=np.float32)
            posed = model.pose(model.shape_default[None], pose.reshape(1, -1))
            body_v = np.asarray(posed.vertices[0], dtype=np.float64)
            body_f = np.asarray(model.part_faces(list(parts)), dtype=np.int64)
            kind = "anny"
    elif body != "capsule":
        raise ValueError(f"body must be 'default' or 'capsule' (got {body!r})")
    if kind == "capsule":
        body_v, body_f = capsule_body(height=1.2, radius=0.15, center=(0.0, 0.0, 0.0))
    used = body_v[np.unique(body_f)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    centre = 0.5 * (lo + hi)
    cloth_v, cloth_f = grid_cloth(resolution, resolution, size, size, plane="xz",
                                  origin=(centre[0] - size / 2, hi[1] + 0.02, centre[2] - size / 2))
    return {"cloth_vertices": cloth_v, "cloth_faces": cloth_f, "body_vertices": body_v, "body_faces": body_f,
            "body_kind": kind}


def cape_scene(resolution: int = 100, *, width: float = 0.5, length: float = 0.9, body: str = "default",
               parts: tuple[str, ...] = ("torso", "arms", "head", "legs")) -> dict:
    """Benchmark scene with a near-unique rest state: a cape pinned along its top edge just behind
    the neck of the body in :data:`BENCH_POSE`, starting horizontal (pointing backwards), that
    swings down and comes to rest on the back.

    Args:
        resolution: vertices along the length (the width gets ``resolution * width / length``,
            at least 2); 100 gives ~5.5k vertices, 135 ~10k.
        width, length: cape size [m].
        body, parts: as in :func:`shawl_scene`.
    Returns:
        dict as :func:`shawl_scene` plus ``pinned`` (indices of the top edge).
    """
    scene = shawl_scene(2, body=body, parts=parts)
    body_v, body_f = scene["body_vertices"], scene["body_faces"]
    used = body_v[np.unique(body_f)]
    centre_x = float(used[np.argmax(used[:, 1]), 0])  # the top of the head marks the mid-plane
    # Shoulder height: the highest body point 10-18 cm to the side of the mid-plane (x), i.e.
    # beside the neck and inside the arms.
    side = used[(np.abs(used[:, 0] - centre_x) > 0.10) & (np.abs(used[:, 0] - centre_x) < 0.18)]
    top_y = float(side[:, 1].max()) + 0.03
    # Just behind the neck: the most backward point of the neck (5 cm around the mid-plane, up to
    # 10 cm above the edge) minus 1 cm; the upper back bulges further back, so the cape rests on it.
    neck = used[(np.abs(used[:, 0] - centre_x) < 0.05) & (used[:, 1] > top_y) & (used[:, 1] < top_y + 0.10)]
    back_z = float(neck[:, 2].min()) - 0.01
    nx = max(2, int(round(resolution * width / length)))
    cloth_v, cloth_f = grid_cloth(nx, resolution, width, length, plane="xz",
                                  origin=(centre_x - width / 2.0, top_y, back_z))
    cloth_v[:, 2] = back_z - (cloth_v[:, 2] - back_z)  # extend backwards (-z), the body faces +z
    cloth_f = cloth_f[:, ::-1].copy()  # keep the winding consistent after the mirror
    return {"cloth_vertices": cloth_v, "cloth_faces": cloth_f, "body_vertices": body_v, "body_faces": body_f,
            "body_kind": scene["body_kind"], "pinned": np.arange(nx)}


def batched_drape(scene: dict, worlds: int, device: str, *, fabric: object = "cotton", jitter: float = 0.0,
                  seed: int = 0, thickness: float = 2.0e-3, features=None, garments: int = 0):
    """Model and collider with ``worlds`` copies of ``scene`` (see :func:`shawl_scene`).

    Args:
        scene: dict from :func:`shawl_scene` (an optional "cloth_uv" (F, 3, 2) entry gives the
            triangles' material frames, see ``ClothBuilder.add_garment``'s ``material_uv``).
        worlds: number of worlds.
        device: Warp device.
        fabric: fabric of every world (a preset name or a Fabric).
        jitter: per-world random sideways (x) shift of the cloth [m] (seeded), so worlds differ.
        seed: RNG seed for the jitter.
        thickness: body contact thickness [m].
        features: simulate.cloth.Features or None.
        garments: 0: every world is the scene's cloth; K > 0: world w wears garment w % K, the
            cloth scaled about its centroid by 1 + 1e-4 (w % K) (K garments of distinct rest
            shapes, as in a dataset batch of K styles).
    Returns:
        (ClothModel, BodyCollider)
    """
    from simulate.cloth.builder import ClothBuilder
    from simulate.contact.body_collider import BodyCollider

    rng = np.random.default_rng(seed)
    builder = ClothBuilder()
    cloth = scene["cloth_vertices"]
    centre = np.mean(cloth, axis=0)
    for w in range(worlds):
        shift = np.zeros(3)
        if jitter > 0.0:
            shift[0] = rng.uniform(-jitter, jitter)
        garment = cloth if garments <= 0 else centre + (cloth - centre) * (1.0 + 1.0e-4 * (w % garments))
        builder.add_garment(garment + shift, scene["cloth_faces"], fabric=fabric, pinned=scene.get("pinned"),
                            material_uv=scene.get("cloth_uv"))
    model = builder.finalize(device, features=features)
    collider = BodyCollider(scene["body_vertices"], scene["body_faces"], device=device, world_count=worlds,
                            thickness=thickness)
    return model, collider
