"""Cloth pixels (seed 001 Sec. 3-4): per-vertex garment values <-> UV images, in torch.

A *cloth pixel* is one (vertex, panel) pair: a vertex inside a panel is one cloth pixel,
a seam vertex is one per panel it belongs to (the template keeps per-corner UVs,
``face_uv`` (F, 3, 2), and a panel per face, ``face_panel`` (F,)). Each panel gets its
own square image: its chart is scaled into the image (one common scale for all panels,
so texel density is uniform) with a margin that holds the padding. Channels are
panel-major: for front/back panels and 3 values per cloth pixel, channels 0-2 are the
front image and 3-5 the back (256 x 256 x 6 in the seed).

Encoding (``to_images``) is linear: each covered pixel interpolates its triangle's
cloth-pixel values barycentrically, then ``padding`` rings of pixels past the chart
border take the mean of their already-filled 4-neighbours (seed Fig. 2: smooth borders
for the convolutions; bilinear sampling at border vertices reads only filled pixels).
The whole map is one sparse matrix (P H W, K), so encoding a batch is one sparse matmul.

Decoding (``sample``) reads every cloth pixel's image bilinearly at its UV with
``torch.nn.functional.grid_sample`` (differentiable w.r.t. the images); per-vertex
values average a vertex's cloth pixels (``vertex_mean``).

Image convention (as :mod:`simulate.garment.uv`): images are (B, C, H, W); pixel (row,
col) has its centre at u = (col + 0.5) / W, v = 1 - (row + 0.5) / H.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
import torch.nn.functional as F

from learn.common.mesh import scipy_to_torch_sparse
from simulate.garment.uv import pixel_map

#: Default image size [px] and padding rings [px] (seed 001: 256 x 256, "some padding").
IMAGE_SIZE = 256
PADDING = 4
#: Largest |barycentric| a padding pixel may extrapolate its neighbour's triangle with
#: (farther, it takes the mean of its filled neighbours). At a sharp chart corner the
#: pixels a border vertex reads can be 3 rings out.
MAX_EXTRAPOLATION = 10.0


def panel_charts(face_uv: np.ndarray, face_panel: np.ndarray, *, size: int, margin_px: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Each panel's corner UVs rescaled to fill its own square image.

    Args:
        face_uv: per-corner atlas UV, shape (F, 3, 2).
        face_panel: panel of each face, shape (F,), values 0..P-1.
        size: image side [px]; margin_px: free border [px] on every side.
    Returns:
        (corner UV in the panel's image, (F, 3, 2) in [0, 1]^2; scale: image units per
        atlas unit, shape () ). One scale for all panels; each chart is centred.
    """
    fuv = np.asarray(face_uv, dtype=np.float64)
    panel = np.asarray(face_panel, dtype=np.int64)
    count = int(panel.max()) + 1
    lo = np.stack([fuv[panel == p].reshape(-1, 2).min(0) for p in range(count)])  # (P, 2)
    hi = np.stack([fuv[panel == p].reshape(-1, 2).max(0) for p in range(count)])
    usable = 1.0 - 2.0 * margin_px / size
    if usable <= 0.1:
        raise ValueError(f"image size {size} px is too small for a {margin_px} px margin")
    scale = usable / float((hi - lo).max())
    centre = 0.5 * (lo + hi)  # (P, 2)
    out = (fuv - centre[panel][:, None, :]) * scale + 0.5
    return out, np.asarray(scale)


def _neighbour_sources(filled: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unfilled pixels with a filled 4-neighbour: (pixel ids (N,), neighbour ids (N,),
    count of filled neighbours per pixel (H W,)), one entry per (pixel, filled neighbour)."""
    size = filled.shape[0]
    pix, src = [], []
    count = np.zeros(filled.shape)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        # from_nb[r, c] = filled[r - dr, c - dc]
        from_nb = np.zeros_like(filled)
        from_nb[max(dr, 0):size + min(dr, 0), max(dc, 0):size + min(dc, 0)] = \
            filled[max(-dr, 0):size + min(-dr, 0), max(-dc, 0):size + min(-dc, 0)]
        grow = from_nb & ~filled
        r, c = np.nonzero(grow)
        pix.append(r * size + c)
        src.append((r - dr) * size + (c - dc))
        count += grow
    return np.concatenate(pix), np.concatenate(src), count.ravel()


def _barycentrics(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentrics (N, 3) of 2D points (N, 2) in triangles (N, 3, 2), extrapolated outside."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    det = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    det = np.where(np.abs(det) < 1e-15, 1e-15, det)
    l0 = ((b[:, 1] - c[:, 1]) * (points[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (points[:, 1] - c[:, 1])) / det
    l1 = ((c[:, 1] - a[:, 1]) * (points[:, 0] - c[:, 0]) + (a[:, 0] - c[:, 0]) * (points[:, 1] - c[:, 1])) / det
    return np.stack([l0, l1, 1.0 - l0 - l1], 1)


def raster_matrix(corner_uv: np.ndarray, corner_pixel: np.ndarray, pixel_count: int, *, size: int,
                  padding: int) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """Sparse map from cloth-pixel values to one panel's image, with padding.

    Each padding ring continues the linear function of a filled 4-neighbour's triangle
    (the one extrapolating least, barycentrics up to :data:`MAX_EXTRAPOLATION`), so
    bilinear reads at border vertices are exact for fields linear over the border
    triangles; a pixel whose triangles would extrapolate farther takes the mean of its
    filled 4-neighbours.

    Args:
        corner_uv: the panel's faces' corner UVs in its image, (Fp, 3, 2).
        corner_pixel: cloth pixel of each corner, (Fp, 3), values < ``pixel_count``.
        size, padding: image side and padding rings [px].
    Returns:
        (matrix (H W, K): row r gives pixel r (row-major) as a combination of cloth pixels;
        covered (H, W) bool: pixel centres inside a triangle; filled (H, W) bool: covered
        or padded (the seed's padded mask W)).
    """
    face, bary, _ = pixel_map(corner_uv, size)
    rows = np.flatnonzero(face >= 0)
    cols = corner_pixel[face[rows]]  # (R, 3)
    matrix = sp.csr_matrix((bary[rows].ravel(), (np.repeat(rows, 3), cols.ravel())), shape=(size * size, pixel_count))
    covered = (face >= 0).reshape(size, size)
    filled = covered.copy()
    # pixel centres in the UV units pixel_map uses: u = (col + 0.5) / W, v = 1 - (row + 0.5) / H
    centre_uv = np.stack([(np.arange(size * size) % size + 0.5) / size, 1.0 - (np.arange(size * size) // size + 0.5) / size], 1)
    for _ in range(int(padding)):
        pix, src, count = _neighbour_sources(filled)
        done = np.zeros(size * size, dtype=bool)
        cand = face[src]
        ok = cand >= 0
        l = np.full((len(pix), 3), np.inf)
        l[ok] = _barycentrics(centre_uv[pix[ok]], corner_uv[cand[ok]])
        worst = np.abs(l).max(1)
        order = np.lexsort((worst, pix))  # per pixel, least extrapolating candidate first
        first = np.ones(len(order), dtype=bool)
        first[1:] = pix[order][1:] != pix[order][:-1]
        best = order[first]
        best = best[worst[best] <= MAX_EXTRAPOLATION]
        p, f = pix[best], cand[best]
        matrix = matrix + sp.csr_matrix((l[best].ravel(), (np.repeat(p, 3), corner_pixel[f].ravel())),
                                        shape=matrix.shape)
        face[p] = f
        done[p] = True
        keep = ~done[pix]
        pix, src = pix[keep], src[keep]
        if len(pix):
            mean = sp.csr_matrix((1.0 / count[pix], (pix, src)), shape=(size * size, size * size))
            matrix = matrix + mean @ matrix  # rows of new pixels: means of filled neighbours' rows
        filled |= (count > 0).reshape(size, size)
    return matrix.tocsr(), covered, filled


class ClothPixels(torch.nn.Module):
    """The cloth-pixel layout of one garment template and its image transfer.

    Args:
        faces: garment triangles, shape (F, 3).
        face_uv: per-corner atlas UV, shape (F, 3, 2) (the template's ``face_uv``).
        face_panel: panel of each face, shape (F,) (0 front, 1 back for tops).
        vertex_count: V.
        size: image side [px]; padding: rings of padding [px].

    Buffers: ``pixel_vertex`` (K,) and ``pixel_panel`` (K,): the vertex and panel of each
    cloth pixel; ``pixel_uv`` (K, 2): its UV in its panel's image; ``corner_pixel`` (F, 3);
    ``mask`` (P, H, W) bool: covered or padded pixels; ``covered`` (P, H, W) bool.
    """

    def __init__(self, faces: np.ndarray, face_uv: np.ndarray, face_panel: np.ndarray, vertex_count: int, *,
                 size: int = IMAGE_SIZE, padding: int = PADDING) -> None:
        super().__init__()
        faces = np.asarray(faces, dtype=np.int64)
        face_uv = np.asarray(face_uv, dtype=np.float64)
        face_panel = np.asarray(face_panel, dtype=np.int64)
        if face_uv.shape != faces.shape + (2,) or face_panel.shape != faces.shape[:1]:
            raise ValueError(f"face_uv must have shape {faces.shape + (2,)} and face_panel ({faces.shape[0]},), "
                             f"got {face_uv.shape} and {face_panel.shape}")
        if int(size) < 8 or int(padding) < 1:
            raise ValueError(f"image size must be >= 8 px and padding >= 1 px, got size={size}, padding={padding}")
        self.size, self.padding, self.vertex_count = int(size), int(padding), int(vertex_count)
        self.panel_count = int(face_panel.max()) + 1
        # cloth pixels: unique (panel, vertex) pairs of the faces' corners
        key = face_panel[:, None] * vertex_count + faces  # (F, 3)
        unique, corner_pixel = np.unique(key.ravel(), return_inverse=True)
        corner_pixel = corner_pixel.reshape(faces.shape)
        pixel_panel, pixel_vertex = np.divmod(unique, vertex_count)
        corner_uv, _ = panel_charts(face_uv, face_panel, size=self.size, margin_px=self.padding + 1.5)
        pixel_uv = np.zeros((len(unique), 2))
        pixel_uv[corner_pixel.ravel()] = corner_uv.reshape(-1, 2)
        blocks, covered, filled = [], [], []
        for p in range(self.panel_count):
            sel = face_panel == p
            m, c, f = raster_matrix(corner_uv[sel], corner_pixel[sel], len(unique), size=self.size, padding=self.padding)
            blocks.append(m)
            covered.append(c)
            filled.append(f)
        self.pixel_count = int(len(unique))
        self.register_buffer("pixel_vertex", torch.as_tensor(pixel_vertex, dtype=torch.int64))
        self.register_buffer("pixel_panel", torch.as_tensor(pixel_panel, dtype=torch.int64))
        self.register_buffer("pixel_uv", torch.as_tensor(pixel_uv, dtype=torch.float32))
        self.register_buffer("corner_pixel", torch.as_tensor(corner_pixel, dtype=torch.int64))
        self.register_buffer("mask", torch.as_tensor(np.stack(filled)))
        self.register_buffer("covered", torch.as_tensor(np.stack(covered)))
        # (P H W, K) encoder, derived (rebuilt from the faces and UVs, not saved)
        self.register_buffer("raster", scipy_to_torch_sparse(sp.vstack(blocks)), persistent=False)
        counts = np.bincount(pixel_vertex, minlength=vertex_count)
        if (counts == 0).any():
            raise ValueError(f"{int((counts == 0).sum())} vertices are in no face: every vertex needs a cloth pixel")
        self.register_buffer("pixel_weight", torch.as_tensor(1.0 / counts[pixel_vertex], dtype=torch.float32))
        # grid_sample coordinates of each panel's cloth pixels, (1, 1, K_p, 2) in [-1, 1]
        grid = np.stack([2.0 * pixel_uv[:, 0] - 1.0, 1.0 - 2.0 * pixel_uv[:, 1]], 1)
        self.register_buffer("grid", torch.as_tensor(grid, dtype=torch.float32), persistent=False)

    @property
    def channels(self) -> int:
        """Image channels for 3 values per cloth pixel: 3 x panels."""
        return 3 * self.panel_count

    def to_images(self, values: torch.Tensor) -> torch.Tensor:
        """Cloth-pixel values (B, K, C) -> images (B, P C, H, W), panel-major channels."""
        if values.ndim != 3 or values.shape[1] != self.pixel_count:
            raise ValueError(f"values must have shape (B, {self.pixel_count}, C), got {tuple(values.shape)}")
        b, k, c = values.shape
        flat = values.permute(1, 0, 2).reshape(k, b * c)  # (K, B C)
        raster = self.raster if self.raster.dtype == values.dtype else self.raster.to(values.dtype)
        img = torch.sparse.mm(raster, flat)  # (P H W, B C)
        img = img.reshape(self.panel_count, self.size, self.size, b, c)
        return img.permute(3, 0, 4, 1, 2).reshape(b, self.panel_count * c, self.size, self.size)

    def sample(self, images: torch.Tensor) -> torch.Tensor:
        """Images (B, P C, H, W) -> cloth-pixel values (B, K, C), bilinear at each UV."""
        b, pc, h, w = images.shape
        if pc % self.panel_count or h != self.size or w != self.size:
            raise ValueError(f"images must have shape (B, {self.panel_count} C, {self.size}, {self.size}), "
                             f"got {tuple(images.shape)}")
        c = pc // self.panel_count
        out = images.new_zeros(b, self.pixel_count, c)
        for p in range(self.panel_count):
            sel = self.pixel_panel == p
            grid = self.grid[sel].to(images.dtype)[None, None].expand(b, 1, -1, 2)  # (B, 1, K_p, 2)
            got = F.grid_sample(images[:, p * c:(p + 1) * c], grid, mode="bilinear", padding_mode="border",
                                align_corners=False)  # (B, C, 1, K_p)
            out[:, sel] = got[:, :, 0].transpose(1, 2)
        return out

    def vertex_mean(self, values: torch.Tensor) -> torch.Tensor:
        """Cloth-pixel values (B, K, C) -> per-vertex means (B, V, C) over a vertex's cloth pixels."""
        weighted = values * self.pixel_weight.to(values.dtype)[None, :, None]
        out = values.new_zeros(values.shape[0], self.vertex_count, values.shape[2])
        return out.index_add(1, self.pixel_vertex, weighted)

    def image_mask(self) -> torch.Tensor:
        """Padded mask per channel group, (P, H, W) float (the loss weights W of seed Eq. 1)."""
        return self.mask.float()
