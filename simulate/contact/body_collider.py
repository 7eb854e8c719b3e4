"""BodyCollider: the body of every world as one Warp mesh, interpolated per substep.

Its contact planes and signed distances come from ``kernels.query_body`` (Euclidean distance to
the nearest face, side from the closest feature's pseudo-normal, an open cut counting as
outside); ``simulate.contact.closest`` says which body query serves contact, the quality metrics
and the learners, and why.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from simulate.cloth.device_copy import copy_cuda_tensor
from simulate.contact import kernels

__all__ = ["BVH_OPTIONS", "BodyCollider", "world_cell_offsets"]

BVH_OPTIONS = {"bvh_constructor": "sah", "bvh_leaf_size": 1}
"""BVH of the contact meshes (body, cloth self-contact): built once (surface area heuristic, on
the host) and only refit afterwards. ``bench/bench_contact_queries.py`` on an H200, 240 worlds of
the 7.7k t-shirt on anny: against Warp's CUDA default (LBVH, 4 triangles per leaf) the body
refit takes 0.56 instead of 2.27 ms, the body query 1.51 instead of 4.21 ms, the self-contact
query 9.2 instead of 17.5 ms per launch; building both takes 4.5 s instead of 7 ms. (The body
contacts do not depend on the tree: ``closest.nearest_face`` measures every face within the
tree's bound again and gives ties to the lower face index.)"""


def world_cell_offsets(world_count: int, spacing: float, centers: np.ndarray | None = None) -> np.ndarray:
    """Offsets [m] (world_count, 3) float32 that place world w in cell (w % n, (w // n) % n, w // n^2)
    of a cube grid, n = ceil(cbrt(world_count)).  Contact meshes of all worlds live in one ``wp.Mesh``
    at these offsets, so one refit and one query launch serve every world.

    The cells are ``S`` = ``spacing`` rounded up to a power of two apart and all lie in one binade
    [B, 2B) of float32 on every axis, B = 8 S for up to 512 worlds (the power of two >= n S beyond);
    each offset is B + S (cell + 1/2) minus the world's centre rounded to a multiple of S / 8, so
    it is a multiple of S / 8. A local coordinate x within S / 2 of that rounded centre then
    shifts to ``x + offset`` rounded to the grid of B's ulp (B / 2^23) the same way in every world,
    and ``(x + offset) - offset`` is exact: the same geometry gives the same float32 numbers,
    relative to its cell, in any world of any grid of up to 512 worlds (B = 64 m for the anny
    body, S = 8 m: a grid of 7.6 um).

    Args:
        world_count: number of worlds.
        spacing: smallest distance between cells [m] (> 0).
        centers: (world_count, 3) [m] centre of each world's geometry, or None (the origin).
    """
    if not (math.isfinite(spacing) and spacing > 0.0):
        raise ValueError(f"spacing must be a finite number > 0 [m] (got {spacing!r})")
    n = max(1, math.ceil(round(world_count ** (1.0 / 3.0), 9)))
    cell = 2.0 ** math.ceil(math.log2(spacing))
    base = 2.0 ** math.ceil(math.log2(max(n, 8) * cell))
    w = np.arange(world_count)
    cells = np.stack([w % n, (w // n) % n, w // (n * n)], axis=1).astype(np.float64)
    if centers is None:
        centers = np.zeros((world_count, 3))
    shift = np.round(np.asarray(centers, np.float64).reshape(world_count, 3) / (cell / 8.0)) * (cell / 8.0)
    return (base + cell * (cells + 0.5) - shift).astype(np.float32)


def _is_tensor(value) -> bool:
    return type(value).__module__.startswith("torch")


def _host(vertices):
    """A torch tensor as a host numpy array; anything else unchanged."""
    return vertices.detach().cpu().numpy() if _is_tensor(vertices) else vertices


class BodyCollider:
    """Body meshes of ``world_count`` worlds packed into one ``wp.Mesh``.

    World ``w``'s body is shifted by ``world_offset[w]`` (a cell of a 3-D grid,
    :func:`world_cell_offsets`); particles of world ``w`` query the mesh at their position plus
    the same offset, with a maximum distance far below the cell spacing, so one BVH refit and one
    query launch serve every world.

    A world's answers do not depend on its cell. The cells are placed so that the shift rounds
    every world's body to the same float32 grid (:func:`world_cell_offsets`; the anny body in up
    to 512 worlds sits at 64-128 m, on a grid of 7.6 um, so each vertex moves by at most 3.8 um),
    and the queries (``kernels.query_body``) use the shifted mesh only to bound the distance:
    they measure the nearest face again in the world's own coordinates (mesh points minus the
    offset, exact in that binade) and give ties to the lower face index. The same body and cloth
    so get the same contact planes and signed distances, and the same garment the same drape,
    bit for bit in every world of any collider of up to 512 worlds (beyond, the grid coarsens
    with the world count). Contact amplifies any difference: shifted by offsets that round each
    world differently (cells at multiples of ~3 extent + 2 m from the origin, world 0 unshifted)
    and measured in shifted coordinates, where float32 resolves ~4 um at 50 m, the same 30 x 30
    cloth dropped on the bench-pose anny in 4 worlds was up to 10 mm apart after 20 frames (median
    0.34 mm) and 1.2 m after 100 (it slides off the shoulder one way or another), and a 12 x 12
    cloth on a capsule in 27 worlds rested up to 8 mm apart after 40 frames. This holds while
    every body vertex stays within half a cell (4 m for anny) of the centre its cell was placed
    around at construction, and rests on the solvers' per-world arithmetic being deterministic
    (no float atomics). Self-contact (``SelfContact``) also measures in world-local coordinates,
    ties going to the lower face index.

    Body motion: ``set_target`` sets the pose at the end of the next frame; the driver calls
    ``update(alpha)`` before each substep (linear interpolation between the frame's start and
    end pose, then one refit) and ``finish_frame()`` after the last one.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        device: wp.context.Devicelike = None,
        thickness: float = 2.0e-3,
        margin: float = 2.0e-2,
        world_count: int | None = None,
        face_groups: list[np.ndarray] | None = None,
    ) -> None:
        """
        Args:
            vertices: body vertices [m], shape (W, Vb, 3), or (Vb, 3) shared by ``world_count`` worlds.
            faces: triangles, shape (Fb, 3); any subset of the body's faces (unreferenced
                vertices are dropped internally, see ``vertex_map``).
            device: Warp device.
            thickness: contact distance kept between the body surface and the cloth [m]
                (half the fabric thickness is added per particle).
            margin: extra search distance beyond the contact distance when contact planes are
                found once per substep [m]; must exceed how far cloth moves in one substep.
            world_count: number of worlds when ``vertices`` is (Vb, 3) (default 1).
            face_groups: primary collision bodies (``simulate.body.collision_parts``): per part, the
                rows of ``faces`` in its collision mesh (may overlap). A particle then meets only the
                part ``ClothModel.particle_body_part`` names (index into this list). None: one
                part, the whole of ``faces``.
        """
        verts = np.asarray(vertices, dtype=np.float64)
        if verts.ndim == 2:
            verts = np.broadcast_to(verts, (world_count or 1,) + verts.shape)
        elif world_count is not None and verts.ndim == 3 and verts.shape[0] != world_count:
            raise ValueError(f"vertices has {verts.shape[0]} worlds but world_count={world_count}")
        if verts.ndim != 3 or verts.shape[2] != 3 or verts.shape[1] < 3 or verts.shape[0] < 1:
            raise ValueError(f"vertices must have shape (W, Vb, 3) or (Vb, 3) (got {np.shape(vertices)})")
        if not np.all(np.isfinite(verts)):
            raise ValueError("vertices must be finite (got NaN or inf)")
        tris = np.asarray(faces)
        if tris.ndim != 2 or tris.shape[1] != 3 or tris.shape[0] < 1 or not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"faces must be an integer array of shape (Fb, 3) (got {tris.shape}, {tris.dtype})")
        if tris.min() < 0 or tris.max() >= verts.shape[1]:
            raise ValueError(f"faces index range [{tris.min()}, {tris.max()}] outside [0, {verts.shape[1]})")
        for name, value in (("thickness", thickness), ("margin", margin)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0 [m] (got {value!r})")
        self.device = wp.get_device(device)
        self.thickness = float(thickness)
        self.margin = float(margin)
        self.world_count = int(verts.shape[0])
        self.source_vertex_count = int(verts.shape[1])
        self.vertex_map, local = np.unique(tris.reshape(-1), return_inverse=True)
        """Indices of the given vertices kept in the mesh (those referenced by ``faces``)."""
        self.faces = local.reshape(-1, 3).astype(np.int32)
        """Faces in compact vertex numbering, shape (Fb, 3)."""
        self.vertex_count = len(self.vertex_map)
        compact = verts[:, self.vertex_map]  # (W, Vk, 3)

        # World cells: a cube grid with spacing well above body extent + cloth excursion, each
        # centred on its body (the body then lies within extent / 2 + spacing / 16 of the centre)
        lo, hi = compact.min(axis=1), compact.max(axis=1)
        extent = float(np.max(hi - lo))
        self.world_offset_np = world_cell_offsets(self.world_count, 3.0 * extent + 2.0, 0.5 * (lo + hi))
        self.world_spacing = float(2.0 ** math.ceil(math.log2(3.0 * extent + 2.0)))
        """Distance between world cells [m] (a power of two)."""
        self.world_offset = wp.array(self.world_offset_np, dtype=wp.vec3, device=self.device)
        """Offset of each world's cell [m], shape (world_count,)."""

        w = np.arange(self.world_count)
        self.vertex_world = wp.array(np.repeat(w, self.vertex_count).astype(np.int32), device=self.device)
        flat = compact.reshape(-1, 3).astype(np.float32)
        self.pose_start = wp.array(flat, dtype=wp.vec3, device=self.device)
        """Body positions at the start of the current frame [m], shape (W * Vk,)."""
        self.pose_end = wp.array(flat, dtype=wp.vec3, device=self.device)
        """Body positions at the end of the current frame [m], shape (W * Vk,)."""
        indices = (self.faces[None, :, :] + (w * self.vertex_count)[:, None, None]).astype(np.int32)
        self.mesh_indices = wp.array(indices.reshape(-1), dtype=wp.int32, device=self.device)
        points = wp.array(flat + np.repeat(self.world_offset_np, self.vertex_count, axis=0),
                          dtype=wp.vec3, device=self.device)
        self.mesh = wp.Mesh(points=points, indices=self.mesh_indices, **BVH_OPTIONS)
        """All faces of every world: the signed distance's mesh, and the contact mesh without parts."""
        self.part_meshes: list[wp.Mesh] = []
        """Per collision part, a mesh of its faces over the same points (empty without ``face_groups``)."""
        if face_groups is not None:
            if len(face_groups) < 1:
                raise ValueError("face_groups must hold at least one group of face rows (got none)")
            for k, rows in enumerate(face_groups):
                rows = np.asarray(rows)
                if rows.ndim != 1 or len(rows) < 1 or not np.issubdtype(rows.dtype, np.integer) or \
                        rows.min() < 0 or rows.max() >= len(self.faces):
                    raise ValueError(f"face_groups[{k}] must be a non-empty integer array of rows in [0, {len(self.faces)}) "
                                     f"(got shape {rows.shape}, dtype {rows.dtype})")
                part = self.faces[rows]
                idx = (part[None, :, :] + (w * self.vertex_count)[:, None, None]).astype(np.int32).reshape(-1)
                self.part_meshes.append(wp.Mesh(points=points, indices=wp.array(idx, dtype=wp.int32, device=self.device),
                                                **BVH_OPTIONS))
        self.part_count = max(1, len(self.part_meshes))
        """Collision parts: 1 without ``face_groups``."""
        self.contact_meshes = wp.array([m.id for m in (self.part_meshes or [self.mesh])], dtype=wp.uint64,
                                       device=self.device)
        """Mesh id per collision part, (part_count,) uint64: the meshes the contact planes come from."""
        self._full_stale = False
        self.motion_scale = 0.0
        """Fraction of the frame's body motion covered by one substep (set by the driver)."""

    # ---------------------------------------------------------------- poses
    def _compact(self, vertices: np.ndarray, *, worlds: int | None = None) -> np.ndarray:
        """Checked, culled, flattened body vertices of ``worlds`` worlds (default all), (worlds * Vk, 3);
        (Vb, 3) input is shared by those worlds."""
        worlds = self.world_count if worlds is None else worlds
        verts = np.asarray(vertices, dtype=np.float32)
        if verts.ndim == 2:
            verts = np.broadcast_to(verts, (worlds,) + verts.shape)
        if verts.ndim != 3 or verts.shape[0] != worlds or verts.shape[2] != 3 or \
                verts.shape[1] not in (self.source_vertex_count, self.vertex_count):
            raise ValueError(f"body vertices must have shape ({worlds}, {self.source_vertex_count} or "
                             f"{self.vertex_count}, 3) (got {np.shape(vertices)})")
        if not np.all(np.isfinite(verts)):
            raise ValueError("body vertices must be finite (got NaN or inf)")
        if verts.shape[1] == self.source_vertex_count:
            verts = verts[:, self.vertex_map]
        return np.ascontiguousarray(verts.reshape(-1, 3))

    def set_target(self, vertices) -> None:
        """Body pose at the end of the next frame [m], shape (W, Vb, 3) or (Vb, 3) for all worlds.

        ``vertices`` may be a numpy array or a torch tensor; a CUDA tensor on a CUDA collider is
        culled and copied without leaving the device.
        """
        if _is_tensor(vertices) and vertices.is_cuda and self.device.is_cuda:
            self._set_target_cuda_tensor(vertices)
            return
        self.pose_end.assign(self._compact(_host(vertices)))

    def _set_target_cuda_tensor(self, vertices) -> None:
        import torch

        t = vertices.detach()
        if t.dim() != 3 or t.shape[0] != self.world_count or t.shape[2] != 3 or \
                t.shape[1] not in (self.source_vertex_count, self.vertex_count):
            raise ValueError(f"body vertices must have shape ({self.world_count}, {self.source_vertex_count} or "
                             f"{self.vertex_count}, 3) (got {tuple(t.shape)})")
        if not bool(torch.isfinite(t).all()):
            raise ValueError("body vertices must be finite (got NaN or inf)")
        if t.shape[1] == self.source_vertex_count:
            if getattr(self, "_vertex_map_torch", None) is None or self._vertex_map_torch.device != t.device:
                self._vertex_map_torch = torch.as_tensor(self.vertex_map, device=t.device)
            t = t[:, self._vertex_map_torch]
        copy_cuda_tensor(self.pose_end, t.reshape(-1, 3))

    def set_pose(self, vertices: np.ndarray) -> None:
        """Place the body at ``vertices`` [m] now (no interpolation), shape as in ``set_target``."""
        flat = self._compact(vertices)
        self.pose_start.assign(flat)
        self.pose_end.assign(flat)
        self.update(1.0)

    def compact_world(self, vertices) -> wp.array:
        """One world's body vertices [m], (Vb, 3) (source or culled count; numpy or torch), checked
        and culled once into a (Vk,) vec3 array on the collider's device: ``place_world`` then
        copies it without a host round trip (a body put back thousands of times)."""
        verts = np.asarray(_host(vertices), dtype=np.float32)
        if verts.ndim != 2:
            raise ValueError(f"body vertices must have shape ({self.source_vertex_count} or {self.vertex_count}, 3) "
                             f"(got {verts.shape})")
        return wp.array(self._compact(verts, worlds=1), dtype=wp.vec3, device=self.device)

    def place_world(self, world: int, vertices) -> None:
        """Place one world's body at ``vertices`` [m] now, shape (Vb, 3) (source or culled count),
        or a ``compact_world`` array.

        The other worlds keep their start and target poses; call ``update`` (the driver does at
        the next substep) to move the mesh.
        """
        if not 0 <= int(world) < self.world_count:
            raise ValueError(f"world must be in [0, {self.world_count}) (got {world!r})")
        if isinstance(vertices, wp.array):
            if vertices.dtype != wp.vec3 or vertices.shape != (self.vertex_count,) or vertices.device != self.device:
                raise ValueError(f"a placed body array must be compact_world's: {wp.vec3.__name__} ({self.vertex_count},) on "
                                 f"{self.device} (got {vertices.dtype.__name__} {vertices.shape} on {vertices.device})")
            src = vertices
        else:
            src = self.compact_world(vertices)
        offset = int(world) * self.vertex_count
        for dst in (self.pose_start, self.pose_end):
            wp.copy(dst, src, dest_offset=offset, src_offset=0, count=self.vertex_count)

    def update(self, alpha: float) -> None:
        """Move the mesh to fraction ``alpha`` in [0, 1] of the frame's motion and refit the BVH."""
        wp.launch(kernels.interpolate_body_points, dim=len(self.pose_start),
                  inputs=[self.pose_start, self.pose_end, self.vertex_world, self.world_offset, float(alpha)],
                  outputs=[self.mesh.points], device=self.device)
        for mesh in self.part_meshes:
            mesh.refit()
        if self.part_meshes:
            self._full_stale = True  # refit when a signed distance asks for it
        else:
            self.mesh.refit()

    def finish_frame(self) -> None:
        """The end pose becomes the next frame's start pose."""
        wp.copy(self.pose_start, self.pose_end)

    # ---------------------------------------------------------------- queries
    def signed_distance(self, points: np.ndarray | wp.array, point_world: np.ndarray | wp.array, *,
                        max_dist: float = 1.0, point_part: np.ndarray | wp.array | None = None) -> np.ndarray:
        """Signed distance [m] of points to their world's body at its current pose.

        The Euclidean distance to the nearest face, negative where the closest feature's
        pseudo-normal says inside (``kernels.query_body``, the query the contact planes use): a
        point outside the body is never negative, also past the open cut of a culled part or
        where skins interpenetrate; a point inside one part but nearest to the skin of another
        sunk into it (an arm in the torso), or nearest to the rim of a cut, reads positive.

        Args:
            points: (N, 3) [m]; point_world: (N,) world index per point.
            max_dist: search radius [m]; points farther away report ``max_dist``, inside or not.
            point_part: (N,) collision part per point (``face_groups`` index): the distance to that
                part only; None: to the whole body.
        Returns:
            (N,) float32, negative inside the body; bit for bit the same in every world cell.
        """
        pts = points if isinstance(points, wp.array) else wp.array(np.asarray(points, np.float32), dtype=wp.vec3,
                                                                    device=self.device)
        pw = point_world if isinstance(point_world, wp.array) else wp.array(
            np.asarray(point_world, np.int32), dtype=wp.int32, device=self.device)
        if len(pts) != len(pw):
            raise ValueError(f"points ({len(pts)}) and point_world ({len(pw)}) must have the same length")
        dist = wp.zeros(len(pts), dtype=float, device=self.device)
        normal = wp.zeros(len(pts), dtype=wp.vec3, device=self.device)
        if point_part is None:
            if self._full_stale:
                self.mesh.refit()
                self._full_stale = False
            meshes = wp.array([self.mesh.id], dtype=wp.uint64, device=self.device)
            part = wp.zeros(len(pts), dtype=wp.int32, device=self.device)
        else:
            meshes = self.contact_meshes
            part = point_part if isinstance(point_part, wp.array) else wp.array(
                np.asarray(point_part, np.int32), dtype=wp.int32, device=self.device)
            if len(part) != len(pts):
                raise ValueError(f"points ({len(pts)}) and point_part ({len(part)}) must have the same length")
        wp.launch(kernels.query_signed_distance, dim=len(pts),
                  inputs=[meshes, self.world_offset, pts, pw, part, float(max_dist)], outputs=[dist, normal],
                  device=self.device)
        return dist.numpy()
