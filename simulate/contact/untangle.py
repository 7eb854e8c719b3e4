"""Untangling of cloth that already passes through itself: intersection contour minimization
(Volino and Magnenat-Thalmann 2006, "Resolving surface collisions through intersection contour
minimization").

Where the cloth passes through itself, its triangles intersect pairwise along curves (the
intersection contours: closed loops, or curves from boundary to boundary). Shrinking a contour
to nothing removes the intersection, whichever layer is on which side, so no side has to be
guessed. The contour's vertices are the edge-triangle crossings (``simulate.quality`` counts
them): edge ``pq`` pierces triangle ``abc`` at ``P``, and from ``P`` the contour runs, in the
plane of ``abc``, into each triangle ``g`` beside the edge, along the unit direction ``R_g``
(the line where the two planes meet, pointing into ``g``). Moving the edge by ``d`` relative to
the triangle moves ``P`` within the plane of ``abc`` (normal ``N``, edge direction ``E``) by
``d - E (N.d) / (N.E)``, so the contour segments leaving ``P`` (their far ends held) shorten at
the rate ``G.d`` with

    G = sum_g R_g - (N (E.R_g) / (E.N)) * normal_factor          (``normal_factor`` 1)

the direction of steepest descent of their length (``crossing_descent``; Volino's paper writes
the normal term with the factor 2, which ``normal_factor=2`` gives). Each crossing moves the
edge's two ends along ``G / |G|`` (weights: where ``P`` divides the edge) and the triangle's
corners against it (weights: ``P``'s barycentric coordinates); each particle then takes a step of
at most ``step x thickness`` along the sum of its crossings' pushes.

A call is five launches for all worlds (points into their world cells, BVH refit, the per-world
crossing counts zeroed, one thread per cloth edge querying the cloth BVH for the triangles its box
overlaps and testing each crossing exactly (``simulate.contact.crossing``, the quality metric's
test), one thread per particle applying the step) and no transfer to the host. Pushes are summed
in fixed point (int32 atomics), so the result does not depend on the order threads add them: the
same positions give the same positions on every run and device. A world without crossings is not
written. None of this is compiled or allocated unless a solver is built with ``untangle``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simulate.cloth.model import ClothModel
from simulate.contact.body_collider import BVH_OPTIONS, world_cell_offsets
from simulate.contact.closest import closest_point_barycentric, shift_tolerance
from simulate.contact.crossing import segment_hits_triangle
from simulate.contact.self_contact import place_cloth_points

wp.set_module_options({"enable_backward": False})

__all__ = ["Untangler", "crossing_descent", "edge_opposite_vertices"]

STEP = 0.5
"""Default largest step of a particle per call, as a share of the thickness."""

FIXED_POINT_SCALE = float(1 << 20)
"""Pushes are summed as integers of 1 / 2^20 (a push is a unit vector times weights <= 1, so
int32 holds the sum of 2,000 of them on a particle)."""


@wp.func
def crossing_descent(p: wp.vec3, q: wp.vec3, hit: wp.vec3, n: wp.vec3, o: wp.vec3, normal_factor: float) -> wp.vec3:
    """Descent direction (not normalized) of the length of the contour segment that leaves the
    crossing point ``hit`` of edge ``pq`` with the plane of unit normal ``n``, into the triangle
    ``p q o`` beside the edge, for a motion of the edge relative to the plane (module docstring);
    zero where the two planes are parallel."""
    e = q - p
    e_len = wp.length(e)
    ng = wp.cross(e, o - p)
    r = wp.cross(n, ng)
    r_len = wp.length(r)
    if e_len < 1.0e-12 or r_len < 1.0e-12 * wp.length(ng) or r_len == 0.0:
        return wp.vec3(0.0)
    r = r / r_len
    if wp.dot(r, o - hit) < 0.0:  # into the triangle beside the edge
        r = -r
    e = e / e_len
    en = wp.dot(e, n)
    # a crossing edge is never parallel to the plane; the clamp only keeps a grazing one finite
    en = wp.where(en >= 0.0, wp.max(en, 1.0e-3), wp.min(en, -1.0e-3))
    return r - n * (normal_factor * wp.dot(e, r) / en)


@wp.func
def add_push(push: wp.array2d(dtype=wp.int32), i: int, d: wp.vec3, scale: float):
    """Adds ``d`` to particle ``i``'s push in fixed point (order-independent sums)."""
    wp.atomic_add(push, i, 0, wp.int32(wp.round(d[0] * scale)))
    wp.atomic_add(push, i, 1, wp.int32(wp.round(d[1] * scale)))
    wp.atomic_add(push, i, 2, wp.int32(wp.round(d[2] * scale)))


@wp.kernel
def accumulate_contour_pushes(
    mesh: wp.uint64,
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_world: wp.array(dtype=wp.int32),
    edges: wp.array(dtype=wp.vec2i),
    edge_opposite: wp.array(dtype=wp.vec2i),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_enabled: wp.array(dtype=wp.int32),
    world_offset: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    normal_factor: float,
    scale: float,
    # Out (zero on entry):
    push_out: wp.array2d(dtype=wp.int32),
    crossings_out: wp.array(dtype=wp.int32),
):
    """One thread per cloth edge: every triangle of the same world that the edge crosses and does
    not touch (the exact test of ``simulate.quality``) adds the contour descent of the crossing to
    the edge's ends and its opposite to the triangle's corners (fixed point, ``scale`` per metre of
    weighted unit push), and counts into its world's ``crossings_out``."""
    e = wp.tid()
    i0 = edges[e][0]
    i1 = edges[e][1]
    w = particle_world[i0]
    if world_active[w] == 0 or world_enabled[w] == 0:
        return
    p = x[i0]
    q = x[i1]
    if not (wp.isfinite(wp.length_sq(p)) and wp.isfinite(wp.length_sq(q))):
        return
    off = world_offset[w]
    tol = shift_tolerance(off)
    r = wp.vec3(tol, tol, tol)
    query = wp.mesh_query_aabb(mesh, wp.min(p, q) + off - r, wp.max(p, q) + off + r)
    face = int(0)
    count = int(0)
    while wp.mesh_query_aabb_next(query, face):
        if tri_world[face] != w:
            continue
        a = tri_indices[face, 0]
        b = tri_indices[face, 1]
        c = tri_indices[face, 2]
        if a == i0 or a == i1 or b == i0 or b == i1 or c == i0 or c == i1:
            continue
        xa = x[a]
        xb = x[b]
        xc = x[c]
        if not segment_hits_triangle(p, q, xa, xb, xc):
            continue
        count += 1
        n = wp.cross(xb - xa, xc - xa)
        n_len = wp.length(n)
        if n_len == 0.0:
            continue
        n = n / n_len
        dp = wp.abs(wp.dot(n, p - xa))
        dq = wp.abs(wp.dot(n, q - xa))
        s = wp.where(dp + dq > 0.0, dp / (dp + dq), 0.5)  # the crossing is at p + s (q - p)
        hit = p + (q - p) * s
        g = wp.vec3(0.0)
        o0 = edge_opposite[e][0]
        o1 = edge_opposite[e][1]
        if o0 >= 0:
            g += crossing_descent(p, q, hit, n, x[o0], normal_factor)
        if o1 >= 0:
            g += crossing_descent(p, q, hit, n, x[o1], normal_factor)
        g_len = wp.length(g)
        if g_len < 1.0e-9:  # a contour through the crossing with no first-order shortening
            continue
        g = g / g_len
        add_push(push_out, i0, g * (1.0 - s), scale)
        add_push(push_out, i1, g * s, scale)
        bary = closest_point_barycentric(hit, xa, xb, xc)
        add_push(push_out, a, -g * bary[0], scale)
        add_push(push_out, b, -g * bary[1], scale)
        add_push(push_out, c, -g * bary[2], scale)
    if count > 0:
        wp.atomic_add(crossings_out, w, count)


@wp.kernel
def apply_contour_pushes(
    inv_mass: wp.array(dtype=float),
    max_step: float,
    scale: float,
    has_x64: int,
    inv_dt: float,
    # In/out:
    push: wp.array2d(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    x64: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3),
):
    """Moves each movable particle with a push by at most ``max_step`` [m] along it (the full
    ``max_step`` once the summed weights reach 1), and zeroes the push for the next call. With
    ``has_x64`` the float64 positions ``x64`` move and ``x`` takes their rounding; with ``inv_dt``
    > 0 [1/s] the velocities ``v`` gain the step times ``inv_dt``."""
    i = wp.tid()
    if push[i, 0] == 0 and push[i, 1] == 0 and push[i, 2] == 0:
        return
    d = wp.vec3(float(push[i, 0]), float(push[i, 1]), float(push[i, 2])) / scale
    push[i, 0] = 0
    push[i, 1] = 0
    push[i, 2] = 0
    if inv_mass[i] == 0.0:
        return
    step = d * (max_step / wp.max(wp.length(d), 1.0))
    if has_x64 != 0:
        p = x64[i] + wp.vec3d(wp.float64(step[0]), wp.float64(step[1]), wp.float64(step[2]))
        x64[i] = p
        x[i] = wp.vec3(float(p[0]), float(p[1]), float(p[2]))
    else:
        x[i] = x[i] + step
    if inv_dt > 0.0:
        v[i] = v[i] + step * inv_dt


def edge_opposite_vertices(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges of a triangle mesh and, for each, the vertices opposite it in the (at most
    two) triangles beside it.

    Args:
        faces: (F, 3) int triangle corners.
    Returns:
        (edges (E, 2) int32, lower index first, sorted; opposite (E, 2) int32, -1 where the edge
        has one triangle; an edge of more than two triangles keeps the first two).
    """
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if not len(f):
        return np.zeros((0, 2), np.int32), np.zeros((0, 2), np.int32)
    pairs = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    third = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    ends = np.sort(pairs, axis=1)
    # one int64 key per edge (lower * n + upper) sorts as the (lower, upper) rows do; one stable
    # sort of the keys groups each edge's triangles in face order (256 worlds of a 7.7k t-shirt:
    # a fraction of a second, against seconds for np.unique over rows)
    n = int(f.max()) + 1
    key = ends[:, 0] * n + ends[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.flatnonzero(np.concatenate([[True], ks[1:] != ks[:-1]]))
    count = np.diff(np.concatenate([first, [len(ks)]]))
    edges = np.stack([ks[first] // n, ks[first] % n], axis=1)
    opposite = np.full((len(edges), 2), -1, np.int64)
    opposite[:, 0] = third[order[first]]
    two = count > 1
    opposite[two, 1] = third[order[first[two] + 1]]
    return edges.astype(np.int32), opposite.astype(np.int32)


class Untangler:
    """Buffers and launches of intersection contour minimization for one ClothModel (module
    docstring): each :meth:`apply` moves the particles of crossing edges and triangles a bounded
    step toward shorter intersection contours, in every world at once."""

    def __init__(self, model: ClothModel, *, thickness: float | None = None, step: float = STEP,
                 normal_factor: float = 1.0, every: int = 1, share_mesh_of=None) -> None:
        """
        Args:
            model: cloth model.
            thickness: length [m] the step is a share of; default the largest fabric thickness of
                the model, at least 2 mm (as :class:`~simulate.contact.self_contact.SelfContact`).
            step: largest displacement of a particle per :meth:`apply`, as a share of
                ``thickness``, in (0, 1]. A crossing moves its edge and its triangle each by up to
                this, so the two close in on each other by up to twice the step.
            normal_factor: weight of the normal term of the contour descent (module docstring), in
                [0, 4]: 1 is the steepest descent of the contour segments' length at a crossing;
                Volino and Magnenat-Thalmann write 2.
            every: a solver applies it on every ``every``-th substep of a frame (substeps 0,
                every, 2 every, ...); the search for crossings is most of its cost.
            share_mesh_of: a :class:`~simulate.contact.self_contact.SelfContact` of the same model:
                its cloth BVH (same world cells) serves here too instead of a second one (the
                BVH's build is seconds of host time for hundreds of worlds). Each user places the
                points and refits before it queries, so neither sees the other's positions.
        """
        self.model = model
        dev = model.device
        if thickness is None:
            thickness = max(2.0e-3, max((f.thickness for f in model.fabrics), default=0.0))
        if not (np.isfinite(thickness) and thickness > 0.0):
            raise ValueError(f"untangle thickness must be > 0 [m] (got {thickness!r})")
        if not (np.isfinite(step) and 0.0 < step <= 1.0):
            raise ValueError(f"untangle step must be in (0, 1] (a share of the thickness) (got {step!r})")
        if not (np.isfinite(normal_factor) and 0.0 <= normal_factor <= 4.0):
            raise ValueError(f"untangle normal_factor must be in [0, 4] (got {normal_factor!r})")
        if int(every) != every or every < 1:
            raise ValueError(f"untangle every must be an integer >= 1 (got {every!r})")
        self.every = int(every)
        self.thickness = float(thickness)
        self.step = float(step)
        self.normal_factor = float(normal_factor)
        self.max_step = self.step * self.thickness
        """Largest displacement [m] of a particle per call."""
        rest = model.particle_q_rest_np
        count = max(model.particle_count, 1)
        if model.particle_count:
            extent = float(np.max(rest.max(axis=0) - rest.min(axis=0)))
            centers = 0.5 * (rest.min(axis=0) + rest.max(axis=0))
        else:
            extent, centers = 0.0, np.zeros(3)
        offsets = world_cell_offsets(model.world_count, 4.0 * extent + 2.0, np.tile(centers, (model.world_count, 1)))
        if share_mesh_of is not None:
            if share_mesh_of.model is not model or not np.array_equal(share_mesh_of.world_offset.numpy(), offsets):
                raise ValueError("share_mesh_of must be a SelfContact of the same model (the same world cells)")
            self.world_offset = share_mesh_of.world_offset
            self.mesh = share_mesh_of.mesh
        else:
            self.world_offset = wp.array(offsets, dtype=wp.vec3, device=dev)
            # built over the rest shape at the world cells and only refit later (see SelfContact)
            self.mesh = wp.Mesh(points=wp.array(rest + offsets[model.particle_world_np], dtype=wp.vec3, device=dev),
                                indices=wp.array(model.tri_indices_np.reshape(-1), dtype=wp.int32, device=dev),
                                **BVH_OPTIONS)
        """Offset [m] of each world's cell in the cloth BVH (``world_offset``, (world_count,) vec3)
        and the BVH (``mesh``) whose points ``apply`` places."""
        edges, opposite = edge_opposite_vertices(model.tri_indices_np)
        self.edges = wp.array(edges, dtype=wp.vec2i, device=dev)
        """Cloth edges (E, 2) int32, each once, lower index first."""
        self.edge_opposite = wp.array(opposite, dtype=wp.vec2i, device=dev)
        """Vertices opposite each edge in the triangles beside it (E, 2), -1 where none."""
        self.push = wp.zeros((count, 3), dtype=wp.int32, device=dev)
        """Summed pushes of the current call, fixed point (``FIXED_POINT_SCALE``), (N, 3) int32; zero between calls."""
        self.crossings = wp.zeros(max(model.world_count, 1), dtype=wp.int32, device=dev)
        """Edge-triangle crossings of each world found by the last :meth:`apply`, before its step,
        (world_count,) int32 (0 for worlds it skipped)."""
        self._no_x64 = wp.zeros(1, dtype=wp.vec3d, device=dev)  # the step kernel's arguments
        self._no_v = wp.zeros(1, dtype=wp.vec3, device=dev)  # without float64 positions or velocities

    def apply(self, x: wp.array, world_active: wp.array, world_self_contact: wp.array | None = None, *,
              x64: wp.array | None = None, v: wp.array | None = None, dt: float = 0.0) -> None:
        """One untangling step, in place: finds the crossings at ``x`` and moves their particles.

        Args:
            x: particle positions [m], (particle_count,) vec3, on the model's device; moved by at
                most ``max_step`` each.
            world_active: (world_count,) int32, worlds with 0 are skipped.
            world_self_contact: (world_count,) int32 or None; worlds with 0 are skipped too
                (``ClothControl.world_self_contact``).
            x64: a solver's float64 positions [m] (particle_count,) vec3d of which ``x`` is the
                rounding: they take the step, ``x`` their rounding.
            v: velocities [m/s] (particle_count,) vec3 that gain the step / ``dt`` [s] (the step
                counts as motion of the substep), for a solver that applies it after its velocities.
        """
        m = self.model
        if m.particle_count == 0 or self.edges.shape[0] == 0:
            return
        if v is not None and not (np.isfinite(dt) and dt > 0.0):
            raise ValueError(f"untangle dt must be > 0 [s] with velocities (got {dt!r})")
        enabled = world_active if world_self_contact is None else world_self_contact
        wp.launch(place_cloth_points, dim=m.particle_count, inputs=[x, m.particle_world, self.world_offset],
                  outputs=[self.mesh.points], device=m.device)
        self.mesh.refit()
        self.crossings.zero_()
        wp.launch(accumulate_contour_pushes, dim=self.edges.shape[0],
                  inputs=[self.mesh.id, m.tri_indices, m.tri_world, self.edges, self.edge_opposite, m.particle_world,
                          world_active, enabled, self.world_offset, x, self.normal_factor, FIXED_POINT_SCALE],
                  outputs=[self.push, self.crossings], device=m.device)
        wp.launch(apply_contour_pushes, dim=m.particle_count,
                  inputs=[m.particle_inv_mass, self.max_step, FIXED_POINT_SCALE, int(x64 is not None),
                          0.0 if v is None else 1.0 / float(dt)],
                  outputs=[self.push, x, self._no_x64 if x64 is None else x64, self._no_v if v is None else v],
                  device=m.device)
