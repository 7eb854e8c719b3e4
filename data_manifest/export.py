"""Export one task's sequence for viewing in Blender or MeshLab.

Formats: ``obj`` (one Wavefront OBJ per frame, with the template faces and UVs when the
template has them), ``ply`` (one binary little-endian PLY per frame), ``pc2`` (one Blender
point-cache file for the whole sequence; apply it with a Mesh Cache modifier to the OBJ of
the first frame). Positions are the posed garment vertices [m], float32.

PC2 layout (little endian): ``b'POINTCACHE2\\0'`` (12 bytes), int32 version (1), int32
point count, float32 start frame, float32 sample rate, int32 sample count, then float32
x, y, z for every point of every sample.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from .reader import DatasetReader
from .schema import check_task_id

EXPORT_FORMATS = ("obj", "ply", "pc2")
PC2_MAGIC = b"POINTCACHE2\0"
PC2_VERSION = 1
_PC2_HEADER = struct.Struct("<12siiffi")


def write_pc2(path: str | os.PathLike[str], positions: np.ndarray, *, start_frame: float = 0.0,
              sample_rate: float = 1.0) -> Path:
    """Write positions [m], shape (sample_count, point_count, 3), as a PC2 point cache."""
    positions = np.asarray(positions, dtype="<f4")
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise ValueError(f"PC2 positions must have shape (samples, points, 3) (got {positions.shape})")
    if not sample_rate > 0:
        raise ValueError(f"PC2 sample_rate must be > 0 (got {sample_rate})")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as handle:
        handle.write(_PC2_HEADER.pack(PC2_MAGIC, PC2_VERSION, positions.shape[1], float(start_frame),
                                      float(sample_rate), positions.shape[0]))
        handle.write(np.ascontiguousarray(positions).tobytes())
    return path


def read_pc2(path: str | os.PathLike[str]) -> tuple[np.ndarray, float, float]:
    """Read a PC2 file: (positions (samples, points, 3) float32, start frame, sample rate)."""
    data = Path(path).read_bytes()
    if len(data) < _PC2_HEADER.size:
        raise ValueError(f"{str(path)!r} is too short for a PC2 header ({len(data)} bytes)")
    magic, version, points, start, rate, samples = _PC2_HEADER.unpack_from(data)
    if magic != PC2_MAGIC or version != PC2_VERSION:
        raise ValueError(f"{str(path)!r} is not a PC2 v1 file (magic {magic!r}, version {version})")
    expected = _PC2_HEADER.size + samples * points * 12
    if len(data) != expected:
        raise ValueError(f"{str(path)!r} has {len(data)} bytes, a PC2 of {samples} samples x {points} points "
                         f"needs {expected}")
    positions = np.frombuffer(data, dtype="<f4", offset=_PC2_HEADER.size).reshape(samples, points, 3)
    return positions.astype(np.float32), start, rate


def write_obj(path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray, *,
              uv: np.ndarray | None = None) -> Path:
    """Write one mesh as OBJ: vertices [m] (V, 3), faces (Fc, 3) 0-based, optional uv (V, 2)."""
    path = Path(path)
    lines = [f"# drape garment frame, {len(vertices)} vertices, {len(faces)} faces, metres"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, dtype=np.float64)]
    one = np.asarray(faces, dtype=np.int64) + 1
    if uv is not None:
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in np.asarray(uv, dtype=np.float64)]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in one]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in one]
    path.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path


def write_ply(path: str | os.PathLike[str], vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write one mesh as binary little-endian PLY: float32 x y z per vertex, faces as
    uchar-count int32-index lists."""
    vertices = np.asarray(vertices, dtype="<f4")
    faces = np.asarray(faces, dtype="<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment drape garment frame, metres\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face_records = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face_records["n"] = 3
    face_records["idx"] = faces
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(np.ascontiguousarray(vertices).tobytes())
        handle.write(face_records.tobytes())
    return Path(path)


def export_task(
    root: str | os.PathLike[str],
    task_id: str,
    *,
    format: str,
    out: str | os.PathLike[str],
    sample_rate: float = 1.0,
) -> list[Path]:
    """Export the posed garment of every kept frame of ``task_id``.

    obj / ply: ``out`` is a directory (created), files ``<task_id>_<frame_index:06d>.<ext>``.
    pc2: ``out`` is the file to write (``.pc2`` appended if missing); the start frame is the
    first kept frame's sequence index. Returns the written paths.
    """
    if format not in EXPORT_FORMATS:
        raise ValueError(f"export format must be one of {EXPORT_FORMATS} (got {format!r})")
    check_task_id(task_id, where="task id")
    with DatasetReader(root) as reader:
        template = reader.template
        arrays = reader.load_task(task_id)
    positions = arrays["posed_vertices"]  # (F, V, 3)
    frame_index = arrays["frame_index"]  # (F,)
    out = Path(out)
    if format == "pc2":
        if out.suffix != ".pc2":
            out = out.with_name(out.name + ".pc2")
        start = float(frame_index[0]) if frame_index.size else 0.0
        return [write_pc2(out, positions, start_frame=start, sample_rate=sample_rate)]
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for frame, vertices in zip(frame_index, positions):
        path = out / f"{task_id}_{int(frame):06d}.{format}"
        if format == "obj":
            written.append(write_obj(path, vertices, template["faces"], uv=template.get("uv")))
        else:
            written.append(write_ply(path, vertices, template["faces"]))
    return written
