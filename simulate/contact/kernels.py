"""Warp kernels for body contact: body interpolation, contact-plane detection, SDF queries."""

from __future__ import annotations

import warp as wp

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
    point: wp.vec3,
    max_dist: float,
):
    """Closest body point: returns (found, signed distance [m], outward normal, face, u, v)."""
    res = wp.mesh_query_point_sign_normal(mesh, point, max_dist)
    normal = wp.vec3(0.0, 1.0, 0.0)
    dist = float(0.0)
    if res.result:
        closest = wp.mesh_eval_position(mesh, res.face, res.u, res.v)
        delta = point - closest
        length = wp.length(delta)
        dist = length * res.sign
        if length > 1.0e-7:
            normal = delta / length * res.sign
        else:
            normal = wp.mesh_eval_face_normal(mesh, res.face)
    return res.result, dist, normal, res.face, res.u, res.v


@wp.kernel
def detect_body_contacts(
    # Body:
    mesh: wp.uint64,
    mesh_indices: wp.array(dtype=wp.int32),
    pose_start: wp.array(dtype=wp.vec3),
    pose_end: wp.array(dtype=wp.vec3),
    world_offset: wp.array(dtype=wp.vec3),
    motion_scale: float,
    thickness: float,
    margin: float,
    # Model:
    particle_world: wp.array(dtype=wp.int32),
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
    (collider thickness + half fabric thickness) along the outward normal.  Particles farther
    than contact distance + ``margin`` get no plane.  ``contact_motion`` is the body's
    displacement during this substep at the contact point [m] (for friction).
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
    found, dist, normal, face, u, v = query_body(mesh, p + world_offset[w], reach + margin)
    if not found:
        return
    i0 = mesh_indices[face * 3 + 0]
    i1 = mesh_indices[face * 3 + 1]
    i2 = mesh_indices[face * 3 + 2]
    bw = 1.0 - u - v
    motion = ((pose_end[i0] - pose_start[i0]) * u + (pose_end[i1] - pose_start[i1]) * v
              + (pose_end[i2] - pose_start[i2]) * bw) * motion_scale
    closest = p - normal * dist
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
    mesh: wp.uint64,
    world_offset: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    point_world: wp.array(dtype=wp.int32),
    max_dist: float,
    # Out:
    dist_out: wp.array(dtype=float),
    normal_out: wp.array(dtype=wp.vec3),
):
    """Signed distance [m] (negative inside) and outward normal at points; +max_dist if none found."""
    i = wp.tid()
    found, dist, normal, face, u, v = query_body(mesh, points[i] + world_offset[point_world[i]], max_dist)
    if found:
        dist_out[i] = dist
        normal_out[i] = normal
    else:
        dist_out[i] = max_dist
        normal_out[i] = wp.vec3(0.0, 0.0, 0.0)
