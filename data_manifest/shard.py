"""Writing and checking one HDF5 shard (one task: one garment style on one body shape, a
sequence of poses).

``ShardWriter`` appends frames one at a time to ``<name>.h5.<pid>-<token>.tmp`` in the final
directory and, on ``close()``, flushes, fsyncs, hashes and atomically renames the file to its
final name. If the writer raises, or the process is killed, nothing exists at the final name:
the ``.tmp`` file is never trusted (readers ignore it, ``validate`` reports it as an orphan,
``remove_orphan_temporaries`` deletes it).

Precision. ``float32`` stores posed vertices and displacements as given (cast to float32).
``float16`` (CLOTH3D's PC16 idea) stores them as float16, posed vertices relative to a
per-frame origin (``position_origin`` (F, 3) float32): the body root translation when the
caller passes ``body_translation``, else the centre of the frame's garment bounding box.
With every relative coordinate below ``FLOAT16_MAX_ABS_M`` (2 m) the round-trip error is at
most ``FLOAT16_ERROR_BOUND_M`` (0.49 mm); for a garment within 1 m of its origin it is at
most 0.24 mm. Pose, shape, style, quality and template arrays are always float32 / int32.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

from .schema import (
    BODY_TRANSLATION,
    COMPRESSIONS,
    DROPPED_FRAME_INDEX,
    DROPPED_GROUP,
    DROPPED_POSE,
    DROPPED_REASON,
    EXTRA_GROUP,
    FLOAT16_MAX_ABS_M,
    FRAME_INDEX,
    POSE,
    POSED_VERTICES,
    POSITION_ORIGIN,
    PRECISIONS,
    QUALITY_GROUP,
    READABLE_SCHEMA_VERSIONS,
    ROOT_JOINT,
    SCHEMA_VERSION,
    SHAPE,
    SIZED_SHAPE,
    SHARD_DIR,
    SHARD_FORMAT,
    SHARD_LAYOUT,
    SHARD_SUFFIX,
    STYLE,
    TIGHTNESS,
    TEMPLATE_GROUP,
    TMP_SUFFIX,
    UNPOSED_DISPLACEMENTS,
    VELOCITIES,
    CanonicalTemplate,
    canonical_json,
    canonical_template,
    check_task_id,
    template_sha256,
)

_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")
_SMALL_CHUNK_ROWS = 256  # rows per chunk of the small per-frame arrays (pose, quality, ...)
_HASH_BLOCK_BYTES = 1 << 20
_MAX_TASK_JSON_BYTES = 32 * 1024  # HDF5 compact attributes must stay below 64 KiB
SPACE_RESERVE_BYTES = 16 << 20
"""Free space [B] a shard writer keeps in hand: a frame is refused (ENOSPC, before HDF5 writes a
byte of it) when the disk would keep less. HDF5 flushes its chunk and metadata caches when a
file closes; a write that fails inside HDF5 leaves the library unable to close the file (it
crashes the process at exit), so the writer stops while the temporary can still be closed and
removed cleanly."""


def free_space(directory: str | os.PathLike[str]) -> int | None:
    """Bytes an unprivileged writer may still use on the file system of ``directory``."""
    try:
        stat = os.statvfs(directory)
    except (OSError, AttributeError):
        return None
    return int(stat.f_bavail) * int(stat.f_frsize)


def shard_path(root: str | os.PathLike[str], task_id: str) -> Path:
    """Canonical location of a task's shard: ``root/shards/<task_id>.h5``."""
    return Path(root) / SHARD_DIR / f"{check_task_id(task_id)}{SHARD_SUFFIX}"


def file_sha256(path: str | os.PathLike[str]) -> str:
    """sha256 (hex) of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(_HASH_BLOCK_BYTES):
            digest.update(block)
    return digest.hexdigest()


def fsync_directory(directory: str | os.PathLike[str]) -> None:
    """Persist a rename inside ``directory`` (no-op where directories cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def is_temporary(path: str | os.PathLike[str]) -> bool:
    """True for files that are being written (or were abandoned): never trusted."""
    return str(path).endswith(TMP_SUFFIX)


def remove_orphan_temporaries(root: str | os.PathLike[str], *, older_than_s: float = 0.0) -> list[Path]:
    """Delete ``*.tmp`` files under ``root`` (recursively) last modified more than
    ``older_than_s`` seconds ago; returns the removed paths. Call it when no writer is
    running on ``root`` (at the start of a resumed job), or with a safe ``older_than_s``."""
    removed: list[Path] = []
    now = time.time()
    for path in sorted(Path(root).rglob(f"*{TMP_SUFFIX}")):
        try:
            if path.is_file() and now - path.stat().st_mtime >= older_than_s:
                path.unlink()
                removed.append(path)
        except FileNotFoundError:
            continue
    return removed


@dataclass
class ShardRecord:
    """What the manifest needs to know about a finished shard."""

    task_id: str
    path: Path
    """Absolute (or caller-given) path of the final shard file."""
    sha256: str
    bytes: int
    frame_count: int
    splits: list[str]
    filter_stats: dict[str, int] = field(default_factory=dict)
    """Dropped frames by reason (e.g. ``{"penetration": 3, "nan": 1}``)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds spent per stage (``write_s`` is measured by the writer)."""


def _check_name(name: str, *, where: str) -> str:
    if not isinstance(name, str) or not name or not set(name) <= _NAME_CHARS or name[0] in "._-":
        raise ValueError(
            f"{where} must be a non-empty name of letters, digits, '.', '_' or '-' starting with "
            f"a letter or digit (got {name!r})"
        )
    return name


def _vector(value: Any, *, where: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 1:
        raise ValueError(f"{where} must be a 1-D array (got shape {array.shape})")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{where} must be finite (got {array.tolist()})")
    return array


_TASK_ARRAYS = {"tightness": TIGHTNESS, "sized_shape": SIZED_SHAPE}
"""Optional task keys written as (1-D float32) datasets of their own, like ``shape`` and ``style``."""


def _check_task(task: Mapping[str, Any]) -> dict[str, Any]:
    if not isinstance(task, Mapping):
        raise ValueError(f"task must be a dict (got {type(task).__name__})")
    for key in ("task_id", "garment", "splits", "seed", "shape", "style"):
        if key not in task:
            raise ValueError(f"task.{key} is missing; a task needs task_id, garment, splits, seed, shape, style")
    check_task_id(task["task_id"], where="task.task_id")
    _check_name(task["garment"], where="task.garment")
    splits = task["splits"]
    if isinstance(splits, str) or not isinstance(splits, (list, tuple)):
        raise ValueError(f"task.splits must be a list of split names (got {splits!r})")
    for index, split in enumerate(splits):
        _check_name(split, where=f"task.splits[{index}]")
    if len(set(splits)) != len(splits):
        raise ValueError(f"task.splits must not repeat a split (got {list(splits)})")
    seed = task["seed"]
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"task.seed must be a non-negative integer (got {seed!r})")
    checked = dict(task)
    checked["splits"] = [str(s) for s in splits]
    checked["seed"] = int(seed)
    checked["shape"] = _vector(task["shape"], where="task.shape")
    checked["style"] = _vector(task["style"], where="task.style")
    for key in _TASK_ARRAYS:  # optional per-task vectors, stored as datasets like shape and style
        if task.get(key) is not None:
            checked[key] = _vector(task[key], where=f"task.{key}")
        else:
            checked.pop(key, None)
    return checked


def _json_safe(value: Any) -> Any:
    """Task metadata as JSON: arrays become lists, numpy scalars Python scalars."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


class ShardWriter:
    """Write one task's frames to an HDF5 shard, atomically.

    Use as a context manager::

        with ShardWriter(shard_path(root, task["task_id"]), template=t, task=task) as writer:
            for frame in frames:
                writer.write_frame(posed, unposed, pose, {"penetration": 0.0}, frame_index=k)
            writer.record_dropped("not_converged")
        manifest.add_shard(writer.record)

    ``template``: see ``schema.canonical_template``. ``task``: ``task_id`` (str), ``garment``
    (str), ``splits`` (list of str), ``seed`` (int), ``shape`` (S,), ``style`` (G,), optionally
    ``tightness`` (T,) and ``sized_shape`` (S,) (datasets of their own, like shape and style); other
    JSON-able keys are kept in the ``task_json`` attribute. ``precision``: "float32" or
    "float16" (see module docstring). ``compression``: "gzip" (level ``compression_level``)
    or "lzf". Datasets are chunked one frame per chunk for (F, V, 3) arrays, byte-shuffled
    and fletcher32-checksummed so a corrupted chunk fails loudly on read.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        template: Mapping[str, Any] | CanonicalTemplate,
        task: Mapping[str, Any],
        precision: str = "float32",
        compression: str = "gzip",
        compression_level: int = 1,
    ):
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS} (got {precision!r})")
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {COMPRESSIONS} (got {compression!r})")
        if isinstance(compression_level, bool) or not isinstance(compression_level, int) or not 0 <= compression_level <= 9:
            raise ValueError(f"compression_level must be an integer in [0, 9] (got {compression_level!r})")
        self.path = Path(path)
        if self.path.suffix != SHARD_SUFFIX:
            raise ValueError(f"shard path must end with {SHARD_SUFFIX!r} (got {str(self.path)!r})")
        self.precision = precision
        self.compression = compression
        self.compression_level = compression_level
        self.task = _check_task(task)
        self.task_id: str = self.task["task_id"]
        metadata = {k: v for k, v in self.task.items() if k not in ("shape", "style", *_TASK_ARRAYS)}
        try:
            self._task_json = canonical_json(_json_safe(metadata))
        except (TypeError, ValueError) as error:
            raise ValueError(f"task {self.task_id!r}: the task dict must be JSON-serializable apart from "
                             f"shape and style ({error})") from None
        if len(self._task_json) > _MAX_TASK_JSON_BYTES:
            raise ValueError(f"task {self.task_id!r}: the task dict is {len(self._task_json)} bytes as JSON, more "
                             f"than {_MAX_TASK_JSON_BYTES} (HDF5 attributes are small); keep per-frame arrays such "
                             f"as pose lists out of it and write them with write_frame")
        if isinstance(template, CanonicalTemplate):  # checked and hashed once by the caller
            self.template, self.template_sha256 = dict(template.arrays), template.sha256
        else:
            self.template = canonical_template(template)
            self.template_sha256 = template_sha256(self.template)
        self.vertex_count = int(self.template["rest_vertices"].shape[0])
        self.tmp_path = self.path.with_name(f"{self.path.name}.{os.getpid()}-{secrets.token_hex(4)}{TMP_SUFFIX}")
        self.filter_stats: dict[str, int] = {}
        self.timings: dict[str, float] = {}
        """Seconds per stage; the caller may add its own (e.g. ``simulate_s``) before close."""
        self.record: ShardRecord | None = None
        """Set by ``close()``: the finished shard's manifest entry."""
        self.frame_count = 0
        self._file: h5py.File | None = None
        self._state = "new"  # new -> open -> closed | aborted
        self._start = 0.0
        self._capacity = 0
        self._frame_datasets: dict[str, h5py.Dataset] = {}
        self._pose: list[np.ndarray] = []
        self._frame_index: list[int] = []
        self._quality: dict[str, list[float]] = {}
        self._body_translation: list[np.ndarray] = []
        self._root_joint: list[np.ndarray] = []
        self._has_velocities: bool | None = None  # fixed by the first frame
        self._origin: list[np.ndarray] = []
        self._extra_shapes: dict[str, tuple[int, ...]] = {}
        self._pose_size: int | None = None
        self._dropped_log: list[tuple[int, str, np.ndarray]] = []  # (frame_index, reason, pose)
        self._dropped_unlogged = 0

    # -- lifecycle ------------------------------------------------------------------------

    def __enter__(self) -> "ShardWriter":
        self._ensure_open()
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def _dataset_options(self) -> dict[str, Any]:
        options: dict[str, Any] = {"shuffle": True, "fletcher32": True, "track_times": False}
        if self.compression == "gzip":
            options.update(compression="gzip", compression_opts=self.compression_level)
        else:
            options.update(compression="lzf")
        return options

    def _check_space(self, needed: int) -> None:
        """Raises OSError(ENOSPC) naming the shard when writing ``needed`` more bytes would leave
        less than :data:`SPACE_RESERVE_BYTES` free."""
        free = free_space(self.path.parent)
        if free is not None and free < needed + SPACE_RESERVE_BYTES:
            raise OSError(errno.ENOSPC, f"No space left on device ({free} B free; the shard of task {self.task_id!r} "
                                        f"needs about {needed} B more and keeps {SPACE_RESERVE_BYTES >> 20} MiB in hand "
                                        f"to close its file cleanly)", str(self.tmp_path))

    def _ensure_open(self) -> h5py.File:
        if self._state == "open":
            assert self._file is not None
            return self._file
        if self._state != "new":
            raise ValueError(f"ShardWriter for task {self.task_id!r} is {self._state}; it cannot be reused")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._check_space(sum(int(np.asarray(v).nbytes) for v in self.template.values()))
        self._start = time.perf_counter()
        # track_times=False everywhere and fixed attribute order keep the bytes (and the
        # sha256) identical for identical content, so a resumed run equals a fresh one.
        try:
            # inside the try: an interruption while h5py creates the file (it exists on disk
            # before the handle is returned) still removes it
            handle = h5py.File(self.tmp_path, "w", track_order=False)
            self._file = handle
            self._state = "open"
            attrs = handle.attrs
            attrs["format"] = SHARD_FORMAT
            attrs["schema_version"] = SCHEMA_VERSION
            attrs["task_id"] = self.task_id
            attrs["garment"] = self.task["garment"]
            attrs.create("splits", np.array(self.task["splits"], dtype=h5py.string_dtype()),
                         shape=(len(self.task["splits"]),), dtype=h5py.string_dtype())
            attrs["seed"] = np.int64(self.task["seed"])
            attrs["precision"] = self.precision
            attrs["compression"] = self.compression
            attrs["template_sha256"] = self.template_sha256
            attrs["position_origin_rule"] = "none"
            attrs["task_json"] = self._task_json
            attrs["filter_stats_json"] = "{}"
            options = self._dataset_options()
            handle.create_dataset(SHAPE, data=self.task["shape"].astype(np.float32), **options)
            handle.create_dataset(STYLE, data=self.task["style"].astype(np.float32), **options)
            for key, name in _TASK_ARRAYS.items():
                if key in self.task:
                    handle.create_dataset(name, data=self.task[key].astype(np.float32), **options)
            group = handle.create_group(TEMPLATE_GROUP)
            for key in sorted(self.template):
                group.create_dataset(key, data=self.template[key], **options)
            position_dtype = np.float16 if self.precision == "float16" else np.float32
            for name in (POSED_VERTICES, UNPOSED_DISPLACEMENTS):
                self._frame_datasets[name] = handle.create_dataset(
                    name, shape=(0, self.vertex_count, 3), maxshape=(None, self.vertex_count, 3),
                    chunks=(1, self.vertex_count, 3), dtype=position_dtype, **options)
        except BaseException:
            self.abort()
            raise
        return handle

    def abort(self) -> None:
        """Discard the shard: close and delete the temporary file. Nothing is left at the
        final path by this writer. Safe to call more than once."""
        if self._file is not None:
            try:
                self._file.close()
            except Exception:  # the file may be in a broken state; deleting it is what matters
                pass
            self._file = None
        try:
            self.tmp_path.unlink()
        except FileNotFoundError:
            pass
        if self._state != "closed":
            self._state = "aborted"

    # -- frames ---------------------------------------------------------------------------

    def record_dropped(self, reason: str, count: int = 1, *, frame_index: int | None = None,
                       pose: Any | None = None) -> None:
        """Count ``count`` frames of this task dropped by a filter for ``reason``.

        With ``frame_index`` (the frame's index in the task's sequence) and ``pose`` (P,) [rad]
        the one dropped frame is also logged in the shard's ``dropped`` group, so readers can see
        which poses the filters removed. A shard logs all its dropped frames or none."""
        _check_name(reason, where="dropped frame reason")
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
            raise ValueError(f"dropped frame count for {reason!r} must be a non-negative integer (got {count!r})")
        if (frame_index is None) != (pose is None):
            raise ValueError(f"dropped frame ({reason!r}) of task {self.task_id!r}: give frame_index and pose "
                             f"together, or neither")
        if frame_index is not None:
            where = f"dropped frame ({reason!r}) of task {self.task_id!r}"
            if count != 1:
                raise ValueError(f"{where}: a logged drop counts one frame (got count={count!r})")
            if isinstance(frame_index, bool) or not isinstance(frame_index, (int, np.integer)) or not \
                    0 <= frame_index <= np.iinfo(np.int32).max:
                raise ValueError(f"frame_index of {where} must be a non-negative int32 (got {frame_index!r})")
            pose_array = self._checked_pose(pose, where)
            if self._dropped_unlogged:
                raise ValueError(f"{where}: {self._dropped_unlogged} earlier dropped frames were counted "
                                 f"without frame_index; a shard logs all its dropped frames or none")
            self._dropped_log.append((int(frame_index), reason, pose_array.astype(np.float32)))
        elif count:
            if self._dropped_log:
                raise ValueError(f"dropped frames ({reason!r}) of task {self.task_id!r} need frame_index and pose: "
                                 f"earlier dropped frames were logged, and a shard logs all its dropped frames or none")
            self._dropped_unlogged += int(count)
        self.filter_stats[reason] = self.filter_stats.get(reason, 0) + int(count)

    def _checked_pose(self, pose: Any, where: str) -> np.ndarray:
        """``pose`` as a finite 1-D array of the length fixed by the frames written or logged so far."""
        pose_array = _vector(pose, where=f"pose of {where}")
        known = self._pose_size if self._pose_size is not None else (
            len(self._dropped_log[0][2]) if self._dropped_log else None)
        if known is not None and pose_array.shape[0] != known:
            raise ValueError(f"pose of {where} must have length {known} like earlier frames "
                             f"(got {pose_array.shape[0]})")
        return pose_array

    def _grow(self, needed: int) -> None:
        if needed <= self._capacity:
            return
        capacity = max(8, self._capacity * 2, needed)
        for dataset in self._frame_datasets.values():
            dataset.resize(capacity, axis=0)
        self._capacity = capacity

    def write_frame(
        self,
        posed_vertices: Any,
        unposed_displacements: Any,
        pose: Any,
        quality: Mapping[str, float],
        *,
        frame_index: int | None = None,
        body_translation: Any | None = None,
        velocities: Any | None = None,
        root_joint: Any | None = None,
        **extra: Any,
    ) -> int:
        """Append one kept frame; returns its row in the shard.

        posed_vertices: garment vertices in world space [m], shape (V, 3).
        unposed_displacements: displacements in unposed space [m], shape (V, 3).
        pose: body pose parameters [rad], shape (P,), same P for every frame.
        quality: metric name -> value for this frame, same names for every frame.
        frame_index: index of this frame in the task's sequence (default: previous + 1),
            strictly increasing.
        body_translation: body root (pelvis) translation [m], shape (3,): in every frame or
            in none; float16 shards store posed vertices relative to it.
        velocities: garment vertex velocities [m/s], shape (V, 3): in every frame or in none
            (stored in the shard's precision, as given: not relative to anything).
        root_joint: the body's root joint (pelvis) in world space [m], shape (3,): in every frame
            or in none (PC16 exports positions relative to it).
        extra: further per-frame float arrays (same shape every frame), stored as extra/<name>.
        """
        handle = self._ensure_open()
        self._check_space(2 * self.vertex_count * 3 * 4)
        row = self.frame_count
        where = f"task {self.task_id!r} frame {row}"
        posed = np.asarray(posed_vertices, dtype=np.float64)
        unposed = np.asarray(unposed_displacements, dtype=np.float64)
        velocity = None if velocities is None else np.asarray(velocities, dtype=np.float64)
        if row > 0 and (velocity is not None) != self._has_velocities:
            raise ValueError(f"velocities of {where} must be given in every frame or in none "
                             f"(earlier frames {'had' if self._has_velocities else 'had no'} them)")
        checked = ((POSED_VERTICES, posed), (UNPOSED_DISPLACEMENTS, unposed)) + (
            () if velocity is None else ((VELOCITIES, velocity),))
        for name, array in checked:
            if array.shape != (self.vertex_count, 3):
                raise ValueError(f"{name} of {where} must have shape ({self.vertex_count}, 3) (got {array.shape})")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"{name} of {where} contains NaN or inf; filter such frames before writing")
        pose_array = self._checked_pose(pose, where)
        if not isinstance(quality, Mapping):
            raise ValueError(f"quality of {where} must be a dict metric -> float (got {type(quality).__name__})")
        if row == 0:
            for name in quality:
                _check_name(name, where=f"quality metric name of {where}")
        elif set(quality) != set(self._quality):
            raise ValueError(f"quality of {where} must have the metrics {sorted(self._quality)} like earlier "
                             f"frames (got {sorted(quality)})")
        quality_values: dict[str, float] = {}
        for name, value in quality.items():
            try:
                quality_values[name] = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"quality[{name!r}] of {where} must be a number (got {value!r})") from None
        if frame_index is None:
            frame_index = self._frame_index[-1] + 1 if self._frame_index else 0
        if isinstance(frame_index, bool) or not isinstance(frame_index, (int, np.integer)) or frame_index < 0:
            raise ValueError(f"frame_index of {where} must be a non-negative integer (got {frame_index!r})")
        if self._frame_index and frame_index <= self._frame_index[-1]:
            raise ValueError(f"frame_index of {where} must be > {self._frame_index[-1]} (the previous "
                             f"frame's), got {frame_index}")
        if frame_index > np.iinfo(np.int32).max:
            raise ValueError(f"frame_index of {where} must fit in int32 (got {frame_index})")
        if row > 0 and (body_translation is not None) != bool(self._body_translation):
            raise ValueError(f"body_translation of {where} must be given in every frame or in none "
                             f"(earlier frames {'had' if self._body_translation else 'had no'} it)")
        if row > 0 and (root_joint is not None) != bool(self._root_joint):
            raise ValueError(f"root_joint of {where} must be given in every frame or in none "
                             f"(earlier frames {'had' if self._root_joint else 'had no'} it)")
        root = None
        if root_joint is not None:
            root = _vector(root_joint, where=f"root_joint of {where}")
            if root.shape != (3,):
                raise ValueError(f"root_joint of {where} must have shape (3,) (got {root.shape})")
        translation = None
        if body_translation is not None:
            translation = _vector(body_translation, where=f"body_translation of {where}")
            if translation.shape != (3,):
                raise ValueError(f"body_translation of {where} must have shape (3,) (got {translation.shape})")
        extra_shapes = dict(self._extra_shapes)
        if row == 0:
            for name, value in extra.items():
                _check_name(name, where=f"extra field name of {where}")
                if np.size(value) == 0:
                    raise ValueError(f"extra field {name!r} of {where} must not be empty (got shape {np.shape(value)})")
                extra_shapes[name] = np.shape(value)
        elif set(extra) != set(extra_shapes):
            raise ValueError(f"extra fields of {where} must be {sorted(self._extra_shapes)} like earlier frames "
                             f"(got {sorted(extra)})")
        extra_arrays: dict[str, np.ndarray] = {}
        for name, value in extra.items():
            array = np.asarray(value, dtype=np.float32)
            if array.shape != extra_shapes[name]:
                raise ValueError(f"extra field {name!r} of {where} must have shape {extra_shapes[name]} "
                                 f"(got {array.shape})")
            extra_arrays[name] = array

        if self.precision == "float16":
            # The body root when known, else the garment's bounding-box centre: either keeps
            # every relative coordinate within the garment's extent of zero.
            if translation is not None:
                origin = translation
            else:
                origin = 0.5 * (posed.min(axis=0) + posed.max(axis=0))
            origin32 = origin.astype(np.float32)
            relative = posed - origin32.astype(np.float64)
            for name, array in (("posed_vertices relative to the origin", relative),
                                (UNPOSED_DISPLACEMENTS, unposed)):
                largest = float(np.abs(array).max())
                if largest >= FLOAT16_MAX_ABS_M:
                    raise ValueError(
                        f"{name} of {where} reaches {largest:.3f} m; float16 shards need |value| < "
                        f"{FLOAT16_MAX_ABS_M} m to keep sub-millimetre precision (use precision='float32')")
            posed_stored = relative.astype(np.float16)
            unposed_stored = unposed.astype(np.float16)
            if velocity is not None and float(np.abs(velocity).max()) >= float(np.finfo(np.float16).max):
                raise ValueError(f"velocities of {where} reach {float(np.abs(velocity).max()):.3g} m/s, beyond "
                                 f"float16 (use precision='float32')")
        else:
            origin32 = None
            posed_stored = posed.astype(np.float32)
            unposed_stored = unposed.astype(np.float32)
        velocity_stored = None if velocity is None else velocity.astype(posed_stored.dtype)

        # All checks passed: only now does the writer's state change.
        if row == 0:
            self._has_velocities = velocity is not None
            if velocity is not None:
                self._frame_datasets[VELOCITIES] = handle.create_dataset(
                    VELOCITIES, shape=(self._capacity, self.vertex_count, 3), maxshape=(None, self.vertex_count, 3),
                    chunks=(1, self.vertex_count, 3), dtype=posed_stored.dtype, **self._dataset_options())
            self._pose_size = pose_array.shape[0]
            self._quality = {name: [] for name in sorted(quality_values)}
            self._extra_shapes = extra_shapes
            if self.precision == "float16":
                handle.attrs["position_origin_rule"] = "body_translation" if translation is not None else "bbox_center"
        if row == 0 and extra_arrays:
            group = handle.create_group(EXTRA_GROUP)
            for name, array in sorted(extra_arrays.items()):
                self._frame_datasets[f"{EXTRA_GROUP}/{name}"] = group.create_dataset(
                    name, shape=(self._capacity, *array.shape), maxshape=(None, *array.shape),
                    chunks=(1, *array.shape), dtype=np.float32, **self._dataset_options())
        self._grow(row + 1)
        self._frame_datasets[POSED_VERTICES][row] = posed_stored
        self._frame_datasets[UNPOSED_DISPLACEMENTS][row] = unposed_stored
        if velocity_stored is not None:
            self._frame_datasets[VELOCITIES][row] = velocity_stored
        for name, array in extra_arrays.items():
            self._frame_datasets[f"{EXTRA_GROUP}/{name}"][row] = array
        self._pose.append(pose_array.astype(np.float32))
        self._frame_index.append(int(frame_index))
        for name, value in quality_values.items():
            self._quality[name].append(value)
        if translation is not None:
            self._body_translation.append(translation.astype(np.float32))
        if root is not None:
            self._root_joint.append(root.astype(np.float32))
        if origin32 is not None:
            self._origin.append(origin32)
        self.frame_count = row + 1
        return row

    # -- finish ---------------------------------------------------------------------------

    def close(self) -> ShardRecord:
        """Finish the shard: write the per-frame tables, flush, fsync, hash, and rename the
        temporary file to ``path``. Returns (and stores in ``record``) the manifest entry."""
        if self._state == "closed":
            assert self.record is not None
            return self.record
        handle = self._ensure_open()
        try:
            frames = self.frame_count
            options = self._dataset_options()
            pose_size = self._pose_size or 0

            def small(name: str, data: np.ndarray) -> None:
                chunks = (max(1, min(_SMALL_CHUNK_ROWS, data.shape[0])), *data.shape[1:])
                if data.size == 0:
                    handle.create_dataset(name, data=data, track_times=False)
                else:
                    handle.create_dataset(name, data=data, chunks=chunks, **options)

            small(POSE, np.array(self._pose, dtype=np.float32).reshape(frames, pose_size))
            small(FRAME_INDEX, np.array(self._frame_index, dtype=np.int32).reshape(frames))
            if self._body_translation:
                small(BODY_TRANSLATION, np.array(self._body_translation, dtype=np.float32).reshape(frames, 3))
            if self._root_joint:
                small(ROOT_JOINT, np.array(self._root_joint, dtype=np.float32).reshape(frames, 3))
            if self.precision == "float16":
                small(POSITION_ORIGIN, np.array(self._origin, dtype=np.float32).reshape(frames, 3))
            group = handle.create_group(QUALITY_GROUP)
            for name in sorted(self._quality):
                small(f"{QUALITY_GROUP}/{name}", np.array(self._quality[name], dtype=np.float32))
            for dataset in self._frame_datasets.values():
                dataset.resize(frames, axis=0)
            del group
            if self._dropped_log:
                kept_index = set(self._frame_index)
                log = sorted(self._dropped_log, key=lambda row: row[0])
                indices = [row[0] for row in log]
                if len(set(indices)) != len(indices) or kept_index & set(indices):
                    raise ValueError(f"task {self.task_id!r}: dropped frames' frame_index values must be unique and "
                                     f"differ from the kept frames' (got {indices})")
                handle.create_group(DROPPED_GROUP)
                small(DROPPED_FRAME_INDEX, np.array(indices, dtype=np.int32))
                small(DROPPED_POSE, np.stack([row[2] for row in log]))
                handle.create_dataset(DROPPED_REASON, data=np.array([row[1] for row in log], dtype=object),
                                      dtype=h5py.string_dtype(), track_times=False)
            handle.attrs["filter_stats_json"] = canonical_json(dict(sorted(self.filter_stats.items())))
            handle.flush()
            handle.close()
            self._file = None
            fd = os.open(self.tmp_path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            digest = file_sha256(self.tmp_path)
            size = self.tmp_path.stat().st_size
            os.replace(self.tmp_path, self.path)
            fsync_directory(self.path.parent)
        except BaseException:
            self.abort()
            raise
        self._state = "closed"
        timings = dict(self.timings)
        timings.setdefault("write_s", time.perf_counter() - self._start)
        self.record = ShardRecord(
            task_id=self.task_id,
            path=self.path,
            sha256=digest,
            bytes=size,
            frame_count=frames,
            splits=list(self.task["splits"]),
            filter_stats=dict(sorted(self.filter_stats.items())),
            timings={k: float(v) for k, v in timings.items()},
        )
        return self.record


class ShardWriterSet:
    """The open shard writers of one batch of tasks, keyed by the caller (a task index), sharing
    one canonical template and the output options.

    Made on the shard-writing worker (``BackgroundWriter.create``), so a worker process gets the
    template once per batch instead of with each of a batch's ~2,000 shards, and checks and hashes
    it there. ``close`` hands back the shard's manifest record; ``abort`` deletes the temporary
    files of every shard not closed (``BackgroundWriter.close(cleanup=ShardWriterSet.abort)``)."""

    def __init__(self, root: str | os.PathLike[str], template: Mapping[str, Any] | CanonicalTemplate, *,
                 precision: str = "float32", compression: str = "gzip") -> None:
        self.root = Path(root)
        self.template = template if isinstance(template, CanonicalTemplate) else CanonicalTemplate.of(template)
        self.precision, self.compression = precision, compression
        self.writers: dict[Any, ShardWriter] = {}

    def open(self, key: Any, task: Mapping[str, Any]) -> None:
        """Starts the shard of ``task`` (see ``ShardWriter``: ``task_id`` names the file) under ``key``."""
        if key in self.writers:
            raise ValueError(f"shard key {key!r} is already open (task {self.writers[key].task_id!r})")
        self.writers[key] = ShardWriter(shard_path(self.root, str(task["task_id"])), template=self.template, task=task,
                                        precision=self.precision, compression=self.compression)

    def write_frame(self, key: Any, *args: Any, **kwargs: Any) -> dict:
        """``ShardWriter.write_frame`` of the shard under ``key``."""
        return self.writers[key].write_frame(*args, **kwargs)

    def record_dropped(self, key: Any, *args: Any, **kwargs: Any) -> None:
        """``ShardWriter.record_dropped`` of the shard under ``key``."""
        self.writers[key].record_dropped(*args, **kwargs)

    def close(self, key: Any, *, started_at: float | None = None) -> ShardRecord:
        """Finishes the shard under ``key`` and forgets it; ``started_at`` (``time.time()`` when the
        batch began) sets the record's ``timings["wall_s"]``."""
        writer = self.writers[key]
        if started_at is not None:
            writer.timings["wall_s"] = time.time() - started_at
        record = writer.close()
        del self.writers[key]
        return record

    def abort(self) -> None:
        """Deletes the temporary file of every shard not closed (after a failure)."""
        for writer in self.writers.values():
            writer.abort()
        self.writers.clear()


# ---------------------------------------------------------------------------------------
# Reading and checking
# ---------------------------------------------------------------------------------------


def _attr_str(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray) and value.shape == ():
        return _attr_str(value.item())
    return str(value)


def read_shard_attrs(handle: h5py.File) -> dict[str, Any]:
    """The root attributes of an open shard as plain Python values (splits as list[str],
    ``task`` and ``filter_stats`` parsed from their JSON). Raises ValueError naming a
    missing or malformed attribute."""
    attrs = handle.attrs
    out: dict[str, Any] = {}
    for key in ("format", "task_id", "garment", "precision", "compression", "template_sha256",
                "position_origin_rule"):
        if key not in attrs:
            raise ValueError(f"shard attribute {key!r} is missing")
        out[key] = _attr_str(attrs[key])
    for key in ("schema_version", "seed"):
        if key not in attrs:
            raise ValueError(f"shard attribute {key!r} is missing")
        out[key] = int(np.asarray(attrs[key]).item())
    if "splits" not in attrs:
        raise ValueError("shard attribute 'splits' is missing")
    out["splits"] = [_attr_str(s) for s in np.atleast_1d(np.asarray(attrs["splits"], dtype=object))] \
        if np.asarray(attrs["splits"]).size else []
    for key, target in (("task_json", "task"), ("filter_stats_json", "filter_stats")):
        if key not in attrs:
            raise ValueError(f"shard attribute {key!r} is missing")
        try:
            out[target] = json.loads(_attr_str(attrs[key]))
        except json.JSONDecodeError as error:
            raise ValueError(f"shard attribute {key!r} is not valid JSON: {error}") from None
    return out


def read_template(handle: h5py.File) -> dict[str, np.ndarray]:
    """The garment template stored in an open shard, as a dict of numpy arrays."""
    if TEMPLATE_GROUP not in handle:
        raise ValueError(f"shard has no {TEMPLATE_GROUP!r} group")
    group = handle[TEMPLATE_GROUP]
    return {key: group[key][()] for key in group}


def check_shard_layout(handle: h5py.File) -> list[str]:
    """Compare an open shard against ``SHARD_LAYOUT``; returns one message per problem
    (empty when the layout is right). Reads only attributes, shapes and ``frame_index``."""
    problems: list[str] = []
    try:
        attrs = read_shard_attrs(handle)
    except ValueError as error:
        return [str(error)]
    if attrs["format"] != SHARD_FORMAT:
        problems.append(f"attribute format is {attrs['format']!r}, expected {SHARD_FORMAT!r}")
    if attrs["schema_version"] not in READABLE_SCHEMA_VERSIONS:
        problems.append(f"attribute schema_version is {attrs['schema_version']}, expected one of "
                        f"{', '.join(map(str, READABLE_SCHEMA_VERSIONS))}")
    elif attrs["schema_version"] < 2:
        for name in (VELOCITIES, ROOT_JOINT):
            if name in handle:
                problems.append(f"dataset {name!r} needs schema version >= 2 (the shard says {attrs['schema_version']})")
    precision = attrs["precision"]
    if precision not in PRECISIONS:
        problems.append(f"attribute precision is {precision!r}, expected one of {PRECISIONS}")
        return problems
    dims: dict[str, int] = {}
    for layout in SHARD_LAYOUT:
        required = layout.required == "always" or (layout.required == "float16" and precision == "float16")
        if layout.name not in handle:
            if required:
                problems.append(f"dataset {layout.name!r} is missing")
            continue
        item = handle[layout.name]
        if not isinstance(item, h5py.Dataset):
            problems.append(f"{layout.name!r} is a group, expected a dataset")
            continue
        shape = item.shape
        expected_dtype = ("float16" if precision == "float16" else "float32") if layout.dtype == "position" else layout.dtype
        if item.dtype != np.dtype(expected_dtype):
            problems.append(f"dataset {layout.name!r} has dtype {item.dtype}, expected {expected_dtype}")
        if len(shape) != len(layout.dims):
            problems.append(f"dataset {layout.name!r} has shape {shape}, expected {layout.dims}")
            continue
        for size, symbol in zip(shape, layout.dims):
            if isinstance(symbol, int):
                if size != symbol:
                    problems.append(f"dataset {layout.name!r} has shape {shape}, expected {layout.dims}")
                    break
            elif dims.setdefault(symbol, size) != size:
                problems.append(f"dataset {layout.name!r} has {symbol}={size} in shape {shape}, but other "
                                f"datasets have {symbol}={dims[symbol]}")
                break
    frames = dims.get("F")
    if QUALITY_GROUP not in handle:
        problems.append(f"group {QUALITY_GROUP!r} is missing")
    else:
        for name, item in handle[QUALITY_GROUP].items():
            if not isinstance(item, h5py.Dataset) or item.shape != (frames,) or item.dtype != np.float32:
                problems.append(f"{QUALITY_GROUP}/{name} must be a ({frames},) float32 dataset "
                                f"(got {getattr(item, 'shape', 'group')} {getattr(item, 'dtype', '')})")
    if EXTRA_GROUP in handle:
        for name, item in handle[EXTRA_GROUP].items():
            if not isinstance(item, h5py.Dataset) or item.ndim < 1 or item.shape[0] != frames:
                problems.append(f"{EXTRA_GROUP}/{name} must be a dataset with {frames} rows "
                                f"(got {getattr(item, 'shape', 'group')})")
    if FRAME_INDEX in handle and isinstance(handle[FRAME_INDEX], h5py.Dataset) and frames:
        try:
            index = handle[FRAME_INDEX][()]
            if index.ndim == 1 and (index.min(initial=0) < 0 or np.any(np.diff(index.astype(np.int64)) <= 0)):
                problems.append("dataset 'frame_index' must be non-negative and strictly increasing")
        except OSError as error:
            problems.append(f"dataset 'frame_index' cannot be read: {error}")
    if precision == "float32" and POSITION_ORIGIN in handle:
        problems.append(f"dataset {POSITION_ORIGIN!r} is only allowed in float16 shards")
    if DROPPED_GROUP in handle:
        problems += _check_dropped_log(handle, attrs.get("filter_stats") or {}, dims.get("P"))
    return problems


def read_dropped_log(handle: h5py.File) -> dict[str, np.ndarray] | None:
    """The ``dropped`` group of an open shard: ``frame_index`` (D,) int64, ``reason`` (D,) str,
    ``pose`` (D, P) float32 [rad]; None when the shard does not log its dropped frames."""
    if DROPPED_GROUP not in handle:
        return None
    return {"frame_index": np.asarray(handle[DROPPED_FRAME_INDEX][()], dtype=np.int64),
            "reason": np.asarray(handle[DROPPED_REASON].asstr()[()], dtype=str),
            "pose": np.asarray(handle[DROPPED_POSE][()], dtype=np.float32)}


def _check_dropped_log(handle: h5py.File, filter_stats: dict, pose_size: int | None) -> list[str]:
    """Problems of the optional ``dropped`` group: shapes, counts against filter_stats, indices."""
    names = (DROPPED_FRAME_INDEX, DROPPED_REASON, DROPPED_POSE)
    missing = [n for n in names if n not in handle or not isinstance(handle[n], h5py.Dataset)]
    if missing:
        return [f"group {DROPPED_GROUP!r} lacks the datasets {missing}"]
    index, reason, pose = (handle[n] for n in names)
    count = index.shape[0] if index.ndim == 1 else -1
    problems = []
    if index.dtype != np.int32 or count < 0:
        problems.append(f"dataset {DROPPED_FRAME_INDEX!r} must be (D,) int32 (got {index.shape} {index.dtype})")
    if reason.shape != (count,) or h5py.check_string_dtype(reason.dtype) is None:
        problems.append(f"dataset {DROPPED_REASON!r} must be ({count},) str (got {reason.shape} {reason.dtype})")
    if pose.ndim != 2 or pose.shape[0] != count or pose.dtype != np.float32 or (pose_size and pose.shape[1] != pose_size):
        problems.append(f"dataset {DROPPED_POSE!r} must be ({count}, {pose_size or 'P'}) float32 "
                        f"(got {pose.shape} {pose.dtype})")
    if problems:
        return problems
    try:
        log = read_dropped_log(handle)
        names, counts = np.unique(log["reason"], return_counts=True)
        logged = {str(r): int(c) for r, c in zip(names, counts)}
        stats = {str(k): int(v) for k, v in filter_stats.items() if int(v)}
        if logged != stats:
            problems.append(f"{DROPPED_GROUP!r} logs {logged} dropped frames but filter_stats_json counts {stats}")
        values = log["frame_index"]
        kept = handle[FRAME_INDEX][()] if FRAME_INDEX in handle else np.zeros(0)
        if len(np.unique(values)) != len(values) or np.intersect1d(values, kept).size:
            problems.append(f"dataset {DROPPED_FRAME_INDEX!r} must hold unique indices that no kept frame has")
    except OSError as error:
        problems.append(f"group {DROPPED_GROUP!r} cannot be read: {error}")
    return problems


def decode_positions(stored: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    """Posed vertices [m] as float32 from their stored form: (..., V, 3) stored values plus
    the per-frame origin (..., 3) when the shard is float16 (``origin`` None for float32)."""
    values = np.asarray(stored, dtype=np.float32)
    if origin is None:
        return values
    return values + np.asarray(origin, dtype=np.float32)[..., None, :]

