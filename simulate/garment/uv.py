"""UV charts of garment templates and the per-vertex <-> UV-image transfer used by the
UV-image learner (seed 001: garment values stored as images on "cloth pixels").

Layout. Faces are split into a ``front`` and a ``back`` panel by the sign of the z
component of heavily smoothed normals (the seam runs along the sides of the torso and
limbs and over the shoulders, like a side-seam pattern); trousers (pants, shorts) are
also split at x = 0 into one front and one back piece per leg, as trouser patterns are. Each panel is flattened by a
least-squares conformal map (LSCM, Levy et al. 2002; sparse normal equations, two pinned
vertices, scale kept metric), refined by as-rigid-as-possible iterations (ARAP, Liu et
al. 2008) and untangled (local Laplacian relaxation of any flipped triangle), then the panels are packed into [0, 1]^2 with one common
scale (uniform texel density) and a margin between them.

Storage. Seam vertices belong to two panels, so UVs are kept per face corner
(``template.face_uv`` (F, 3, 2)); ``template.uv`` (V, 2) is each vertex's UV in its first
panel (its main chart). Rasterization uses the per-corner UVs, sampling averages a
vertex's samples over all its corners.

Image convention: images are (N, C, H, W); pixel (row, col) has its centre at
u = (col + 0.5) / W, v = 1 - (row + 0.5) / H (v up, row 0 at the top).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg  # noqa: F401  (sparse.linalg.factorized)
from scipy import sparse
from scipy.sparse.linalg import spsolve

from simulate.garment import mesh_ops

PANEL_NAMES = ("front", "back")
#: Local/global ARAP iterations after the LSCM initialisation.
ARAP_ITERATIONS = 15
#: Raster size of the per-panel overlap check.
OVERLAP_CHECK_SIZE = 1024
#: Gap between panels and around the atlas, in UV units.
UV_MARGIN = 0.03


def face_neighbours(faces: np.ndarray) -> np.ndarray:
    """Edge-adjacent face of each face edge (F, 3), -1 on the boundary."""
    _, fe = mesh_ops.unique_edges(faces)
    flat = fe.ravel()
    order = np.argsort(flat, kind="stable")
    sorted_e = flat[order]
    nbr = np.full(flat.shape, -1, dtype=np.int64)
    same = sorted_e[1:] == sorted_e[:-1]
    a, b = order[:-1][same], order[1:][same]
    nbr[a] = b // 3
    nbr[b] = a // 3
    return nbr.reshape(-1, 3)


def split_panels(vertices: np.ndarray, faces: np.ndarray, *, smoothing: int = 80, split_x: bool = False) -> np.ndarray:
    """Panel per face (F,): 0 front, 1 back (z component of vertex normals diffused over
    the mesh for ``smoothing`` iterations, so the seam follows the sides of the torso and
    limbs); with ``split_x`` also left/right (x >= 0 / x < 0): 0 front-left, 1 front-right,
    2 back-left, 3 back-right (trouser patterns are one piece per leg and side).

    Then, until nothing changes, faces with two or more edges on a seam toward the same
    panel ("ears" of a staircase seam) and components smaller than their panel's largest
    move to the neighbouring panel.
    """
    n = mesh_ops.smooth_normals(vertices, faces, iterations=smoothing)
    panel = (n[faces, 2].mean(1) < 0).astype(np.int64)
    if split_x:
        panel = 2 * panel + (np.asarray(vertices)[faces, 0].mean(1) < 0)
    count = int(panel.max()) + 1
    nbr = face_neighbours(faces)
    for _ in range(50):
        changed = False
        nb_panel = np.where(nbr >= 0, panel[np.maximum(nbr, 0)], -1)  # (F, 3)
        for target in range(count):
            votes = ((nb_panel == target) & (panel[:, None] != target)).sum(1)
            ears = votes >= 2
            if ears.any():
                panel[ears] = target
                changed = True
                nb_panel = np.where(nbr >= 0, panel[np.maximum(nbr, 0)], -1)
        for p in range(count):
            idx = np.nonzero(panel == p)[0]
            if len(idx) == 0:
                continue
            labels = mesh_ops.face_components(faces[idx])
            sizes = np.bincount(labels)
            if len(sizes) > 1:
                small = idx[labels != np.argmax(sizes)]
                nb = nb_panel[small]
                for fi, row in zip(small, nb):
                    cand = row[(row >= 0) & (row != p)]
                    panel[fi] = np.bincount(cand).argmax() if len(cand) else (p + 1) % count
                changed = True
        if not changed:
            break
    return panel


def lscm(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Least-squares conformal map of a disk-like mesh: UV (V, 2) in metres-like units.

    Pins the two vertices farthest apart along the mesh's principal axis, at their true
    3D distance, so the chart keeps the metric scale. Orientation is made positive
    (counter-clockwise for outward faces seen from outside).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1 = p1 - p0
    l1 = np.linalg.norm(e1, axis=1)
    e1 = e1 / np.maximum(l1, 1e-15)[:, None]
    n = np.cross(p1 - p0, p2 - p0)
    area2 = np.linalg.norm(n, axis=1)
    n = n / np.maximum(area2, 1e-15)[:, None]
    e2 = np.cross(n, e1)
    x = np.stack([np.zeros(len(f)), l1, ((p2 - p0) * e1).sum(1)], 1)
    y = np.stack([np.zeros(len(f)), np.zeros(len(f)), ((p2 - p0) * e2).sum(1)], 1)
    scale = 1.0 / np.sqrt(np.maximum(area2, 1e-15))
    a = (np.roll(x, -2, axis=1) - np.roll(x, -1, axis=1)) * scale[:, None]  # x_{j+2} - x_{j+1}
    b = (np.roll(y, -2, axis=1) - np.roll(y, -1, axis=1)) * scale[:, None]
    nv = len(v)
    rows_r = np.repeat(np.arange(len(f)), 3)
    rows_i = rows_r + len(f)
    cols = f.ravel()
    # Real: sum a u - b v ; Imag: sum b u + a v
    data = np.concatenate([a.ravel(), -b.ravel(), b.ravel(), a.ravel()])
    rr = np.concatenate([rows_r, rows_r, rows_i, rows_i])
    cc = np.concatenate([cols, cols + nv, cols, cols + nv])
    mat = sparse.csr_matrix((data, (rr, cc)), shape=(2 * len(f), 2 * nv))
    # Pins: extremes along the principal axis.
    centred = v - v.mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    proj = centred @ axis
    i0, i1 = int(np.argmin(proj)), int(np.argmax(proj))
    dist = float(np.linalg.norm(v[i1] - v[i0]))
    pins = np.array([i0, i1, i0 + nv, i1 + nv])
    pin_values = np.array([0.0, dist, 0.0, 0.0])
    free = np.setdiff1d(np.arange(2 * nv), pins)
    a_free = mat[:, free]
    rhs = -(mat[:, pins] @ pin_values)
    sol = spsolve((a_free.T @ a_free).tocsc(), a_free.T @ rhs)
    full = np.zeros(2 * nv)
    full[free] = sol
    full[pins] = pin_values
    uv = np.stack([full[:nv], full[nv:]], 1)
    if signed_areas(uv, f).sum() < 0:
        uv[:, 1] = -uv[:, 1]
    return uv


def chart_overlaps(uv: np.ndarray, faces: np.ndarray, *, size: int = OVERLAP_CHECK_SIZE) -> int:
    """Pixel centres covered by 2+ triangles when the chart fills a size x size raster."""
    c = uv - uv.min(0)
    c = 0.02 + 0.96 * c / max(float(c.max()), 1e-15)
    return int((pixel_map(c[faces], size)[2] > 1).sum())


def flatten_panel(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """LSCM, then ARAP refinement, untangled; the most ARAP iterations (of
    ARAP_ITERATIONS, ARAP_ITERATIONS // 3, 0) whose chart has no flipped triangles and no
    overlaps is kept (ARAP can fold a boundary over itself; LSCM with untangling rarely does)."""
    base = lscm(vertices, faces)
    for iterations in (ARAP_ITERATIONS, ARAP_ITERATIONS // 3, 0):
        uv = untangle(arap(vertices, faces, base, iterations=iterations) if iterations else base, faces)
        if (signed_areas(uv, faces) > 0).all() and chart_overlaps(uv, faces) == 0:
            return uv
    return uv


def arap(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, *, iterations: int = ARAP_ITERATIONS) -> np.ndarray:
    """As-rigid-as-possible refinement of a chart (Liu et al. 2008 local/global):
    per-triangle best rotations, then one sparse cotangent-Laplacian solve per
    iteration; removes most of a conformal map's area distortion. (V, 2) -> (V, 2)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1 = p1 - p0
    l1 = np.maximum(np.linalg.norm(e1, axis=1), 1e-15)
    e1 = e1 / l1[:, None]
    n = np.cross(p1 - p0, p2 - p0)
    n = n / np.maximum(np.linalg.norm(n, axis=1), 1e-15)[:, None]
    e2 = np.cross(n, e1)
    local = np.zeros((len(f), 3, 2))  # isometric flattening of each triangle
    local[:, 1, 0] = l1
    local[:, 2, 0] = ((p2 - p0) * e1).sum(1)
    local[:, 2, 1] = ((p2 - p0) * e2).sum(1)
    # cotangent of the angle at corner k weights the opposite edge (k+1, k+2)
    cot = np.zeros((len(f), 3))
    for k in range(3):
        a = local[:, (k + 1) % 3] - local[:, k]
        b = local[:, (k + 2) % 3] - local[:, k]
        cross = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
        cot[:, k] = np.clip((a * b).sum(1) / np.maximum(cross, 1e-15), 1e-3, 1e3)
    i_idx = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    j_idx = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    w = np.concatenate([cot[:, 0], cot[:, 1], cot[:, 2]])
    nv = len(v)
    lap = sparse.csr_matrix((np.concatenate([w, w, -w, -w]),
                             (np.concatenate([i_idx, j_idx, i_idx, j_idx]), np.concatenate([i_idx, j_idx, j_idx, i_idx]))),
                            shape=(nv, nv))
    lap = lap + sparse.identity(nv) * 1e-9  # fixes the free translation
    solve = sparse.linalg.factorized(lap.tocsc())
    u = np.asarray(uv, dtype=np.float64).copy()
    ci = [(1, 2), (2, 0), (0, 1)]  # edge opposite corner k
    for _ in range(iterations):
        cov = np.zeros((len(f), 2, 2))
        for k, (a, b) in enumerate(ci):
            du = u[f[:, a]] - u[f[:, b]]
            dx = local[:, a] - local[:, b]
            cov += cot[:, k, None, None] * du[:, :, None] * dx[:, None, :]
        uu, _, vt = np.linalg.svd(cov)
        rot = uu @ vt
        flip = np.linalg.det(rot) < 0
        uu[flip, :, 1] *= -1
        rot = uu @ vt
        rhs = np.zeros((nv, 2))
        for k, (a, b) in enumerate(ci):
            r = cot[:, k, None] * np.einsum("fij,fj->fi", rot, local[:, a] - local[:, b])
            np.add.at(rhs, f[:, a], r)
            np.add.at(rhs, f[:, b], -r)
        centre = u.mean(0)
        u = np.stack([solve(rhs[:, 0]), solve(rhs[:, 1])], 1)
        u += centre - u.mean(0)
    return u


def untangle(uv: np.ndarray, faces: np.ndarray, *, max_rounds: int = 200) -> np.ndarray:
    """Removes flipped UV triangles by local Laplacian relaxation: the vertices of flipped
    triangles and their neighbours move toward their neighbours' mean, growing the region
    until no triangle is flipped (or ``max_rounds`` is reached)."""
    uv = uv.copy()
    adj = mesh_ops.vertex_adjacency(faces, len(uv))
    deg = np.maximum(np.asarray(adj.sum(1)).ravel(), 1)
    ring = 1
    for r in range(max_rounds):
        flipped = signed_areas(uv, faces) <= 0
        if not flipped.any():
            break
        region = np.zeros(len(uv), dtype=bool)
        region[faces[flipped].ravel()] = True
        for _ in range(ring):
            region |= (adj @ region.astype(np.float64)) > 0
        for _ in range(5):
            avg = (adj @ uv) / deg[:, None]
            uv[region] = 0.5 * uv[region] + 0.5 * avg[region]
        if r % 20 == 19:
            ring += 1
    return uv


def signed_areas(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed areas (F,) of triangles in UV (positive = counter-clockwise). ``uv`` is (V, 2)
    indexed by ``faces``, or per-corner (F, 3, 2) when ``faces`` is None."""
    t = uv if faces is None else uv[faces]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


def _orient_panel(uv: np.ndarray, vertices: np.ndarray, panel: int) -> np.ndarray:
    """Rotates a chart so its up direction matches the body's +y (garment hangs upright)."""
    c = uv - uv.mean(0)
    y3 = vertices[:, 1] - vertices[:, 1].mean()
    # best rotation aligning chart with the 3D (x or -x, y) projection: least squares
    target_x = vertices[:, 0] - vertices[:, 0].mean()
    if panel == 1:
        target_x = -target_x
    target = np.stack([target_x, y3], 1)
    m = c.T @ target
    u, _, vt = np.linalg.svd(m)
    rot = u @ vt
    if np.linalg.det(rot) < 0:  # keep orientation (no reflection)
        u[:, -1] = -u[:, -1]
        rot = u @ vt
    return c @ rot


def _pack(sizes: np.ndarray) -> tuple[float, np.ndarray]:
    """Common scale and lower-left offsets (P, 2) placing panels of (width, height)
    ``sizes`` in rows (in order) inside [0, 1]^2 with UV_MARGIN gaps; the row count
    with the largest scale wins."""
    count = len(sizes)
    best = (-1.0, None)
    for rows in range(1, count + 1):
        per_row = int(np.ceil(count / rows))
        groups = [list(range(i, min(i + per_row, count))) for i in range(0, count, per_row)]
        widths = [sizes[g, 0].sum() for g in groups]
        heights = [sizes[g, 1].max() for g in groups]
        scale = min((1 - (per_row + 1) * UV_MARGIN) / max(widths), (1 - (len(groups) + 1) * UV_MARGIN) / sum(heights))
        if scale > best[0]:
            offsets = np.zeros((count, 2))
            y = 1 - UV_MARGIN
            for g, h in zip(groups, heights):
                y -= h * scale
                x = UV_MARGIN
                for i in g:
                    offsets[i] = (x, y)
                    x += sizes[i, 0] * scale + UV_MARGIN
                y -= UV_MARGIN
            best = (scale, offsets)
    return best


def compute_uv(vertices: np.ndarray, faces: np.ndarray, garment_type: str
               ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Panels and packed charts of a mesh: (face_uv (F, 3, 2), face_panel (F,), panel names)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    split_x = garment_type in ("pants", "shorts", "jumpsuit")
    face_panel = split_panels(v, f, split_x=split_x)
    names = ["front_left", "front_right", "back_left", "back_right"] if split_x else list(PANEL_NAMES)
    charts = []
    for p in range(len(names)):
        fidx = np.nonzero(face_panel == p)[0]
        sub, used = mesh_ops.remove_unused_vertices(f[fidx], len(v))
        uv = _orient_panel(flatten_panel(v[used], sub), v[used], p // 2 if split_x else p)
        charts.append((fidx, sub, used, uv - uv.min(0)))
    sizes = np.array([c[3].max(0) for c in charts])  # (P, 2) width, height
    scale, offsets = _pack(sizes)
    face_uv = np.zeros((len(f), 3, 2))
    for (fidx, sub, _, uv), off in zip(charts, offsets):
        face_uv[fidx] = (uv * scale + off)[sub]
    return face_uv, face_panel, names


def assign_uv(template, face_uv: np.ndarray, face_panel: np.ndarray, names: list[str]) -> None:
    """Stores per-corner UVs, panels and the per-vertex main-chart UV on a template."""
    f = np.asarray(template.faces, dtype=np.int64)
    vertex_uv = np.zeros((template.vertex_count, 2))
    vertex_panel = np.full(template.vertex_count, -1, dtype=np.int64)
    for p in reversed(range(len(names))):  # lower panel ids written last: a seam vertex's main chart
        sel = face_panel == p
        vertex_uv[f[sel].ravel()] = face_uv[sel].reshape(-1, 2)
        vertex_panel[f[sel].ravel()] = p
    template.face_uv = np.asarray(face_uv, dtype=np.float32)
    template.uv = vertex_uv.astype(np.float32)
    template.face_panel = np.asarray(face_panel, dtype=np.int64)
    template.vertex_panel = vertex_panel
    template.panel_names = list(names)


def build_uv(template) -> None:
    """Computes and stores panels and UVs of a template from its own vertices."""
    assign_uv(template, *compute_uv(template.vertices, template.faces, template.garment_type))


# --------------------------------------------------------------------- raster maps
def pixel_map(face_uv: np.ndarray, size: int, *, inside_eps: float = 1e-9, chunk: int = 4096
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which face covers each pixel centre, and where.

    Returns:
        (face (H*W,) int, -1 where empty; barycentrics (H*W, 3); coverage count (H*W,)
        = number of faces whose strict interior contains the pixel centre).
    """
    fuv = np.asarray(face_uv, dtype=np.float64)
    h = w = int(size)
    px = fuv[..., 0] * w - 0.5  # (F, 3) in pixel units (col)
    py = (1.0 - fuv[..., 1]) * h - 0.5  # row
    face = np.full(h * w, -1, dtype=np.int64)
    bary = np.zeros((h * w, 3))
    count = np.zeros(h * w, dtype=np.int64)
    c0 = np.floor(px.min(1)).astype(int)
    r0 = np.floor(py.min(1)).astype(int)
    extent = int(max(np.ceil(px.max(1) - c0).max(), np.ceil(py.max(1) - r0).max())) + 2
    dc, dr = np.meshgrid(np.arange(extent), np.arange(extent))
    dc, dr = dc.ravel(), dr.ravel()
    for s in range(0, len(fuv), chunk):
        sl = slice(s, min(s + chunk, len(fuv)))
        cols = c0[sl, None] + dc[None]
        rows = r0[sl, None] + dr[None]
        ax, ay = px[sl, 0, None], py[sl, 0, None]
        bx, by = px[sl, 1, None], py[sl, 1, None]
        cx, cy = px[sl, 2, None], py[sl, 2, None]
        det = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        det = np.where(np.abs(det) < 1e-15, 1e-15, det)
        l0 = ((by - cy) * (cols - cx) + (cx - bx) * (rows - cy)) / det
        l1 = ((cy - ay) * (cols - cx) + (ax - cx) * (rows - cy)) / det
        l2 = 1.0 - l0 - l1
        valid = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
        inside = valid & (l0 >= -inside_eps) & (l1 >= -inside_eps) & (l2 >= -inside_eps)
        strict = valid & (l0 > 1e-6) & (l1 > 1e-6) & (l2 > 1e-6)
        fi, ki = np.nonzero(inside)
        pix = rows[fi, ki] * w + cols[fi, ki]
        face[pix] = fi + s
        bary[pix] = np.stack([l0[fi, ki], l1[fi, ki], l2[fi, ki]], 1)
        fs, ks = np.nonzero(strict)
        np.add.at(count, rows[fs, ks] * w + cols[fs, ks], 1)
    return face, bary, count


_MAP_CACHE: dict[tuple[str, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _cached_map(template, size: int):
    key = (template.content_hash(), int(size))
    if key not in _MAP_CACHE:
        if len(_MAP_CACHE) > 8:
            _MAP_CACHE.clear()
        _MAP_CACHE[key] = pixel_map(template.face_uv, size)
    return _MAP_CACHE[key]


def _as_batch(values: np.ndarray, vertex_count: int) -> tuple[np.ndarray, bool]:
    x = np.asarray(values, dtype=np.float64)
    single = x.ndim == 2
    if single:
        x = x[None]
    if x.ndim != 3 or x.shape[1] != vertex_count:
        raise ValueError(f"values must have shape (V, C) or (N, V, C) with V = {vertex_count}, got {np.shape(values)}")
    return x, single


def rasterize(values, template, *, size: int = 256, padding: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex values -> UV images.

    Args:
        values: (V, C) or (N, V, C) per-vertex values (any unit).
        template: a GarmentTemplate with UVs.
        size: image height = width [px].
        padding: pixels of outward dilation (each ring takes the mean of its filled
            4-neighbours), so bilinear sampling near panel borders stays exact.
    Returns:
        (images (N, C, H, W) float32, mask (H, W) bool: pixels covered by a triangle).
    """
    if int(size) < 8:
        raise ValueError(f"size must be >= 8 pixels, got {size}")
    x, _ = _as_batch(values, template.vertex_count)
    face, bary, _ = _cached_map(template, size)
    covered = face >= 0
    corners = template.faces[face[covered]]  # (P, 3)
    pix_vals = np.einsum("pk,npkc->npc", bary[covered], x[:, corners])  # (N, P, C)
    n, c = x.shape[0], x.shape[2]
    img = np.zeros((n, size * size, c))
    img[:, covered] = pix_vals
    filled = covered.reshape(size, size).copy()
    img = img.reshape(n, size, size, c)
    for _ in range(int(padding)):
        acc = np.zeros_like(img)
        cnt = np.zeros((size, size))
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            src = np.roll(filled, (dr, dc), axis=(0, 1))
            if dr == 1:
                src[0, :] = False
            if dr == -1:
                src[-1, :] = False
            if dc == 1:
                src[:, 0] = False
            if dc == -1:
                src[:, -1] = False
            shifted = np.roll(img, (dr, dc), axis=(1, 2))
            acc += shifted * src[None, :, :, None]
            cnt += src
        grow = (~filled) & (cnt > 0)
        img[:, grow] = acc[:, grow] / cnt[grow][None, :, None]
        filled |= grow
    return img.transpose(0, 3, 1, 2).astype(np.float32), covered.reshape(size, size)


def sample(images, template) -> np.ndarray:
    """UV images (N, C, H, W) -> per-vertex values (N, V, C), bilinear at every face
    corner's UV and averaged over a vertex's corners."""
    img = np.asarray(images, dtype=np.float64)
    if img.ndim == 3:
        img = img[None]
    if img.ndim != 4 or img.shape[2] != img.shape[3]:
        raise ValueError(f"images must have shape (N, C, H, W) with H == W, got {np.shape(images)}")
    n, c, h, w = img.shape
    fuv = np.asarray(template.face_uv, dtype=np.float64).reshape(-1, 2)
    x = np.clip(fuv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - fuv[:, 1]) * h - 0.5, 0, h - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    tx, ty = (x - x0)[None, None], (y - y0)[None, None]
    v00, v01 = img[:, :, y0, x0], img[:, :, y0, x0 + 1]
    v10, v11 = img[:, :, y0 + 1, x0], img[:, :, y0 + 1, x0 + 1]
    vals = (v00 * (1 - tx) + v01 * tx) * (1 - ty) + (v10 * (1 - tx) + v11 * tx) * ty  # (N, C, 3F)
    flat = template.faces.ravel()
    counts = np.bincount(flat, minlength=template.vertex_count)
    average = sparse.csr_matrix((1.0 / np.maximum(counts[flat], 1), (flat, np.arange(len(flat)))),
                                shape=(template.vertex_count, len(flat)))  # (V, 3F) corner -> vertex mean
    out = (average @ vals.reshape(n * c, -1).T).T.reshape(n, c, -1)  # (N, C, V)
    return out.transpose(0, 2, 1).astype(np.float32)


def uv_distortion(template, vertices: np.ndarray | None = None) -> dict[str, float]:
    """Area distortion of the charts: mean |log(area_uv / area_3d * k)| where k
    normalises total areas, and the fraction of flipped (negative) UV triangles.
    ``vertices`` (V, 3): the 3D mesh to compare with (default the template's rest
    vertices; charts of body-topology templates are made on the zero-offset body region,
    see :func:`simulate.garment.templates.template_surface`)."""
    v = np.asarray(template.vertices if vertices is None else vertices, dtype=np.float64)
    a3 = 0.5 * np.linalg.norm(np.cross(v[template.faces[:, 1]] - v[template.faces[:, 0]],
                                       v[template.faces[:, 2]] - v[template.faces[:, 0]]), axis=1)
    a2 = signed_areas(np.asarray(template.face_uv, dtype=np.float64), None)
    k = a3.sum() / max(np.abs(a2).sum(), 1e-15)
    ratio = np.abs(a2) * k / np.maximum(a3, 1e-15)
    return {"area_log_mean": float(np.abs(np.log(np.maximum(ratio, 1e-12))).mean()),
            "flipped_fraction": float((a2 <= 0).mean())}
