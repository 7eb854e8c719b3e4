"""Random access to a dataset's frames by split, for training.

``DatasetReader`` numbers the listed shards in manifest order (sorted by task id) and the
frames of a split as rows of ``index(split)`` = (shard_no, frame_row). HDF5 files are opened
lazily and kept in a small LRU of handles; the handles belong to one process id, so a reader
created before a torch DataLoader forks its workers reopens its files in each worker (and
pickles without handles for the spawn start method). float16 shards come back as float32,
posed vertices with their per-frame origin added back.
"""

from __future__ import annotations

import contextlib
import os
from collections import OrderedDict
from collections.abc import Collection
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .manifest import Manifest
from .schema import (
    BODY_TRANSLATION,
    FRAME_INDEX,
    POSE,
    POSED_VERTICES,
    POSITION_ORIGIN,
    QUALITY_GROUP,
    SHAPE,
    SIZED_SHAPE,
    STYLE,
    TIGHTNESS,
    ROOT_JOINT,
    UNPOSED_DISPLACEMENTS,
    VELOCITIES,
    CorruptShardError,
    MissingShardError,
)
from .integrity import IntegrityChecker
from .shard import decode_positions, read_dropped_log, read_template

#: The per-vertex arrays of a frame, (V, 3) each: ``load_split``'s ``per_vertex`` chooses among them.
PER_VERTEX_ARRAYS = ("posed_vertices", "unposed_displacements", "velocities")


def per_vertex_names(per_vertex: Collection[str] | None) -> tuple[str, ...]:
    """``per_vertex`` checked against :data:`PER_VERTEX_ARRAYS` (None: all of them); a ValueError
    names the value and the choices."""
    if per_vertex is None:
        return PER_VERTEX_ARRAYS
    names = tuple(per_vertex)
    unknown = sorted(set(names) - set(PER_VERTEX_ARRAYS))
    if unknown or isinstance(per_vertex, str):
        raise ValueError(f"per_vertex must name arrays among {', '.join(PER_VERTEX_ARRAYS)}; got {per_vertex!r}")
    return names

#: What h5py and numpy raise on damaged HDF5 (a flipped byte in a header, chunk index or
#: attribute can surface as any of these); the reader reports each as CorruptShardError.
_DECODE_ERRORS = (OSError, KeyError, TypeError, ValueError, IndexError, RuntimeError, AttributeError,
                  UnicodeDecodeError, OverflowError)


class DatasetReader:
    """Read a drape dataset directory.

    root: the dataset directory (holding manifest.json). integrity (default True): before a
    shard is first read, its size and sha256 are checked against the manifest
    (``integrity.IntegrityChecker``; digests are cached per file, so a second read of an
    unchanged shard costs a ``stat``). verify: check every listed shard up front (existence,
    size, sha256, layout, template; see ``validate.check_shard_file``) and raise on the first
    problem. max_open_files: size of the LRU of open HDF5 handles.

    Errors: a missing directory or manifest raises FileNotFoundError naming the path; an
    unknown split raises ValueError listing the available ones; a listed shard that is
    missing raises MissingShardError (a FileNotFoundError), one that is truncated or
    unreadable raises CorruptShardError (a ValueError), both naming the file and task; so
    does a shard that HDF5 cannot decode (never a TypeError from deep inside h5py).
    """

    def __init__(self, root: str | os.PathLike[str], *, verify: bool = False, max_open_files: int = 16,
                 integrity: bool = True):
        if isinstance(max_open_files, bool) or not isinstance(max_open_files, int) or max_open_files < 1:
            raise ValueError(f"max_open_files must be an integer >= 1 (got {max_open_files!r})")
        self.root = Path(root)
        self.manifest = Manifest.load(self.root)
        self.max_open_files = max_open_files
        self._entries = self.manifest.shards
        self._shard_no = {entry["task_id"]: number for number, entry in enumerate(self._entries)}
        self._index_cache: dict[str, np.ndarray] = {}
        self._template: dict[str, np.ndarray] | None = None
        self._handles: OrderedDict[int, h5py.File] = OrderedDict()
        self._pid = os.getpid()
        self._integrity = IntegrityChecker(self.root) if integrity else None
        self._checked: set[int] = set()  # shards whose bytes matched the manifest in this reader
        self._task_info: dict[int, dict[str, Any]] = {}  # shard number -> its task dict (task_info)
        if verify:
            self.verify()

    # -- pickling / processes ------------------------------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_handles"] = OrderedDict()
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._pid = os.getpid()

    def _check_process(self) -> None:
        if os.getpid() != self._pid:
            # Forked child: the inherited HDF5 handles belong to the parent; forget them
            # (never close or use them here) and open our own.
            self._handles = OrderedDict()
            self._pid = os.getpid()

    def close(self) -> None:
        """Close the open HDF5 handles of this process."""
        self._check_process()
        while self._handles:
            _, handle = self._handles.popitem(last=False)
            handle.close()

    def __enter__(self) -> "DatasetReader":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- structure -----------------------------------------------------------------------

    @property
    def splits(self) -> dict[str, list[str]]:
        """split -> task ids, as the manifest lists them."""
        return self.manifest.splits

    @property
    def shard_entries(self) -> list[dict[str, Any]]:
        """Manifest entries of the listed shards; ``shard_no`` indexes this list."""
        return [dict(entry) for entry in self._entries]

    def shard_no(self, task_id: str) -> int:
        """Position of a task's shard in ``shard_entries``."""
        if task_id not in self._shard_no:
            import difflib

            listed = sorted(self._shard_no)
            close = difflib.get_close_matches(str(task_id), listed, n=1)
            examples = ", ".join(listed[:5]) + (", ..." if len(listed) > 5 else "")
            raise ValueError(f"task {task_id!r} has no shard in dataset {str(self.root)!r}"
                             + (f" (did you mean {close[0]}?)" if close else "")
                             + f"; {len(listed)} tasks listed: {examples or 'none'} (see `drape dataset info`)")
        return self._shard_no[task_id]

    def _check_split(self, split: str) -> None:
        if split not in self.manifest.splits:
            available = ", ".join(sorted(self.manifest.splits)) or "none"
            raise ValueError(f"split {split!r} is not in dataset {str(self.root)!r}; available splits: {available}")

    def _split_shards(self, split: str) -> list[int]:
        self._check_split(split)
        return [number for number, entry in enumerate(self._entries) if split in entry["splits"]]

    def num_frames(self, split: str) -> int:
        """Number of frames in ``split`` (from the manifest)."""
        return sum(self._entries[number]["frame_count"] for number in self._split_shards(split))

    def index(self, split: str) -> np.ndarray:
        """(N, 2) int64 rows [shard_no, frame_row] of every frame of ``split``, in shard
        order then frame order. Row i is what ``get(split, i)`` returns."""
        if split not in self._index_cache:
            blocks = [np.stack([np.full(self._entries[number]["frame_count"], number, dtype=np.int64),
                                np.arange(self._entries[number]["frame_count"], dtype=np.int64)], axis=1)
                      for number in self._split_shards(split)]
            index = np.concatenate(blocks, axis=0) if blocks else np.zeros((0, 2), dtype=np.int64)
            index.setflags(write=False)
            self._index_cache[split] = index
        return self._index_cache[split]

    @property
    def template(self) -> dict[str, np.ndarray]:
        """The garment template (faces, rest_vertices [m], skinning_weights,
        body_vertex_index, optional uv), read from the first listed shard."""
        if self._template is None:
            if not self._entries:
                raise ValueError(f"dataset {str(self.root)!r} lists no shards, so it has no template yet")
            handle = self._open(0)
            try:
                self._template = read_template(handle)
            except _DECODE_ERRORS as error:
                raise self._corrupt(0, error) from None
        return {key: value.copy() for key, value in self._template.items()}

    # -- files ---------------------------------------------------------------------------

    def _path(self, number: int) -> Path:
        return self.root / self._entries[number]["path"]

    def _corrupt(self, number: int, error: BaseException) -> CorruptShardError:
        entry = self._entries[number]
        return CorruptShardError(f"shard {str(self._path(number))!r} of task {entry['task_id']!r} is corrupt or "
                                 f"unreadable ({error}); run `drape dataset validate {self.root}`")

    def _open(self, number: int) -> h5py.File:
        self._check_process()
        handle = self._handles.get(number)
        if handle is not None:
            self._handles.move_to_end(number)
            return handle
        entry = self._entries[number]
        path = self._path(number)
        if not path.is_file():
            raise MissingShardError(f"shard {str(path)!r} of task {entry['task_id']!r} is listed in the manifest "
                                    f"but does not exist")
        size = path.stat().st_size
        if size != entry["bytes"]:
            raise CorruptShardError(f"shard {str(path)!r} of task {entry['task_id']!r} has {size} bytes, the "
                                    f"manifest lists {entry['bytes']} (truncated or replaced)")
        if self._integrity is not None and number not in self._checked:
            problem = self._integrity.problem(entry)
            if problem is not None:
                kind, message = problem
                raise (MissingShardError if kind == "missing" else CorruptShardError)(
                    f"{message}; run `drape dataset validate {self.root}`")
            self._checked.add(number)
        try:
            handle = h5py.File(path, "r")
        except Exception as error:  # h5py raises OSError, and others on some damage
            raise self._corrupt(number, error) from None
        self._handles[number] = handle
        while len(self._handles) > self.max_open_files:
            _, oldest = self._handles.popitem(last=False)
            oldest.close()
        return handle

    def verify(self) -> None:
        """Check every listed shard fully (see ``validate.check_shard_file``); raises
        MissingShardError or CorruptShardError naming the first bad shard."""
        from .validate import check_shard_file

        for entry in self._entries:
            problems = check_shard_file(self.root, entry, manifest=self.manifest, check_sha256=True)
            if problems:
                text = "; ".join(str(problem) for problem in problems)
                if problems[0].kind == "missing":
                    raise MissingShardError(text)
                raise CorruptShardError(text)

    # -- frames --------------------------------------------------------------------------

    def get(self, split: str, i: int) -> dict[str, Any]:
        """Frame ``i`` of ``split`` (negative counts from the end): a dict with ``pose`` (P,)
        [rad], ``shape`` (S,), ``style`` (G,), ``posed_vertices`` (V, 3) [m] and
        ``unposed_displacements`` (V, 3) [m] as float32, ``quality`` {metric: float32},
        ``body_translation`` (3,) [m], ``root_joint`` (3,) [m], ``velocities`` (V, 3) [m/s],
        ``tightness`` (T,) and ``sized_shape`` (S,) where stored, ``fabric`` (str) where the task
        names it, ``task_id``, ``shard_no`` and ``frame_index`` (index in the task's sequence)."""
        index = self.index(split)
        count = index.shape[0]
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -count <= i < count:
            raise IndexError(f"frame {i!r} is out of range for split {split!r} with {count} frames")
        number, row = (int(v) for v in index[int(i)])
        handle = self._open(number)
        try:
            origin = handle[POSITION_ORIGIN][row] if POSITION_ORIGIN in handle else None
            item: dict[str, Any] = {
                "task_id": self._entries[number]["task_id"],
                "shard_no": number,
                "frame_index": int(handle[FRAME_INDEX][row]),
                "pose": np.asarray(handle[POSE][row], dtype=np.float32),
                "shape": np.asarray(handle[SHAPE][()], dtype=np.float32),
                "style": np.asarray(handle[STYLE][()], dtype=np.float32),
                "posed_vertices": decode_positions(handle[POSED_VERTICES][row], origin),
                "unposed_displacements": np.asarray(handle[UNPOSED_DISPLACEMENTS][row], dtype=np.float32),
                "quality": {name: np.float32(dataset[row]) for name, dataset in handle[QUALITY_GROUP].items()},
            }
            if BODY_TRANSLATION in handle:
                item["body_translation"] = np.asarray(handle[BODY_TRANSLATION][row], dtype=np.float32)
            if VELOCITIES in handle:
                item["velocities"] = np.asarray(handle[VELOCITIES][row], dtype=np.float32)
            if ROOT_JOINT in handle:
                item["root_joint"] = np.asarray(handle[ROOT_JOINT][row], dtype=np.float32)
            for name in (TIGHTNESS, SIZED_SHAPE):
                if name in handle:
                    item[name] = np.asarray(handle[name][()], dtype=np.float32)
            fabric = self.task_info(item["task_id"]).get("fabric")
            if isinstance(fabric, str):
                item["fabric"] = fabric
        except _DECODE_ERRORS as error:
            raise self._corrupt(number, error) from None
        return item

    def _read_shard(self, number: int, per_vertex: Collection[str] | None = None) -> dict[str, np.ndarray]:
        per_vertex = per_vertex_names(per_vertex)
        handle = self._open(number)
        try:
            frames = handle[POSED_VERTICES].shape[0]
            origin = handle[POSITION_ORIGIN][()] if POSITION_ORIGIN in handle else None
            arrays = {
                "pose": np.asarray(handle[POSE][()], dtype=np.float32),
                "shape": np.repeat(np.asarray(handle[SHAPE][()], dtype=np.float32)[None], frames, axis=0),
                "style": np.repeat(np.asarray(handle[STYLE][()], dtype=np.float32)[None], frames, axis=0),
                "shard_no": np.full(frames, number, dtype=np.int64),
                "frame_index": np.asarray(handle[FRAME_INDEX][()], dtype=np.int64),
            }
            if "posed_vertices" in per_vertex:
                arrays["posed_vertices"] = decode_positions(handle[POSED_VERTICES][()], origin)
            if "unposed_displacements" in per_vertex:
                arrays["unposed_displacements"] = np.asarray(handle[UNPOSED_DISPLACEMENTS][()], dtype=np.float32)
            for name, dataset in handle[QUALITY_GROUP].items():
                arrays[f"{QUALITY_GROUP}/{name}"] = np.asarray(dataset[()], dtype=np.float32)
            if BODY_TRANSLATION in handle:
                arrays["body_translation"] = np.asarray(handle[BODY_TRANSLATION][()], dtype=np.float32)
            if VELOCITIES in handle and "velocities" in per_vertex:
                arrays["velocities"] = np.asarray(handle[VELOCITIES][()], dtype=np.float32)
            if ROOT_JOINT in handle:
                arrays["root_joint"] = np.asarray(handle[ROOT_JOINT][()], dtype=np.float32)
            for name in (TIGHTNESS, SIZED_SHAPE):  # per task, repeated per frame like shape and style
                if name in handle:
                    arrays[name] = np.repeat(np.asarray(handle[name][()], dtype=np.float32)[None], frames, axis=0)
        except _DECODE_ERRORS as error:
            raise self._corrupt(number, error) from None
        if frames != self._entries[number]["frame_count"]:
            raise CorruptShardError(f"shard {str(self._path(number))!r} holds {frames} frames, the manifest "
                                    f"lists {self._entries[number]['frame_count']}")
        return arrays

    def task_info(self, task_id: str) -> dict[str, Any]:
        """The task dict a shard was written with (its ``task_json`` attribute: garment, fabric,
        pair, style_index, motion, fps, ... as the writer gave them); read once per shard."""
        number = self.shard_no(task_id)
        if number not in self._task_info:
            from .shard import read_shard_attrs

            try:
                self._task_info[number] = read_shard_attrs(self._open(number))["task"]
            except _DECODE_ERRORS as error:
                raise self._corrupt(number, error) from None
        return self._task_info[number]

    def load_task(self, task_id: str, per_vertex: Collection[str] | None = None) -> dict[str, np.ndarray]:
        """Every frame of one task, with the keys and shapes of ``load_split``."""
        return self._read_shard(self.shard_no(task_id), per_vertex)

    def load_split(self, split: str, per_vertex: Collection[str] | None = None) -> dict[str, np.ndarray]:
        """All frames of ``split`` stacked, in ``index(split)`` order: ``pose`` (N, P),
        ``shape`` (N, S), ``style`` (N, G), ``posed_vertices`` (N, V, 3) [m],
        ``unposed_displacements`` (N, V, 3) [m], ``quality/<metric>`` (N,) as float32;
        ``body_translation`` (N, 3), ``root_joint`` (N, 3) [m], ``velocities`` (N, V, 3) [m/s],
        ``tightness`` (N, T) and ``sized_shape`` (N, S) where every shard has them;
        ``shard_no`` and ``frame_index`` (N,) as int64.

        ``per_vertex``: which of the (N, V, 3) arrays (:data:`PER_VERTEX_ARRAYS`) to read; default
        all. They are nearly all of a split's bytes: a learner that needs only the displacements
        reads a third to a half of them."""
        parts: dict[str, list[np.ndarray]] = {}
        keys: set[str] | None = None
        # each shard is checked against the manifest as it is read; new digests are cached once
        with self._integrity.batch() if self._integrity is not None else contextlib.nullcontext():
            for number in self._split_shards(split):
                if self._entries[number]["frame_count"] == 0:
                    continue  # a task whose frames were all filtered out: nothing to stack
                arrays = self._read_shard(number, per_vertex)
                metrics = sorted(key for key in arrays if key.startswith(f"{QUALITY_GROUP}/"))
                if keys is not None:
                    known = sorted(key for key in keys if key.startswith(f"{QUALITY_GROUP}/"))
                    if metrics != known:
                        raise ValueError(f"shards of split {split!r} disagree on quality metrics: "
                                         f"{self._entries[number]['task_id']!r} has {metrics}, earlier shards {known}")
                    keys &= set(arrays)
                else:
                    keys = set(arrays)
                for key, value in arrays.items():
                    parts.setdefault(key, []).append(value)
        if keys is None:
            return self._empty_split()
        # body_translation, root_joint and velocities are kept only when every shard of the split has them
        return {key: np.concatenate(values, axis=0) for key, values in parts.items() if key in keys
                and len(values) == len(parts["pose"])}

    def dropped_frames(self, split: str) -> dict[str, np.ndarray]:
        """The frames of ``split`` that the filters dropped, as logged by the shards that log
        them (``dropped`` group): ``shard_no`` (D,) int64, ``frame_index`` (D,) int64 (index in
        the task's sequence), ``reason`` (D,) str, ``pose`` (D, P) float32 [rad]. Shards
        written without the log contribute nothing; their drops are still counted in the
        manifest's ``filter_stats``."""
        parts: dict[str, list[np.ndarray]] = {"shard_no": [], "frame_index": [], "reason": [], "pose": []}
        for number in self._split_shards(split):
            if not sum(self._entries[number].get("filter_stats", {}).values()):
                continue
            handle = self._open(number)
            try:
                log = read_dropped_log(handle)
            except _DECODE_ERRORS as error:
                raise self._corrupt(number, error) from None
            if log is None:
                continue
            for key, value in log.items():
                parts[key].append(value)
            parts["shard_no"].append(np.full(len(log["frame_index"]), number, dtype=np.int64))
        if not parts["pose"]:
            return {"shard_no": np.zeros(0, np.int64), "frame_index": np.zeros(0, np.int64),
                    "reason": np.zeros(0, dtype=str), "pose": np.zeros((0, 0), np.float32)}
        return {key: np.concatenate(values, axis=0) for key, values in parts.items()}

    def _empty_split(self) -> dict[str, np.ndarray]:
        vertex_count = self.template["rest_vertices"].shape[0] if self._entries else 0
        return {
            "pose": np.zeros((0, 0), dtype=np.float32),
            "shape": np.zeros((0, 0), dtype=np.float32),
            "style": np.zeros((0, 0), dtype=np.float32),
            "posed_vertices": np.zeros((0, vertex_count, 3), dtype=np.float32),
            "unposed_displacements": np.zeros((0, vertex_count, 3), dtype=np.float32),
            "shard_no": np.zeros(0, dtype=np.int64),
            "frame_index": np.zeros(0, dtype=np.int64),
        }

    def __repr__(self) -> str:
        return (f"DatasetReader({str(self.root)!r}, shards={len(self._entries)}, "
                f"splits={ {split: self.num_frames(split) for split in self.manifest.splits} })")
