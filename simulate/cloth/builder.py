"""ClothBuilder: checks garments and packs them, one garment per world, into a ClothModel."""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import warp as wp

from simulate.cloth.fabric import Fabric, resolve_fabric
from simulate.cloth.model import ClothModel, Features

__all__ = ["ClothBuilder", "greedy_colour", "dihedral_angles", "triangle_rest_frames"]

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


def triangle_rest_frames(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse rest-frame matrices and areas of triangles.

    The rest frame of face (i0, i1, i2) has its first axis along x1 - x0 and its second in the
    triangle plane, so ``F = [x1 - x0, x2 - x0] @ Dm_inv`` is the (3, 2) deformation gradient.

    Returns:
        dm_inv (F, 2, 2) [1/m] and area (F,) [m^2].
    """
    x0, x1, x2 = (vertices[faces[:, k]].astype(np.float64) for k in range(3))
    e1, e2 = x1 - x0, x2 - x0
    cross = np.cross(e1, e2)
    double_area = np.linalg.norm(cross, axis=1)
    len1 = np.linalg.norm(e1, axis=1)
    u = e1 / np.maximum(len1, 1e-30)[:, None]
    n = cross / np.maximum(double_area, 1e-30)[:, None]
    v = np.cross(n, u)
    e2u = np.einsum("ij,ij->i", e2, u)
    e2v = np.einsum("ij,ij->i", e2, v)
    dm_inv = np.zeros((len(faces), 2, 2))
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate faces are rejected by the caller
        dm_inv[:, 0, 0] = 1.0 / len1
        dm_inv[:, 0, 1] = -e2u / (len1 * e2v)
        dm_inv[:, 1, 1] = 1.0 / e2v
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


def _mesh_digest(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A 128-bit digest of a garment's rest vertices and faces (as the builder stores them):
    garments with equal digests are checked and turned into elements once."""
    digest = hashlib.blake2b(digest_size=16)
    for a in (vertices, faces):
        digest.update(str((a.dtype, a.shape)).encode())
        digest.update(np.ascontiguousarray(a).tobytes())
    return digest.digest()


@dataclasses.dataclass
class _Garment:
    vertices: np.ndarray
    faces: np.ndarray
    fabric: Fabric
    pinned: np.ndarray
    attached: np.ndarray
    skinning_weights: np.ndarray | None
    digest: bytes  # of vertices and faces (_mesh_digest)


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
    ) -> int:
        """Add one garment as a new world and return the world index.

        Args:
            vertices: rest (and initial) positions [m], shape (V, 3).
            faces: triangles, shape (F, 3), int indices into ``vertices``.
            fabric: a Fabric or a preset name from ``FABRICS``.
            pinned: vertex indices (or a (V,) bool mask) fixed in space (inverse mass 0).
            attached: vertex indices (or mask) pulled by soft, releasable springs to targets.
            skinning_weights: per-vertex skinning weights, shape (V, J), kept for callers.
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
        digest = _mesh_digest(verts, tris)
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
        self._garments.append(_Garment(verts, tris, fab, pinned_idx, attached_idx, weights, digest))
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
        triangles (colour (F,), dm_inv (F, 2, 2), area (F,) [m^2], compliance (F, 3)); bending
        stencils (indices (E, 4), colour (E,), rest angle (E,) [rad], compliance (E,)), or None
        without bending or interior edges. Computed in float64; the per-element values are
        returned as the float32 the model stores (casting before packing is what casting after
        gives, with half the bytes to pack)."""
        dm_inv, area = triangle_rest_frames(g.vertices, g.faces)
        vmass = np.zeros(len(g.vertices))
        np.add.at(vmass, g.faces.reshape(-1), np.repeat(area / 3.0, 3) * g.fabric.density)
        bend, tri_colour, bend_colour = self._topology(g.faces)
        comp = np.stack([1.0 / (g.fabric.stretch_stiffness * area)] * 2
                        + [1.0 / (g.fabric.shear_stiffness * area)], axis=1)
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
        q, mass, inv_mass, pworld, radius = [], [], [], [], []
        tri_parts, bend_parts = [], []  # per world: (indices global, colours, extra arrays)
        att = []
        offset = 0
        # garments that share rest geometry, faces and fabric (a dataset batch: ~40 styles in 256
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
