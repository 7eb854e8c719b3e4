"""SMPL-format backend on a synthetic model file against a naive per-vertex numpy SMPL."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from simulate.body import POSE_JOINTS, load_body_model
from simulate.body.smpl_backend import read_smpl_file

ATOL_POSITION_M = 1e-5
N_JOINTS, N_VERTS, N_BETAS = 24, 60, 4
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]


def synthetic_smpl(rng) -> dict[str, np.ndarray]:
    """A small random model with SMPL's keys, shapes and kinematic tree."""
    verts = rng.normal(0, 0.3, (N_VERTS, 3))
    regressor = rng.dirichlet(np.ones(N_VERTS) * 0.3, size=N_JOINTS)
    weights = rng.dirichlet(np.ones(N_JOINTS) * 0.2, size=N_VERTS)
    kintree = np.array([[2**32 - 1] + SMPL_PARENTS[1:], list(range(N_JOINTS))], dtype=np.int64)
    faces = np.array([[i, i + 1, i + 2] for i in range(N_VERTS - 2)])
    return {
        "v_template": verts, "f": faces, "J_regressor": regressor, "weights": weights, "kintree_table": kintree,
        "shapedirs": rng.normal(0, 0.01, (N_VERTS, 3, N_BETAS)), "posedirs": rng.normal(0, 0.01, (N_VERTS, 3, 9 * (N_JOINTS - 1))),
    }


def rodrigues(a):
    angle = np.linalg.norm(a)
    if angle < 1e-12:
        return np.eye(3)
    k = a / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def naive_smpl(m, betas, full_pose):
    """Textbook SMPL, one vertex and one joint at a time."""
    v_shaped = m["v_template"] + m["shapedirs"] @ betas
    joints = m["J_regressor"] @ v_shaped
    rots = [rodrigues(full_pose[j]) for j in range(N_JOINTS)]
    feature = np.concatenate([(rots[j] - np.eye(3)).ravel() for j in range(1, N_JOINTS)])
    v_posed = v_shaped + m["posedirs"] @ feature
    world = []
    for j in range(N_JOINTS):
        local = np.eye(4)
        local[:3, :3] = rots[j]
        local[:3, 3] = joints[j] - (joints[SMPL_PARENTS[j]] if j else 0)
        world.append(local if j == 0 else world[SMPL_PARENTS[j]] @ local)
    out = np.zeros_like(v_posed)
    for i in range(N_VERTS):
        blended = np.zeros((4, 4))
        for j in range(N_JOINTS):
            a = world[j].copy()
            a[:3, 3] -= world[j][:3, :3] @ joints[j]
            blended += m["weights"][i, j] * a
        out[i] = blended[:3, :3] @ v_posed[i] + blended[:3, 3]
    return out


@pytest.fixture
def smpl_file(tmp_path):
    m = synthetic_smpl(np.random.default_rng(0))
    path = tmp_path / "SMPL_SYNTH.npz"
    np.savez(path, **m)
    return path, m


def test_smpl_backend_matches_naive_reference(smpl_file):
    path, m = smpl_file
    body = load_body_model("smpl", path=str(path), num_betas=N_BETAS)
    rng = np.random.default_rng(1)
    betas = rng.normal(0, 1, (3, N_BETAS)).astype(np.float32)
    pose = rng.normal(0, 0.4, (3, len(POSE_JOINTS) * 3)).astype(np.float32)
    posed = body.pose(betas, pose)
    m_norm = dict(m, weights=m["weights"] / m["weights"].sum(1, keepdims=True))
    for b in range(3):
        full = np.zeros((N_JOINTS, 3))
        full[body.pose_joint_indices] = pose[b].reshape(-1, 3)
        expected = naive_smpl(m_norm, betas[b].astype(np.float64), full)
        np.testing.assert_allclose(posed.vertices[b], expected, atol=ATOL_POSITION_M,
                                   err_msg=f"SMPL backend differs from the naive reference for batch item {b}")
    # the copy ``on_device`` makes for another device (here forced on the CPU) is the same model
    import torch

    assert body.on_device("cpu") is body
    copy = body._copy_on(torch.device("cpu"))
    assert copy is not body and copy.shape_size == N_BETAS
    np.testing.assert_array_equal(copy.pose(betas, pose).vertices, posed.vertices)


def test_smpl_pkl_with_chumpy_objects_reads(tmp_path):
    m = synthetic_smpl(np.random.default_rng(2))

    class Ch:  # pickled under a chumpy module name, as original SMPL files are
        def __init__(self, x):
            self.x = x

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = "Ch"
    import sys
    import types

    fake = types.ModuleType("chumpy.ch")
    fake.Ch = Ch
    sys.modules["chumpy"] = types.ModuleType("chumpy")
    sys.modules["chumpy.ch"] = fake
    try:
        payload = dict(m, shapedirs=Ch(m["shapedirs"]), v_template=Ch(m["v_template"]))
        path = tmp_path / "model.pkl"
        with open(path, "wb") as fh:
            pickle.dump(payload, fh, protocol=2)
    finally:
        del sys.modules["chumpy.ch"], sys.modules["chumpy"]
    data = read_smpl_file(path)
    np.testing.assert_allclose(data["shapedirs"], m["shapedirs"])
    np.testing.assert_allclose(data["v_template"], m["v_template"])


def test_missing_and_malformed_files_name_what_was_expected(tmp_path, smpl_file):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_body_model("smpl", path=str(tmp_path / "nope.npz"))
    with pytest.raises(ValueError, match="needs body.path"):
        load_body_model("smpl")
    _, m = smpl_file
    bad = dict(m)
    del bad["J_regressor"]
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(ValueError, match="missing keys \\['J_regressor'\\]"):
        load_body_model("smpl", path=str(tmp_path / "bad.npz"))
    np.savez(tmp_path / "bad2.npz", **dict(m, weights=m["weights"][:, :5]))
    with pytest.raises(ValueError, match="weights must have shape"):
        load_body_model("smpl", path=str(tmp_path / "bad2.npz"))
    (tmp_path / "garbage.pkl").write_bytes(b"not a pickle")
    with pytest.raises(ValueError, match="not a readable SMPL"):
        load_body_model("smpl", path=str(tmp_path / "garbage.pkl"))
    with pytest.raises(ValueError, match="unknown body backend"):
        load_body_model("smplx2000")


def test_smpl_wrong_pose_and_shape_length(smpl_file):
    path, _ = smpl_file
    body = load_body_model("smpl", path=str(path), num_betas=N_BETAS)
    with pytest.raises(ValueError, match="shape must have 4 values"):
        body.pose(np.zeros(7), np.zeros(60))
    with pytest.raises(ValueError, match="pose must be axis-angle rotations"):
        body.pose(np.zeros(4), np.zeros(59))
