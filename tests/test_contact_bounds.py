"""Cloth self-contact with displacement bounds (SolverVBD, SolverXPBD): no new intersection, whatever the speed."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from simulate.cloth import ClothBuilder, Features
from simulate.contact import BodyCollider
from simulate.contact.self_contact import MIN_SEPARATION_M
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth, icosphere
from simulate.quality import QualityMeter
from simulate.solvers.vbd.kernels import edge_edge_contact, vertex_triangle_contact
from contact_scenes import folded_sheet_worlds
from unit_sim import unit_settings

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def _layers():
    lower_v, lower_f = grid_cloth(9, 9, 0.4, 0.4, plane="xz", origin=(-0.2, 0.0, -0.2))
    upper_v, upper_f = grid_cloth(7, 7, 0.3, 0.3, plane="xz", origin=(-0.16, 0.03, -0.14))
    return lower_v, np.vstack([lower_v, upper_v]), np.vstack([lower_f, upper_f + len(lower_v)])


def _throw_layer(device: str, solver: str, self_contact_options: dict, velocity: tuple[float, float, float]):
    """The upper layer of ``_layers`` thrown at ``velocity`` [m/s] onto the pinned lower one (5 x 5
    at 1/60 s, damping 2/s) for 20 frames: (upper layer's vertices, crossings per frame)."""
    lower_v, verts, faces = _layers()
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)))
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver=solver, settings=unit_settings(substeps=5, iterations=5, damping=2.0,
                                                                                frame_dt=1.0 / 60.0),
                               solver_options={"self_contact_options": self_contact_options})
    v0 = np.zeros((len(verts), 3), np.float32)
    v0[len(lower_v):] = velocity
    sim.state_0.particle_qd.assign(v0)
    meter = QualityMeter(faces, verts, faces[:1], 3, device=device)
    crossings = []
    for _ in range(20):
        sim.step_frame()
        crossings.append(meter.self_intersections(sim.positions()))
    return sim.positions()[len(lower_v):], crossings


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bounds", [True, False], ids=["bounds", "no-bounds"])
@pytest.mark.parametrize("solver", ["vbd", "xpbd"])
def test_fast_layer_does_not_pass_through(device: str, bounds: bool, solver: str) -> None:
    """A layer thrown at 6 m/s onto a pinned one, 3 cm below: a substep carries it 2 cm, past the
    penalty's reach; the bounds hold it to a fraction of the distance it was searched at, so it
    lands and never crosses (crossings counted every frame); with the penalty alone it passes."""
    upper, crossings = _throw_layer(device, solver, {"bounds": bounds}, (0.0, -6.0, 0.0))
    if bounds:
        assert max(crossings) == 0, f"crossings per frame: {crossings}"
        assert upper[:, 1].min() > 0.0 and upper[:, 1].max() < 0.02, upper[:, 1].min()
    else:
        assert upper[:, 1].min() < -0.05, "the scene must be fast enough to pass without the bounds"


@pytest.mark.parametrize("device", DEVICES)
def test_world_without_self_contact_is_unaffected(device: str) -> None:
    """A world whose self-contact is switched off beside one with it steps bit for bit as the same
    world in a model without self-contact."""
    lower_v, verts, faces = _layers()
    runs = {}
    for on in (True, False):
        builder = ClothBuilder()
        for _ in range(2 if on else 1):
            builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(len(lower_v)))
        model = builder.finalize(device, features=Features(self_contact=on, body_contact=False))
        sim = QuasiStaticSimulator(model, None, solver="vbd", settings=unit_settings(substeps=4, iterations=3))
        if on:
            sim.control.set_self_contact(np.array([True, False]))
        for _ in range(8):
            sim.step_frame()
        runs[on] = sim.positions().reshape(model.world_count, len(verts), 3)
    np.testing.assert_array_equal(runs[True][1], runs[False][0])
    assert not np.array_equal(runs[True][0], runs[False][0]), "self-contact changed nothing in its own world"


@pytest.mark.parametrize("device", DEVICES)
def test_free_layers_bounce_off_each_other_without_crossing(device: str) -> None:
    """Two free layers flying at each other without gravity or damping, bounds off: the pair
    energies alone stop them at the contact distance and send them apart, none crossing."""
    lower_v, lower_f = grid_cloth(6, 6, 0.1, 0.1, plane="xz", origin=(-0.05, 0.0, -0.05))
    upper_v, upper_f = grid_cloth(6, 6, 0.1, 0.1, plane="xz", origin=(-0.047, 0.012, -0.052))
    verts = np.vstack([lower_v, upper_v])
    faces = np.vstack([lower_f, upper_f + len(lower_v)])
    builder = ClothBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_garment(verts, faces, fabric="cotton")
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver="vbd", settings=unit_settings(substeps=10, iterations=5, damping=0.0,
                                                                               frame_dt=1.0 / 60.0),
                               solver_options={"self_contact_options": {"bounds": False}})
    n = len(lower_v)
    v0 = np.zeros((len(verts), 3), np.float32)
    v0[:n, 1] = 0.25
    v0[n:, 1] = -0.25
    sim.state_0.particle_qd.assign(v0)
    meter = QualityMeter(faces, verts, faces[:1], 3, device=device)
    crossings, gaps = [], []
    for _ in range(12):
        sim.step_frame()
        x = sim.positions()
        crossings.append(meter.self_intersections(x))
        gaps.append(float(x[n:, 1].mean() - x[:n, 1].mean()))
    assert max(crossings) == 0, f"crossings per frame: {crossings}"
    assert min(gaps) < 0.004, f"the layers never met: mean gaps {gaps}"
    v = sim.state_0.particle_qd.numpy()[:len(verts)]
    assert v[n:, 1].mean() > 0.1 and v[:n, 1].mean() < -0.1, "the layers must have bounced off each other"


@wp.kernel
def _pair_terms(x: wp.array(dtype=wp.vec3), radius: float, stiffness: float, edge: int,
                force: wp.array(dtype=wp.vec3)):
    k = wp.tid()
    if edge == 0:
        role = k - 1  # particle 0 is the point, 1..3 the triangle's corners
        f, h = vertex_triangle_contact(x[0] - x[k], x[1] - x[k], x[2] - x[k], x[3] - x[k], role, radius, stiffness)
        force[k] = f
    else:
        end = k % 2
        if k < 2:
            f, h = edge_edge_contact(x[0] - x[k], x[1] - x[k], x[2] - x[k], x[3] - x[k], end, radius, stiffness)
        else:
            f, h = edge_edge_contact(x[2] - x[k], x[3] - x[k], x[0] - x[k], x[1] - x[k], end, radius, stiffness)
        force[k] = f


def _pair_energy(x: np.ndarray, radius: float, stiffness: float, edge: bool) -> float:
    if edge:
        s = np.linspace(0.0, 1.0, 301)
        a = x[0] + (x[1] - x[0]) * s[:, None]
        b = x[2] + (x[3] - x[2]) * s[:, None]
        d = np.linalg.norm(a[:, None] - b[None], axis=2).min()
    else:
        u, v = np.meshgrid(np.linspace(0, 1, 241), np.linspace(0, 1, 241))
        keep = (u + v) <= 1.0
        pts = x[1] + (x[2] - x[1]) * u[keep][:, None] + (x[3] - x[1]) * v[keep][:, None]
        d = np.linalg.norm(pts - x[0], axis=1).min()
    return 0.5 * stiffness * max(radius - d, 0.0) ** 2


@pytest.mark.parametrize("edge", [False, True], ids=["vertex-triangle", "edge-edge"])
def test_contact_pair_forces_are_the_energy_gradient_and_sum_to_zero(edge: bool) -> None:
    """Each pair's force on each of its four particles is minus the gradient of its contact energy
    (central differences of a brute-force distance), and the four forces cancel: the pair pushes
    both sides, equal and opposite."""
    rng = np.random.default_rng(3)
    radius, stiffness = 0.004, 1.0e4
    tested = 0
    while tested < 6:
        x = rng.normal(scale=0.004, size=(4, 3)).astype(np.float32)
        if _pair_energy(x, radius, stiffness, edge) < 1.0e-6:
            continue
        out = wp.zeros(4, dtype=wp.vec3, device="cpu")
        wp.launch(_pair_terms, dim=4, inputs=[wp.array(x, dtype=wp.vec3, device="cpu"), radius, stiffness, int(edge)],
                  outputs=[out], device="cpu")
        forces = out.numpy()
        np.testing.assert_allclose(forces.sum(axis=0), 0.0, atol=1.0e-3 * np.abs(forces).max())
        h = 2.0e-5
        for k in range(4):
            grad = np.zeros(3)
            for c in range(3):
                xp = x.astype(np.float64).copy()
                xm = xp.copy()
                xp[k, c] += h
                xm[k, c] -= h
                grad[c] = (_pair_energy(xp, radius, stiffness, edge) - _pair_energy(xm, radius, stiffness, edge)) / (2 * h)
            np.testing.assert_allclose(forces[k], -grad, atol=0.05 * np.abs(forces).max() + 1e-4)
        tested += 1


def _stacked_layers(gap: float):
    """A 5 x 5 patch (8 cm) ``gap`` [m] above a pinned 60 x 20 cm sheet: (rest vertices, faces, sheet count)."""
    lower_v, lower_f = grid_cloth(13, 5, 0.6, 0.2, plane="xz", origin=(-0.3, 0.0, -0.1))
    upper_v, upper_f = grid_cloth(5, 5, 0.08, 0.08, plane="xz", origin=(-0.2, gap, -0.04))
    return np.vstack([lower_v, upper_v]), np.vstack([lower_f, upper_f + len(lower_v)]), len(lower_v)


def _launch_patch(device: str, gap: float, velocity: tuple[float, float, float], directional: bool,
                  frames: int = 3) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """The patch thrown at ``velocity`` [m/s] over the sheet (no gravity, no damping, VBD 5 x 3 at
    1/60 s) after a frame at rest (the first search has no pairs to take bound normals from):
    (patch vertices before the throw, after ``frames`` frames, crossings per frame)."""
    verts, faces, n = _stacked_layers(gap)
    builder = ClothBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_garment(verts, faces, fabric="cotton", pinned=np.arange(n))
    model = builder.finalize(device, features=Features(self_contact=True, body_contact=False))
    sim = QuasiStaticSimulator(model, None, solver="vbd",
                               settings=unit_settings(substeps=5, iterations=3, damping=0.0, frame_dt=1.0 / 60.0),
                               solver_options={"self_contact_options": {"directional_bounds": directional}})
    sim.step_frame()
    start = sim.positions()[n:]
    v0 = np.zeros((len(verts), 3), np.float32)
    v0[n:] = velocity
    sim.state_0.particle_qd.assign(v0)
    meter = QualityMeter(faces, verts, faces[:1], 3, device=device)
    crossings = []
    for _ in range(frames):
        sim.step_frame()
        crossings.append(meter.self_intersections(sim.positions()))
    return start, sim.positions()[n:], crossings


@pytest.mark.parametrize("device", DEVICES)
def test_directional_bounds_let_a_layer_slide_over_another(device: str) -> None:
    """A patch sliding at 0.6 m/s over a pinned sheet 3 mm below it: a substep carries it 2 mm,
    more than its ball bound (0.45 x the gap, 1.3 mm), so the ball holds it back; its half-space
    bound (along the normal away from the sheet) does not limit sliding, and it keeps its speed.
    Neither passes through the sheet."""
    travel = {}
    for directional in (False, True):
        rest, x, crossings = _launch_patch(device, 0.003, (0.6, 0.0, 0.0), directional)
        assert max(crossings) == 0, f"directional={directional}: crossings per frame {crossings}"
        assert x[:, 1].min() > 0.0, f"directional={directional}: the patch went below the sheet"
        travel[directional] = float(np.mean(x[:, 0] - rest[:, 0]))
    _, again, _ = _launch_patch(device, 0.003, (0.6, 0.0, 0.0), True)
    np.testing.assert_array_equal(again, x, err_msg="the same run twice must give the same positions")
    free = 0.6 * 3.0 / 60.0
    assert travel[False] < 0.75 * free, f"the ball should hold the patch back: {travel}, free {free}"
    assert travel[True] > 0.9 * free, f"the directional bound should let it slide: {travel}, free {free}"


@pytest.mark.parametrize("device", DEVICES)
def test_directional_bounds_let_pressed_layers_part(device: str) -> None:
    """A patch 0.2 mm above the sheet (pressed) leaving it at 0.3 m/s: its ball (0.45 x its gap
    less 0.1 mm) keeps it within micrometres of the sheet, its half-space bound lets it go."""
    rise = {}
    for directional in (False, True):
        rest, x, crossings = _launch_patch(device, 2.0e-4, (0.0, 0.3, 0.0), directional)
        assert max(crossings) == 0
        rise[directional] = float(np.mean(x[:, 1] - rest[:, 1]))
    assert rise[False] < 1.0e-3, f"the ball should pin the pressed patch: {rise}"
    assert rise[True] > 0.8 * 0.3 * 3.0 / 60.0, f"the directional bound should let it part: {rise}"


REFRESHED = {"search_every": 5, "skin": 2.0e-3}
"""Self-contact options: a BVH search on every 5th substep, the lists refreshed in between."""


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("lists", [{}, REFRESHED], ids=["searched", "refreshed"])
def test_directional_bounds_stop_a_fast_layer(device: str, lists: dict) -> None:
    """The fast-layer scene of ``test_fast_layer_does_not_pass_through`` with directional bounds:
    the patch thrown at the sheet lands on it and never crosses it, also with one search per
    frame (5 substeps) and the lists refreshed in between."""
    upper, crossings = _throw_layer(device, "vbd", {"directional_bounds": True, **lists}, (1.5, -6.0, 0.0))
    assert max(crossings) == 0, f"crossings per frame: {crossings}"
    assert upper[:, 1].min() > 0.0


def _layer_gap(x: np.ndarray, faces: np.ndarray, lower_faces: int, lower_count: int) -> float:
    """Smallest distance [m] from the upper layer's vertices to the lower layer's triangles."""
    import trimesh

    tri = x[faces[:lower_faces]]
    points = x[lower_count:]
    closest = trimesh.triangles.closest_point(np.repeat(tri, len(points), axis=0), np.tile(points, (len(tri), 1)))
    return float(np.linalg.norm(closest - np.tile(points, (len(tri), 1)), axis=1).min())


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("lists", [{}, REFRESHED], ids=["searched", "refreshed"])
def test_directional_bounds_keep_squeezed_layers_apart(device: str, lists: dict) -> None:
    """Two 6 cm patches between a torso sphere and an arm sphere that sinks 15 mm into it, each
    patch meeting only its own sphere (primary parts): the skins squeeze the layers together, the
    bounds win, and the gap settles at the bounds' separation (0.1 mm) instead of closing by a
    share of itself search after search (to float32's resolution, ~0.2 um, and through); also
    with two searches per frame and the lists refreshed in between."""
    torso_r, arm_r = 0.15, 0.06
    tv, tf = icosphere(torso_r, subdivisions=4)
    av, af = icosphere(arm_r, subdivisions=4)
    faces = np.concatenate([tf, af + len(tv)])
    groups = [np.arange(len(tf)), np.arange(len(tf), len(tf) + len(af))]
    lower_v, lower_f = grid_cloth(7, 7, 0.06, 0.06, plane="xz", origin=(-0.03, torso_r + 0.002, -0.03))
    upper_v, upper_f = grid_cloth(7, 7, 0.06, 0.06, plane="xz", origin=(-0.03, torso_r + 0.006, -0.03))
    n = len(lower_v)
    verts = np.vstack([lower_v, upper_v])
    cloth_faces = np.vstack([lower_f, upper_f + n])
    builder = ClothBuilder()
    builder.add_garment(verts, cloth_faces, fabric="cotton",
                        body_part=np.r_[np.zeros(n, np.int32), np.ones(len(upper_v), np.int32)])
    model = builder.finalize(device, features=Features(self_contact=True, friction=False))
    arm_y = torso_r + 0.008 + arm_r
    collider = BodyCollider(np.concatenate([tv, av + [0.0, arm_y, 0.0]]), faces, device=device, face_groups=groups)
    sim = QuasiStaticSimulator(model, collider, solver="vbd",
                               settings=unit_settings(substeps=10, iterations=3, damping=20.0, frame_dt=1.0 / 45.0),
                               solver_options={"self_contact_options": {"directional_bounds": True, **lists}})
    meter = QualityMeter(cloth_faces, verts, cloth_faces[:1], 3, device=device)
    gaps, crossings = [], []
    for k in range(30):
        sim.set_body_target(np.concatenate([tv, av + [0.0, arm_y - 0.001 * min(k, 15), 0.0]]))
        sim.step_frame()
        x = sim.positions()
        gaps.append(_layer_gap(x, cloth_faces, len(lower_f), n))
        crossings.append(meter.self_intersections(x))
    assert max(crossings) == 0, f"crossings per frame: {crossings}"
    assert min(gaps[10:]) < 2.0 * MIN_SEPARATION_M, f"the skins should squeeze the layers: gaps {gaps}"
    assert min(gaps) > 0.5 * MIN_SEPARATION_M, f"squeezed layers closed below the bounds' separation: {gaps}"


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return a + t * (b - a)


def _point_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Point of triangle abc closest to p: the plane's foot where inside, else the nearest edge point."""
    n = np.cross(b - a, c - a)
    q = p - np.dot(p - a, n) / np.dot(n, n) * n
    if all(np.dot(np.cross(v - u, q - u), n) >= 0.0 for u, v in ((a, b), (b, c), (c, a))):
        return q
    return min((_point_segment(p, u, v) for u, v in ((a, b), (b, c), (c, a))), key=lambda x: np.linalg.norm(p - x))


def _segments(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of segments p1q1 and p2q2: the interior solution where both parameters fall
    inside, else the nearest of the four end-to-segment pairs."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, b = d1 @ d1, d2 @ d2, d1 @ d2
    options = [(x, _point_segment(x, p2, q2)) for x in (p1, q1)] + [(_point_segment(y, p1, q1), y) for y in (p2, q2)]
    denom = a * e - b * b
    if denom > 1e-12 * a * e:
        s = (b * (d2 @ r) - (d1 @ r) * e) / denom
        t = (a * (d2 @ r) - b * (d1 @ r)) / denom
        if 0.0 < s < 1.0 and 0.0 < t < 1.0:
            options.append((p1 + s * d1, p2 + t * d2))
    return min(options, key=lambda pq: np.linalg.norm(pq[0] - pq[1]))


def _certificate(own: np.ndarray, other: np.ndarray, raw: np.ndarray, closest: tuple[np.ndarray, np.ndarray]):
    """(m from ``own``'s side, s, margins to the rule's thresholds) of a pair (module docstring)."""
    d = np.linalg.norm(closest[0] - closest[1])
    m, sep, margin = None, 0.0, abs(np.linalg.norm(raw) - 0.5)
    if np.linalg.norm(raw) > 0.5:
        m = raw / np.linalg.norm(raw)
        sep = min(own @ m) - max(other @ m)
        margin = min(margin, abs(sep - 0.5 * d))
    if m is None or sep < 0.5 * d:
        m, sep = (closest[0] - closest[1]) / d, d
    return m, sep, margin


@pytest.mark.parametrize("directional", [True, False], ids=["directional", "ball"])
def test_bounds_match_brute_force(directional: bool) -> None:
    """Every particle's bounds after a search are those of every vertex-triangle pair (the particle
    as the point or a corner) and every edge-edge pair (as an end) within the reach, by brute force
    in float64: the ball's smallest distance, or each pair's certificate into the half-space or
    the ball by its direction (module docstring of ``simulate.contact.self_contact``). A sheet
    folded onto itself 3 mm apart with jitter, in two worlds (one shifted), so the pairs fall at
    every distance and direction. Particles with a pair within float32 rounding of a threshold of
    the rules are left out (a handful)."""
    from simulate.contact.self_contact import SelfContact

    model, x = folded_sheet_worlds(seed=5, jitter=6e-4)
    contact = SelfContact(model, pairs=True, directional_bounds=directional)
    xw = wp.array(x, dtype=wp.vec3, device="cpu")
    for _ in range(2):  # the second search takes its bound normals from the first one's pairs
        contact.detect(xw, model.control().world_active)
    normal = contact.bound_normal.numpy().astype(np.float64)
    x = x.astype(np.float64)
    tri = model.tri_indices.numpy()
    pworld = model.particle_world.numpy()
    edges = contact.edges.numpy()
    reach = contact.thickness + contact.margin
    cone = contact.cone_cos
    n = model.particle_count
    side, ball, d_min = np.full(n, reach), np.full(n, reach), np.full(n, reach)
    fragile = np.zeros(n, bool)
    pairs = 0

    def bound(particles, m_own, sep, margin, d):
        for j, sign in particles:
            near_cone = abs(sign * m_own @ normal[j] - cone) < 1e-4
            if abs(d - reach) < 1e-6 or (directional and (margin < 1e-6 or near_cone)):
                fragile[j] = True
            if d >= reach:
                continue
            d_min[j] = min(d_min[j], d)
            if sign * m_own @ normal[j] >= cone:
                side[j] = min(side[j], sep)
            else:
                ball[j] = min(ball[j], sep)

    for i in range(n):
        for a, b, c in tri:
            if pworld[a] != pworld[i] or i in (a, b, c):
                continue
            foot = _point_triangle(x[i], x[a], x[b], x[c])
            d = np.linalg.norm(x[i] - foot)
            if d >= reach + 1e-6:
                continue
            pairs += 1
            m, sep, margin = _certificate(x[[i]], x[[a, b, c]], normal[i] - normal[a] - normal[b] - normal[c],
                                          (x[i], foot))
            bound([(i, 1.0), (a, -1.0), (b, -1.0), (c, -1.0)], m, sep, margin, d)
    for e, (i0, i1) in enumerate(edges):
        for g in range(e + 1, len(edges)):
            a, b = edges[g]
            if pworld[a] != pworld[i0] or len({i0, i1, a, b}) < 4:
                continue
            cl = _segments(x[i0], x[i1], x[a], x[b])
            d = np.linalg.norm(cl[0] - cl[1])
            if d >= reach + 1e-6:
                continue
            pairs += 1
            m, sep, margin = _certificate(x[[i0, i1]], x[[a, b]], normal[i0] + normal[i1] - normal[a] - normal[b], cl)
            bound([(i0, 1.0), (i1, 1.0), (a, -1.0), (b, -1.0)], m, sep, margin, d)
    assert pairs > 1000 and (side < reach).sum() > n // 4 if directional else pairs > 1000
    keep = ~fragile
    assert keep.sum() > 0.9 * n, f"{fragile.sum()} of {n} particles near a threshold"
    if directional:
        np.testing.assert_allclose(contact.d_side.numpy()[keep], side[keep], rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(contact.d_ball.numpy()[keep], ball[keep], rtol=1e-4, atol=1e-7)
    else:
        np.testing.assert_allclose(contact.d_min.numpy()[keep], d_min[keep], rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("directional", [True, False], ids=["directional", "ball"])
def test_refreshed_bounds_are_never_wider_than_a_search(directional: bool) -> None:
    """A refresh of the pair lists (``SelfContact.detect(refresh=True)``: no BVH query in worlds
    that moved less than half the skin) bounds every particle at least as tightly as a search at
    the same positions would: the listed pairs as the search, the pairs the lists left out (one
    per primitive here, so most are) by their distance at the search less twice the world's
    largest displacement since. Right after the search, a refresh gives the search's ball bounds
    exactly. Then the folded half of the second world is pressed 1.5 mm down (the pairs there
    close by half) and both worlds jittered, both within half the 4 mm skin: a refresh without
    the displacement term, or without the left-out pairs, would bound some particle wider than
    the search does. Pressed 1 mm further, the second world searches again and its bounds are
    the search's."""
    from simulate.contact.self_contact import SelfContact

    model, x0 = folded_sheet_worlds(seed=7, jitter=6e-4)
    n = len(x0) // 2
    x1 = x0 + np.random.default_rng(3).normal(0.0, 2.0e-4, x0.shape).astype(np.float32)
    x1[n:][x0[n:, 1] > 0.0015, 1] -= 0.0015
    x2 = x1.copy()
    x2[n:][x0[n:, 1] > 0.0015, 1] -= 0.001
    active = model.control().world_active
    opts = {"pairs": True, "directional_bounds": directional, "pairs_per_primitive": 1, "skin": 4.0e-3}

    def searched_at_x0():
        contact = SelfContact(model, **opts)
        for _ in range(2):  # the second search takes its bound normals from the first one's pairs
            contact.detect(wp.array(x0, dtype=wp.vec3, device="cpu"), active)
        return contact

    refreshed = searched_at_x0()
    reach = refreshed.thickness + refreshed.margin
    assert (refreshed.horizon.numpy() < reach).sum() > 20, "the lists must leave pairs within the reach out"
    if not directional:
        at_search = refreshed.d_min.numpy().copy()
        refreshed.detect(wp.array(x0, dtype=wp.vec3, device="cpu"), active, refresh=True)
        np.testing.assert_array_equal(refreshed.world_search.numpy(), [0, 0])
        np.testing.assert_array_equal(refreshed.d_min.numpy(), at_search)

    def bounds(contact):
        if directional:
            return np.minimum(contact.d_side.numpy(), contact.d_ball.numpy()), contact.d_ball.numpy()
        return contact.d_min.numpy(), contact.d_min.numpy()

    for x, searching in ((x1, [0, 0]), (x2, [0, 1])):
        refreshed.detect(wp.array(x, dtype=wp.vec3, device="cpu"), active, refresh=True)
        searched = searched_at_x0()  # the same lists, so the same bound normals at x
        searched.detect(wp.array(x, dtype=wp.vec3, device="cpu"), active)
        np.testing.assert_array_equal(refreshed.world_search.numpy(), searching)
        (r, r_ball), (s, s_ball) = bounds(refreshed), bounds(searched)
        assert (r <= s + 1e-7).all(), f"a refreshed bound is wider than the search's by {np.max(r - s)} m"
        assert (r_ball <= s_ball + 1e-7).all(), f"a refreshed ball is wider than the search's by {np.max(r_ball - s_ball)} m"
        assert (s < reach).sum() > n
        assert np.median(r[:n] / s[:n]) > 0.3, "where little moved, the refresh should keep most of the search's bounds"
    moved = refreshed.world_moved.numpy()
    assert 2.0e-3 > moved[0] > 5.0e-4 and moved[1] > 2.0e-3, moved
    np.testing.assert_array_equal(r[n:], s[n:], err_msg="the world that searched again has the search's bounds")
    detects = 5 if not directional else 4  # two searches at x0, (a refresh at x0,) x1, x2
    np.testing.assert_array_equal(refreshed.search_counts.numpy(), [[detects, 2], [detects, 3]])
