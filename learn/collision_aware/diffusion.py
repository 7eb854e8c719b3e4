"""Body surface values extended to any point in space (seed 002, Eq. 4-6).

A surface value (skinning weights, a blendshape offset) is known at the body vertices and
interpolated barycentrically over the faces. Its diffused version at a point p averages the
surface value at the closest surface point phi(q_n) of N Gaussian samples q_n ~ N(p, d^2 I),
d being the distance from p to the body: on the surface (d = 0) it is the surface value, and off
the surface it blends the values of a neighbourhood whose size grows with the distance, so it has
no jump across the medial axis (between the legs, under an arm) where the closest point does.

The average is linear in the vertex values, so it is built once per point set as a sparse matrix
``D`` (points x body vertices); the diffused values of any per-vertex field are ``D @ values``.
That lets one set of Gaussian samples serve every field and every body shape.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import warp as wp

from simulate.contact.closest import closest_point_barycentric, face_points

#: Gaussian samples averaged per point (seed 002 does not give its N).
DEFAULT_SAMPLES = 64
#: Query radius [m] of the closest-point search; farther points are an error.
MAX_QUERY_DISTANCE_M = 10.0


@wp.kernel(enable_backward=False)
def query_closest_surface_point(
    # Body:
    mesh_id: wp.uint64,
    # Query:
    points: wp.array(dtype=wp.vec3),
    max_distance: float,
    # Out:
    face_out: wp.array(dtype=wp.int32),
    barycentric_out: wp.array(dtype=wp.vec3),
    distance_out: wp.array(dtype=float),
):
    """Closest body face, barycentric coordinates of the closest point on it, and the
    (unsigned) Euclidean distance [m]; face -1 beyond ``max_distance``."""
    tid = wp.tid()
    p = points[tid]
    query = wp.mesh_query_point_no_sign(mesh_id, p, max_distance)
    if query.result:
        a, b, c = face_points(mesh_id, query.face, wp.vec3(0.0))
        bary = closest_point_barycentric(p, a, b, c)
        closest = a * bary[0] + b * bary[1] + c * bary[2]
        face_out[tid] = query.face
        barycentric_out[tid] = bary
        distance_out[tid] = wp.length(p - closest)
    else:
        face_out[tid] = -1
        barycentric_out[tid] = wp.vec3(0.0)
        distance_out[tid] = max_distance


def closest_surface_points(
    points: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    device: str | None = None,
    max_distance: float = MAX_QUERY_DISTANCE_M,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on a triangle mesh of each query point.

    Args:
        points: query points [m], shape (N, 3).
        vertices: mesh vertices [m], shape (Vb, 3).
        faces: mesh triangles, shape (F, 3).
    Returns:
        face index (N,) int64, barycentric coordinates (N, 3), distance [m] (N,).
    """
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    device = wp.get_device(device)
    mesh = wp.Mesh(points=wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device=device),
                   indices=wp.array(faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=device))
    n = points.shape[0]
    face = wp.empty(n, dtype=wp.int32, device=device)
    bary = wp.empty(n, dtype=wp.vec3, device=device)
    distance = wp.empty(n, dtype=float, device=device)
    if n:
        wp.launch(query_closest_surface_point, dim=n,
                  inputs=[mesh.id, wp.array(points, dtype=wp.vec3, device=device), float(max_distance)],
                  outputs=[face, bary, distance], device=device)
    face_np = face.numpy().astype(np.int64)
    if (face_np < 0).any():
        far = int(np.flatnonzero(face_np < 0)[0])
        raise ValueError(f"point {far} at {points[far].tolist()} is farther than {max_distance} m from the body")
    return face_np, bary.numpy().astype(np.float64), distance.numpy().astype(np.float64)


def interpolation_matrix(face: np.ndarray, barycentric: np.ndarray, faces: np.ndarray,
                         vertex_count: int) -> sp.csr_matrix:
    """Sparse (N, Vb) matrix whose row n interpolates vertex values at (face[n], barycentric[n])."""
    rows = np.repeat(np.arange(face.shape[0]), 3)
    cols = np.asarray(faces, np.int64)[face].reshape(-1)
    return sp.csr_matrix((np.asarray(barycentric).reshape(-1), (rows, cols)), shape=(face.shape[0], vertex_count))


def diffusion_operator(
    points: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    samples: int = DEFAULT_SAMPLES,
    spread: float = 1.0,
    seed: int = 0,
    device: str | None = None,
) -> sp.csr_matrix:
    """The diffusion of Eq. 4-6 as a sparse matrix D, shape (N, Vb): ``D @ values`` (values
    (Vb, C) at the body vertices) is the diffused field at the N points.

    Args:
        points: where the field is wanted [m], shape (N, 3).
        vertices, faces: the body surface [m], (Vb, 3) and (F, 3).
        samples: Gaussian samples per point.
        spread: standard deviation of the samples as a multiple of the point's distance to the
            body (seed 002: 1).
        seed: RNG seed of the samples (same inputs and seed, same matrix).
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    if spread < 0:
        raise ValueError(f"spread must be >= 0, got {spread}")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    vertex_count = int(np.asarray(vertices).shape[0])
    _, _, distance = closest_surface_points(points, vertices, faces, device=device)
    rng = np.random.default_rng(seed)
    offsets = rng.standard_normal((points.shape[0], samples, 3)) * (spread * distance)[:, None, None]
    queries = (points[:, None, :] + offsets).reshape(-1, 3)  # (N * samples, 3)
    face, bary, _ = closest_surface_points(queries, vertices, faces, device=device)
    per_sample = interpolation_matrix(face, bary, faces, vertex_count)  # (N * samples, Vb)
    average = sp.csr_matrix(
        (np.full(points.shape[0] * samples, 1.0 / samples),
         (np.repeat(np.arange(points.shape[0]), samples), np.arange(points.shape[0] * samples))),
        shape=(points.shape[0], points.shape[0] * samples),
    )
    return sp.csr_matrix(average @ per_sample)


def distance_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *,
                        device: str | None = None) -> np.ndarray:
    """Unsigned distance [m] of each point (N, 3) to the surface, shape (N,)."""
    return closest_surface_points(points, vertices, faces, device=device)[2]
