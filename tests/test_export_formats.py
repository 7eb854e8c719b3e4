"""Export: PC2 parsed back with plain numpy equals the stored sequence; OBJ and PLY files
carry the frame's vertices and the template faces."""

from __future__ import annotations

import numpy as np
import pytest

from data_manifest.cli import main as cli_main
from data_manifest.export import export_task, read_pc2
from data_manifest.reader import DatasetReader
from data_manifest.synthetic import write_synthetic_dataset

OBJ_ATOL_M = 1e-6
"""OBJ stores 6 decimals [m]."""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    write_synthetic_dataset(root, splits={"train": 1, "test": 1}, frames_per_task=3, precision="float16")
    reader = DatasetReader(root)
    return root, reader.load_task("train-000"), reader.template


def test_pc2_round_trip_parsed_with_numpy(dataset, tmp_path):
    root, frames, _ = dataset
    (path,) = export_task(root, "train-000", format="pc2", out=tmp_path / "seq", sample_rate=0.5)
    assert path.name == "seq.pc2"
    raw = path.read_bytes()
    assert raw[:12] == b"POINTCACHE2\0"
    header = np.frombuffer(raw, dtype="<i4", count=2, offset=12)  # version, points
    start, rate = np.frombuffer(raw, dtype="<f4", count=2, offset=20)
    samples = int(np.frombuffer(raw, dtype="<i4", count=1, offset=28)[0])
    assert header.tolist() == [1, 50] and samples == 3, f"header {header.tolist()}, samples {samples}"
    assert start == frames["frame_index"][0] and rate == np.float32(0.5)
    positions = np.frombuffer(raw, dtype="<f4", offset=32).reshape(samples, 50, 3)
    np.testing.assert_array_equal(positions, frames["posed_vertices"], err_msg="PC2 positions differ")
    parsed, parsed_start, parsed_rate = read_pc2(path)
    np.testing.assert_array_equal(parsed, positions)
    assert (parsed_start, parsed_rate) == (float(start), 0.5)


def test_obj_per_frame(dataset, tmp_path):
    root, frames, template = dataset
    paths = export_task(root, "train-000", format="obj", out=tmp_path / "obj")
    assert [p.name for p in paths] == [f"train-000_{k:06d}.obj" for k in frames["frame_index"]]
    for path, expected in zip(paths, frames["posed_vertices"]):
        lines = path.read_text().splitlines()
        vertices = np.array([[float(x) for x in line.split()[1:]] for line in lines if line.startswith("v ")])
        faces = np.array([[int(c.split("/")[0]) for c in line.split()[1:]] for line in lines if line.startswith("f ")])
        uv_count = sum(line.startswith("vt ") for line in lines)
        np.testing.assert_allclose(vertices, expected, atol=OBJ_ATOL_M, err_msg=f"{path.name} vertices")
        np.testing.assert_array_equal(faces - 1, template["faces"], err_msg=f"{path.name} faces")
        assert uv_count == 50


def test_ply_per_frame(dataset, tmp_path):
    root, frames, template = dataset
    paths = export_task(root, "train-000", format="ply", out=tmp_path / "ply")
    raw = paths[1].read_bytes()
    header_end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:header_end].decode("ascii")
    assert "format binary_little_endian 1.0" in header and "element vertex 50" in header
    face_count = len(template["faces"])
    assert f"element face {face_count}" in header
    vertices = np.frombuffer(raw, dtype="<f4", count=150, offset=header_end).reshape(50, 3)
    faces = np.frombuffer(raw, dtype=[("n", "u1"), ("idx", "<i4", (3,))], offset=header_end + 600)
    np.testing.assert_array_equal(vertices, frames["posed_vertices"][1])
    assert (faces["n"] == 3).all() and len(faces) == face_count
    np.testing.assert_array_equal(faces["idx"], template["faces"])


def test_export_errors_and_cli(dataset, tmp_path, capsys):
    root, _, _ = dataset
    with pytest.raises(ValueError, match="export format must be one of"):
        export_task(root, "train-000", format="fbx", out=tmp_path)
    with pytest.raises(ValueError, match="task 'nope' has no shard"):
        export_task(root, "nope", format="obj", out=tmp_path)
    assert cli_main(["dataset", "export", str(root), "--task", "test-000", "--format", "pc2",
                     "--out", str(tmp_path / "t.pc2")]) == 0
    assert read_pc2(tmp_path / "t.pc2")[0].shape == (3, 50, 3)
    assert cli_main(["dataset", "export", str(root), "--task", "nope", "--format", "obj",
                     "--out", str(tmp_path / "x")]) == 2  # bad input (an unknown task id)
    assert "nope" in capsys.readouterr().err
