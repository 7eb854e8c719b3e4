"""XPBD element kernels: triangle stretch/shear and dihedral bending, Gauss-Seidel and Jacobi.

Gauss-Seidel kernels run over one graph colour at a time (``offset`` + thread id) and write
positions in place: elements of one colour share no particle, so there is no race.  Jacobi
kernels read positions and write one correction per (element, corner) slot; the particle
pass sums them.  Each Jacobi element takes the share ``relaxation / max_k n_k`` of its
multiplier step (n_k = elements of its kind, triangle or bending, touching corner k), so a
particle's summed correction is an average-like step while multiplier and positions stay
consistent."""

from __future__ import annotations

import warp as wp

from simulate.solvers.common_kernels import bending_angle_grad, triangle_constraint_deltas

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
    i0 = tri_indices[t, 0]
    i1 = tri_indices[t, 1]
    i2 = tri_indices[t, 2]
    d0, d1, d2, lam = triangle_constraint_deltas(x[i0], x[i1], x[i2], inv_mass[i0], inv_mass[i1], inv_mass[i2],
                                                 tri_dm_inv[t], tri_compliance[t], tri_lambda[t], inv_dt2, relaxation)
    x[i0] = x[i0] + d0
    x[i1] = x[i1] + d1
    x[i2] = x[i2] + d2
    tri_lambda[t] = lam


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
