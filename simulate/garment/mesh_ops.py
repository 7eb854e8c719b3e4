"""Triangle-mesh operations the garment layer needs, in numpy/scipy: cutting a mesh
along the zero set of a scalar field, midpoint subdivision that keeps an embedding in
the body's triangles, boundary loops, manifold checks, connected components, closest
points on a mesh and normal/attribute smoothing.

Meshes are (vertices (V, 3) [m], faces (F, 3) int). Every function is deterministic.
"""
from __future__ import annotations

import functools

import numpy as np
from scipy import sparse


# ------------------------------------------------------------------------- topology
def unique_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges of a triangle mesh.

    Returns:
        (edges (E, 2) sorted vertex pairs, face_edge (F, 3): index of edge
        (corner k, corner k+1) of each face).
    """
    f = np.asarray(faces, dtype=np.int64)
    half = np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2)  # (3F, 2): (c0,c1),(c1,c2),(c2,c0)
    key = np.sort(half, axis=1)
    n = int(f.max()) + 1 if f.size else 1
    scalar = key[:, 0] * n + key[:, 1]  # 1-D keys: much faster than np.unique(axis=0)
    uniq, inverse = np.unique(scalar, return_inverse=True)
    edges = np.stack([uniq // n, uniq % n], axis=1)
    return edges, inverse.reshape(-1, 3)


def edge_face_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges (E, 2) and how many faces use each, shape (E,)."""
    edges, fe = unique_edges(faces)
    return edges, np.bincount(fe.ravel(), minlength=len(edges))


def boundary_edges_directed(faces: np.ndarray) -> np.ndarray:
    """Boundary half-edges (B, 2), oriented as in their single face."""
    f = np.asarray(faces, dtype=np.int64)
    half = np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2)
    _, fe = unique_edges(f)
    counts = np.bincount(fe.ravel())
    return half[counts[fe.ravel()] == 1]


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops as ordered vertex index arrays, longest first.

    Raises ValueError if the boundary is not a disjoint union of simple loops (a vertex
    with more than one outgoing boundary edge).
    """
    half = boundary_edges_directed(faces)
    if len(half) == 0:
        return []
    starts, counts = np.unique(half[:, 0], return_counts=True)
    if (counts > 1).any():
        raise ValueError(f"boundary is not a set of simple loops: vertex {int(starts[counts > 1][0])} "
                         f"starts {int(counts.max())} boundary edges")
    nxt = dict(zip(half[:, 0].tolist(), half[:, 1].tolist()))
    seen: set[int] = set()
    loops = []
    for start in half[:, 0].tolist():
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        cur = nxt[start]
        while cur != start:
            if cur in seen or cur not in nxt:
                raise ValueError(f"boundary is not a set of simple loops near vertex {cur}")
            loop.append(cur)
            seen.add(cur)
            cur = nxt[cur]
        loops.append(np.array(loop, dtype=np.int64))
    loops.sort(key=len, reverse=True)
    return loops


def face_components(faces: np.ndarray) -> np.ndarray:
    """Connected-component label per face (faces sharing an edge are connected), shape (F,)."""
    edges, fe = unique_edges(faces)
    f_count = len(faces)
    rows = np.repeat(np.arange(f_count), 3)
    inc = sparse.csr_matrix((np.ones(3 * f_count), (rows, fe.ravel())), shape=(f_count, len(edges)))
    adj = inc @ inc.T
    _, labels = sparse.csgraph.connected_components(adj, directed=False)
    return labels


def nonmanifold_vertices(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """Vertices whose incident faces do not form one edge-connected fan, shape (K,)."""
    f = np.asarray(faces, dtype=np.int64)
    edges, fe = unique_edges(f)
    counts = np.bincount(fe.ravel(), minlength=len(edges))
    vert_faces = np.bincount(f.ravel(), minlength=vertex_count)
    inner = counts == 2
    vert_inner_edges = np.bincount(edges[inner].ravel(), minlength=vertex_count)
    vert_bnd_edges = np.bincount(edges[counts == 1].ravel(), minlength=vertex_count)
    # A single fan around an interior vertex: faces == inner edges; around a boundary
    # vertex: faces == inner edges + 1 and exactly 2 boundary edges.
    interior_ok = (vert_bnd_edges == 0) & (vert_faces == vert_inner_edges)
    boundary_ok = (vert_bnd_edges == 2) & (vert_faces == vert_inner_edges + 1)
    used = vert_faces > 0
    bad = np.nonzero(used & ~(interior_ok | boundary_ok))[0]
    if (counts > 2).any():
        bad = np.union1d(bad, edges[counts > 2].ravel())
    return bad


def is_manifold(faces: np.ndarray, vertex_count: int) -> tuple[bool, str]:
    """(ok, reason): every edge in 1 or 2 faces and every vertex a single fan."""
    _, counts = edge_face_counts(faces)
    if (counts > 2).any():
        return False, f"{int((counts > 2).sum())} edges are shared by more than 2 faces"
    bad = nonmanifold_vertices(faces, vertex_count)
    if len(bad):
        return False, f"{len(bad)} non-manifold vertices (first {int(bad[0])})"
    return True, "manifold"


def remove_unused_vertices(faces: np.ndarray, vertex_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Re-indexes faces onto the used vertices. Returns (faces', kept vertex indices (V',))."""
    used = np.unique(faces)
    remap = np.full(vertex_count, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return remap[faces], used


def clean_submesh(faces: np.ndarray, vertex_count: int, *, max_rounds: int = 50) -> np.ndarray:
    """Keeps the largest edge-connected component and removes ears and non-manifold fans
    until the boundary is a set of simple loops. Returns a bool mask over the input faces."""
    keep = np.ones(len(faces), dtype=bool)
    for _ in range(max_rounds):
        f = faces[keep]
        idx = np.nonzero(keep)[0]
        labels = face_components(f)
        largest = np.argmax(np.bincount(labels))
        changed = False
        if (labels != largest).any():
            keep[idx[labels != largest]] = False
            changed = True
            f = faces[keep]
            idx = np.nonzero(keep)[0]
        # Ears: faces with 2 or 3 boundary edges (dangling triangles along a cut).
        edges, fe = unique_edges(f)
        counts = np.bincount(fe.ravel(), minlength=len(edges))
        boundary_per_face = (counts[fe] == 1).sum(1)
        ears = boundary_per_face >= 2
        if ears.any():
            keep[idx[ears]] = False
            continue
        bad = nonmanifold_vertices(f, vertex_count)
        if len(bad):
            # Drop the smaller fans: remove every face touching a bad vertex except the
            # ones in the largest component once that vertex is removed.
            touching = np.isin(f, bad).any(1)
            keep[idx[touching]] = False
            continue
        if not changed:
            break
    return keep


# ------------------------------------------------------------------------- cutting
def cut_by_field(
    vertices: np.ndarray,
    faces: np.ndarray,
    field: np.ndarray,
    *,
    face_bary: np.ndarray | None = None,
    snap: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cuts a mesh along the zero set of a per-vertex scalar field and keeps field <= 0.

    Triangles crossing the zero set are split at linearly interpolated edge points, so
    the new boundary follows the level set exactly (planar for a plane's distance).

    Args:
        vertices: (V, 3) [m]; faces: (F, 3).
        field: per-vertex values (V,); the kept side is field <= 0 [any unit].
        face_bary: optional per-face-corner barycentric coordinates in a parent
            triangle, (F, 3, 3); cut points get interpolated coordinates.
        snap: vertices with |field| < snap are moved onto the zero set first (field = 0)
            so no sliver triangles appear [same unit as field].
    Returns:
        (vertices' (V', 3), faces' (F', 3), face_parent (F',) index of the input face each
        output face came from, face_bary' (F', 3, 3) or empty, vertex_source (V', 2)
        input vertex pair (a, a) for an old vertex, (a, b) for a cut point on edge ab,
        with vertex_t (V',) the interpolation weight of b) -- the last two packed as
        (source (V', 2), t (V',)) in a tuple in position 4.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    d = np.asarray(field, dtype=np.float64).copy()
    d[np.abs(d) < snap] = 0.0
    sign = np.sign(d).astype(np.int64)  # -1 keep, 0 on the cut, +1 remove
    s = sign[f]  # (F, 3)
    keep_all = (s <= 0).all(1) & (s < 0).any(1)
    mixed = (s < 0).any(1) & (s > 0).any(1)

    new_points: dict[tuple[int, int], int] = {}
    src_a = list(range(len(v)))
    src_b = list(range(len(v)))
    src_t = [0.0] * len(v)

    def cut_point(a: int, b: int) -> int:
        key = (a, b) if a < b else (b, a)
        if key not in new_points:
            t = d[key[0]] / (d[key[0]] - d[key[1]])
            new_points[key] = len(src_a)
            src_a.append(key[0])
            src_b.append(key[1])
            src_t.append(float(t))
        return new_points[key]

    out_faces = [f[keep_all]]
    out_parent = [np.nonzero(keep_all)[0]]
    extra_faces = []
    extra_parent = []
    for fi in np.nonzero(mixed)[0]:
        tri = f[fi]
        sg = s[fi]
        # rotate so the polygon walk starts at a kept vertex
        poly = []
        for k in range(3):
            a, b = tri[k], tri[(k + 1) % 3]
            if sg[k] <= 0:
                poly.append(a)
            if sg[k] * sg[(k + 1) % 3] < 0:
                poly.append(cut_point(int(a), int(b)))
        for k in range(1, len(poly) - 1):
            extra_faces.append((poly[0], poly[k], poly[k + 1]))
            extra_parent.append(fi)
    if extra_faces:
        out_faces.append(np.array(extra_faces, dtype=np.int64))
        out_parent.append(np.array(extra_parent, dtype=np.int64))
    new_f = np.concatenate(out_faces)
    parent = np.concatenate(out_parent)
    src = np.stack([np.array(src_a), np.array(src_b)], axis=1)
    t = np.array(src_t)
    new_v = v[src[:, 0]] * (1 - t[:, None]) + v[src[:, 1]] * t[:, None]
    # drop degenerate faces (a corner repeated)
    good = (new_f[:, 0] != new_f[:, 1]) & (new_f[:, 1] != new_f[:, 2]) & (new_f[:, 2] != new_f[:, 0])
    new_f, parent = new_f[good], parent[good]
    bary_out = np.zeros((0, 3, 3))
    if face_bary is not None:
        bary_out = corner_bary_from_parent(f, np.asarray(face_bary, dtype=np.float64), new_f, parent, src, t)
    return new_v, new_f, parent, bary_out, (src, t)


def corner_bary_from_parent(
    faces: np.ndarray, face_bary: np.ndarray, new_faces: np.ndarray, parent: np.ndarray,
    src: np.ndarray, t: np.ndarray,
) -> np.ndarray:
    """Per-corner barycentrics (F', 3, 3) of new faces inside their parents' parent
    triangles, for vertices that are old vertices or points on old edges."""
    out = np.zeros((len(new_faces), 3, 3))
    for k in range(3):
        vid = new_faces[:, k]
        a, b, tt = src[vid, 0], src[vid, 1], t[vid]
        pf = faces[parent]  # (F', 3)
        ka = np.argmax(pf == a[:, None], axis=1)
        kb = np.argmax(pf == b[:, None], axis=1)
        ba = face_bary[parent, ka]
        bb = face_bary[parent, kb]
        out[:, k] = ba * (1 - tt[:, None]) + bb * tt[:, None]
    return out


def midpoint_subdivide(
    vertices: np.ndarray, faces: np.ndarray, face_bary: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """1-to-4 midpoint subdivision (positions stay on the flat input triangles).

    Returns:
        (vertices' (V + E, 3), faces' (4F, 3), face_parent (4F,), face_bary' (4F, 3, 3)
        per-corner barycentrics in the parent's parent triangle, or empty).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    edges, fe = unique_edges(f)
    mid = len(v) + fe  # (F, 3): midpoint vertex of edge (ck, ck+1)
    new_v = np.concatenate([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])])
    c0, c1, c2 = f[:, 0], f[:, 1], f[:, 2]
    m01, m12, m20 = mid[:, 0], mid[:, 1], mid[:, 2]
    new_f = np.concatenate([
        np.stack([c0, m01, m20], 1), np.stack([m01, c1, m12], 1),
        np.stack([m20, m12, c2], 1), np.stack([m01, m12, m20], 1),
    ])
    parent = np.tile(np.arange(len(f)), 4)
    bary_out = np.zeros((0, 3, 3))
    if face_bary is not None:
        b = np.asarray(face_bary, dtype=np.float64)
        b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
        h01, h12, h20 = 0.5 * (b0 + b1), 0.5 * (b1 + b2), 0.5 * (b2 + b0)
        bary_out = np.concatenate([
            np.stack([b0, h01, h20], 1), np.stack([h01, b1, h12], 1),
            np.stack([h20, h12, b2], 1), np.stack([h01, h12, h20], 1),
        ])
    return new_v, new_f, parent, bary_out


# ------------------------------------------------------------------------- geometry
def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit face normals (F, 3) (zero for degenerate faces)."""
    tri = np.asarray(vertices, dtype=np.float64)[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def vertex_adjacency(faces: np.ndarray, vertex_count: int) -> sparse.csr_matrix:
    """Symmetric 0/1 vertex adjacency (V, V) from the faces' edges."""
    edges, _ = unique_edges(faces)
    ij = np.concatenate([edges, edges[:, ::-1]])
    return sparse.csr_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(vertex_count, vertex_count))


def uniform_laplacian(faces: np.ndarray, vertex_count: int, *, boundary_aware: bool = True) -> sparse.csr_matrix:
    """Uniform graph Laplacian L = A_normalized - I, shape (vertex_count, vertex_count).

    Row i of ``L @ x`` is the mean of the neighbours of vertex i minus x_i. With
    ``boundary_aware`` (TailorNet's choice), a vertex on an open boundary averages only its
    neighbours along boundary edges, so smoothing slides the boundary along itself instead
    of shrinking it inward. Vertices referenced by no face have an all-zero row (they stay put).
    """
    edges, counts = edge_face_counts(faces)
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    if boundary_aware:
        # interior rows keep all their edges, boundary rows only their boundary edges
        on_boundary = np.zeros(vertex_count, dtype=bool)
        on_boundary[edges[counts == 1].ravel()] = True
        keep = ~on_boundary[rows] | np.concatenate([counts == 1, counts == 1])
        rows, cols = rows[keep], cols[keep]
    adjacency = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(vertex_count, vertex_count))
    degree = np.asarray(adjacency.sum(axis=1)).reshape(-1)
    inverse_degree = np.where(degree > 0, 1.0 / np.maximum(degree, 1.0), 0.0)
    return sparse.csr_matrix(sparse.diags(inverse_degree) @ adjacency - sparse.diags((degree > 0).astype(np.float64)))


def smooth_vertex_values(values: np.ndarray, faces: np.ndarray, *, iterations: int = 10,
                         lam: float = 0.5, fixed: np.ndarray | None = None) -> np.ndarray:
    """Uniform-Laplacian diffusion of per-vertex values (V, C): x += lam * (mean(nbrs) - x).

    ``fixed`` (bool (V,)) keeps those vertices unchanged.
    """
    x = np.asarray(values, dtype=np.float64).copy()
    adj = vertex_adjacency(faces, len(x))
    deg = np.asarray(adj.sum(1)).ravel()
    deg[deg == 0] = 1.0
    for _ in range(iterations):
        avg = (adj @ x) / deg[:, None]
        step = lam * (avg - x)
        if fixed is not None:
            step[fixed] = 0.0
        x += step
    return x


def smooth_normals(vertices: np.ndarray, faces: np.ndarray, *, iterations: int = 10) -> np.ndarray:
    """Area-weighted vertex normals, diffused over the mesh and renormalised, (V, 3)."""
    from simulate.body.mesh_utils import vertex_normals

    n = vertex_normals(vertices, faces).astype(np.float64)
    n = smooth_vertex_values(n, faces, iterations=iterations, lam=0.5)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on triangles (a, b, c) to points p, all (..., 3); returns
    (points (..., 3), barycentrics (..., 3)). Ericson's region test, vectorised."""
    ab, ac, ap = b - a, c - a, p - a
    d1 = (ab * ap).sum(-1)
    d2 = (ac * ap).sum(-1)
    bp = p - b
    d3 = (ab * bp).sum(-1)
    d4 = (ac * bp).sum(-1)
    cp = p - c
    d5 = (ab * cp).sum(-1)
    d6 = (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    eps = 1e-30
    denom = va + vb + vc
    v_in = vb / np.where(np.abs(denom) > eps, denom, eps)
    w_in = vc / np.where(np.abs(denom) > eps, denom, eps)
    bary = np.stack([1 - v_in - w_in, v_in, w_in], -1)
    # edge regions
    t_ab = d1 / np.where(np.abs(d1 - d3) > eps, d1 - d3, eps)
    t_ac = d2 / np.where(np.abs(d2 - d6) > eps, d2 - d6, eps)
    t_bc = (d4 - d3) / np.where(np.abs((d4 - d3) + (d5 - d6)) > eps, (d4 - d3) + (d5 - d6), eps)
    regions = [
        ((d1 <= 0) & (d2 <= 0), np.stack([np.ones_like(d1), 0 * d1, 0 * d1], -1)),
        ((d3 >= 0) & (d4 <= d3), np.stack([0 * d1, np.ones_like(d1), 0 * d1], -1)),
        ((d6 >= 0) & (d5 <= d6), np.stack([0 * d1, 0 * d1, np.ones_like(d1)], -1)),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - t_ab, t_ab, 0 * d1], -1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - t_ac, 0 * d1, t_ac], -1)),
        ((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([0 * d1, 1 - t_bc, t_bc], -1)),
    ]
    done = np.zeros(d1.shape, dtype=bool)
    for cond, bc in regions:
        sel = cond & ~done
        bary[sel] = bc[sel]
        done |= sel
    pts = bary[..., 0:1] * a + bary[..., 1:2] * b + bary[..., 2:3] * c
    return pts, bary


@functools.cache
def _closest_point_kernel():
    import warp as wp

    @wp.kernel(enable_backward=False)
    def closest_points_on_mesh(mesh: wp.uint64, points: wp.array(dtype=wp.vec3d), max_distance: float,
                               face_out: wp.array(dtype=wp.int32), bary_out: wp.array(dtype=wp.vec3d)):
        tid = wp.tid()
        p = points[tid]
        query = wp.mesh_query_point_no_sign(mesh, wp.vec3(float(p[0]), float(p[1]), float(p[2])), max_distance)
        if query.result:
            face_out[tid] = query.face
            bary_out[tid] = wp.vec3d(wp.float64(query.u), wp.float64(query.v), wp.float64(1.0 - query.u - query.v))
        else:
            face_out[tid] = -1

    return closest_points_on_mesh


class ClosestPointQuery:
    """Closest points on a fixed triangle mesh for many query points.

    A Warp BVH (on the CPU) finds each point's closest triangle; the closest point itself is then
    taken again in float64 on that triangle (Ericson's region test), so it is exact up to float32
    ties between triangles at the same distance. It replaced a KD-tree over triangle centroids
    (16 candidates per point, exact only for uniform triangles) that took ~60 s of the TailorNet
    spec's 75 s of style drapes on the device host.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, max_distance: float = 1.0e3) -> None:
        import warp as wp

        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"faces must have shape (F, 3) with F > 0 (got {self.faces.shape})")
        self.normals = face_normals(self.vertices, self.faces)
        self.max_distance = float(max_distance)
        self._points = wp.array(self.vertices.astype(np.float32), dtype=wp.vec3, device="cpu")
        self._mesh = wp.Mesh(self._points, wp.array(self.faces.astype(np.int32).ravel(), dtype=wp.int32, device="cpu"))

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Returns (closest points (N, 3) [m], face index (N,), barycentrics (N, 3),
        signed distance (N,) [m] along the closest face's normal: negative inside)."""
        import warp as wp

        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = len(p)
        face_d = wp.zeros(n, dtype=wp.int32, device="cpu")
        bary_d = wp.zeros(n, dtype=wp.vec3d, device="cpu")
        wp.launch(_closest_point_kernel(), dim=n, device="cpu",
                  inputs=[self._mesh.id, wp.array(p, dtype=wp.vec3d, device="cpu"), self.max_distance],
                  outputs=[face_d, bary_d])
        face = face_d.numpy().astype(np.int64)
        if (face < 0).any():
            raise ValueError(f"{int((face < 0).sum())} query points are farther than max_distance "
                             f"{self.max_distance} m from the mesh")
        tri = self.vertices[self.faces[face]]  # (N, 3, 3)
        closest, bary = closest_points_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
        dist = np.linalg.norm(p - closest, axis=-1)
        sign = np.sign(((p - closest) * self.normals[face]).sum(-1))
        sign[sign == 0] = 1.0
        return closest, face, bary, sign * dist


def collapse_short_edges(vertices: np.ndarray, faces: np.ndarray, min_length: float, *, max_passes: int = 10
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Collapses edges shorter than ``min_length`` [m] into one endpoint (a boundary
    endpoint when there is one), only where the collapse keeps the mesh manifold (link
    condition) and never joining two boundary vertices through the interior.

    Returns:
        (faces' (F', 3) over the same vertex array, kept vertex mask (V,)).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).copy()
    for _ in range(max_passes):
        edges, fe = unique_edges(f)
        counts = np.bincount(fe.ravel(), minlength=len(edges))
        on_boundary = np.zeros(len(v), dtype=bool)
        on_boundary[edges[counts == 1].ravel()] = True
        length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
        short = np.nonzero(length < min_length)[0]
        if len(short) == 0:
            break
        short = short[np.argsort(length[short])]
        csr = vertex_adjacency(f, len(v))

        def nbrs(i: int) -> list[int]:
            return csr.indices[csr.indptr[i]:csr.indptr[i + 1]].tolist()
        touched = np.zeros(len(v), dtype=bool)
        target = np.arange(len(v))
        done = 0
        for e in short:
            a, b = edges[e]
            if touched[a] or touched[b]:
                continue
            boundary_edge = counts[e] == 1
            if on_boundary[a] and on_boundary[b] and not boundary_edge:
                continue
            na, nb = nbrs(a), nbrs(b)
            common = set(na) & set(nb)
            if len(common) != (1 if boundary_edge else 2):
                continue
            keep, drop = (b, a) if (on_boundary[b] and not on_boundary[a]) else (a, b)
            target[drop] = keep
            touched[na + nb + [a, b]] = True
            done += 1
        if done == 0:
            break
        f = target[f]
        good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
        f = f[good]
    kept = np.zeros(len(v), dtype=bool)
    kept[f.ravel()] = True
    return f, kept


# ------------------------------------------------------------------------- sewing
def sew_loops(vertices_a: np.ndarray, faces_a: np.ndarray, loop_a: np.ndarray, vertices_b: np.ndarray,
              faces_b: np.ndarray, loop_b: np.ndarray, *, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sews mesh b to mesh a along a boundary loop of each: the loops' vertices are matched one
    to one (b's loop is shifted and, if need be, reversed so that corresponding vertices are
    nearest) and b's are merged into a's, so the seam has no duplicate vertices.

    b's faces are reversed when its orientation disagrees with a's across the seam (a seam
    half-edge running the same way in both), so the sewn mesh is consistently oriented like a.

    Args:
        vertices_a, faces_a, loop_a: mesh a [m] (Va, 3), (Fa, 3) and its ordered boundary loop (N,).
        vertices_b, faces_b, loop_b: mesh b and its loop, of the same length N.
        tolerance: largest distance [m] between matched loop vertices.
    Returns:
        (vertices (Va + Vb - N, 3): a's then b's non-seam vertices in their order, faces
        (Fa + Fb, 3): a's then b's, index_b (Vb,): each b vertex's index in the sewn mesh).
    Raises:
        ValueError when the loops differ in length or a matched pair is farther apart than
        ``tolerance``.
    """
    la, lb = np.asarray(loop_a, np.int64), np.asarray(loop_b, np.int64)
    va, vb = np.asarray(vertices_a, np.float64), np.asarray(vertices_b, np.float64)
    if len(la) != len(lb) or len(la) < 3:
        raise ValueError(f"seam loops must have the same length >= 3, got {len(la)} and {len(lb)} vertices")
    best = (np.inf, None)
    for order in (lb, lb[::-1]):
        k = int(np.argmin(np.linalg.norm(vb[order] - va[la[0]], axis=1)))
        cand = np.roll(order, -k)
        gap = float(np.linalg.norm(va[la] - vb[cand], axis=1).max())
        if gap < best[0]:
            best = (gap, cand)
    gap, matched = best
    if gap > tolerance:
        raise ValueError(f"seam loops do not match: matched vertices are up to {gap:.3g} m apart "
                         f"(tolerance {tolerance:.3g} m)")
    index_b = np.full(len(vb), -1, np.int64)
    index_b[matched] = la
    rest = np.setdiff1d(np.arange(len(vb)), matched)
    index_b[rest] = len(va) + np.arange(len(rest))
    fa = np.asarray(faces_a, np.int64)
    fb = index_b[np.asarray(faces_b, np.int64)]

    def half_edges(f: np.ndarray) -> set[tuple[int, int]]:
        return set(map(tuple, np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2).tolist()))

    seam = set(zip(la.tolist(), np.roll(la, -1).tolist())) | set(zip(np.roll(la, -1).tolist(), la.tolist()))
    along_a = half_edges(fa) & seam
    if along_a & half_edges(fb):
        fb = fb[:, ::-1]
    return np.concatenate([va, vb[rest]]), np.concatenate([fa, fb]), index_b


def oriented_consistently(faces: np.ndarray) -> bool:
    """True when every edge shared by two faces is traversed in opposite directions by them."""
    f = np.asarray(faces, np.int64)
    half = np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2)
    _, counts = np.unique(half, axis=0, return_counts=True)
    return bool((counts == 1).all())
