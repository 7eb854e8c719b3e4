"""The default anny backend: geometry, posing, shape response, parts, self-intersection."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.body import PARTS, POSE_JOINTS, inverse_lbs
from simulate.body.mesh_utils import SelfIntersectionChecker, vertex_normals

ATOL_POSITION_M = 1e-4


def test_counts_and_frame(anny_body):
    assert anny_body.vertex_count == 13718 and len(anny_body.faces) == 27420
    v, _ = anny_body.rest(anny_body.shape_default)
    extent = np.ptp(v[0], axis=0)
    assert extent[1] > 1.4 and extent[1] > extent[0] and extent[1] > extent[2], f"y must be up, extent {extent}"
    nose_z = v[0][v[0][:, 1] > v[0][:, 1].max() - 0.15, 2].max()
    back_z = v[0][v[0][:, 1] > v[0][:, 1].max() - 0.15, 2].min()
    assert nose_z > -back_z - 0.05, "the body must face +z"


def test_height_phenotype_increases_height_monotonically(anny_body):
    shapes = np.tile(anny_body.shape_default, (5, 1))
    shapes[:, anny_body.shape_names.index("height")] = np.linspace(0, 1, 5)
    v, _ = anny_body.rest(shapes)
    heights = np.ptp(v[:, :, 1], axis=1)
    assert np.all(np.diff(heights) > 0.01), f"heights not increasing: {heights}"


def test_inverse_lbs_of_posed_body_returns_rest(anny_body):
    rng = np.random.default_rng(0)
    pose = rng.normal(0, 0.3, (2, 60)).astype(np.float32)
    posed = anny_body.pose(anny_body.shape_default, pose)
    unposed = inverse_lbs(posed.vertices, anny_body.skinning_weights, posed.skinning_transforms)
    np.testing.assert_allclose(unposed, posed.rest_vertices, atol=ATOL_POSITION_M)
    zero = anny_body.pose(anny_body.shape_default, np.zeros(60))
    np.testing.assert_allclose(zero.vertices, zero.rest_vertices, atol=1e-6)


def test_rigid_vertex_follows_its_joint(anny_body):
    weights = anny_body.skinning_weights
    k = POSE_JOINTS.index("left_elbow")
    bone = anny_body.pose_joint_indices[k]
    rigid = np.nonzero(weights[:, bone] > 0.999)[0]
    assert len(rigid) > 0
    pose = anny_body.pose_from_dict({"left_elbow": [0, -1.2, 0], "left_shoulder": [0, 0, 0.8]})
    posed = anny_body.pose(anny_body.shape_default, pose)
    g = posed.joint_transforms[0, bone]
    local = posed.rest_vertices[0, rigid] - posed.rest_joints[0, bone]
    np.testing.assert_allclose(posed.vertices[0, rigid], local @ g[:3, :3].T + g[:3, 3], atol=ATOL_POSITION_M)


def test_bad_input_names_what_was_expected(anny_body):
    with pytest.raises(ValueError, match="shape must have 6 values \\(gender, age"):
        anny_body.pose(np.zeros(5), np.zeros(60))
    with pytest.raises(ValueError, match="pose must be axis-angle.*got shape \\(61,\\)"):
        anny_body.pose(anny_body.shape_default, np.zeros(61))
    with pytest.raises(ValueError, match="unknown joint name 'left_tentacle'"):
        anny_body.pose_from_dict({"left_tentacle": [0, 0, 0]})
    with pytest.raises(ValueError, match="unknown body part"):
        anny_body.part_faces(["wings"])


def test_parts_normals_and_culling(anny_body):
    counts = np.bincount(anny_body.vertex_parts, minlength=len(PARTS))
    assert (counts > 300).all(), f"every part should have vertices: {dict(zip(PARTS, counts))}"
    v, _ = anny_body.rest(anny_body.shape_default)
    hands = anny_body.part_vertex_mask(["hands"])
    assert np.abs(v[0][hands, 0]).min() > 0.3, "hand vertices must lie at the ends of the arms"
    torso_faces = anny_body.part_faces(["torso", "legs"])
    assert 0 < len(torso_faces) < len(anny_body.faces)
    n = vertex_normals(v[0], anny_body.faces)
    chest = np.argmax(v[0][:, 2] * (np.abs(v[0][:, 0]) < 0.05) * (np.abs(v[0][:, 1] - 0.3) < 0.05))
    assert n[chest, 2] > 0.7, "the front-most chest vertex's normal must point forward (+z)"


def test_self_intersection_flags_arm_in_torso_and_crossed_legs(anny_body):
    checker = SelfIntersectionChecker(anny_body, anny_body.shape_default)
    poses = np.stack([
        np.zeros(60, np.float32),
        anny_body.pose_from_dict({"left_shoulder": [0, 0, -1.2], "left_elbow": [0, -2.0, 0]}),  # forearm through chest
        anny_body.pose_from_dict({"left_hip": [0, 0, -0.6], "right_hip": [0, 0, 0.6]}),  # legs crossing
        anny_body.pose_from_dict({"left_shoulder": [0, 0, 1.5]}),  # arm raised: fine
        anny_body.pose_from_dict({"left_hip": [-1.2, 0, 0], "left_knee": [1.8, 0, 0]}),  # knee up: fine
    ])
    flags, depth = checker.check(poses)
    assert flags.tolist() == [False, True, True, False, False], f"depths {depth}"


def test_on_device_is_the_same_model_here_and_poses_where_it_lives(anny_body):
    """``on_device`` returns the model itself on its own device; on a GPU the copy poses on the GPU
    (posing runs where the model's tensors are, not where the inputs are) and agrees with the CPU."""
    import torch

    assert anny_body.on_device("cpu") is anny_body
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    gpu = anny_body.on_device("cuda")
    shapes = np.tile(anny_body.shape_default, (3, 1))
    poses = np.tile(anny_body.canonical_pose, (3, 1))
    poses[1] += anny_body.pose_from_dict({"left_shoulder": [0.0, 0.0, 0.6]})
    with torch.no_grad():
        on_gpu = gpu.pose_torch(torch.as_tensor(shapes, device="cuda"), torch.as_tensor(poses, device="cuda")).vertices
        on_cpu = anny_body.pose_torch(torch.as_tensor(shapes), torch.as_tensor(poses)).vertices
    assert on_gpu.is_cuda
    np.testing.assert_allclose(on_gpu.cpu().numpy(), on_cpu.numpy(), rtol=0, atol=ATOL_POSITION_M)


def test_a_batch_that_repeats_shapes_poses_each_body_as_if_alone(anny_body, monkeypatch):
    """pose_torch blends each distinct shape once, alone, and keeps it: every body must still get its
    own shape (wrong inverse indices would hand one body another's), bit for bit the shape's own
    blend, and a shape seen before is not blended again."""
    import torch

    rng = np.random.default_rng(2)
    distinct = rng.uniform(0.2, 0.8, (3, anny_body.shape_size)).astype(np.float32)
    which = np.array([2, 0, 0, 1, 2, 2, 1])
    poses = (rng.normal(0.0, 0.2, (len(which), 60))).astype(np.float32)
    blends = []
    blend = anny_body._rest_torch

    def counting(shape):
        blends.append(shape.shape[0])
        return blend(shape)

    monkeypatch.setattr(anny_body, "_rest_torch", counting)
    with torch.no_grad():
        batch = anny_body.pose_torch(torch.as_tensor(distinct[which]), torch.as_tensor(poses))
        assert blends == [1, 1, 1], f"one blend per distinct shape, each alone: {blends}"
        for i, k in enumerate(which):
            own, _ = blend(torch.as_tensor(distinct[k][None]))
            assert torch.equal(batch.rest_vertices[i], own[0]), f"body {i} did not get shape {k}"
            alone = anny_body.pose_torch(torch.as_tensor(distinct[k][None]), torch.as_tensor(poses[i][None]))
            np.testing.assert_allclose(batch.vertices[i].numpy(), alone.vertices[0].numpy(), rtol=0, atol=1e-5)
        assert blends == [1, 1, 1], "kept shapes are not blended again"
    # the shapes differ by centimetres somewhere, so a mix-up could not pass the checks above
    assert np.abs(batch.rest_vertices[0].numpy() - batch.rest_vertices[1].numpy()).max() > 5e-3


def test_shaped_bodies_do_not_depend_on_torch_threads(anny_body):
    """A body is the same whatever torch's intra-op thread count (Ray workers run with 1, a default
    process with one per core): unpinned, anny's shape blend rounded differently with 1 and 2
    threads, and a Ray-made dataset differed from a local one."""
    import torch

    shapes = np.tile(anny_body.shape_default, (3, 1))
    shapes[:, anny_body.shape_names.index("weight")] = [0.2, 0.6, 0.9]
    pose = np.random.default_rng(1).normal(0, 0.2, (3, 60)).astype(np.float32)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            anny_body.__dict__.pop("_rest_cache", None)  # blend afresh, not from the kept bodies
            out.append((anny_body.rest(shapes)[0], anny_body.pose(shapes, pose).vertices))
            assert torch.get_num_threads() == threads, "posing must give the caller's thread count back"
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(out[0][0], out[1][0]), "rest bodies differ between 1 and 2 torch threads"
    assert np.array_equal(out[0][1], out[1][1]), "posed bodies differ between 1 and 2 torch threads"


def test_posed_vertices_of_a_subset_equal_those_of_the_full_pose(anny_body):
    """``posed_vertices`` skins only the vertices asked for, with pose()'s numbers."""
    from simulate.poses import PoseSampler

    poses = PoseSampler().sample(6, np.random.default_rng(2))
    idx = np.array([0, 17, 4000, anny_body.vertex_count - 1])
    full = anny_body.pose(np.repeat(anny_body.shape_default[None], 6, 0), poses).vertices
    np.testing.assert_array_equal(anny_body.posed_vertices(anny_body.shape_default, poses, idx), full[:, idx])
    with pytest.raises(ValueError, match="one shape"):
        anny_body.posed_vertices(np.repeat(anny_body.shape_default[None], 2, 0), poses[:2], idx)
