"""CI version of ``drape report stability``: four cells on a towel over a capsule (CPU, CUDA where present).

The cells declared supported for the capsule scene must pass; the heat map and the supported/failed
bookkeeping are checked on the same run."""
from __future__ import annotations

import pytest
import warp as wp

from simulate.reports.scenes import build_scene
from simulate.reports.stability import (CUDA_EXCEPTIONS, SUPPORTED, failing_supported, supported_cells, format_table, plot_heatmap, run_stability,
                                        stability_cases, unexpected_passes)

wp.init()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


@pytest.mark.parametrize("device", DEVICES)
def test_supported_ci_cells_pass(device: str, tmp_path) -> None:
    scene = build_scene(body="capsule", resolution=60)
    cases = stability_cases(scene, "ci")
    assert {c.family for c in cases} == {"stretch", "fabric", "timestep", "transition"}
    report = run_stability(scene, cases, device=device, max_frames=200)
    assert report["canonical_drape"]["status"] == "CONVERGED", report["canonical_drape"]
    declared = SUPPORTED[scene.name]
    for cell in report["cells"]:
        assert cell["declared"], f"{cell['cell']} is not declared in SUPPORTED[{scene.name!r}]"
    assert not failing_supported(report), "supported cells failed:\n" + format_table(report)
    assert not unexpected_passes(report), "cells declared unsupported passed:\n" + format_table(report)
    assert all(declared[c.cell][0] for c in cases), "every CI cell is meant to be supported on the capsule"
    png = plot_heatmap(report, tmp_path / "heat.png")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_failed_cell_is_reported_against_the_table() -> None:
    report = {"cells": [{"cell": "a/1", "supported": True, "passed": False},
                        {"cell": "b/2", "supported": False, "passed": True},
                        {"cell": "c/3", "supported": True, "passed": True}]}
    assert [c["cell"] for c in failing_supported(report)] == ["a/1"]
    assert [c["cell"] for c in unexpected_passes(report)] == ["b/2"]


def test_cuda_exceptions_are_declared_cells_and_unsupported_on_cuda_only() -> None:
    for name, cells in CUDA_EXCEPTIONS.items():
        cpu, cuda = supported_cells(name, "cpu"), supported_cells(name, "cuda:0")
        for cell in cells:
            assert SUPPORTED[name][cell][0], f"{name}: {cell} is a CUDA exception but not supported on CPU either"
            assert cpu[cell][0] and not cuda[cell][0] and cuda[cell][1].startswith("on CUDA: "), (cell, cpu[cell], cuda[cell])
        same = [c for c in SUPPORTED[name] if c not in cells]
        assert all(cpu[c] == cuda[c] for c in same), f"{name}: cells outside the exceptions differ between devices"


def test_every_declared_cell_exists_and_bad_sizes_raise() -> None:
    scene = build_scene(body="capsule", resolution=60)
    with pytest.raises(ValueError, match="size"):
        stability_cases(scene, "medium")
    with pytest.raises(ValueError, match="anny"):
        stability_cases(scene, "small")
    for name, table in SUPPORTED.items():
        for cell, (ok, why) in table.items():
            assert "/" in cell and isinstance(ok, bool), f"{name}: bad entry {cell!r}"
            assert ok or why, f"{name}: unsupported cell {cell} must say why"


def test_every_full_matrix_cell_of_the_default_scene_is_declared() -> None:
    """The cells of ``--size full`` on the default scene all have a SUPPORTED entry (no silent 'undeclared')."""
    import numpy as np

    from simulate.reports.scenes import Scene
    from simulate.reports.stability import DEFAULT_SCENE

    names = ["gender", "age", "muscle", "weight", "height", "proportions"]  # anny's shape parameters
    fake = Scene(name=DEFAULT_SCENE, garment="shawl", body_kind="anny", rest_vertices=np.zeros((3, 3)),
                 start_vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]), body_faces=np.array([[0, 1, 2]]),
                 body_vertex_count=3, canonical_pose=np.zeros(60, np.float32), neutral_shape=np.full(6, 0.5, np.float32),
                 shape_ranges=np.tile([0.0, 1.0], (6, 1)).astype(np.float32), shape_names=names,
                 _pose_fn=lambda s, p: (np.zeros((len(s), 3, 3)), np.zeros((len(s), 3))))
    table = SUPPORTED[DEFAULT_SCENE]
    for size in ("small", "full"):
        cells = [c.cell for c in stability_cases(fake, size)]
        assert len(cells) == len(set(cells)), f"{size}: duplicate cells"
        missing = [c for c in cells if c not in table]
        assert not missing, f"{size}: cells without a SUPPORTED entry: {missing}"
    families = {c.split("/")[0] for c in table}
    assert families == {"stretch", "bending", "timestep", "fabric", "pose", "shape", "transition"}
