"""Small procedural meshes for tests, examples and benchmarks (grid cloth, tube, sphere, capsule)."""

from __future__ import annotations

import numpy as np
import trimesh

__all__ = ["grid_cloth", "tube_cloth", "icosphere", "capsule_body"]


def grid_cloth(nx: int, ny: int, size_x: float, size_y: float, *, plane: str = "xz",
               origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Regular triangulated rectangle with ``nx`` x ``ny`` vertices.

    Each quad is split into two triangles whose first edge runs along the first axis, so the
    triangles' first material direction is the grid's first axis (used by the strip oracle).

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
