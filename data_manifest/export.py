"""Export one task's sequence for viewing in Blender or MeshLab.

Formats: ``obj`` (one Wavefront OBJ per frame, with the template faces and UVs when the
template has them), ``ply`` (one binary little-endian PLY per frame), ``pc2`` (one Blender
point-cache file for the whole sequence; apply it with a Mesh Cache modifier to the OBJ of
the first frame), ``pc16`` (CLOTH3D's point cache, seed 004 section 3.6: the PC2 layout with
float16 positions relative to the body's root joint, plus the faces and the root trajectory
beside it; ``read_pc16`` / ``import_pc16`` read it back). Positions are the posed garment
vertices [m], float32 (pc16: float16).

PC2 layout (little endian): ``b'POINTCACHE2\\0'`` (12 bytes), int32 version (1), int32
point count, float32 start frame, float32 sample rate, int32 sample count, then float32
x, y, z for every point of every sample.

PC16 layout: the same 32-byte header, then float16 x, y, z (little endian) for every point of
every sample, each relative to the body's root joint (pelvis) in that sample [m]: a body-sized
garment stays within 1 m of it, where float16 keeps 0.24 mm (2**-12 m). Beside ``NAME.pc16``:
``NAME.faces.npy`` (Fc, 3) uint16 triangles (0-based vertex indices; a garment of at most 65,536
vertices) and ``NAME.root.npy`` (samples, 3) float32, the root joint's world position [m] per sample.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from .reader import DatasetReader
from .schema import check_task_id

EXPORT_FORMATS = ("obj", "ply", "pc2", "pc16")
PC2_MAGIC = b"POINTCACHE2\0"
PC2_VERSION = 1
_PC2_HEADER = struct.Struct("<12siiffi")
PC16_MAX_ABS_M = 60000.0
"""Largest |coordinate| [m] float16 holds (65504, rounded down); a body-sized garment relative to
its root joint stays within 1 m, where the float16 step is 2**-11 m and the error half of it."""


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


def _read_point_cache(path: str | os.PathLike[str], kind: str, dtype: str) -> tuple[np.ndarray, float, float]:
    """A point cache with the PC2 header and ``dtype`` xyz values (``<f4``: PC2, ``<f2``: PC16):
    (positions (samples, points, 3) float32, start frame, sample rate). Raises ValueError naming
    the file for a wrong header or size."""
    data = Path(path).read_bytes()
    if len(data) < _PC2_HEADER.size:
        raise ValueError(f"{str(path)!r} is too short for a {kind} header ({len(data)} bytes, expected {_PC2_HEADER.size})")
    magic, version, points, start, rate, samples = _PC2_HEADER.unpack_from(data)
    if magic != PC2_MAGIC or version != PC2_VERSION:
        raise ValueError(f"{str(path)!r} is not a {kind} file (magic {magic!r}, version {version}; expected "
                         f"{PC2_MAGIC!r}, {PC2_VERSION})")
    if points < 0 or samples < 0:
        raise ValueError(f"{str(path)!r} has a {kind} header of {points} points and {samples} samples")
    expected = _PC2_HEADER.size + samples * points * 3 * np.dtype(dtype).itemsize
    if len(data) != expected:
        raise ValueError(f"{str(path)!r} has {len(data)} bytes, a {kind} of {samples} samples x {points} points "
                         f"needs {expected}")
    values = np.frombuffer(data, dtype=dtype, offset=_PC2_HEADER.size).reshape(samples, points, 3)
    return values.astype(np.float32), start, rate


def read_pc2(path: str | os.PathLike[str]) -> tuple[np.ndarray, float, float]:
    """Read a PC2 file: (positions (samples, points, 3) float32, start frame, sample rate)."""
    return _read_point_cache(path, "PC2", "<f4")


def write_pc16(path: str | os.PathLike[str], positions: np.ndarray, root: np.ndarray, faces: np.ndarray, *,
               start_frame: float = 0.0, sample_rate: float = 1.0) -> list[Path]:
    """Write a PC16 point cache (module docstring) and its faces and root trajectory beside it.

    Args:
        path: the ``.pc16`` file; ``.faces.npy`` and ``.root.npy`` go next to it with its stem.
        positions: garment vertices in world space [m], (samples, points, 3).
        root: the body's root joint in world space [m] per sample, (samples, 3).
        faces: triangles (Fc, 3), 0-based, indices below 65,536.
        start_frame: the first sample's frame number; sample_rate: frames per sample (> 0).
    Returns:
        the written paths: the .pc16, the faces and the root trajectory.
    """
    positions = np.asarray(positions, dtype=np.float64)
    root = np.asarray(root, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[1] == 0:
        raise ValueError(f"PC16 positions must have shape (samples, points, 3) (got {positions.shape})")
    if root.shape != (positions.shape[0], 3):
        raise ValueError(f"PC16 root must have shape ({positions.shape[0]}, 3), one root joint per sample (got {root.shape})")
    if not (np.isfinite(positions).all() and np.isfinite(root).all()):
        raise ValueError("PC16 positions and root must be finite")
    if not (np.isfinite(sample_rate) and sample_rate > 0):
        raise ValueError(f"PC16 sample_rate must be > 0 (got {sample_rate})")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"PC16 faces must be integer triangles (Fc, 3) (got {faces.dtype} {faces.shape})")
    if positions.shape[1] > 65536 or (faces.size and (faces.min() < 0 or faces.max() >= positions.shape[1])):
        raise ValueError(f"PC16 faces are uint16: a garment of at most 65,536 vertices whose faces index them "
                         f"(got {positions.shape[1]} vertices, face indices in [{faces.min()}, {faces.max()}])")
    relative = positions - root[:, None, :]
    largest = float(np.abs(relative).max()) if relative.size else 0.0
    if largest > PC16_MAX_ABS_M:
        raise ValueError(f"PC16 positions reach {largest:.3g} m from the root joint; float16 holds at most "
                         f"{PC16_MAX_ABS_M:g} (export pc2 instead)")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.with_suffix("")
    faces_path, root_path = Path(f"{stem}.faces.npy"), Path(f"{stem}.root.npy")
    header = _PC2_HEADER.pack(PC2_MAGIC, PC2_VERSION, positions.shape[1], float(start_frame), float(sample_rate),
                              positions.shape[0])
    for target, write in ((path, lambda h: (h.write(header), h.write(relative.astype("<f2").tobytes()))),
                          (faces_path, lambda h: np.save(h, faces.astype("<u2"))),
                          (root_path, lambda h: np.save(h, root.astype("<f4")))):
        tmp = target.with_name(target.name + ".tmp")
        try:  # a reader never finds a half-written file under the final name
            with open(tmp, "wb") as handle:
                write(handle)
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    return [path, faces_path, root_path]


def read_pc16(path: str | os.PathLike[str]) -> tuple[np.ndarray, float, float]:
    """Read a PC16 file: (positions relative to the root joint (samples, points, 3) float32 [m],
    start frame, sample rate). Raises ValueError naming the file for a wrong header or size."""
    return _read_point_cache(path, "PC16", "<f2")


def import_pc16(path: str | os.PathLike[str]) -> dict[str, np.ndarray | float]:
    """Read a PC16 export back (``write_pc16``): ``relative`` (samples, points, 3) float32 [m] as
    stored, ``faces`` (Fc, 3) int64 and, where ``NAME.root.npy`` lies beside it, ``root`` (samples, 3)
    and ``positions`` (samples, points, 3) in world space [m]; ``start_frame``, ``sample_rate``."""
    path = Path(path)
    relative, start, rate = read_pc16(path)
    stem = path.with_suffix("")
    faces_path, root_path = Path(f"{stem}.faces.npy"), Path(f"{stem}.root.npy")
    if not faces_path.is_file():
        raise FileNotFoundError(f"the faces of {str(path)!r} are missing: expected {str(faces_path)!r} beside it")
    faces = np.load(faces_path, allow_pickle=False)
    if faces.dtype != np.dtype("<u2") or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{str(faces_path)!r} must hold uint16 triangles (Fc, 3) (got {faces.dtype} {faces.shape})")
    if faces.size and faces.max() >= relative.shape[1]:
        raise ValueError(f"{str(faces_path)!r} indexes vertex {int(faces.max())} but {str(path)!r} has {relative.shape[1]}")
    out: dict[str, np.ndarray | float] = {"relative": relative, "faces": faces.astype(np.int64),
                                          "start_frame": start, "sample_rate": rate}
    if root_path.is_file():
        root = np.load(root_path, allow_pickle=False).astype(np.float32)
        if root.shape != (relative.shape[0], 3):
            raise ValueError(f"{str(root_path)!r} must have shape ({relative.shape[0]}, 3) (got {root.shape})")
        out["root"] = root
        out["positions"] = relative + root[:, None, :]
    return out


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
    first kept frame's sequence index. pc16: ``out`` is the ``.pc16`` file (appended if missing),
    written with its faces and root trajectory beside it (``write_pc16``); the shard must store the
    root joint per frame (``root_joint``: motion datasets do) and its kept frames must be
    consecutive (a point cache has no gaps). Returns the written paths.
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
    if format == "pc16":
        if "root_joint" not in arrays:
            raise ValueError(f"task {task_id!r}: its shard stores no root joint per frame (root_joint), and "
                             f"PC16 positions are relative to it; datasets of motion sequences store it "
                             f"(docs/motion.md), or export --format pc2")
        if frame_index.size == 0:
            raise ValueError(f"task {task_id!r} has no kept frame to export")
        gaps = np.nonzero(np.diff(frame_index) != 1)[0]
        if gaps.size:
            g = int(gaps[0])
            raise ValueError(f"task {task_id!r}: its kept frames are not consecutive (frame {int(frame_index[g])} is "
                             f"followed by {int(frame_index[g + 1])}; {int(gaps.size)} gap(s) where the filters dropped "
                             f"frames) and a point cache holds consecutive samples; export --format pc2 or obj")
        if out.suffix != ".pc16":
            out = out.with_name(out.name + ".pc16")
        return write_pc16(out, positions, arrays["root_joint"], template["faces"],
                          start_frame=float(frame_index[0]), sample_rate=sample_rate)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for frame, vertices in zip(frame_index, positions):
        path = out / f"{task_id}_{int(frame):06d}.{format}"
        if format == "obj":
            written.append(write_obj(path, vertices, template["faces"], uv=template.get("uv")))
        else:
            written.append(write_ply(path, vertices, template["faces"]))
    return written
