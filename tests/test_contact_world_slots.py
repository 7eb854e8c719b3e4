"""A world's body queries and drape do not depend on its slot in the world grid (BodyCollider)."""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import ClothBuilder
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import capsule_body, grid_cloth
from simulate.contact import BodyCollider
from simulate.contact.body_collider import world_cell_offsets
from unit_sim import unit_settings

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def test_world_cells_shift_every_world_onto_the_same_grid():
    rng = np.random.default_rng(0)
    spacing = 7.25  # anny: 3 x extent + 2 m
    # within S / 2 = 4 m of the centre rounded to S / 8: (0, 1, 0)
    local = (rng.uniform(-3.9, 3.9, (2000, 3)) + [0.0, 1.0, 0.0]).astype(np.float32)
    shifted = {}
    for worlds in (1, 2, 27, 512):
        off = world_cell_offsets(worlds, spacing, np.tile([0.0, 0.85, 0.0], (worlds, 1)))
        assert off.dtype == np.float32 and all(np.all(np.diff(np.unique(off[:, k])) == 8.0) for k in range(3))
        for w in {0, 1 % worlds, worlds - 1}:
            back = (local + off[w]) - off[w]  # float32 throughout
            assert np.all(np.abs(back - local) <= 3.9e-6)  # the grid of [64, 128): 7.6 um
            shifted.setdefault("any", back)
            np.testing.assert_array_equal(back, shifted["any"])  # the same rounding in every world and grid


def _capsule_scene():
    body_v, body_f = capsule_body(height=0.6, radius=0.15, center=(0.0, 0.0, 0.0), count=(16, 16))
    cloth_v, cloth_f = grid_cloth(12, 12, 0.5, 0.5, plane="xz", origin=(-0.25, 0.47, -0.25))  # 2 cm above the top
    return body_v, body_f, cloth_v, cloth_f


def _drape(device: str, worlds: int, frames: int = 40) -> tuple[np.ndarray, BodyCollider]:
    body_v, body_f, cloth_v, cloth_f = _capsule_scene()
    builder = ClothBuilder()
    for _ in range(worlds):
        builder.add_garment(cloth_v, cloth_f, fabric="cotton")
    model = builder.finalize(device)
    collider = BodyCollider(body_v, body_f, device=device, world_count=worlds)
    sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=5, iterations=5, max_frames=frames))
    for _ in range(frames):
        sim.step_frame()
    return sim.positions().reshape(worlds, len(cloth_v), 3), collider


@pytest.mark.parametrize("device", DEVICES)
def test_the_same_cloth_drapes_alike_in_every_world_slot(device):
    """A cloth dropped on a capsule, in all 27 worlds of a 3 x 3 x 3 grid and in both of a 2-world
    grid: every world comes to rest at the same positions, bit for bit."""
    grid, collider = _drape(device, 27)
    pair, _ = _drape(device, 2)
    world = np.repeat(np.arange(27, dtype=np.int32), grid.shape[1])
    sd = collider.signed_distance(grid.reshape(-1, 3), world, max_dist=0.1).reshape(27, -1)
    assert np.sum(sd[0] < 0.01) > 20, "the cloth must lie on the capsule (contacts)"
    assert sd.min() > 0.0
    for w in (1, 13, 26):
        np.testing.assert_array_equal(grid[w], grid[0], err_msg=f"world {w} of 27 rests elsewhere than world 0")
        np.testing.assert_array_equal(sd[w], sd[0])
    np.testing.assert_array_equal(pair[0], grid[0])
    np.testing.assert_array_equal(pair[1], grid[0])


@pytest.mark.parametrize("device", DEVICES)
def test_body_queries_read_alike_in_every_world(device):
    body_v, body_f, _, _ = _capsule_scene()
    collider = BodyCollider(body_v, body_f, device=device, world_count=27)
    rng = np.random.default_rng(3)
    points = (rng.normal(size=(500, 3)) * [0.2, 0.4, 0.2]).astype(np.float32)
    first = collider.signed_distance(points, np.zeros(len(points), np.int32), max_dist=0.3)
    assert np.any(first < 0.0) and np.any((first > 0.0) & (first < 0.3))
    for w in (1, 26):
        np.testing.assert_array_equal(collider.signed_distance(points, np.full(len(points), w, np.int32), max_dist=0.3),
                                      first)
    alone = BodyCollider(body_v, body_f, device=device)
    np.testing.assert_array_equal(alone.signed_distance(points, np.zeros(len(points), np.int32), max_dist=0.3), first)
