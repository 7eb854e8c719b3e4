"""Registration of a rest-pose garment onto the common body mesh (seed 004, Sec. 4.1): per
body vertex an offset [m] and a mask bit, so that ``body + offset`` on the masked vertices,
with the body faces whose three vertices are masked, is the garment.

1. Mask: a ray from each body vertex along its (smoothed) normal, started ``RAY_START_M``
   inside the body, must leave the garment from inside (hit face facing along the ray)
   within ``max_distance`` [m], or a garment vertex projected onto the body (closest point)
   must lie within half a body edge of it (rays from concave places such as the crotch can
   meet the garment from outside first); isolated bits are then cleaned (a vertex whose neighbours are
   all covered is covered, one with no covered neighbour is not). Rays, not closest points:
   a skirt's flare, 20 cm off the thighs, is where the thigh's normal points, while its
   closest body point is at the hips.
2. Offsets: non-rigid ICP. Start at each covered vertex's ray hit, then
   ``rounds`` times: Laplacian-smooth the offsets over the covered vertices (so they stay
   evenly spread instead of bunching at creases) and project ``body + offset`` back onto
   the garment. The last step is a projection, so registered points lie on the garment.

The error of the representation is measured both ways (:func:`registration_error`):
garment vertices to the reconstructed surface (what the representation misses, e.g. a
flare past the last covered row) and reconstructed vertices to the garment.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from simulate.garment import mesh_ops

#: Coverage rays start this far inside the body [m] (tight garments dip into it).
RAY_START_M = 0.01
#: Diffusion iterations of the body normals the rays follow (crossing rays in creases).
NORMAL_SMOOTHING = 5
#: Longest offset [m] per topology: tops and trousers stay within looseness + flare (5 + 6 cm)
#: of the body; a skirt's hem flares up to 25 cm off the legs.
MAX_OFFSET_M: dict[str, float] = {"standard": 0.12, "dual": 0.35}
#: Offsets smoothing per ICP round: iterations and step.
SMOOTH_ITERATIONS = 3
SMOOTH_STEP = 0.5


@dataclass
class Registration:
    """offsets (N, 3) [m] (zero off the mask), mask (N,) bool."""

    offsets: np.ndarray
    mask: np.ndarray


@functools.cache
def _ray_kernel():
    import warp as wp

    @wp.kernel(enable_backward=False)
    def first_hits(mesh: wp.uint64, starts: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                   max_t: float, t_out: wp.array(dtype=float), face_out: wp.array(dtype=wp.int32)):
        tid = wp.tid()
        q = wp.mesh_query_ray(mesh, starts[tid], directions[tid], max_t)
        if q.result:
            t_out[tid] = q.t
            face_out[tid] = q.face
        else:
            face_out[tid] = -1

    return first_hits


def ray_hits(vertices: np.ndarray, faces: np.ndarray, starts: np.ndarray, directions: np.ndarray,
             max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """First hits of rays on a mesh: (distance t (R,) [m], face (R,), -1 where none within
    ``max_distance``)."""
    import warp as wp

    mesh = wp.Mesh(wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device="cpu"),
                   wp.array(np.asarray(faces, np.int32).ravel(), dtype=wp.int32, device="cpu"))
    n = len(starts)
    t = wp.zeros(n, dtype=float, device="cpu")
    face = wp.zeros(n, dtype=wp.int32, device="cpu")
    wp.launch(_ray_kernel(), dim=n, device="cpu",
              inputs=[mesh.id, wp.array(np.asarray(starts, np.float32), dtype=wp.vec3, device="cpu"),
                      wp.array(np.asarray(directions, np.float32), dtype=wp.vec3, device="cpu"), float(max_distance)],
              outputs=[t, face])
    return t.numpy().astype(np.float64), face.numpy().astype(np.int64)


def coverage(garment_vertices: np.ndarray, garment_faces: np.ndarray, body_vertices: np.ndarray,
             body_faces: np.ndarray, *, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Body vertices under the garment (N,) bool and their ray hits (N, 3) [m] (step 1 of
    the module docstring)."""
    n = len(body_vertices)
    normals = mesh_ops.smooth_normals(body_vertices, body_faces, iterations=NORMAL_SMOOTHING)
    starts = body_vertices - RAY_START_M * normals
    t, face = ray_hits(garment_vertices, garment_faces, starts, normals, max_distance + RAY_START_M)
    garment_normals = mesh_ops.face_normals(garment_vertices, garment_faces)
    in_faces = np.zeros(n, bool)
    in_faces[np.unique(body_faces)] = True
    hit = in_faces & (face >= 0)
    hit[hit] &= (garment_normals[face[hit]] * normals[hit]).sum(1) > 0.0
    points = np.where(hit[:, None], starts + t[:, None] * normals, np.nan)
    projected = mesh_ops.ClosestPointQuery(body_vertices, body_faces).query(garment_vertices)[0]
    edges, _ = mesh_ops.unique_edges(body_faces)
    radius = 0.5 * float(np.median(np.linalg.norm(body_vertices[edges[:, 0]] - body_vertices[edges[:, 1]], axis=1)))
    near = np.zeros(n, bool)
    near[in_faces] = cKDTree(projected).query(body_vertices[in_faces])[0] <= radius
    hit |= near
    adjacency = mesh_ops.vertex_adjacency(body_faces, n)
    degree = np.asarray(adjacency.sum(1)).ravel()
    covered = adjacency @ hit.astype(np.float64)
    mask = (hit | ((covered == degree) & (degree > 0))) & (covered > 0)
    return mask, points


def register(garment_vertices: np.ndarray, garment_faces: np.ndarray, body_vertices: np.ndarray,
             body_faces: np.ndarray, *, rounds: int = 6, max_distance: float = 0.35) -> Registration:
    """Offsets and mask of a garment (Vg, 3) [m] on body positions (N, 3) [m] with the
    topology ``body_faces`` the garment type registers on (standard or dual)."""
    g = np.asarray(garment_vertices, dtype=np.float64)
    b = np.asarray(body_vertices, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != 3 or len(g) == 0:
        raise ValueError(f"garment_vertices must have shape (V, 3) with V > 0, got {g.shape}")
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"body_vertices must have shape (N, 3), got {b.shape}")
    mask, hits = coverage(g, garment_faces, b, body_faces, max_distance=max_distance)
    garment = mesh_ops.ClosestPointQuery(g, garment_faces)
    offsets = np.zeros_like(b)
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return Registration(offsets.astype(np.float32), mask)
    offsets[idx] = np.where(np.isfinite(hits[idx]).all(1, keepdims=True), hits[idx], garment.query(b[idx])[0]) - b[idx]
    # Laplacian over the covered vertices only: uncovered neighbours do not pull offsets to 0.
    sub = mesh_ops.vertex_adjacency(body_faces, len(b))[idx][:, idx]
    degree = np.asarray(sub.sum(1)).ravel()
    average = sparse.diags(np.where(degree > 0, 1.0 / np.maximum(degree, 1), 0.0)) @ sub
    keep = (degree == 0)[:, None]
    for _ in range(int(rounds)):
        d = offsets[idx]
        for _ in range(SMOOTH_ITERATIONS):
            d = np.where(keep, d, d + SMOOTH_STEP * (average @ d - d))
        offsets[idx] = garment.query(b[idx] + d)[0] - b[idx]
    return Registration(offsets.astype(np.float32), mask)


def reconstruct(body_vertices: np.ndarray, body_faces: np.ndarray, offsets: np.ndarray,
                mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The garment of an offsets/mask pair: (vertices (M, 3) [m], faces (F', 3), body
    vertex index of each vertex (M,)): masked vertices moved by their offsets, the faces
    whose three vertices are masked, unused vertices dropped."""
    mask = np.asarray(mask, bool)
    faces = np.asarray(body_faces, np.int64)
    faces = faces[mask[faces].all(1)]
    used = np.unique(faces)
    remap = np.full(len(mask), -1, np.int64)
    remap[used] = np.arange(len(used))
    vertices = (np.asarray(body_vertices, np.float64) + np.asarray(offsets, np.float64))[used]
    return vertices, remap[faces], used


def registration_error(garment_vertices: np.ndarray, garment_faces: np.ndarray, body_vertices: np.ndarray,
                       body_faces: np.ndarray, registration: Registration) -> dict[str, float]:
    """Mean distances [mm]: ``garment_to_registered`` (garment vertices to the reconstructed
    surface) and ``registered_to_garment`` (reconstructed vertices to the garment)."""
    v, f, _ = reconstruct(body_vertices, body_faces, registration.offsets, registration.mask)
    g = np.asarray(garment_vertices, np.float64)
    if len(f) == 0:
        return {"garment_to_registered_mm": float("inf"), "registered_to_garment_mm": float("inf")}
    to_rec = np.abs(mesh_ops.ClosestPointQuery(v, f).query(g)[3])
    to_garment = np.abs(mesh_ops.ClosestPointQuery(g, garment_faces).query(v)[3])
    return {"garment_to_registered_mm": 1e3 * float(to_rec.mean()),
            "registered_to_garment_mm": 1e3 * float(to_garment.mean())}
