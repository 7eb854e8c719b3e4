"""The garment CLI module (``drape garment``, ``drape style-space``) run in-process with
small settings."""
from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from pipelines import garment as garment_cli


def _parse(argv):
    parser = argparse.ArgumentParser(prog="drape")
    garment_cli.register(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_garment_writes_meshes_and_preview(tmp_path, capsys, anny_body):
    import trimesh

    out = tmp_path / "skirt.obj"
    args = _parse(["garment", "--type", "skirt", "--style", "length=0.3,width_profile=0.1", "--resolution", "300",
                   "--out", str(out), "--preview", str(tmp_path / "skirt.png"), "--max-frames", "300"])
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["status"] == "CONVERGED" and summary["max_penetration_mm"] <= 1.0
    mesh = trimesh.load(out, process=False)
    assert len(mesh.vertices) == summary["vertices"]
    body = trimesh.load(tmp_path / "skirt_body.obj", process=False)
    assert len(body.vertices) == anny_body.vertex_count
    assert (tmp_path / "skirt.png").stat().st_size > 1000


def test_garment_no_drape_and_errors(tmp_path, capsys):
    args = _parse(["garment", "--type", "shorts", "--resolution", "300", "--no-drape", "--out", str(tmp_path / "s.ply")])
    assert args.func(args) == 0
    assert "status" not in json.loads(capsys.readouterr().out)
    bad = _parse(["garment", "--type", "shorts", "--style", "sleeve_length=0.5", "--out", str(tmp_path / "x.obj")])
    with pytest.raises(ValueError, match="leg_length"):
        bad.func(bad)
    bad = _parse(["garment", "--type", "shorts", "--shape", "0.5,0.5", "--out", str(tmp_path / "x.obj")])
    with pytest.raises(ValueError, match="--shape must have 6 values"):
        bad.func(bad)
    bad = _parse(["garment", "--type", "shorts", "--out", str(tmp_path / "x.stl")])
    with pytest.raises(ValueError, match=r"\.obj or \.ply"):
        bad.func(bad)


def test_style_space_command(tmp_path, capsys):
    args = _parse(["style-space", "--type", "skirt", "--samples", "3", "--rounds", "2", "--components", "2",
                   "--resolution", "200", "--prototype-styles", "1", "--prototypes", "5", "--max-frames", "200",
                   "--out", str(tmp_path)])
    assert args.func(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["pairs"] == 9 and len(set(summary["prototype_indices"])) == 5
    errors = np.array(summary["mean_error_mm"])
    assert (np.diff(errors) <= 1e-9).all()
    for name in ("template.npz", "style_space.npz", "prototypes.npz", "prototype_error.png", "style_components.png",
                 "summary.json"):
        assert (tmp_path / name).exists(), name


def test_register_fills_placeholders():
    parser = argparse.ArgumentParser(prog="drape")
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("style-space", help="placeholder")
    garment_cli.register(sub)
    args = parser.parse_args(["style-space", "--type", "skirt", "--out", "x"])
    assert args.func is garment_cli.run_style_space and args.samples == 20 and args.rounds == 2
