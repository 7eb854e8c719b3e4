"""Optional self-contact: a falling layer rests on a pinned layer only when self-contact is on."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator, SimSettings
from simulate.scenes import grid_cloth
from contact_scenes import folded_sheet_worlds
from unit_sim import unit_settings

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
ATOL_GAP_M = 5.0e-4
"""Allowed shortfall of the kept distance below the self-contact thickness [m]."""


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", ["gauss_seidel", "jacobi"])
@pytest.mark.parametrize("self_contact", [True, False])
def test_layer_rests_on_layer_with_self_contact(device: str, mode: str, self_contact: bool) -> None:
    lower_v, lower_f = grid_cloth(9, 9, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    upper_v, upper_f = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.16, 0.02, -0.14))
    verts = np.vstack([lower_v, upper_v])
    faces = np.vstack([lower_f, upper_f + len(lower_v)])
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)))  # the lower layer is a table
    model = builder.finalize(device, features=Features(self_contact=self_contact, body_contact=False))
    sim = QuasiStaticSimulator(model, None, settings=unit_settings(substeps=5, iterations=5, damping=2.0,
                                                                 xpbd_mode=mode))
    assert (sim.solver.self_contact is not None) == self_contact, "self-contact buffers/kernels present when off"
    for _ in range(30):
        sim.step_frame()
    upper = sim.positions()[len(lower_v):]
    if self_contact:
        thickness = sim.solver.self_contact.thickness
        assert upper[:, 1].min() > thickness - ATOL_GAP_M, (
            f"upper layer at y = {upper[:, 1].min() * 1e3:.2f} mm, expected >= {thickness * 1e3:.1f} mm")
        assert upper[:, 1].max() < 0.01, "upper layer did not come down onto the lower one"
    else:
        assert upper[:, 1].max() < -0.1, "without self-contact the upper layer should fall through"


def test_a_garment_at_rest_has_no_self_contacts(anny_body):
    """Neighbours (the 2-ring) and pairs already close in the rest shape (the armpit crease of a
    t-shirt) are not contacts: repelling them blew a 7k-vertex shirt apart at its first frame."""
    from simulate.contact.self_contact import SelfContact
    from simulate.garment.templates import make_template

    template = make_template("tshirt", anny_body, resolution=7700)
    builder = ClothBuilder()
    builder.add_garment(template.vertices, template.faces, fabric="cotton")
    model = builder.finalize("cpu", features=Features(self_contact=True))
    contact = SelfContact(model)
    x = wp.array(model.particle_q_rest_np, dtype=wp.vec3, device="cpu")
    active = wp.ones(1, dtype=wp.int32, device="cpu")
    contact.detect(x, active)
    assert (contact.candidate.numpy() >= 0).sum() == 0, "a garment in its rest shape must not push itself apart"
    no_exclusion = SelfContact(model, rest_exclusion=0.0)
    no_exclusion.detect(x, active)
    assert (no_exclusion.candidate.numpy() >= 0).sum() > 0, "the armpit crease is within reach without the rest exclusion"


@pytest.mark.parametrize("device", DEVICES)
def test_self_contact_bvh_is_built_where_it_is_refit(device: str) -> None:
    """The cloth BVH is built once and then only refit, so it must be built over the points at
    their world cells: built over the overlapping rest garments its nodes spanned every world and
    each query walked all of them (40 t-shirts' canonical drapes went from 45 s to > 440 s)."""
    from simulate.contact.self_contact import SelfContact

    v, f = grid_cloth(6, 6, 0.1, 0.1)
    builder = ClothBuilder()
    for _ in range(3):
        builder.add_garment(v, f, fabric="cotton")
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    contact = SelfContact(model)
    built = contact.points.numpy().copy()
    x = wp.array(model.particle_q_rest_np, dtype=wp.vec3, device=device)
    contact.detect(x, wp.ones(model.world_count, dtype=wp.int32, device=device))
    np.testing.assert_array_equal(contact.points.numpy(), built)
    per_world = built.reshape(model.world_count, -1, 3)
    assert np.ptp(per_world[:, :, 0].mean(axis=1)) > 1.0, "worlds must sit in separate cells"


def test_self_contact_relaxation_is_validated() -> None:
    from simulate.contact.self_contact import SelfContact

    verts, faces = grid_cloth(3, 3, 0.1, 0.1, plane="xz")
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton")
    model = builder.finalize("cpu", features=Features(self_contact=True, body_contact=False))
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="relaxation"):
            SelfContact(model, relaxation=bad)
    for bad in (0, 2.5):
        with pytest.raises(ValueError, match="detect_every"):
            SelfContact(model, detect_every=bad)


def test_detecting_every_fifth_substep_still_holds_the_layer() -> None:
    """self_contact_detect_every=5 with 5 substeps: one candidate search per frame instead of 5,
    and the falling layer still rests on the table layer at the contact thickness."""
    lower_v, lower_f = grid_cloth(9, 9, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    upper_v, upper_f = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.16, 0.02, -0.14))
    builder = ClothBuilder()
    builder.add_garment(np.vstack([lower_v, upper_v]), np.vstack([lower_f, upper_f + len(lower_v)]), fabric="cotton",
                        pinned=np.arange(len(lower_v)))
    model = builder.finalize("cpu", features=Features(self_contact=True, body_contact=False))
    calls = {}
    for every in (1, 5):
        sim = QuasiStaticSimulator(model, None, settings=unit_settings(substeps=5, iterations=5, damping=2.0,
                                                                     self_contact_detect_every=every))
        contact = sim.solver.self_contact
        assert contact.detect_every == every
        detect = contact.detect
        calls[every] = 0

        def counted(*args, _detect=detect, _every=every, **kwargs):
            calls[_every] += 1
            _detect(*args, **kwargs)

        contact.detect = counted
        for _ in range(30):
            sim.step_frame()
        upper = sim.positions()[len(lower_v):]
        assert upper[:, 1].min() > contact.thickness - ATOL_GAP_M, (every, upper[:, 1].min())
        assert upper[:, 1].max() < 0.01, every
    assert calls == {1: 150, 5: 30}, calls


@pytest.mark.parametrize("device", DEVICES)
def test_worlds_with_self_contact_off_get_no_candidates(device: str) -> None:
    """``ClothControl.world_self_contact`` turns the search off per world: two layers 2 mm apart
    find each other in the world that has it on and not in the one that has it off."""
    from simulate.contact.self_contact import SelfContact

    v, f = grid_cloth(5, 5, 0.1, 0.1, plane="xz")
    layers = np.concatenate([v, v + np.array([0.0, 0.002, 0.0], np.float32)])
    faces = np.concatenate([f, f + len(v)])
    builder = ClothBuilder()
    for _ in range(2):
        builder.add_garment(layers, faces, fabric="cotton")
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    control = model.control()
    contact = SelfContact(model, rest_exclusion=0.0)  # the layers are this close at rest too
    x = wp.array(model.particle_q_rest_np, dtype=wp.vec3, device=device)
    per_world = len(layers)
    found = {}
    for mask in ((True, True), (True, False)):
        control.set_self_contact(np.array(mask))
        contact.detect(x, control.world_active, world_self_contact=control.world_self_contact)
        found[mask] = (contact.candidate.numpy().reshape(2, per_world) >= 0).sum(axis=1)
    assert found[(True, True)][0] == found[(True, True)][1] > per_world // 2, f"layers 2 mm apart must touch: {found}"
    assert found[(True, False)][0] == found[(True, True)][0] and found[(True, False)][1] == 0, found
    with pytest.raises(ValueError, match=r"self-contact mask must have shape \(2,\)"):
        control.set_self_contact(np.ones(3, bool))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bounds", [False, True], ids=["pushes", "bounds"])
def test_tiled_substep_pushes_self_contacts_as_the_separate_launches_do(device: str, bounds: bool) -> None:
    """With the positions in shared memory the whole substep, self-contact pushes (and the
    displacement bounds) included, is one launch per world block; it steps exactly as the
    per-colour launches followed by ``SelfContact.project``, the particle kernel (and the bounds'
    clamp): two worlds where a falling layer lands on a pinned one over a sphere (body contact
    too), one with an attached vertex."""
    lower_v, lower_f = grid_cloth(9, 9, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    upper_v, upper_f = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.16, 0.02, -0.14))
    verts = np.vstack([lower_v, upper_v])
    faces = np.vstack([lower_f, upper_f + len(lower_v)])
    from simulate.scenes import icosphere
    from simulate.contact import BodyCollider

    out, pushed = {}, {}
    for sweep, shared in (("colour_launches", False), ("world_blocks", True)):
        builder = ClothBuilder()
        for k in range(2):
            builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)),
                                attached=[len(lower_v) + 3] if k else None)
        model = builder.finalize(device, features=Features(self_contact=True))
        sv, sf = icosphere(0.05, subdivisions=2)
        collider = BodyCollider(sv + np.array([0.0, 0.05, 0.0], np.float32), sf, device=device, world_count=2)
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=5, iterations=4, damping=2.0,
                                                                         gs_sweep=sweep, gs_block_dim=64),
                                   solver_options={"gs_shared": shared, "self_contact_options": {"bounds": bounds}})
        assert sim.solver._fused == shared and sim.solver.bounds == bounds
        pushed[sweep] = 0
        for _ in range(20):
            sim.step_frame()
            pushed[sweep] += int((np.linalg.norm(sim.solver.self_contact.delta.numpy(), axis=1) > 0).sum())
        out[sweep] = sim.positions()
    upper = out["world_blocks"][len(lower_v):len(verts)]
    assert pushed["world_blocks"] > 0 and pushed["world_blocks"] == pushed["colour_launches"], pushed
    assert upper[:, 1].max() < 0.15 and upper[:, 1].min() > 0.0, "the upper layer must come to rest on the lower"
    assert np.array_equal(out["world_blocks"], out["colour_launches"]), (
        f"the tiled substep differs by {np.abs(out['world_blocks'] - out['colour_launches']).max():.3g} m")


def _closest_point(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Point of triangle abc closest to p, by projecting onto the plane and, outside the
    triangle, onto the nearest of its edges (a plain reference for Ericson's region tests)."""
    n = np.cross(b - a, c - a)
    q = p - np.dot(p - a, n) / np.dot(n, n) * n
    ab, ac, aq = b - a, c - a, q - a
    d00, d01, d11 = ab @ ab, ab @ ac, ac @ ac
    v = (d11 * (aq @ ab) - d01 * (aq @ ac)) / (d00 * d11 - d01 * d01)
    w = (d00 * (aq @ ac) - d01 * (aq @ ab)) / (d00 * d11 - d01 * d01)
    if v >= 0 and w >= 0 and v + w <= 1:
        return q
    best = None
    for s, e in ((a, b), (b, c), (c, a)):
        t = np.clip(np.dot(p - s, e - s) / np.dot(e - s, e - s), 0.0, 1.0)
        x = s + t * (e - s)
        if best is None or np.linalg.norm(p - x) < np.linalg.norm(p - best):
            best = x
    return best


@pytest.mark.parametrize("rest_exclusion", [0.0, 0.03])
def test_candidate_search_matches_brute_force(rest_exclusion: float) -> None:
    """Each particle's candidate is the nearest triangle of its world within the reach, outside its
    2-ring and not closer than ``rest_exclusion`` at rest, found by brute force over every
    triangle: a sheet folded onto itself 3 mm apart with jitter, in two worlds (one shifted).
    Without the rest-shape exclusion the 2-ring alone keeps the fold's own triangles out."""
    from simulate.contact.self_contact import SelfContact

    model, x = folded_sheet_worlds(seed=3, jitter=4e-4)
    contact = SelfContact(model, thickness=0.004, margin=0.004, rest_exclusion=rest_exclusion)
    contact.detect(wp.array(x, dtype=wp.vec3, device="cpu"), model.control().world_active)
    got = contact.candidate.numpy()
    tri = model.tri_indices.numpy()
    tri_world = model.tri_world.numpy()
    rest = np.asarray(model.particle_q_rest_np, np.float64)
    pworld = model.particle_world.numpy()
    reach = contact.thickness + contact.margin
    expected = np.full(model.particle_count, -1)
    nearest = np.full(model.particle_count, np.inf)  # distance to the nearest allowed triangle [m]
    allowed = [set() for _ in range(model.particle_count)]
    for i in range(model.particle_count):
        ring1 = {int(u) for t in tri if i in t for u in t}
        for t, (a, b, c) in enumerate(tri):
            if tri_world[t] != pworld[i] or i in (a, b, c) or ring1 & {int(a), int(b), int(c)}:
                continue
            if np.linalg.norm(rest[i] - _closest_point(rest[i], *rest[[a, b, c]])) < contact.rest_exclusion:
                continue
            allowed[i].add(t)
            d = np.linalg.norm(x[i] - _closest_point(x[i].astype(np.float64), *x[[a, b, c]].astype(np.float64)))
            if d < min(reach, nearest[i]):
                nearest[i], expected[i] = d, t
    assert (expected >= 0).sum() > model.particle_count // 4, "the folded halves must find each other"
    assert np.array_equal(got >= 0, expected >= 0), np.nonzero((got >= 0) != (expected >= 0))[0]
    for i in np.nonzero(got >= 0)[0]:  # the nearest, up to ties (two triangles meeting at the closest point)
        a, b, c = tri[got[i]]
        d = np.linalg.norm(x[i] - _closest_point(x[i].astype(np.float64), *x[[a, b, c]].astype(np.float64)))
        assert got[i] in allowed[i] and d < nearest[i] + 1e-6, (i, got[i], expected[i], d, nearest[i])


def test_rest_exclusion_comes_from_the_settings() -> None:
    """``SimSettings.self_contact_rest_exclusion`` reaches the solver's SelfContact; None keeps its
    default, a negative value is refused."""
    v, f = grid_cloth(5, 5, 0.1, 0.1, plane="xz")
    builder = ClothBuilder()
    builder.add_garment(v, f, fabric="cotton")
    model = builder.finalize("cpu", features=Features(self_contact=True, body_contact=False))
    for value in (None, 0.006):
        settings = SimSettings(self_contact_rest_exclusion=value)
        sim = QuasiStaticSimulator(model, None, settings=settings)
        contact = sim.solver.self_contact
        expected = 2.0 * (contact.thickness + contact.margin) if value is None else value
        assert contact.rest_exclusion == pytest.approx(expected)
    with pytest.raises(ValueError, match="self_contact_rest_exclusion"):
        SimSettings(self_contact_rest_exclusion=-1.0)
