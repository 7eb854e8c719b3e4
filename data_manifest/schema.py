"""The on-disk contract of a drape dataset: shard layout constants and the manifest schema.

A dataset directory looks like::

    DIR/
      manifest.json            the manifest (JSON, validated by ``validate_manifest_dict``)
      shards/<task_id>.h5      one HDF5 shard per task (layout: ``SHARD_LAYOUT``)
      shards/*.tmp             shards being written (ignored by readers, orphans for validate)

The manifest schema is written by hand (no jsonschema dependency) as a small tree of
``Field`` objects; ``validate_manifest_dict`` walks it and returns one ``SchemaError`` per
problem, each naming the JSON path (``$.shards[2].sha256``), the value found and what was
expected.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

SCHEMA_VERSION = 2
"""Version of both the manifest JSON schema and the shard layout this code writes; bump on any
change. Version 2 added the optional ``velocities`` and ``root_joint`` datasets (motion sequences)
and the optional ``tightness`` and ``sized_shape`` datasets (garments sized for shape + tightness);
a shard without them reads as before."""

READABLE_SCHEMA_VERSIONS = (1, 2)
"""Versions this code reads: a version-1 dataset is a version-2 one without ``velocities`` and
``root_joint``."""

MANIFEST_FORMAT = "drape-dataset"
"""Value of ``manifest["format"]``: tells a drape manifest from any other JSON file."""

SHARD_FORMAT = "drape-shard"
"""Value of the ``format`` attribute of every shard's root group."""

MANIFEST_NAME = "manifest.json"
SHARD_DIR = "shards"
SHARD_SUFFIX = ".h5"
TMP_SUFFIX = ".tmp"
"""Files ending in ``TMP_SUFFIX`` are shards (or manifests) being written: never trusted."""

PRECISIONS = ("float32", "float16")
COMPRESSIONS = ("gzip", "lzf")

TASK_ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,199}$")
"""Task ids double as file names, so they are restricted to a portable character set."""

SHA256_PATTERN = re.compile(r"^[0-9a-f]{64}$")

FLOAT16_MAX_ABS_M = 2.0
"""Largest |coordinate| [m] accepted for float16 storage (positions relative to the origin,
and displacements). Below 2 m the float16 spacing is at most 2**-10 m, so the round-trip
error is at most half of it: ``FLOAT16_ERROR_BOUND_M``."""

FLOAT16_ERROR_BOUND_M = 2.0**-11
"""Worst-case float16 round-trip error [m] (0.488 mm) for |value| < ``FLOAT16_MAX_ABS_M``.
For a body-sized garment (all vertices within 1 m of the pelvis) it is 2**-12 m (0.244 mm)."""

# ---------------------------------------------------------------------------------------
# Shard layout
# ---------------------------------------------------------------------------------------

# Names of the datasets in a shard (HDF5 paths relative to the file's root group).
POSED_VERTICES = "posed_vertices"
UNPOSED_DISPLACEMENTS = "unposed_displacements"
POSITION_ORIGIN = "position_origin"
POSE = "pose"
VELOCITIES = "velocities"
ROOT_JOINT = "root_joint"
BODY_TRANSLATION = "body_translation"
SHAPE = "shape"
STYLE = "style"
TIGHTNESS = "tightness"
SIZED_SHAPE = "sized_shape"
FRAME_INDEX = "frame_index"
QUALITY_GROUP = "quality"
EXTRA_GROUP = "extra"
DROPPED_GROUP = "dropped"
DROPPED_FRAME_INDEX = "dropped/frame_index"
DROPPED_REASON = "dropped/reason"
DROPPED_POSE = "dropped/pose"
TEMPLATE_GROUP = "template"
TEMPLATE_FACES = "template/faces"
TEMPLATE_REST_VERTICES = "template/rest_vertices"
TEMPLATE_SKINNING_WEIGHTS = "template/skinning_weights"
TEMPLATE_BODY_VERTEX_INDEX = "template/body_vertex_index"
TEMPLATE_UV = "template/uv"


@dataclass(frozen=True)
class DatasetLayout:
    """One HDF5 dataset of a shard.

    ``dims`` uses symbols bound per shard: F frames, V garment vertices, P pose length,
    S shape length, G style length, J skinning joints, Fc template faces; ints are fixed.
    ``dtype`` is a numpy dtype name, or "position" for the frame arrays whose storage type
    is the shard's precision (float32 or float16).
    """

    name: str
    dims: tuple[str | int, ...]
    dtype: str
    required: str  # "always", "optional" or "float16" (required iff precision is float16)
    doc: str


SHARD_LAYOUT: tuple[DatasetLayout, ...] = (
    DatasetLayout(POSED_VERTICES, ("F", "V", 3), "position", "always",
                  "Garment vertices in world space [m] (float16: relative to position_origin)."),
    DatasetLayout(UNPOSED_DISPLACEMENTS, ("F", "V", 3), "position", "always",
                  "Displacements D from the unposed body under the garment [m] (TailorNet Eq. 5)."),
    DatasetLayout(VELOCITIES, ("F", "V", 3), "position", "optional",
                  "Garment vertex velocities [m/s] at each frame (motion sequences; schema version >= 2)."),
    DatasetLayout(ROOT_JOINT, ("F", 3), "float32", "optional",
                  "The body's root joint (pelvis) in world space [m] per frame (motion sequences; schema >= 2)."),
    DatasetLayout(POSITION_ORIGIN, ("F", 3), "float32", "float16",
                  "Per-frame origin [m] that float16 posed_vertices are stored relative to."),
    DatasetLayout(POSE, ("F", "P"), "float32", "always", "Body pose parameters [rad] per frame."),
    DatasetLayout(BODY_TRANSLATION, ("F", 3), "float32", "optional",
                  "Body root (pelvis) translation in world space [m] per frame."),
    DatasetLayout(SHAPE, ("S",), "float32", "always", "Body shape parameters of the task."),
    DatasetLayout(STYLE, ("G",), "float32", "always", "Garment style parameters of the task."),
    DatasetLayout(TIGHTNESS, ("T",), "float32", "optional",
                  "Tightness offsets tau of the task's garment (seed 004; anny height, weight): absent when "
                  "the garment is sized for the neutral shape."),
    DatasetLayout(SIZED_SHAPE, ("S",), "float32", "optional",
                  "Body shape the task's garment is sized and draped on (shape + tightness, clipped to the "
                  "shape ranges); the body blends from it to ``shape`` before the sequence."),
    DatasetLayout(FRAME_INDEX, ("F",), "int32", "always",
                  "Index of each kept frame in the task's sequence (strictly increasing)."),
    DatasetLayout(TEMPLATE_FACES, ("Fc", 3), "int32", "always", "Garment triangles (vertex indices)."),
    DatasetLayout(TEMPLATE_REST_VERTICES, ("V", 3), "float32", "always",
                  "Garment template vertices at rest [m]."),
    DatasetLayout(TEMPLATE_SKINNING_WEIGHTS, ("V", "J"), "float32", "always",
                  "Linear-blend-skinning weights per garment vertex, rows sum to 1."),
    DatasetLayout(TEMPLATE_BODY_VERTEX_INDEX, ("V",), "int32", "always",
                  "Body vertex each garment vertex was cut from, -1 where none."),
    DatasetLayout(TEMPLATE_UV, ("V", 2), "float32", "optional", "Texture coordinates per vertex."),
)
"""Every fixed dataset of a shard. Per-metric ``quality/<metric>`` datasets are (F,) float32,
and optional ``extra/<name>`` datasets are (F, ...) float32. The optional ``dropped`` group logs
the frames the filters dropped: ``dropped/frame_index`` (D,) int32 (their index in the task's
sequence, disjoint from ``frame_index``), ``dropped/reason`` (D,) str and ``dropped/pose`` (D, P)
float32; when present, its reasons count exactly the ``filter_stats_json`` attribute."""

SHARD_ATTRS: dict[str, str] = {
    "format": f"str, always {SHARD_FORMAT!r}",
    "schema_version": "int, one of READABLE_SCHEMA_VERSIONS (SCHEMA_VERSION when written by this code)",
    "task_id": "str, matches TASK_ID_PATTERN and the manifest entry",
    "garment": "str, garment type name",
    "splits": "array of str, the splits this task belongs to",
    "seed": "int, the task's seed",
    "precision": "str, one of PRECISIONS",
    "compression": "str, one of COMPRESSIONS",
    "template_sha256": "str, template_sha256() of the template group",
    "position_origin_rule": "str, 'none' (float32), 'body_translation' or 'bbox_center'",
    "task_json": "str, JSON of the task dict (without its array fields)",
    "filter_stats_json": "str, JSON {reason: dropped frame count}",
}
"""Attributes of a shard's root group."""

TEMPLATE_DTYPES: dict[str, str] = {
    "faces": "int32",
    "rest_vertices": "float32",
    "skinning_weights": "float32",
    "body_vertex_index": "int32",
    "uv": "float32",
}
"""Canonical storage dtype of each template array (keys of the template dict)."""


class DatasetError(Exception):
    """Base class of the errors about a dataset on disk."""


class CorruptShardError(DatasetError, ValueError):
    """A shard listed in the manifest is unreadable, truncated or fails its checksum."""


class MissingShardError(DatasetError, FileNotFoundError):
    """A shard listed in the manifest does not exist on disk."""


def check_task_id(task_id: Any, *, where: str = "task_id") -> str:
    """Return ``task_id`` if it is a valid task id, else raise ValueError naming ``where``."""
    if not isinstance(task_id, str) or not TASK_ID_PATTERN.match(task_id):
        raise ValueError(
            f"{where} must be a string of letters, digits, '.', '_' or '-' starting with a "
            f"letter or digit, at most 200 characters (got {task_id!r})"
        )
    return task_id


def canonical_json(value: Any) -> str:
    """JSON text with sorted keys and no spaces: the form that spec hashes are taken of."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def spec_sha256(spec: Mapping[str, Any]) -> str:
    """sha256 (hex) of the canonical JSON of a dataset spec."""
    return hashlib.sha256(canonical_json(spec).encode("utf-8")).hexdigest()


def canonical_template(template: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Check a garment template dict and return its arrays in canonical dtype and layout.

    Keys: ``faces`` (Fc, 3) int, ``rest_vertices`` (V, 3) [m], ``skinning_weights`` (V, J),
    ``body_vertex_index`` (V,) int (-1 where none), optional ``uv`` (V, 2).
    Raises ValueError naming the key, the shape or value found and what was expected.
    """
    if not isinstance(template, Mapping):
        raise ValueError(f"template must be a dict of arrays (got {type(template).__name__})")
    unknown = sorted(set(template) - set(TEMPLATE_DTYPES))
    if unknown:
        raise ValueError(f"template has unknown keys {unknown}; expected keys among {sorted(TEMPLATE_DTYPES)}")
    out: dict[str, np.ndarray] = {}
    for key, dtype in TEMPLATE_DTYPES.items():
        if key not in template:
            if key == "uv":
                continue
            raise ValueError(f"template.{key} is missing; expected keys {sorted(set(TEMPLATE_DTYPES) - {'uv'})}")
        array = np.asarray(template[key])
        if dtype == "int32":
            if not np.issubdtype(array.dtype, np.integer):
                raise ValueError(f"template.{key} must hold integers (got dtype {array.dtype})")
        elif not np.issubdtype(array.dtype, np.number) or np.issubdtype(array.dtype, np.complexfloating):
            raise ValueError(f"template.{key} must hold real numbers (got dtype {array.dtype})")
        out[key] = np.ascontiguousarray(array.astype(dtype))
    vertex_count = out["rest_vertices"].shape[0] if out["rest_vertices"].ndim == 2 else -1
    expectations = {
        "rest_vertices": (out["rest_vertices"].ndim == 2 and out["rest_vertices"].shape[1] == 3
                          and vertex_count >= 3, "(V, 3) with V >= 3"),
        "faces": (out["faces"].ndim == 2 and out["faces"].shape[1] == 3 and out["faces"].shape[0] >= 1,
                  "(Fc, 3) with Fc >= 1"),
        "skinning_weights": (out["skinning_weights"].ndim == 2
                             and out["skinning_weights"].shape[0] == vertex_count
                             and out["skinning_weights"].shape[1] >= 1, f"({vertex_count}, J) with J >= 1"),
        "body_vertex_index": (out["body_vertex_index"].shape == (vertex_count,), f"({vertex_count},)"),
    }
    if "uv" in out:
        expectations["uv"] = (out["uv"].shape == (vertex_count, 2), f"({vertex_count}, 2)")
    for key, (ok, expected) in expectations.items():
        if not ok:
            raise ValueError(f"template.{key} must have shape {expected} (got {out[key].shape})")
    faces = out["faces"]
    if faces.min() < 0 or faces.max() >= vertex_count:
        raise ValueError(
            f"template.faces must index vertices in [0, {vertex_count - 1}] "
            f"(got values in [{faces.min()}, {faces.max()}])"
        )
    for key in ("rest_vertices", "skinning_weights", "uv"):
        if key in out and not np.all(np.isfinite(out[key])):
            raise ValueError(f"template.{key} must be finite (got NaN or inf)")
    if out["body_vertex_index"].min() < -1:
        raise ValueError(
            f"template.body_vertex_index must be >= -1 (got minimum {out['body_vertex_index'].min()})"
        )
    return out


@dataclass(frozen=True)
class CanonicalTemplate:
    """A garment template checked once: its canonical arrays (``canonical_template``) and their
    ``template_sha256``. Shard writers take it in place of the dict, so a dataset of thousands of
    shards checks and hashes its template (~4 MB for a 7.7k t-shirt) once instead of per shard."""

    arrays: Mapping[str, np.ndarray]
    sha256: str

    @classmethod
    def of(cls, template: Mapping[str, Any]) -> "CanonicalTemplate":
        arrays = canonical_template(template)
        return cls(arrays, template_sha256(arrays))


def template_sha256(template: Mapping[str, Any]) -> str:
    """sha256 (hex) identifying a garment template: names, dtypes, shapes and bytes of its
    canonical arrays in sorted key order. Equal for the dict written and the arrays read back."""
    arrays = canonical_template(template)
    digest = hashlib.sha256()
    for key in sorted(arrays):
        array = arrays[key]
        digest.update(f"{key}|{array.dtype.str}|{array.shape}|".encode("ascii"))
        digest.update(array.tobytes(order="C"))
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------
# Manifest schema
# ---------------------------------------------------------------------------------------


class _Missing:
    """Marks a required key that is absent (its 'value' in a SchemaError)."""

    def __repr__(self) -> str:
        return "<missing>"


MISSING = _Missing()


@dataclass(frozen=True)
class SchemaError:
    """One violation of the manifest schema: where, what was found, what was expected."""

    path: str
    value: Any
    expected: str

    def __str__(self) -> str:
        if self.value is MISSING:
            return f"{self.path}: required key is missing (expected {self.expected})"
        return f"{self.path}: expected {self.expected}, got {_describe_value(self.value)}"


class ManifestSchemaError(ValueError):
    """A manifest does not match the schema; ``errors`` lists every violation."""

    def __init__(self, errors: list[SchemaError], *, source: str | None = None):
        self.errors = list(errors)
        self.source = source
        where = f" in {source}" if source else ""
        shown = "\n  ".join(str(error) for error in self.errors[:20])
        more = f"\n  ... and {len(self.errors) - 20} more" if len(self.errors) > 20 else ""
        super().__init__(f"manifest schema violation{where} ({len(self.errors)} errors):\n  {shown}{more}")


def _describe_value(value: Any) -> str:
    text = repr(value)
    if len(text) > 80:
        text = text[:77] + "..."
    return f"{text} ({type(value).__name__})"


def _child(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    if re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", key):
        return f"{path}.{key}"
    return f"{path}[{json.dumps(key)}]"


@dataclass(frozen=True)
class Field:
    """A node of the hand-written schema. ``kind`` is one of: str, int, number, bool, object,
    array, any, null_or_str. ``fields`` maps required/optional keys of an object; ``values`` is
    the schema of every value of a free-keyed object (``fields`` empty); ``items`` of an array."""

    kind: str
    doc: str = ""
    pattern: re.Pattern[str] | None = None
    enum: tuple[Any, ...] | None = None
    minimum: float | None = None
    fields: dict[str, tuple["Field", bool]] = field(default_factory=dict)
    values: "Field | None" = None
    items: "Field | None" = None
    unique: bool = False
    key_pattern: re.Pattern[str] | None = None
    text: str | None = None
    """Overrides the generated description of what is expected."""

    def expected(self) -> str:
        if self.text is not None:
            return self.text
        base = {
            "str": "a string",
            "null_or_str": "a string or null",
            "int": "an integer",
            "number": "a finite number",
            "bool": "true or false",
            "object": "an object",
            "array": "an array",
            "any": "any JSON value",
        }[self.kind]
        if self.enum is not None:
            base = "one of " + ", ".join(json.dumps(v) for v in self.enum)
        if self.pattern is not None:
            base += f" matching {self.pattern.pattern}"
        if self.minimum is not None:
            base += f" >= {self.minimum:g}"
        return base


def _validate(schema: Field, value: Any, path: str, errors: list[SchemaError]) -> None:
    kind = schema.kind
    if kind == "any":
        return
    if kind in ("str", "null_or_str"):
        if value is None and kind == "null_or_str":
            return
        if not isinstance(value, str):
            errors.append(SchemaError(path, value, schema.expected()))
            return
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            errors.append(SchemaError(path, value, schema.expected()))
            return
    elif kind == "number":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            errors.append(SchemaError(path, value, schema.expected()))
            return
    elif kind == "bool":
        if not isinstance(value, bool):
            errors.append(SchemaError(path, value, schema.expected()))
            return
    elif kind == "object":
        if not isinstance(value, dict):
            errors.append(SchemaError(path, value, schema.expected()))
            return
        for key, item in value.items():
            if schema.key_pattern is not None and not schema.key_pattern.match(key):
                errors.append(SchemaError(_child(path, key), key,
                                          f"a key matching {schema.key_pattern.pattern}"))
            if schema.fields:
                if key not in schema.fields:
                    errors.append(SchemaError(_child(path, key), item,
                                              "no such key (allowed: " + ", ".join(schema.fields) + ")"))
                    continue
                _validate(schema.fields[key][0], item, _child(path, key), errors)
            elif schema.values is not None:
                _validate(schema.values, item, _child(path, key), errors)
        for key, (child_schema, required) in schema.fields.items():
            if required and key not in value:
                errors.append(SchemaError(_child(path, key), MISSING, child_schema.expected()))
        return
    elif kind == "array":
        if not isinstance(value, list):
            errors.append(SchemaError(path, value, schema.expected()))
            return
        if schema.items is not None:
            for index, item in enumerate(value):
                _validate(schema.items, item, _child(path, index), errors)
        if schema.unique:
            seen: set[str] = set()
            for index, item in enumerate(value):
                token = canonical_json(item) if not isinstance(item, float) else repr(item)
                if token in seen:
                    errors.append(SchemaError(_child(path, index), item, "no duplicate entries"))
                seen.add(token)
        return
    if schema.enum is not None and value not in schema.enum:
        errors.append(SchemaError(path, value, schema.expected()))
    if schema.pattern is not None and isinstance(value, str) and not schema.pattern.match(value):
        errors.append(SchemaError(path, value, schema.expected()))
    if schema.minimum is not None and value < schema.minimum:
        errors.append(SchemaError(path, value, schema.expected()))


_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_TASK_ID = Field("str", "task id", pattern=TASK_ID_PATTERN)
_SHA = Field("str", "sha256 hex digest", pattern=SHA256_PATTERN)
_COUNT = Field("int", minimum=0)
_SECONDS = Field("number", minimum=0)
_RELATIVE_PATH = Field("str", "POSIX path relative to the dataset directory, no '..'",
                       pattern=re.compile(r"^(?!/)(?!.*(^|/)\.\.(/|$))[^\\]+$"),
                       text="a relative POSIX path inside the dataset directory (no leading '/', no '..', "
                            "no backslash)")

SHARD_ENTRY_SCHEMA = Field("object", "one finished shard", fields={
    "task_id": (_TASK_ID, True),
    "path": (_RELATIVE_PATH, True),
    "sha256": (_SHA, True),
    "bytes": (_COUNT, True),
    "frame_count": (_COUNT, True),
    "splits": (Field("array", items=Field("str", pattern=_NAME), unique=True), True),
    "filter_stats": (Field("object", "dropped frames by reason", values=_COUNT, key_pattern=_NAME), True),
    "timings": (Field("object", "seconds by stage", values=_SECONDS), True),
})

PROVENANCE_SCHEMA = Field("object", "where and how the dataset was made", fields={
    "code_version": (Field("str", "git describe of the code, else the package version"), True),
    "packages": (Field("object", "package -> version (null if not installed)",
                       values=Field("null_or_str")), True),
    "device": (Field("str", "device the simulation ran on, e.g. cuda:0"), True),
    "devices": (Field("array", items=Field("str"), unique=True), False),
    "seeds": (Field("any", "seeds used (spec seed, per-task seeds, ...)"), True),
    "start_time": (Field("str", "ISO 8601 UTC"), True),
    "end_time": (Field("null_or_str", "ISO 8601 UTC, null while running"), True),
    "resumed": (Field("array", "start times of the runs that resumed this dataset", items=Field("str")), False),
    "hostname": (Field("str"), True),
    "hostnames": (Field("array", items=Field("str"), unique=True), False),
    "python": (Field("str"), False),
    "platform": (Field("str"), False),
    "command": (Field("any", "command line or executor settings"), False),
})

MANIFEST_SCHEMA = Field("object", "a drape dataset manifest", fields={
    "format": (Field("str", enum=(MANIFEST_FORMAT,)), True),
    "schema_version": (Field("int", enum=READABLE_SCHEMA_VERSIONS), True),
    "name": (Field("str", "dataset name", pattern=_NAME), True),
    "precision": (Field("str", enum=PRECISIONS), True),
    "spec": (Field("object", "the full dataset spec", values=Field("any")), True),
    "spec_sha256": (_SHA, True),
    "template_sha256": (_SHA, True),
    "provenance": (PROVENANCE_SCHEMA, True),
    "splits": (Field("object", "split -> task ids", key_pattern=_NAME,
                     values=Field("array", items=_TASK_ID, unique=True)), True),
    "shards": (Field("array", items=SHARD_ENTRY_SCHEMA), True),
    "totals": (Field("object", fields={
        "shards": (_COUNT, True),
        "bytes": (_COUNT, True),
        "frames_kept": (_COUNT, True),
        "frames_dropped": (Field("object", values=_COUNT, key_pattern=_NAME), True),
    }), True),
    "audit": (Field("object", "free-form audit results", values=Field("any")), False),
})
"""The manifest JSON schema (version ``SCHEMA_VERSION``)."""


def validate_manifest_dict(data: Any) -> list[SchemaError]:
    """Check a parsed manifest against ``MANIFEST_SCHEMA`` plus the cross-field rules
    (unique task ids among shards). Returns every violation, empty when valid."""
    errors: list[SchemaError] = []
    if isinstance(data, dict) and "schema_version" in data and data["schema_version"] not in READABLE_SCHEMA_VERSIONS:
        # A different version has a different schema: report only that, not a cascade.
        readable = ", ".join(map(str, READABLE_SCHEMA_VERSIONS))
        return [SchemaError("$.schema_version", data["schema_version"],
                            f"one of {readable} (this drape reads schema versions {readable})")]
    _validate(MANIFEST_SCHEMA, data, "$", errors)
    if isinstance(data, dict) and isinstance(data.get("shards"), list):
        seen: dict[str, int] = {}
        for index, entry in enumerate(data["shards"]):
            if isinstance(entry, dict) and isinstance(entry.get("task_id"), str):
                task_id = entry["task_id"]
                if task_id in seen:
                    errors.append(SchemaError(f"$.shards[{index}].task_id", task_id,
                                              f"a task id not already used by $.shards[{seen[task_id]}]"))
                seen.setdefault(task_id, index)
    return errors


def describe_schema(schema: Field = MANIFEST_SCHEMA, *, path: str = "$", indent: int = 0) -> str:
    """Human-readable outline of a schema (one line per key), for docs and --help."""
    lines: list[str] = []
    pad = "  " * indent
    lines.append(f"{pad}{path}: {schema.expected()}" + (f"  -- {schema.doc}" if schema.doc else ""))
    for key, (child, required) in schema.fields.items():
        sub = describe_schema(child, path=_child(path, key), indent=indent + 1)
        if not required:
            sub = sub.replace(":", " (optional):", 1)
        lines.append(sub)
    if schema.values is not None and schema.values.kind != "any":
        lines.append(describe_schema(schema.values, path=f"{path}.<key>", indent=indent + 1))
    if schema.items is not None:
        lines.append(describe_schema(schema.items, path=f"{path}[]", indent=indent + 1))
    return "\n".join(lines)
