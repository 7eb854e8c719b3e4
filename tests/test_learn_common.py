"""Tests of learn.common: mesh topology, smoothing, losses, MLP, collisions, post-process."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
import warp as wp

from learn.common.collision import body_signed_distance, collision_rate
from learn.common.losses import l1_displacement_loss, per_vertex_error_mm
from learn.common.mesh import boundary_vertices, grid_mesh, mesh_edges, uniform_laplacian
from learn.common.mlp import MLP
from learn.common.postprocess import mesh_signed_distance_fn, remove_body_penetration
from learn.common.smoothing import LaplacianSmoother, laplacian_smooth, laplacian_smooth_naive, split_frequencies

torch.set_num_threads(1)  # the test machine is shared; intra-op threads only contend

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
ATOL_SMOOTH_M = 1e-9
ATOL_SMOOTH_FLOAT32_M = 2e-6
SPHERE_RADIUS_M = 0.3


def test_grid_topology() -> None:
    vertices, faces = grid_mesh(4, 5)
    assert vertices.shape == (20, 3) and faces.shape == (24, 3)
    edges = mesh_edges(faces)
    # grid edges: horizontal 4*4 + vertical 3*5 + diagonals 3*4
    assert edges.shape[0] == 16 + 15 + 12, f"edge count {edges.shape[0]}"
    boundary = boundary_vertices(faces, 20)
    assert boundary.sum() == 14, f"a 4x5 grid has 14 boundary vertices, found {boundary.sum()}"
    lap = uniform_laplacian(faces, 20)
    np.testing.assert_allclose(np.asarray(lap.sum(axis=1)).reshape(-1), 0.0, atol=1e-12,
                               err_msg="Laplacian rows must sum to zero")


def test_bad_faces_raise() -> None:
    with pytest.raises(ValueError, match="faces"):
        uniform_laplacian(np.zeros((3, 4), dtype=np.int32), 5)
    with pytest.raises(ValueError, match="vertex_count"):
        uniform_laplacian(np.array([[0, 1, 9]]), 5)


def test_smoothing_matches_naive_loop() -> None:
    rng = np.random.default_rng(0)
    vertices, faces = grid_mesh(6, 7)
    field = vertices + rng.normal(scale=0.01, size=vertices.shape)
    naive = laplacian_smooth_naive(field, faces, iterations=12)
    fast = laplacian_smooth(field, faces, iterations=12)
    np.testing.assert_allclose(fast, naive, atol=ATOL_SMOOTH_M, err_msg="sparse smoothing differs from the loop")
    # batched torch path, float32 and float64
    batch = np.stack([field, field * 2.0 + 0.1])
    smoother = LaplacianSmoother(faces, field.shape[0], iterations=12)
    out64 = smoother(torch.from_numpy(batch))
    np.testing.assert_allclose(out64[1].numpy(), laplacian_smooth_naive(batch[1], faces, iterations=12),
                               atol=ATOL_SMOOTH_M, err_msg="torch batched frame 1 differs from the loop")
    out32 = smoother(torch.from_numpy(batch).float())
    assert out32.dtype == torch.float32
    np.testing.assert_allclose(out32[0].numpy(), naive, atol=ATOL_SMOOTH_FLOAT32_M,
                               err_msg="float32 torch smoothing differs from the loop")


def test_boundary_aware_smoothing_shrinks_less_and_removes_detail() -> None:
    vertices, faces = grid_mesh(10, 10, spacing=0.01)
    boundary = boundary_vertices(faces, 100)
    smooth = laplacian_smooth(vertices, faces)
    plain = vertices.copy()
    plain_step = uniform_laplacian(faces, 100, boundary_aware=False)
    for _ in range(80):
        plain = plain + 0.15 * (plain_step @ plain)
    centre = vertices.mean(axis=0)

    def radius(v: np.ndarray) -> float:
        return float(np.linalg.norm(v[boundary] - centre, axis=1).mean())

    shrink_aware = radius(vertices) - radius(smooth)
    shrink_plain = radius(vertices) - radius(plain)
    assert shrink_aware < 0.5 * shrink_plain, (
        f"boundary-aware smoothing shrank the boundary by {shrink_aware:.4f} m, plain by {shrink_plain:.4f} m"
    )
    bumps = np.zeros_like(vertices)
    bumps[:, 2] = 0.005 * np.sin(40.0 * vertices[:, 0]) * np.sin(40.0 * vertices[:, 1])
    low, high = split_frequencies(bumps, LaplacianSmoother(faces, 100))
    assert np.abs(low).max() < 0.5 * np.abs(bumps).max(), "smoothing kept the high-frequency bumps"
    np.testing.assert_allclose(low + high, bumps, atol=1e-15, err_msg="LF + HF must reconstruct D")


def test_losses_and_mlp() -> None:
    prediction = torch.zeros(2, 4, 3)
    target = torch.zeros(2, 4, 3)
    target[..., 0] = 0.003
    target[..., 1] = 0.004
    assert torch.allclose(per_vertex_error_mm(prediction, target), torch.tensor([5.0, 5.0]))
    assert torch.isclose(l1_displacement_loss(prediction, target), torch.tensor(0.007))
    with pytest.raises(ValueError, match="shape"):
        l1_displacement_loss(prediction, target[:, :3])
    mlp = MLP(5, 7, hidden_size=16)
    assert [type(m).__name__ for m in mlp.layers] == ["Linear", "ReLU", "Dropout", "Linear", "ReLU", "Linear"]
    assert mlp(torch.zeros(3, 5)).shape == (3, 7)
    with pytest.raises(ValueError, match="input"):
        mlp(torch.zeros(3, 4))


def _closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Ericson's closest point on triangle, broadcast over p (N,1,3) and triangles (1,F,3)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    v = vb / denom
    w = vc / denom
    result = a + ab * v[..., None] + ac * w[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        cases = [
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
             b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[..., None]),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / (d2 - d6))[..., None]),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / (d1 - d3))[..., None]),
            ((d6 >= 0) & (d5 <= d6), np.broadcast_to(c, result.shape)),
            ((d3 >= 0) & (d4 <= d3), np.broadcast_to(b, result.shape)),
            ((d1 <= 0) & (d2 <= 0), np.broadcast_to(a, result.shape)),
        ]
    for mask, value in cases:  # later cases (vertices) take priority, as in Ericson's order
        result = np.where(mask[..., None], value, result)
    return result


def _naive_signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (vertices[faces[:, i]][None] for i in range(3))
    closest = _closest_point_on_triangles(points[:, None, :], a, b, c)  # (N, F, 3)
    nearest = np.argmin(np.linalg.norm(points[:, None, :] - closest, axis=-1), axis=1)
    normals = np.cross(b[0] - a[0], c[0] - a[0])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    rows = np.arange(points.shape[0])
    return ((points - closest[rows, nearest]) * normals[nearest]).sum(-1)


def _sphere() -> tuple[np.ndarray, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=SPHERE_RADIUS_M)
    return np.asarray(sphere.vertices), np.asarray(sphere.faces)


@pytest.mark.parametrize("device", DEVICES)
def test_collision_rate_matches_naive_numpy_on_sphere(device: str) -> None:
    vertices, faces = _sphere()
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(2, 300, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    points = directions * rng.uniform(0.25, 0.33, size=(2, 300, 1))
    rate = collision_rate(points, vertices, faces, device=device)
    for frame in range(2):
        naive = _naive_signed_distance(points[frame], vertices, faces)
        expected = np.mean(naive < -1e-3)
        assert abs(rate[frame] - expected) <= 1.0 / 300 + 1e-12, (
            f"frame {frame}: warp collision rate {rate[frame]} vs naive {expected}"
        )
        sd = body_signed_distance(points[frame], vertices, faces, device=device)
        inside = naive < -2e-3  # away from edge ambiguity near the surface
        np.testing.assert_allclose(sd.distance[inside], naive[inside], atol=1e-5,
                                   err_msg="signed distance of interior points differs from the naive oracle")
    # Translating the body per frame: frame 1's body moved far away -> no collisions.
    bodies = np.stack([vertices, vertices + np.array([5.0, 0.0, 0.0])])
    rates = collision_rate(points, bodies, faces, device=device)
    assert rates[1] == 0.0 and rates[0] > 0.1, f"per-frame bodies ignored: {rates}"


@pytest.mark.parametrize("device", DEVICES)
def test_postprocess_removes_collisions_and_keeps_laplacian(device: str) -> None:
    body_vertices, body_faces = _sphere()
    grid, faces = grid_mesh(12, 12, spacing=0.01)
    grid = grid - grid.mean(axis=0)
    # A wrinkled cap over the sphere's top: 1 mm above the surface, wrinkles of 6 mm
    # amplitude, so the wrinkle troughs dip 5 mm into the body.
    directions = grid + np.array([0.0, 0.0, SPHERE_RADIUS_M])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    garment = directions * (SPHERE_RADIUS_M + 0.001 + 0.006 * np.sin(80.0 * grid[:, [0]]))
    query = mesh_signed_distance_fn(body_vertices, body_faces, device=device)
    result = remove_body_penetration(garment, faces, query)
    assert result.collisions_before > 10, f"test set-up: only {result.collisions_before} collisions"
    assert result.collisions_after == 0, f"{result.collisions_after} vertices still inside after post-process"
    lap = uniform_laplacian(faces, garment.shape[0], boundary_aware=False)
    # The naive fix projects each inside vertex independently: it flattens the wrinkles.
    distance, closest, normal = query(garment)
    naive = garment.copy()
    inside = distance < 0
    naive[inside] = closest[inside] + 1e-3 * normal[inside]
    change_ls = np.linalg.norm(lap @ result.vertices - lap @ garment, axis=1).mean()
    change_naive = np.linalg.norm(lap @ naive - lap @ garment, axis=1).mean()
    assert change_ls < 0.5 * change_naive, (
        f"least-squares Laplacian change {change_ls:.2e} m not well below naive projection's {change_naive:.2e} m"
    )


def test_postprocess_batch_in_worker_processes_equals_in_process() -> None:
    """Frames spread over worker processes come back in order with the in-process result."""
    from learn.common.postprocess import remove_body_penetration_batch, warm_pool

    warm_pool(2)  # started ahead, as drape evaluate does while its models predict
    body_vertices, body_faces = _sphere()
    grid, faces = grid_mesh(8, 8, spacing=0.01)
    grid = grid - grid.mean(axis=0)
    directions = grid + np.array([0.0, 0.0, SPHERE_RADIUS_M])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    garments = np.stack([directions * (SPHERE_RADIUS_M + 0.001 + a * np.sin(80.0 * grid[:, [0]]))
                         for a in (0.003, 0.006, 0.009)]).astype(np.float32)
    bodies = np.stack([body_vertices] * 3).astype(np.float32)
    serial = remove_body_penetration_batch(garments, faces, bodies, body_faces, device="cpu")
    spread = remove_body_penetration_batch(garments, faces, bodies, body_faces, device="cpu", workers=2)
    assert min(serial[1]) > 0 and not np.array_equal(serial[0][0], serial[0][1]), "frames must collide and differ"
    for a, b in zip(serial, spread):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="workers"):
        remove_body_penetration_batch(garments, faces, bodies, body_faces, workers=0)


def test_garment_posing_functions_with_fake_body_model() -> None:
    from types import SimpleNamespace

    from learn.common.skinning import garment_posing_functions

    class FakeBody:
        """Four body vertices shifted by shape[0]; posing translates every joint by pose[:3]."""

        def rest_torch(self, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            vertices = torch.arange(12, dtype=torch.float32).reshape(1, 4, 3) + shape[:, :1, None]
            return vertices, torch.zeros(shape.shape[0], 2, 3)

        def pose_torch(self, shape: torch.Tensor, pose: torch.Tensor) -> SimpleNamespace:
            transforms = torch.eye(4).repeat(pose.shape[0], 2, 1, 1)
            transforms[:, :, :3, 3] = pose[:, None, :3]
            vertices, _ = self.rest_torch(shape)
            return SimpleNamespace(skinning_transforms=transforms, vertices=vertices + pose[:, None, :3])

    rest = np.full((3, 3), 7.0, dtype=np.float32)
    weights = np.array([[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]], dtype=np.float32)
    with pytest.raises(ValueError, match="rest_vertices"):
        garment_posing_functions(FakeBody(), np.array([2, 0, -1]), weights)
    unposed_body, poser, posed_body = garment_posing_functions(
        FakeBody(), np.array([2, 0, -1]), weights, rest_vertices=rest
    )
    shape = torch.tensor([[1.0, 0.0]])
    under = unposed_body(shape)
    expected = torch.tensor([[[7.0, 8.0, 9.0], [1.0, 2.0, 3.0], [7.0, 7.0, 7.0]]])
    torch.testing.assert_close(under, expected, msg="body vertex under the garment / -1 fallback wrong")
    pose = torch.tensor([[0.1, 0.2, 0.3, 0.0, 0.0, 0.0]])
    torch.testing.assert_close(poser(under, pose, shape), under + pose[:, None, :3])
    assert posed_body(pose, shape).shape == (1, 4, 3)


@pytest.mark.parametrize("merge, overrides, message", [
    ("tailornet", {"hf": {"epochs": "ten"}}, "hf.epochs must be an integer (got 'ten')"),
    ("tailornet", {"lf": {"lr": 0.0}}, "lf.lr must be > 0 (got 0.0)"),
    ("tailornet", {"model": {"pose_mask": "yes"}}, "model.pose_mask must be true or false (got 'yes')"),
    ("collision_aware", {"vae": {"kl": -1.0e-5}}, "vae.kl must be >= 0 (got -1e-05)"),
    ("collision_aware", {"vae": {"batch_size": 0}}, "vae.batch_size must be >= 1 (got 0)"),
    ("collision_aware", {"regressor": {"dropout": 1.0}}, "regressor.dropout must be in [0, 1) (got 1.0)"),
    ("collision_aware", {"sdf": {"voxel_m": float("nan")}}, "sdf.voxel_m must be a finite number (got nan)"),
    ("uvimage", {"uvimage": {"norm": 1}}, "uvimage.norm must be text (got 1)"),
    ("gcvae", {"model": {"channels": 64}}, "model.channels must be a list (got 64)"),
    ("gcvae", {"train": {"epochs": 2.5}}, "train.epochs must be an integer (got 2.5)"),
])
def test_hyperparameter_overrides_of_the_wrong_type_or_range_are_refused_by_name(merge, overrides, message) -> None:
    """Every learner's merge checks an override against its default's type and range, so a typo
    fails before any stage instead of as an internal error or a silently odd training."""
    if merge == "tailornet":
        from learn.tailornet.train import merged_hyperparameters

        def call():
            return merged_hyperparameters(overrides)
    elif merge == "collision_aware":
        from learn.collision_aware.train import DEFAULT_HYPERPARAMETERS
        from learn.tailornet.train import merged_hyperparameters

        def call():
            return merged_hyperparameters(overrides, DEFAULT_HYPERPARAMETERS)
    elif merge == "uvimage":
        from learn.uvimage.train import merged_hyperparameters

        def call():
            return merged_hyperparameters("uvimage", overrides)
    else:
        from learn.gcvae.hyperparameters import merged

        def call():
            return merged(overrides)
    with pytest.raises(ValueError) as raised:
        call()
    assert str(raised.value) == message


def test_hyperparameter_overrides_of_the_default_type_pass_and_ints_stand_for_floats() -> None:
    from learn.collision_aware.train import DEFAULT_HYPERPARAMETERS
    from learn.gcvae.hyperparameters import merged
    from learn.tailornet.train import merged_hyperparameters

    hyper = merged_hyperparameters({"vae": {"kl": 0, "epochs": 2, "lr_schedule": "cosine", "lr": "1e-3"},
                                    "projection": {"lr": 1}}, DEFAULT_HYPERPARAMETERS)
    assert hyper["vae"]["kl"] == 0 and hyper["vae"]["epochs"] == 2 and hyper["projection"]["lr"] == 1
    assert hyper["vae"]["lr"] == 1e-3 and isinstance(hyper["vae"]["lr"], float)  # YAML's text for 1e-3
    steps = merged_hyperparameters({"projection": {"steps": 30.0}}, DEFAULT_HYPERPARAMETERS)["projection"]["steps"]
    assert steps == 30 and isinstance(steps, int)
    assert merged({"representation": {"inner_leg_cosine": -0.2}})["representation"]["inner_leg_cosine"] == -0.2
