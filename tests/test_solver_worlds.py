"""Batched worlds: isolation of an exploding world, determinism, stability matrix, attachments,
mass-spring stable step, CPU vs CUDA agreement."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from simulate.cloth import FABRICS, ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus
from simulate.scenes import grid_cloth, icosphere
from simulate.contact import BodyCollider
from unit_sim import unit_settings

wp.init()
HAS_CUDA = wp.get_cuda_device_count() > 0
DEVICES = ["cpu"] + (["cuda:0"] if HAS_CUDA else [])

MAX_STRETCH_RATIO = 1.5
"""Stability matrix: no triangle may stretch beyond this ratio at rest [-]."""
ATOL_CPU_CUDA_M = 1.0e-3
"""CPU vs CUDA after 12 frames of a drape (cloth lands on the sphere at frame ~6) [m]: both are
float32 with the same operation order per element, but CUDA contracts multiply-adds (FMA) and
evaluates transcendental functions differently, so results drift apart by rounding amplified
by contact events."""


def _sphere_scene(fabrics: list, device: str, *, n: int = 9, collider_worlds: int | None = None):
    verts, faces = grid_cloth(n, n, 0.6, 0.6, plane="xz", origin=(-0.3, 0.28, -0.3))
    builder = ClothBuilder()
    for fab in fabrics:
        builder.add_garment(verts, faces, fabric=fab)
    model = builder.finalize(device)
    sv, sf = icosphere(0.25, subdivisions=2)
    collider = BodyCollider(sv, sf, device=device, world_count=collider_worlds or len(fabrics))
    return model, collider


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solver,mode", [("xpbd", "gauss_seidel"), ("xpbd", "jacobi"), ("mass_spring", None)])
def test_exploding_world_is_frozen_and_others_are_bit_identical(device: str, solver: str, mode: str | None) -> None:
    settings = unit_settings(substeps=5 if solver == "xpbd" else 40, iterations=4, damping=2.0, tolerance=0.02,
                           max_frames=40, xpbd_mode=mode or "gauss_seidel")
    results = []
    for blow_up in (False, True):
        model, collider = _sphere_scene(["cotton", "cotton", "silk"], device)
        sim = QuasiStaticSimulator(model, collider, solver=solver, settings=settings)
        if blow_up:
            qd = sim.velocities()
            sl = model.world_slice(1)
            qd[sl] = np.random.default_rng(1).normal(0.0, 1.0e4, size=qd[sl].shape)  # absurd velocities [m/s]
            sim.state_0.particle_qd.assign(qd)
        status = sim.relax()
        results.append((status, sim.positions(), model, sim.world_frames.copy()))
    (st_ok, q_ok, model, _), (st_bad, q_bad, _, frames_bad) = results
    assert st_bad[1] == WorldStatus.EXPLODED, f"world 1 should be EXPLODED, got {WorldStatus(st_bad[1]).name}"
    assert st_ok[1] != WorldStatus.EXPLODED
    for w in (0, 2):
        sl = model.world_slice(w)
        assert st_ok[w] == st_bad[w], f"world {w} status changed: {st_ok[w]} vs {st_bad[w]}"
        assert np.array_equal(q_ok[sl], q_bad[sl]), (
            f"world {w} differs by {np.abs(q_ok[sl] - q_bad[sl]).max()} m when world 1 explodes")
    # Frozen: the exploded world was stepped for one frame only (detected after the first frame).
    assert frames_bad[1] == 1, f"exploded world was stepped {frames_bad[1]} frames"


@pytest.mark.parametrize("device", DEVICES)
def test_same_run_twice_gives_identical_arrays(device: str) -> None:
    runs = []
    for _ in range(2):
        model, collider = _sphere_scene(["denim", "silk"], device)
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=4, iterations=4, max_frames=15,
                                                                          xpbd_mode="jacobi"))
        sim.relax()
        runs.append((sim.positions(), sim.velocities(), sim.residual_history))
    for a, b, name in zip(runs[0], runs[1], ("positions", "velocities", "residual history")):
        assert np.array_equal(a, b, equal_nan=True), f"{name} differ between identical runs"


@pytest.mark.parametrize("device", DEVICES)
def test_frames_report_their_device_time(device: str) -> None:
    """On CUDA each launched frame's device time (CUDA events) is positive and within the wall time
    from its launch to its finish; on the CPU it stays 0."""
    import time

    model, collider = _sphere_scene(["denim", "silk"], device)
    sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=4, iterations=4, max_frames=15))
    walls = []
    for _ in range(4):
        t0 = time.perf_counter()
        sim.launch_frame()
        sim.finish_frame()
        walls.append(time.perf_counter() - t0)
        if device.startswith("cuda"):
            assert 0 < sim.last_frame_device_s <= walls[-1]
    if device.startswith("cuda"):
        assert 0 < sim.device_frame_s <= sum(walls)
    else:
        assert sim.device_frame_s == 0.0 and sim.last_frame_device_s == 0.0


@pytest.mark.parametrize("device", DEVICES)
def test_a_world_revived_while_a_frame_is_in_flight_keeps_its_new_state(device: str) -> None:
    """launch_frame / finish_frame (what the sequence driver does between them): a world frozen
    when the frame was launched and revived before it finished is not stepped by that frame, keeps
    the RUNNING status and zero frame count revive gave it, and its positions are those put back;
    the other worlds equal plain step_frame calls bit for bit. Misuse raises."""
    settings = unit_settings(substeps=4, iterations=4, tolerance=0.02, max_frames=40)
    runs = []
    for split in (False, True):
        model, collider = _sphere_scene(["cotton", "silk"], device)
        sim = QuasiStaticSimulator(model, collider, settings=settings)
        for _ in range(3):
            sim.step_frame()
        saved = sim.world_positions(1)
        sim.status[1] = WorldStatus.CONVERGED  # frozen, as a world whose frame is being handed over
        moved = saved + np.float32(0.01)
        if split:
            sim.launch_frame()
            assert sim.launched_running.tolist() == [True, False]
            sim.revive(1, moved)  # queued behind the frame in flight
            status = sim.finish_frame()
            assert sim.launched_running is None
            assert status[1] == WorldStatus.RUNNING, "finish_frame overwrote the revived world's status"
        else:
            sim.step_frame()
            sim.revive(1, moved)
        assert sim.status[1] == WorldStatus.RUNNING and sim.world_frames[1] == 0
        np.testing.assert_array_equal(sim.world_positions(1), moved, err_msg="the revived world was stepped")
        runs.append(sim.positions()[model.world_slice(0)])
    np.testing.assert_array_equal(runs[0], runs[1], err_msg="world 0 differs when stepped by launch/finish")
    with pytest.raises(RuntimeError, match="finish_frame called without launch_frame"):
        sim.finish_frame()
    sim.launch_frame()
    with pytest.raises(RuntimeError, match="launch_frame called twice"):
        sim.launch_frame()
    sim.finish_frame()


@pytest.mark.parametrize("dt_scale", [1, 4])
def test_stability_matrix_stiffness_dt_fabric(dt_scale: int) -> None:
    """Stretch stiffness over four decades x silk/denim x dt up to 4x default: no NaN, bounded
    stretch, every world converges (XPBD, all variants batched as worlds)."""
    fabrics = [dataclasses.replace(FABRICS[name], stretch_stiffness=k, weft_stiffness=None, shear_stiffness=k / 100.0)
               for name in ("silk", "denim") for k in (1.0e1, 1.0e3, 1.0e5)]
    model, collider = _sphere_scene(fabrics, "cpu")
    settings = unit_settings(frame_dt=dt_scale / 60.0, substeps=5, iterations=5, damping=2.0, tolerance=0.02,
                           max_frames=600 // dt_scale)
    sim = QuasiStaticSimulator(model, collider, settings=settings)
    status = sim.relax()
    names = [f"{f.name}/k={f.stretch_stiffness:g}" for f in fabrics]
    assert all(s == WorldStatus.CONVERGED for s in status), dict(zip(names, [WorldStatus(s).name for s in status]))
    q = sim.positions()
    assert np.all(np.isfinite(q))
    from simulate.cloth.builder import triangle_rest_frames

    for w, name in enumerate(names):
        sl = model.world_slice(w)
        faces = model.world_faces[w]
        dm_inv, _ = triangle_rest_frames(model.particle_q_rest[sl], faces)
        x = q[sl].astype(np.float64)
        ds = np.stack([x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]]], axis=2)  # (F, 3, 2)
        f = ds @ dm_inv
        stretch = np.linalg.norm(f, axis=1).max()
        assert stretch < MAX_STRETCH_RATIO, f"{name}: max stretch ratio {stretch:.3f}"


def test_mass_spring_stable_dt_bound() -> None:
    """Below its stable-step bound the explicit solver settles; at 8x beyond it, it blows up
    and the world is flagged EXPLODED (not NaN-propagating into the result arrays of others)."""
    model, collider = _sphere_scene(["cotton"], "cpu", n=7)
    auto = QuasiStaticSimulator(model, collider, solver="mass_spring",
                                settings=unit_settings(substeps=None, damping=2.0, tolerance=0.02, max_frames=200))
    dt_stable = auto.solver.stable_dt()
    assert auto.dt <= 0.5 * dt_stable * (1 + 1e-9), f"auto dt {auto.dt} above half the stable bound {dt_stable}"
    assert auto.relax()[0] == WorldStatus.CONVERGED
    substeps = max(1, int(np.floor((1.0 / 60.0) / (8.0 * dt_stable))))
    fast = QuasiStaticSimulator(model, collider, solver="mass_spring",
                                settings=unit_settings(substeps=substeps, damping=2.0, max_frames=100))
    assert fast.dt > 4.0 * dt_stable
    assert fast.relax()[0] == WorldStatus.EXPLODED


def test_attachments_follow_targets_and_release() -> None:
    verts, faces = grid_cloth(6, 6, 0.3, 0.3, plane="xz", origin=(0.0, 1.0, 0.0))
    builder = ClothBuilder(attachment_stiffness=50.0)
    corners = np.array([0, 5])
    builder.add_garment(verts, faces, fabric="cotton", attached=corners)
    model = builder.finalize("cpu", features=Features(body_contact=False))
    sim = QuasiStaticSimulator(model, None, settings=unit_settings(substeps=5, iterations=5, damping=3.0,
                                                                 tolerance=0.01, max_frames=400))
    targets = verts[corners] + np.array([0.1, 0.2, 0.0])
    sim.control.set_attachment_targets(targets)
    assert sim.relax()[0] == WorldStatus.CONVERGED
    q = sim.positions()
    # Soft springs: each corner carries about half the cloth weight, offset = weight / k below target.
    weight = model.particle_mass.numpy().sum() * 9.81
    sag = targets[:, 1] - q[corners, 1]
    assert np.all(sag > 0.0) and np.all(sag < weight / 50.0), f"corner sag {sag} vs total weight / k {weight / 50.0}"
    assert np.allclose(q[corners][:, [0, 2]], targets[:, [0, 2]], atol=0.02)
    sim.control.release_attachments()
    sim.restart()
    y_before = q[:, 1].mean()
    for _ in range(10):
        sim.step_frame()
    assert sim.positions()[:, 1].mean() < y_before - 0.02, "released cloth did not fall"


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device"))])
def test_attachment_targets_from_torch_tensors(device: str) -> None:
    """Targets given as a torch tensor on the model's device (the sequence driver's bodies) land
    as the same numbers as from numpy; a wrong shape or a NaN is refused either way."""
    torch = pytest.importorskip("torch")
    verts, faces = grid_cloth(4, 4, 0.3, 0.3, plane="xz")
    builder = ClothBuilder()
    builder.add_garment(verts, faces, fabric="cotton", attached=np.array([0, 3, 12]))
    model = builder.finalize(device, features=Features(body_contact=False))
    sim = QuasiStaticSimulator(model, None, settings=unit_settings())
    targets = np.random.default_rng(0).normal(size=(3, 3)).astype(np.float64)
    sim.control.set_attachment_targets(torch.as_tensor(targets, device=device))
    np.testing.assert_array_equal(sim.control.attachment_target.numpy(), targets.astype(np.float32))
    sim.control.set_attachment_targets(torch.as_tensor(2 * targets, device=device), check_finite=False)
    np.testing.assert_array_equal(sim.control.attachment_target.numpy(), (2 * targets).astype(np.float32))
    with pytest.raises(ValueError, match=r"shape \(3, 3\)"):
        sim.control.set_attachment_targets(torch.zeros(2, 3, device=device))
    bad = torch.as_tensor(targets, device=device)
    bad[1, 2] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        sim.control.set_attachment_targets(bad)


@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
@pytest.mark.parametrize("mode", ["gauss_seidel", "jacobi"])
def test_cpu_and_cuda_agree(mode: str) -> None:
    out = {}
    for device in ("cpu", "cuda:0"):
        model, collider = _sphere_scene(["cotton", "denim"], device)
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=5, iterations=5, xpbd_mode=mode))
        for _ in range(12):
            sim.step_frame()
        out[device] = sim.positions()
    diff = np.abs(out["cpu"] - out["cuda:0"]).max()
    assert diff < ATOL_CPU_CUDA_M, f"CPU and CUDA differ by {diff * 1e3:.3f} mm after 12 frames"


@pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")
def test_cuda_graph_replay_matches_eager() -> None:
    out = {}
    for graph in (False, True):
        model, collider = _sphere_scene(["cotton"], "cuda:0")
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=5, iterations=5,
                                                                         use_cuda_graph=graph))
        for _ in range(10):
            sim.step_frame()
        out[graph] = sim.positions()
    assert np.array_equal(out[False], out[True]), "CUDA graph replay differs from eager launches"


@pytest.mark.parametrize("mode", ["gauss_seidel", "jacobi"])
@pytest.mark.parametrize("substeps", [4, 5])
def test_cpu_graph_replay_matches_eager(mode: str, substeps: int) -> None:
    """CPU substep graphs (both buffer parities) replay bit-identically to eager launches,
    including a body target change mid-run and attachments."""
    out = {}
    for graph in (False, True):
        verts, faces = grid_cloth(9, 9, 0.6, 0.6, plane="xz", origin=(-0.3, 0.28, -0.3))
        builder = ClothBuilder()
        builder.add_garment(verts, faces, pinned=[0], attached=[40])
        model = builder.finalize("cpu")
        sv, sf = icosphere(0.25, subdivisions=2)
        collider = BodyCollider(sv, sf, device="cpu")
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=substeps, iterations=3,
                                                                         xpbd_mode=mode, use_cpu_graph=graph))
        for k in range(12):
            if k == 6:
                sim.set_body_target(sv + np.array([0.0, 0.03, 0.01]))
            sim.step_frame()
        out[graph] = (sim.positions(), sim.velocities())
    assert np.array_equal(out[False][0], out[True][0]), "CPU graph positions differ from eager"
    assert np.array_equal(out[False][1], out[True][1]), "CPU graph velocities differ from eager"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bending_mode", ["gauss_seidel", "jacobi"])
@pytest.mark.parametrize("shared", [True, False])
@pytest.mark.parametrize("one_topology", [False, True])
def test_world_block_sweep_equals_colour_launches(device: str, bending_mode: str, shared: bool, one_topology: bool) -> None:
    """One launch per iteration with a block per world (a barrier between colours), positions in
    shared memory or in global memory, sweeps the colours exactly as one launch per colour does:
    worlds of different sizes and fabrics (the last world's tile reaches past the array), or of
    one topology with different rest shapes and fabrics (their shared-memory sweep reads one
    shared table of world-local corners), a frozen world, contact with the sphere, an attached
    vertex.  In shared memory with Gauss-Seidel bending the whole substep (every iteration's
    sweep and particle pass) is one launch."""
    out = {}
    grids = ((12, 0.6, "cotton"), (12, 0.5, "silk"), (12, 0.7, "denim")) if one_topology else (
        (9, 0.6, "cotton"), (12, 0.6, "silk"), (7, 0.6, "denim"))
    for sweep in ("colour_launches", "world_blocks"):
        builder = ClothBuilder()
        for k, (n, size, fab) in enumerate(grids):
            verts, faces = grid_cloth(n, n, size, 0.6, plane="xz", origin=(-0.3, 0.28, -0.3))
            builder.add_garment(verts, faces, fabric=fab, attached=[n + 1] if k == 1 else None)
        model = builder.finalize(device)
        sv, sf = icosphere(0.25, subdivisions=2)
        collider = BodyCollider(sv, sf, device=device, world_count=3)
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(
            substeps=4, iterations=3, xpbd_bending_mode=bending_mode, gs_sweep=sweep, gs_block_dim=64),
            solver_options={"gs_shared": shared})
        if sweep == "world_blocks":
            assert (sim.solver._shared_kernel is not None) == shared
            assert sim.solver._fused == (shared and bending_mode == "gauss_seidel")
            assert sim.solver.attachments
            if shared:
                assert sim.solver.shared_topology == one_topology
        sim.status[2] = WorldStatus.CONVERGED  # frozen: its block returns at once
        for _ in range(12):
            sim.step_frame()
        out[sweep] = sim.positions()
    rest = np.asarray(model.particle_q_rest_np)
    frozen = int(model.world_particle_start[2])
    assert np.abs(out["world_blocks"] - rest)[:frozen].max() > 0.1, "the cloth did not fall"
    assert np.array_equal(out["world_blocks"][frozen:], rest[frozen:]), "the frozen world moved"
    assert np.array_equal(out["world_blocks"], out["colour_launches"]), (
        f"sweeps differ by {np.abs(out['world_blocks'] - out['colour_launches']).max():.3g} m")


@pytest.mark.parametrize("device", DEVICES)
def test_worlds_that_repeat_a_garment_read_one_copy_of_its_data(device: str) -> None:
    """Worlds with the same topology, rest shape, fabric and masses read the first such world's
    element data in the tiled sweep (``shared_element_data``) and step exactly as when each reads
    its own; a world with another rest shape, fabric or pinned vertex keeps its own data."""
    n = 12
    shapes = [(0.6, "cotton", None), (0.5, "cotton", None), (0.6, "cotton", None), (0.6, "silk", None),
              (0.5, "cotton", None), (0.6, "cotton", [0])]
    out = {}
    for share in (True, False):
        builder = ClothBuilder()
        for size, fab, pinned in shapes:
            verts, faces = grid_cloth(n, n, size, 0.6, plane="xz", origin=(-0.3, 0.28, -0.3))
            builder.add_garment(verts, faces, fabric=fab, pinned=pinned)
        model = builder.finalize(device)
        sv, sf = icosphere(0.25, subdivisions=2)
        collider = BodyCollider(sv, sf, device=device, world_count=len(shapes))
        sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=3, iterations=3, gs_block_dim=64),
                                   solver_options={"gs_shared": True, "share_element_data": share})
        assert sim.solver._fused and sim.solver.shared_topology
        expected = [0, 1, 0, 3, 1, 5] if share else list(range(len(shapes)))
        assert sim.solver.element_data_source.tolist() == expected
        for _ in range(10):
            sim.step_frame()
        out[share] = sim.positions()
    rest = np.asarray(model.particle_q_rest_np)
    assert np.abs(out[True] - rest).max() > 0.1, "the cloth did not fall"
    assert np.array_equal(out[True], out[False]), (
        f"shared element data changed the result by {np.abs(out[True] - out[False]).max():.3g} m")


def test_shared_element_data_needs_every_value_equal() -> None:
    from simulate.solvers.xpbd.solver_xpbd import shared_element_data, world_colour_offsets

    # three worlds of 4 particles, 3 triangles each (colour 0: two, colour 1: one), no bending
    world = np.array([0, 0, 1, 1, 2, 2, 0, 1, 2])
    offsets = world_colour_offsets([0, 6, 9], world, 3)
    comp = np.array([[1, 1, 1], [2, 2, 2]] * 3 + [[3, 3, 3]] * 3, np.float32)
    dm = np.ones((9, 2, 2), np.float32)
    bend = world_colour_offsets([0], np.zeros(0), 3)
    inv_mass = np.ones(12, np.float32)
    starts, counts = np.array([0, 4, 8]), np.array([4, 4, 4])
    tri_dshift, bend_dshift, data_start, source = shared_element_data(
        offsets, [dm, comp], bend, [np.zeros(0, np.float32)], inv_mass, starts, counts)
    assert source.tolist() == [0, 0, 0] and data_start.tolist() == [0, 0, 0] and not bend_dshift.any()
    for t in range(9):  # every element reads the first world's element of the same place
        c, w = (0, t // 2) if t < 6 else (1, t - 6)
        assert np.array_equal(comp[t - tri_dshift[c, w]], comp[t]) and world[t - tri_dshift[c, w]] == 0
    comp_other = comp.copy()
    comp_other[8, 2] = 4  # world 2's colour-1 triangle: another shear compliance
    mass_other = inv_mass.copy()
    mass_other[5] = 0.0  # world 1 pins a particle
    _, _, data_start, source = shared_element_data(offsets, [dm, comp_other], bend, [np.zeros(0, np.float32)],
                                                   mass_other, starts, counts)
    assert source.tolist() == [0, 1, 2] and data_start.tolist() == [0, 4, 8]


def test_local_topology_is_shared_only_when_every_world_has_the_same_corners() -> None:
    from simulate.solvers.xpbd.solver_xpbd import local_topology, world_colour_offsets

    # two worlds of 4 particles; colour 0: two triangles per world, colour 1: one per world
    tri = np.array([[0, 1, 2], [1, 2, 3], [4, 5, 6], [5, 6, 7], [0, 2, 3], [4, 6, 7]])
    world = np.array([0, 0, 1, 1, 0, 1])
    offsets = world_colour_offsets([0, 4, 6], world, 2)
    shift, local, shared = local_topology(offsets, tri, world, np.array([0, 4]))
    assert shared and local.tolist() == [[0, 1, 2], [1, 2, 3], [0, 2, 3]]
    for t in range(len(tri)):  # every element finds its own corners
        c = 0 if t < 4 else 1
        assert (local[t - shift[c, world[t]]] + 4 * world[t]).tolist() == tri[t].tolist()
    other = tri.copy()
    other[3] = [5, 7, 6]  # same counts, another corner order in world 1
    shift, local, shared = local_topology(offsets, other, world, np.array([0, 4]))
    assert not shared and not shift.any() and (local == other - 4 * world[:, None]).all()
    fewer = world_colour_offsets([0, 3, 5], np.array([0, 0, 1, 0, 1]), 2)  # colour 0: 2 and 1 elements
    assert not local_topology(fewer, tri[[0, 1, 2, 4, 5]], np.array([0, 0, 1, 0, 1]), np.array([0, 4]))[2]
    # no elements (a strip without bending, particles without triangles): an empty shared table
    shift, local, shared = local_topology(world_colour_offsets([0], np.zeros(0), 1), np.zeros((0, 4), np.int32),
                                          np.zeros(0, np.int32), np.array([0]))
    assert shared and local.shape == (0, 4) and shift.shape == (1, 1)


def test_world_colour_offsets_locate_each_worlds_elements() -> None:
    from simulate.solvers.xpbd.solver_xpbd import world_colour_offsets

    # colour 0: worlds 0, 0, 2; colour 1: world 1; colour 2: nothing for 3 worlds
    offs = world_colour_offsets([0, 3, 4], np.array([0, 0, 2, 1]), 3)
    assert offs.tolist() == [[0, 2, 2, 3], [3, 3, 4, 4]]
    with pytest.raises(ValueError, match="colour 0 are not sorted by world"):
        world_colour_offsets([0, 2], np.array([1, 0]), 2)
    assert world_colour_offsets([0], np.zeros(0), 2).tolist() == [[0, 0, 0]]


def test_driver_and_solver_argument_errors() -> None:
    from simulate.solvers import make_solver

    model, collider = _sphere_scene(["cotton", "silk"], "cpu", n=5)
    with pytest.raises(ValueError, match="solver must be one of"):
        make_solver("implicit_euler", model)
    with pytest.raises(ValueError, match="mode must be one of"):
        make_solver("xpbd", model, mode="red_black")
    with pytest.raises(ValueError, match="iterations must be an integer >= 1"):
        make_solver("xpbd", model, iterations=0)
    with pytest.raises(ValueError, match="gs_sweep must be one of"):
        make_solver("xpbd", model, gs_sweep="by_colour")
    with pytest.raises(ValueError, match=r"gs_block_dim must be a multiple of 32 in \[32, 1024\] \(got 100\)"):
        make_solver("xpbd", model, gs_block_dim=100)
    with pytest.raises(ValueError, match="SimSettings.gs_sweep is invalid"):
        SimSettings(gs_sweep="x")
    with pytest.raises(ValueError, match="SimSettings.tolerance is invalid"):
        SimSettings(tolerance=-1.0)
    _, one_world = _sphere_scene(["cotton"], "cpu", n=5)
    with pytest.raises(ValueError, match="collider has 1 worlds but the model has 2"):
        QuasiStaticSimulator(model, one_world)
    sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=2, iterations=2))
    with pytest.raises(ValueError, match=r"positions must have shape \(25, 3\)"):
        sim.set_positions(np.zeros((3, 3)), world=1)
    with pytest.raises(ValueError, match=r"worlds must be indices in \[0, 2\)"):
        sim.restart([5])
    with pytest.raises(ValueError, match="body_contact is on but contacts is None"):
        sim.solver.step(sim.state_0, sim.state_1, model.control(), None, 0.01)
    # set_positions on one world leaves the other untouched and zeroes that world's velocities.
    sim.relax(max_frames=3)
    before = sim.positions()
    sim.set_positions(model.particle_q_rest[model.world_slice(1)] + 0.01, world=1)
    after = sim.positions()
    assert np.array_equal(after[model.world_slice(0)], before[model.world_slice(0)])
    assert np.allclose(after[model.world_slice(1)], model.particle_q_rest[model.world_slice(1)] + 0.01)
    assert not sim.velocities()[model.world_slice(1)].any()


@pytest.mark.parametrize("solver", ["xpbd", "mass_spring"])
def test_nan_world_is_flagged_and_frozen(solver: str) -> None:
    model, collider = _sphere_scene(["cotton", "cotton"], "cpu", n=5)
    sim = QuasiStaticSimulator(model, collider, solver=solver,
                               settings=unit_settings(substeps=4 if solver == "xpbd" else None, iterations=2,
                                                    max_frames=5))
    bad = sim.positions()
    bad[model.world_particle_start[0] + 3] = np.nan
    sim.state_0.particle_q.assign(bad)
    status = sim.step_frame()
    assert status[0] == WorldStatus.EXPLODED and status[1] == WorldStatus.RUNNING, status
    frozen = sim.positions()[model.world_slice(0)].copy()
    sim.relax()
    after = sim.positions()
    assert np.array_equal(after[model.world_slice(0)], frozen, equal_nan=True), "exploded world kept moving"
    assert np.all(np.isfinite(after[model.world_slice(1)])), "NaN leaked into world 1"


@pytest.mark.parametrize("device", DEVICES)
def test_setting_one_worlds_positions_leaves_the_others_alone(device: str) -> None:
    """set_positions(world=w) writes w's particles and zeroes their velocities in place; every
    other world's positions and velocities stay bit-identical (explosion recovery relies on it)."""
    model, collider = _sphere_scene(["cotton"] * 3, device)
    sim = QuasiStaticSimulator(model, collider, settings=unit_settings(substeps=4, iterations=4))
    for _ in range(3):
        sim.step_frame()
    q0, qd0 = sim.positions(), sim.velocities()
    assert np.abs(qd0).max() > 0.1, "the falling cloth must be moving before the reset"
    sl = model.world_slice(1)
    new = q0[sl] + np.array([0.0, 0.05, 0.0], np.float32)
    sim.set_positions(new, world=1)
    q1, qd1 = sim.positions(), sim.velocities()
    np.testing.assert_array_equal(q1[sl], new)
    assert not qd1[sl].any()
    others = np.ones(len(q0), bool)
    others[sl] = False
    np.testing.assert_array_equal(q1[others], q0[others])
    np.testing.assert_array_equal(qd1[others], qd0[others])
    with pytest.raises(ValueError, match=r"positions must have shape \(81, 3\)"):
        sim.set_positions(new[:-1], world=1)
    with pytest.raises(ValueError, match="finite"):
        sim.set_positions(np.full_like(new, np.nan), world=1)
    # positions sent to the device once (a home state) set the world the same way
    for _ in range(2):
        sim.step_frame()
    q2, qd2 = sim.positions(), sim.velocities()
    sim.set_positions(sim.device_positions(new), world=1)
    q3, qd3 = sim.positions(), sim.velocities()
    np.testing.assert_array_equal(q3[sl], new)
    assert not qd3[sl].any() and np.abs(qd2[sl]).max() > 0.0
    np.testing.assert_array_equal(q3[others], q2[others])
    np.testing.assert_array_equal(qd3[others], qd2[others])
    with pytest.raises(ValueError, match=r"vec3f \(81,\) on .* \(got vec3f \(80,\)"):
        sim.set_positions(sim.device_positions(new[:-1]), world=1)
    with pytest.raises(ValueError, match="finite"):
        sim.device_positions(np.full_like(new, np.nan))


@pytest.mark.parametrize("device", DEVICES)
def test_small_limit_cycles_count_as_rest_and_drift_does_not(device: str) -> None:
    """limit_cycle_window: a particle orbiting between two positions 2 mm apart (0.12 m/s, above
    the 0.05 m/s tolerance) counts as at rest once the window holds its history; one drifting
    2 mm per frame, or orbiting 1 cm (beyond window x tolerance x frame_dt = 3.3 mm), does not;
    without the window all three move; new positions (set_positions) forget the history."""
    verts, faces = grid_cloth(3, 3, 0.2, 0.2)
    builder = ClothBuilder()
    for _ in range(3):
        builder.add_garment(verts, faces)
    model = builder.finalize(device, features=Features(body_contact=False))
    base = model.particle_q_rest_np.astype(np.float32)
    world = model.particle_world_np
    n = np.bincount(world)

    def frame_positions(t: int) -> np.ndarray:
        q = base.copy()
        q[world == 0, 1] += 0.002 * (t % 2)  # period 2, 2 mm
        q[world == 1, 1] += 0.002 * t  # drift, 2 mm per frame
        q[world == 2, 1] += 0.01 * (t % 2)  # period 2, 1 cm
        return q

    def fast_counts(window: int, frames: int, reset_at: int | None = None) -> list[np.ndarray]:
        sim = QuasiStaticSimulator(model, None, settings=unit_settings(tolerance=0.05, limit_cycle_window=window))
        qd = np.zeros_like(base)
        qd[:, 1] = 0.12
        out = []
        for t in range(frames):
            if t == reset_at:
                sim.set_positions(frame_positions(t)[world == 0], world=0)
            sim.state_0.particle_q.assign(frame_positions(t))
            sim.state_0.particle_qd.assign(qd)
            sim._measure()
            out.append(sim.world_fast_count.numpy().copy())
        return out

    counts = fast_counts(4, 8)
    for t in range(4):  # history not yet full of the particle's own positions
        np.testing.assert_array_equal(counts[t], n)
    for t in range(4, 8):
        np.testing.assert_array_equal(counts[t], [0, n[1], n[2]])
    for c in fast_counts(0, 8):
        np.testing.assert_array_equal(c, n)
    after_reset = fast_counts(4, 12, reset_at=6)
    np.testing.assert_array_equal(after_reset[5][0], 0)
    for t in range(6, 10):
        assert after_reset[t][0] == n[0], (t, after_reset[t])
    np.testing.assert_array_equal(after_reset[11][0], 0)
    with pytest.raises(ValueError, match="limit_cycle_window"):
        SimSettings(limit_cycle_window=-1)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("solver, shared", [("xpbd", True), ("xpbd", False), ("mass_spring", None)])
def test_a_world_that_adopts_another_garment_steps_as_a_world_built_with_it(device: str, solver: str,
                                                                             shared: bool | None) -> None:
    """``adopt_garment``: world 1 takes world 0's garment (rest shape, fabric) in place and then
    steps bit for bit as world 1 of a batch built with that garment: XPBD in the tiled sweep
    (which then reads world 0's element data) and in global memory, with body and self-contact
    on; mass-spring (which reads the model's arrays at every step) with body contact."""
    v, f = grid_cloth(8, 8, 0.4, 0.4, plane="xz", origin=(-0.2, 0.3, -0.2))
    loose = (1.03 * v).astype(np.float32)
    sv, sf = icosphere(0.25, subdivisions=2)
    xpbd = solver == "xpbd"

    def make(garments):
        builder = ClothBuilder()
        for verts, fab, *faces in garments:
            builder.add_garment(verts, faces[0] if faces else f, fabric=fab)
        model = builder.finalize(device, features=Features(self_contact=xpbd, friction=True))
        collider = BodyCollider(sv, sf, device=device, world_count=len(garments))
        options = {"gs_shared": shared, "gs_block_dim": 64} if xpbd else {}
        return QuasiStaticSimulator(model, collider, solver=solver, settings=unit_settings(substeps=4, iterations=4),
                                    solver_options=options)

    swapped = make([(v, "cotton"), (loose, "silk"), (loose, "silk")])
    built = make([(v, "cotton"), (v, "cotton"), (loose, "silk")])
    for _ in range(3):
        swapped.step_frame()
        built.step_frame()
    swapped.adopt_garment(1, 0)
    if shared:
        assert swapped.solver.element_data_source.tolist() == [0, 0, 2]
    assert swapped.model.fabrics[1].name == "cotton"
    if xpbd:
        np.testing.assert_array_equal(swapped.solver.self_contact.rest.numpy(),
                                      built.solver.self_contact.rest.numpy())
    for sim in (swapped, built):
        sim.revive(1, v)
    for _ in range(8):
        swapped.step_frame()
        built.step_frame()
    one = built.model.world_slice(1)
    assert np.abs(built.positions()[one] - v).max() > 0.05, "the cloth did not move"
    # world 2 read world 1's copy of the loose garment before: it reads its own now
    np.testing.assert_array_equal(swapped.positions(), built.positions())
    small_v, small_f = grid_cloth(7, 7, 0.4, 0.4, plane="xz")
    other = make([(v, "cotton"), (small_v, "silk", small_f)])
    with pytest.raises(ValueError, match="same triangles"):
        other.adopt_garment(1, 0)


@pytest.mark.parametrize("solver", ["xpbd", "vbd"])
def test_garments_held_by_the_same_particles_swap_and_step_as_built(solver: str) -> None:
    """Bottoms are held by their waistband: world 1 takes world 0's garment where both attach the
    same particles (each world keeps its attachment slots, whose targets the caller sets) and then
    steps bit for bit as a batch built with that garment; garments attached at different particles
    refuse the swap by name."""
    v, f = grid_cloth(6, 6, 0.3, 0.3, plane="xy", origin=(-0.15, 0.0, 0.0))
    loose = (1.05 * v).astype(np.float32)
    top = np.nonzero(v[:, 1] > v[:, 1].max() - 1e-6)[0]

    def make(garments, attached=(top, top)):
        builder = ClothBuilder()
        for (verts, fab), held in zip(garments, attached):
            builder.add_garment(verts, f, fabric=fab, attached=held)
        model = builder.finalize("cpu", features=Features(friction=False))
        return QuasiStaticSimulator(model, None, solver=solver, settings=unit_settings(substeps=4, iterations=4))

    swapped = make([(v, "cotton"), (loose, "silk")])
    built = make([(v, "cotton"), (v, "cotton")])
    targets = np.concatenate([v[top], v[top] + np.array([0.0, 0.02, 0.0], np.float32)])
    for sim in (swapped, built):
        sim.control.set_attachment_targets(targets)
        sim.step_frame()
    swapped.adopt_garment(1, 0)
    assert swapped.model.fabrics[1].name == "cotton"
    for sim in (swapped, built):
        sim.revive(1, v)
    for _ in range(6):
        swapped.step_frame()
        built.step_frame()
    one = built.model.world_slice(1)
    assert np.abs(built.positions()[one] - v).max() > 0.01, "the cloth did not move"
    np.testing.assert_array_equal(swapped.positions(), built.positions())
    other = make([(v, "cotton"), (v, "cotton")], attached=(top, top[:-1]))
    with pytest.raises(ValueError, match="attach different particles"):
        other.adopt_garment(1, 0)
