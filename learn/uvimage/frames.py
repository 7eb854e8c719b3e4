"""Cloth pixels embedded in the body (seed 001 Sec. 5): points and tangent frames.

Each garment vertex is embedded at rest in a body triangle (the template's ``body_face``
(V,), ``body_bary`` (V, 3)); on a posed body its *embedded point* is the same
barycentric combination of the posed triangle. A garment vertex is stored as an offset
from its embedded point, in the tangent / bitangent / normal frame of the skinned body
there (seed Sec. 6: (du, dv, dn)), so the network learns only what skinning does not
give.

The frame of a cloth pixel (a (vertex, panel) pair, :mod:`learn.uvimage.pixels`):
- normal n: the barycentric mean of the posed body's area-weighted vertex normals,
  normalised (smooth across body triangles);
- tangent t: the direction of increasing u of the pixel's panel chart on the rest
  surface (area-weighted mean over the panel's faces around the vertex, as normal
  mapping derives tangents from texture coordinates), written once as a combination
  a e1 + b e2 of the rest body triangle's edges; on a posed body the same combination
  of the posed edges, made orthogonal to n and normalised (it turns and shears with the
  triangle, and is smooth over the chart because the chart is);
- bitangent = n x t.
Seam vertices get one frame per panel, so each panel's image is smooth up to its
border. Frames are (B, K, 3, 3) with columns (t, b, n).
"""

from __future__ import annotations

import numpy as np
import torch

from learn.common.normals import NORMAL_EPS


def chart_tangents(points: np.ndarray, faces: np.ndarray, corner_uv: np.ndarray, corner_pixel: np.ndarray,
                   pixel_count: int) -> np.ndarray:
    """Unnormalised rest tangent (dP/du) of each cloth pixel, shape (K, 3).

    points: rest surface points [m], (V, 3); faces (F, 3); corner_uv (F, 3, 2) in the
    panels' images; corner_pixel (F, 3): cloth pixel of each corner.
    Each face's dP/du (from its 3D edges and UV edges) is added, times its 3D area, to
    its three corners' cloth pixels.
    """
    tri = np.asarray(points, dtype=np.float64)[faces]  # (F, 3, 3)
    d_p = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], -1)  # (F, 3, 2)
    d_uv = np.stack([corner_uv[:, 1] - corner_uv[:, 0], corner_uv[:, 2] - corner_uv[:, 0]], -1)  # (F, 2, 2)
    det = d_uv[:, 0, 0] * d_uv[:, 1, 1] - d_uv[:, 0, 1] * d_uv[:, 1, 0]
    ok = np.abs(det) > 1e-14
    inv = np.zeros_like(d_uv)
    inv[ok] = np.linalg.inv(d_uv[ok])
    jac = d_p @ inv  # (F, 3, 2): columns dP/du, dP/dv
    area = 0.5 * np.linalg.norm(np.cross(d_p[..., 0], d_p[..., 1]), axis=-1)
    du = jac[..., 0]
    du = du / np.maximum(np.linalg.norm(du, axis=-1, keepdims=True), 1e-15) * area[:, None]
    out = np.zeros((pixel_count, 3))
    for k in range(3):
        np.add.at(out, corner_pixel[:, k], du)
    return out


def edge_coefficients(tangent: np.ndarray, triangle: np.ndarray) -> np.ndarray:
    """(a, b) with a e1 + b e2 the projection of ``tangent`` (K, 3) onto the plane of
    ``triangle`` (K, 3, 3) (e1 = v1 - v0, e2 = v2 - v0): shape (K, 2), least squares."""
    e = np.stack([triangle[:, 1] - triangle[:, 0], triangle[:, 2] - triangle[:, 0]], -1)  # (K, 3, 2)
    gram = np.einsum("kdi,kdj->kij", e, e)
    rhs = np.einsum("kdi,kd->ki", e, tangent)
    return np.linalg.solve(gram + 1e-18 * np.eye(2), rhs[..., None])[..., 0]


class BodyEmbedding(torch.nn.Module):
    """Embedded points and tangent frames of one template's cloth pixels on posed bodies.

    Args:
        body_faces: body triangles, (Fb, 3).
        body_face, body_bary: embedding of each garment vertex, (V,), (V, 3).
        pixel_vertex: vertex of each cloth pixel, (K,).
        tangent_coefficients: (a, b) of each cloth pixel's rest tangent in its body
            triangle's edges, (K, 2) (:func:`edge_coefficients`).
    Only the body faces around the embedding triangles' vertices are kept (their
    vertex normals need their one-rings), so a posed body is read, never copied whole.
    """

    def __init__(self, body_faces: np.ndarray, body_face: np.ndarray, body_bary: np.ndarray, pixel_vertex: np.ndarray,
                 tangent_coefficients: np.ndarray) -> None:
        super().__init__()
        body_faces = np.asarray(body_faces, dtype=np.int64)
        body_face = np.asarray(body_face, dtype=np.int64)
        if (body_face < 0).any():
            raise ValueError(f"{int((body_face < 0).sum())} garment vertices have no body triangle (body_face = -1): "
                             "the UV-image learner needs a garment embedded in the body (not the skirt)")
        tri = body_faces[body_face]  # (V, 3) body vertex ids
        used = np.unique(tri)
        ring = np.isin(body_faces, used).any(1)
        ring_faces = body_faces[ring]
        local_ids = np.unique(ring_faces)  # body vertices whose positions are read
        remap = np.full(int(body_faces.max()) + 1, -1, dtype=np.int64)
        remap[local_ids] = np.arange(len(local_ids))
        self.vertex_count = int(len(body_face))
        self.register_buffer("body_vertices_used", torch.as_tensor(local_ids))
        self.register_buffer("ring_faces", torch.as_tensor(remap[ring_faces]))
        self.register_buffer("triangle", torch.as_tensor(remap[tri]))  # (V, 3) in used-vertex ids
        self.register_buffer("bary", torch.as_tensor(np.asarray(body_bary), dtype=torch.float32))
        self.register_buffer("pixel_vertex", torch.as_tensor(np.asarray(pixel_vertex), dtype=torch.int64))
        self.register_buffer("coefficients", torch.as_tensor(np.asarray(tangent_coefficients), dtype=torch.float32))

    def forward(self, body_vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed body (B, Vb, 3) [m] -> (embedded points (B, V, 3) [m], frames (B, K, 3, 3))."""
        x = body_vertices[:, self.body_vertices_used]  # (B, U, 3)
        tri = x[:, self.triangle]  # (B, V, 3, 3)
        bary = self.bary.to(x.dtype)
        points = torch.einsum("vk,bvkd->bvd", bary, tri)
        ring = x[:, self.ring_faces]  # (B, Fr, 3, 3)
        face_n = torch.linalg.cross(ring[:, :, 1] - ring[:, :, 0], ring[:, :, 2] - ring[:, :, 0], dim=-1)
        vn = torch.zeros_like(x)
        for k in range(3):
            vn = vn.index_add(1, self.ring_faces[:, k], face_n)
        vn = vn / torch.linalg.vector_norm(vn, dim=-1, keepdim=True).clamp_min(NORMAL_EPS)
        n = torch.einsum("vk,bvkd->bvd", bary, vn[:, self.triangle])  # (B, V, 3)
        n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(NORMAL_EPS)
        n = n[:, self.pixel_vertex]  # (B, K, 3)
        tri_k = tri[:, self.pixel_vertex]  # (B, K, 3, 3)
        coef = self.coefficients.to(x.dtype)
        t = coef[None, :, 0:1] * (tri_k[:, :, 1] - tri_k[:, :, 0]) + coef[None, :, 1:2] * (tri_k[:, :, 2] - tri_k[:, :, 0])
        t = t - (t * n).sum(-1, keepdim=True) * n
        t = t / torch.linalg.vector_norm(t, dim=-1, keepdim=True).clamp_min(NORMAL_EPS)
        b = torch.linalg.cross(n, t, dim=-1)
        return points, torch.stack([t, b, n], -1)  # (B, K, 3, 3), columns t, b, n

    def to_local(self, vertices: torch.Tensor, points: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """Garment vertices (B, V, 3) [m] -> cloth-pixel offsets (du, dv, dn) (B, K, 3) [m]."""
        offset = (vertices - points)[:, self.pixel_vertex]  # (B, K, 3)
        return torch.einsum("bkdc,bkd->bkc", frames, offset)

    def to_world(self, local: torch.Tensor, points: torch.Tensor, frames: torch.Tensor,
                 pixel_weight: torch.Tensor) -> torch.Tensor:
        """Cloth-pixel offsets (B, K, 3) -> garment vertices (B, V, 3) [m]: each vertex's
        embedded point plus the ``pixel_weight``-weighted (K,) sum of its pixels' world offsets."""
        world = torch.einsum("bkdc,bkc->bkd", frames, local) * pixel_weight.to(local.dtype)[None, :, None]
        return points.index_add(1, self.pixel_vertex, world)


def tangent_frames_naive(body_vertices: np.ndarray, body_faces: np.ndarray, body_face: np.ndarray,
                         body_bary: np.ndarray, pixel_vertex: np.ndarray, coefficients: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Loop twin of :class:`BodyEmbedding` for one posed body (Vb, 3), for tests:
    (points (V, 3), frames (K, 3, 3)), every quantity computed vertex by vertex."""
    bv = np.asarray(body_vertices, dtype=np.float64)
    normals = np.zeros_like(bv)
    for f in body_faces:
        a, b, c = bv[f[0]], bv[f[1]], bv[f[2]]
        n = np.cross(b - a, c - a)
        for i in f:
            normals[i] += n
    points = np.zeros((len(body_face), 3))
    vertex_normal = np.zeros((len(body_face), 3))
    for v, (face, w) in enumerate(zip(body_face, body_bary)):
        corners = body_faces[face]
        points[v] = sum(w[k] * bv[corners[k]] for k in range(3))
        n = sum(w[k] * normals[corners[k]] / np.linalg.norm(normals[corners[k]]) for k in range(3))
        vertex_normal[v] = n / np.linalg.norm(n)
    frames = np.zeros((len(pixel_vertex), 3, 3))
    for k, v in enumerate(pixel_vertex):
        corners = body_faces[body_face[v]]
        n = vertex_normal[v]
        t = coefficients[k, 0] * (bv[corners[1]] - bv[corners[0]]) + coefficients[k, 1] * (bv[corners[2]] - bv[corners[0]])
        t = t - np.dot(t, n) * n
        t = t / np.linalg.norm(t)
        frames[k] = np.stack([t, np.cross(n, t), n], 1)
    return points, frames


def embedding_for(pixels, faces: np.ndarray, body_rest_vertices: np.ndarray, body_faces: np.ndarray,
                  body_face: np.ndarray, body_bary: np.ndarray) -> BodyEmbedding:
    """The :class:`BodyEmbedding` of a :class:`learn.uvimage.pixels.ClothPixels` layout.

    body_rest_vertices: the body the template was embedded in (neutral shape, rest pose)
    [m], (Vb, 3); faces: garment triangles (F, 3); body_face (V,), body_bary (V, 3).
    """
    body_faces = np.asarray(body_faces, dtype=np.int64)
    body_face = np.asarray(body_face, dtype=np.int64)
    rest_tri = np.asarray(body_rest_vertices, dtype=np.float64)[body_faces[np.maximum(body_face, 0)]]  # (V, 3, 3)
    rest_points = np.einsum("vk,vkd->vd", np.asarray(body_bary, dtype=np.float64), rest_tri)
    pixel_vertex = pixels.pixel_vertex.cpu().numpy()
    corner_pixel = pixels.corner_pixel.cpu().numpy()
    corner_uv = pixels.pixel_uv.cpu().numpy().astype(np.float64)[corner_pixel]
    tangent = chart_tangents(rest_points, np.asarray(faces, dtype=np.int64), corner_uv, corner_pixel,
                             pixels.pixel_count)
    coefficients = edge_coefficients(tangent, rest_tri[pixel_vertex])
    return BodyEmbedding(body_faces, body_face, body_bary, pixel_vertex, coefficients)
