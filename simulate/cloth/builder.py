"""ClothBuilder: checks garments and packs them, one garment per world, into a ClothModel."""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import warp as wp

from simulate.cloth.fabric import Fabric, resolve_fabric
from simulate.cloth.model import ClothModel, Features

__all__ = ["ClothBuilder", "greedy_colour", "dihedral_angles", "triangle_rest_frames", "material_directions",
           "GRAIN_AXIS"]

_DEGENERATE_RATIO = 1.0e-6
"""A triangle is degenerate when area < _DEGENERATE_RATIO * (longest edge)^2."""


def greedy_colour(elements: np.ndarray) -> np.ndarray:
    """Colour elements so that no two elements sharing a vertex get the same colour.

    Args:
        elements: vertex indices per element, shape (E, k), int.
    Returns:
        colour per element, shape (E,), int32, colours 0..C-1 (greedy, first fit).
    """
    elements = np.asarray(elements)
    if elements.size == 0:
        return np.zeros(0, dtype=np.int32)
    # One Python int per vertex used as a bit set of the colours already touching it.
    used = [0] * (int(elements.max()) + 1)
    colours = np.empty(len(elements), dtype=np.int32)
    for e, verts in enumerate(elements.tolist()):
        mask = 0
        for v in verts:
            mask |= used[v]
        free = ~mask & (mask + 1)  # lowest zero bit
        c = free.bit_length() - 1
        colours[e] = c
        for v in verts:
            used[v] |= free
    return colours


GRAIN_AXIS = (0.0, 1.0, 0.0)
"""Default warp direction of garments without a material UV map: the garment's up axis (+y)."""
_GRAIN_MIN_SINE = 0.1
"""Below this sine of the angle between the grain axis and a triangle's plane (about 5.7 degrees)
the projected grain is too short to give a stable direction; such triangles take the fallback
axis (perpendicular to the grain: x for the default +y) instead."""
_DEGENERATE_UV_RATIO = 1.0e-6
"""A face's material UV triangle is degenerate (no warp direction) when its UV area is below
this times its longest UV edge squared; such faces take the grain axis instead."""


def _fallback_axes(grain: np.ndarray) -> np.ndarray:
    """Per row of ``grain`` (N, 3), the unit vector perpendicular to it built from the coordinate
    axis least aligned with it (x for +y: the first of the tied axes)."""
    g = grain / np.linalg.norm(grain, axis=1, keepdims=True)
    axis = np.eye(3)[np.argmin(np.abs(g), axis=1)]
    perp = axis - np.einsum("ij,ij->i", axis, g)[:, None] * g
    return perp / np.linalg.norm(perp, axis=1, keepdims=True)


def material_directions(vertices: np.ndarray, faces: np.ndarray, *, material_uv: np.ndarray | None = None,
                        grain_axis: np.ndarray | tuple[float, float, float] = GRAIN_AXIS
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warp and weft directions of triangles in their rest planes.

    The warp of a face is the 3-D direction of its pattern's vertical: with ``material_uv`` the
    tangent d x / d v of the affine map from the face's UV triangle to its rest triangle (the
    image of a line of constant u, as a warp thread runs in a pattern piece whose v axis points
    up); without it (or where the UV triangle is degenerate) ``grain_axis`` projected into the
    triangle's plane, or, where the triangle is within ~6 degrees of perpendicular to it
    (``_GRAIN_MIN_SINE``), an axis perpendicular to the grain (x for +y) projected likewise. The
    weft is normal x warp. Both depend only on the triangle's geometry, UVs and orientation,
    not on which corner a face lists first.

    Args:
        vertices: rest positions [m], (V, 3).
        faces: triangles, (F, 3) int.
        material_uv: optional pattern coordinates per face corner, (F, 3, 2) (any unit; only
            directions are used), v up the pattern piece.
        grain_axis: fallback warp direction, (3,) or one per face (F, 3); need not be unit.
    Returns:
        warp (F, 3), weft (F, 3) unit vectors and the unit normals (F, 3) (float64).
    """
    faces = np.asarray(faces)
    x0, x1, x2 = (np.asarray(vertices, dtype=np.float64)[faces[:, k]] for k in range(3))
    e1, e2 = x1 - x0, x2 - x0
    cross = np.cross(e1, e2)
    n = cross / np.maximum(np.linalg.norm(cross, axis=1), 1e-300)[:, None]
    grain = np.broadcast_to(np.asarray(grain_axis, dtype=np.float64), (len(faces), 3))
    direction = grain.copy()
    if material_uv is not None:
        uv = np.asarray(material_uv, dtype=np.float64)
        d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]  # twice the signed UV area
        longest2 = np.max([np.sum(d * d, axis=1) for d in (d1, d2, d2 - d1)], axis=0)
        ok = np.abs(det) > 2.0 * _DEGENERATE_UV_RATIO * longest2
        # [e1 e2] = J [d1 d2]  ->  d x / d v = J[:, 1] = (d1_u e2 - d2_u e1) / det
        with np.errstate(divide="ignore", invalid="ignore"):
            dxdv = (d1[:, 0, None] * e2 - d2[:, 0, None] * e1) / det[:, None]
        direction[ok] = dxdv[ok]
    warp = direction - np.einsum("ij,ij->i", direction, n)[:, None] * n
    length = np.linalg.norm(warp, axis=1)
    weak = length <= _GRAIN_MIN_SINE * np.linalg.norm(direction, axis=1)
    if weak.any():
        alt = _fallback_axes(grain[weak])
        warp[weak] = alt - np.einsum("ij,ij->i", alt, n[weak])[:, None] * n[weak]
        length[weak] = np.linalg.norm(warp[weak], axis=1)
    warp /= np.maximum(length, 1e-300)[:, None]
    return warp, np.cross(n, warp), n


def triangle_rest_frames(vertices: np.ndarray, faces: np.ndarray, *, material_uv: np.ndarray | None = None,
                         grain_axis: np.ndarray | tuple[float, float, float] = GRAIN_AXIS
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse rest-frame matrices and areas of triangles, in each triangle's (warp, weft) frame.

    ``Dm`` holds the rest edges x1 - x0, x2 - x0 in the orthonormal (warp, weft) frame of
    :func:`material_directions` (rows: warp, weft components), so the (3, 2) deformation
    gradient ``F = [x1 - x0, x2 - x0] @ Dm_inv`` has the deformed warp direction as its first
    column f1 and the deformed weft as f2: |f1| - 1 is warp strain, |f2| - 1 weft strain and
    f1 . f2 shear. Rolling a face's corners gives the same F (up to rounding).

    Args:
        vertices: rest positions [m], (V, 3); faces: (F, 3) int.
        material_uv, grain_axis: see :func:`material_directions`.
    Returns:
        dm_inv (F, 2, 2) [1/m] and area (F,) [m^2].
    """
    faces = np.asarray(faces)
    v = np.asarray(vertices, dtype=np.float64)
    warp, weft, _ = material_directions(v, faces, material_uv=material_uv, grain_axis=grain_axis)
    x0, x1, x2 = (v[faces[:, k]] for k in range(3))
    e1, e2 = x1 - x0, x2 - x0
    double_area = np.linalg.norm(np.cross(e1, e2), axis=1)
    dm = np.stack([np.stack([np.einsum("ij,ij->i", e1, warp), np.einsum("ij,ij->i", e2, warp)], axis=1),
                   np.stack([np.einsum("ij,ij->i", e1, weft), np.einsum("ij,ij->i", e2, weft)], axis=1)], axis=1)
    # det(Dm) = (e1 x e2) . (warp x weft) = twice the area, as warp x weft is the unit normal.
    dm_inv = np.empty_like(dm)
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate faces are rejected by the caller
        inv_det = 1.0 / double_area
        dm_inv[:, 0, 0] = dm[:, 1, 1] * inv_det
        dm_inv[:, 0, 1] = -dm[:, 0, 1] * inv_det
        dm_inv[:, 1, 0] = -dm[:, 1, 0] * inv_det
        dm_inv[:, 1, 1] = dm[:, 0, 0] * inv_det
    return dm_inv, 0.5 * double_area


def dihedral_angles(x: np.ndarray, bend_indices: np.ndarray) -> np.ndarray:
    """Signed dihedral angles [rad] of bending stencils (opp0, opp1, edge0, edge1), 0 when flat.

    Same formula as the Warp function ``bending_angle_grad`` used by the solvers.
    """
    x1, x2, x3, x4 = (x[bend_indices[:, k]].astype(np.float64) for k in range(4))
    n1 = np.cross(x3 - x1, x4 - x1)
    n2 = np.cross(x4 - x2, x3 - x2)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
    e = x4 - x3
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    cos_t = np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0)
    sign = np.sign(np.einsum("ij,ij->i", np.cross(n2, n1), e))
    sign[sign == 0.0] = 1.0
    return np.arccos(cos_t) * sign


def _array_digest(*arrays: np.ndarray | None) -> bytes:
    """A 128-bit digest of arrays (dtype, shape and bytes of each; None counts as a value)."""
    digest = hashlib.blake2b(digest_size=16)
    for a in arrays:
        if a is None:
            digest.update(b"none")
            continue
        digest.update(str((a.dtype, a.shape)).encode())
        digest.update(np.ascontiguousarray(a).tobytes())
    return digest.digest()


def _mesh_digest(vertices: np.ndarray, faces: np.ndarray, material_key: bytes = b"") -> bytes:
    """A 128-bit digest of a garment's rest vertices and faces (as the builder stores them) and
    the digest of its material-frame inputs (UVs, grain axis): garments with equal digests are
    checked and turned into elements once, so everything the elements depend on besides the
    fabric goes in."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(_array_digest(vertices, faces))
    digest.update(material_key)
    return digest.digest()


@dataclasses.dataclass
class _Garment:
    vertices: np.ndarray
    faces: np.ndarray
    fabric: Fabric
    pinned: np.ndarray
    attached: np.ndarray
    skinning_weights: np.ndarray | None
    material_uv: np.ndarray | None  # (F, 3, 2) float64 pattern coordinates per face corner
    grain_axis: np.ndarray  # (3,) or (F, 3) float64 warp direction where there is no UV
    digest: bytes  # of vertices, faces, material_uv and grain_axis (_mesh_digest)
    body_part: np.ndarray | None = None  # (V,) int32 primary collision part per vertex


def _index_array(name: str, value: object, count: int) -> np.ndarray:
    if value is None:
        return np.zeros(0, dtype=np.int64)
    arr = np.asarray(value)
    if arr.dtype == bool:
        if arr.shape != (count,):
            raise ValueError(f"{name} as a mask must have shape ({count},) (got {arr.shape})")
        return np.nonzero(arr)[0].astype(np.int64)
    arr = arr.reshape(-1)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must be integer vertex indices (got dtype {arr.dtype})")
    arr = arr.astype(np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= count):
        bad = arr[(arr < 0) | (arr >= count)][0]
        raise ValueError(f"{name} contains vertex index {bad}, expected indices in [0, {count})")
    return np.unique(arr)


class ClothBuilder:
    """Collects garments (one per world) and packs them into a :class:`ClothModel`."""

    def __init__(self, *, gravity: tuple[float, float, float] = (0.0, -9.81, 0.0),
                 attachment_stiffness: float = 1.0e3) -> None:
        """
        Args:
            gravity: gravity acceleration [m/s^2]; y is up.
            attachment_stiffness: default attachment spring stiffness [N/m per particle].
        """
        self.gravity = tuple(float(g) for g in gravity)
        if len(self.gravity) != 3 or not all(np.isfinite(self.gravity)):
            raise ValueError(f"gravity must be 3 finite numbers [m/s^2] (got {gravity!r})")
        if not (np.isfinite(attachment_stiffness) and attachment_stiffness > 0):
            raise ValueError(f"attachment_stiffness must be > 0 [N/m] (got {attachment_stiffness!r})")
        self.attachment_stiffness = float(attachment_stiffness)
        self._garments: list[_Garment] = []
        self._colour_cache: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._checked: set[bytes] = set()  # digests of garment meshes whose geometry passed the checks
        # material-frame inputs by digest: the worlds of a batch share one (F, 3, 2) UV array
        self._materials: dict[bytes, tuple[np.ndarray | None, np.ndarray]] = {}

    @property
    def world_count(self) -> int:
        return len(self._garments)

    def add_garment(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        fabric: Fabric | str = "cotton",
        pinned: np.ndarray | None = None,
        attached: np.ndarray | None = None,
        skinning_weights: np.ndarray | None = None,
        material_uv: np.ndarray | None = None,
        grain_axis: np.ndarray | tuple[float, float, float] = GRAIN_AXIS,
        body_part: np.ndarray | None = None,
    ) -> int:
        """Add one garment as a new world and return the world index.

        Each triangle's material frame (warp, weft; see :func:`material_directions`) comes from
        ``material_uv`` where given (a garment template's ``face_uv``: the warp runs up each
        pattern panel), else from ``grain_axis``; the fabric's warp stiffness acts along the warp.

        Args:
            vertices: rest (and initial) positions [m], shape (V, 3).
            faces: triangles, shape (F, 3), int indices into ``vertices``.
            fabric: a Fabric or a preset name from ``FABRICS``.
            pinned: vertex indices (or a (V,) bool mask) fixed in space (inverse mass 0).
            attached: vertex indices (or mask) pulled by soft, releasable springs to targets.
            skinning_weights: per-vertex skinning weights, shape (V, J), kept for callers.
            material_uv: pattern coordinates per face corner, shape (F, 3, 2), in the order of
                ``faces`` (v up the pattern piece; scale free). None: use ``grain_axis``.
            grain_axis: warp direction projected into each triangle where there is no usable UV,
                shape (3,) or (F, 3) (default +y, the garment's up axis).
            body_part: primary collision body of each vertex, shape (V,), int in [0, 255]: the
                index of the collider's face group it meets (``simulate.body.collision_parts``);
                None: 0 (the whole body for a collider without parts).
        Raises:
            ValueError naming the field, the value received and what was expected.
        """
        verts = np.asarray(vertices)
        if verts.ndim != 2 or verts.shape[1] != 3 or verts.shape[0] < 3:
            raise ValueError(f"vertices must have shape (V, 3) with V >= 3 (got {verts.shape})")
        if not np.issubdtype(verts.dtype, np.number):
            raise ValueError(f"vertices must be numeric (got dtype {verts.dtype})")
        verts = verts.astype(np.float64)
        bad = np.nonzero(~np.all(np.isfinite(verts), axis=1))[0]
        if bad.size:
            raise ValueError(f"vertices must be finite; vertex {bad[0]} is {verts[bad[0]].tolist()} "
                             f"({bad.size} non-finite vertices)")
        tris = np.asarray(faces)
        if tris.ndim != 2 or tris.shape[1] != 3 or tris.shape[0] < 1:
            raise ValueError(f"faces must have shape (F, 3) with F >= 1 (got {tris.shape})")
        if not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"faces must be integer vertex indices (got dtype {tris.dtype})")
        tris = tris.astype(np.int64)
        vcount = len(verts)
        out = np.nonzero((tris < 0) | (tris >= vcount))
        if out[0].size:
            f = out[0][0]
            raise ValueError(f"faces[{f}] = {tris[f].tolist()} has an index out of range, expected [0, {vcount})")
        repeated = np.nonzero((tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2]))[0]
        if repeated.size:
            f = repeated[0]
            raise ValueError(f"faces[{f}] = {tris[f].tolist()} repeats a vertex (degenerate triangle, area 0)")
        uv = None if material_uv is None else np.asarray(material_uv)
        if uv is not None:
            if uv.shape != (len(tris), 3, 2):
                raise ValueError(f"material_uv must have shape ({len(tris)}, 3, 2), one UV per face corner "
                                 f"(got {uv.shape})")
            if not np.issubdtype(uv.dtype, np.number):
                raise ValueError(f"material_uv must be numeric (got dtype {uv.dtype})")
        grain = np.asarray(grain_axis)
        if grain.shape not in ((3,), (len(tris), 3)) or not np.issubdtype(grain.dtype, np.number):
            raise ValueError(f"grain_axis must be numbers of shape (3,) or ({len(tris)}, 3) (got {grain.shape}, "
                             f"dtype {grain.dtype})")
        # The worlds of a batch pass one template's UVs: checked, converted and stored once.
        material_key = _array_digest(uv, grain)
        if material_key not in self._materials:
            if uv is not None:
                uv = uv.astype(np.float64)
                bad_uv = np.nonzero(~np.all(np.isfinite(uv), axis=(1, 2)))[0]
                if bad_uv.size:
                    raise ValueError(f"material_uv must be finite; face {bad_uv[0]} has {uv[bad_uv[0]].tolist()}")
            grain = grain.astype(np.float64)
            rows = grain.reshape(-1, 3)
            bad_grain = np.nonzero(~(np.all(np.isfinite(rows), axis=1) & (np.linalg.norm(rows, axis=1) > 0.0)))[0]
            if bad_grain.size:
                raise ValueError(f"grain_axis must be finite and non-zero (got {rows[bad_grain[0]].tolist()}"
                                 + (f" for face {bad_grain[0]})" if grain.ndim == 2 else ")"))
            self._materials[material_key] = (uv, grain)
        uv, grain = self._materials[material_key]
        digest = _mesh_digest(verts, tris, material_key)
        if digest not in self._checked:  # a dataset batch adds ~40 distinct garments to 256 worlds
            self._check_geometry(verts, tris)
            self._checked.add(digest)
        fab = resolve_fabric(fabric)
        pinned_idx = _index_array("pinned", pinned, vcount)
        attached_idx = _index_array("attached", attached, vcount)
        weights = None
        if skinning_weights is not None:
            weights = np.asarray(skinning_weights, dtype=np.float32)
            if weights.ndim != 2 or weights.shape[0] != vcount:
                raise ValueError(f"skinning_weights must have shape ({vcount}, J) (got {weights.shape})")
            if not np.all(np.isfinite(weights)):
                raise ValueError("skinning_weights must be finite (got NaN or inf)")
        part = None
        if body_part is not None:
            part = np.asarray(body_part)
            if part.shape != (vcount,) or not np.issubdtype(part.dtype, np.integer) or \
                    (vcount and (part.min() < 0 or part.max() > 255)):
                raise ValueError(f"body_part must be integers in [0, 255] of shape ({vcount},) (got shape {part.shape}, "
                                 f"dtype {part.dtype})")
            part = part.astype(np.int32)
        self._garments.append(_Garment(verts, tris, fab, pinned_idx, attached_idx, weights, uv, grain, digest, part))
        return len(self._garments) - 1

    @staticmethod
    def _check_geometry(verts: np.ndarray, tris: np.ndarray) -> None:
        """Rejects degenerate triangles, unreferenced vertices and non-manifold edges (see add_garment)."""
        vcount = len(verts)
        _, area = triangle_rest_frames(verts, tris)
        edge_len2 = np.stack([np.sum((verts[tris[:, (k + 1) % 3]] - verts[tris[:, k]]) ** 2, axis=1)
                              for k in range(3)], axis=1).max(axis=1)
        degenerate = np.nonzero(area < _DEGENERATE_RATIO * edge_len2)[0]
        if degenerate.size:
            f = degenerate[0]
            raise ValueError(f"faces[{f}] = {tris[f].tolist()} is degenerate: area {area[f]:.3e} m^2, expected "
                             f">= {_DEGENERATE_RATIO:g} * longest edge^2 = {_DEGENERATE_RATIO * edge_len2[f]:.3e} m^2 "
                             f"({degenerate.size} degenerate triangles)")
        referenced = np.zeros(vcount, dtype=bool)
        referenced[tris.reshape(-1)] = True
        if not referenced.all():
            missing = np.nonzero(~referenced)[0]
            raise ValueError(f"vertex {missing[0]} is not referenced by any face ({missing.size} unreferenced "
                             "vertices); remove them before add_garment")
        edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
        uniq, counts = np.unique(edges[:, 0] * vcount + edges[:, 1], return_counts=True)  # 1-D keys: fast
        if (counts > 2).any():
            k = uniq[np.nonzero(counts > 2)[0][0]]
            raise ValueError(f"edge {[int(k // vcount), int(k % vcount)]} is shared by {counts[counts > 2][0]} faces, "
                             "expected at most 2 (non-manifold mesh)")

    # ------------------------------------------------------------------ packing
    def _topology(self, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bending stencils and colours for one garment topology (cached by face array)."""
        key = (faces.shape, hash(faces.tobytes()))
        if key in self._colour_cache:
            return self._colour_cache[key]
        # Interior edges -> (opposite 0, opposite 1, edge 0, edge 1).
        f_count = len(faces)
        # Half-edges (3F, 3): edge start, edge end, opposite vertex.
        half = np.concatenate([faces[:, [0, 1, 2]], faces[:, [1, 2, 0]], faces[:, [2, 0, 1]]])
        key_e = np.sort(half[:, :2], axis=1)
        order = np.lexsort((key_e[:, 1], key_e[:, 0]))
        ks = key_e[order]
        same = np.all(ks[1:] == ks[:-1], axis=1)
        first = order[:-1][same]
        second = order[1:][same]
        bend = np.stack([half[first, 2], half[second, 2], half[first, 0], half[first, 1]], axis=1)
        tri_colour = greedy_colour(faces)
        bend_colour = greedy_colour(bend) if len(bend) else np.zeros(0, dtype=np.int32)
        assert f_count == len(tri_colour)
        result = (bend.astype(np.int64), tri_colour, bend_colour)
        self._colour_cache[key] = result
        return result

    def _elements(self, g: _Garment, bending: bool) -> tuple:
        """One garment's element arrays in its own vertex numbering: vertex masses (V,) [kg];
        triangles (colour (F,), dm_inv (F, 2, 2) in the (warp, weft) frame, area (F,) [m^2],
        compliance (F, 3): 1/(Y_warp A), 1/(Y_weft A), 1/(G A) [1/(N m)]); bending
        stencils (indices (E, 4), colour (E,), rest angle (E,) [rad], compliance (E,)), or None
        without bending or interior edges. Computed in float64; the per-element values are
        returned as the float32 the model stores (casting before packing is what casting after
        gives, with half the bytes to pack)."""
        dm_inv, area = triangle_rest_frames(g.vertices, g.faces, material_uv=g.material_uv, grain_axis=g.grain_axis)
        vmass = np.zeros(len(g.vertices))
        np.add.at(vmass, g.faces.reshape(-1), np.repeat(area / 3.0, 3) * g.fabric.density)
        bend, tri_colour, bend_colour = self._topology(g.faces)
        comp = np.stack([1.0 / (g.fabric.warp_stiffness * area), 1.0 / (g.fabric.weft_stretch_stiffness * area),
                         1.0 / (g.fabric.shear_stiffness * area)], axis=1)
        tri = (tri_colour, dm_inv.astype(np.float32), area.astype(np.float32), comp.astype(np.float32))
        if not (bending and len(bend)):
            return vmass, tri, None
        e_len2 = np.sum((g.vertices[bend[:, 3]] - g.vertices[bend[:, 2]]) ** 2, axis=1)
        face_area = np.zeros(len(bend))
        # Adjacent face areas from the two triangles (opp, e0, e1).
        for k in (0, 1):
            a = g.vertices[bend[:, k]]
            e0, e1 = g.vertices[bend[:, 2]] - a, g.vertices[bend[:, 3]] - a
            face_area += 0.5 * np.linalg.norm(np.cross(e0, e1), axis=1)
        # k_e = B |e|^2 / (A1 + A2): on an equilateral lattice bent into a cylinder of
        # curvature kappa, sum_e 1/2 k_e theta_e^2 = 1/2 B kappa^2 area in every direction
        # (tests/test_cloth_builder.py); Grinspun's 3 |e|^2 / (A1 + A2) is 3x stiffer.
        k_bend = g.fabric.bending_stiffness * e_len2 / face_area
        with np.errstate(divide="ignore"):
            bcomp = np.where(k_bend > 0.0, 1.0 / np.maximum(k_bend, 1e-300), 0.0)
        rest = dihedral_angles(g.vertices, bend)
        keep = k_bend > 0.0
        return vmass, tri, (bend[keep], bend_colour[keep], rest[keep].astype(np.float32), bcomp[keep].astype(np.float32))

    def finalize(self, device: wp.context.Devicelike = None, *, features: Features | None = None) -> ClothModel:
        """Pack all garments into one model on ``device``.

        Args:
            device: Warp device ("cpu", "cuda:0", ...; None = Warp's default).
            features: physics switches; attachments default to on iff any garment has attached vertices.
        """
        if not self._garments:
            raise ValueError("ClothBuilder has no garments: call add_garment at least once before finalize")
        feats = dataclasses.replace(features) if features is not None else Features()
        any_attached = any(g.attached.size for g in self._garments)
        if feats.attachments is None:
            feats.attachments = any_attached
        device = wp.get_device(device)

        m = ClothModel()
        m.device = device
        m.features = feats
        m.gravity = self.gravity
        m.default_attachment_stiffness = self.attachment_stiffness
        m.world_count = len(self._garments)

        starts, counts = [], []
        q, mass, inv_mass, pworld, radius, body_part = [], [], [], [], [], []
        tri_parts, bend_parts = [], []  # per world: (indices global, colours, extra arrays)
        att = []
        offset = 0
        # garments that share rest geometry, faces, material frames and fabric (a dataset batch: ~40 styles in 256
        # worlds) share their element arrays, computed once (~35 ms per 7k-vertex t-shirt)
        elements: dict[tuple, tuple] = {}
        for w, g in enumerate(self._garments):
            vcount = len(g.vertices)
            starts.append(offset)
            counts.append(vcount)
            key = (g.digest, repr(g.fabric))
            if key not in elements:
                elements[key] = self._elements(g, feats.bending)
            vmass, tri, bend = elements[key]
            vinv = 1.0 / vmass
            vinv[g.pinned] = 0.0
            q.append(g.vertices)
            mass.append(vmass)
            inv_mass.append(vinv)
            pworld.append(np.full(vcount, w))
            radius.append(np.full(vcount, 0.5 * g.fabric.thickness))
            body_part.append(np.zeros(vcount, np.int32) if g.body_part is None else g.body_part)
            tri_parts.append((g.faces + offset, *tri, np.full(len(g.faces), w, dtype=np.int32)))
            if bend is not None:
                bend_parts.append((bend[0] + offset, *bend[1:], np.full(len(bend[0]), w, dtype=np.int32)))
            att.append(g.attached + offset)
            offset += vcount

        m.particle_count = offset
        m.world_particle_start = np.asarray(starts, dtype=np.int64)
        m.world_particle_count = np.asarray(counts, dtype=np.int64)
        m.fabrics = [g.fabric for g in self._garments]
        m.skinning_weights = [g.skinning_weights for g in self._garments]
        m.world_faces = [g.faces.astype(np.int32) for g in self._garments]
        q_np = np.concatenate(q).astype(np.float32)
        m.particle_q_rest_np = q_np
        m.particle_mass_np = np.concatenate(mass).astype(np.float32)
        m.particle_inv_mass_np = np.concatenate(inv_mass).astype(np.float32)

        def sort_by_colour(parts: list[tuple]) -> tuple[list[np.ndarray], list[int]]:
            if not parts:
                return [], [0]
            cols = np.concatenate([p[1] for p in parts])
            fields = [np.concatenate([p[i] for p in parts]) for i in range(len(parts[0])) if i != 1]
            order = np.argsort(cols, kind="stable")
            ncol = int(cols.max()) + 1 if cols.size else 0
            offsets = np.searchsorted(cols[order], np.arange(ncol + 1)).tolist()
            return [f[order] for f in fields], offsets

        (tri_idx, dm_inv, area, comp, tri_world), m.tri_colour_offsets = sort_by_colour(tri_parts)
        m.tri_count = len(tri_idx)
        m.tri_indices_np = tri_idx.astype(np.int32)
        if bend_parts and sum(len(p[0]) for p in bend_parts):
            (bend_idx, rest, bcomp, bend_world), m.bend_colour_offsets = sort_by_colour(bend_parts)
        else:
            bend_idx = np.zeros((0, 4), dtype=np.int64)
            rest = bcomp = np.zeros(0)
            bend_world = np.zeros(0, dtype=np.int64)
            m.bend_colour_offsets = [0]
        m.bend_count = len(bend_idx)
        m.bend_indices_np = bend_idx.astype(np.int32)

        # CSR of element slots per particle (deterministic gather instead of float atomics).
        slot_vertex = np.concatenate([tri_idx.reshape(-1), bend_idx.reshape(-1)]).astype(np.int64)
        order = np.argsort(slot_vertex, kind="stable")
        adj_start = np.zeros(offset + 1, dtype=np.int64)
        np.cumsum(np.bincount(slot_vertex, minlength=offset), out=adj_start[1:])

        # Jacobi share per element: 1 / (most elements of its kind meeting at any of its corners).
        # Shares are per kind (triangles, bending) so the soft bending elements do not dilute the
        # membrane's step: on a 31x31 drape this halves the under-iteration stretch of Jacobi.
        n_tri = np.bincount(tri_idx.reshape(-1), minlength=offset).astype(np.float64)
        n_bend = np.bincount(bend_idx.reshape(-1), minlength=offset).astype(np.float64)
        tri_scale = 1.0 / n_tri[tri_idx].max(axis=1) if len(tri_idx) else np.zeros(0)
        bend_scale = 1.0 / n_bend[bend_idx].max(axis=1) if len(bend_idx) else np.zeros(0)

        att_idx = np.concatenate(att).astype(np.int32) if feats.attachments else np.zeros(0, dtype=np.int32)
        m.attachment_count = len(att_idx)
        m.attachment_particle_np = att_idx
        p_att = np.full(offset, -1, dtype=np.int32)
        p_att[att_idx] = np.arange(len(att_idx), dtype=np.int32)

        def arr(a: np.ndarray, dtype: object, min_len: int = 1) -> wp.array:
            a = np.asarray(a)
            if len(a) < min_len:  # Warp kernels need a non-empty array argument.
                a = np.zeros((min_len,) + a.shape[1:], dtype=a.dtype)
            return wp.array(a, dtype=dtype, device=device)

        m.particle_mass = arr(m.particle_mass_np, wp.float32)
        m.particle_inv_mass = arr(m.particle_inv_mass_np, wp.float32)
        m.particle_world = arr(np.concatenate(pworld).astype(np.int32), wp.int32)
        m.particle_world_np = np.concatenate(pworld).astype(np.int32)
        m.particle_radius = arr(np.concatenate(radius).astype(np.float32), wp.float32)
        m.particle_body_part = arr(np.concatenate(body_part).astype(np.int32), wp.int32)
        m.particle_attachment = arr(p_att, wp.int32)
        m.particle_adj_start = arr(adj_start.astype(np.int32), wp.int32)
        m.particle_adj_slot = arr(order.astype(np.int32), wp.int32)
        m.tri_indices = arr(m.tri_indices_np, wp.int32)
        m.tri_dm_inv = arr(dm_inv.astype(np.float32, copy=False), wp.mat22)
        m.tri_area = arr(area.astype(np.float32, copy=False), wp.float32)
        m.tri_compliance = arr(comp.astype(np.float32, copy=False), wp.vec3)
        m.tri_jacobi_scale = arr(tri_scale.astype(np.float32), wp.float32)
        m.bend_jacobi_scale = arr(bend_scale.astype(np.float32), wp.float32)
        m.tri_world = arr(tri_world.astype(np.int32, copy=False), wp.int32)
        m.bend_indices = arr(m.bend_indices_np, wp.int32)
        m.bend_rest_angle = arr(rest.astype(np.float32, copy=False), wp.float32)
        m.bend_compliance = arr(bcomp.astype(np.float32, copy=False), wp.float32)
        m.bend_world = arr(bend_world.astype(np.int32, copy=False), wp.int32)
        m.attachment_particle = arr(att_idx, wp.int32)
        m.world_damping = arr(np.array([g.fabric.damping for g in self._garments], dtype=np.float32), wp.float32)
        m.world_friction = arr(np.array([g.fabric.friction for g in self._garments], dtype=np.float32), wp.float32)
        return m
