"""Rotations, FK and LBS against direct computations (no body model needed)."""
from __future__ import annotations

import numpy as np
import torch

from simulate.body import inverse_lbs, lbs
from simulate.body import kinematics as kin

ATOL_POSITION_M = 1e-5


def _random_chain(rng, joint_count=6):
    parents = np.array([-1] + [int(rng.integers(0, k)) for k in range(1, joint_count)])
    rest_joints = torch.as_tensor(rng.normal(0, 0.3, (1, joint_count, 3)), dtype=torch.float64)
    return parents, rest_joints


def test_axis_angle_matches_rodrigues_and_round_trips():
    rng = np.random.default_rng(0)
    aa = rng.normal(0, 1.0, (50, 3))
    rot = kin.axis_angle_to_matrix(torch.as_tensor(aa)).numpy()
    for a, r in zip(aa, rot):
        angle = np.linalg.norm(a)
        k = a / angle
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        expected = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
        np.testing.assert_allclose(r, expected, atol=1e-12)
    back = kin.matrix_to_axis_angle(torch.as_tensor(rot)).numpy()
    np.testing.assert_allclose(back, aa * np.where(np.linalg.norm(aa, axis=1, keepdims=True) < np.pi, 1, np.nan), atol=1e-6)
    assert np.allclose(kin.axis_angle_to_matrix(torch.zeros(3, dtype=torch.float64)).numpy(), np.eye(3))


def test_apply_linear_matches_per_point_matrix_products():
    rng = np.random.default_rng(3)
    m = rng.normal(size=(4, 50, 3, 3))
    v = rng.normal(size=(4, 50, 3))
    expected = np.einsum("bnij,bnj->bni", m, v)
    np.testing.assert_allclose(kin.apply_linear(torch.as_tensor(m), torch.as_tensor(v)).numpy(), expected, atol=1e-12)
    # a vector broadcast over the batch (a shared rest shape) and a transposed (non-contiguous) matrix
    mt = torch.as_tensor(m).transpose(-1, -2)
    np.testing.assert_allclose(kin.apply_linear(mt, torch.as_tensor(v[:1])).numpy(),
                               np.einsum("bnji,nj->bni", m, v[0]), atol=1e-12)


def test_inverse_lbs_undoes_lbs_for_random_points_and_poses():
    rng = np.random.default_rng(1)
    parents, rest_joints = _random_chain(rng)
    rot = kin.axis_angle_to_matrix(torch.as_tensor(rng.normal(0, 0.6, (3, 6, 3))))
    _, skin = kin.forward_kinematics(rot, rest_joints.expand(3, -1, -1), parents)
    points = rng.normal(0, 0.5, (3, 200, 3))
    weights = rng.dirichlet(np.ones(6) * 0.5, size=200)
    posed = lbs(points, weights, skin.numpy())
    assert np.abs(posed - points).max() > 0.05, "the random pose should move the points"
    np.testing.assert_allclose(inverse_lbs(posed, weights, skin.numpy()), points, atol=ATOL_POSITION_M)


def test_rest_pose_is_identity():
    rng = np.random.default_rng(2)
    parents, rest_joints = _random_chain(rng)
    rot = torch.eye(3, dtype=torch.float64).repeat(2, 6, 1, 1)
    world, skin = kin.forward_kinematics(rot, rest_joints.expand(2, -1, -1), parents)
    np.testing.assert_allclose(skin.numpy(), np.broadcast_to(np.eye(4), (2, 6, 4, 4)), atol=1e-12)
    np.testing.assert_allclose(world[..., :3, 3].numpy(), rest_joints.expand(2, -1, -1).numpy(), atol=1e-12)


def test_vertex_weighted_to_one_bone_moves_rigidly_with_it():
    rng = np.random.default_rng(3)
    parents, rest_joints = _random_chain(rng)
    rot = kin.axis_angle_to_matrix(torch.as_tensor(rng.normal(0, 0.7, (1, 6, 3))))
    world, skin = kin.forward_kinematics(rot, rest_joints, parents)
    bone = 4
    offset = rng.normal(0, 0.1, 3)
    point = rest_joints[0, bone].numpy() + offset
    weights = np.zeros((1, 6))
    weights[0, bone] = 1.0
    posed = lbs(point[None, None], weights, skin.numpy())[0, 0]
    expected = world[0, bone, :3, :3].numpy() @ offset + world[0, bone, :3, 3].numpy()
    np.testing.assert_allclose(posed, expected, atol=1e-10)


def test_lbs_is_differentiable_in_torch():
    rng = np.random.default_rng(4)
    parents, rest_joints = _random_chain(rng)
    aa = torch.tensor(rng.normal(0, 0.3, (1, 6, 3)), requires_grad=True)
    _, skin = kin.forward_kinematics(kin.axis_angle_to_matrix(aa), rest_joints, parents)
    out = kin.lbs(torch.ones(1, 5, 3, dtype=torch.float64), torch.full((5, 6), 1 / 6, dtype=torch.float64), skin)
    out.sum().backward()
    assert aa.grad is not None and torch.isfinite(aa.grad).all() and aa.grad.abs().sum() > 0


def test_forward_kinematics_takes_device_index_tensors():
    """Parents and levels given as tensors (what body models cache per device) give the same
    transforms as numpy indices, and a wrong level order changes them (the levels are used)."""
    rng = np.random.default_rng(5)
    parents, rest_joints = _random_chain(rng, joint_count=8)
    rot = kin.axis_angle_to_matrix(torch.as_tensor(rng.normal(0, 0.7, (2, 8, 3))))
    world, skin = kin.forward_kinematics(rot, rest_joints, parents)
    levels = kin.kinematic_levels(parents)
    assert len(levels) >= 2, "the random chain should have several levels"
    as_t = [torch.as_tensor(i) for i in levels]
    world_t, skin_t = kin.forward_kinematics(rot, rest_joints, torch.as_tensor(parents), levels=as_t)
    np.testing.assert_array_equal(world_t.numpy(), world.numpy())
    np.testing.assert_array_equal(skin_t.numpy(), skin.numpy())
    world_r, _ = kin.forward_kinematics(rot, rest_joints, torch.as_tensor(parents), levels=as_t[::-1])
    assert not torch.allclose(world_r, world), "children composed before their parents must differ"


def _devices():
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def test_to_device_async_copies_values_that_later_host_writes_do_not_reach():
    for device in _devices():
        host = np.arange(12, dtype=np.int64).reshape(3, 4)
        moved = kin.to_device_async(host, device)
        assert moved.device.type == device and moved.dtype == torch.int64
        if device == "cuda":  # the copy is queued, not done: it must have taken the values already
            host[:] = -1
        assert moved.cpu().tolist() == np.arange(12).reshape(3, 4).tolist()
        as_float = kin.to_device_async(torch.arange(3), device, dtype=torch.float32)
        assert as_float.dtype == torch.float32 and as_float.cpu().tolist() == [0.0, 1.0, 2.0]
        grad = torch.ones(2, requires_grad=True)
        kin.to_device_async(grad, device).sum().backward()  # stays on the autograd graph
        assert grad.grad.tolist() == [1.0, 1.0]
