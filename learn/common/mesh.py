"""Mesh topology helpers shared by the learners: edges, boundaries, uniform Laplacians.

All functions take triangle faces as an integer array of shape (face_count, 3) and work
on topology only (no vertex positions), so their results can be cached per template.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch


def check_faces(faces: np.ndarray, vertex_count: int | None = None) -> np.ndarray:
    """``faces`` (F, 3) as int64 vertex indices, checked (shape, integer dtype, indices in range)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (face_count, 3), got {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be an integer array, got dtype {faces.dtype}")
    faces = faces.astype(np.int64)
    if faces.size and faces.min() < 0:
        raise ValueError(f"faces must hold non-negative vertex indices, got min {faces.min()}")
    if vertex_count is not None and faces.size and faces.max() >= vertex_count:
        raise ValueError(
            f"faces reference vertex {faces.max()} but vertex_count is {vertex_count}"
        )
    return faces


def face_edges(faces: np.ndarray) -> np.ndarray:
    """Directed half-edges of every face, sorted per edge, shape (3 * face_count, 2)."""
    faces = check_faces(faces)
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=0)
    return np.sort(half, axis=1)


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (i < j), shape (edge_count, 2), int64, lexicographically sorted."""
    return np.unique(face_edges(faces), axis=0)


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """Edges used by exactly one face (i < j), shape (boundary_edge_count, 2), int64."""
    edges, counts = np.unique(face_edges(faces), axis=0, return_counts=True)
    return edges[counts == 1]


def boundary_vertices(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """Boolean mask of vertices on an open boundary, shape (vertex_count,)."""
    faces = check_faces(faces, vertex_count)
    mask = np.zeros(vertex_count, dtype=bool)
    mask[boundary_edges(faces).reshape(-1)] = True
    return mask


def uniform_laplacian(
    faces: np.ndarray, vertex_count: int, *, boundary_aware: bool = True
) -> sp.csr_matrix:
    """Uniform graph Laplacian L = A_normalized - I, shape (vertex_count, vertex_count).

    Row i of ``L @ x`` is the mean of the neighbours of vertex i minus x_i. With
    ``boundary_aware`` (TailorNet's choice), a vertex on an open boundary averages only its
    neighbours along boundary edges, so smoothing slides the boundary along itself instead
    of shrinking it inward. Vertices referenced by no face have an all-zero row (they stay
    put).
    """
    from simulate.garment.mesh_ops import uniform_laplacian as laplacian

    return laplacian(check_faces(faces, vertex_count), vertex_count, boundary_aware=boundary_aware)


def scipy_to_torch_sparse(
    matrix: sp.spmatrix, *, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Convert a scipy sparse matrix to a coalesced torch sparse COO tensor."""
    coo = sp.coo_matrix(matrix)
    indices = torch.from_numpy(np.vstack([coo.row, coo.col]).astype(np.int64))
    values = torch.from_numpy(coo.data).to(dtype)
    tensor = torch.sparse_coo_tensor(indices, values, coo.shape, device=device, check_invariants=True)
    return tensor.coalesce()


def uniform_laplacian_torch(
    faces: np.ndarray,
    vertex_count: int,
    *,
    boundary_aware: bool = True,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """:func:`uniform_laplacian` as a torch sparse tensor, shape (vertex_count, vertex_count)."""
    return scipy_to_torch_sparse(
        uniform_laplacian(faces, vertex_count, boundary_aware=boundary_aware),
        device=device,
        dtype=dtype,
    )


def grid_mesh(rows: int, cols: int, *, spacing: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Flat triangulated grid in the xy plane, for tests and examples.

    Returns vertices [m], shape (rows * cols, 3), and faces, shape (2 (rows-1)(cols-1), 3).
    """
    if rows < 2 or cols < 2:
        raise ValueError(f"grid_mesh needs rows >= 2 and cols >= 2, got rows={rows}, cols={cols}")
    ys, xs = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    vertices = np.stack([xs * spacing, ys * spacing, np.zeros_like(xs, dtype=float)], axis=-1)
    vertices = vertices.reshape(-1, 3).astype(np.float64)
    index = np.arange(rows * cols).reshape(rows, cols)
    a = index[:-1, :-1].reshape(-1)
    b = index[:-1, 1:].reshape(-1)
    c = index[1:, :-1].reshape(-1)
    d = index[1:, 1:].reshape(-1)
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)], axis=0)
    return vertices, faces.astype(np.int32)
