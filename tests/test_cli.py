"""The `drape` entry point: help for every subcommand, info, body, clear errors."""
from __future__ import annotations

import json

import pytest

from pipelines.cli import SUBCOMMAND_MODULES, main


@pytest.mark.parametrize("command", [name for name, _, _ in SUBCOMMAND_MODULES])
def test_every_subcommand_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert "usage: drape" in capsys.readouterr().out


def test_info_reports_versions_and_devices(capsys):
    assert main(["info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["packages"]["warp-lang"] and info["packages"]["torch"]
    assert "cpu" in info["warp_devices"][0] and info["warp_kernel_cache"]


def test_body_writes_mesh_and_preview(tmp_path, capsys, anny_body):
    out, png = tmp_path / "b.ply", tmp_path / "b.png"
    assert main(["body", "--set", "height=0.9", "--joint", "left_shoulder=0,0,1.2", "--out", str(out), "--preview", str(png)]) == 0
    summary = json.loads(capsys.readouterr().out)
    import trimesh

    mesh = trimesh.load(out, process=False)
    assert len(mesh.vertices) == summary["vertices"] == 13718
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"


def test_body_bad_input_exits_2_naming_the_field(tmp_path, capsys, anny_body):
    assert main(["body", "--set", "wingspan=0.3", "--out", str(tmp_path / "x.obj")]) == 2
    assert "unknown shape parameter 'wingspan'" in capsys.readouterr().err
    assert main(["body", "--joint", "tail=0,0,1", "--out", str(tmp_path / "x.obj")]) == 2
    assert "unknown joint name 'tail'" in capsys.readouterr().err
    assert main(["body", "--set", "height=1.5", "--out", str(tmp_path / "x.obj")]) == 2
    assert "outside its range" in capsys.readouterr().err
