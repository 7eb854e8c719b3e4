"""Untangling of cloth that passes through itself (intersection contour minimization,
``simulate.contact.untangle``): crossed layers and a folded sleeve come apart, worlds stay
independent, and the step shortens the intersection contour."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import ClothBuilder, Features
from simulate.contact.untangle import Untangler, crossing_descent, edge_opposite_vertices
from simulate.quality import QualityMeter
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth
from unit_sim import unit_settings

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def _rotation(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def _crossed_layers(lift: float = 0.004) -> tuple[np.ndarray, np.ndarray]:
    """A 20 cm sheet and an 8 cm sheet tilted by 0.4 rad about a diagonal, passed through it along
    a chord (``lift`` [m] above the big sheet at its centre); lift 0.1: apart."""
    lower_v, lower_f = grid_cloth(13, 13, 0.2, 0.2, plane="xz", origin=(-0.1, 0.0, -0.1))
    upper_v, upper_f = grid_cloth(9, 9, 0.08, 0.08, plane="xz", origin=(-0.04, 0.0, -0.04))
    upper_v = upper_v @ _rotation((1.0, 0.0, 1.0), 0.4).T + np.array([0.008, lift, 0.0])
    return np.vstack([lower_v, upper_v]).astype(np.float32), np.vstack([lower_f, upper_f + len(lower_v)])


def _tube(n_around: int, n_along: int, radius: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Open cylinder along x [m]."""
    t = 2.0 * np.pi * np.arange(n_around) / n_around
    xs = np.linspace(-length / 2, length / 2, n_along)
    v = np.stack([np.repeat(xs, n_around), np.tile(radius * np.sin(t), n_along),
                  np.tile(radius * np.cos(t), n_along)], 1)
    faces = []
    for i in range(n_along - 1):
        for j in range(n_around):
            a, b = i * n_around + j, i * n_around + (j + 1) % n_around
            faces += [[a, b, b + n_around], [a, b + n_around, a + n_around]]
    return v.astype(np.float32), np.array(faces, np.int64)


def _model(verts: np.ndarray, faces: np.ndarray, device: str, worlds: int = 1, rest: np.ndarray | None = None):
    builder = ClothBuilder(gravity=(0.0, 0.0, 0.0))
    for _ in range(worlds):
        builder.add_garment(verts if rest is None else rest, faces, fabric="cotton")
    return builder.finalize(device, features=Features(body_contact=False))


def _crossings(meter: QualityMeter, x: np.ndarray) -> int:
    return int(meter.self_intersections(x))


def contour_length(x: np.ndarray, faces: np.ndarray) -> float:
    """Total length [m] of the intersection contours, brute force in float64: every edge-triangle
    crossing (edge not touching the triangle) ends a segment of each triangle pair (triangle
    beside the edge, pierced triangle); a pair's segment joins its two ends."""
    x = np.asarray(x, np.float64)
    faces = np.asarray(faces, np.int64)
    edges, _ = edge_opposite_vertices(faces)
    p, q = x[edges[:, 0]][:, None], x[edges[:, 1]][:, None]
    a, b, c = (x[faces[:, k]][None] for k in range(3))
    n = np.cross(b - a, c - a)
    sp = np.einsum("efk,efk->ef", n, p - a)
    sq = np.einsum("efk,efk->ef", n, q - a)

    def orient(u, v, w, z):
        return np.einsum("efk,efk->ef", np.cross(v - u, w - u), z - u)

    u, v, w = orient(p, q, a, b), orient(p, q, b, c), orient(p, q, c, a)
    touch = (edges[:, :1, None] == faces[None]).any(-1) | (edges[:, 1:, None] == faces[None]).any(-1)
    hit = (sp * sq < 0) & (((u >= 0) & (v >= 0) & (w >= 0)) | ((u <= 0) & (v <= 0) & (w <= 0))) & ~touch
    ei, fi = np.nonzero(hit)
    s = np.abs(sp[ei, fi]) / (np.abs(sp[ei, fi]) + np.abs(sq[ei, fi]))
    points = x[edges[ei, 0]] + (x[edges[ei, 1]] - x[edges[ei, 0]]) * s[:, None]
    beside: dict[tuple[int, int], list[int]] = {}
    for t, f in enumerate(faces):
        for k in range(3):
            beside.setdefault(tuple(sorted((int(f[k]), int(f[(k + 1) % 3])))), []).append(t)
    ends: dict[tuple[int, int], list[np.ndarray]] = {}
    for e, f, pt in zip(ei, fi, points):
        for g in beside[tuple(int(i) for i in edges[e])]:
            ends.setdefault((min(g, int(f)), max(g, int(f))), []).append(pt)
    return float(sum(np.linalg.norm(v[0] - v[1]) for v in ends.values() if len(v) == 2))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solver,every", [("xpbd", 1), ("vbd", 1), ("xpbd", 5)])
def test_crossed_layers_are_untangled(device: str, solver: str, every: int) -> None:
    """A small sheet passed through a big one along a chord, no gravity: with untangling on (on
    every substep, or every 5th), the solver's steps bring the crossings to 0 within 8 frames;
    without, they stay."""
    verts, faces = _crossed_layers()
    meter = QualityMeter(faces, verts, faces[:1], 3, device=device)
    before = _crossings(meter, verts)
    assert before > 10
    counts = {}
    for untangle in (True, False):
        model = _model(verts, faces, device)
        sim = QuasiStaticSimulator(model, None, solver=solver, settings=unit_settings(substeps=10, iterations=5),
                                   solver_options={"untangle": {"every": every} if untangle else False})
        if untangle:
            assert sim.solver.untangler.every == every
        counts[untangle] = []
        for _ in range(8):
            sim.step_frame()
            counts[untangle].append(_crossings(meter, sim.positions()))
            if counts[untangle][-1] == 0:
                break
    assert counts[True][-1] == 0, counts[True]
    assert min(counts[False]) > 10, counts[False]


@pytest.mark.parametrize("device", DEVICES)
def test_folded_sleeve_is_untangled(device: str) -> None:
    """A sleeve (tube, 8 cm across, 30 cm long) lying flattened, its upper layer dented 2 cm down
    through the lower one (3 closed contours, 144 crossing edges; the dent stretches edges by up to
    34 %): XPBD with untangling clears every crossing within 3 frames, no edge then stretched or
    shrunk more than the dent did, and 10 frames later every edge is within 5 % of its rest length
    with still no crossing."""
    tube, faces = _tube(24, 19, 0.04, 0.3)
    rest = tube * np.array([1.0, 0.15, 1.0], np.float32)  # flattened: the layers 12 mm apart
    dented = rest.copy()
    upper = dented[:, 1] > 0.0
    dent = 0.02 * np.exp(-(dented[:, 0] / 0.04) ** 2 - (dented[:, 2] / 0.03) ** 2)
    dented[upper, 1] -= dent[upper]
    meter = QualityMeter(faces, rest, faces[:1], 3, device=device)
    assert _crossings(meter, rest) == 0
    assert _crossings(meter, dented) > 100
    assert meter.self_intersection_contours(dented[None])[0] >= 1
    edges, _ = edge_opposite_vertices(faces)

    def strain(x: np.ndarray) -> float:
        length = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
        return float(np.abs(length / np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1) - 1.0).max())

    model = _model(dented, faces, device, rest=rest)
    sim = QuasiStaticSimulator(model, None, solver="xpbd", settings=unit_settings(substeps=10, iterations=5),
                               solver_options={"untangle": True})
    sim.state_0.particle_q.assign(dented)
    counts = []
    for _ in range(3):
        sim.step_frame()
        counts.append(_crossings(meter, sim.positions()))
        if counts[-1] == 0:
            break
    assert counts[-1] == 0, counts
    assert strain(sim.positions()) <= strain(dented), (strain(sim.positions()), strain(dented))
    for _ in range(10):
        sim.step_frame()
    assert _crossings(meter, sim.positions()) == 0
    assert strain(sim.positions()) < 0.05, strain(sim.positions())


@pytest.mark.parametrize("device", DEVICES)
def test_worlds_without_crossings_or_untangling_are_untouched(device: str) -> None:
    """Three worlds: crossed layers, the same layers apart, crossed layers with
    ``world_self_contact`` off. Untangling steps move only the first (its crossings fall), and
    leave the other two bit for bit as they were; the per-world crossing count says which."""
    crossed, faces = _crossed_layers()
    apart, _ = _crossed_layers(lift=0.1)
    model = _model(crossed, faces, device, worlds=3)
    n = len(crossed)
    x0 = np.concatenate([crossed, apart, crossed])
    x = wp.array(x0, dtype=wp.vec3, device=device)
    control = model.control()
    control.set_self_contact(np.array([True, True, False]))
    untangler = Untangler(model)
    meter = QualityMeter(faces, crossed, faces[:1], 3, device=device)
    before = _crossings(meter, crossed)
    for _ in range(20):
        untangler.apply(x, control.world_active, control.world_self_contact)
    assert untangler.crossings.numpy().tolist()[1:] == [0, 0]
    out = x.numpy().reshape(3, n, 3)
    np.testing.assert_array_equal(out[1], apart)
    np.testing.assert_array_equal(out[2], crossed)
    assert not np.array_equal(out[0], crossed)
    assert _crossings(meter, out[0]) < before


@pytest.mark.parametrize("device", DEVICES)
def test_world_beside_untangling_steps_as_alone(device: str) -> None:
    """A world of layers apart beside a world of crossed layers, XPBD with untangling, steps bit
    for bit as the same world alone without untangling."""
    crossed, faces = _crossed_layers()
    apart, _ = _crossed_layers(lift=0.1)
    runs = {}
    for together in (True, False):
        builder = ClothBuilder(gravity=(0.0, -9.81, 0.0))
        for v in ([crossed, apart] if together else [apart]):
            builder.add_garment(v, faces, fabric="cotton")
        model = builder.finalize(device, features=Features(body_contact=False))
        sim = QuasiStaticSimulator(model, None, solver="xpbd", settings=unit_settings(substeps=5, iterations=5),
                                   solver_options={"untangle": together})
        for _ in range(4):
            sim.step_frame()
        runs[together] = sim.positions().reshape(model.world_count, -1, 3)[-1]
    np.testing.assert_array_equal(runs[True], runs[False])


@wp.kernel
def _descent_kernel(p: wp.vec3, q: wp.vec3, hit: wp.vec3, n: wp.vec3, o: wp.vec3, normal_factor: float,
                    out: wp.array(dtype=wp.vec3)):
    out[0] = crossing_descent(p, q, hit, n, o, normal_factor)


def test_crossing_descent_is_the_contour_segments_steepest_descent() -> None:
    """Edge pq pierces the plane y = 0 at P; the contour segment runs in the plane from P into the
    triangle pqo, to the point Q where edge qo meets the plane. With Q held, the segment's length
    as the edge translates by d has the gradient (central differences, float64) whose opposite is
    ``crossing_descent`` with normal factor 1; with Volino's factor 2 the direction still shortens
    the segment; and the flipped direction lengthens it."""
    p = np.array([0.01, -0.03, 0.02])
    q = np.array([0.03, 0.05, -0.01])
    o = np.array([0.08, 0.04, 0.05])
    n = np.array([0.0, 1.0, 0.0])

    def on_plane(a, b):
        t = a[1] / (a[1] - b[1])
        return a + (b - a) * t

    far = on_plane(q, o)

    def length(d):
        return np.linalg.norm(far - on_plane(p + d, q + d))

    hit = on_plane(p, q)
    h = 1e-6
    grad = np.array([(length(h * np.eye(3)[k]) - length(-h * np.eye(3)[k])) / (2 * h) for k in range(3)])
    out = wp.zeros(1, dtype=wp.vec3, device="cpu")
    results = {}
    for factor in (1.0, 2.0):
        wp.launch(_descent_kernel, dim=1, inputs=[wp.vec3(*p), wp.vec3(*q), wp.vec3(*hit), wp.vec3(*n), wp.vec3(*o),
                                                  factor, out], device="cpu")
        results[factor] = out.numpy()[0].astype(np.float64)
    np.testing.assert_allclose(results[1.0], -grad, rtol=1e-3, atol=1e-4)
    for g in results.values():
        step = 1e-4 * g / np.linalg.norm(g)
        assert length(step) < length(np.zeros(3)) < length(-step)


def test_one_step_shortens_the_contours() -> None:
    """On the crossed layers, one untangling call (0.2 mm steps) shortens the total contour
    length (brute force), with either normal factor."""
    verts, faces = _crossed_layers()
    model = _model(verts, faces, "cpu")
    before = contour_length(verts, faces)
    assert before > 0.02
    for factor in (1.0, 2.0):
        x = wp.array(verts, dtype=wp.vec3, device="cpu")
        Untangler(model, step=0.1, normal_factor=factor).apply(x, model.control().world_active)
        after = contour_length(x.numpy(), faces)
        assert after < before - 1e-4, (factor, before, after)


def test_same_positions_same_result() -> None:
    """Two calls on the same positions give the same positions bit for bit (fixed-point sums)."""
    verts, faces = _crossed_layers()
    model = _model(verts, faces, "cpu")
    untangler = Untangler(model)
    outs = []
    for _ in range(2):
        x = wp.array(verts, dtype=wp.vec3, device="cpu")
        untangler.apply(x, model.control().world_active)
        outs.append(x.numpy().copy())
    np.testing.assert_array_equal(outs[0], outs[1])
    assert np.abs(outs[0] - verts).max() <= untangler.max_step * (1 + 1e-5)


@pytest.mark.parametrize(("options", "field"), [({"step": 0.0}, "step"), ({"step": 2.0}, "step"),
                                                ({"normal_factor": -1.0}, "normal_factor"),
                                                ({"thickness": 0.0}, "thickness"), ({"every": 0}, "every"),
                                                ({"every": 1.5}, "every")])
def test_bad_options_name_the_field(options: dict, field: str) -> None:
    verts, faces = _crossed_layers()
    with pytest.raises(ValueError, match=field):
        Untangler(_model(verts, faces, "cpu"), **options)


@pytest.mark.parametrize("solver", ["xpbd", "vbd"])
def test_bad_untangle_option_names_it(solver: str) -> None:
    verts, faces = _crossed_layers()
    with pytest.raises(ValueError, match="untangle"):
        QuasiStaticSimulator(_model(verts, faces, "cpu"), None, solver=solver, solver_options={"untangle": "yes"})


@pytest.mark.parametrize("self_contact", [True, False])
def test_the_library_untangles_models_with_self_contact_only(self_contact: bool) -> None:
    """``SimSettings`` untangles on every 5th substep where the model has self-contact; a model
    without it gets no Untangler (none of its kernels compile)."""
    from simulate.quasi_static import SimSettings

    verts, faces = _crossed_layers()
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton")
    model = builder.finalize("cpu", features=Features(self_contact=self_contact, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver="xpbd", settings=SimSettings())
    if self_contact:
        assert sim.solver.untangler is not None and sim.solver.untangler.every == 5
    else:
        assert sim.solver.untangler is None


def test_shared_cloth_bvh_gives_the_same_steps() -> None:
    """An untangler on a SelfContact's cloth BVH (``share_mesh_of``) steps as one with a BVH of its
    own, bit for bit, also with the self-contact's searches in between; another model's
    SelfContact is refused."""
    from simulate.contact.self_contact import SelfContact

    crossed, faces = _crossed_layers()
    results = []
    for share in (False, True):
        model = _model(crossed, faces, "cpu", worlds=2)
        contact = SelfContact(model)
        untangler = Untangler(model, share_mesh_of=contact if share else None)
        assert (untangler.mesh is contact.mesh) == share
        x = wp.array(np.concatenate([crossed, crossed + 0.001]), dtype=wp.vec3, device="cpu")
        control = model.control()
        for _ in range(6):
            contact.detect(x, control.world_active)
            untangler.apply(x, control.world_active)
        results.append(x.numpy())
    np.testing.assert_array_equal(results[0], results[1])
    other = _model(crossed, faces, "cpu")
    with pytest.raises(ValueError, match="same model"):
        Untangler(_model(crossed, faces, "cpu"), share_mesh_of=SelfContact(other))
