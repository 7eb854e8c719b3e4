"""VBD kernels: the inertial target, and the per-vertex Newton step of one colour's vertices.

Each vertex minimizes the substep's incremental potential over its own position with every
other vertex held (block coordinate descent, Chen et al. 2024 "Vertex Block Descent"):

    G(x) = m / (2 dt^2) |x - y|^2 + E_elastic(x) + E_attachment(x),    y = x_prev + dt v + dt^2 g

one Newton step ``x += H^-1 f`` with f = -dG/dx and H its 3 x 3 Hessian block (stretch and bending
terms projected to be positive semi-definite; shear by Gauss-Newton), then the body-contact plane
``n . x >= offset`` as a hard constraint (projection).  Vertices of one colour share no element, so
a colour updates in parallel with the result of a sequential sweep.  The energy terms are the
model's (``common_kernels``: triangle stretch along the two material directions and shear,
dihedral bending), so the fixed point at rest is the model's static equilibrium.

The element adjacency is the model's CSR of element slots per particle (``particle_adj_start``,
``particle_adj_slot``): slot ``s < 3 T`` is corner ``s % 3`` of triangle ``s // 3``, a slot past
them corner ``(s - 3 T) % 4`` of bending element ``(s - 3 T) // 4``.  The sum runs in that fixed
order, so results are bit-reproducible (no atomics).
"""

from __future__ import annotations

import warp as wp

from simulate.contact.closest import closest_point_barycentric
from simulate.contact.self_contact import segment_closest
from simulate.solvers.common_kernels import bending_angle_grad, tile_writer, triangle_coefficients
from simulate.solvers.xpbd.kernels import block_sync

wp.set_module_options({"enable_backward": False})

_EPS = 1.0e-9


@wp.kernel
def predict_particles(
    # Model:
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    gravity: wp.vec3,
    dt: float,
    # State in:
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    gravity_share: wp.array(dtype=float),
    # In/out:
    x64: wp.array(dtype=wp.vec3d),
    # Out:
    x64_prev_out: wp.array(dtype=wp.vec3d),
    target_out: wp.array(dtype=wp.vec3),
    predicted_out: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
):
    """Start of a substep: the float64 position, its copy at the substep's start, the inertial
    displacement target dt v + dt^2 g, the predicted position x + dt v + dt^2 g (where body contact
    planes are found) and the descent's start x + dt v + s dt^2 g, where s in [0, 1] is the share of
    gravity the particle's last substep accelerated it by (``gravity_share``, VBD's adaptive
    initialization): a falling cloth starts its substep where it would fall to, a resting one
    where it is.

    ``x64`` holds the solver's own float64 positions; where ``x`` (float32, the state) is no longer
    their rounding, the caller has set the state (restart, revive, a new garment) and ``x`` wins.

    At rest (v = 0, s = 0) the start is the particle's own position, where the descent only moves
    it if the forces there do not balance, so the fixed point is the static equilibrium.  Starting
    at rest from x + dt^2 g instead, the few sweeps of a substep would have to pull every vertex
    back up by g dt^2, and the rest state sags by whatever they leave undone (a cotton strip of 80
    rows: ~50x its extension); starting a falling cloth without gravity, the sweeps would have to
    carry the fall through the whole mesh from vertex to vertex."""
    i = wp.tid()
    p32 = x[i]
    p = x64[i]
    r = wp.vec3(p)
    if r[0] != p32[0] or r[1] != p32[1] or r[2] != p32[2]:
        p = wp.vec3d(p32)
    x64_prev_out[i] = p
    if world_active[particle_world[i]] == 0 or inv_mass[i] == 0.0:
        x64[i] = p
        target_out[i] = wp.vec3(0.0)
        predicted_out[i] = p32
        x_out[i] = p32
        return
    vi = v[i]
    target_out[i] = (vi + gravity * dt) * dt
    predicted_out[i] = p32 + target_out[i]
    q = p + wp.vec3d((vi + gravity * (gravity_share[i] * dt)) * dt)
    x64[i] = q
    x_out[i] = wp.vec3(q)


@wp.func
def stretch_hessian(n: wp.vec3, length: float):
    """Hessian of 1/2 (|f| - 1)^2 in f, projected to PSD: n n^T + max(0, 1 - 1/|f|) (I - n n^T)."""
    nn = wp.outer(n, n)
    c = wp.max(1.0 - 1.0 / length, 0.0)
    return nn + (wp.identity(n=3, dtype=float) - nn) * c


@wp.func
def triangle_vertex_terms(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, corner: int, dm: wp.mat22, compliance: wp.vec3):
    """Force [N] on one corner of a triangle and its 3 x 3 Hessian block [N/m] (see module doc)."""
    a, b = triangle_coefficients(dm)
    # Edge vectors: x0 a0 + x1 a1 + x2 a2 would cancel terms ~|x| / h large.
    e1 = x1 - x0
    e2 = x2 - x0
    f1 = e1 * a[1] + e2 * a[2]
    f2 = e1 * b[1] + e2 * b[2]
    ac = a[corner]
    bc = b[corner]
    force = wp.vec3(0.0)
    hess = wp.mat33(0.0)
    len1 = wp.length(f1)
    if len1 > _EPS:
        n1 = f1 / len1
        k1 = 1.0 / compliance[0]
        force = force - n1 * (ac * k1 * (len1 - 1.0))
        hess = hess + stretch_hessian(n1, len1) * (ac * ac * k1)
    len2 = wp.length(f2)
    if len2 > _EPS:
        n2 = f2 / len2
        k2 = 1.0 / compliance[1]
        force = force - n2 * (bc * k2 * (len2 - 1.0))
        hess = hess + stretch_hessian(n2, len2) * (bc * bc * k2)
    ks = 1.0 / compliance[2]
    g = f2 * ac + f1 * bc  # d(f1 . f2) / d x_corner
    force = force - g * (ks * wp.dot(f1, f2))
    hess = hess + wp.outer(g, g) * ks
    return force, hess


@wp.func
def bending_vertex_terms(x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, x4: wp.vec3, corner: int, rest: float,
                         compliance: float):
    """Force [N] on one corner of a bending stencil and its Gauss-Newton Hessian block k d d^T."""
    ok, theta, d1, d2, d3, d4 = bending_angle_grad(x1, x2, x3, x4)
    if ok == 0 or compliance <= 0.0:
        return wp.vec3(0.0), wp.mat33(0.0)
    d = d1
    if corner == 1:
        d = d2
    elif corner == 2:
        d = d3
    elif corner == 3:
        d = d4
    k = 1.0 / compliance
    return d * (-k * (theta - rest)), wp.outer(d, d) * k


@wp.func
def vertex_triangle_contact(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, role: int, radius: float,
                            stiffness: float):
    """Force [N] and Hessian block [N/m] on one particle of a vertex-triangle pair from the
    contact energy stiffness / 2 (radius - d)^2 while the distance d between the point ``p`` and
    triangle abc is below ``radius`` [m]: the particle is the point (``role`` -1) or the
    triangle's corner ``role`` (0, 1, 2), which takes its barycentric share of the push. Positions
    relative to the particle (float32 is exact enough); Gauss-Newton Hessian."""
    bary = closest_point_barycentric(p, a, b, c)
    diff = p - (a * bary[0] + b * bary[1] + c * bary[2])
    d = wp.length(diff)
    if d >= radius or d < 1.0e-9:
        return wp.vec3(0.0), wp.mat33(0.0)
    n = diff / d
    share = float(1.0)
    if role >= 0:
        share = -bary[role]
    return n * (stiffness * (radius - d) * share), wp.outer(n, n) * (stiffness * share * share)


@wp.func
def edge_edge_contact(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3, end: int, radius: float,
                      stiffness: float):
    """Force [N] and Hessian block [N/m] on end ``end`` (0: p1, 1: q1) of edge p1q1 from the
    contact energy stiffness / 2 (radius - d)^2 while its distance d to edge p2q2 is below
    ``radius`` [m]; the end takes its share of the push by its weight at the closest point."""
    closest = segment_closest(p1, q1, p2, q2)
    d = closest[2]
    if d >= radius or d < 1.0e-9:
        return wp.vec3(0.0), wp.mat33(0.0)
    n = ((p1 + (q1 - p1) * closest[0]) - (p2 + (q2 - p2) * closest[1])) / d
    share = wp.where(end == 0, 1.0 - closest[0], closest[0])
    return n * (stiffness * (radius - d) * share), wp.outer(n, n) * (stiffness * share * share)


@wp.func
def within_bound(p: wp.vec3d, searched: wp.vec3, d_min: float, fraction: float, min_separation: float) -> wp.vec3d:
    """``p`` [m] pulled back to the particle's self-contact displacement bound around where it was
    searched: ``fraction`` of its smallest pair distance ``d_min`` less ``min_separation`` (a tenth
    of ``d_min`` for a pair already closer; ``simulate.contact.self_contact``); ``fraction`` 0: no
    bound."""
    if fraction <= 0.0:
        return p
    start = wp.vec3d(searched)
    step = p - start
    length = wp.length(step)
    bound = wp.float64(fraction * wp.where(d_min > min_separation, d_min - min_separation, 0.1 * d_min))
    if length > bound:
        return start + step * (bound / length)
    return p


@wp.func
def within_directional_bound(p: wp.vec3d, searched: wp.vec3, normal: wp.vec3, d_side: float, d_ball: float,
                             slope: float, fraction: float, min_separation: float) -> wp.vec3d:
    """``p`` [m] scaled back toward where the particle was searched until its displacement u
    keeps the directional bounds (``simulate.contact.self_contact``): n . u - slope |u| >= -f'
    d_side and |u| <= f' d_ball, with f' d = ``fraction`` max(d - ``min_separation``, 0): a pair
    closer than ``min_separation`` (float32 rounding puts one there) may part but not close, so
    it never closes by a share of its distance search after search. Both sets are convex and
    hold u = 0, so the scaled step keeps them."""
    start = wp.vec3d(searched)
    step = wp.vec3(p - start)
    length = wp.length(step)
    ball = fraction * wp.max(d_ball - min_separation, 0.0)
    side = fraction * wp.max(d_side - min_separation, 0.0)
    scale = float(1.0)
    if length > ball:
        scale = ball / length
    lhs = wp.dot(normal, step) - slope * length
    if scale * lhs < -side:
        scale = side / (-lhs)  # lhs < -side <= 0
    if scale < 1.0:
        return start + wp.vec3d(step * scale)
    return p


@wp.func
def friction_terms(slip: wp.vec3, n: wp.vec3, limit: float, slip_scale: float):
    """Coulomb friction of a vertex on its body contact plane (normal ``n``) as a force [N] and its
    Hessian [N/m] in the vertex's Newton step: ``slip`` [m] is the vertex's displacement relative
    to the body this substep, ``limit`` = mu N [N] (N from the same step: what presses the vertex
    into the plane).  The force opposes the tangential slip with magnitude ``limit`` once the slip
    exceeds ``slip_scale`` [m]; below it, IPC's C1 ramp f1(y) = 2y/e - y^2/e^2 (Li et al. 2020)
    makes static friction a stiff spring, so a vertex whose tangential load stays under mu N
    creeps less than ``slip_scale`` per substep and one above it slides against mu N.  The
    Hessian is f1(|u|)/|u| times mu N on the tangent plane (the PSD part)."""
    u = slip - n * wp.dot(n, slip)
    length = wp.length(u)
    if length >= slip_scale:
        scale = limit / length
    else:
        scale = limit * (2.0 / slip_scale - length / (slip_scale * slip_scale))
    tangent = wp.identity(n=3, dtype=float) - wp.outer(n, n)
    return -u * scale, tangent * scale


def make_vbd_sweep_kernel(tile_particles: int, bending: bool, attachments: bool, body_contact: bool,
                          self_contact: bool = False, friction: bool = False):
    """Kernel running ``iterations`` VBD sweeps of every colour of a world, one thread block per world.

    ``vertex_world_offsets[c, w]`` .. ``[c, w + 1]`` index ``vertex_order``, the particles of colour
    ``c`` in world ``w``; the block's lanes stride over them and meet at a barrier before the next
    colour.  Positions are the solver's float64 copy: a Newton step of a stiff vertex near rest is
    far below float32's resolution at 1 m (6e-8 m; cotton at 1.25 cm edges stalls with residual
    forces of several vertex weights, and those residuals add up to millimetres along a garment),
    and element terms are evaluated in float32 on positions relative to the vertex, which are
    small and exact.  With ``tile_particles`` > 0 (CUDA) the world's positions sit in a
    shared-memory tile of that many particles for the whole launch (loaded and stored once); with
    0 they are read and written in global memory.  One kernel per flag set: the flags remove what
    a scene does not have at compile time.

    With ``self_contact``, each particle's Newton step also carries the contact energy of every
    vertex-triangle and edge-edge pair it belongs to (``SelfContact``'s pair lists of the last
    search; the pair pushes all of its particles), and the step is then kept within the particle's
    displacement bound of where it was searched, after the body-contact plane: where a body part presses two layers together, the layers do not cross and
    the body (whose skin is soft in reality) is what gives."""
    shared = tile_particles > 0
    tile_n = max(tile_particles, 1)
    tile_type = wp.tile[wp.vec3d, tile_n]

    tile_write = tile_writer(wp.vec3d, tile_n)

    def position(xs, x64, j, base):
        """Particle ``j``'s float64 position, from the tile or from global memory."""
        if wp.static(shared):
            return xs[j - base]
        return x64[j]

    position.__annotations__ = {"xs": tile_type, "x64": wp.array(dtype=wp.vec3d), "j": int, "base": int,
                                "return": wp.vec3d}
    position = wp.func(position, module="unique")

    def self_contact_vertex_terms(xs, x64, i, base, xi, adj_start, adj_slot, tri_count, tri_indices, vt_tri, vt_radius,
                                  tv_start, tv_count, tv_vertex, tv_radius, ee_edge, ee_radius, edges, edge_adj_start, edge_adj, stiffness):
        """Force [N] and Hessian [N/m] on particle ``i`` (at ``xi``) from every contact pair it
        belongs to: as the point of its own vertex-triangle pairs, as a corner of its triangles'
        pairs, as an end of its edges' edge-edge pairs (``SelfContact`` with ``pairs``)."""
        force = wp.vec3(0.0)
        hess = wp.mat33(0.0)
        for k in range(vt_tri.shape[1]):
            t = vt_tri[i, k]
            if t < 0:
                break
            f, h = vertex_triangle_contact(wp.vec3(0.0), wp.vec3(position(xs, x64, tri_indices[t, 0], base) - xi),
                                           wp.vec3(position(xs, x64, tri_indices[t, 1], base) - xi),
                                           wp.vec3(position(xs, x64, tri_indices[t, 2], base) - xi), -1,
                                           vt_radius[i, k], stiffness)
            force = force + f
            hess = hess + h
        for s in range(adj_start[i], adj_start[i + 1]):
            slot = adj_slot[s]
            if slot < 3 * tri_count:
                t = slot // 3
                corner = slot - 3 * t
                for k in range(tv_start[t], tv_start[t] + tv_count[t]):
                    j = tv_vertex[k]
                    f, h = vertex_triangle_contact(wp.vec3(position(xs, x64, j, base) - xi),
                                                   wp.vec3(position(xs, x64, tri_indices[t, 0], base) - xi),
                                                   wp.vec3(position(xs, x64, tri_indices[t, 1], base) - xi),
                                                   wp.vec3(position(xs, x64, tri_indices[t, 2], base) - xi), corner,
                                                   tv_radius[k], stiffness)
                    force = force + f
                    hess = hess + h
        for s in range(edge_adj_start[i], edge_adj_start[i + 1]):
            code = edge_adj[s]
            e = code // 2
            end = code - 2 * e
            p1 = wp.vec3(position(xs, x64, edges[e][0], base) - xi)
            q1 = wp.vec3(position(xs, x64, edges[e][1], base) - xi)
            for k in range(ee_edge.shape[1]):
                g = ee_edge[e, k]
                if g < 0:
                    break
                f, h = edge_edge_contact(p1, q1, wp.vec3(position(xs, x64, edges[g][0], base) - xi),
                                         wp.vec3(position(xs, x64, edges[g][1], base) - xi), end, ee_radius[e, k],
                                         stiffness)
                force = force + f
                hess = hess + h
        return force, hess

    self_contact_vertex_terms.__annotations__ = {
        "xs": tile_type, "x64": wp.array(dtype=wp.vec3d), "i": int, "base": int, "xi": wp.vec3d,
        "adj_start": wp.array(dtype=wp.int32), "adj_slot": wp.array(dtype=wp.int32), "tri_count": int,
        "tri_indices": wp.array2d(dtype=wp.int32), "vt_tri": wp.array2d(dtype=wp.int32),
        "vt_radius": wp.array2d(dtype=float), "tv_start": wp.array(dtype=wp.int32),
        "tv_count": wp.array(dtype=wp.int32), "tv_vertex": wp.array(dtype=wp.int32), "tv_radius": wp.array(dtype=float),
        "ee_edge": wp.array2d(dtype=wp.int32), "ee_radius": wp.array2d(dtype=float), "edges": wp.array(dtype=wp.vec2i),
        "edge_adj_start": wp.array(dtype=wp.int32), "edge_adj": wp.array(dtype=wp.int32), "stiffness": float}
    self_contact_vertex_terms = wp.func(self_contact_vertex_terms, module="unique")

    @wp.kernel(module="unique", enable_backward=False)
    def solve_vertices_vbd(
        # Model:
        world_particle_start: wp.array(dtype=wp.int32),
        world_particle_count: wp.array(dtype=wp.int32),
        vertex_world_offsets: wp.array2d(dtype=wp.int32),
        vertex_order: wp.array(dtype=wp.int32),
        inv_mass: wp.array(dtype=float),
        adj_start: wp.array(dtype=wp.int32),
        adj_slot: wp.array(dtype=wp.int32),
        tri_count: int,
        tri_indices: wp.array2d(dtype=wp.int32),
        tri_dm_inv: wp.array(dtype=wp.mat22),
        tri_compliance: wp.array(dtype=wp.vec3),
        bend_indices: wp.array2d(dtype=wp.int32),
        bend_rest_angle: wp.array(dtype=float),
        bend_compliance: wp.array(dtype=float),
        world_active: wp.array(dtype=wp.int32),
        inv_dt2: float,
        iterations: int,
        # Attachments:
        particle_attachment: wp.array(dtype=wp.int32),
        attachment_target: wp.array(dtype=wp.vec3),
        world_attachment_stiffness: wp.array(dtype=float),
        world_attachment_enabled: wp.array(dtype=wp.int32),
        # Body contact:
        contact_active: wp.array(dtype=wp.int32),
        contact_normal: wp.array(dtype=wp.vec3),
        contact_offset: wp.array(dtype=float),
        contact_motion: wp.array(dtype=wp.vec3),
        world_friction: wp.array(dtype=float),
        friction_slip: float,
        # Substep start:
        x64_prev: wp.array(dtype=wp.vec3d),
        target: wp.array(dtype=wp.vec3),
        # Self-contact (SelfContact's pair lists of the last search):
        sc_vt_tri: wp.array2d(dtype=wp.int32),
        sc_vt_radius: wp.array2d(dtype=float),
        sc_tv_start: wp.array(dtype=wp.int32),
        sc_tv_count: wp.array(dtype=wp.int32),
        sc_tv_vertex: wp.array(dtype=wp.int32),
        sc_tv_radius: wp.array(dtype=float),
        sc_ee_edge: wp.array2d(dtype=wp.int32),
        sc_ee_radius: wp.array2d(dtype=float),
        sc_edges: wp.array(dtype=wp.vec2i),
        sc_edge_adj_start: wp.array(dtype=wp.int32),
        sc_edge_adj: wp.array(dtype=wp.int32),
        sc_stiffness: float,
        sc_x_searched: wp.array(dtype=wp.vec3),
        sc_d_min: wp.array(dtype=float),
        sc_fraction: float,
        sc_min_separation: float,
        sc_normal: wp.array(dtype=wp.vec3),
        sc_d_side: wp.array(dtype=float),
        sc_d_ball: wp.array(dtype=float),
        sc_slope: float,
        world_self_contact: wp.array(dtype=wp.int32),
        # In/out:
        x64: wp.array(dtype=wp.vec3d),
    ):
        w, lane = wp.tid()
        if world_active[w] == 0:
            return
        stride = wp.block_dim()
        base = world_particle_start[w]
        xs = wp.tile_load(x64, shape=tile_n, offset=base, storage="shared")
        for _it in range(iterations):
            for c in range(vertex_world_offsets.shape[0]):
                for k in range(vertex_world_offsets[c, w] + lane, vertex_world_offsets[c, w + 1], stride):
                    i = vertex_order[k]
                    im = inv_mass[i]
                    if im == 0.0:
                        continue
                    xi = position(xs, x64, i, base)
                    m_dt2 = inv_dt2 / im
                    # inertia: m / dt^2 (y - x) with y - x = (dt v + dt^2 g) - (x - x_prev)
                    force = (target[i] - wp.vec3(xi - x64_prev[i])) * m_dt2
                    hess = wp.identity(n=3, dtype=float) * m_dt2
                    for s in range(adj_start[i], adj_start[i + 1]):
                        slot = adj_slot[s]
                        if slot < 3 * tri_count:
                            t = slot // 3
                            corner = slot - 3 * t
                            p0 = wp.vec3(position(xs, x64, tri_indices[t, 0], base) - xi)
                            p1 = wp.vec3(position(xs, x64, tri_indices[t, 1], base) - xi)
                            p2 = wp.vec3(position(xs, x64, tri_indices[t, 2], base) - xi)
                            ft, ht = triangle_vertex_terms(p0, p1, p2, corner, tri_dm_inv[t], tri_compliance[t])
                            force = force + ft
                            hess = hess + ht
                        else:
                            if wp.static(bending):
                                e = slot - 3 * tri_count
                                b = e // 4
                                q0 = wp.vec3(position(xs, x64, bend_indices[b, 0], base) - xi)
                                q1 = wp.vec3(position(xs, x64, bend_indices[b, 1], base) - xi)
                                q2 = wp.vec3(position(xs, x64, bend_indices[b, 2], base) - xi)
                                q3 = wp.vec3(position(xs, x64, bend_indices[b, 3], base) - xi)
                                fb, hb = bending_vertex_terms(q0, q1, q2, q3, e - 4 * b, bend_rest_angle[b],
                                                              bend_compliance[b])
                                force = force + fb
                                hess = hess + hb
                    if wp.static(attachments):
                        a = particle_attachment[i]
                        if a >= 0:
                            if world_attachment_enabled[w] != 0:
                                ka = world_attachment_stiffness[w]
                                force = force + (attachment_target[a] - wp.vec3(xi)) * ka
                                hess = hess + wp.identity(n=3, dtype=float) * ka
                    sc_on = int(0)
                    if wp.static(self_contact):
                        sc_on = world_self_contact[w]
                        if sc_on != 0:
                            fc, hc = self_contact_vertex_terms(xs, x64, i, base, xi, adj_start, adj_slot, tri_count,
                                                               tri_indices, sc_vt_tri, sc_vt_radius, sc_tv_start,
                                                               sc_tv_count, sc_tv_vertex, sc_tv_radius, sc_ee_edge,
                                                               sc_ee_radius, sc_edges, sc_edge_adj_start, sc_edge_adj,
                                                               sc_stiffness)
                            force = force + fc
                            hess = hess + hc
                    p = xi
                    if wp.abs(wp.determinant(hess)) > 1.0e-30:
                        p = xi + wp.vec3d(wp.inverse(hess) * force)
                    if wp.static(body_contact):
                        if contact_active[i] != 0:
                            n = contact_normal[i]
                            gap = wp.dot(n, wp.vec3(p)) - contact_offset[i]
                            if gap < 0.0:
                                if wp.static(friction):
                                    # mu N, N the normal force the plane carries [N]: what pushes the
                                    # vertex into it (inertia, gravity, elastic and layer forces)
                                    limit = world_friction[w] * wp.max(-wp.dot(force, n), 0.0)
                                    if limit > 0.0:
                                        f_t, h_t = friction_terms(wp.vec3(xi - x64_prev[i]) - contact_motion[i], n,
                                                                  limit, friction_slip)
                                        hf = hess + h_t
                                        if wp.abs(wp.determinant(hf)) > 1.0e-30:
                                            p = xi + wp.vec3d(wp.inverse(hf) * (force + f_t))
                                        gap = wp.dot(n, wp.vec3(p)) - contact_offset[i]
                                if gap < 0.0:
                                    p = p - wp.vec3d(n * gap)
                    # cloth-cloth bounds win over the body plane: where an arm presses a sleeve against
                    # the torso layer, the skin (soft in reality) gives, not the layers
                    if wp.static(self_contact):
                        if sc_on != 0:
                            if sc_slope > 0.0 and sc_fraction > 0.0:
                                p = within_directional_bound(p, sc_x_searched[i], sc_normal[i], sc_d_side[i],
                                                             sc_d_ball[i], sc_slope, sc_fraction, sc_min_separation)
                            else:
                                p = within_bound(p, sc_x_searched[i], sc_d_min[i], sc_fraction, sc_min_separation)
                    if wp.static(shared):
                        tile_write(xs, i - base, p)
                    else:
                        x64[i] = p
                block_sync()
        if wp.static(shared):
            for j in range(lane, world_particle_count[w], stride):
                x64[base + j] = xs[j]

    return solve_vertices_vbd


@wp.kernel(enable_backward=False)
def finalize_particles_vbd(
    # Model:
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_damping: wp.array(dtype=float),
    extra_damping: float,
    gravity: wp.vec3,
    dt: float,
    # Substep start:
    x64_prev: wp.array(dtype=wp.vec3d),
    v_prev: wp.array(dtype=wp.vec3),
    # In:
    x64: wp.array(dtype=wp.vec3d),
    # Out:
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    gravity_share_out: wp.array(dtype=float),
):
    """Velocities (x - x_prev) / dt with damping, on the float64 positions (friction acted inside
    the sweep); the state's float32 positions are their rounding.  Also the share of gravity
    (0..1) the substep accelerated each particle by, for the next substep's start
    (``predict_particles``)."""
    i = wp.tid()
    w = particle_world[i]
    if world_active[w] == 0:
        v_out[i] = v_prev[i]
        return
    p = x64[i]
    if inv_mass[i] == 0.0:
        x_out[i] = wp.vec3(p)
        v_out[i] = wp.vec3(0.0)
        return
    disp = wp.vec3(p - x64_prev[i])
    x_out[i] = wp.vec3(p)
    decay = wp.max(1.0 - (world_damping[w] + extra_damping) * dt, 0.0)
    vel = disp / dt * decay
    v_out[i] = vel
    g2 = wp.dot(gravity, gravity)
    if g2 > 0.0:
        accel = (vel - v_prev[i]) / dt
        # dead zone: below half of g counts as supported (0), so a resting or swinging particle
        # starts at its own position and the rest state is not biased by noise in its acceleration
        gravity_share_out[i] = wp.clamp(2.0 * wp.dot(accel, gravity) / g2 - 1.0, 0.0, 1.0)
