"""Inside/outside of the body queries: no point outside the body is ever called inside.

Reference: the winding number of the full, closed anny body (Warp's winding-number query; it
agrees with an exact float64 winding number on 15,000 points around three poses). Checked on a
pose whose arms sink into the torso, for the full body and for culled (open) part sets, in two
world cells: the collider's signed distance, the contact planes of ``detect_body_contacts`` and
the quality meter's penetration distance.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

from simulate.contact import BodyCollider
from simulate.contact import kernels as contact_kernels
from simulate.quality import QualityMeter

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])

ARMS_INTO_TORSO = {"left_shoulder": (0.0, 0.0, -1.0), "right_shoulder": (0.0, 0.0, 1.0)}
"""Arms lowered into the torso: 121 of every 4th arm vertex (272) lie inside the torso."""
PART_SETS = [None, ("torso", "arms", "legs"), ("torso", "legs")]
MAX_DIST = 0.2  # [m] search radius of the signed-distance queries


@wp.kernel
def _winding_inside(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, points[i], 1.0e3, 2.0, 0.5)
    out[i] = wp.where(q.sign < 0.0, 1, 0)


@wp.kernel
def _normal_sign(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float, out: wp.array(dtype=float)):
    i = wp.tid()
    q = wp.mesh_query_point_sign_normal(mesh, points[i], max_dist)
    out[i] = wp.where(q.result, q.sign, 1.0)


def _mesh(vertices, faces, device, **kwargs) -> wp.Mesh:
    return wp.Mesh(wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device=device),
                   wp.array(np.asarray(faces, np.int32).ravel(), dtype=wp.int32, device=device), **kwargs)


@pytest.fixture(scope="module")
def posed(anny_body):
    """The posed body (Vb, 3) [m], its faces, sample points (N, 3) [m] and whether each is inside
    the full body (N,) bool."""
    pose = anny_body.pose_from_dict(ARMS_INTO_TORSO)
    verts = np.asarray(anny_body.pose(anny_body.shape_default[None], pose[None]).vertices[0], np.float64)
    faces = np.asarray(anny_body.faces, np.int64)
    normals = trimesh.Trimesh(verts, faces, process=False).vertex_normals
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(verts), 1500)
    along = rng.uniform(-0.03, 0.08, len(idx))[:, None]
    box = rng.uniform(verts.min(0) - 0.1, verts.max(0) + 0.1, (300, 3))
    points = np.concatenate([verts[idx] + normals[idx] * along, box]).astype(np.float32)
    inside = wp.zeros(len(points), dtype=wp.int32, device="cpu")
    full = _mesh(verts, faces, "cpu", support_winding_number=True)
    wp.launch(_winding_inside, dim=len(points), inputs=[full.id, wp.array(points, dtype=wp.vec3, device="cpu")],
              outputs=[inside], device="cpu")
    return verts, faces, points, inside.numpy().astype(bool)


def _contact_planes(collider: BodyCollider, points: np.ndarray, world: int, reach: float):
    """detect_body_contacts for particles at ``points`` in ``world``: (active, normal, offset - reach)."""
    dev = collider.device
    n = len(points)
    active = wp.zeros(n, dtype=wp.int32, device=dev)
    normal = wp.zeros(n, dtype=wp.vec3, device=dev)
    offset = wp.zeros(n, dtype=float, device=dev)
    motion = wp.zeros(n, dtype=wp.vec3, device=dev)
    depth = wp.zeros(n, dtype=float, device=dev)
    world_active = wp.ones(collider.world_count, dtype=wp.int32, device=dev)
    wp.launch(contact_kernels.detect_body_contacts, dim=n,
              inputs=[collider.contact_meshes, collider.pose_start, collider.pose_end,
                      collider.world_offset, 0.0, reach, 0.0,
                      wp.full(n, world, dtype=wp.int32, device=dev), wp.zeros(n, dtype=wp.int32, device=dev),
                      wp.zeros(n, dtype=float, device=dev), world_active,
                      wp.array(points, dtype=wp.vec3, device=dev)],
              outputs=[active, normal, offset, motion, depth], device=dev)
    return active.numpy().astype(bool), normal.numpy(), offset.numpy() - reach


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("parts", PART_SETS, ids=lambda p: "full" if p is None else "+".join(p))
def test_no_point_outside_the_body_is_called_inside(anny_body, posed, device, parts):
    verts, faces, points, inside = posed
    part_faces = faces if parts is None else anny_body.part_faces(list(parts))
    outside = ~inside
    assert outside.sum() > 1000 and inside.sum() > 300

    # Warp's normal sign calls hundreds of these outside points inside once parts are culled:
    # the sample reaches past the open cuts
    sign = wp.zeros(len(points), dtype=float, device=device)
    mesh = _mesh(verts, part_faces, device)
    wp.launch(_normal_sign, dim=len(points), inputs=[mesh.id, wp.array(points, dtype=wp.vec3, device=device), MAX_DIST],
              outputs=[sign], device=device)
    if parts is not None:
        assert (outside & (sign.numpy() < 0.0)).sum() > 50

    collider = BodyCollider(verts, part_faces, device=device, world_count=2)
    meter = QualityMeter(np.array([[0, 1, 2]]), np.zeros((len(points), 3)), part_faces, len(verts), device=device)
    hood = meter.signed_distance(points, verts)
    assert not np.any(outside & (hood < 0.0)), f"quality meter: {np.sum(outside & (hood < 0.0))} outside points inside"
    for world in (0, 1):
        sd = collider.signed_distance(points, np.full(len(points), world, np.int32), max_dist=MAX_DIST)
        wrong = outside & (sd < 0.0)
        assert not wrong.any(), \
            f"world {world}: {wrong.sum()} outside points inside, deepest {-sd[wrong].min() * 1e3:.1f} mm"
        if parts is None:
            # and it is no blanket "outside": inside points within reach read inside, but for the
            # few nearest to a skin sunk into another part (arm in the torso), or to the eyes
            near = inside & (sd < MAX_DIST)
            assert (sd[near] < 0.0).mean() > 0.75
        # a contact plane keeps an outside point on the side it is on
        active, normal, surface = _contact_planes(collider, points, world, reach=0.02)
        lifted = np.einsum("ij,ij->i", normal, points) - surface
        flipped = outside & active & (lifted < -1e-6)
        assert not flipped.any(), f"world {world}: {flipped.sum()} contact planes push outside points into the body"
        assert np.any(outside & active)


@pytest.mark.parametrize("device", DEVICES)
def test_a_point_past_an_open_cut_is_outside(device):
    """A sphere with its cap cut off: points above the opening are outside, and so are points inside
    the sphere past the cut (no skin there) or nearer the rim than any skin (on the axis just below
    the cut); points inside the lower half are inside."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    verts, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    cup = faces[verts[faces].mean(axis=1)[:, 1] < 0.2]
    collider = BodyCollider(verts, cup, device=device)
    heights = np.linspace(-0.25, 0.6, 35)
    rng = np.random.default_rng(1)
    points = np.concatenate([np.stack([np.zeros_like(heights), heights, np.zeros_like(heights)], 1),
                             rng.normal(size=(300, 3)) * 0.25]).astype(np.float32)
    sd = collider.signed_distance(points, np.zeros(len(points), np.int32), max_dist=1.0)
    r = np.linalg.norm(points, axis=1)
    outside = r > 0.3 + 2e-3  # outside the whole sphere (facets sit up to 1 mm inside it)
    assert not np.any(outside & (sd < 0.0))
    lower = (r < 0.3 - 2e-3) & (points[:, 1] < 0.0)
    assert lower.sum() > 50 and np.all(sd[lower] < 0.0)
    past_cut = (r < 0.3 - 2e-3) & (points[:, 1] > 0.22)  # inside the sphere but past the cut (rim at y 0.18-0.21)
    assert np.all(sd[past_cut] > 0.0)
