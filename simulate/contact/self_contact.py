"""Cloth self-contact found with a BVH over the cloth: vertex-triangle pushes (``SolverXPBD``)
or vertex-triangle and edge-edge pair lists for a contact energy (``SolverVBD``).

All worlds' cloth triangles live in one ``wp.Mesh`` whose points are the particles shifted to
per-world grid cells (as for the body), so one refit and one query launch serve every world
and a world never sees another world's cloth.  None of this runs unless
``Features.self_contact`` is on.

**Pushes** (default): once per search each particle finds the nearest triangle outside its
2-ring within ``thickness + margin`` (BVH AABB query, exact point-triangle distance) and
remembers which side of it it was on.  In every solver iteration the particle is then pushed
part of the way (``relaxation``) back to ``thickness`` on that side (one-sided: the particle
moves, each triangle's corners are pushed by their own queries), written to a per-particle
delta so results stay deterministic.

**Pairs** (``pairs=True``): each search lists, within the reach, every particle's nearest
triangles that do not contain it and every edge's nearest edges that share no vertex with it (a
BVH over the edges), at most ``pairs_per_primitive`` each, the nearest, ties broken by index, so
the lists do not depend on the BVH's visit order; the same vertex-triangle pairs are also listed
per triangle (CSR rows sorted by particle), so each pair acts on its four particles alike. A solver gives each pair
the energy stiffness / 2 (r - d)^2 while the pair's distance d is below its radius r (the
thickness, or the pair's distance in the rest geometry where that is less) and every particle of
the pair its share of the push: as the point, as a triangle's corner, as an edge's end
(``simulate.solvers.vbd.kernels``). Neighbours are pairs too (only primitives sharing a vertex
are not): a fold pushes back wherever it closes below its rest distance.

**Displacement bounds** (conservative, as in VBD's and Offset Geometric Contact's cloth contact):
at each search, every particle also gets ``d_min``, the smallest distance from it to any
vertex-triangle or edge-edge pair it belongs to (as the vertex or as a triangle's corner, as an
edge's end) within the reach, the reach itself where there is none. Every pair counts but those
sharing a vertex (the contact candidates' 2-ring and rest exclusions do not apply: a bound only
limits motion). Until the next search a solver keeps each particle within ``bound_fraction``
(< 1/2) of ``d_min - min_separation`` of where it was searched (``SolverVBD``'s sweep; a tenth
of ``d_min`` for a pair that starts closer). Two primitives then close by less than the distance
between them, and never below ``min_separation`` once that far apart: new intersections cannot
form, whatever the penalty and the elastic forces do. The bounds also win over body contact: where a body part presses two layers together
(an arm lowered onto the torso), the layers stay apart and the skin, soft in reality, gives.

**Refreshed lists** (``search_every``, ``skin``): the BVH queries are most of the cost, so a solver
may have every world search on every ``search_every``-th substep only, listing pairs up to ``skin``
beyond the reach. In between, a world searches only where one of its particles moved farther than
half the skin since its last search; the others *refresh*: the listed pairs' distances,
certificates and bounds at the new positions, computed as a search computes them, without a query.
A pair the lists leave out (farther than the list reach, or past ``pairs_per_primitive``) put its
distance at the search into its particles' ``horizon``; at a refresh it bounds them by ``horizon``
less twice the largest displacement in the world since the search (no pair closed by more), and,
with directional bounds, by half of that in the ball (a certificate is at least half its pair's
distance). A refresh's bounds are therefore never wider than a search's at the same positions, and
pairs beyond the list reach at the search stay beyond the contact reach.

**Directional bounds** (``directional_bounds``): a ball of 0.45 ``d_min`` pins two layers pressed
together (the gap and so the ball go to ``min_separation``): they can neither slide nor part, and
the cloth around them stretches. Instead each particle gets a *bound normal* ``n`` (the direction
away from its nearest pair, from the last search's pairs at the new positions) and keeps to

    n . u - c |u| >= -f d_side     and     |u| <= f d_ball      (u: its displacement, f < 1/2)

where ``d_side`` is the smallest certificate distance of the pairs whose certificate direction is
within atan(c) of ``n`` (``BOUND_CONE_SLOPE``) and ``d_ball`` that of all others (the reach where
none). A pair's certificate is a unit direction m and s > 0 with m . (a - b) >= s for every point a
of one primitive and b of the other (the mean of its particles' bound normals where that separates
by at least half the distance, else the closest points' direction and s = the distance). A particle
on the pair's a-side within the cone then approaches along m by at most f d_side cos(theta) <= f s
(n . u >= -f d_side + c |u| and tan(theta) <= c), one in its ball by at most f s, and the b-side
likewise along -m: the pair closes by less than 2 f s < s along m, and as m . (a - b) is linear in
the corners it stays positive over both primitives: no crossing, as with the balls. Here f d is
0.45 max(d - ``min_separation``, 0): a pair closer than that (float32 rounding can put one there)
may part but not close. A particle moving away from its nearest pair (u along n) is held only by
its ball, and one sliding along it by f d_side / c.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from simulate.cloth.model import ClothModel
from simulate.contact.body_collider import BVH_OPTIONS, world_cell_offsets
from simulate.contact.closest import closest_point_barycentric, point_triangle_offset, shift_tolerance

wp.set_module_options({"enable_backward": False})

__all__ = ["SelfContact"]

MAX_SWEEP_M = 0.03
"""Largest extra search reach for a fast particle between candidate searches [m]."""

BOUND_FRACTION = 0.45
"""Share of its smallest pair distance a particle may move between searches (< 1/2: two
primitives moving toward each other then close by at most 90 % of their distance)."""

BOUND_CONE_SLOPE = 0.25
"""Directional bounds: a pair whose separating direction is within atan(this) (14 degrees) of a
particle's bound normal is held by the particle's half-space bound, the rest by its ball bound
(module docstring); a particle may move tangentially 1 / this times its half-space budget."""

PAIRS_PER_PRIMITIVE = 8
"""Contact pairs listed per particle, triangle or edge (the nearest within the reach)."""

MIN_SEPARATION_M = 1.0e-4
"""Distance [m] the bounds keep pairs apart: a particle moves at most ``BOUND_FRACTION`` x (its
smallest pair distance less this), so a pair never closes below it. Pairs the contact penalty does
not act on (a fold within the 2-ring) would otherwise close by 90 % every search and in the end
cross by float32 rounding (positions at 1 m resolve 0.06 um)."""


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


@wp.func
def in_two_ring(i: int, a: int, b: int, c: int, adj_start: wp.array(dtype=wp.int32), adj_slot: wp.array(dtype=wp.int32),
                tri_slots: int, tri_indices: wp.array2d(dtype=wp.int32)) -> bool:
    """Whether triangle (a, b, c) shares a vertex with a triangle incident to particle i."""
    for s in range(adj_start[i], adj_start[i + 1]):
        slot = adj_slot[s]
        if slot >= tri_slots:  # a particle's slots ascend: its triangles' come before its bending elements'
            break
        t = slot // 3
        u0 = tri_indices[t, 0]
        u1 = tri_indices[t, 1]
        u2 = tri_indices[t, 2]
        if u0 == a or u0 == b or u0 == c or u1 == a or u1 == b or u1 == c or u2 == a or u2 == b or u2 == c:
            return True
    return False


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
        if in_two_ring(i, a, b, c, adj_start, adj_slot, tri_slots, tri_indices):
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


@wp.func
def segment_closest(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3) -> wp.vec3:
    """Closest points of segments p1q1 and p2q2 (Ericson 2004, 5.1.9): ``(s, t, distance [m])``
    with the points at ``p1 + s (q1 - p1)`` and ``p2 + t (q2 - p2)``."""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    eps = 1.0e-20
    if a <= eps and e <= eps:
        return wp.vec3(0.0, 0.0, wp.length(r))
    if a <= eps:
        t = wp.clamp(f / e, 0.0, 1.0)
    else:
        c = wp.dot(d1, r)
        if e <= eps:
            s = wp.clamp(-c / a, 0.0, 1.0)
        else:
            b = wp.dot(d1, d2)
            denom = a * e - b * b
            if denom > eps * a * e:
                s = wp.clamp((b * f - c * e) / denom, 0.0, 1.0)
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = wp.clamp(-c / a, 0.0, 1.0)
            elif t > 1.0:
                t = 1.0
                s = wp.clamp((b - c) / a, 0.0, 1.0)
    return wp.vec3(s, t, wp.length((p1 + d1 * s) - (p2 + d2 * t)))


@wp.func
def segment_distance(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3) -> float:
    """Distance [m] between segments p1q1 and p2q2."""
    return segment_closest(p1, q1, p2, q2)[2]


@wp.func
def insert_nearest(ids: wp.array2d(dtype=wp.int32), dist: wp.array2d(dtype=float), row: int, key: int, d: float):
    """Puts ``key`` at distance ``d`` into row ``row`` of a list kept sorted by (distance, key),
    the farthest entry falling off a full row. Each key arrives once (its BVH leaf is visited
    once), and the result does not depend on the order keys arrive in (no atomics, one row per
    thread). Returns the key that is not in the row after the insert and its distance: ``key``
    itself where the row is full of nearer ones, the entry that fell off, or -1."""
    n = ids.shape[1]
    pos = n
    for k in range(n):
        kk = ids[row, k]
        if kk < 0 or d < dist[row, k] or (d == dist[row, k] and key < kk):
            pos = k
            break
    if pos == n:
        return key, d
    dropped = ids[row, n - 1]
    dropped_d = dist[row, n - 1]
    k = n - 1
    while k > pos:
        ids[row, k] = ids[row, k - 1]
        dist[row, k] = dist[row, k - 1]
        k -= 1
    ids[row, pos] = key
    dist[row, pos] = d
    return dropped, dropped_d


@wp.func
def contact_radius(rest_distance: float, thickness: float) -> float:
    """Distance [m] a pair's contact energy keeps: ``thickness``, or the pair's distance in the
    rest geometry where that is less (where panels meet at an acute angle, the rest shape is
    at rest)."""
    return wp.min(thickness, rest_distance)


@wp.func
def vertex_triangle_bound(p: wp.vec3, a: int, b: int, c: int, xa: wp.vec3, xb: wp.vec3, xc: wp.vec3, diff: wp.vec3,
                          d: float, n_i: wp.vec3, normal: wp.array(dtype=wp.vec3), cone_cos: float,
                          side_i: float, ball_i: float, d_min: wp.array(dtype=float), d_side: wp.array(dtype=float),
                          d_ball: wp.array(dtype=float)):
    """A vertex-triangle pair (point ``p`` with bound normal ``n_i``, triangle ``a b c`` at ``xa xb
    xc``, offset ``diff`` of length ``d`` [m] from the triangle to the point) into the bounds: with
    ``cone_cos`` 0 its distance into the corners' ``d_min`` (atomics), else its certificate into
    the corners' ``d_side`` / ``d_ball`` (atomics) and the point's, which are returned (the point
    gathers its own in registers)."""
    if cone_cos == 0.0:
        wp.atomic_min(d_min, a, d)
        wp.atomic_min(d_min, b, d)
        wp.atomic_min(d_min, c, d)
        return side_i, ball_i
    # certificate: the particles' mean bound normal where it separates by >= d / 2
    m = wp.vec3(0.0)
    sep = float(0.0)
    na = normal[a]
    nb = normal[b]
    nc = normal[c]
    raw = n_i - na - nb - nc
    if wp.length(raw) > 0.5:
        m = wp.normalize(raw)
        sep = wp.dot(m, p) - wp.max(wp.dot(m, xa), wp.max(wp.dot(m, xb), wp.dot(m, xc)))
    if sep < 0.5 * d:
        m = diff / wp.max(d, 1.0e-12)
        sep = d
    side = side_i
    ball = ball_i
    if wp.dot(m, n_i) >= cone_cos:
        side = wp.min(side, sep)
    else:
        ball = wp.min(ball, sep)
    classify_bound(a, na, -m, sep, cone_cos, d_side, d_ball)
    classify_bound(b, nb, -m, sep, cone_cos, d_side, d_ball)
    classify_bound(c, nc, -m, sep, cone_cos, d_side, d_ball)
    return side, ball


@wp.func
def own_bounds(i: int, best: float, side_i: float, ball_i: float, cone_cos: float, d_min: wp.array(dtype=float),
               d_side: wp.array(dtype=float), d_ball: wp.array(dtype=float)):
    """A particle's bounds gathered in registers, into its ``d_min`` (``cone_cos`` 0) or its
    ``d_side`` / ``d_ball`` (one atomic each)."""
    if cone_cos == 0.0:
        wp.atomic_min(d_min, i, best)
    else:
        wp.atomic_min(d_side, i, side_i)
        wp.atomic_min(d_ball, i, ball_i)


@wp.kernel
def vertex_triangle_pairs(
    mesh: wp.uint64,
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_world: wp.array(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_self_contact: wp.array(dtype=wp.int32),
    world_offset: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    x_rest: wp.array(dtype=wp.vec3),
    reach: float,
    list_reach: float,
    thickness: float,
    normal: wp.array(dtype=wp.vec3),
    cone_cos: float,
    world_search: wp.array(dtype=wp.int32),
    # Out:
    pair_tri: wp.array2d(dtype=wp.int32),
    pair_dist: wp.array2d(dtype=float),
    pair_radius: wp.array2d(dtype=float),
    # In/out (filled with ``reach``, ``horizon`` with ``list_reach``, by the caller):
    d_min: wp.array(dtype=float),
    d_side: wp.array(dtype=float),
    d_ball: wp.array(dtype=float),
    horizon: wp.array(dtype=float),
):
    """Each particle's nearest triangles within ``list_reach`` [m] that do not contain it
    (``pair_tri``, -1 past the last; their contact radii in ``pair_radius``), and the bounds of
    the pairs within ``reach``: with ``cone_cos`` 0 the smallest distance of these pairs to the
    particle and the triangle's corners (``d_min``), else each pair's certificate into its four
    particles' ``d_side`` / ``d_ball`` (the particle's own gathered in registers; float atomic
    min). A pair within ``list_reach`` that the full list leaves out puts its distance into its
    four particles' ``horizon`` (what a refresh of the lists cannot see). Worlds with
    ``world_search`` 0 keep their lists (``vertex_triangle_refresh``)."""
    i = wp.tid()
    w = particle_world[i]
    if world_search[w] == 0:
        return
    for k in range(pair_tri.shape[1]):
        pair_tri[i, k] = -1
    if world_active[w] == 0 or world_self_contact[w] == 0:
        return
    p = x[i]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])):
        return
    q = p + world_offset[w]
    r_box = list_reach + shift_tolerance(world_offset[w])
    r = wp.vec3(r_box, r_box, r_box)
    query = wp.mesh_query_aabb(mesh, q - r, q + r)
    face = int(0)
    best = reach
    # the particle's own bounds gather in registers (one atomic each), its pairs' triangle corners
    # take theirs by atomics
    n_i = normal[i]
    side_i = reach
    ball_i = reach
    hor_i = list_reach
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
        diff = point_triangle_offset(p, xa, xb, xc)
        d = wp.length(diff)
        if d >= list_reach:
            continue
        if d < reach:
            best = wp.min(best, d)
            side_i, ball_i = vertex_triangle_bound(p, a, b, c, xa, xb, xc, diff, d, n_i, normal, cone_cos, side_i,
                                                   ball_i, d_min, d_side, d_ball)
        dropped, dropped_d = insert_nearest(pair_tri, pair_dist, i, face, d)
        if dropped >= 0:
            hor_i = wp.min(hor_i, dropped_d)
            wp.atomic_min(horizon, tri_indices[dropped, 0], dropped_d)
            wp.atomic_min(horizon, tri_indices[dropped, 1], dropped_d)
            wp.atomic_min(horizon, tri_indices[dropped, 2], dropped_d)
    own_bounds(i, best, side_i, ball_i, cone_cos, d_min, d_side, d_ball)
    wp.atomic_min(horizon, i, hor_i)
    pr = x_rest[i]
    for k in range(pair_tri.shape[1]):
        t = pair_tri[i, k]
        if t < 0:
            break
        rest_offset = point_triangle_offset(pr, x_rest[tri_indices[t, 0]], x_rest[tri_indices[t, 1]],
                                            x_rest[tri_indices[t, 2]])
        pair_radius[i, k] = contact_radius(wp.length(rest_offset), thickness)


@wp.kernel
def vertex_triangle_refresh(
    tri_indices: wp.array2d(dtype=wp.int32),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_self_contact: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    reach: float,
    normal: wp.array(dtype=wp.vec3),
    cone_cos: float,
    pair_tri: wp.array2d(dtype=wp.int32),
    horizon: wp.array(dtype=float),
    world_moved: wp.array(dtype=float),
    world_search: wp.array(dtype=wp.int32),
    # In/out (filled with ``reach`` by the caller):
    d_min: wp.array(dtype=float),
    d_side: wp.array(dtype=float),
    d_ball: wp.array(dtype=float),
):
    """The bounds of each particle's listed vertex-triangle pairs at positions ``x``, as the search
    finds them (``vertex_triangle_pairs``), and of the pairs the lists left out: at least the
    particle's ``horizon`` less twice its world's largest displacement since the search
    (``world_moved``), into ``d_min``, or as half of that into ``d_ball`` (a left-out pair has no
    certificate, which is at least half its distance). Only in worlds with ``world_search`` 0."""
    i = wp.tid()
    w = particle_world[i]
    if world_search[w] != 0 or world_active[w] == 0 or world_self_contact[w] == 0:
        return
    p = x[i]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])):
        return
    best = reach
    n_i = normal[i]
    side_i = reach
    ball_i = reach
    for k in range(pair_tri.shape[1]):
        face = pair_tri[i, k]
        if face < 0:
            break
        a = tri_indices[face, 0]
        b = tri_indices[face, 1]
        c = tri_indices[face, 2]
        xa = x[a]
        xb = x[b]
        xc = x[c]
        diff = point_triangle_offset(p, xa, xb, xc)
        d = wp.length(diff)
        if d < reach:
            best = wp.min(best, d)
            side_i, ball_i = vertex_triangle_bound(p, a, b, c, xa, xb, xc, diff, d, n_i, normal, cone_cos, side_i,
                                                   ball_i, d_min, d_side, d_ball)
    unseen = wp.max(horizon[i] - 2.0 * world_moved[w], 0.0)
    if cone_cos == 0.0:
        best = wp.min(best, unseen)
    else:
        ball_i = wp.min(ball_i, 0.5 * unseen)
    own_bounds(i, best, side_i, ball_i, cone_cos, d_min, d_side, d_ball)


@wp.kernel
def world_displacement(x: wp.array(dtype=wp.vec3), x_listed: wp.array(dtype=wp.vec3),
                       particle_world: wp.array(dtype=wp.int32), world_moved: wp.array(dtype=float)):
    """Each world's largest particle displacement [m] since the lists were searched (float atomic
    max: the result does not depend on the order)."""
    i = wp.tid()
    u = wp.length(x[i] - x_listed[i])
    if wp.isfinite(u):
        wp.atomic_max(world_moved, particle_world[i], u)
    else:
        wp.atomic_max(world_moved, particle_world[i], 1.0e30)


@wp.kernel
def choose_search_worlds(world_moved: wp.array(dtype=float), world_active: wp.array(dtype=wp.int32),
                         world_self_contact: wp.array(dtype=wp.int32), threshold: float,
                         world_search: wp.array(dtype=wp.int32), world_listed: wp.array(dtype=wp.int32),
                         counts: wp.array2d(dtype=wp.int32)):
    """A world searches where a particle moved farther than ``threshold`` [m] since its last search
    or its lists were not searched with self-contact on (inactive then: empty lists); its
    ``world_listed`` then records whether this search lists pairs. ``counts[w]``: (self-contact
    substeps, searches among them) of an active world with self-contact on."""
    w = wp.tid()
    search = int(0)
    if world_moved[w] > threshold or world_listed[w] == 0:
        search = 1
    world_search[w] = search
    on = world_active[w] != 0 and world_self_contact[w] != 0
    if search == 1:
        world_listed[w] = wp.where(on, 1, 0)
    if on:
        counts[w, 0] = counts[w, 0] + 1
        counts[w, 1] = counts[w, 1] + search


@wp.kernel
def restart_lists(x: wp.array(dtype=wp.vec3), particle_world: wp.array(dtype=wp.int32),
                  world_search: wp.array(dtype=wp.int32), list_reach: float, x_listed: wp.array(dtype=wp.vec3),
                  horizon: wp.array(dtype=float)):
    """In searching worlds: the lists' positions set to ``x``, ``horizon`` to the list reach."""
    i = wp.tid()
    if world_search[particle_world[i]] != 0:
        x_listed[i] = x[i]
        horizon[i] = list_reach


@wp.kernel
def count_triangle_pairs(pair_tri: wp.array2d(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    """Vertex-triangle pairs listed per triangle (integer atomics: the count does not depend on
    the order)."""
    i = wp.tid()
    for k in range(pair_tri.shape[1]):
        t = pair_tri[i, k]
        if t < 0:
            break
        wp.atomic_add(count, t, 1)


@wp.kernel
def scatter_triangle_pairs(pair_tri: wp.array2d(dtype=wp.int32), pair_radius: wp.array2d(dtype=float),
                           start: wp.array(dtype=wp.int32), cursor: wp.array(dtype=wp.int32),
                           tv_vertex: wp.array(dtype=wp.int32), tv_radius: wp.array(dtype=float)):
    """Each particle's vertex-triangle pairs written into its triangles' rows of the CSR lists (in
    any order; ``sort_triangle_pairs`` orders them)."""
    i = wp.tid()
    for k in range(pair_tri.shape[1]):
        t = pair_tri[i, k]
        if t < 0:
            break
        slot = start[t] + wp.atomic_add(cursor, t, 1)
        tv_vertex[slot] = i
        tv_radius[slot] = pair_radius[i, k]


@wp.kernel
def sort_triangle_pairs(start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                        tv_vertex: wp.array(dtype=wp.int32), tv_radius: wp.array(dtype=float)):
    """Each triangle's row sorted by particle index, so forces sum in the same order every run."""
    t = wp.tid()
    a = start[t]
    b = a + count[t]
    for k in range(a + 1, b):
        v = tv_vertex[k]
        r = tv_radius[k]
        m = k - 1
        while m >= a and tv_vertex[m] > v:
            tv_vertex[m + 1] = tv_vertex[m]
            tv_radius[m + 1] = tv_radius[m]
            m -= 1
        tv_vertex[m + 1] = v
        tv_radius[m + 1] = r


@wp.kernel
def place_edge_boxes(edges: wp.array(dtype=wp.vec2i), particle_world: wp.array(dtype=wp.int32),
                     world_offset: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3),
                     lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Bounding box of each edge at its world's grid cell (the edge BVH's leaves)."""
    e = wp.tid()
    off = world_offset[particle_world[edges[e][0]]]
    p = x[edges[e][0]] + off
    q = x[edges[e][1]] + off
    lowers[e] = wp.min(p, q)
    uppers[e] = wp.max(p, q)


@wp.kernel
def bound_normals(
    x: wp.array(dtype=wp.vec3),
    tri_count: int,
    tri_indices: wp.array2d(dtype=wp.int32),
    adj_start: wp.array(dtype=wp.int32),
    adj_slot: wp.array(dtype=wp.int32),
    vt_tri: wp.array2d(dtype=wp.int32),
    tv_start: wp.array(dtype=wp.int32),
    tv_count: wp.array(dtype=wp.int32),
    tv_vertex: wp.array(dtype=wp.int32),
    ee_edge: wp.array2d(dtype=wp.int32),
    edges: wp.array(dtype=wp.vec2i),
    edge_adj_start: wp.array(dtype=wp.int32),
    edge_adj: wp.array(dtype=wp.int32),
    # Out:
    normal_out: wp.array(dtype=wp.vec3),
):
    """Each particle's bound normal: the unit direction away from its nearest listed pair (as the
    point, a triangle's corner or an edge's end) at positions ``x``, zero without one. The lists
    are read in a fixed order, the first of equal distances wins (deterministic)."""
    i = wp.tid()
    best = float(1.0e30)
    n = wp.vec3(0.0)
    p = x[i]
    for k in range(vt_tri.shape[1]):
        t = vt_tri[i, k]
        if t < 0:
            break
        diff = point_triangle_offset(p, x[tri_indices[t, 0]], x[tri_indices[t, 1]], x[tri_indices[t, 2]])
        d = wp.length(diff)
        if d < best and d > 1.0e-12:
            best = d
            n = diff / d
    for s in range(adj_start[i], adj_start[i + 1]):
        slot = adj_slot[s]
        if slot < 3 * tri_count:
            t = slot // 3
            a = x[tri_indices[t, 0]]
            b = x[tri_indices[t, 1]]
            c = x[tri_indices[t, 2]]
            for k in range(tv_start[t], tv_start[t] + tv_count[t]):
                diff = -point_triangle_offset(x[tv_vertex[k]], a, b, c)
                d = wp.length(diff)
                if d < best and d > 1.0e-12:
                    best = d
                    n = diff / d
    for s in range(edge_adj_start[i], edge_adj_start[i + 1]):
        e = edge_adj[s] // 2
        p1 = x[edges[e][0]]
        q1 = x[edges[e][1]]
        for k in range(ee_edge.shape[1]):
            g = ee_edge[e, k]
            if g < 0:
                break
            p2 = x[edges[g][0]]
            q2 = x[edges[g][1]]
            cl = segment_closest(p1, q1, p2, q2)
            diff = (p1 + (q1 - p1) * cl[0]) - (p2 + (q2 - p2) * cl[1])
            d = wp.length(diff)
            if d < best and d > 1.0e-12:
                best = d
                n = diff / d
    normal_out[i] = n


@wp.func
def classify_bound(j: int, n_j: wp.vec3, m: wp.vec3, s: float, cone_cos: float,
                   d_side: wp.array(dtype=float), d_ball: wp.array(dtype=float)):
    """A pair's certificate (direction ``m`` from particle ``j``'s side, distance ``s`` [m]) into
    ``j``'s half-space bound where ``m`` is within the cone around its bound normal ``n_j``, else
    its ball."""
    if wp.dot(m, n_j) >= cone_cos:
        wp.atomic_min(d_side, j, s)
    else:
        wp.atomic_min(d_ball, j, s)


@wp.func
def edge_certificate(cl: wp.vec3, p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3, raw: wp.vec3):
    """Certificate (m from the first edge's side, s [m]) of the edge pair p1q1, p2q2 with closest
    points ``cl`` (``segment_closest``) and ``raw`` the first edge's ends' bound normals less the
    second's: the mean normal where it separates them by at least half their distance, else the
    closest points' direction and their distance."""
    d = cl[2]
    m = wp.vec3(0.0)
    sep = float(0.0)
    if wp.length(raw) > 0.5:
        m = wp.normalize(raw)
        sep = wp.min(wp.dot(m, p1), wp.dot(m, q1)) - wp.max(wp.dot(m, p2), wp.dot(m, q2))
    if sep < 0.5 * d:
        m = ((p1 + (q1 - p1) * cl[0]) - (p2 + (q2 - p2) * cl[1])) / wp.max(d, 1.0e-12)
        sep = d
    return m, sep


@wp.func
def edge_edge_bound(e: int, f: int, p: wp.vec3, q: wp.vec3, xa: wp.vec3, xb: wp.vec3, cl: wp.vec3, n0: wp.vec3,
                    n1: wp.vec3, raw: wp.vec3, cone_cos: float, side0: float, ball0: float, side1: float,
                    ball1: float):
    """Edge ``e`` (ends ``p q``, bound normals ``n0 n1``)'s pair with edge ``f`` (``xa xb``;
    ``cl``: ``segment_closest(p, q, xa, xb)``, ``raw``: e's ends' bound normals less f's) into
    e's ends' half-space and ball bounds (returned). The certificate is computed lower edge first
    from both edges of a pair, so its four particles keep to the same m and s (bit for bit)."""
    if e < f:
        m, sep = edge_certificate(cl, p, q, xa, xb, raw)
    else:
        m, sep = edge_certificate(segment_closest(xa, xb, p, q), xa, xb, p, q, -raw)
        m = -m
    s0 = side0
    b0 = ball0
    s1 = side1
    b1 = ball1
    if wp.dot(m, n0) >= cone_cos:
        s0 = wp.min(s0, sep)
    else:
        b0 = wp.min(b0, sep)
    if wp.dot(m, n1) >= cone_cos:
        s1 = wp.min(s1, sep)
    else:
        b1 = wp.min(b1, sep)
    return s0, b0, s1, b1


@wp.func
def edge_end_bounds(i0: int, i1: int, best: float, side0: float, ball0: float, side1: float, ball1: float,
                    cone_cos: float, d_min: wp.array(dtype=float), d_side: wp.array(dtype=float),
                    d_ball: wp.array(dtype=float)):
    """An edge's bounds gathered in registers into its two ends (one atomic per end and bound)."""
    if cone_cos == 0.0:
        wp.atomic_min(d_min, i0, best)
        wp.atomic_min(d_min, i1, best)
    else:
        wp.atomic_min(d_side, i0, side0)
        wp.atomic_min(d_ball, i0, ball0)
        wp.atomic_min(d_side, i1, side1)
        wp.atomic_min(d_ball, i1, ball1)


@wp.kernel
def edge_edge_pairs(
    edge_bvh: wp.uint64,
    edges: wp.array(dtype=wp.vec2i),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_self_contact: wp.array(dtype=wp.int32),
    world_offset: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    x_rest: wp.array(dtype=wp.vec3),
    reach: float,
    list_reach: float,
    thickness: float,
    normal: wp.array(dtype=wp.vec3),
    cone_cos: float,
    world_search: wp.array(dtype=wp.int32),
    # Out:
    pair_edge: wp.array2d(dtype=wp.int32),
    pair_dist: wp.array2d(dtype=float),
    pair_radius: wp.array2d(dtype=float),
    # In/out:
    d_min: wp.array(dtype=float),
    d_side: wp.array(dtype=float),
    d_ball: wp.array(dtype=float),
    horizon: wp.array(dtype=float),
):
    """Each edge's nearest edges within ``list_reach`` [m] that share no vertex with it (a BVH over
    the edges' boxes), and the bounds of its pairs within ``reach``: with ``cone_cos`` 0 the
    smallest distance at both its ends (``d_min``), else its pairs' certificates (``d_side`` /
    ``d_ball``, ``edge_edge_bound``). A pair within ``list_reach`` that the full list leaves out
    puts its distance into the edge's ends' ``horizon``. Worlds with ``world_search`` 0 keep their
    lists (``edge_edge_refresh``)."""
    e = wp.tid()
    i0 = edges[e][0]
    i1 = edges[e][1]
    w = particle_world[i0]
    if world_search[w] == 0:
        return
    for k in range(pair_edge.shape[1]):
        pair_edge[e, k] = -1
    if world_active[w] == 0 or world_self_contact[w] == 0:
        return
    p = x[i0]
    q = x[i1]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]) and wp.isfinite(q[0]) and wp.isfinite(q[1])
            and wp.isfinite(q[2])):
        return
    off = world_offset[w]
    r_box = list_reach + shift_tolerance(off)
    r = wp.vec3(r_box, r_box, r_box)
    query = wp.bvh_query_aabb(edge_bvh, wp.min(p, q) + off - r, wp.max(p, q) + off + r)
    f = int(0)
    best = reach
    hor = list_reach
    n0 = normal[i0]
    n1 = normal[i1]
    side0 = reach
    ball0 = reach
    side1 = reach
    ball1 = reach
    while wp.bvh_query_next(query, f):
        a = edges[f][0]
        b = edges[f][1]
        if a == i0 or a == i1 or b == i0 or b == i1 or particle_world[a] != w:
            continue
        xa = x[a]
        xb = x[b]
        cl = segment_closest(p, q, xa, xb)
        d = cl[2]
        if d < reach:
            best = wp.min(best, d)
            if cone_cos > 0.0:
                side0, ball0, side1, ball1 = edge_edge_bound(e, f, p, q, xa, xb, cl, n0, n1,
                                                             n0 + n1 - normal[a] - normal[b], cone_cos, side0, ball0,
                                                             side1, ball1)
        if d < list_reach:
            dropped, dropped_d = insert_nearest(pair_edge, pair_dist, e, f, d)
            if dropped >= 0:
                hor = wp.min(hor, dropped_d)
    edge_end_bounds(i0, i1, best, side0, ball0, side1, ball1, cone_cos, d_min, d_side, d_ball)
    wp.atomic_min(horizon, i0, hor)
    wp.atomic_min(horizon, i1, hor)
    rp = x_rest[i0]
    rq = x_rest[i1]
    for k in range(pair_edge.shape[1]):
        g = pair_edge[e, k]
        if g < 0:
            break
        pair_radius[e, k] = contact_radius(segment_distance(rp, rq, x_rest[edges[g][0]], x_rest[edges[g][1]]), thickness)


@wp.kernel
def edge_edge_refresh(
    edges: wp.array(dtype=wp.vec2i),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_self_contact: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    reach: float,
    normal: wp.array(dtype=wp.vec3),
    cone_cos: float,
    pair_edge: wp.array2d(dtype=wp.int32),
    world_search: wp.array(dtype=wp.int32),
    # In/out:
    d_min: wp.array(dtype=float),
    d_side: wp.array(dtype=float),
    d_ball: wp.array(dtype=float),
):
    """The bounds of each edge's listed edge-edge pairs at positions ``x``, as the search finds
    them (``edge_edge_pairs``); the pairs the lists left out are in the particles' horizon
    (``vertex_triangle_refresh``). Only in worlds with ``world_search`` 0."""
    e = wp.tid()
    i0 = edges[e][0]
    i1 = edges[e][1]
    w = particle_world[i0]
    if world_search[w] != 0 or world_active[w] == 0 or world_self_contact[w] == 0:
        return
    p = x[i0]
    q = x[i1]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]) and wp.isfinite(q[0]) and wp.isfinite(q[1])
            and wp.isfinite(q[2])):
        return
    best = reach
    n0 = normal[i0]
    n1 = normal[i1]
    side0 = reach
    ball0 = reach
    side1 = reach
    ball1 = reach
    for k in range(pair_edge.shape[1]):
        f = pair_edge[e, k]
        if f < 0:
            break
        a = edges[f][0]
        b = edges[f][1]
        xa = x[a]
        xb = x[b]
        cl = segment_closest(p, q, xa, xb)
        d = cl[2]
        if d < reach:
            best = wp.min(best, d)
            if cone_cos > 0.0:
                side0, ball0, side1, ball1 = edge_edge_bound(e, f, p, q, xa, xb, cl, n0, n1,
                                                             n0 + n1 - normal[a] - normal[b], cone_cos, side0, ball0,
                                                             side1, ball1)
    edge_end_bounds(i0, i1, best, side0, ball0, side1, ball1, cone_cos, d_min, d_side, d_ball)


class SelfContact:
    """Buffers and launches of vertex-triangle self-contact for one ClothModel."""

    def __init__(self, model: ClothModel, *, thickness: float | None = None, margin: float = 5.0e-3,
                 rest_exclusion: float | None = None, relaxation: float = 0.3, detect_every: int = 1,
                 bounds: bool = True, bound_fraction: float = BOUND_FRACTION,
                 min_separation: float = MIN_SEPARATION_M, pairs: bool = False,
                 pairs_per_primitive: int = PAIRS_PER_PRIMITIVE, directional_bounds: bool = False,
                 search_every: int = 1, skin: float = 0.0) -> None:
        """
        Args:
            model: cloth model.
            thickness: distance kept between a particle and other triangles [m]; default the
                largest fabric thickness of the model, at least 2 mm.
            margin: extra search distance when candidates are found once per substep [m].
            rest_exclusion: particle-triangle pairs closer than this in the rest geometry are never
                pushed [m]; default twice the contact reach (thickness + margin). The pair lists
                keep such pairs at their rest distance instead (``contact_radius``).
            relaxation: fraction of the push applied per solver iteration, in (0, 1]. The full
                push (1) separates layers but keeps them moving: on a CPU dataset slice (1.8k
                t-shirt, 42 targets) 34 holds of 42 never converged; 0.3: 12 (7 without
                self-contact), and 22 frames kept instead of 6 (16 without).
            detect_every: candidates are found on every ``detect_every``-th substep of a frame
                (the solver's ``step(substep=)``) and reused in between. The search then reaches
                further by the particle's own travel until the next search (speed x the substeps
                in between, at most ``MAX_SWEEP_M``); a layer moving toward a slow particle must
                stay within ``margin``. Detection is the costly part (a BVH query per particle).
            bounds: also find each particle's displacement bound at every search (module
                docstring; ``d_min``, ``x_searched``), for solvers that keep to it (``SolverVBD``).
            bound_fraction: share of its smallest pair distance a particle may move between
                searches, in (0, 0.5).
            min_separation: distance the bounds keep pairs apart [m] (``MIN_SEPARATION_M``).
            pairs: list every particle's nearest triangles (also per triangle) and every edge's
                nearest edges within the reach at each search (``vt_*``, ``tv_*``, ``ee_*``), for a contact energy acting on all particles of a pair
                (``SolverVBD``), instead of one candidate triangle per particle; the bounds'
                distances come from the same queries.
            pairs_per_primitive: the most pairs listed per particle, triangle or edge (the
                nearest ones).
            directional_bounds: with ``pairs``, each particle's bound is a half-space along its
                bound normal and a ball (module docstring: ``bound_normal``, ``d_side``,
                ``d_ball``) instead of the ball of ``d_min``: pressed layers may part and slide.
            search_every: with ``pairs``, every world searches (BVH queries) on every this-many-th
                ``detect`` of a solver; in between (``detect(refresh=True)``) only worlds that moved
                farther than half the ``skin`` since their last search do, and the others refresh
                their lists (the listed pairs' distances and bounds at the new positions, no query).
            skin: with ``pairs``, the search lists pairs up to ``thickness + margin + skin`` [m]
                apart, so pairs that close before the next search are already listed. A pair the
                lists leave out (farther, or past ``pairs_per_primitive``) still bounds its
                particles at a refresh: by its distance at the search less twice the largest
                displacement in its world since (``horizon``, ``world_moved``).
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
        if not (np.isfinite(bound_fraction) and 0.0 < bound_fraction < 0.5):
            raise ValueError(f"self-contact bound_fraction must be in (0, 0.5) (got {bound_fraction!r})")
        if not (np.isfinite(min_separation) and 0.0 <= min_separation < self.thickness):
            raise ValueError(f"self-contact min_separation must be in [0, thickness) [m] (got {min_separation!r})")
        self.bounds = bool(bounds)
        self.pairs = bool(pairs)
        if int(pairs_per_primitive) != pairs_per_primitive or pairs_per_primitive < 1:
            raise ValueError(f"self-contact pairs_per_primitive must be an integer >= 1 (got {pairs_per_primitive!r})")
        self.bound_fraction = float(bound_fraction)
        self.min_separation = float(min_separation)
        if int(search_every) != search_every or search_every < 1:
            raise ValueError(f"self-contact search_every must be an integer >= 1 (got {search_every!r})")
        if not (np.isfinite(skin) and skin >= 0.0):
            raise ValueError(f"self-contact skin must be >= 0 [m] (got {skin!r})")
        self.search_every = int(search_every)
        self.skin = float(skin)
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
        self.d_min = wp.full(count, 1.0e30, dtype=float, device=dev)
        """Smallest pair distance of each particle at the last search [m] (module docstring); 1e30
        (no bound) without ``bounds``; the reach with ``directional_bounds`` (their bounds are
        ``d_side`` and ``d_ball``)."""
        self.x_searched = wp.zeros(count, dtype=wp.vec3, device=dev)
        """Positions at the last search [m]: the centres of the displacement bounds."""
        self.directional_bounds = bool(directional_bounds) and self.pairs
        self.bound_normal = wp.zeros(count, dtype=wp.vec3, device=dev)
        """Directional bounds: each particle's unit direction away from its nearest pair (zero: none)."""
        self.d_side = wp.full(count, 1.0e30, dtype=float, device=dev)
        """Directional bounds: smallest certificate distance [m] of the pairs within each particle's cone."""
        self.d_ball = wp.full(count, 1.0e30, dtype=float, device=dev)
        """Directional bounds: smallest certificate distance [m] of the particle's other pairs (the reach where none)."""
        self.cone_cos = float(np.cos(np.arctan(BOUND_CONE_SLOPE))) if self.directional_bounds else 0.0
        """Cosine of the bound cone's half-angle (0: directional bounds off)."""
        if self.bounds or self.pairs:
            tris = np.asarray(model.tri_indices_np, np.int64).reshape(-1, 3)
            keys = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
            edges = np.unique(keys, axis=0) if len(keys) else np.zeros((1, 2), np.int64)
            self.edges = wp.array(edges.astype(np.int32), dtype=wp.vec2i, device=dev)
            """Cloth edges (E, 2), each once, lower index first."""
            # the pair lists: the pair energy's and the bounds' queries fill them
            k = int(pairs_per_primitive)
            n_tri = max(model.tri_count, 1)
            n_edge = len(edges)
            self.vt_tri = wp.full((count, k), -1, dtype=wp.int32, device=dev)
            """Each particle's nearest triangles within the reach, nearest first, -1 after the last."""
            self.vt_radius = wp.zeros((count, k), dtype=float, device=dev)
            """Contact radius of each listed pair [m] (``contact_radius``)."""
            self.tv_count = wp.zeros(n_tri, dtype=wp.int32, device=dev)
            """Particles listing each triangle (the same pairs seen from the triangle)."""
            self.tv_start = wp.zeros(n_tri, dtype=wp.int32, device=dev)
            """Start of each triangle's row in ``tv_vertex`` / ``tv_radius`` (CSR, rows sorted by particle)."""
            self.tv_vertex = wp.zeros(count * k, dtype=wp.int32, device=dev)
            self.tv_radius = wp.zeros(count * k, dtype=float, device=dev)
            self._tv_cursor = wp.zeros(n_tri, dtype=wp.int32, device=dev)
            self.ee_edge = wp.full((n_edge, k), -1, dtype=wp.int32, device=dev)
            """Each edge's nearest edges within the reach (sharing no vertex with it)."""
            self.ee_radius = wp.zeros((n_edge, k), dtype=float, device=dev)
            self._dist = [wp.zeros((count, k), dtype=float, device=dev), wp.zeros((n_edge, k), dtype=float, device=dev)]
            self.horizon = wp.zeros(count, dtype=float, device=dev)
            """Smallest distance [m] at the last search of a pair within the list reach that the lists
            left out, per particle (the list reach where none)."""
            self.x_listed = wp.zeros(count, dtype=wp.vec3, device=dev)
            """Positions at the last search [m] (the lists' and ``horizon``'s)."""
            self.world_moved = wp.zeros(model.world_count, dtype=float, device=dev)
            """Largest particle displacement [m] per world from ``x_listed`` at the last refresh."""
            self.world_search = wp.ones(model.world_count, dtype=wp.int32, device=dev)
            """1 where the last ``detect`` searched the world, 0 where it refreshed its lists."""
            self._world_listed = wp.zeros(model.world_count, dtype=wp.int32, device=dev)
            self.search_counts = wp.zeros((model.world_count, 2), dtype=wp.int32, device=dev)
            """Per world, cumulative (self-contact substeps, BVH searches among them) while active with
            self-contact on: the share ``detect(refresh=True)`` still searches."""
            lowers = wp.zeros(n_edge, dtype=wp.vec3, device=dev)
            uppers = wp.zeros(n_edge, dtype=wp.vec3, device=dev)
            wp.launch(place_edge_boxes, dim=n_edge if model.particle_count else 0,
                      inputs=[self.edges, model.particle_world, self.world_offset, self.rest],
                      outputs=[lowers, uppers], device=dev)
            # SAH with one edge per leaf, as the triangle BVHs (``BVH_OPTIONS``): CUDA's default LBVH
            # sorts the leaves by Morton codes over the whole grid of world cells, coarser there than
            # an edge, so its nodes overlap and each query walks many of them (one H100, 256
            # t-shirts of 7.7k: 125 ms per search with LBVH, 53 ms with SAH; ``docs/benchmarks.md``,
            # "Where VBD's time goes")
            self.edge_bvh = wp.Bvh(lowers, uppers, constructor=BVH_OPTIONS["bvh_constructor"],
                                   leaf_size=BVH_OPTIONS["bvh_leaf_size"])
            """BVH over the edges' boxes at their world cells, built here at rest and refit at each search."""
            ends = np.concatenate([edges[:, 0], edges[:, 1]])
            code = np.concatenate([2 * np.arange(n_edge), 2 * np.arange(n_edge) + 1])
            order = np.lexsort((code, ends))
            start = np.searchsorted(ends[order], np.arange(count + 1)).astype(np.int32)
            self.edge_adj_start = wp.array(start, dtype=wp.int32, device=dev)
            """CSR start of each particle's edges in ``edge_adj`` (particle_count + 1,)."""
            self.edge_adj = wp.array(code[order].astype(np.int32), dtype=wp.int32, device=dev)
            """2 e + end for each edge e a particle ends (end 0: ``edges[e][0]``)."""

    def detect(self, x: wp.array, world_active: wp.array, v: wp.array | None = None, dt: float = 0.0, *,
               world_self_contact: wp.array | None = None, refresh: bool = False) -> None:
        """Refit the cloth BVH at positions ``x`` and find one candidate triangle per particle (the
        pushes), or with ``pairs`` or ``bounds`` the pair lists and the displacement bounds.

        With velocities ``v`` [m/s] and the substep ``dt`` [s], the search of each particle also
        covers its travel over the ``detect_every - 1`` substeps until the next search.
        ``world_self_contact`` (int32, (world_count,), optional): worlds with 0 get no candidates,
        so no self-contact push until their next search (``ClothControl.world_self_contact``).

        ``refresh`` (with ``pairs``): only worlds in which a particle moved farther than half the
        ``skin`` since their last search (or whose last search listed nothing: self-contact off,
        inactive) search; the others refresh their lists (module docstring): the listed pairs'
        distances and certificates as a search computes them, and every pair the lists left out
        at its ``horizon`` less twice the world's largest displacement since the search, never
        wider than a search at ``x`` (``tests/test_contact_bounds.py``). ``world_search`` says
        which worlds searched."""
        m = self.model
        if refresh and not self.pairs:
            raise ValueError("SelfContact.detect(refresh=True) needs pairs=True (the pair lists it refreshes)")
        wp.launch(place_cloth_points, dim=m.particle_count, inputs=[x, m.particle_world, self.world_offset],
                  outputs=[self.mesh.points], device=m.device)
        self.mesh.refit()
        if not self.pairs:
            self._detect_candidates(x, world_active, v, dt, world_self_contact)
        if not (self.bounds or self.pairs):
            return
        reach = self.thickness + self.margin
        list_reach = reach + self.skin
        active_sc = world_active if world_self_contact is None else world_self_contact
        self.world_moved.zero_()
        if refresh:
            wp.launch(world_displacement, dim=m.particle_count, inputs=[x, self.x_listed, m.particle_world],
                      outputs=[self.world_moved], device=m.device)
        wp.launch(choose_search_worlds, dim=m.world_count,
                  inputs=[self.world_moved, world_active, active_sc, 0.5 * self.skin if refresh else -1.0],
                  outputs=[self.world_search, self._world_listed, self.search_counts], device=m.device)
        if self.directional_bounds:
            # bound normals from the current lists' pairs at the new positions (empty lists at the
            # first search: zero normals, every pair in the ball)
            wp.launch(bound_normals, dim=m.particle_count,
                      inputs=[x, int(m.tri_count), m.tri_indices, m.particle_adj_start, m.particle_adj_slot,
                              self.vt_tri, self.tv_start, self.tv_count, self.tv_vertex, self.ee_edge, self.edges,
                              self.edge_adj_start, self.edge_adj],
                      outputs=[self.bound_normal], device=m.device)
            self.d_side.fill_(reach)
            self.d_ball.fill_(reach)
        self.d_min.fill_(reach)
        wp.copy(self.x_searched, x)
        wp.launch(restart_lists, dim=m.particle_count, inputs=[x, m.particle_world, self.world_search, list_reach],
                  outputs=[self.x_listed, self.horizon], device=m.device)
        wp.launch(vertex_triangle_pairs, dim=m.particle_count,
                  inputs=[self.mesh.id, m.tri_indices, m.tri_world, m.particle_world, world_active, active_sc,
                          self.world_offset, x, self.rest, reach, list_reach, self.thickness, self.bound_normal,
                          self.cone_cos, self.world_search],
                  outputs=[self.vt_tri, self._dist[0], self.vt_radius, self.d_min, self.d_side, self.d_ball,
                           self.horizon],
                  device=m.device)
        if refresh:
            wp.launch(vertex_triangle_refresh, dim=m.particle_count,
                      inputs=[m.tri_indices, m.particle_world, world_active, active_sc, x, reach, self.bound_normal,
                              self.cone_cos, self.vt_tri, self.horizon, self.world_moved, self.world_search],
                      outputs=[self.d_min, self.d_side, self.d_ball], device=m.device)
        self.tv_count.zero_()
        self._tv_cursor.zero_()
        wp.launch(count_triangle_pairs, dim=m.particle_count, inputs=[self.vt_tri], outputs=[self.tv_count],
                  device=m.device)
        wp.utils.array_scan(self.tv_count, self.tv_start, inclusive=False)
        wp.launch(scatter_triangle_pairs, dim=m.particle_count,
                  inputs=[self.vt_tri, self.vt_radius, self.tv_start, self._tv_cursor],
                  outputs=[self.tv_vertex, self.tv_radius], device=m.device)
        wp.launch(sort_triangle_pairs, dim=m.tri_count, inputs=[self.tv_start, self.tv_count],
                  outputs=[self.tv_vertex, self.tv_radius], device=m.device)
        wp.launch(place_edge_boxes, dim=self.edges.shape[0],
                  inputs=[self.edges, m.particle_world, self.world_offset, x],
                  outputs=[self.edge_bvh.lowers, self.edge_bvh.uppers], device=m.device)
        self.edge_bvh.refit()
        wp.launch(edge_edge_pairs, dim=self.edges.shape[0],
                  inputs=[self.edge_bvh.id, self.edges, m.particle_world, world_active, active_sc,
                          self.world_offset, x, self.rest, reach, list_reach, self.thickness, self.bound_normal,
                          self.cone_cos, self.world_search],
                  outputs=[self.ee_edge, self._dist[1], self.ee_radius, self.d_min, self.d_side, self.d_ball,
                           self.horizon],
                  device=m.device)
        if refresh:
            wp.launch(edge_edge_refresh, dim=self.edges.shape[0],
                      inputs=[self.edges, m.particle_world, world_active, active_sc, x, reach, self.bound_normal,
                              self.cone_cos, self.ee_edge, self.world_search],
                      outputs=[self.d_min, self.d_side, self.d_ball], device=m.device)

    def _detect_candidates(self, x, world_active, v, dt, world_self_contact) -> None:
        """One candidate triangle and side per particle (the pushes' search)."""
        m = self.model
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
