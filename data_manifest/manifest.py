"""The dataset manifest: one versioned JSON file that lists every finished shard.

A shard is listed only after it was renamed to its final name, and the manifest itself is
written atomically (temporary file, fsync, rename), so at every moment ``manifest.json``
describes only complete shards. ``is_complete(task_id)`` (listed, present, same sha256) is
what a resumed job uses to skip finished tasks; ``merge`` joins the partial manifests that
workers of a distributed executor write.
"""

from __future__ import annotations

import copy
import datetime as _dt
import importlib.metadata
import json
import os
import platform
import secrets
import socket
import subprocess
from pathlib import Path, PurePosixPath
from typing import Any, Iterable, Mapping

from .schema import (
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    PRECISIONS,
    SCHEMA_VERSION,
    TMP_SUFFIX,
    ManifestSchemaError,
    SchemaError,
    check_task_id,
    spec_sha256,
    validate_manifest_dict,
)
from .shard import ShardRecord, file_sha256, fsync_directory

PROVENANCE_PACKAGES = ("warp-lang", "torch", "numpy", "h5py", "drape")
"""Distributions whose versions ``collect_provenance`` records."""


def utc_now() -> str:
    """Current time, ISO 8601 UTC with milliseconds, e.g. ``2026-11-21T10:00:52.125+00:00``."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def code_version() -> str:
    """``git describe --always --dirty --tags`` of the source tree drape runs from, or
    ``drape <package version>`` when it is not a git checkout (or git is absent)."""
    source = Path(__file__).resolve().parent.parent
    if (source / ".git").exists():
        try:
            described = subprocess.run(
                ["git", "describe", "--always", "--dirty", "--tags"], cwd=source,
                capture_output=True, text=True, timeout=10, check=True,
            ).stdout.strip()
            if described:
                return f"git {described}"
        except (OSError, subprocess.SubprocessError):
            pass
    try:
        return f"drape {importlib.metadata.version('drape')}"
    except importlib.metadata.PackageNotFoundError:
        return "drape (unknown version)"


def package_versions(names: Iterable[str] = PROVENANCE_PACKAGES) -> dict[str, str | None]:
    """Installed version of each distribution (None where not installed), without importing it."""
    versions: dict[str, str | None] = {}
    for name in names:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def collect_provenance(
    *,
    device: str,
    seeds: Any,
    start_time: str | None = None,
    end_time: str | None = None,
    command: Any | None = None,
) -> dict[str, Any]:
    """Provenance block of a manifest: code version, package versions (warp, torch, numpy,
    h5py, drape), ``device`` (e.g. "cuda:0"), ``seeds`` (any JSON: the spec seed, per-task
    seeds), start/end time (ISO 8601 UTC; start defaults to now), hostname, Python, platform,
    and optionally the ``command`` that made the dataset."""
    if not isinstance(device, str) or not device:
        raise ValueError(f"provenance device must be a non-empty string such as 'cpu' or 'cuda:0' (got {device!r})")
    provenance: dict[str, Any] = {
        "code_version": code_version(),
        "packages": package_versions(),
        "device": device,
        "seeds": _json_value(seeds, where="provenance seeds"),
        "start_time": start_time or utc_now(),
        "end_time": end_time,
        "hostname": socket.gethostname(),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    if command is not None:
        provenance["command"] = _json_value(command, where="provenance command")
    return provenance


def _json_value(value: Any, *, where: str) -> Any:
    """A deep copy of ``value`` as plain JSON types (tuples -> lists, numpy -> Python)."""
    def convert(item: Any) -> Any:
        if hasattr(item, "tolist") and not isinstance(item, (str, bytes)):
            return item.tolist()
        raise TypeError(f"{type(item).__name__} is not JSON serializable")

    try:
        return json.loads(json.dumps(value, default=convert, allow_nan=False))
    except (TypeError, ValueError) as error:
        raise ValueError(f"{where} must be JSON-serializable without NaN/inf ({error})") from None


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same directory, fsync, rename:
    readers see the old content or the new, never a partial file."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}{TMP_SUFFIX}")
    try:
        with open(tmp, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise
    fsync_directory(path.parent)


class Manifest:
    """In-memory form of ``manifest.json``.

    name: dataset name. spec: the full dataset spec (JSON-able dict); ``spec_sha256`` is
    derived from it. template_sha256: ``schema.template_sha256`` of the garment template.
    precision: "float32" or "float16". provenance: see ``collect_provenance``.
    splits: split -> task ids (planned or finished). root: the dataset directory that
    shard paths are relative to (set by ``load``/``create``; needed for file checks).
    """

    def __init__(
        self,
        *,
        name: str,
        spec: Mapping[str, Any],
        template_sha256: str,
        precision: str,
        provenance: Mapping[str, Any],
        splits: Mapping[str, Iterable[str]] | None = None,
        shards: Iterable[Mapping[str, Any]] = (),
        audit: Mapping[str, Any] | None = None,
        root: str | os.PathLike[str] | None = None,
        _validated: bool = False,
    ):
        self.name = name
        self.spec: dict[str, Any] = _json_value(dict(spec), where="spec")
        self.template_sha256 = template_sha256
        self.precision = precision
        self.provenance: dict[str, Any] = _json_value(dict(provenance), where="provenance")
        self.audit: dict[str, Any] | None = None if audit is None else _json_value(dict(audit), where="audit")
        self.root: Path | None = Path(root) if root is not None else None
        self._splits: dict[str, set[str]] = {}
        self._shards: dict[str, dict[str, Any]] = {}
        self.loaded_totals: dict[str, Any] | None = None
        """Totals as read from disk by ``load`` (the validator compares them with ``totals``)."""
        self.schema_version = SCHEMA_VERSION
        """Schema version of the dataset: as loaded (an older dataset stays readable), else the
        version this code writes (also after a resume, which writes shards of that version)."""
        for split, task_ids in (splits or {}).items():
            self.plan_split(split, task_ids)
        if _validated:  # from_dict checked the whole manifest: each entry is listed as it is
            for entry in shards:
                self._put_entry(dict(entry))
            return
        for entry in shards:
            self.add_shard(entry)
        errors = validate_manifest_dict(self.to_dict())
        if errors:
            raise ManifestSchemaError(errors)

    # -- construction / IO ----------------------------------------------------------------

    @classmethod
    def create(
        cls,
        root: str | os.PathLike[str],
        *,
        name: str,
        spec: Mapping[str, Any],
        template_sha256: str,
        precision: str,
        provenance: Mapping[str, Any],
        splits: Mapping[str, Iterable[str]] | None = None,
    ) -> "Manifest":
        """A new, empty manifest for the dataset directory ``root`` (not yet saved)."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS} (got {precision!r})")
        return cls(name=name, spec=spec, template_sha256=template_sha256, precision=precision,
                   provenance=provenance, splits=splits, root=root)

    @classmethod
    def load_or_create(
        cls,
        root: str | os.PathLike[str],
        *,
        name: str,
        spec: Mapping[str, Any],
        template_sha256: str,
        precision: str,
        provenance: Mapping[str, Any],
        splits: Mapping[str, Iterable[str]] | None = None,
    ) -> "Manifest":
        """Resume-or-start: load ``root``'s manifest when there is one, else ``create``.

        A loaded manifest must describe the same dataset: name, spec (by sha256), template
        and precision must match, else ValueError naming the field (rerun into a new
        directory instead). On resume the provenance becomes ``provenance`` except that the
        original ``start_time`` is kept and this run's start is appended to ``resumed``;
        ``splits`` are added to the planned ones. Listed shards are kept: check each with
        ``is_complete`` before skipping its task.
        """
        if not (Path(root) / MANIFEST_NAME).is_file():
            return cls.create(root, name=name, spec=spec, template_sha256=template_sha256, precision=precision,
                              provenance=provenance, splits=splits)
        manifest = cls.load(root)
        wanted = {"name": name, "spec_sha256": spec_sha256(_json_value(dict(spec), where="spec")),
                  "template_sha256": template_sha256, "precision": precision}
        for field_name, value in wanted.items():
            if getattr(manifest, field_name) != value:
                raise ValueError(
                    f"dataset {str(root)!r} was made with {field_name} {getattr(manifest, field_name)!r}, this run "
                    f"has {value!r}; resume only with the same spec, template and precision, or write to a new "
                    f"directory")
        manifest.schema_version = SCHEMA_VERSION  # the shards this run adds are written at this version
        previous = manifest.provenance
        updated = _json_value(dict(provenance), where="provenance")
        updated["resumed"] = list(previous.get("resumed", [])) + [updated["start_time"]]
        updated["start_time"] = previous["start_time"]
        updated["end_time"] = None
        manifest.provenance = updated
        for split, task_ids in (splits or {}).items():
            manifest.plan_split(split, task_ids)
        return manifest

    @classmethod
    def from_dict(cls, data: Any, *, root: str | os.PathLike[str] | None = None,
                  source: str | None = None, _owned: bool = False) -> "Manifest":
        """Build from parsed JSON; raises ManifestSchemaError listing every violation. The
        manifest keeps copies of ``data``'s shard entries (``_owned``: ``data`` was parsed for
        it alone, as by :meth:`load`, and is kept as it is)."""
        errors = validate_manifest_dict(data)
        if errors:
            raise ManifestSchemaError(errors, source=source)
        if data["spec_sha256"] != spec_sha256(data["spec"]):
            raise ManifestSchemaError([_spec_hash_error(data)], source=source)
        manifest = cls(name=data["name"], spec=data["spec"], template_sha256=data["template_sha256"],
                       precision=data["precision"], provenance=data["provenance"], splits=data["splits"],
                       shards=data["shards"] if _owned else copy.deepcopy(data["shards"]), audit=data.get("audit"),
                       root=root, _validated=True)
        manifest.loaded_totals = copy.deepcopy(data["totals"])
        manifest.schema_version = int(data["schema_version"])
        return manifest

    @classmethod
    def load(cls, root: str | os.PathLike[str], *, filename: str = MANIFEST_NAME) -> "Manifest":
        """Read ``root/filename``. FileNotFoundError names the missing directory or file;
        ValueError (ManifestSchemaError) names every schema violation by JSON path."""
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"dataset directory {str(root)!r} does not exist")
        path = root / filename
        if not path.is_file():
            raise FileNotFoundError(f"dataset manifest {str(path)!r} does not exist (is {str(root)!r} a drape "
                                    f"dataset directory, and has its generation finished a first shard?)")
        text = path.read_text(encoding="utf-8")
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"dataset manifest {str(path)!r} is not valid JSON: {error.msg} at line "
                             f"{error.lineno} column {error.colno}") from None
        return cls.from_dict(data, root=root, source=str(path), _owned=True)

    def to_dict(self) -> dict[str, Any]:
        """The manifest as JSON-ready data (shards sorted by task id, split lists sorted)."""
        data: dict[str, Any] = {
            "format": MANIFEST_FORMAT,
            "schema_version": self.schema_version,
            "name": self.name,
            "precision": self.precision,
            "spec": copy.deepcopy(self.spec),
            "spec_sha256": self.spec_sha256,
            "template_sha256": self.template_sha256,
            "provenance": copy.deepcopy(self.provenance),
            "splits": self.splits,
            "shards": self.shards,
            "totals": self.totals,
        }
        if self.audit is not None:
            data["audit"] = copy.deepcopy(self.audit)
        return data

    def save(self, root: str | os.PathLike[str] | None = None, *, filename: str = MANIFEST_NAME) -> Path:
        """Atomically write ``root/filename`` (root defaults to ``self.root``); returns the path."""
        directory = Path(root) if root is not None else self._require_root()
        directory.mkdir(parents=True, exist_ok=True)
        data = self.to_dict()
        errors = validate_manifest_dict(data)
        if errors:
            raise ManifestSchemaError(errors, source="manifest being saved")
        path = directory / filename
        atomic_write_text(path, json.dumps(data, indent=1, sort_keys=False, allow_nan=False) + "\n")
        if self.root is None:
            self.root = directory
        return path

    # -- content --------------------------------------------------------------------------

    @property
    def spec_sha256(self) -> str:
        return spec_sha256(self.spec)

    @property
    def splits(self) -> dict[str, list[str]]:
        """split -> sorted task ids."""
        return {split: sorted(ids) for split, ids in sorted(self._splits.items())}

    @property
    def shards(self) -> list[dict[str, Any]]:
        """Shard entries (copies), sorted by task id: the order ``DatasetReader`` numbers them."""
        return [copy.deepcopy(self._shards[task_id]) for task_id in sorted(self._shards)]

    @property
    def task_ids(self) -> list[str]:
        """Task ids of the listed shards, sorted."""
        return sorted(self._shards)

    @property
    def totals(self) -> dict[str, Any]:
        """Shard count, bytes, frames kept and frames dropped by reason, summed over shards."""
        dropped: dict[str, int] = {}
        for entry in self._shards.values():
            for reason, count in entry["filter_stats"].items():
                dropped[reason] = dropped.get(reason, 0) + count
        return {
            "shards": len(self._shards),
            "bytes": sum(entry["bytes"] for entry in self._shards.values()),
            "frames_kept": sum(entry["frame_count"] for entry in self._shards.values()),
            "frames_dropped": dict(sorted(dropped.items())),
        }

    def shard(self, task_id: str) -> dict[str, Any] | None:
        """The entry of a listed shard (a copy), or None."""
        entry = self._shards.get(task_id)
        return copy.deepcopy(entry) if entry is not None else None

    def plan_split(self, split: str, task_ids: Iterable[str]) -> None:
        """Declare that ``task_ids`` belong to ``split`` (before or after their shards exist)."""
        if isinstance(task_ids, str):
            raise ValueError(f"splits[{split!r}] must be a list of task ids (got the string {task_ids!r})")
        members = self._splits.setdefault(split, set())
        for task_id in task_ids:
            members.add(check_task_id(task_id, where=f"splits[{split!r}] entry"))

    def add_shard(self, record: ShardRecord | Mapping[str, Any], *,
                  timings: Mapping[str, float] | None = None) -> dict[str, Any]:
        """List a finished shard (replacing an earlier entry of the same task) and add its
        task to its splits. ``record``: a ``ShardRecord`` from ``ShardWriter.close()`` (its
        path must lie under ``root``) or a manifest entry dict. ``timings`` are merged into
        the entry's timings. Returns the stored entry."""
        if isinstance(record, ShardRecord):
            root = self._require_root()
            try:
                relative = Path(os.path.abspath(record.path)).relative_to(os.path.abspath(root))
            except ValueError:
                raise ValueError(f"shard {str(record.path)!r} of task {record.task_id!r} is not inside the "
                                 f"dataset directory {str(root)!r}") from None
            entry = {
                "task_id": record.task_id,
                "path": PurePosixPath(*relative.parts).as_posix(),
                "sha256": record.sha256,
                "bytes": int(record.bytes),
                "frame_count": int(record.frame_count),
                "splits": list(record.splits),
                "filter_stats": dict(record.filter_stats),
                "timings": dict(record.timings),
            }
        else:
            entry = _json_value(dict(record), where="shard entry")
        if timings:
            entry.setdefault("timings", {}).update({k: float(v) for k, v in timings.items()})
        errors = validate_manifest_dict({"shards": [entry]})
        errors = [error for error in errors if error.path.startswith("$.shards")]
        if errors:
            raise ManifestSchemaError(errors, source=f"shard entry of task {entry.get('task_id')!r}")
        self._put_entry(entry)
        return copy.deepcopy(entry)

    def _put_entry(self, entry: dict[str, Any]) -> None:
        entry["splits"] = sorted(entry.get("splits", []))
        entry["filter_stats"] = dict(sorted(entry.get("filter_stats", {}).items()))
        entry["timings"] = dict(sorted(entry.get("timings", {}).items()))
        task_id = entry.get("task_id")
        if isinstance(task_id, str):
            self._shards[task_id] = entry
            for split in entry["splits"]:
                self._splits.setdefault(split, set()).add(task_id)

    def remove_shard(self, task_id: str) -> None:
        """Unlist a shard (its task stays planned in its splits)."""
        self._shards.pop(task_id, None)

    def shard_file(self, task_id: str) -> Path:
        """Absolute path of a listed shard's file."""
        entry = self._shards.get(task_id)
        if entry is None:
            raise ValueError(f"task {task_id!r} has no shard in the manifest of dataset {self.name!r}")
        return self._require_root() / entry["path"]

    def is_complete(self, task_id: str) -> bool:
        """True when the task's shard is listed, its file exists with the listed size, and
        its sha256 matches: the test a resumed job uses to skip a task."""
        entry = self._shards.get(task_id)
        if entry is None:
            return False
        path = self._require_root() / entry["path"]
        try:
            if path.stat().st_size != entry["bytes"]:
                return False
        except OSError:
            return False
        return file_sha256(path) == entry["sha256"]

    def finish(self, *, end_time: str | None = None) -> None:
        """Record the end time of the generation in the provenance (now by default)."""
        self.provenance["end_time"] = end_time or utc_now()

    def _require_root(self) -> Path:
        if self.root is None:
            raise ValueError(f"manifest of dataset {self.name!r} has no root directory; load it with "
                             f"Manifest.load(dir) or create it with Manifest.create(dir, ...)")
        return self.root

    # -- merging --------------------------------------------------------------------------

    def merge(self, *others: "Manifest") -> "Manifest":
        """A new manifest holding the shards and splits of ``self`` and ``others`` (partial
        manifests of workers of one job). They must agree on name, spec, template and
        precision; a task listed twice must have the same sha256. Provenance: ``self``'s,
        with the earliest start, the latest end (null if any is still running), and every
        device and hostname in ``devices`` / ``hostnames``."""
        merged = Manifest(name=self.name, spec=self.spec, template_sha256=self.template_sha256,
                          precision=self.precision, provenance=self.provenance, splits=self.splits,
                          shards=self.shards, audit=self.audit, root=self.root)
        devices = set(self.provenance.get("devices", [])) | {self.provenance["device"]}
        hosts = set(self.provenance.get("hostnames", [])) | {self.provenance["hostname"]}
        starts = [self.provenance["start_time"]]
        ends = [self.provenance["end_time"]]
        for index, other in enumerate(others):
            for field_name in ("name", "spec_sha256", "template_sha256", "precision"):
                mine, theirs = getattr(self, field_name), getattr(other, field_name)
                if mine != theirs:
                    raise ValueError(f"cannot merge manifests: {field_name} differs ({mine!r} in the first, "
                                     f"{theirs!r} in manifest {index + 1} of the others)")
            for split, task_ids in other.splits.items():
                merged.plan_split(split, task_ids)
            for entry in other.shards:
                existing = merged._shards.get(entry["task_id"])
                if existing is not None and existing["sha256"] != entry["sha256"]:
                    raise ValueError(
                        f"cannot merge manifests: task {entry['task_id']!r} is listed with sha256 "
                        f"{existing['sha256']} and {entry['sha256']} (two different shards for one task)")
                merged._put_entry(copy.deepcopy(entry))
            devices |= set(other.provenance.get("devices", [])) | {other.provenance["device"]}
            hosts |= set(other.provenance.get("hostnames", [])) | {other.provenance["hostname"]}
            starts.append(other.provenance["start_time"])
            ends.append(other.provenance["end_time"])
        merged.provenance["devices"] = sorted(devices)
        merged.provenance["hostnames"] = sorted(hosts)
        merged.provenance["start_time"] = min(starts, key=parse_time)
        merged.provenance["end_time"] = None if any(end is None for end in ends) else max(ends, key=parse_time)
        return merged

    def __repr__(self) -> str:
        totals = self.totals
        return (f"Manifest(name={self.name!r}, precision={self.precision!r}, shards={totals['shards']}, "
                f"frames_kept={totals['frames_kept']}, splits={sorted(self._splits)})")


def parse_time(text: str) -> _dt.datetime:
    """A provenance time (ISO 8601) as an aware datetime (UTC when it names no zone)."""
    try:
        parsed = _dt.datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"provenance time {text!r} is not ISO 8601 (e.g. 2026-11-21T10:00:52+00:00)") from None
    return parsed if parsed.tzinfo else parsed.replace(tzinfo=_dt.timezone.utc)


def _spec_hash_error(data: Mapping[str, Any]) -> SchemaError:
    return SchemaError("$.spec_sha256", data["spec_sha256"],
                       f"the sha256 of the canonical JSON of $.spec ({spec_sha256(data['spec'])})")


def merge_manifests(manifests: Iterable[Manifest]) -> Manifest:
    """Merge a non-empty sequence of partial manifests (see ``Manifest.merge``)."""
    items = list(manifests)
    if not items:
        raise ValueError("merge_manifests needs at least one manifest (got none)")
    return items[0].merge(*items[1:])


__all__ = [
    "Manifest",
    "atomic_write_text",
    "code_version",
    "collect_provenance",
    "merge_manifests",
    "package_versions",
    "parse_time",
    "utc_now",
]
