"""Collision-aware learner (seed 002): diffused fields, the garment model's inverse, the canonical
projection, the VAE's self-supervised collision term, and the CLI path on a tiny anny dataset."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import trimesh

from learn.collision_aware.canonicalize import (ProjectionSettings, project_frames, project_sequences, projection_key,
                                               projection_quality)
from learn.collision_aware.diffusion import closest_surface_points, diffusion_operator, interpolation_matrix
from learn.collision_aware.fields import DiffusedBody
from learn.collision_aware.garment_model import mesh_parts, pose_garment, unpose_garment
from learn.collision_aware.vae import GarmentVAE
from learn.common.mesh import grid_mesh, mesh_edges
from simulate.body.kinematics import axis_angle_to_matrix

ATOL_SURFACE = 1e-5  # diffused value on the surface vs the surface value (values in [0, 1])
MAX_STEP_OFF_SURFACE = 0.3  # largest change between 1 cm steps across the 8 cm gap (a linear ramp: 0.125; closest point: 1)
ATOL_ROUND_TRIP_M = 1e-5
COLLISION_DEPTH_M = 1e-3


class SphereSDF(torch.nn.Module):
    """Exact SDF of a sphere [m]: the canonical body of the synthetic cases."""

    def __init__(self, radius: float = 0.2) -> None:
        super().__init__()
        self.radius = radius

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return torch.linalg.vector_norm(points, dim=-1) - self.radius


def two_boxes() -> trimesh.Trimesh:
    """Two 10 cm boxes 10 cm apart along x (a pair of legs): the medial plane is x = 0."""
    a = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    a.apply_translation((-0.1, 0.0, 0.0))
    b = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    b.apply_translation((0.1, 0.0, 0.0))
    return trimesh.util.concatenate([a, b])


def test_grid_sdf_is_the_exact_signed_distance_near_the_surface_and_outside_beyond_the_grid() -> None:
    """A 1 cm grid of a sphere mesh's signed distance, against the same query at random points:
    within 0.3 mm wherever the points are inside the grid (trilinear on a 0.2 m radius: ~0.1 mm),
    the sign right for every point more than 1 mm off the surface, beyond the grid a positive upper
    bound of the distance, and a gradient pointing out of the body."""
    from learn.collision_aware.sdf import grid_sdf
    from learn.common.collision import body_signed_distance

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
    vertices, faces = np.asarray(sphere.vertices, np.float32), np.asarray(sphere.faces)
    sdf = grid_sdf(vertices, faces, voxel_m=0.01, margin_m=0.05)
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(4000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(0.12, 0.3, size=4000)
    points = (direction * radius[:, None]).astype(np.float32)
    query = body_signed_distance(points, vertices, faces, max_distance=1.0)
    exact = np.linalg.norm(points - query.closest, axis=1) * np.sign(query.distance)
    predicted = sdf(torch.as_tensor(points)).numpy()
    in_grid = radius < 0.2 + 0.05
    error = np.abs(predicted - exact)
    assert error[in_grid].max() < 3e-4, float(error[in_grid].max())
    clear = np.abs(exact) > 1e-3
    assert np.all(np.sign(predicted[clear]) == np.sign(exact[clear]))
    beyond = ~in_grid & (np.abs(points) > 0.25).any(axis=1)
    assert beyond.any() and np.all(predicted[beyond] > 0.04) and np.all(predicted[beyond] >= exact[beyond] - 3e-4)
    near = torch.as_tensor(points[np.abs(exact) < 0.02]).requires_grad_(True)
    sdf(near).sum().backward()
    outward = (near.grad * near.detach()).sum(-1) / near.detach().norm(dim=-1)
    assert torch.all(outward > 0.9), float(outward.min())


def test_diffused_field_is_the_surface_value_on_the_surface_and_smooth_off_it() -> None:
    mesh = two_boxes()
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(0)
    values = rng.random((len(vertices), 2))
    on_surface = trimesh.sample.sample_surface(mesh, 200, seed=1)[0]
    face, bary, distance = closest_surface_points(on_surface, vertices, faces)
    assert distance.max() < 1e-6, f"surface samples {distance.max()} m off the surface"
    exact = interpolation_matrix(face, bary, faces, len(vertices)) @ values
    diffused = diffusion_operator(on_surface, vertices, faces, samples=32, seed=2) @ values
    assert np.abs(diffused - exact).max() < ATOL_SURFACE, f"on-surface error {np.abs(diffused - exact).max()}"

    side = np.where(vertices[:, 0] > 0, 1.0, 0.0)[:, None]  # 0 on the left box, 1 on the right one
    line = np.stack([np.linspace(-0.04, 0.04, 9), np.zeros(9), np.zeros(9)], axis=1)  # across the gap
    nearest = interpolation_matrix(*closest_surface_points(line, vertices, faces)[:2], faces, len(vertices)) @ side
    field = diffusion_operator(line, vertices, faces, samples=1024, seed=3) @ side
    assert np.abs(np.diff(nearest[:, 0])).max() == pytest.approx(1.0), "the closest-point field should jump"
    steps = np.abs(np.diff(field[:, 0]))
    assert steps.max() < MAX_STEP_OFF_SURFACE, f"diffused field jumps by {steps.max():.3f} across the medial plane"
    assert field[0, 0] < 0.5 < field[-1, 0], f"diffused field does not follow the sides: {field[:, 0]}"


def _rotations(batch: int, joints: int, scale: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    transforms = torch.eye(4).repeat(batch, joints, 1, 1)
    transforms[..., :3, :3] = axis_angle_to_matrix(scale * torch.randn(batch, joints, 3, generator=g))
    transforms[..., :3, 3] = 0.02 * torch.randn(batch, joints, 3, generator=g)
    return transforms


def _small_fields(seed: int = 0) -> DiffusedBody:
    torch.manual_seed(seed)
    return DiffusedBody(3, [0.5], [0.5], hidden_size=16, layers=2, frequencies=1, scale=0.5)


def test_shape_field_error_measures_the_skin_against_the_body_models_own_shapes(anny_body) -> None:
    """``shape_field_error`` is zero for a field that gives the body's own offsets at its vertices
    and the offsets' size for a field that gives none; vertex_index restricts it to those vertices."""
    from learn.collision_aware.fields import canonical_body, shape_field_error

    rest = torch.as_tensor(canonical_body(anny_body), dtype=torch.float32)

    class Exact(torch.nn.Module):  # the body's own shaped rest minus the canonical one, at its vertices
        def __init__(self, scale: float) -> None:
            super().__init__()
            self.scale = torch.nn.Parameter(torch.tensor(scale), requires_grad=False)

        def shape_offset(self, points: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
            shaped, _ = anny_body.rest(shape.numpy())
            return self.scale * (torch.as_tensor(shaped)[:, :points.shape[1]] - rest[None, :points.shape[1]])

    ranges = np.asarray(anny_body.shape_ranges)
    shapes = np.stack([ranges[:, 0], ranges[:, 1]]).astype(np.float32)
    exact = shape_field_error(Exact(1.0), anny_body, shapes)
    assert exact["max_mm"] < 1e-3 and exact["shapes"] == 2, exact
    none = shape_field_error(Exact(0.0), anny_body, shapes)
    shaped, _ = anny_body.rest(shapes)
    sizes = np.linalg.norm(shaped - rest.numpy()[None], axis=-1) * 1e3
    assert none["max_mm"] == pytest.approx(float(sizes.max()), rel=1e-4) and none["median_mm"] > 10.0, none
    first = shape_field_error(Exact(0.0), anny_body, shapes, vertex_index=np.arange(100))
    assert first["max_mm"] == pytest.approx(float(sizes[:, :100].max()), rel=1e-4)
    # the data's shapes are drawn their share of the time, uniformly among them; share 0: all alike
    from learn.collision_aware.fields import draw_shapes

    drawn = draw_shapes(40000, 128, 3, 0.5, torch.Generator().manual_seed(0))
    assert abs(float((drawn >= 128).float().mean()) - 0.5) < 0.01 and int(drawn.max()) == 130
    assert np.allclose(np.bincount(drawn[drawn >= 128].numpy() - 128) / float((drawn >= 128).sum()), 1 / 3, atol=0.02)
    alike = draw_shapes(40000, 128, 3, 0.0, torch.Generator().manual_seed(0))
    assert abs(float((alike >= 128).float().mean()) - 3 / 131) < 0.005
    # the data's shapes join the random ones among the field's training shapes, offsets and all
    from learn.collision_aware.fields import field_targets

    targets = field_targets(anny_body, point_count=64, shape_count=2, samples=4, extra_shapes=shapes, seed=0)
    assert targets.shapes.shape[0] == 4 and np.array_equal(targets.shapes[2:], shapes) and targets.data_count == 2
    assert targets.offsets.shape[:2] == (4, 64)
    assert np.abs(targets.offsets[3]).max() > 0.01, "the extra shapes get their own offsets"


def test_basis_shape_field_is_the_body_models_own_offsets_in_the_span_of_its_basis(anny_body) -> None:
    """The basis field: the components of sampled shapes' offsets span those shapes, so their
    coefficients (by the body model) rebuild their offsets exactly; with components exact at the
    body's vertices the skin is shaped to the body model's own; zero at the default shape; a
    basis wider than the offsets' span is refused; a field without its body says so."""
    from learn.collision_aware.fields import canonical_body, new_diffused_body, shape_basis, shape_field_error

    rest = canonical_body(anny_body).astype(np.float64)
    ranges = np.asarray(anny_body.shape_ranges, np.float64)
    shapes = np.random.default_rng(3).uniform(ranges[:, 0], ranges[:, 1], size=(3, len(ranges))).astype(np.float32)
    offsets = anny_body.rest(shapes)[0].astype(np.float64) - rest  # (3, Vb, 3)
    vectors, scale = shape_basis(offsets, 3)
    assert vectors.shape == (3, rest.shape[0], 3) and np.all(np.diff(scale) <= 0)
    assert np.allclose(np.einsum("cvd,evd->ce", vectors, vectors), np.eye(3), atol=1e-5), "orthonormal"
    with pytest.raises(ValueError, match="span only 3 dimensions"):
        shape_basis(offsets, 4)
    fields = new_diffused_body(anny_body, hidden_size=8, layers=1, frequencies=0, shape_basis=3, shape_hidden_size=8,
                               shape_layers=1, shape_frequencies=0)
    fields.set_shape_basis(vectors, scale, rest)
    coefficients = fields.shape_coefficients(torch.as_tensor(shapes)).numpy()  # (3, C)
    rebuilt = np.einsum("kc,c,cvd->kvd", coefficients, scale, vectors)
    assert np.abs(rebuilt - offsets).max() < 1e-4, np.abs(rebuilt - offsets).max()  # [m], float32 sums over 41k
    default = torch.as_tensor(np.asarray(anny_body.shape_default, np.float32))[None]
    assert fields.shape_coefficients(default).abs().max() < 1e-3

    index = {tuple(np.round(v, 5)): i for i, v in enumerate(rest.astype(np.float32))}
    components = torch.as_tensor(vectors * scale[:, None, None], dtype=torch.float32)  # (C, Vb, 3)

    class ExactComponents(torch.nn.Module):  # the diffused components on the skin: their values there
        def forward(self, points: torch.Tensor) -> torch.Tensor:
            rows = [index[tuple(np.round(p, 5))] for p in points.reshape(-1, 3).numpy()]
            return components[:, rows].permute(1, 0, 2).reshape(*points.shape[:-1], -1)

    fields.shape_net = ExactComponents()
    exact = shape_field_error(fields, anny_body, shapes)
    assert exact["max_mm"] < 0.1, exact
    outside = np.random.default_rng(4).uniform(ranges[:, 0], ranges[:, 1], size=(2, len(ranges))).astype(np.float32)
    off_span = shape_field_error(fields, anny_body, outside)  # three shapes do not span anny's offsets
    assert off_span["max_mm"] > 1.0, off_span
    # a conditioned field saved without the (empty) basis buffers loads
    conditioned = new_diffused_body(anny_body, hidden_size=8, layers=1, frequencies=0)
    state = {k: v for k, v in conditioned.state_dict().items() if not k.startswith("basis_")}
    new_diffused_body(anny_body, hidden_size=8, layers=1, frequencies=0).load_state_dict(state)
    bare = new_diffused_body(anny_body, hidden_size=8, layers=1, frequencies=0, shape_basis=3)
    bare.use_body(None)
    with pytest.raises(RuntimeError, match="use_body"):
        bare.shape_offset(torch.zeros(1, 2, 3), default)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_posed_collision_term_is_zero_outside_the_posed_body_and_pushes_points_out_of_it(anny_body, device) -> None:
    """At the rest pose and default shape the garment model is the identity, so the posed term
    sees the canonical points themselves: 0 for skin points 5 mm outside (margin 1 mm), the
    depth plus the margin for points 5 mm inside, and its gradient moves them out along the
    normal. The distance is the collision metric's own (its BVHs refitted from batch to batch)."""
    from learn.collision_aware.fields import canonical_body, new_diffused_body
    from learn.collision_aware.posed_collision import PosedCollision
    from learn.common.collision import collision_mask
    from simulate.body.mesh_utils import vertex_normals

    rest = canonical_body(anny_body).astype(np.float32)
    normals = vertex_normals(rest, anny_body.faces).astype(np.float32)
    chest = np.flatnonzero((np.asarray(anny_body.vertex_parts) == 0) & (normals[:, 2] > 0.9))[::40][:50]
    fields = new_diffused_body(anny_body, hidden_size=8, layers=1, frequencies=0).to(device)
    term = PosedCollision(anny_body, fields, epsilon_m=1e-3, device=device)
    pose = torch.as_tensor(np.asarray(anny_body.canonical_pose, np.float32), device=device)[None]
    shape = torch.as_tensor(np.asarray(anny_body.shape_default, np.float32), device=device)[None]
    outside = torch.as_tensor(rest[chest] + 5e-3 * normals[chest], device=device)[None]
    with torch.no_grad():
        assert float(term(outside, pose, shape)) == 0.0
    inside = torch.as_tensor(rest[chest] - 5e-3 * normals[chest], device=device)[None].requires_grad_(True)
    penalty = term(inside, pose, shape)
    assert float(penalty.detach()) == pytest.approx(6e-3, abs=1e-3), float(penalty.detach())
    penalty.backward()
    outward = (inside.grad[0].cpu() * torch.as_tensor(normals[chest])).sum(-1)
    assert outward.max() < 0, "descent moves the points outward"
    both = torch.cat([outside, inside.detach()])  # two frames: two BVHs, the first refitted again
    posed, body_vertices = term.posed(both, pose.expand(2, -1), shape.expand(2, -1))
    distance = term.distance(posed, body_vertices).cpu()
    mask = collision_mask(posed.cpu(), body_vertices.cpu(), anny_body.faces)
    assert bool((distance[0] > 4e-3).all()) and bool((distance[1] < -4e-3).all()) and not mask[0].any() and mask[1].all()


def test_canonical_posed_canonical_round_trip() -> None:
    fields = _small_fields()
    g = torch.Generator().manual_seed(1)
    canonical = 0.2 * torch.randn(2, 50, 3, generator=g)
    shape = torch.tensor([[0.7], [0.3]])
    transforms = _rotations(2, 3, 0.3, seed=2)
    with torch.no_grad():
        posed = pose_garment(fields, canonical, shape, transforms)
        back = unpose_garment(fields, posed, shape, transforms, initial=canonical + 0.01 * torch.randn(2, 50, 3, generator=g),
                              iterations=30)
    error = (back - canonical).abs().max().item()
    assert error < ATOL_ROUND_TRIP_M, f"canonical -> posed -> canonical differs by {error} m"
    assert (posed - canonical).abs().max() > 0.01, "the test transforms should move the garment"


class _FoldedWeights:
    """Two joints, joint 1 shifted +0.5 m in x, its weight 1 where |x| > 0.3 m and 0 between: a
    point M near the origin is reached both from X = M (weight 0) and from X = M - 0.5 m (weight
    1), the fold LBS has where diffused weights change over a short distance."""

    shift = 0.5

    def skinning_weights(self, x: torch.Tensor) -> torch.Tensor:
        far = (x[..., 0].abs() > 0.3).to(x.dtype)
        return torch.stack([1.0 - far, far], dim=-1)

    def shape_offset(self, x: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(x)


def test_unposing_keeps_a_vertex_on_its_neighbours_branch_of_a_fold() -> None:
    grid, faces = grid_mesh(5, 5, spacing=0.01)
    truth = torch.as_tensor(grid, dtype=torch.float32)[None]  # weight 0 everywhere: posed == canonical
    transforms = torch.eye(4).repeat(1, 2, 1, 1)
    transforms[0, 1, 0, 3] = _FoldedWeights.shift
    start = truth.clone()
    start[0, 12, 0] += 0.35  # the centre vertex starts on the other side of the fold
    kwargs = dict(initial=start, iterations=5)
    stray = unpose_garment(_FoldedWeights(), truth, torch.zeros(1, 1), transforms, **kwargs)
    # the plain fixed point converges to the other, exact, solution: 0.5 m from its neighbours
    assert abs(float(stray[0, 12, 0] - truth[0, 12, 0]) + _FoldedWeights.shift) < 1e-5
    kept = unpose_garment(_FoldedWeights(), truth, torch.zeros(1, 1), transforms,
                          edges=torch.as_tensor(mesh_edges(faces)), **kwargs)
    assert (kept - truth).abs().max() < 1e-6, (kept - truth).abs().max()


def test_unposing_brings_back_a_patch_that_strayed_across_a_fold() -> None:
    """A 9 x 9 patch that starts on the far branch holds itself there (its inner vertices have
    only neighbours on that branch: the neighbours' mean weights, as a guard, leave its centre
    0.17 m off after 5 steps); cut from the rest of the mesh by its long edges, it takes the
    weights carried in from the rest, and lands back within one step."""
    grid, faces = grid_mesh(15, 15, spacing=0.01)
    truth = torch.as_tensor(grid, dtype=torch.float32)[None].repeat(2, 1, 1)
    transforms = torch.eye(4).repeat(2, 2, 1, 1)
    transforms[:, 1, 0, 3] = _FoldedWeights.shift
    patch = np.flatnonzero((np.abs(grid[:, 0] - grid[:, 0].mean()) < 0.041) & (np.abs(grid[:, 1] - grid[:, 1].mean()) < 0.041))
    assert patch.size == 81
    start = truth.clone()
    start[0, patch, 0] += 0.35  # frame 0: the patch on the other side; frame 1: all on the right one
    edges = torch.as_tensor(mesh_edges(faces))
    for iterations in (1, 5):
        kept = unpose_garment(_FoldedWeights(), truth, torch.zeros(2, 1), transforms, initial=start,
                              iterations=iterations, edges=edges)
        assert (kept - truth).abs().max() < 1e-6, (iterations, (kept - truth).abs().max())
    # the vertices' own neighbours, as a guard, would keep the patch's centre where it strayed
    lone = unpose_garment(_FoldedWeights(), truth, torch.zeros(2, 1), transforms, initial=start, iterations=5)
    assert float((lone[0, patch] - truth[0, patch]).abs().max()) > 0.4


def test_mesh_parts_match_a_graph_library() -> None:
    """The parts of a grid mesh with random edges cut equal scipy's connected components (each
    vertex labelled by the smallest vertex index of its part)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    grid, faces = grid_mesh(12, 10, spacing=0.01)
    edges = mesh_edges(faces)
    rng = np.random.default_rng(3)
    cut = rng.random((4, edges.shape[0])) < np.array([0.0, 0.3, 0.6, 0.9])[:, None]
    labels = mesh_parts(len(grid), torch.as_tensor(edges), torch.as_tensor(cut)).numpy()
    for b in range(4):
        kept = edges[~cut[b]]
        graph = coo_matrix((np.ones(len(kept)), (kept[:, 0], kept[:, 1])), shape=(len(grid), len(grid)))
        count, parts = connected_components(graph, directed=False)
        smallest = np.full(count, len(grid))
        np.minimum.at(smallest, parts, np.arange(len(grid)))
        np.testing.assert_array_equal(labels[b], smallest[parts])
    assert len(np.unique(labels[0])) == 1 and len(np.unique(labels[3])) > 10


def _patch_on_sphere(radius: float, offsets: np.ndarray) -> tuple[torch.Tensor, np.ndarray]:
    """A 10 x 10 grid patch over the sphere's +z cap at ``radius + offsets`` [m] (B, 100)."""
    grid, faces = grid_mesh(10, 10, spacing=0.025)
    theta = (grid[:, 0] - grid[:, 0].mean()) / radius
    phi = (grid[:, 1] - grid[:, 1].mean()) / radius
    direction = np.stack([np.sin(theta) * np.cos(phi), np.sin(phi), np.cos(theta) * np.cos(phi)], axis=1)
    points = (radius + np.asarray(offsets)[..., None]) * direction
    return torch.as_tensor(points, dtype=torch.float32), faces


def _posed_patches(frames: int, *, fields_seed: int, scale: float, transforms_seed: int) -> tuple:
    """``frames`` copies of a patch 1 cm over the sphere, shape 0.5, posed by random transforms of
    ``scale`` rad: truth (canonical), faces, fields, shape, transforms, target (posed)."""
    truth, faces = _patch_on_sphere(0.2, np.full((frames, 100), 0.01))
    fields = _small_fields(fields_seed)
    shape = torch.full((frames, 1), 0.5)
    transforms = _rotations(frames, 3, scale, seed=transforms_seed)
    with torch.no_grad():
        target = pose_garment(fields, truth, shape, transforms)
    return truth, faces, fields, shape, transforms, target


def test_projection_reduces_its_objective_and_clears_the_body() -> None:
    sdf = SphereSDF(0.2)
    grid_offsets = np.linspace(-0.004, 0.008, 100)  # some vertices up to 4 mm inside the sphere
    truth, faces = _patch_on_sphere(0.2, np.stack([grid_offsets, grid_offsets[::-1]]))
    fields = _small_fields(3)
    shape = torch.tensor([[0.6], [0.4]])
    transforms = _rotations(2, 3, 0.2, seed=4)
    with torch.no_grad():
        target = pose_garment(fields, truth, shape, transforms)
    settings = ProjectionSettings(steps=80, lr=1e-3, epsilon_m=2e-3)
    x, info = project_frames(target, shape, transforms, fields=fields, sdf=sdf, faces=torch.as_tensor(faces, dtype=torch.int64),
                             initial=truth + 0.005, settings=settings)
    assert torch.all(info["objective"] < 0.5 * info["objective_start"]), info
    inside_start = (sdf(truth) < -COLLISION_DEPTH_M).float().mean().item()
    inside = (sdf(x) < -COLLISION_DEPTH_M).float().mean().item()
    assert inside_start > 0.1, "the synthetic frames should start with collisions"
    assert inside == 0.0, f"{100 * inside:.1f} % of projected vertices are more than 1 mm inside the body"
    rms = info["reconstruction"].sqrt().max().item()
    assert rms < 0.004, f"projection reconstructs the frames only to {rms * 1000:.2f} mm rms"


class _FixedPoses:
    """A body whose skinning transforms for frame k (pose[:, 0] == k) are ``transforms[k]``."""

    def __init__(self, transforms: torch.Tensor) -> None:
        self.transforms = transforms

    def on_device(self, device):
        return self

    def pose_torch(self, shape, pose):
        return type("Posed", (), {"skinning_transforms": self.transforms[pose[:, 0].long()]})()


def test_warm_started_frames_take_the_warm_step_and_only_they_key_it() -> None:
    """Under a warm start the first frame is refined at ``lr`` from the template and every later
    frame at ``warm_lr`` from the frame before; without one every frame at ``lr`` from the
    template. ``warm_lr`` enters the cache key only under a warm start."""
    from dataclasses import replace

    truth, faces, fields, shape, transforms, target = _posed_patches(3, fields_seed=7, scale=0.1, transforms_seed=8)
    template = truth[0].numpy() + 0.01
    settings = ProjectionSettings(steps=20, lr=1e-2, warm_lr=1e-4)
    sequence = {"target": target.numpy(), "pose": np.arange(3, dtype=np.float32)[:, None], "shape": np.array([0.5], np.float32)}
    kwargs = dict(body=_FixedPoses(transforms), fields=fields, sdf=SphereSDF(0.2), faces=faces, template=template)
    faces_t = torch.as_tensor(faces, dtype=torch.int64)

    def frame(t: int, start: torch.Tensor, step: ProjectionSettings) -> torch.Tensor:
        return project_frames(target[t:t + 1], shape[t:t + 1], transforms[t:t + 1], fields=fields, sdf=SphereSDF(0.2),
                              faces=faces_t, initial=start[None], settings=step)[0][0]

    (warm,), _ = project_sequences([sequence], settings=settings, warm_start=True, **kwargs)
    (cold,), _ = project_sequences([sequence], settings=settings, warm_start=False, **kwargs)
    start = torch.as_tensor(template)
    expected_warm = [frame(0, start, settings)]
    for t in (1, 2):
        expected_warm.append(frame(t, expected_warm[-1], replace(settings, lr=settings.warm_lr)))
    np.testing.assert_allclose(warm, torch.stack(expected_warm).numpy(), atol=1e-7)
    np.testing.assert_allclose(cold, torch.stack([frame(t, start, settings) for t in range(3)]).numpy(), atol=1e-7)
    at_lr = frame(1, expected_warm[0], settings).numpy()
    assert np.abs(at_lr - warm[1]).max() > 1e-4, "the warm step should change the second frame's refinement"

    other = replace(settings, warm_lr=1e-3)
    template_m = np.asarray(template, np.float32)
    assert projection_key(fields, SphereSDF(0.2), template_m, settings) == projection_key(fields, SphereSDF(0.2), template_m, other)
    assert (projection_key(fields, SphereSDF(0.2), template_m, settings, warm_start=True)
            != projection_key(fields, SphereSDF(0.2), template_m, other, warm_start=True))


def test_projection_quality_names_the_one_failed_frame() -> None:
    """Exact projections score ~0 mm; one frame moved 1 m shows as a 1 m frame in the maximum and
    the count over 50 mm, and leaves the other frames' scores as they were."""
    from types import SimpleNamespace

    truth, faces, fields, shape, transforms, target = _posed_patches(4, fields_seed=5, scale=0.3, transforms_seed=6)
    frames = SimpleNamespace(posed_vertices=target.numpy(), translation=None, shape=shape.numpy(),
                             pose=np.arange(4, dtype=np.float32)[:, None])
    kwargs = dict(body=_FixedPoses(transforms), fields=fields, sdf=SphereSDF(0.2), faces=faces, batch_size=3)
    exact = projection_quality(truth.numpy(), frames, **kwargs)
    assert exact["frames"] == 4 and exact["reconstruction_rms_mm"]["max"] < 1e-3, exact
    failed = truth.numpy().copy()
    failed[2] += np.array([0.0, 1.0, 0.0], np.float32)
    report = projection_quality(failed, frames, **kwargs)
    per_frame = report["per_frame_reconstruction_rms_mm"]
    assert report["frames_over_50mm"] == 1 and report["frames_over_10mm"] == 1, report
    assert per_frame.argmax() == 2 and 700.0 < per_frame[2] < 1300.0, per_frame
    np.testing.assert_array_equal(np.delete(per_frame, 2), np.delete(exact["per_frame_reconstruction_rms_mm"], 2))
    assert report["reconstruction_rms_mm"]["median"] < 1e-3


def test_posed_term_on_reconstructions_joins_the_vae_loss_with_its_weight() -> None:
    """vae.posed_collision: the loss with the posed term differs from the loss without it by the
    weight times the term of the reconstructions, and its gradient reaches the decoder. The
    stand-in for the posed body is a sphere larger than the canonical one, so garments clear in
    the canonical space collide in it (as where an arm lies on the torso)."""
    from learn.collision_aware.sdf import collision_penalty
    from learn.collision_aware.vae import vae_loss
    from learn.common.mesh import uniform_laplacian_torch

    sdf, posed_body = SphereSDF(0.2), SphereSDF(0.25)
    garments, faces = _patch_on_sphere(0.2, np.full((8, 100), 0.02))  # 2 cm outside the canonical sphere
    torch.manual_seed(0)
    vae = GarmentVAE(100, garments.mean(0).numpy(), 0.01, latent_size=4, hidden_size=16)
    laplacian = uniform_laplacian_torch(faces, 100, boundary_aware=False)
    seen = []

    def posed(reconstruction: torch.Tensor) -> torch.Tensor:
        seen.append(reconstruction.shape)
        return collision_penalty(posed_body(reconstruction), 1e-3).mean()

    results = {}
    for w in (100.0, 0.0):
        torch.manual_seed(1)
        terms = vae_loss(vae, garments, laplacian=laplacian, sdf=sdf, weights={"laplacian": 1.0, "collision": 10.0,
                         "kl": 1e-3, "random_collision": 0.0, "posed_collision": w}, epsilon_m=2e-3,
                         random_samples=0, posed=posed)
        vae.zero_grad()
        terms["loss"].backward()
        results[w] = (float(terms["loss"].detach()), float(terms["posed_collision"].detach()),
                      [q.grad.clone() for q in vae.decoder.parameters()])
    assert seen[0] == garments.shape, "the term sees the batch's reconstructions"
    assert results[100.0][1] > 0.02, "the reconstructions lie inside the posed stand-in"
    assert results[100.0][0] == pytest.approx(results[0.0][0] + 100.0 * results[100.0][1], rel=1e-5)
    assert sum(float((a - b).abs().sum()) for a, b in zip(results[100.0][2], results[0.0][2])) > 0
    terms = vae_loss(vae, garments, laplacian=laplacian, sdf=sdf, weights={"laplacian": 1.0, "collision": 10.0,
                     "kl": 1e-3}, epsilon_m=2e-3, random_samples=0)
    assert float(terms["posed_collision"]) == 0.0, "no posed term without posed="


def test_self_supervised_term_pushes_random_samples_out_of_the_body() -> None:
    """The term on decoded random latents is what trains the decoder away from the body where
    there is no data: with training garments outside the body and a decoder whose random samples
    are inside, the loss with the term differs from the loss without it exactly by that term, its
    gradient reaches the decoder, and a step along it lowers the random samples' collisions.
    (Training to convergence on a tiny case put no random sample inside with or without the term,
    so the comparison is made on the gradient.)"""
    from learn.collision_aware.sdf import collision_penalty
    from learn.collision_aware.vae import vae_loss
    from learn.common.mesh import uniform_laplacian_torch

    sdf = SphereSDF(0.2)
    outside, faces = _patch_on_sphere(0.2, np.full((8, 100), 0.01))  # training garments 1 cm outside
    inside, _ = _patch_on_sphere(0.2, np.full(100, -0.01))  # the decoder's mean: 1 cm inside
    torch.manual_seed(0)
    vae = GarmentVAE(100, inside.numpy(), 0.01, latent_size=4, hidden_size=16)
    laplacian = uniform_laplacian_torch(faces, 100, boundary_aware=False)
    weights = {"laplacian": 1.0, "collision": 10.0, "kl": 1e-3}
    losses, grads = {}, {}
    for w in (1.0, 0.0):
        torch.manual_seed(1)  # same posterior and random latents in both
        terms = vae_loss(vae, outside, laplacian=laplacian, sdf=sdf, weights={**weights, "random_collision": w},
                         epsilon_m=2e-3, random_samples=64)
        vae.zero_grad()
        terms["loss"].backward()
        losses[w] = {k: v.detach() for k, v in terms.items()}
        grads[w] = [p.grad.clone() for p in vae.decoder.parameters()]
    assert float(losses[1.0]["random_collision"]) > 0.005, "random samples should start inside the body"
    expected = float(losses[0.0]["loss"]) + 10.0 * float(losses[1.0]["random_collision"])
    assert float(losses[1.0]["loss"]) == pytest.approx(expected, rel=1e-5), "the two losses differ by more than the term"
    difference = [g1 - g0 for g1, g0 in zip(grads[1.0], grads[0.0])]
    assert sum(float(d.abs().sum()) for d in difference) > 0, "the random-sample term gives the decoder no gradient"

    z = torch.randn(256, 4, generator=torch.Generator().manual_seed(2))

    def random_penalty() -> float:
        with torch.no_grad():
            return float(collision_penalty(sdf(vae.decode(z)), 2e-3).mean())

    before = random_penalty()
    step = 0.2 / max(float(d.abs().max()) for d in difference)  # largest parameter change 0.2
    with torch.no_grad():
        for p, d in zip(vae.decoder.parameters(), difference):
            p -= step * d
    assert random_penalty() < 0.9 * before, (before, random_penalty())


def test_batch_random_latents_follow_the_encoded_data_not_the_prior() -> None:
    """``random_latents: batch`` draws the self-supervised term's latents where the batch's latent
    means lie (their per-dimension mean and spread), ``prior`` from N(0, I); an unknown source is
    named. Data latents far from N(0, I) (a weak KL weight) are covered only by the first."""
    from learn.collision_aware.vae import random_latents

    torch.manual_seed(0)
    mu = torch.tensor([3.0, -2.0, 0.0]) + torch.randn(64, 3) * torch.tensor([2.0, 0.5, 1.0])
    batch = random_latents(mu, 20000, "batch")
    assert torch.allclose(batch.mean(0), mu.mean(0), atol=0.05), batch.mean(0)
    assert torch.allclose(batch.std(0), mu.std(0, unbiased=False), rtol=0.03), batch.std(0)
    prior = random_latents(mu, 20000, "prior")
    assert torch.allclose(prior.mean(0), torch.zeros(3), atol=0.05) and torch.allclose(prior.std(0), torch.ones(3), rtol=0.03)
    assert not random_latents(mu.clone().requires_grad_(True), 4, "batch").requires_grad, "the data's latents are detached"
    with pytest.raises(ValueError, match="vae.random_latents must be one of prior, batch, got 'uniform'"):
        random_latents(mu, 4, "uniform")


def test_vae_collision_gradient_points_out_of_the_body() -> None:
    """The collision term's gradient moves decoded vertices that are inside the body outward."""
    sdf = SphereSDF(0.2)
    torch.manual_seed(0)
    vae = GarmentVAE(100, np.zeros((100, 3)), 0.1, latent_size=4, hidden_size=8)
    decoded = vae.decode(torch.zeros(1, 4)).detach().requires_grad_(True)
    from learn.collision_aware.sdf import collision_penalty

    collision_penalty(sdf(decoded), 2e-3).mean().backward()
    inside = sdf(decoded.detach())[0] < 2e-3
    assert inside.any()
    radial = (decoded.grad[0] * decoded.detach()[0]).sum(-1)
    assert torch.all(radial[inside] < 0), "descending the gradient must move vertices away from the centre"


def test_cli_train_evaluate_predict_on_a_tiny_anny_dataset(tmp_path, anny_body, capsys) -> None:
    from collision_aware_data import write_band_dataset, write_tiny_config
    from pipelines.cli import main

    data = tmp_path / "data"
    write_band_dataset(data, anny_body, splits={"train": 2, "test_test": 1}, frames_per_task=2)
    config = write_tiny_config(tmp_path / "tiny.yaml")
    run = tmp_path / "run"
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--config", str(config),
                 "--epochs", "2", "--no-progress"]) == 0
    cached = sorted((data / "cache" / "canonical").glob("*.npy"))
    assert len(cached) == 2, f"expected one cached projection per training shard, got {cached}"
    fields_report = json.loads((run / "fields.json").read_text())["shape_field_error_on_skin_under_garment"]
    assert fields_report["data_shapes"]["shapes"] >= 1 and fields_report["random_shapes"]["shapes"] == 16
    assert all(np.isfinite(v["median_mm"]) for v in fields_report.values()), fields_report
    # each stage's loss log names its units; the default (mlp) regressor compares decoded garments [m]
    headers = {stage: (run / f"{stage}_loss.csv").read_text().splitlines()[0] for stage in ("fields", "vae", "regressor")}
    assert headers == {"fields": "epoch,train_l1,seconds", "vae": "epoch,train_l1_m,seconds",
                       "regressor": "epoch,train_l1_m,seconds"}, headers
    # the posed-space collision term: the VAE and the regressor retrained with it on the run's fields and SDF
    import shutil

    import yaml

    posed_run = tmp_path / "posed"
    posed_run.mkdir()
    for path in run.iterdir():
        if path.name.split(".")[0] in ("fields", "sdf"):
            shutil.copy(path, posed_run / path.name)
    posed = yaml.safe_load(open(config))
    posed["regressor"]["posed_collision"] = 100.0
    posed["vae"]["posed_collision"] = 100.0
    (tmp_path / "posed.yaml").write_text(yaml.safe_dump(posed))
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(posed_run), "--config",
                 str(tmp_path / "posed.yaml"), "--epochs", "2", "--no-progress"]) == 0
    assert (posed_run / "regressor_loss.csv").read_text().splitlines()[0] == "epoch,train_loss_m,seconds"
    assert (posed_run / "fields.pt").read_bytes() == (run / "fields.pt").read_bytes(), "the copied stages are kept"
    vae_terms = json.loads((posed_run / "vae_terms.json").read_text())
    assert np.isfinite(vae_terms["posed_collision"]) and vae_terms["posed_collision"] >= 0.0, vae_terms
    assert json.loads((run / "vae_terms.json").read_text())["posed_collision"] == 0.0, "off by default"
    # sampled poses are drawn as the dataset's spec draws them: this dataset's spec samples none
    posed["regressor"]["sampled_poses"] = 4
    (tmp_path / "sampled.yaml").write_text(yaml.safe_dump(posed))
    capsys.readouterr()
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(tmp_path / "sampled"), "--config",
                 str(tmp_path / "sampled.yaml"), "--epochs", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "regressor.sampled_poses = 4" in err and "poses.source: sampled" in err and "Traceback" not in err, err

    coarser = yaml.safe_load(open(config))
    coarser["sdf"]["voxel_m"] = 0.04
    (tmp_path / "coarser.yaml").write_text(yaml.safe_dump(coarser))
    capsys.readouterr()
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--config",
                 str(tmp_path / "coarser.yaml"), "--epochs", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "sdf.pt holds a grid at 0.03 m, not a grid at 0.04 m" in err and "Traceback" not in err, err
    assert main(["evaluate", str(run), "--data", str(data), "--postprocess-frames", "1", "--renders", "0"]) == 0
    report = json.loads((run / "evaluation" / "evaluation.json").read_text())
    metrics = report["splits"]["test_test"]["collision_aware"]
    for key in ("unposed_error_mm", "posed_error_mm", "collision_rate", "collision_rate_postprocessed"):
        assert np.isfinite(metrics[key]), (key, metrics)
    assert abs(metrics["posed_error_mm"] - metrics["unposed_error_mm"]) < 0.5 * metrics["unposed_error_mm"] + 1.0, metrics
    timing = report["timing"]["collision_aware"]["cpu"]
    assert timing["ms_per_frame_batch_1"] > 0 and timing["decoder_ms_per_frame_batch_1"] > 0
    # the canonical collision rate: the predicted canonical garments' vertices inside the run's SDF
    assert 0.0 <= metrics["canonical_collision_rate"] <= 1.0, metrics
    from learn.collision_aware.sdf import load_run_sdf
    from learn.registry import LEARNERS

    model = LEARNERS["collision_aware"].load(run / "collision_aware_model.pt", fingerprint=None,
                                             require_same_manifest=False, device="cpu")
    assert load_run_sdf(tmp_path / "nowhere") is None
    sdf = load_run_sdf(run)
    from learn.data import DrapeDataset
    from learn.tailornet.train import frame_arrays_from_dataset

    test = frame_arrays_from_dataset(DrapeDataset(data, "test_test", frequencies=False))

    class Offset(torch.nn.Module):  # the run's SDF moved by a constant [m]
        def __init__(self, by: float) -> None:
            super().__init__()
            self.by = by

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return sdf(x) + self.by

    rate = model.canonical_collision_rate(sdf, test.pose, test.shape, test.style)
    assert rate == pytest.approx(metrics["canonical_collision_rate"])
    assert model.canonical_collision_rate(Offset(-1.0), test.pose, test.shape, test.style) == 1.0  # all 1 m inside
    assert model.canonical_collision_rate(Offset(1.0), test.pose, test.shape, test.style) == 0.0
    assert model.canonical_collision_rate(Offset(-0.002), test.pose, test.shape, test.style) >= rate
    out = tmp_path / "pred.obj"
    assert main(["predict", str(run), "--learner", "collision_aware", "--style", "0.1,0.2", "--out", str(out)]) == 0
    with np.load(run / "template.npz") as template:
        assert len(trimesh.load(out, process=False).vertices) == len(template["rest_vertices"])


def _frozen_tiny_vae() -> GarmentVAE:
    """A seeded 20-vertex VAE with frozen weights: a fixed decoder for the regressor's tests."""
    torch.manual_seed(0)
    vae = GarmentVAE(20, np.zeros((20, 3)), 0.05, latent_size=4, hidden_size=16)
    for p in vae.parameters():
        p.requires_grad_(False)
    return vae


def test_regressor_with_the_canonical_target_fits_the_decoded_garment_not_the_latents(tmp_path) -> None:
    """``regressor.target: canonical`` trains through the frozen decoder against the projected
    frames: given latents that carry nothing (all zero), it still fits the garments, where the
    latent target fits the zeros. A bad target value names the setting."""
    from learn.collision_aware.train import _regressor_target, train_regressor
    from learn.data import FrameArrays

    vae = _frozen_tiny_vae()
    rng = np.random.default_rng(0)
    n, poses = 64, 6
    pose = rng.uniform(-1, 1, (n, poses)).astype(np.float32)
    with torch.no_grad():  # garments the decoder can make, a function of the pose
        canonical = vae.decode(torch.as_tensor(pose[:, :4])).numpy()
    data = FrameArrays(pose=pose, shape=np.zeros((n, 2), np.float32), style=np.zeros((n, 2), np.float32),
                       displacements=np.zeros((n, 20, 3), np.float32), pair_id=np.zeros(n, np.int64))
    zeros = np.zeros((n, 4), np.float32)
    hyper = {"lr": 1e-2, "weight_decay": 0.0, "batch_size": 16, "epochs": 150, "hidden_size": 32, "dropout": 0.0}

    def decoded_error(target: str) -> float:
        regressor = train_regressor(data, zeros, np.arange(poses), run_dir=tmp_path / target, seed=0, progress=False,
                                    hyperparameters={**hyper, "target": target}, vae=vae, canonical=canonical)
        with torch.no_grad():
            garment = vae.decode(regressor(torch.as_tensor(pose), torch.as_tensor(data.shape), torch.as_tensor(data.style)))
        return float((garment - torch.as_tensor(canonical)).norm(dim=-1).mean())

    spread = float(np.linalg.norm(canonical - canonical.mean(0), axis=-1).mean())
    assert decoded_error("canonical") < 0.2 * spread < decoded_error("latent"), spread
    # the loss logs name their units: metres against the garment, none against the latents
    for target, column in (("canonical", "train_l1_m"), ("latent", "train_l1_latent")):
        assert (tmp_path / target / "regressor_loss.csv").read_text().splitlines()[0] == f"epoch,{column},seconds"
    with pytest.raises(ValueError, match="regressor.target must be auto, latent or canonical, got 'vertices'"):
        _regressor_target({"target": "vertices"}, "mlp")
    with pytest.raises(ValueError, match="regressor.target 'canonical' is for the mlp regressor"):
        _regressor_target({"target": "canonical"}, "gru")
    # auto (the default): the decoded garment for the mlp, the seed's latents for the gru
    assert (_regressor_target({}, "mlp"), _regressor_target({}, "gru")) == ("canonical", "latent")
    assert _regressor_target({"target": "auto"}, "gru") == "latent"
    with pytest.raises(ValueError, match="regressor.target 'auto' trains against the decoded garment"):
        train_regressor(data, zeros, np.arange(poses), run_dir=tmp_path / "none", progress=False, hyperparameters=hyper)


def test_sampled_poses_join_the_regressors_posed_term(tmp_path) -> None:
    """regressor.sampled_poses: every step the posed term also sees that many poses of the bank,
    each with a training frame's shape; the term changes what the regressor learns. Without the
    posed term, or without sampled poses to draw from, the setting is refused by name."""
    from learn.collision_aware.train import train_regressor
    from learn.data import FrameArrays

    vae = _frozen_tiny_vae()
    rng = np.random.default_rng(0)
    n, poses = 48, 6
    pose = rng.uniform(-1, 0, (n, poses)).astype(np.float32)  # the training poses: all entries <= 0
    shape = np.repeat(rng.normal(size=(3, 2)).astype(np.float32), n // 3, axis=0)
    with torch.no_grad():
        canonical = vae.decode(torch.as_tensor(pose[:, :4])).numpy()
    data = FrameArrays(pose=pose, shape=shape, style=np.zeros((n, 2), np.float32),
                       displacements=np.zeros((n, 20, 3), np.float32), pair_id=np.zeros(n, np.int64))
    bank = rng.uniform(0.5, 1.0, (32, poses)).astype(np.float32)  # poses no frame has: all entries > 0
    seen: list[tuple[np.ndarray, np.ndarray]] = []

    def posed(garment: torch.Tensor, pose_batch: torch.Tensor, shape_batch: torch.Tensor) -> torch.Tensor:
        seen.append((pose_batch.detach().numpy().copy(), shape_batch.detach().numpy().copy()))
        return torch.relu(0.05 - garment[..., 1]).mean()  # a stand-in: every vertex above y = 0.05

    hyper = {"lr": 1e-2, "weight_decay": 0.0, "batch_size": 16, "epochs": 30, "hidden_size": 32, "dropout": 0.0,
             "target": "canonical", "posed_collision": 10.0}

    def fit(sampled: int) -> torch.nn.Module:
        seen.clear()
        return train_regressor(data, np.zeros((n, 4), np.float32), np.arange(poses), run_dir=tmp_path / str(sampled),
                               seed=0, progress=False, hyperparameters={**hyper, "sampled_poses": sampled}, vae=vae,
                               canonical=canonical, posed=posed, sampled_pose=bank if sampled else None)

    fit(0)
    assert all((p <= 0).all() for p, _ in seen), "without sampled poses the term sees the training poses only"
    plain = fit(0)
    sampled = fit(8)
    from_bank = [(p, s) for p, s in seen if (p > 0).all()]
    assert len(from_bank) == 30 * 3 and all(len(p) == 8 for p, _ in from_bank), len(from_bank)
    assert all(any(np.array_equal(row, b) for b in bank) for p, _ in from_bank for row in p)
    assert all(any(np.array_equal(row, s) for s in shape) for _, s in from_bank for row in s), "shapes of the frames"

    def violation(model: torch.nn.Module) -> float:
        with torch.no_grad():
            garment = vae.decode(model(torch.as_tensor(bank), torch.as_tensor(shape[:32]), torch.zeros(32, 2)))
        return float(torch.relu(0.05 - garment[..., 1]).mean())

    assert violation(sampled) < violation(plain), "the sampled poses' term did not reach the regressor"
    with pytest.raises(ValueError, match="regressor.sampled_poses adds sampled poses"):
        train_regressor(data, np.zeros((n, 4), np.float32), np.arange(poses), run_dir=tmp_path / "bad", progress=False,
                        hyperparameters={**hyper, "sampled_poses": 8, "posed_collision": 0.0}, vae=vae,
                        canonical=canonical, posed=posed, sampled_pose=bank)


def test_sampled_poses_are_drawn_as_the_spec_draws_them_and_refused_by_name(anny_body, tmp_path) -> None:
    """The bank follows the spec's sampling (its joints move, the others keep the canonical pose,
    within the limits), from a seed of its own; fit_collision_aware refuses sampled_poses without
    the posed term, for a dataset whose poses are not sampled, and a non-integer count."""
    from learn.collision_aware.train import fit_collision_aware, spec_poses
    from learn.data import FrameArrays
    from simulate.body.base import POSE_JOINTS
    from simulate.poses import GARMENT_POSE_JOINTS

    spec = {"poses": {"source": "sampled", "joints": "upper", "range_scale": 0.5, "min_clearance": None},
            "garment": {"type": "tshirt"}}
    a, b = spec_poses(spec, anny_body, 16, seed=3), spec_poses(spec, anny_body, 16, seed=3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, spec_poses(spec, anny_body, 16, seed=4))
    per_joint = a.reshape(16, len(POSE_JOINTS), 3)
    canonical = np.asarray(anny_body.canonical_pose, np.float32).reshape(len(POSE_JOINTS), 3)
    moved = set(GARMENT_POSE_JOINTS["upper"])
    for k, joint in enumerate(POSE_JOINTS):
        if joint not in moved:
            np.testing.assert_allclose(per_joint[:, k], np.broadcast_to(canonical[k], (16, 3)), err_msg=joint)
    assert np.abs(per_joint[:, [POSE_JOINTS.index(j) for j in moved]]).max() > 0.05, "no joint moved"
    wider = spec_poses({**spec, "poses": {**spec["poses"], "range_scale": 1.0}}, anny_body, 64, seed=3)
    assert np.abs(wider - anny_body.canonical_pose).mean() > 1.5 * np.abs(
        spec_poses(spec, anny_body, 64, seed=3) - anny_body.canonical_pose).mean(), "the spec's range_scale is ignored"

    n = 4
    data = FrameArrays(pose=np.zeros((n, 60), np.float32), shape=np.zeros((n, 2), np.float32),
                       style=np.zeros((n, 2), np.float32), displacements=np.zeros((n, 5, 3), np.float32),
                       pair_id=np.zeros(n, np.int64), posed_vertices=np.zeros((n, 5, 3), np.float32))
    args = dict(run_dir=tmp_path, body=anny_body, template={"faces": np.zeros((1, 3), np.int64)}, progress=False)
    cases = [({"regressor": {"sampled_poses": 8}}, spec, "which is off: set regressor.posed_collision > 0"),
             ({"regressor": {"sampled_poses": 8, "posed_collision": 10.0}}, {**spec, "poses": {"source": "file"}},
              "needs a dataset whose spec samples its poses"),
             ({"regressor": {"sampled_poses": 2.5, "posed_collision": 10.0}}, spec,
              r"regressor.sampled_poses must be an integer \(got 2.5\)"),
             ({"regressor": {"sampled_poses": -1, "posed_collision": 10.0}}, spec,
              r"regressor.sampled_poses must be >= 0 \(got -1\)")]
    for hyper, dataset_spec, message in cases:
        with pytest.raises(ValueError, match=message):
            fit_collision_aware(data, np.zeros((1, 3), np.int64), hyperparameters=hyper, dataset_spec=dataset_spec,
                                **args)
