"""Optional cloth self-contact: vertex-triangle repulsion found with a BVH over the cloth.

All worlds' cloth triangles live in one ``wp.Mesh`` whose points are the particles shifted to
per-world grid cells (as for the body), so one refit and one query launch serve every world
and a world never sees another world's cloth.  Once per substep each particle finds the
nearest triangle outside its 2-ring within ``thickness + margin`` (BVH AABB query, exact
point-triangle distance) and remembers which side of it it was on.  In every solver
iteration the particle is then pushed part of the way (``relaxation``) back to ``thickness`` on
that side (one-sided: the particle moves, each triangle's corners are pushed by their own
queries), written to a per-particle delta so results stay deterministic.  None of this runs unless
``Features.self_contact`` is on.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simulate.cloth.model import ClothModel
from simulate.contact.body_collider import BVH_OPTIONS, world_cell_offsets
from simulate.contact.closest import closest_point_barycentric, shift_tolerance

wp.set_module_options({"enable_backward": False})

__all__ = ["SelfContact"]

MAX_SWEEP_M = 0.03
"""Largest extra search reach for a fast particle between candidate searches [m]."""


@wp.kernel
def place_cloth_points(
    x: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=wp.int32),
    world_offset: wp.array(dtype=wp.vec3),
    # Out:
    points_out: wp.array(dtype=wp.vec3),
):
    """Cloth points shifted to their world's cell; non-finite points collapse to the cell corner."""
    i = wp.tid()
    p = x[i]
    off = world_offset[particle_world[i]]
    if wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]):
        points_out[i] = p + off
    else:
        points_out[i] = off


@wp.kernel
def detect_self_contacts(
    mesh: wp.uint64,
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_world: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_self_contact: wp.array(dtype=wp.int32),
    world_offset: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    adj_start: wp.array(dtype=wp.int32),
    adj_slot: wp.array(dtype=wp.int32),
    tri_slots: int,
    x_rest: wp.array(dtype=wp.vec3),
    rest_exclusion: float,
    reach: float,
    v: wp.array(dtype=wp.vec3),
    horizon: float,
    max_sweep: float,
    # Out:
    candidate_out: wp.array(dtype=wp.int32),
    side_out: wp.array(dtype=float),
):
    """Nearest triangle of the same world within ``reach`` [m] (plus the particle's own travel over
    ``horizon`` [s] at its velocity ``v``, at most ``max_sweep`` [m]) outside the particle's
    topological neighbourhood, and the side the particle is on.

    The neighbourhood is every triangle sharing a vertex with a triangle incident to the
    particle (its 2-ring): at cloth resolution these are closer than the contact reach whenever
    the cloth curves or compresses, and repelling them pushed a 7k-vertex shirt apart.  Pairs
    closer than ``rest_exclusion`` [m] in the rest geometry (a garment's armpit crease, where
    sleeve and torso panels meet at an acute angle) are not contacts either. Particles of worlds
    that are not active, or whose ``world_self_contact`` is 0, get no candidate (no push).
    """
    i = wp.tid()
    candidate_out[i] = -1
    w = particle_world[i]
    if world_active[w] == 0 or world_self_contact[w] == 0:
        return
    p = x[i]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])):
        return
    q = p + world_offset[w]
    reach_i = reach + wp.min(wp.length(v[i]) * horizon, max_sweep)
    # the box also covers the float32 rounding of the shifted points; distances are local
    r_box = reach_i + shift_tolerance(world_offset[w])
    r = wp.vec3(r_box, r_box, r_box)
    query = wp.mesh_query_aabb(mesh, q - r, q + r)
    face = int(0)
    best = reach_i
    best_face = int(-1)
    best_side = float(1.0)
    while wp.mesh_query_aabb_next(query, face):
        if tri_world[face] != w:
            continue
        a = tri_indices[face, 0]
        b = tri_indices[face, 1]
        c = tri_indices[face, 2]
        if a == i or b == i or c == i:
            continue
        xa = x[a]
        xb = x[b]
        xc = x[c]
        bary = closest_point_barycentric(p, xa, xb, xc)
        closest = xa * bary[0] + xb * bary[1] + xc * bary[2]
        d = wp.length(p - closest)
        # nearer than the best so far (strictly nearer than the reach while there is none); an
        # equal distance goes to the lower face index, so the BVH's visit order does not matter
        if d > best or (d == best and (best_face < 0 or face > best_face)):
            continue
        # only a would-be nearest triangle pays for the rest-shape and neighbourhood tests; the
        # rest-shape test first: three loads, and at cloth resolution it already excludes most of
        # the 2-ring (either test excludes, so the order does not change the result)
        pr = x_rest[i]
        ra = x_rest[a]
        rb_ = x_rest[b]
        rc = x_rest[c]
        rb = closest_point_barycentric(pr, ra, rb_, rc)
        if wp.length(pr - (ra * rb[0] + rb_ * rb[1] + rc * rb[2])) < rest_exclusion:
            continue
        near = bool(False)
        for s in range(adj_start[i], adj_start[i + 1]):
            slot = adj_slot[s]
            if slot >= tri_slots:  # a particle's slots ascend: its triangles' come before its bending elements'
                break
            t = slot // 3
            u0 = tri_indices[t, 0]
            u1 = tri_indices[t, 1]
            u2 = tri_indices[t, 2]
            if u0 == a or u0 == b or u0 == c or u1 == a or u1 == b or u1 == c or u2 == a or u2 == b or u2 == c:
                near = True
                break
        if near:
            continue
        best = d
        best_face = face
        normal = wp.cross(xb - xa, xc - xa)
        best_side = wp.where(wp.dot(p - closest, normal) >= 0.0, 1.0, -1.0)
    candidate_out[i] = best_face
    side_out[i] = best_side


@wp.func
def self_contact_correction(p: wp.vec3, xa: wp.vec3, xb: wp.vec3, xc: wp.vec3, side: float, thickness: float,
                            relaxation: float):
    """Push [m] of a particle at ``p`` toward ``thickness`` on its ``side`` (+1/-1 along the
    normal of the counter-clockwise triangle abc): ``relaxation`` times the shortfall of its gap
    to the triangle's closest point, zero when the gap is at least ``thickness`` or the triangle
    is degenerate.  Shared by ``project_self_contacts`` and the XPBD tiled sweep, so both push
    alike."""
    n = wp.cross(xb - xa, xc - xa)
    n_len = wp.length(n)
    if n_len < 1.0e-12:
        return wp.vec3(0.0)
    n = n / n_len * side
    bary = closest_point_barycentric(p, xa, xb, xc)
    closest = xa * bary[0] + xb * bary[1] + xc * bary[2]
    gap = wp.dot(p - closest, n)
    if gap < thickness:
        return n * (relaxation * (thickness - gap))
    return wp.vec3(0.0)


@wp.kernel
def project_self_contacts(
    tri_indices: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    candidate: wp.array(dtype=wp.int32),
    side: wp.array(dtype=float),
    thickness: float,
    relaxation: float,
    x: wp.array(dtype=wp.vec3),
    # Out:
    delta_out: wp.array(dtype=wp.vec3),
):
    """Correction [m]: ``relaxation`` times the push back to ``thickness`` on the particle's side of its triangle."""
    i = wp.tid()
    delta_out[i] = wp.vec3(0.0)
    t = candidate[i]
    if t < 0 or inv_mass[i] == 0.0:
        return
    delta_out[i] = self_contact_correction(x[i], x[tri_indices[t, 0]], x[tri_indices[t, 1]], x[tri_indices[t, 2]],
                                           side[i], thickness, relaxation)


class SelfContact:
    """Buffers and launches of vertex-triangle self-contact for one ClothModel."""

    def __init__(self, model: ClothModel, *, thickness: float | None = None, margin: float = 5.0e-3,
                 rest_exclusion: float | None = None, relaxation: float = 0.3, detect_every: int = 1) -> None:
        """
        Args:
            model: cloth model.
            thickness: distance kept between a particle and other triangles [m]; default the
                largest fabric thickness of the model, at least 2 mm.
            margin: extra search distance when candidates are found once per substep [m].
            rest_exclusion: particle-triangle pairs closer than this in the rest geometry are never
                contacts [m]; default twice the contact reach (thickness + margin).
            relaxation: fraction of the push applied per solver iteration, in (0, 1]. The full
                push (1) separates layers but keeps them moving: on a CPU dataset slice (1.8k
                t-shirt, 42 targets) 34 holds of 42 never converged; 0.3: 12 (7 without
                self-contact), and 22 frames kept instead of 6 (16 without).
            detect_every: candidates are found on every ``detect_every``-th substep of a frame
                (the solver's ``step(substep=)``) and reused in between. The search then reaches
                further by the particle's own travel until the next search (speed x the substeps
                in between, at most ``MAX_SWEEP_M``); a layer moving toward a slow particle must
                stay within ``margin``. Detection is the costly part (a BVH query per particle).
        """
        self.model = model
        dev = model.device
        if thickness is None:
            thickness = max(2.0e-3, max(f.thickness for f in model.fabrics))
        if not (np.isfinite(thickness) and thickness > 0.0 and np.isfinite(margin) and margin >= 0.0):
            raise ValueError(f"self-contact thickness must be > 0 and margin >= 0 [m] (got {thickness!r}, {margin!r})")
        self.thickness = float(thickness)
        self.margin = float(margin)
        rest_exclusion = 2.0 * (self.thickness + self.margin) if rest_exclusion is None else float(rest_exclusion)
        if not (np.isfinite(rest_exclusion) and rest_exclusion >= 0.0):
            raise ValueError(f"self-contact rest_exclusion must be >= 0 [m] (got {rest_exclusion!r})")
        self.rest_exclusion = rest_exclusion
        if not (np.isfinite(relaxation) and 0.0 < relaxation <= 1.0):
            raise ValueError(f"self-contact relaxation must be in (0, 1] (got {relaxation!r})")
        self.relaxation = float(relaxation)
        if int(detect_every) != detect_every or detect_every < 1:
            raise ValueError(f"self-contact detect_every must be an integer >= 1 (got {detect_every!r})")
        self.detect_every = int(detect_every)
        rest = model.particle_q_rest_np
        extent = float(np.max(rest.max(axis=0) - rest.min(axis=0)))
        centers = 0.5 * (rest.min(axis=0) + rest.max(axis=0))
        offsets = world_cell_offsets(model.world_count, 4.0 * extent + 2.0, np.tile(centers, (model.world_count, 1)))
        self.world_offset = wp.array(offsets, dtype=wp.vec3, device=dev)
        count = max(model.particle_count, 1)
        # the BVH is built here and only refit later: build it over the points at their world
        # cells, or its nodes span all worlds (identical garments overlap at rest) and every
        # query walks all of them (measured: 40 t-shirts' canonical drapes > 440 s on an H200)
        self.points = wp.array(rest + offsets[model.particle_world_np], dtype=wp.vec3, device=dev)
        self.rest = wp.array(rest, dtype=wp.vec3, device=dev)
        """Rest positions [m] on the model's device (rest-shape exclusion of near pairs)."""
        self.mesh = wp.Mesh(points=self.points, indices=wp.array(model.tri_indices_np.reshape(-1), dtype=wp.int32,
                                                                 device=dev), **BVH_OPTIONS)
        self.candidate = wp.full(count, -1, dtype=wp.int32, device=dev)
        self.side = wp.ones(count, dtype=float, device=dev)
        self.delta = wp.zeros(count, dtype=wp.vec3, device=dev)
        """Per-particle self-contact correction of the current iteration [m]."""

    def detect(self, x: wp.array, world_active: wp.array, v: wp.array | None = None, dt: float = 0.0, *,
               world_self_contact: wp.array | None = None) -> None:
        """Refit the cloth BVH at positions ``x`` and find one candidate triangle per particle.

        With velocities ``v`` [m/s] and the substep ``dt`` [s], the search of each particle also
        covers its travel over the ``detect_every - 1`` substeps until the next search.
        ``world_self_contact`` (int32, (world_count,), optional): worlds with 0 get no candidates,
        so no self-contact push until their next search (``ClothControl.world_self_contact``)."""
        m = self.model
        wp.launch(place_cloth_points, dim=m.particle_count, inputs=[x, m.particle_world, self.world_offset],
                  outputs=[self.mesh.points], device=m.device)
        self.mesh.refit()
        wp.launch(detect_self_contacts, dim=m.particle_count,
                  inputs=[self.mesh.id, m.tri_indices, m.tri_world, m.particle_world, world_active,
                          world_active if world_self_contact is None else world_self_contact, self.world_offset,
                          x, m.particle_adj_start, m.particle_adj_slot, 3 * m.tri_count,
                          self.rest, self.rest_exclusion, self.thickness + self.margin,
                          x if v is None else v, 0.0 if v is None else float(dt) * (self.detect_every - 1), MAX_SWEEP_M],
                  outputs=[self.candidate, self.side], device=m.device)

    def project(self, x: wp.array, world_active: wp.array) -> None:
        """Corrections for the current positions into ``delta`` (applied by the particle pass)."""
        m = self.model
        wp.launch(project_self_contacts, dim=m.particle_count,
                  inputs=[m.tri_indices, m.particle_inv_mass, self.candidate, self.side, self.thickness, self.relaxation, x],
                  outputs=[self.delta], device=m.device)
