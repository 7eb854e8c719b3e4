"""XPBD element kernels: triangle stretch/shear and dihedral bending, Gauss-Seidel and Jacobi.

Gauss-Seidel kernels run over one graph colour at a time (``offset`` + thread id) and write
positions in place: elements of one colour share no particle, so there is no race.  Jacobi
kernels read positions and write one correction per (element, corner) slot; the particle
pass sums them.  ``solve_elements_gs_world_blocks`` runs the same Gauss-Seidel sweep as the
per-colour kernels, every colour of every element kind, in one launch: one thread block per
world, a block barrier between colours.  Each Jacobi element takes the share ``relaxation / max_k n_k`` of its
multiplier step (n_k = elements of its kind, triangle or bending, touching corner k), so a
particle's summed correction is an average-like step while multiplier and positions stay
consistent."""

from __future__ import annotations

import warp as wp

from simulate.contact.self_contact import self_contact_correction
from simulate.solvers.common_kernels import (bending_angle_grad, clamp_to_bound, project_attachment, project_body_contact,
                                             tile_writer, triangle_constraint_deltas)

wp.set_module_options({"enable_backward": False})


@wp.func
def bending_deltas(x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, x4: wp.vec3,
                   w1: float, w2: float, w3: float, w4: float,
                   rest: float, compliance: float, lam: float, inv_dt2: float, scale: float):
    """XPBD projection of C = theta - theta_rest (multiplier step times ``scale``).

    Returns four corrections and the new multiplier.
    """
    ok, theta, d1, d2, d3, d4 = bending_angle_grad(x1, x2, x3, x4)
    zero = wp.vec3(0.0)
    if ok == 0:
        return zero, zero, zero, zero, lam
    alpha = compliance * inv_dt2
    denom = w1 * wp.dot(d1, d1) + w2 * wp.dot(d2, d2) + w3 * wp.dot(d3, d3) + w4 * wp.dot(d4, d4) + alpha
    if denom <= 0.0:
        return zero, zero, zero, zero, lam
    dl = scale * (-(theta - rest) - alpha * lam) / denom
    return d1 * (w1 * dl), d2 * (w2 * dl), d3 * (w3 * dl), d4 * (w4 * dl), lam + dl


@wp.func
def solve_triangle_in_place(t: int, tri_indices: wp.array2d(dtype=wp.int32), tri_dm_inv: wp.array(dtype=wp.mat22),
                            tri_compliance: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), inv_dt2: float,
                            relaxation: float, tri_lambda: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3)):
    """Gauss-Seidel projection of triangle ``t``, written into ``x`` and ``tri_lambda``."""
    i0 = tri_indices[t, 0]
    i1 = tri_indices[t, 1]
    i2 = tri_indices[t, 2]
    d0, d1, d2, lam = triangle_constraint_deltas(x[i0], x[i1], x[i2], inv_mass[i0], inv_mass[i1], inv_mass[i2],
                                                 tri_dm_inv[t], tri_compliance[t], tri_lambda[t], inv_dt2, relaxation)
    x[i0] = x[i0] + d0
    x[i1] = x[i1] + d1
    x[i2] = x[i2] + d2
    tri_lambda[t] = lam


@wp.func
def solve_bending_in_place(b: int, bend_indices: wp.array2d(dtype=wp.int32), bend_rest_angle: wp.array(dtype=float),
                           bend_compliance: wp.array(dtype=float), inv_mass: wp.array(dtype=float), inv_dt2: float,
                           relaxation: float, bend_lambda: wp.array(dtype=float), x: wp.array(dtype=wp.vec3)):
    """Gauss-Seidel projection of bending element ``b``, written into ``x`` and ``bend_lambda``."""
    i1 = bend_indices[b, 0]
    i2 = bend_indices[b, 1]
    i3 = bend_indices[b, 2]
    i4 = bend_indices[b, 3]
    d1, d2, d3, d4, lam = bending_deltas(x[i1], x[i2], x[i3], x[i4], inv_mass[i1], inv_mass[i2], inv_mass[i3],
                                         inv_mass[i4], bend_rest_angle[b], bend_compliance[b], bend_lambda[b], inv_dt2,
                                         relaxation)
    x[i1] = x[i1] + d1
    x[i2] = x[i2] + d2
    x[i3] = x[i3] + d3
    x[i4] = x[i4] + d4
    bend_lambda[b] = lam


@wp.kernel
def solve_triangles_gs(
    # Model:
    offset: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_dm_inv: wp.array(dtype=wp.mat22),
    tri_compliance: wp.array(dtype=wp.vec3),
    tri_world: wp.array(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    world_active: wp.array(dtype=wp.int32),
    inv_dt2: float,
    relaxation: float,
    # In/out:
    tri_lambda: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
):
    t = wp.tid() + offset
    if world_active[tri_world[t]] == 0:
        return
    solve_triangle_in_place(t, tri_indices, tri_dm_inv, tri_compliance, inv_mass, inv_dt2, relaxation, tri_lambda, x)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__syncthreads();
#endif
""")
def block_sync():
    """Barrier of the thread block (CUDA ``__syncthreads``): every write before it is visible to
    the whole block after it.  A no-op on CPU, where a tiled launch runs one lane per block."""
    ...


@wp.kernel
def solve_elements_gs_world_blocks(
    # Model:
    tri_world_offsets: wp.array2d(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_dm_inv: wp.array(dtype=wp.mat22),
    tri_compliance: wp.array(dtype=wp.vec3),
    bend_world_offsets: wp.array2d(dtype=wp.int32),
    bend_indices: wp.array2d(dtype=wp.int32),
    bend_rest_angle: wp.array(dtype=float),
    bend_compliance: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    world_active: wp.array(dtype=wp.int32),
    inv_dt2: float,
    relaxation: float,
    # In/out:
    tri_lambda: wp.array(dtype=wp.vec3),
    bend_lambda: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
):
    """One Gauss-Seidel iteration of one world's triangles then bending elements, colour by colour.

    Launched tiled with one block per world (``dim=[worlds]``).  ``*_world_offsets[c, w]`` ..
    ``[c, w + 1]`` are world w's elements of colour c (elements are sorted by colour, then world).
    The block's lanes stride over a colour's elements (no two share a particle), then meet at a
    barrier before the next colour, so the sweep equals one launch per colour.  Positions stay in
    global memory (lanes read each other's writes through L2): the fallback for worlds too large
    for ``make_elements_gs_shared_kernel``'s tile (240 t-shirts of 7.7k on an H200: 106 ms per
    frame against 59 ms with the tile and 134 ms with one launch per colour)."""
    w, lane = wp.tid()
    if world_active[w] == 0:
        return
    stride = wp.block_dim()
    for c in range(tri_world_offsets.shape[0]):
        for t in range(tri_world_offsets[c, w] + lane, tri_world_offsets[c, w + 1], stride):
            solve_triangle_in_place(t, tri_indices, tri_dm_inv, tri_compliance, inv_mass, inv_dt2, relaxation,
                                    tri_lambda, x)
        block_sync()
    for c in range(bend_world_offsets.shape[0]):
        for b in range(bend_world_offsets[c, w] + lane, bend_world_offsets[c, w + 1], stride):
            solve_bending_in_place(b, bend_indices, bend_rest_angle, bend_compliance, inv_mass, inv_dt2, relaxation,
                                   bend_lambda, x)
        block_sync()


def make_elements_gs_shared_kernel(tile_particles: int, particle_pass: bool = False, body_contact: bool = False,
                                   attachments: bool = False, self_contact: bool = False, bounds: bool = False):
    """World-block Gauss-Seidel iterations with the world's positions in shared memory.

    The block loads its world's positions (at most ``tile_particles``, 12 bytes each) into a
    shared-memory tile, sweeps every colour there and stores them back.  Within a colour no two
    elements share a particle, so each lane writes its elements' corners straight into the tile
    and the block meets at one barrier per colour.  Global positions written by one lane and read
    by another would go through L2 on every colour; in shared memory they stay on the SM.

    Without ``particle_pass`` a launch is one iteration of the element sweep, the same sweep and
    result as ``solve_elements_gs_world_blocks`` (``iterations`` must be 1); the solver's particle
    kernel runs after it.  With ``particle_pass`` a launch is a whole substep's ``iterations``:
    after each sweep every lane applies the particle constraints of
    ``common_kernels.make_particle_constraints_kernel`` (``project_attachment``, then
    ``project_body_contact``) to its own particles in the tile, so the result is bit-identical to
    alternating the two launches while the tile is loaded and stored once per substep.  One
    kernel per (tile size, flags): the tile's shape is a compile-time constant.

    With ``self_contact`` (and ``particle_pass``) the particle pass first adds each particle's
    self-contact push (``self_contact_correction``, as ``SelfContact.project`` computes it): the
    candidate triangle lies in the particle's own world (the search only finds those), so its
    corners are in the tile. Every lane computes its particles' pushes from the swept tile into
    ``self_delta`` (global, each lane only its own entries), the block meets at a barrier, then
    lanes apply them; so no push reads a position another lane has already moved, as in the
    separate launches of ``SelfContact.project`` and the particle kernel. With ``bounds`` the pass
    ends by keeping each particle of a world with self-contact within its displacement bound
    (``common_kernels.clamp_to_bounds``).

    Element corners come as world-local indices (``local_topology``): element ``t`` of colour
    ``c`` in world ``w`` has corners ``*_local[t - *_shift[c, w]]``. Worlds with one topology
    share one table (a 7.7k t-shirt: 0.5 MB, L2-resident) instead of streaming 12 B per triangle
    and 16 B per bending element from every world's own indices at every sweep.

    Element data (rest shape, compliance, rest angle) and inverse masses are read at the element's
    place in a world that holds the same values (``shared_element_data``): element ``t`` of colour
    ``c`` in world ``w`` reads ``tri_dm_inv[t - tri_dshift[c, w]]`` and its corners' inverse masses
    at ``world_data_start[w] + j``. Worlds that repeat a garment (a dataset batch: 40 styles in
    256 worlds) then read one copy of it, which stays in L2, instead of one copy each; the
    multipliers stay per element. With zero shifts and ``world_data_start`` = each world's own
    start every world reads its own data."""

    tile_write = tile_writer(wp.vec3, tile_particles)

    @wp.kernel(module="unique", enable_backward=False)
    def solve_elements_gs_shared(
        # Model:
        world_particle_start: wp.array(dtype=wp.int32),
        world_particle_count: wp.array(dtype=wp.int32),
        tri_world_offsets: wp.array2d(dtype=wp.int32),
        tri_shift: wp.array2d(dtype=wp.int32),
        tri_local: wp.array2d(dtype=wp.int32),
        tri_dm_inv: wp.array(dtype=wp.mat22),
        tri_compliance: wp.array(dtype=wp.vec3),
        bend_world_offsets: wp.array2d(dtype=wp.int32),
        bend_shift: wp.array2d(dtype=wp.int32),
        bend_local: wp.array2d(dtype=wp.int32),
        bend_rest_angle: wp.array(dtype=float),
        bend_compliance: wp.array(dtype=float),
        inv_mass: wp.array(dtype=float),
        tri_dshift: wp.array2d(dtype=wp.int32),
        bend_dshift: wp.array2d(dtype=wp.int32),
        world_data_start: wp.array(dtype=wp.int32),
        world_active: wp.array(dtype=wp.int32),
        inv_dt2: float,
        relaxation: float,
        iterations: int,
        # Particle pass (read only with particle_pass):
        particle_attachment: wp.array(dtype=wp.int32),
        attachment_target: wp.array(dtype=wp.vec3),
        world_attachment_stiffness: wp.array(dtype=float),
        world_attachment_enabled: wp.array(dtype=wp.int32),
        attachment_lambda: wp.array(dtype=wp.vec3),
        contact_active: wp.array(dtype=wp.int32),
        contact_normal: wp.array(dtype=wp.vec3),
        contact_offset: wp.array(dtype=float),
        contact_depth: wp.array(dtype=float),
        tri_indices: wp.array2d(dtype=wp.int32),
        self_candidate: wp.array(dtype=wp.int32),
        self_side: wp.array(dtype=float),
        self_thickness: float,
        self_relaxation: float,
        self_delta: wp.array(dtype=wp.vec3),
        sc_searched: wp.array(dtype=wp.vec3),
        sc_d_min: wp.array(dtype=float),
        sc_fraction: float,
        sc_min_separation: float,
        world_self_contact: wp.array(dtype=wp.int32),
        # In/out:
        tri_lambda: wp.array(dtype=wp.vec3),
        bend_lambda: wp.array(dtype=float),
        x: wp.array(dtype=wp.vec3),
    ):
        w, lane = wp.tid()
        if world_active[w] == 0:
            return
        stride = wp.block_dim()
        base = world_particle_start[w]
        dbase = world_data_start[w]
        count_w = world_particle_count[w]
        xs = wp.tile_load(x, shape=tile_particles, offset=base, storage="shared")
        for _it in range(iterations):
            for c in range(tri_world_offsets.shape[0]):
                shift = tri_shift[c, w]
                dshift = tri_dshift[c, w]
                for t in range(tri_world_offsets[c, w] + lane, tri_world_offsets[c, w + 1], stride):
                    j0 = tri_local[t - shift, 0]
                    j1 = tri_local[t - shift, 1]
                    j2 = tri_local[t - shift, 2]
                    td = t - dshift
                    p0 = xs[j0]
                    p1 = xs[j1]
                    p2 = xs[j2]
                    d0, d1, d2, tlam = triangle_constraint_deltas(p0, p1, p2, inv_mass[dbase + j0],
                                                                  inv_mass[dbase + j1], inv_mass[dbase + j2],
                                                                  tri_dm_inv[td], tri_compliance[td],
                                                                  tri_lambda[t], inv_dt2, relaxation)
                    tile_write(xs, j0, p0 + d0)
                    tile_write(xs, j1, p1 + d1)
                    tile_write(xs, j2, p2 + d2)
                    tri_lambda[t] = tlam
                block_sync()
            for c in range(bend_world_offsets.shape[0]):
                shift = bend_shift[c, w]
                dshift = bend_dshift[c, w]
                for b in range(bend_world_offsets[c, w] + lane, bend_world_offsets[c, w + 1], stride):
                    k1 = bend_local[b - shift, 0]
                    k2 = bend_local[b - shift, 1]
                    k3 = bend_local[b - shift, 2]
                    k4 = bend_local[b - shift, 3]
                    bd = b - dshift
                    q1 = xs[k1]
                    q2 = xs[k2]
                    q3 = xs[k3]
                    q4 = xs[k4]
                    e1, e2, e3, e4, blam = bending_deltas(q1, q2, q3, q4, inv_mass[dbase + k1], inv_mass[dbase + k2],
                                                         inv_mass[dbase + k3], inv_mass[dbase + k4],
                                                         bend_rest_angle[bd], bend_compliance[bd], bend_lambda[b],
                                                         inv_dt2, relaxation)
                    tile_write(xs, k1, q1 + e1)
                    tile_write(xs, k2, q2 + e2)
                    tile_write(xs, k3, q3 + e3)
                    tile_write(xs, k4, q4 + e4)
                    bend_lambda[b] = blam
                block_sync()
            if wp.static(particle_pass and self_contact):
                for j in range(lane, count_w, stride):
                    i = base + j
                    push = wp.vec3(0.0)
                    t = self_candidate[i]
                    if t >= 0 and inv_mass[dbase + j] != 0.0:
                        push = self_contact_correction(xs[j], xs[tri_indices[t, 0] - base], xs[tri_indices[t, 1] - base],
                                                       xs[tri_indices[t, 2] - base], self_side[i], self_thickness,
                                                       self_relaxation)
                    self_delta[i] = push
                block_sync()
            if wp.static(particle_pass):
                for j in range(lane, count_w, stride):
                    i = base + j
                    im = inv_mass[dbase + j]
                    if im != 0.0:
                        p = xs[j]
                        if wp.static(self_contact):
                            p = p + self_delta[i]
                        if wp.static(attachments):
                            p = project_attachment(p, im, i, w, inv_dt2, particle_attachment, attachment_target,
                                                   world_attachment_stiffness, world_attachment_enabled,
                                                   attachment_lambda)
                        if wp.static(body_contact):
                            p = project_body_contact(p, i, contact_active, contact_normal, contact_offset,
                                                     contact_depth)
                        if wp.static(bounds):
                            if world_self_contact[w] != 0:
                                p = clamp_to_bound(p, sc_searched[i], sc_d_min[i], sc_fraction, sc_min_separation)
                        tile_write(xs, j, p)
                block_sync()
        for j in range(lane, count_w, stride):
            x[base + j] = xs[j]

    return solve_elements_gs_shared


@wp.kernel
def solve_triangles_jacobi(
    # Model:
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_dm_inv: wp.array(dtype=wp.mat22),
    tri_compliance: wp.array(dtype=wp.vec3),
    tri_world: wp.array(dtype=wp.int32),
    tri_jacobi_scale: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    world_active: wp.array(dtype=wp.int32),
    inv_dt2: float,
    relaxation: float,
    x: wp.array(dtype=wp.vec3),
    # In/out:
    tri_lambda: wp.array(dtype=wp.vec3),
    # Out:
    slot_delta_out: wp.array(dtype=wp.vec3),
):
    t = wp.tid()
    zero = wp.vec3(0.0)
    if world_active[tri_world[t]] == 0:
        slot_delta_out[3 * t + 0] = zero
        slot_delta_out[3 * t + 1] = zero
        slot_delta_out[3 * t + 2] = zero
        return
    i0 = tri_indices[t, 0]
    i1 = tri_indices[t, 1]
    i2 = tri_indices[t, 2]
    d0, d1, d2, lam = triangle_constraint_deltas(x[i0], x[i1], x[i2], inv_mass[i0], inv_mass[i1], inv_mass[i2],
                                                 tri_dm_inv[t], tri_compliance[t], tri_lambda[t], inv_dt2,
                                                 relaxation * tri_jacobi_scale[t])
    slot_delta_out[3 * t + 0] = d0
    slot_delta_out[3 * t + 1] = d1
    slot_delta_out[3 * t + 2] = d2
    tri_lambda[t] = lam


@wp.kernel
def solve_bending_gs(
    # Model:
    offset: int,
    bend_indices: wp.array2d(dtype=wp.int32),
    bend_rest_angle: wp.array(dtype=float),
    bend_compliance: wp.array(dtype=float),
    bend_world: wp.array(dtype=wp.int32),
    inv_mass: wp.array(dtype=float),
    world_active: wp.array(dtype=wp.int32),
    inv_dt2: float,
    relaxation: float,
    # In/out:
    bend_lambda: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
):
    b = wp.tid() + offset
    if world_active[bend_world[b]] == 0:
        return
    solve_bending_in_place(b, bend_indices, bend_rest_angle, bend_compliance, inv_mass, inv_dt2, relaxation, bend_lambda, x)


@wp.kernel
def solve_bending_jacobi(
    # Model:
    slot_base: int,
    bend_indices: wp.array2d(dtype=wp.int32),
    bend_rest_angle: wp.array(dtype=float),
    bend_compliance: wp.array(dtype=float),
    bend_world: wp.array(dtype=wp.int32),
    bend_jacobi_scale: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    world_active: wp.array(dtype=wp.int32),
    inv_dt2: float,
    relaxation: float,
    x: wp.array(dtype=wp.vec3),
    # In/out:
    bend_lambda: wp.array(dtype=float),
    # Out:
    slot_delta_out: wp.array(dtype=wp.vec3),
):
    b = wp.tid()
    s = slot_base + 4 * b
    zero = wp.vec3(0.0)
    if world_active[bend_world[b]] == 0:
        for k in range(4):
            slot_delta_out[s + k] = zero
        return
    i1 = bend_indices[b, 0]
    i2 = bend_indices[b, 1]
    i3 = bend_indices[b, 2]
    i4 = bend_indices[b, 3]
    d1, d2, d3, d4, lam = bending_deltas(x[i1], x[i2], x[i3], x[i4], inv_mass[i1], inv_mass[i2], inv_mass[i3],
                                         inv_mass[i4], bend_rest_angle[b], bend_compliance[b], bend_lambda[b], inv_dt2,
                                         relaxation * bend_jacobi_scale[b])
    slot_delta_out[s + 0] = d1
    slot_delta_out[s + 1] = d2
    slot_delta_out[s + 2] = d3
    slot_delta_out[s + 3] = d4
    bend_lambda[b] = lam
