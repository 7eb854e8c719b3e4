"""Cloth grain: warp and weft material frames from the pattern (UV panels) or a grain axis,
independent of the order in which a face lists its corners, and orthotropic fabrics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from simulate.cloth import FABRICS, ClothBuilder, Fabric, Features
from simulate.cloth.builder import material_directions, triangle_rest_frames
from simulate.quasi_static import QuasiStaticSimulator, WorldStatus
from simulate.scenes import grid_cloth, tube_cloth
from unit_sim import unit_settings

wp.init()

GRAVITY = 9.81
RTOL_STRIP = 0.01
"""Hanging strip: relative error of the extension against rho g L^2 / (2 Y) (as the oracle test)."""
RTOL_ROLLED = 1.0e-3
"""Hanging strip: relative difference of the extension when every face's corners are rolled
(the frames are the same up to float rounding; measured equal to 1e-7)."""
RTOL_ENERGY_ROLLED = 1.0e-5
"""Triangle energies from the model's float32 rest frames, rolled corners against not."""
ATOL_REST_F = 1.0e-6
"""At rest the deformation gradient's columns are the unit warp and weft (float32 dm_inv)."""


def _uv_of(vertices: np.ndarray, faces: np.ndarray, u_axis: np.ndarray, v_axis: np.ndarray) -> np.ndarray:
    """Per-corner UVs (F, 3, 2) of a planar pattern whose u and v run along the given 3-D axes."""
    corners = vertices[faces]  # (F, 3, 3)
    return np.stack([corners @ u_axis, corners @ v_axis], axis=-1)


def _tube_uv(vertices: np.ndarray, faces: np.ndarray, radius: float) -> np.ndarray:
    """Per-corner UVs of a tube along y unrolled around its axis (u = arc length, v = y), with the
    seam's faces unwrapped so that no UV triangle spans the cut."""
    theta = np.arctan2(vertices[:, 2], vertices[:, 0])[faces]  # (F, 3)
    wrap = theta.max(axis=1, keepdims=True) - theta > np.pi
    theta = np.where(wrap, theta + 2.0 * np.pi, theta)
    return np.stack([-radius * theta, vertices[faces][..., 1]], axis=-1)


def _triangle_energies(model, x: np.ndarray) -> dict[tuple[int, ...], float]:
    """Per triangle (keyed by its sorted corners), the membrane energy [J] at positions ``x`` from the
    model's rest frames and compliances (the energy of simulate/cloth/fabric.py)."""
    tri = model.tri_indices.numpy()[:model.tri_count]
    dm_inv = model.tri_dm_inv.numpy()[:model.tri_count].astype(np.float64)
    comp = model.tri_compliance.numpy()[:model.tri_count].astype(np.float64)
    ds = np.stack([x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]], axis=2)  # (F, 3, 2)
    f = ds @ dm_inv
    f1, f2 = f[:, :, 0], f[:, :, 1]
    energy = 0.5 * ((np.linalg.norm(f1, axis=1) - 1.0) ** 2 / comp[:, 0]
                    + (np.linalg.norm(f2, axis=1) - 1.0) ** 2 / comp[:, 1]
                    + np.einsum("ij,ij->i", f1, f2) ** 2 / comp[:, 2])
    return {tuple(sorted(t)): e for t, e in zip(tri.tolist(), energy)}


def test_rest_frame_is_warp_and_weft_whatever_corner_comes_first() -> None:
    """dm_inv maps the rest edges to the unit warp and weft, the warp is the pattern's vertical
    (a line of constant u, v increasing), and rolling a face's corners (with its UVs) changes
    dm_inv only by float rounding."""
    rng = np.random.default_rng(3)
    verts = rng.normal(size=(60, 3))
    faces = np.arange(60).reshape(20, 3)
    uv = rng.normal(size=(20, 3, 2))
    for material_uv in (uv, None):
        warp, weft, normal = material_directions(verts, faces, material_uv=material_uv)
        dm_inv, area = triangle_rest_frames(verts, faces, material_uv=material_uv)
        ds = np.stack([verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]]], axis=2)
        rest_f = ds @ dm_inv
        assert np.allclose(rest_f[:, :, 0], warp, atol=1e-12) and np.allclose(rest_f[:, :, 1], weft, atol=1e-12)
        assert np.allclose(np.cross(warp, weft), normal, atol=1e-12), "warp x weft is not the face normal"
        for shift in (1, 2):
            rolled = np.roll(faces, shift, axis=1)
            rolled_uv = None if material_uv is None else np.roll(material_uv, shift, axis=1)
            dm_rolled, area_rolled = triangle_rest_frames(verts, rolled, material_uv=rolled_uv)
            ds_rolled = np.stack([verts[rolled[:, 1]] - verts[rolled[:, 0]], verts[rolled[:, 2]] - verts[rolled[:, 0]]],
                                 axis=2)
            assert np.allclose(ds_rolled @ dm_rolled, rest_f, atol=1e-12), f"roll {shift} changed the frame"
            assert np.allclose(area_rolled, area)
    # The warp is d x / d v: moving along it changes v and not u.
    warp, _, _ = material_directions(verts, faces, material_uv=uv)
    for f in range(len(faces)):
        edges = np.stack([verts[faces[f, 1]] - verts[faces[f, 0]], verts[faces[f, 2]] - verts[faces[f, 0]]], axis=1)
        duv = np.stack([uv[f, 1] - uv[f, 0], uv[f, 2] - uv[f, 0]], axis=1)
        coeff = np.linalg.lstsq(edges, warp[f], rcond=None)[0]  # warp in edge coordinates
        du, dv = duv @ coeff
        assert abs(du) < 1e-9 * abs(dv) and dv > 0.0, f"face {f}: warp moves (du, dv) = ({du}, {dv}) in UV"


def test_grain_axis_fallback() -> None:
    """Without UVs the warp is the grain axis (+y) projected into each triangle, x where the
    triangle is horizontal; a degenerate UV triangle falls back to the grain too."""
    vertical, vfaces = grid_cloth(3, 3, 0.2, 0.2, plane="xy")
    warp, _, _ = material_directions(vertical, vfaces)
    assert np.allclose(warp, [0.0, 1.0, 0.0])
    flat, ffaces = grid_cloth(3, 3, 0.2, 0.2, plane="xz")
    warp, _, _ = material_directions(flat, ffaces)
    assert np.allclose(warp, [1.0, 0.0, 0.0]), "a horizontal cloth's warp falls back to x"
    tilted = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.5, 1.0]])
    warp, _, normal = material_directions(tilted, np.array([[0, 1, 2]]))
    up = np.array([0.0, 1.0, 0.0]) - normal[0, 1] * normal[0]
    assert np.allclose(warp[0], up / np.linalg.norm(up))
    warp, _, _ = material_directions(tilted, np.array([[0, 1, 2]]), grain_axis=(1.0, 0.0, 0.0))
    assert np.allclose(warp[0], [1.0, 0.0, 0.0])
    zero_uv = np.zeros((len(vfaces), 3, 2))
    warp, _, _ = material_directions(vertical, vfaces, material_uv=zero_uv, grain_axis=(1.0, 0.0, 0.0))
    assert np.allclose(warp, [1.0, 0.0, 0.0]), "degenerate UV triangles take the grain axis"


@pytest.mark.parametrize("with_uv", [True, False])
def test_energies_do_not_depend_on_face_corner_order(with_uv: bool) -> None:
    """A deformed tube stores the same energy per triangle whichever corner each face lists first
    (with the tube's unrolled UVs and with the default grain). A frame along each face's first
    edge would change the energies of sheared triangles by O(1)."""
    radius = 0.15
    verts, faces = tube_cloth(12, 6, radius, 0.4)
    uv = _tube_uv(verts, faces, radius) if with_uv else None
    rng = np.random.default_rng(5)
    x = verts + 0.01 * rng.normal(size=verts.shape)
    x[:, 1] *= 1.05  # stretched along the warp
    fabric = dataclasses.replace(FABRICS["cotton"], name="grain test")
    energies = []
    for shift in (0, 1, 2):
        builder = ClothBuilder()
        builder.add_garment(verts, np.roll(faces, shift, axis=1), fabric=fabric,
                            material_uv=None if uv is None else np.roll(uv, shift, axis=1))
        energies.append(_triangle_energies(builder.finalize("cpu"), x))
    for shift in (1, 2):
        assert energies[shift].keys() == energies[0].keys()
        for key, value in energies[0].items():
            assert abs(energies[shift][key] - value) <= RTOL_ENERGY_ROLLED * value + 1e-12, (
                f"roll {shift}: triangle {key} energy {energies[shift][key]:.6e} vs {value:.6e} J")


def _hang_strip(fabric: Fabric, *, length: float, width: float, rows: int, roll: int = 0, solver: str = "mass_spring",
                material_uv=None, grain_axis=(0.0, 1.0, 0.0)) -> tuple[float, int]:
    """Extension [m] of a vertical strip (pinned along its top edge) at rest, and its status."""
    verts, faces = grid_cloth(2, rows + 1, width, length, plane="xy", origin=(0.0, 1.0, 0.0))
    uv = None
    if material_uv is not None:
        uv = np.roll(material_uv(verts, faces), roll, axis=1)
    builder = ClothBuilder()
    builder.add_garment(verts, np.roll(faces, roll, axis=1), fabric=fabric, pinned=[0, 1], material_uv=uv,
                        grain_axis=grain_axis)
    model = builder.finalize("cpu", features=Features(body_contact=False, bending=False))
    if solver == "xpbd":  # as the strip oracle (tests/test_cloth_oracles.py)
        settings = unit_settings(substeps=10, iterations=10, damping=5.0, tolerance=1e-4, max_frames=2000)
    else:  # heavy damping settles the explicit solver in ~50 frames; its speed floor is ~1e-3 m/s
        settings = unit_settings(substeps=None, damping=20.0, tolerance=2e-3, max_frames=400)
    sim = QuasiStaticSimulator(model, None, solver=solver, settings=settings)
    status = sim.relax()
    q = sim.positions()
    return float((verts[-2:, 1] - q[-2:, 1]).mean()), int(status[0])


@pytest.mark.parametrize("stretch", [3.0e3, 30.0])
def test_hanging_strip_extension_does_not_depend_on_face_corner_order(stretch: float) -> None:
    """A 1 m x 5 cm strip (shear stiffness 30 N/m) stretches by rho g L^2 / (2 Y) whichever corner
    each face lists first. With a frame along each face's first edge, rolling every face's
    corners would change the extension 24x at Y = 3000 N/m and by 27 % at Y = 30 N/m (the
    diagonal edges put the strip's weight on the shear term)."""
    fabric = Fabric("strip", density=0.18, stretch_stiffness=stretch, shear_stiffness=30.0, bending_stiffness=0.0,
                    damping=0.0, friction=0.0, thickness=1.0e-3)
    length = 1.0
    expected = fabric.density * GRAVITY * length ** 2 / (2.0 * stretch)
    ext = {}
    for roll in (0, 1, 2):
        ext[roll], status = _hang_strip(fabric, length=length, width=0.05, rows=20, roll=roll)
        assert status == WorldStatus.CONVERGED, f"roll {roll}: {WorldStatus(status).name}"
    assert abs(ext[0] - expected) <= RTOL_STRIP * expected, (
        f"extension {ext[0] * 1e3:.4f} mm vs rho g L^2/(2Y) = {expected * 1e3:.4f} mm")
    for roll in (1, 2):
        assert abs(ext[roll] - ext[0]) <= RTOL_ROLLED * ext[0], (
            f"roll {roll}: extension {ext[roll] * 1e3:.4f} mm vs {ext[0] * 1e3:.4f} mm unrolled")


ORTHOTROPIC = Fabric("orthotropic", density=0.2, stretch_stiffness=20.0, shear_stiffness=5.0, bending_stiffness=0.0,
                     damping=0.0, friction=0.0, thickness=1.0e-3, weft_stiffness=8.0)


@pytest.mark.parametrize("solver", ["xpbd", "mass_spring"])
@pytest.mark.parametrize("cut", ["uv", "grain_axis"])
def test_orthotropic_strip_stretches_by_its_warp_or_weft_stiffness(solver: str, cut: str) -> None:
    """A strip cut along the warp hangs rho g L^2 / (2 Y_warp) longer, one cut along the weft
    rho g L^2 / (2 Y_weft) (Poisson 0: the cross direction does not take part). The cut comes
    from pattern UVs (v along the strip, or across it) or from the grain axis."""
    length = 0.5
    y_axis, x_axis = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    for along, stiffness in (("warp", ORTHOTROPIC.warp_stiffness), ("weft", ORTHOTROPIC.weft_stretch_stiffness)):
        vertical = y_axis if along == "warp" else -x_axis  # the pattern's v (warp) direction in 3-D
        if cut == "uv":
            u_axis = np.cross(vertical, np.array([0.0, 0.0, 1.0]))
            extension, status = _hang_strip(ORTHOTROPIC, length=length, width=0.05, rows=20, solver=solver,
                                            material_uv=lambda v, f: _uv_of(v, f, u_axis, vertical))
        else:
            extension, status = _hang_strip(ORTHOTROPIC, length=length, width=0.05, rows=20, solver=solver,
                                            grain_axis=vertical)
        assert status == WorldStatus.CONVERGED, f"{along}: {WorldStatus(status).name}"
        expected = ORTHOTROPIC.density * GRAVITY * length ** 2 / (2.0 * stiffness)
        assert abs(extension - expected) <= RTOL_STRIP * expected, (
            f"{solver}/{cut}, strip along the {along}: extension {extension * 1e3:.3f} mm vs "
            f"rho g L^2/(2 Y_{along}) = {expected * 1e3:.3f} mm")


def test_fabric_warp_and_weft() -> None:
    """Woven presets are stiffer along the warp; weft_stiffness=None means isotropic; the
    compliances per triangle are 1/(Y_warp A), 1/(Y_weft A), 1/(G A)."""
    for name in ("silk", "cotton", "denim"):
        fab = FABRICS[name]
        assert fab.warp_stiffness > fab.weft_stretch_stiffness, f"{name}: warp not stiffer than weft"
    assert FABRICS["leather"].warp_stiffness == FABRICS["leather"].weft_stretch_stiffness
    order = ["silk", "cotton", "denim", "leather"]
    weft = [FABRICS[n].weft_stretch_stiffness for n in order]
    assert weft == sorted(weft), f"weft stiffness not increasing silk < cotton < denim < leather: {weft}"
    iso = Fabric(stretch_stiffness=123.0)
    assert iso.weft_stiffness is None and iso.weft_stretch_stiffness == 123.0 == iso.warp_stiffness
    with pytest.raises(ValueError, match="Fabric.weft_stiffness must be None or a finite number > 0"):
        Fabric(weft_stiffness=0.0)
    verts, faces = grid_cloth(3, 3, 0.2, 0.2, plane="xy")
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton")
    model = builder.finalize("cpu")
    area = model.tri_area.numpy().astype(np.float64)
    comp = model.tri_compliance.numpy().astype(np.float64)
    cotton = FABRICS["cotton"]
    for k, stiffness in enumerate((cotton.warp_stiffness, cotton.weft_stretch_stiffness, cotton.shear_stiffness)):
        assert np.allclose(comp[:, k], 1.0 / (stiffness * area), rtol=1e-6)


def test_material_uv_is_checked_and_keys_the_shared_elements() -> None:
    """Bad UVs or grain axes are named; garments that differ only in their UVs get their own rest
    frames, garments with the same UVs share them (and equal the garment built alone)."""
    verts, faces = tube_cloth(8, 4, 0.2, 0.3)
    with pytest.raises(ValueError, match=r"material_uv must have shape \(48, 3, 2\)"):
        ClothBuilder().add_garment(verts, faces, material_uv=np.zeros((48, 2)))
    bad = np.zeros((48, 3, 2))
    bad[5, 1, 0] = np.nan
    with pytest.raises(ValueError, match="material_uv must be finite; face 5"):
        ClothBuilder().add_garment(verts, faces, material_uv=bad)
    with pytest.raises(ValueError, match="grain_axis must be finite and non-zero"):
        ClothBuilder().add_garment(verts, faces, grain_axis=(0.0, 0.0, 0.0))
    uv = _tube_uv(verts, faces, 0.2)
    turned = uv[..., ::-1] * np.array([-1.0, 1.0])  # the pattern turned by 90 degrees: warp around the tube
    worlds = [uv, turned, uv, None]
    builder = ClothBuilder()
    for w in worlds:
        builder.add_garment(verts, faces, material_uv=w)
    model = builder.finalize("cpu")
    tri_world = model.tri_world.numpy()
    dm = [model.tri_dm_inv.numpy()[tri_world == w] for w in range(len(worlds))]
    assert np.array_equal(dm[0], dm[2])
    assert not np.allclose(dm[0], dm[1], atol=1e-3), "a turned pattern gave the same rest frames"
    for w, material_uv in enumerate(worlds):
        alone = ClothBuilder()
        alone.add_garment(verts, faces, material_uv=material_uv)
        assert np.array_equal(alone.finalize("cpu").tri_dm_inv.numpy(), dm[w]), f"world {w} differs from alone"
    # Stretched 10 % along its axis, the tube loads its warp when cut from the unrolled pattern
    # and its weft when cut from the turned one: energies in the ratio Y_warp / Y_weft.
    x = verts.copy()
    x[:, 1] *= 1.1
    energy = _triangle_energies(model, np.concatenate([x] * len(worlds)))
    per_world = np.zeros(len(worlds))
    for corners, value in energy.items():
        per_world[corners[0] // len(verts)] += value
    cotton = FABRICS["cotton"]
    assert np.isclose(per_world[0] / per_world[1], cotton.warp_stiffness / cotton.weft_stretch_stiffness, rtol=1e-4)


def _unfolded_neighbour_angles(vertices: np.ndarray, faces: np.ndarray, warp: np.ndarray, normal: np.ndarray,
                               panel: np.ndarray) -> np.ndarray:
    """Angle [deg] between the warps of edge-adjacent faces of one panel, the neighbour's warp
    carried into the face's plane by unfolding the hinge about the shared edge (accounts for
    the surface's curvature)."""
    from simulate.garment.uv import face_neighbours

    nbr = face_neighbours(faces)
    a, k = np.nonzero(nbr >= 0)
    b = nbr[a, k]
    same = panel[a] == panel[b]
    a, k, b = a[same], k[same], b[same]
    edge = vertices[faces[a, (k + 1) % 3]] - vertices[faces[a, k]]
    edge /= np.linalg.norm(edge, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", warp[b], edge)
    across = np.einsum("ij,ij->i", warp[b], np.cross(normal[b], edge))
    carried = along[:, None] * edge + across[:, None] * np.cross(normal[a], edge)
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", warp[a], carried), -1.0, 1.0)))


MAX_MEDIAN_NEIGHBOUR_DEG = 2.0
MAX_P90_NEIGHBOUR_DEG = 10.0
"""Warp of neighbouring faces of one panel (measured on the level-0 t-shirt: median 0.9, 90th
percentile 6.8 degrees; the tail is where the style offset stretched the chart, which is made on
the body region, up to 12:1)."""
MAX_MEDIAN_TORSO_DEG = 5.0
"""Warp of the t-shirt's torso faces against +y projected into them (measured median 3.2 degrees)."""


def test_template_warp_runs_up_its_panels(anny_body, monkeypatch) -> None:
    """On a t-shirt template, the warp from its UV panels is continuous across each panel, runs up
    the torso (the panels' v axis is the body's up, ``uv._orient_panel``), and is what the builder
    puts in the rest frames (rest F = [warp, weft]); ``drape_canonical`` and ``drape_static`` pass
    the template's UVs to the builder."""
    from simulate.garment.templates import SEGMENT_TORSO, make_template

    tpl = make_template("tshirt", anny_body, resolution=500)
    verts = tpl.vertices.astype(np.float64)
    faces = tpl.faces
    warp, weft, normal = material_directions(verts, faces, material_uv=tpl.face_uv)
    angles = _unfolded_neighbour_angles(verts, faces, warp, normal, tpl.face_panel)
    assert np.median(angles) < MAX_MEDIAN_NEIGHBOUR_DEG and np.percentile(angles, 90) < MAX_P90_NEIGHBOUR_DEG, (
        f"neighbour warps differ by {np.median(angles):.2f} (median), {np.percentile(angles, 90):.2f} (90th pct) deg")
    up = np.array([0.0, 1.0, 0.0]) - normal[:, 1:2] * normal
    up_len = np.linalg.norm(up, axis=1)
    torso = (tpl.segment[faces] <= SEGMENT_TORSO).all(axis=1) & (up_len > 0.3)
    cos_up = np.einsum("ij,ij->i", warp[torso], up[torso]) / up_len[torso]
    torso_deg = np.degrees(np.arccos(np.clip(cos_up, -1.0, 1.0)))
    assert np.median(torso_deg) < MAX_MEDIAN_TORSO_DEG, f"torso warp {np.median(torso_deg):.1f} deg from +y (median)"
    assert (warp[:, 1] > 0.0).mean() > 0.95, "the warp does not point up the garment"

    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", material_uv=tpl.face_uv)
    model = builder.finalize("cpu")
    tri = model.tri_indices.numpy()
    order = {tuple(t): i for i, t in enumerate(faces.tolist())}
    rows = np.array([order[tuple(t)] for t in tri.tolist()])
    x = model.particle_q_rest.astype(np.float64)
    rest_f = np.stack([x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]], axis=2) @ model.tri_dm_inv.numpy()
    assert np.abs(rest_f[:, :, 0] - warp[rows]).max() < ATOL_REST_F, "rest f1 is not the warp"
    assert np.abs(rest_f[:, :, 1] - weft[rows]).max() < ATOL_REST_F, "rest f2 is not the weft"

    class Built(Exception):
        pass

    calls = []

    def record(self, vertices, faces, **kwargs):
        calls.append(kwargs.get("material_uv"))
        raise Built

    from simulate.garment.drape import drape_canonical
    from simulate.sequence import SequenceSettings, drape_static

    monkeypatch.setattr(ClothBuilder, "add_garment", record)
    with pytest.raises(Built):
        drape_canonical([(tpl, tpl.vertices)], anny_body, anny_body.shape_default)
    with pytest.raises(Built):
        drape_static(anny_body, faces, tpl.vertices[None], shapes=anny_body.shape_default[None],
                     poses=anny_body.canonical_pose[None], body_faces=anny_body.part_faces(["torso"]),
                     settings=SequenceSettings(sim=unit_settings()), device="cpu", material_uv=tpl.face_uv)
    assert len(calls) == 2 and all(c is not None and np.array_equal(c, tpl.face_uv) for c in calls)
