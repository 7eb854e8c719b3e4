"""ClothBuilder input checks, packing over worlds, colouring and fabric presets."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import FABRICS, ClothBuilder, Fabric, Features
from simulate.cloth.builder import dihedral_angles, greedy_colour
from simulate.scenes import grid_cloth, tube_cloth

wp.init()


def _grid() -> tuple[np.ndarray, np.ndarray]:
    return grid_cloth(4, 3, 0.3, 0.2, plane="xz")


@pytest.mark.parametrize("mutate,match", [
    (lambda v, f: (v[:, :2], f), r"vertices must have shape \(V, 3\)"),
    (lambda v, f: (np.where(np.arange(len(v))[:, None] == 2, np.nan, v), f), r"vertex 2 is \[nan"),
    (lambda v, f: (v, f[:, :2]), r"faces must have shape \(F, 3\)"),
    (lambda v, f: (v, f.astype(np.float64)), "faces must be integer"),
    (lambda v, f: (v, np.vstack([f, [[0, 1, 99]]])), r"faces\[12\] = \[0, 1, 99\] has an index out of range"),
    (lambda v, f: (v, np.vstack([f, [[0, 0, 1]]])), r"faces\[12\] = \[0, 0, 1\] repeats a vertex"),
    (lambda v, f: (np.vstack([v, v[:1] + 1.0]), f), "vertex 12 is not referenced"),
])
def test_add_garment_rejects_bad_input(mutate, match: str) -> None:
    verts, faces = mutate(*_grid())
    with pytest.raises(ValueError, match=match):
        ClothBuilder().add_garment(verts, faces)


def test_zero_area_triangle_is_named_with_its_area() -> None:
    verts = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 3, 1], [0, 1, 2]])
    with pytest.raises(ValueError, match=r"faces\[1\] = \[0, 1, 2\] is degenerate: area 0.000e\+00 m\^2"):
        ClothBuilder().add_garment(verts, faces)


def test_non_manifold_edge_is_rejected() -> None:
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(ValueError, match=r"edge \[0, 1\] is shared by 3 faces"):
        ClothBuilder().add_garment(verts, faces)


def test_bad_fabric_and_indices() -> None:
    verts, faces = _grid()
    with pytest.raises(ValueError, match="fabric must be one of"):
        ClothBuilder().add_garment(verts, faces, fabric="tweed")
    with pytest.raises(ValueError, match=r"pinned contains vertex index 50, expected indices in \[0, 12\)"):
        ClothBuilder().add_garment(verts, faces, pinned=[0, 50])
    with pytest.raises(ValueError, match=r"skinning_weights must have shape \(12, J\)"):
        ClothBuilder().add_garment(verts, faces, skinning_weights=np.ones((5, 2)))
    with pytest.raises(ValueError, match="Fabric.density must be a finite number > 0"):
        Fabric(density=0.0)
    with pytest.raises(ValueError, match="no garments"):
        ClothBuilder().finalize("cpu")


def test_fabric_presets_are_ordered_by_weight_and_stiffness() -> None:
    assert set(FABRICS) == {"cotton", "silk", "denim", "leather"}
    order = ["silk", "cotton", "denim", "leather"]
    for field in ("density", "stretch_stiffness", "bending_stiffness"):
        values = [getattr(FABRICS[n], field) for n in order]
        assert values == sorted(values), f"{field} not increasing silk < cotton < denim < leather: {values}"
    assert 0.05 <= FABRICS["silk"].density <= 0.08 and 0.3 <= FABRICS["denim"].density <= 0.4


def test_packing_offsets_masses_and_colouring() -> None:
    builder = ClothBuilder()
    grid_v, grid_f = grid_cloth(5, 4, 0.4, 0.3, plane="xz")
    tube_v, tube_f = tube_cloth(8, 4, 0.2, 0.3)
    assert builder.add_garment(grid_v, grid_f, fabric="silk", pinned=[0]) == 0
    assert builder.add_garment(tube_v, tube_f, fabric=FABRICS["denim"], attached=np.arange(8),
                               skinning_weights=np.ones((len(tube_v), 3))) == 1
    model = builder.finalize("cpu")
    assert model.world_count == 2 and model.particle_count == len(grid_v) + len(tube_v)
    assert model.world_particle_start.tolist() == [0, len(grid_v)]
    assert model.world_particle_count.tolist() == [len(grid_v), len(tube_v)]
    pworld = model.particle_world.numpy()
    assert (pworld[: len(grid_v)] == 0).all() and (pworld[len(grid_v):] == 1).all()
    # Lumped masses add up to density x area per world; the pinned vertex has inverse mass 0.
    mass = model.particle_mass.numpy()
    assert np.isclose(mass[: len(grid_v)].sum(), FABRICS["silk"].density * 0.4 * 0.3, rtol=1e-5)
    assert model.particle_inv_mass.numpy()[0] == 0.0
    assert model.features.attachments and model.attachment_count == 8
    assert model.attachment_particle.numpy().tolist() == list(range(len(grid_v), len(grid_v) + 8))
    # Colours: no two triangles (bending stencils) of one colour share a particle.
    tri = model.tri_indices.numpy()
    for offsets, elems in ((model.tri_colour_offsets, tri), (model.bend_colour_offsets, model.bend_indices.numpy())):
        for a, b in zip(offsets[:-1], offsets[1:]):
            flat = elems[a:b].reshape(-1)
            assert len(np.unique(flat)) == len(flat), f"colour range {a}:{b} shares particles"
    # Every triangle of the input appears once, in the right world.
    packed = {tuple(sorted(t)) for t in tri.tolist()}
    expected = {tuple(sorted(t)) for t in grid_f.tolist()} | {tuple(sorted(t)) for t in (tube_f + len(grid_v)).tolist()}
    assert packed == expected
    # Element slots per particle: exactly its corners' slots, ascending (triangles before bending).
    start, slots = model.particle_adj_start.numpy(), model.particle_adj_slot.numpy()
    corners = np.concatenate([tri.reshape(-1), model.bend_indices.numpy()[:model.bend_count].reshape(-1)])
    for i in range(model.particle_count):
        own = slots[start[i]:start[i + 1]]
        assert (np.diff(own) > 0).all() and own.tolist() == np.nonzero(corners == i)[0].tolist(), i
    # Flat rest cloth: all rest dihedral angles are zero.
    assert np.allclose(model.bend_rest_angle.numpy()[model.bend_world.numpy() == 0], 0.0, atol=1e-6)
    assert model.skinning_weights[1].shape == (len(tube_v), 3) and model.skinning_weights[0] is None


def test_worlds_that_repeat_a_garment_get_the_arrays_of_a_garment_built_alone() -> None:
    """Garments with the same rest geometry, faces and fabric share their element arrays (computed
    once); each world's elements, masses and pins are still exactly those of the garment alone."""
    tube_v, tube_f = tube_cloth(8, 4, 0.2, 0.3)
    bent = tube_v * np.array([1.0, 1.1, 0.9])  # another rest geometry, same faces
    worlds = [(tube_v, "cotton", [0]), (bent, "cotton", []), (tube_v, "cotton", [3, 5]), (tube_v, "silk", [])]
    builder = ClothBuilder()
    for v, fabric, pinned in worlds:
        builder.add_garment(v, tube_f, fabric=fabric, pinned=pinned)
    model = builder.finalize("cpu")
    for w, (v, fabric, pinned) in enumerate(worlds):
        alone = ClothBuilder()
        alone.add_garment(v, tube_f, fabric=fabric, pinned=pinned)
        ref = alone.finalize("cpu")
        start, count = int(model.world_particle_start[w]), int(model.world_particle_count[w])
        span = slice(start, start + count)
        assert np.array_equal(model.particle_mass.numpy()[span], ref.particle_mass.numpy())
        assert np.array_equal(model.particle_inv_mass.numpy()[span], ref.particle_inv_mass.numpy())
        for kind, fields in (("tri", ("indices", "dm_inv", "area", "compliance")),
                             ("bend", ("indices", "rest_angle", "compliance"))):
            mine = getattr(model, f"{kind}_world").numpy() == w  # this world's elements, in colour order
            for name in fields:
                got = getattr(model, f"{kind}_{name}").numpy()[mine]
                want = getattr(ref, f"{kind}_{name}").numpy()
                if name == "indices":
                    got = got - start
                assert np.array_equal(got, want), f"world {w}: {kind}_{name} differs from the garment built alone"


def test_features_switch_off_bending() -> None:
    verts, faces = _grid()
    builder = ClothBuilder()
    builder.add_garment(verts, faces)
    assert builder.finalize("cpu", features=Features(bending=False)).bend_count == 0
    assert builder.finalize("cpu").bend_count > 0


def test_greedy_colour_and_dihedral_naive_twins() -> None:
    rng = np.random.default_rng(0)
    elems = np.stack([rng.choice(30, size=3, replace=False) for _ in range(200)])
    colours = greedy_colour(elems)
    for c in np.unique(colours):
        flat = elems[colours == c].reshape(-1)
        assert len(np.unique(flat)) == len(flat)
    # A hinge folded by a known angle.
    angle = 0.7
    x = np.array([[0.0, 0.0, 1.0], [np.sin(angle) * 1.0, 0.0, -np.cos(angle)], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    theta = dihedral_angles(x, np.array([[0, 1, 2, 3]]))[0]
    assert np.isclose(abs(theta), angle, atol=1e-9), f"dihedral {theta} vs {angle}"


RTOL_BENDING_ENERGY = 0.03
"""Discrete bending energy of a bent equilateral sheet against 1/2 B kappa^2 area (edge effects)."""


def _equilateral_sheet(n: int, h: float) -> tuple[np.ndarray, np.ndarray]:
    rows = [[i * h + (j % 2) * h / 2.0, 0.0, j * h * np.sqrt(3.0) / 2.0] for j in range(n) for i in range(n)]
    verts = np.asarray(rows)
    verts -= verts.mean(axis=0)
    faces = []
    for j in range(n - 1):
        for i in range(n - 1):
            a, b, c, d = j * n + i, j * n + i + 1, (j + 1) * n + i, (j + 1) * n + i + 1
            faces += [[a, b, c], [b, d, c]] if j % 2 == 0 else [[a, b, d], [a, d, c]]
    return verts, np.asarray(faces)


@pytest.mark.parametrize("direction_deg", [0.0, 30.0, 45.0, 90.0])
def test_bending_energy_of_a_cylinder_matches_continuum(direction_deg: float) -> None:
    """Oracle for the bending stiffness: an equilateral sheet bent into a cylinder of radius R
    stores 1/2 B (1/R)^2 area, whichever direction it is bent in."""
    verts, faces = _equilateral_sheet(61, 0.005)
    fabric = Fabric(bending_stiffness=2.0e-5)
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric=fabric)
    model = builder.finalize("cpu", features=Features(body_contact=False))
    radius = 1.5
    d = np.array([np.cos(np.radians(direction_deg)), 0.0, np.sin(np.radians(direction_deg))])
    s = verts @ d
    bent = verts - np.outer(s, d) + np.outer(radius * np.sin(s / radius), d)
    bent[:, 1] = radius * (1.0 - np.cos(s / radius))
    theta = dihedral_angles(bent, model.bend_indices.numpy())
    energy = 0.5 * np.sum(theta ** 2 / model.bend_compliance.numpy().astype(np.float64))
    e1, e2 = verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum()
    expected = 0.5 * fabric.bending_stiffness * area / radius ** 2
    assert abs(energy / expected - 1.0) < RTOL_BENDING_ENERGY, f"bending energy {energy:.4e} vs {expected:.4e} J"


def test_benchmark_scenes_build_valid_worlds() -> None:
    from simulate.scenes import batched_drape, cape_scene, shawl_scene

    for scene in (shawl_scene(8, body="capsule"), cape_scene(12, body="capsule")):
        model, collider = batched_drape(scene, 3, "cpu", jitter=0.01)
        assert model.world_count == collider.world_count == 3
        q = model.particle_q_rest
        depth = collider.signed_distance(q, model.particle_world_np)
        assert depth.min() > collider.thickness, f"scene cloth starts {depth.min():.4f} m from the body"
    assert (model.particle_inv_mass.numpy() == 0.0).sum() == 3 * len(scene["pinned"])
