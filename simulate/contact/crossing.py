"""Exact test of an edge crossing a triangle (Warp functions): the quality metric's
self-intersection count (``simulate.quality``) and the untangling (``simulate.contact.untangle``)
use the same one, so what the untangling clears is what the dataset filter counts."""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["as_vec3d", "orient3d", "segment_hits_triangle"]


@wp.func
def as_vec3d(p: wp.vec3) -> wp.vec3d:
    return wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))


@wp.func
def orient3d(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, d: wp.vec3d) -> wp.float64:
    """Six times the signed volume of the tetrahedron abcd: > 0 where d lies on the side of the
    plane abc that the counter-clockwise normal points to."""
    return wp.dot(wp.cross(b - a, c - a), d - a)


@wp.func
def segment_hits_triangle(p: wp.vec3, q: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> bool:
    """Whether the segment pq crosses the triangle abc: p and q strictly on opposite sides of its
    plane, and the line pq through the closed triangle (the three orientations of pq against the
    triangle's edges agree in sign). Orientation predicates in float64 on the float32 points:
    no tolerance to tune, and a crossing is a crossing however thin the triangle."""
    p64 = as_vec3d(p)
    q64 = as_vec3d(q)
    a64 = as_vec3d(a)
    b64 = as_vec3d(b)
    c64 = as_vec3d(c)
    sp = orient3d(a64, b64, c64, p64)
    sq = orient3d(a64, b64, c64, q64)
    if sp == wp.float64(0.0) or sq == wp.float64(0.0) or (sp > wp.float64(0.0)) == (sq > wp.float64(0.0)):
        return False
    u = orient3d(p64, q64, a64, b64)
    v = orient3d(p64, q64, b64, c64)
    w = orient3d(p64, q64, c64, a64)
    zero = wp.float64(0.0)
    if u >= zero and v >= zero and w >= zero:
        return True
    return u <= zero and v <= zero and w <= zero
