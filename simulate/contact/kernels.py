"""Warp kernels for body contact: body interpolation, contact-plane detection, SDF queries.

The contact planes (``detect_body_contacts``) and the collider's signed distance
(``query_signed_distance``) share :func:`query_body`: the nearest face measured in the world's own
coordinates and the side from the closest feature's pseudo-normal, a point past an open cut
counting as outside (``simulate.contact.closest`` says why, and which query the quality metrics
use instead).
"""

from __future__ import annotations

import warp as wp

from simulate.contact.closest import face_points, nearest_face, point_side

wp.set_module_options({"enable_backward": False})


@wp.kernel
def interpolate_body_points(
    # Body key poses:
    pose_start: wp.array(dtype=wp.vec3),
    pose_end: wp.array(dtype=wp.vec3),
    vertex_world: wp.array(dtype=wp.int32),
    world_offset: wp.array(dtype=wp.vec3),
    alpha: float,
    # Out:
    points_out: wp.array(dtype=wp.vec3),
):
    """Body mesh points at fraction ``alpha`` of the frame, shifted to each world's cell."""
    i = wp.tid()
    a = pose_start[i]
    b = pose_end[i]
    points_out[i] = a + (b - a) * alpha + world_offset[vertex_world[i]]


@wp.func
def query_body(
    mesh: wp.uint64,
    offset: wp.vec3,
    point: wp.vec3,
    max_dist: float,
):
    """Closest point of the body in the world cell at ``offset`` to the local ``point`` [m], within
    ``max_dist`` [m].

    Returns (found, signed distance [m] (negative inside), outward unit normal (from the closest
    point towards ``point`` outside, away from it inside; the face normal on the surface),
    closest point [m] in local coordinates, face, barycentric weights (3,) of its corners).
    The nearest face and every distance are measured in local coordinates, so a body gives the
    same answer bit for bit in every world cell (``BodyCollider``).
    """
    found, face, bary, closest = nearest_face(mesh, offset, point, max_dist)
    normal = wp.vec3(0.0, 1.0, 0.0)
    dist = float(0.0)
    if found:
        side = point_side(mesh, offset, face, bary, point, closest)
        delta = point - closest
        length = wp.length(delta)
        dist = length * side
        if length > 1.0e-7:
            normal = delta / length * side
        else:
            a, b, c = face_points(mesh, face, offset)
            normal = wp.normalize(wp.cross(b - a, c - a))
    return found, dist, normal, closest, face, bary


@wp.kernel
def detect_body_contacts(
    # Body:
    meshes: wp.array(dtype=wp.uint64),
    pose_start: wp.array(dtype=wp.vec3),
    pose_end: wp.array(dtype=wp.vec3),
    world_offset: wp.array(dtype=wp.vec3),
    motion_scale: float,
    thickness: float,
    margin: float,
    # Model:
    particle_world: wp.array(dtype=wp.int32),
    particle_part: wp.array(dtype=wp.int32),
    particle_radius: wp.array(dtype=float),
    world_active: wp.array(dtype=wp.int32),
    # State in (predicted positions):
    x: wp.array(dtype=wp.vec3),
    # Out:
    contact_active_out: wp.array(dtype=wp.int32),
    contact_normal_out: wp.array(dtype=wp.vec3),
    contact_offset_out: wp.array(dtype=float),
    contact_motion_out: wp.array(dtype=wp.vec3),
    contact_depth_out: wp.array(dtype=float),
):
    """Contact plane per particle, found once per substep and reused by every iteration.

    The plane is ``dot(n, x) >= offset``: the closest body point lifted by the contact distance
    (collider thickness + half fabric thickness) along the outward normal (``query_body``; a
    particle outside the body is never taken for inside, which would flip its plane and push it
    through).  Particles farther than contact distance + ``margin`` get no plane.
    ``contact_motion`` is the body's displacement during this substep at the contact point [m]
    (for friction).  Planes, offsets and motions are in world-local coordinates.

    ``meshes`` holds one mesh per collision part over the same points (``BodyCollider``); a
    particle meets the part ``particle_part`` names (the first where that is out of range).
    """
    i = wp.tid()
    contact_depth_out[i] = 0.0
    contact_active_out[i] = 0
    w = particle_world[i]
    if world_active[w] == 0:
        return
    reach = thickness + particle_radius[i]
    p = x[i]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])):
        return
    g = particle_part[i]
    if g < 0 or g >= meshes.shape[0]:
        g = 0
    mesh = meshes[g]
    found, dist, normal, closest, face, bary = query_body(mesh, world_offset[w], p, reach + margin)
    if not found:
        return
    indices = wp.mesh_get(mesh).indices
    i0 = indices[face * 3 + 0]
    i1 = indices[face * 3 + 1]
    i2 = indices[face * 3 + 2]
    motion = ((pose_end[i0] - pose_start[i0]) * bary[0] + (pose_end[i1] - pose_start[i1]) * bary[1]
              + (pose_end[i2] - pose_start[i2]) * bary[2]) * motion_scale
    contact_active_out[i] = 1
    contact_normal_out[i] = normal
    contact_offset_out[i] = wp.dot(normal, closest) + reach
    contact_motion_out[i] = motion


@wp.kernel
def advance_body_contacts(
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    contact_active: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_motion: wp.array(dtype=wp.vec3),
    # In/out:
    contact_offset: wp.array(dtype=float),
    contact_depth: wp.array(dtype=float),
):
    """Carry the planes found on an earlier substep of this frame to the next substep.

    Within a frame the body moves linearly, so each contact point moves by the same
    ``contact_motion`` every substep: the plane shifts by its normal component, and the friction
    budget restarts from zero.  Used between the substeps that query the body
    (``SolverBase.contact_detect_every``)."""
    i = wp.tid()
    if world_active[particle_world[i]] == 0:
        return
    contact_depth[i] = 0.0
    if contact_active[i] != 0:
        contact_offset[i] = contact_offset[i] + wp.dot(contact_normal[i], contact_motion[i])


@wp.kernel
def query_signed_distance(
    meshes: wp.array(dtype=wp.uint64),
    world_offset: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    point_world: wp.array(dtype=wp.int32),
    point_part: wp.array(dtype=wp.int32),
    max_dist: float,
    # Out:
    dist_out: wp.array(dtype=float),
    normal_out: wp.array(dtype=wp.vec3),
):
    """Signed distance [m] (negative inside) and outward normal at points to the collision part
    ``point_part`` names (``meshes``, as ``detect_body_contacts``); +max_dist if none found."""
    i = wp.tid()
    g = point_part[i]
    if g < 0 or g >= meshes.shape[0]:
        g = 0
    found, dist, normal, closest, face, bary = query_body(meshes[g], world_offset[point_world[i]], points[i], max_dist)
    if found:
        dist_out[i] = dist
        normal_out[i] = normal
    else:
        dist_out[i] = max_dist
        normal_out[i] = wp.vec3(0.0, 0.0, 0.0)
