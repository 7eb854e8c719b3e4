"""Closest point on a body mesh and the side of the body a point lies on (Warp functions).

Which query answers "how far from the body, and on which side?":

* **Body contact** (``kernels.detect_body_contacts``: the contact plane of every particle, all
  solvers) and **the collider's signed distance** (``BodyCollider.signed_distance``: what the
  canonical drape reports as penetration) use :func:`nearest_face` + :func:`point_side`: the
  nearest face measured in the world's own (unshifted) coordinates, the Euclidean distance to it,
  and the side from the angle-weighted pseudo-normal of the closest *feature* (face, edge or
  vertex), every point whose closest feature lies on an open boundary of the mesh (the cut where
  a body part was culled away) counting as outside.  Contact needs all of it: a point called
  inside gets its plane flipped and is pushed through the body; the contact meshes are culled
  (open) and their skins interpenetrate (an arm against the torso); and the answer must not
  depend on the world cell (``BodyCollider``).  Warp's ``mesh_query_point_sign_normal`` calls
  points up to 20 cm outside inside: past an open cut the closest point is on the
  rim, whose normals face sideways (hundreds of 5,000 points sampled around a posed anny culled
  to torso, arms and legs), and in a thin gap between two facing skins its tie tolerance (1e-3 x
  the mean edge, ~10 um) sums the normals of both sides, so that the sign there flips with the
  world's float32 shift.  A winding number would give the side too, but needs the mesh's
  solid-angle data refit with the BVH on every substep (8x the refit time for the anny body on
  the CPU) and a winding query costs 6x a closest-point query.
* **Quality metrics** (``simulate.quality.query_body_signed_distance``: the penetration filter
  of the dataset, the reports' penetration) and **``learn.common.collision``** (the learners'
  collision rate; the same kernel, so both count alike): the HOOD-style distance along the normal
  of the nearest face, which published collision rates use; one mesh per frame and no world shift,
  so the nearest face comes straight from Warp's query.  Its side is checked with
  :func:`point_side`: the nearest face's normal alone calls 2 of 4,285 points outside the closed
  anny body (bench pose) inside, one 38 mm outside read as 8 mm deep beside the head, where the
  nearest face of a point off a sharp edge or corner need not face it; past an open cut, hundreds.

The side rule cannot call a point outside the body inside: for a closed, non-self-intersecting
surface the pseudo-normal of the closest feature gives the exact side (Baerentzen and Aanaes
2005); where skins interpenetrate, a point outside the union of the parts has its closest point
on the outer skin, whose side is again right; past an open cut the point counts as outside. The
converse does not hold: a point inside one part but nearest to the embedded skin of another (an
arm sunk into the torso) is called outside, as by Warp's queries, and so is a point inside a part
that is nearer the rim of an open cut than any skin (inside a sphere whose cap was cut off, on its
axis just below the cut).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = [
    "closest_point_barycentric", "face_points", "nearest_face", "nearest_in_box", "point_side",
    "point_triangle_offset", "shift_tolerance",
]


@wp.func
def closest_point_barycentric(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Barycentric coordinates of the point of triangle abc closest to p (Ericson 2004); exact
    zeros where the closest point is an edge or a vertex."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.func
def point_triangle_offset(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """``p`` less the point of triangle abc closest to it [m] (its length is their distance)."""
    bary = closest_point_barycentric(p, a, b, c)
    return p - (a * bary[0] + b * bary[1] + c * bary[2])


@wp.func
def face_points(mesh: wp.uint64, face: int, offset: wp.vec3):
    """Corners [m] of ``face`` in local coordinates: the mesh points minus ``offset`` (exact for
    the collider's world cells, see ``body_collider.world_cell_offsets``)."""
    m = wp.mesh_get(mesh)
    a = m.points[m.indices[face * 3 + 0]] - offset
    b = m.points[m.indices[face * 3 + 1]] - offset
    c = m.points[m.indices[face * 3 + 2]] - offset
    return a, b, c


@wp.func
def is_sliver(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> bool:
    """Degenerate triangle: twice its area at most 1e-6 x the sum of its squared edges (the test
    Warp's closest-point queries skip faces by)."""
    s = wp.length_sq(b - a) + wp.length_sq(c - a) + wp.length_sq(c - b)
    return wp.length_sq(wp.cross(b - a, c - a)) <= 1.0e-12 * s * s


@wp.func
def shift_tolerance(offset: wp.vec3) -> float:
    """Bound [m] on the float32 rounding of coordinates shifted by ``offset``: 4 ulps of their
    magnitude (< 2 |offset| in a world cell, an ulp of x being at most 1.2e-7 |x|), plus 1 um.
    A distance Warp computes in shifted coordinates is within 4 of these of the local one."""
    s = wp.max(wp.max(wp.abs(offset[0]), wp.abs(offset[1])), wp.abs(offset[2]))
    return 1.0e-6 + 1.0e-6 * s


@wp.func
def nearest_in_box(mesh: wp.uint64, offset: wp.vec3, p: wp.vec3, radius: float):
    """Nearest face to the local point ``p`` [m] among the faces whose bounding box overlaps the
    cube of half-side ``radius`` [m] around it, measured in local coordinates, equal distances
    going to the lower face index.

    Returns:
        (face (-1 if none), squared distance [m^2], barycentric weights (3,), closest point [m]).
    """
    face = int(-1)
    best = float(3.0e38)
    bary = wp.vec3(0.0)
    closest = p
    q = p + offset
    box = wp.vec3(radius, radius, radius)
    m = wp.mesh_get(mesh)
    query = wp.mesh_query_aabb(mesh, q - box, q + box)
    f = int(0)
    while wp.mesh_query_aabb_next(query, f):
        a = m.points[m.indices[f * 3 + 0]] - offset
        b = m.points[m.indices[f * 3 + 1]] - offset
        c = m.points[m.indices[f * 3 + 2]] - offset
        if is_sliver(a, b, c):
            continue
        # a face whose plane is farther than the nearest so far (by more than rounding, so that
        # ties are measured whatever the visit order) is not measured
        n = wp.cross(b - a, c - a)
        h = wp.dot(p - a, n)
        if h * h > 1.0001 * best * wp.length_sq(n):
            continue
        w = closest_point_barycentric(p, a, b, c)
        cl = a * w[0] + b * w[1] + c * w[2]
        d = wp.length_sq(p - cl)
        if d < best or (d == best and f < face):
            best = d
            face = f
            bary = w
            closest = cl
    return face, best, bary, closest


@wp.func
def nearest_face(mesh: wp.uint64, offset: wp.vec3, p: wp.vec3, max_dist: float):
    """Nearest face of the mesh shifted by ``offset`` to the local point ``p`` [m], within ``max_dist``.

    Warp's BVH query (in shifted coordinates) returns a face within the shift's float32 rounding
    of the nearest; every face within that face's local distance plus the rounding
    (:func:`shift_tolerance`) is then measured in local coordinates (:func:`nearest_in_box`),
    equal distances going to the lower face index. So the result depends only on ``p`` and the
    body's local geometry, not on the world cell the body sits in nor on the BVH.

    Returns:
        (found, face, barycentric weights (3,) of the face's corners, closest point [m] local).
    """
    tol = shift_tolerance(offset)
    res = wp.mesh_query_point_no_sign(mesh, p + offset, max_dist + 4.0 * tol)
    if not res.result:
        return False, int(-1), wp.vec3(0.0), p
    a0, b0, c0 = face_points(mesh, res.face, offset)
    w0 = closest_point_barycentric(p, a0, b0, c0)
    radius = wp.length(p - (a0 * w0[0] + b0 * w0[1] + c0 * w0[2])) + tol
    face, best, bary, closest = nearest_in_box(mesh, offset, p, radius)
    return face >= 0 and wp.sqrt(best) < max_dist, face, bary, closest


@wp.func
def corner_angle(p: wp.vec3, a: wp.vec3, b: wp.vec3) -> float:
    """Angle [rad] at corner ``p`` of a triangle with the other corners ``a``, ``b``."""
    return wp.acos(wp.clamp(wp.dot(wp.normalize(a - p), wp.normalize(b - p)), -1.0, 1.0))


@wp.func
def point_side(mesh: wp.uint64, offset: wp.vec3, face: int, bary: wp.vec3, p: wp.vec3, closest: wp.vec3) -> float:
    """Side of the surface the local point ``p`` lies on: +1 outside, -1 inside.

    ``closest`` is p's closest point on ``face`` with barycentric weights ``bary`` (from
    :func:`nearest_face`, or Warp's query evaluated with :func:`closest_point_barycentric`).
    The side is that of the angle-weighted pseudo-normal of the closest feature: the face's normal
    (no zero weight), the sum of the two face normals at an edge (one zero), the corner-angle
    weighted normals around a vertex (two zeros). An edge with one face, or a vertex whose ring
    of faces does not close, lies on an open boundary: the point is outside (faces are told apart
    by vertex index, so a seam of duplicated vertices is open too). A point on the surface is
    outside. The edge and vertex cases look up the faces around the feature with a BVH box query.
    """
    m = wp.mesh_get(mesh)
    i0 = m.indices[face * 3 + 0]
    i1 = m.indices[face * 3 + 1]
    i2 = m.indices[face * 3 + 2]
    a, b, c = face_points(mesh, face, offset)
    delta = p - closest
    zeros = int(0)
    for k in range(3):
        if bary[k] == 0.0:
            zeros += 1
    if zeros == 0:
        return wp.where(wp.dot(wp.cross(b - a, c - a), delta) >= 0.0, 1.0, -1.0)
    pad = shift_tolerance(offset)
    normal = wp.vec3(0.0)
    f = int(0)
    if zeros == 1:
        ea = i0
        eb = i1
        if bary[0] == 0.0:
            ea = i1
            eb = i2
        elif bary[1] == 0.0:
            eb = i2
        pa = m.points[ea]
        pb = m.points[eb]
        pad3 = wp.vec3(pad, pad, pad)
        query = wp.mesh_query_aabb(mesh, wp.min(pa, pb) - pad3, wp.max(pa, pb) + pad3)
        count = int(0)
        while wp.mesh_query_aabb_next(query, f):
            j0 = m.indices[f * 3 + 0]
            j1 = m.indices[f * 3 + 1]
            j2 = m.indices[f * 3 + 2]
            has_a = j0 == ea or j1 == ea or j2 == ea
            has_b = j0 == eb or j1 == eb or j2 == eb
            if has_a and has_b:
                count += 1
                fa, fb, fc = face_points(mesh, f, offset)
                if not is_sliver(fa, fb, fc):
                    normal += wp.normalize(wp.cross(fb - fa, fc - fa))
        if count < 2:
            return 1.0
        return wp.where(wp.dot(normal, delta) >= 0.0, 1.0, -1.0)
    # vertex: each neighbour of a closed ring of faces is shared by two of them, so the hashes of
    # the neighbours, XORed over the ring, cancel; an open ring leaves its two end neighbours
    vi = i0
    if bary[1] != 0.0:
        vi = i1
    elif bary[2] != 0.0:
        vi = i2
    pv = m.points[vi]
    pad3 = wp.vec3(pad, pad, pad)
    query = wp.mesh_query_aabb(mesh, pv - pad3, pv + pad3)
    ring = wp.uint32(0)
    while wp.mesh_query_aabb_next(query, f):
        j0 = m.indices[f * 3 + 0]
        j1 = m.indices[f * 3 + 1]
        j2 = m.indices[f * 3 + 2]
        if j0 != vi and j1 != vi and j2 != vi:
            continue
        fa, fb, fc = face_points(mesh, f, offset)
        angle = float(0.0)
        if j0 == vi:
            ring = ring ^ wp.rand_init(j1) ^ wp.rand_init(j2)
            angle = corner_angle(fa, fb, fc)
        elif j1 == vi:
            ring = ring ^ wp.rand_init(j2) ^ wp.rand_init(j0)
            angle = corner_angle(fb, fc, fa)
        else:
            ring = ring ^ wp.rand_init(j0) ^ wp.rand_init(j1)
            angle = corner_angle(fc, fa, fb)
        if not is_sliver(fa, fb, fc):
            normal += angle * wp.normalize(wp.cross(fb - fa, fc - fa))
    if ring != wp.uint32(0):
        return 1.0
    return wp.where(wp.dot(normal, delta) >= 0.0, 1.0, -1.0)
