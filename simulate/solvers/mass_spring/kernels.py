"""Mass-spring (semi-implicit Euler) kernels: element forces per slot, gather + integrate, contact."""

from __future__ import annotations

import warp as wp

from simulate.solvers.common_kernels import bending_angle_grad, triangle_forces

wp.set_module_options({"enable_backward": False})


@wp.kernel
def eval_triangle_forces(
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_dm_inv: wp.array(dtype=wp.mat22),
    tri_compliance: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    # Out:
    slot_force_out: wp.array(dtype=wp.vec3),
):
    """Stretch/shear forces [N] of each triangle into its three slots."""
    t = wp.tid()
    f0, f1, f2 = triangle_forces(x[tri_indices[t, 0]], x[tri_indices[t, 1]], x[tri_indices[t, 2]],
                                 tri_dm_inv[t], tri_compliance[t])
    slot_force_out[3 * t + 0] = f0
    slot_force_out[3 * t + 1] = f1
    slot_force_out[3 * t + 2] = f2


@wp.kernel
def eval_bending_forces(
    slot_base: int,
    bend_indices: wp.array2d(dtype=wp.int32),
    bend_rest_angle: wp.array(dtype=float),
    bend_compliance: wp.array(dtype=float),
    x: wp.array(dtype=wp.vec3),
    # Out:
    slot_force_out: wp.array(dtype=wp.vec3),
):
    """Bending forces [N] -k (theta - theta_rest) grad(theta) into four slots."""
    b = wp.tid()
    s = slot_base + 4 * b
    ok, theta, d1, d2, d3, d4 = bending_angle_grad(x[bend_indices[b, 0]], x[bend_indices[b, 1]],
                                                   x[bend_indices[b, 2]], x[bend_indices[b, 3]])
    c = -(theta - bend_rest_angle[b]) / bend_compliance[b]
    if ok == 0:
        c = 0.0
    slot_force_out[s + 0] = d1 * c
    slot_force_out[s + 1] = d2 * c
    slot_force_out[s + 2] = d3 * c
    slot_force_out[s + 3] = d4 * c


def make_integrate_kernel(attachments: bool):
    """Gather slot forces, add gravity and attachment springs, semi-implicit Euler step."""
    key = (attachments,)
    if key in _INTEGRATE:
        return _INTEGRATE[key]

    @wp.kernel(module="unique", enable_backward=False)
    def integrate_mass_spring(
        # Model:
        mass: wp.array(dtype=float),
        inv_mass: wp.array(dtype=float),
        particle_world: wp.array(dtype=wp.int32),
        world_active: wp.array(dtype=wp.int32),
        world_damping: wp.array(dtype=float),
        extra_damping: float,
        gravity: wp.vec3,
        dt: float,
        adj_start: wp.array(dtype=wp.int32),
        adj_slot: wp.array(dtype=wp.int32),
        slot_force: wp.array(dtype=wp.vec3),
        # Attachments:
        particle_attachment: wp.array(dtype=wp.int32),
        attachment_target: wp.array(dtype=wp.vec3),
        world_attachment_stiffness: wp.array(dtype=float),
        world_attachment_enabled: wp.array(dtype=wp.int32),
        # State in:
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        # Out:
        x_out: wp.array(dtype=wp.vec3),
        v_out: wp.array(dtype=wp.vec3),
    ):
        i = wp.tid()
        w = particle_world[i]
        p = x[i]
        if world_active[w] == 0:
            x_out[i] = p
            v_out[i] = v[i]
            return
        im = inv_mass[i]
        if im == 0.0:
            x_out[i] = p
            v_out[i] = wp.vec3(0.0)
            return
        f = gravity * mass[i]
        for k in range(adj_start[i], adj_start[i + 1]):
            f = f + slot_force[adj_slot[k]]
        if wp.static(attachments):
            a = particle_attachment[i]
            if a >= 0:
                if world_attachment_enabled[w] != 0:
                    f = f + (attachment_target[a] - p) * world_attachment_stiffness[w]
        decay = wp.max(1.0 - (world_damping[w] + extra_damping) * dt, 0.0)
        vel = (v[i] + f * (im * dt)) * decay
        x_out[i] = p + vel * dt
        v_out[i] = vel

    _INTEGRATE[key] = integrate_mass_spring
    return integrate_mass_spring


_INTEGRATE: dict[tuple, wp.Kernel] = {}


@wp.kernel
def resolve_body_contacts(
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=wp.int32),
    world_active: wp.array(dtype=wp.int32),
    world_friction: wp.array(dtype=float),
    dt: float,
    contact_active: wp.array(dtype=wp.int32),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_offset: wp.array(dtype=float),
    contact_motion: wp.array(dtype=wp.vec3),
    # In/out:
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
):
    """Project onto the contact plane, cancel approaching normal velocity, Coulomb friction on velocity."""
    i = wp.tid()
    if world_active[particle_world[i]] == 0 or inv_mass[i] == 0.0 or contact_active[i] == 0:
        return
    n = contact_normal[i]
    p = x[i]
    gap = wp.dot(n, p) - contact_offset[i]
    if gap >= 0.0:
        return
    x[i] = p - n * gap
    body_v = contact_motion[i] / dt
    rel = v[i] - body_v
    vn = wp.dot(n, rel)
    dvn = wp.max(-vn, 0.0)
    rel_t = rel - n * vn
    slip = wp.length(rel_t)
    limit = world_friction[particle_world[i]] * dvn
    if slip <= limit:
        rel_t = wp.vec3(0.0)
    else:
        rel_t = rel_t * (1.0 - limit / slip)
    v[i] = body_v + rel_t + n * wp.max(vn, 0.0)
