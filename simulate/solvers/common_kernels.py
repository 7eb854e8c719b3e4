"""Kernels shared by the cloth solvers: integration, particle constraints, velocity update,
frame metrics, and the cloth energy terms (triangle stretch/shear, dihedral bending).

No float atomics are used for positions or forces: element kernels write one value per
(element, corner) slot and a per-particle kernel gathers its slots in a fixed (CSR) order, so
results are bit-identical run to run on CPU and GPU.  Only order-independent atomics
(``atomic_max`` on per-world metrics) are used.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

_EPS = 1.0e-9


# ----------------------------------------------------------------------------- energies
@wp.func
def triangle_coefficients(dm: wp.mat22):
    """Corner weights a_k, b_k with f1 = sum a_k x_k, f2 = sum b_k x_k (deformation gradient columns)."""
    a1 = dm[0, 0]
    a2 = dm[1, 0]
    b1 = dm[0, 1]
    b2 = dm[1, 1]
    return wp.vec3(-(a1 + a2), a1, a2), wp.vec3(-(b1 + b2), b1, b2)


@wp.func
def triangle_constraint_deltas(
    x0: wp.vec3, x1: wp.vec3, x2: wp.vec3,
    w0: float, w1: float, w2: float,
    dm: wp.mat22, compliance: wp.vec3, lam: wp.vec3, inv_dt2: float, scale: float,
):
    """XPBD projection of a triangle's stretch-u, stretch-v and shear constraints (in sequence).

    C_u = |f1| - 1, C_v = |f2| - 1 with compliance 1/(Y A); C_s = f1 . f2 with 1/(G A).
    ``scale`` shrinks each multiplier step (1 for Gauss-Seidel; the Jacobi share, see
    ``ClothModel.tri_jacobi_scale``); positions move by exactly the applied multiplier change,
    so M (x - x_pred) = grad(C)^T lambda holds and the converged state is the true equilibrium.
    Returns the position corrections of the three corners and the updated multipliers.
    """
    a, b = triangle_coefficients(dm)
    p0 = x0
    p1 = x1
    p2 = x2
    l0 = lam[0]
    l1 = lam[1]
    l2 = lam[2]
    # Stretch along the first material direction.
    f1 = p0 * a[0] + p1 * a[1] + p2 * a[2]
    len1 = wp.length(f1)
    if len1 > _EPS:
        n = f1 / len1
        alpha = compliance[0] * inv_dt2
        denom = w0 * a[0] * a[0] + w1 * a[1] * a[1] + w2 * a[2] * a[2] + alpha
        if denom > 0.0:
            dl = scale * (-(len1 - 1.0) - alpha * l0) / denom
            p0 = p0 + n * (w0 * a[0] * dl)
            p1 = p1 + n * (w1 * a[1] * dl)
            p2 = p2 + n * (w2 * a[2] * dl)
            l0 = l0 + dl
    # Stretch along the second material direction.
    f2 = p0 * b[0] + p1 * b[1] + p2 * b[2]
    len2 = wp.length(f2)
    if len2 > _EPS:
        n = f2 / len2
        alpha = compliance[1] * inv_dt2
        denom = w0 * b[0] * b[0] + w1 * b[1] * b[1] + w2 * b[2] * b[2] + alpha
        if denom > 0.0:
            dl = scale * (-(len2 - 1.0) - alpha * l1) / denom
            p0 = p0 + n * (w0 * b[0] * dl)
            p1 = p1 + n * (w1 * b[1] * dl)
            p2 = p2 + n * (w2 * b[2] * dl)
            l1 = l1 + dl
    # Shear.
    f1 = p0 * a[0] + p1 * a[1] + p2 * a[2]
    f2 = p0 * b[0] + p1 * b[1] + p2 * b[2]
    g0 = f2 * a[0] + f1 * b[0]
    g1 = f2 * a[1] + f1 * b[1]
    g2 = f2 * a[2] + f1 * b[2]
    alpha = compliance[2] * inv_dt2
    denom = w0 * wp.dot(g0, g0) + w1 * wp.dot(g1, g1) + w2 * wp.dot(g2, g2) + alpha
    if denom > 0.0:
        dl = scale * (-wp.dot(f1, f2) - alpha * l2) / denom
        p0 = p0 + g0 * (w0 * dl)
        p1 = p1 + g1 * (w1 * dl)
        p2 = p2 + g2 * (w2 * dl)
        l2 = l2 + dl
    return p0 - x0, p1 - x1, p2 - x2, wp.vec3(l0, l1, l2)


@wp.func
def triangle_forces(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, dm: wp.mat22, compliance: wp.vec3):
    """Elastic forces [N] on a triangle's corners: -grad of 1/2 sum_j C_j^2 / compliance_j."""
    a, b = triangle_coefficients(dm)
    f1 = x0 * a[0] + x1 * a[1] + x2 * a[2]
    f2 = x0 * b[0] + x1 * b[1] + x2 * b[2]
    len1 = wp.length(f1)
    len2 = wp.length(f2)
    t1 = wp.vec3(0.0)
    t2 = wp.vec3(0.0)
    if len1 > _EPS:
        t1 = f1 * (-(len1 - 1.0) / len1 / compliance[0])
    if len2 > _EPS:
        t2 = f2 * (-(len2 - 1.0) / len2 / compliance[1])
    s = -wp.dot(f1, f2) / compliance[2]
    # dE/dx_k = a_k dE/df1 + b_k dE/df2, with the shear term dE/df1 = s f2, dE/df2 = s f1.
    g1 = t1 + f2 * s
    g2 = t2 + f1 * s
    return g1 * a[0] + g2 * b[0], g1 * a[1] + g2 * b[1], g1 * a[2] + g2 * b[2]


@wp.func
def bending_angle_grad(x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, x4: wp.vec3):
    """Signed dihedral angle [rad] of stencil (opp0, opp1, edge0, edge1) and its gradients.

    Bridson et al. 2003 gradients; returns (ok, theta, d1, d2, d3, d4), ok = 0 when degenerate.
    """
    n1 = wp.cross(x3 - x1, x4 - x1)
    n2 = wp.cross(x4 - x2, x3 - x2)
    n1_len = wp.length(n1)
    n2_len = wp.length(n2)
    e = x4 - x3
    e_len = wp.length(e)
    zero = wp.vec3(0.0)
    if n1_len < 1.0e-12 or n2_len < 1.0e-12 or e_len < 1.0e-9:
        return int(0), float(0.0), zero, zero, zero, zero
    cos_t = wp.clamp(wp.dot(n1, n2) / (n1_len * n2_len), -1.0, 1.0)
    n1 = n1 / (n1_len * n1_len)
    n2 = n2 / (n2_len * n2_len)
    e_hat = e / e_len
    s = wp.sign(wp.dot(wp.cross(n2, n1), e_hat))
    if s == 0.0:
        s = 1.0
    theta = wp.acos(cos_t) * s
    d1 = n1 * e_len
    d2 = n2 * e_len
    d3 = n1 * wp.dot(x1 - x4, e_hat) + n2 * wp.dot(x2 - x4, e_hat)
    d4 = n1 * wp.dot(x3 - x1, e_hat) + n2 * wp.dot(x3 - x2, e_hat)
    return int(1), theta, d1, d2, d3, d4


# ----------------------------------------------------------------------------- particles
@wp.kernel
def integrate_particles(
    # Model:
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    gravity: wp.vec3,
    dt: float,
    # State in:
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # Out:
    x_out: wp.array(dtype=wp.vec3),
):
    """Predicted positions x + dt (v + dt g); pinned and frozen particles stay."""
    i = wp.tid()
    p = x[i]
    if world_active[particle_world[i]] == 0 or inv_mass[i] == 0.0:
        x_out[i] = p
        return
    x_out[i] = p + (v[i] + gravity * dt) * dt


@wp.func
def project_attachment(p: wp.vec3, im: float, i: int, w: int, inv_dt2: float,
                       particle_attachment: wp.array(dtype=wp.int32), attachment_target: wp.array(dtype=wp.vec3),
                       world_attachment_stiffness: wp.array(dtype=float),
                       world_attachment_enabled: wp.array(dtype=wp.int32), attachment_lambda: wp.array(dtype=wp.vec3)):
    """XPBD step of particle ``i``'s soft attachment (if it has one and its world enables them);
    returns the new position and updates the multiplier."""
    a = particle_attachment[i]
    if a >= 0:
        if world_attachment_enabled[w] != 0:
            alpha = inv_dt2 / world_attachment_stiffness[w]
            lam = attachment_lambda[a]
            c = p - attachment_target[a]
            dl = (-c - lam * alpha) / (im + alpha)
            attachment_lambda[a] = lam + dl
            return p + dl * im
    return p


@wp.func
def project_body_contact(p: wp.vec3, i: int, contact_active: wp.array(dtype=wp.int32),
                         contact_normal: wp.array(dtype=wp.vec3), contact_offset: wp.array(dtype=float),
                         contact_depth: wp.array(dtype=float)):
    """Particle ``i`` pushed out to its contact plane (if it has one and is behind it); the push
    adds to its friction budget ``contact_depth``.  Returns the new position."""
    if contact_active[i] != 0:
        n = contact_normal[i]
        gap = wp.dot(n, p) - contact_offset[i]
        if gap < 0.0:
            contact_depth[i] = contact_depth[i] - gap
            return p - n * gap
    return p


def make_particle_constraints_kernel(jacobi: bool, body_contact: bool, attachments: bool, self_contact: bool):
    """Per-particle XPBD pass: Jacobi gather (optional), self-contact, attachments, body contact."""
    key = (jacobi, body_contact, attachments, self_contact)
    if key in _PARTICLE_KERNELS:
        return _PARTICLE_KERNELS[key]

    @wp.kernel(module="unique", enable_backward=False)
    def solve_particle_constraints(
        # Model:
        inv_mass: wp.array(dtype=float),
        particle_world: wp.array(dtype=wp.int32),
        world_active: wp.array(dtype=wp.int32),
        inv_dt2: float,
        # Jacobi gather:
        adj_start: wp.array(dtype=wp.int32),
        adj_slot: wp.array(dtype=wp.int32),
        slot_delta: wp.array(dtype=wp.vec3),
        # Self contact:
        self_delta: wp.array(dtype=wp.vec3),
        # Attachments:
        particle_attachment: wp.array(dtype=wp.int32),
        attachment_target: wp.array(dtype=wp.vec3),
        world_attachment_stiffness: wp.array(dtype=float),
        world_attachment_enabled: wp.array(dtype=wp.int32),
        attachment_lambda: wp.array(dtype=wp.vec3),
        # Body contact:
        contact_active: wp.array(dtype=wp.int32),
        contact_normal: wp.array(dtype=wp.vec3),
        contact_offset: wp.array(dtype=float),
        contact_depth: wp.array(dtype=float),
        # State (in/out, own entry only):
        x: wp.array(dtype=wp.vec3),
    ):
        i = wp.tid()
        w = particle_world[i]
        im = inv_mass[i]
        if world_active[w] == 0 or im == 0.0:
            return
        p = x[i]
        if wp.static(jacobi):
            start = adj_start[i]
            end = adj_start[i + 1]
            acc = wp.vec3(0.0)
            for k in range(start, end):
                acc = acc + slot_delta[adj_slot[k]]
            p = p + acc
        if wp.static(self_contact):
            p = p + self_delta[i]
        if wp.static(attachments):
            p = project_attachment(p, im, i, w, inv_dt2, particle_attachment, attachment_target,
                                   world_attachment_stiffness, world_attachment_enabled, attachment_lambda)
        if wp.static(body_contact):
            p = project_body_contact(p, i, contact_active, contact_normal, contact_offset, contact_depth)
        x[i] = p

    _PARTICLE_KERNELS[key] = solve_particle_constraints
    return solve_particle_constraints


def tile_writer(dtype, tile_particles: int):
    """A ``wp.func`` ``tile_write(t, i, v)``: ``t[i] = v`` on a shared tile of ``tile_particles``
    values of ``dtype``, without the block barrier Warp's tile item assignment ends with. Lanes of
    a world block write their own entries and meet at one barrier per colour (a barrier inside a
    lane's own loop would deadlock the block). One function per (dtype, size): the tile's shape is
    part of its type."""
    key = (dtype, int(tile_particles))
    if key not in _TILE_WRITERS:
        def tile_write(t, i, v):
            ...

        tile_write.__annotations__ = {"t": wp.tile[dtype, int(tile_particles)], "i": int, "v": dtype}
        _TILE_WRITERS[key] = wp.func_native("t.data(wp::tile_coord(i)) = v;")(tile_write)
    return _TILE_WRITERS[key]


_TILE_WRITERS: dict[tuple, object] = {}


@wp.func
def friction_cancel(rel: wp.vec3, n: wp.vec3, limit: float):
    """Coulomb friction at the position level: the part of a particle's displacement ``rel`` relative
    to the body [m] that friction cancels: its tangential part (normal ``n``), up to ``limit`` [m]
    (mu times the normal displacement the contact imposed)."""
    tangent = rel - n * wp.dot(n, rel)
    slip = wp.length(tangent)
    if slip <= limit:
        return tangent
    return tangent * (limit / slip)


_PARTICLE_KERNELS: dict[tuple, wp.Kernel] = {}
_FINALIZE_KERNELS: dict[tuple, wp.Kernel] = {}


@wp.func
def clamp_to_bound(p: wp.vec3, searched: wp.vec3, d_min: float, fraction: float, min_separation: float) -> wp.vec3:
    """``p`` [m] pulled back within the particle's self-contact displacement bound around where it
    was searched: ``fraction`` of its smallest pair distance ``d_min`` less ``min_separation`` (a
    tenth of ``d_min`` for a pair already closer; ``simulate.contact.self_contact``)."""
    step = p - searched
    length = wp.length(step)
    bound = fraction * wp.where(d_min > min_separation, d_min - min_separation, 0.1 * d_min)
    if length > bound:
        return searched + step * (bound / length)
    return p


@wp.kernel
def clamp_to_bounds(
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_self_contact: wp.array(dtype=wp.int32),
    searched: wp.array(dtype=wp.vec3),
    d_min: wp.array(dtype=float),
    fraction: float,
    min_separation: float,
    x: wp.array(dtype=wp.vec3),
):
    """Every particle of an active world with self-contact kept within its displacement bound."""
    i = wp.tid()
    w = particle_world[i]
    if world_active[w] == 0 or world_self_contact[w] == 0 or inv_mass[i] == 0.0:
        return
    x[i] = clamp_to_bound(x[i], searched[i], d_min[i], fraction, min_separation)


def make_finalize_kernel(friction: bool, bounds: bool = False):
    """Friction on the substep's displacement, then velocities (x - x_prev)/dt with damping. With
    ``bounds``, a particle that friction carries along with the body stays within its self-contact
    displacement bound (``clamp_to_bound``)."""
    key = (friction, bounds)
    if key in _FINALIZE_KERNELS:
        return _FINALIZE_KERNELS[key]

    @wp.kernel(module="unique", enable_backward=False)
    def finalize_particles(
        # Model:
        inv_mass: wp.array(dtype=float),
        particle_world: wp.array(dtype=wp.int32),
        world_active: wp.array(dtype=wp.int32),
        world_damping: wp.array(dtype=float),
        world_friction: wp.array(dtype=float),
        extra_damping: float,
        dt: float,
        # Contacts:
        contact_active: wp.array(dtype=wp.int32),
        contact_normal: wp.array(dtype=wp.vec3),
        contact_motion: wp.array(dtype=wp.vec3),
        contact_depth: wp.array(dtype=float),
        # State in:
        x_prev: wp.array(dtype=wp.vec3),
        v_prev: wp.array(dtype=wp.vec3),
        # Self-contact bounds:
        sc_searched: wp.array(dtype=wp.vec3),
        sc_d_min: wp.array(dtype=float),
        sc_fraction: float,
        sc_min_separation: float,
        world_self_contact: wp.array(dtype=wp.int32),
        # In/out:
        x: wp.array(dtype=wp.vec3),
        # Out:
        v_out: wp.array(dtype=wp.vec3),
    ):
        i = wp.tid()
        w = particle_world[i]
        if world_active[w] == 0:
            v_out[i] = v_prev[i]
            return
        if inv_mass[i] == 0.0:
            v_out[i] = wp.vec3(0.0)
            return
        p = x[i]
        if wp.static(friction):
            depth = contact_depth[i]
            if contact_active[i] != 0 and depth > 0.0:
                # Coulomb: the tangential slip (relative to the body) this substep is cancelled
                # up to mu times the normal displacement the contact imposed.
                p = p - friction_cancel(p - x_prev[i] - contact_motion[i], contact_normal[i],
                                        world_friction[w] * depth)
                if wp.static(bounds):
                    if world_self_contact[w] != 0:
                        p = clamp_to_bound(p, sc_searched[i], sc_d_min[i], sc_fraction, sc_min_separation)
                x[i] = p
        vel = (p - x_prev[i]) / dt
        decay = wp.max(1.0 - (world_damping[w] + extra_damping) * dt, 0.0)
        v_out[i] = vel * decay

    _FINALIZE_KERNELS[key] = finalize_particles
    return finalize_particles


# ----------------------------------------------------------------------------- metrics
@wp.kernel
def measure_particles(
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    v: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tolerance: float,
    history: wp.array2d(dtype=wp.vec3),
    history_slot: wp.array(dtype=wp.int32),
    window: int,
    return_distance: float,
    stray_distance: float,
    # Out (per world, reset by the caller):
    world_max_speed_out: wp.array(dtype=float),
    world_bad_out: wp.array(dtype=wp.int32),
    world_fast_count_out: wp.array(dtype=wp.int32),
):
    """Per world: max particle speed [m/s], a flag for non-finite positions/velocities and the
    number of particles not at rest.

    A particle is at rest when it is slower than ``tolerance`` [m/s] or, with ``window`` > 1
    frames of position history (``history`` (window, particle_count), ring slot
    ``history_slot[0]`` = the oldest, overwritten here with ``x``), when it is back within
    ``return_distance`` [m] of where it was 2..window frames ago and strayed no further than
    ``stray_distance`` [m] from any of them: a small limit cycle (contact planes or pushes that
    alternate between frames) instead of motion toward a rest state."""
    i = wp.tid()
    w = particle_world[i]
    if world_active[w] == 0:
        return
    vi = v[i]
    xi = x[i]
    speed = wp.length(vi)
    finite = wp.isfinite(speed) and wp.isfinite(xi[0]) and wp.isfinite(xi[1]) and wp.isfinite(xi[2])
    if finite:
        wp.atomic_max(world_max_speed_out, w, speed)
        rest = speed < tolerance
        if window > 1:
            oldest = history_slot[0]
            newest = (oldest + window - 1) % window
            nearest = float(1.0e30)
            farthest = float(0.0)
            for k in range(window):
                d = wp.length(xi - history[k, i])
                farthest = wp.max(farthest, d)
                if k != newest:
                    nearest = wp.min(nearest, d)
            if nearest < return_distance and farthest < stray_distance:
                rest = True
        if not rest:
            wp.atomic_add(world_fast_count_out, w, 1)
    else:
        wp.atomic_max(world_bad_out, w, 1)
    if window > 1:
        history[history_slot[0], i] = xi


@wp.kernel
def advance_history_slot(window: int, history_slot: wp.array(dtype=wp.int32)):
    """Moves the position-history ring of :func:`measure_particles` on by one frame."""
    history_slot[0] = (history_slot[0] + 1) % window


@wp.kernel
def measure_triangles(
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_dm_inv: wp.array(dtype=wp.mat22),
    tri_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    # Out (per world, reset by the caller):
    world_max_stretch_out: wp.array(dtype=float),
):
    """Per world: largest stretch ratio max(|f1|, |f2|) over triangles [-]."""
    t = wp.tid()
    w = tri_world[t]
    if world_active[w] == 0:
        return
    a, b = triangle_coefficients(tri_dm_inv[t])
    x0 = x[tri_indices[t, 0]]
    x1 = x[tri_indices[t, 1]]
    x2 = x[tri_indices[t, 2]]
    s = wp.max(wp.length(x0 * a[0] + x1 * a[1] + x2 * a[2]), wp.length(x0 * b[0] + x1 * b[1] + x2 * b[2]))
    if wp.isfinite(s):
        wp.atomic_max(world_max_stretch_out, w, s)
