"""Checking a dataset directory against its manifest, and summarizing it.

``validate_dataset(root)`` checks the manifest schema and spec hash, that every listed shard
exists with the listed size and sha256, that its HDF5 layout, attributes, template and frame
count match the manifest, that split membership is consistent and that totals add up; it
also lists orphans (``*.tmp`` files and unlisted ``*.h5`` shards). ``info(root)`` renders the
summary table printed by ``drape dataset info``.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

from .manifest import Manifest, parse_time
from .schema import (
    FRAME_INDEX,
    MANIFEST_NAME,
    SHARD_SUFFIX,
    TMP_SUFFIX,
    ManifestSchemaError,
    template_sha256,
)
from .shard import check_shard_layout, file_sha256, read_dropped_log, read_shard_attrs, read_template

ERROR_KINDS = ("missing", "schema", "checksum", "size", "corrupt", "layout", "template",
               "frame_count", "split", "totals", "pending")
"""Kinds of problems that make a dataset invalid."""

WARNING_KINDS = ("orphan_tmp", "orphan_shard")
"""Kinds of problems reported but tolerated (readers never look at these files)."""


@dataclass(frozen=True)
class Problem:
    """One finding: ``kind`` (see ERROR_KINDS / WARNING_KINDS), ``where`` (a file path or a
    JSON path), ``message`` (what is wrong and what was expected)."""

    kind: str
    where: str
    message: str

    def __str__(self) -> str:
        return f"[{self.kind}] {self.where}: {self.message}"


@dataclass
class Report:
    """Outcome of ``validate_dataset``. ``ok`` is True when there are no errors."""

    root: Path
    errors: list[Problem] = field(default_factory=list)
    warnings: list[Problem] = field(default_factory=list)
    shards_checked: int = 0
    frames_checked: int = 0

    @property
    def ok(self) -> bool:
        return not self.errors

    def add(self, kind: str, where: str | os.PathLike[str], message: str) -> None:
        problem = Problem(kind, str(where), message)
        (self.warnings if kind in WARNING_KINDS else self.errors).append(problem)

    def kinds(self) -> dict[str, int]:
        """Number of findings per kind."""
        counts: dict[str, int] = {}
        for problem in self.errors + self.warnings:
            counts[problem.kind] = counts.get(problem.kind, 0) + 1
        return counts

    def __str__(self) -> str:
        status = "OK" if self.ok else "INVALID"
        lines = [f"dataset {str(self.root)!r}: {status} ({self.shards_checked} shards, "
                 f"{self.frames_checked} frames checked; {len(self.errors)} errors, "
                 f"{len(self.warnings)} warnings)"]
        lines += [f"  error   {problem}" for problem in self.errors]
        lines += [f"  warning {problem}" for problem in self.warnings]
        return "\n".join(lines)


def check_shard_file(
    root: str | os.PathLike[str],
    entry: Mapping[str, Any],
    *,
    manifest: Manifest,
    check_sha256: bool = True,
) -> list[Problem]:
    """Check one listed shard against its manifest entry: exists, size, sha256, opens as
    HDF5, layout, attributes (task id, splits, precision, template hash, filter stats),
    stored template hash, frame count. Returns the problems found (empty when sound)."""
    report = Report(Path(root))
    path = Path(root) / entry["path"]
    task_id = entry["task_id"]
    if not path.is_file():
        report.add("missing", path, f"shard of task {task_id!r} is listed in the manifest but does not exist")
        return report.errors
    size = path.stat().st_size
    if size != entry["bytes"]:
        report.add("size", path, f"shard of task {task_id!r} has {size} bytes, the manifest lists {entry['bytes']}")
    if check_sha256:
        digest = file_sha256(path)
        if digest != entry["sha256"]:
            report.add("checksum", path, f"shard of task {task_id!r} has sha256 {digest}, the manifest lists "
                                         f"{entry['sha256']} (the file is corrupt or was replaced)")
    try:
        with h5py.File(path, "r") as handle:
            for message in check_shard_layout(handle):
                report.add("layout", path, message)
            try:
                attrs = read_shard_attrs(handle)
            except ValueError as error:
                report.add("layout", path, str(error))
                return report.errors
            expectations = (
                ("task_id", attrs["task_id"], task_id),
                ("splits", sorted(attrs["splits"]), sorted(entry["splits"])),
                ("precision", attrs["precision"], manifest.precision),
                ("template_sha256", attrs["template_sha256"], manifest.template_sha256),
                ("filter_stats", dict(sorted(attrs["filter_stats"].items())), dict(entry["filter_stats"])),
            )
            for name, found, expected in expectations:
                if found != expected:
                    kind = "template" if name == "template_sha256" else ("split" if name == "splits" else "layout")
                    report.add(kind, path, f"attribute {name} is {found!r}, the manifest says {expected!r}")
            try:
                stored_hash = template_sha256(read_template(handle))
            except (ValueError, OSError, KeyError) as error:
                report.add("template", path, f"stored template cannot be read or is malformed: {error}")
            else:
                if stored_hash != attrs["template_sha256"]:
                    report.add("template", path, f"stored template hashes to {stored_hash}, its attribute says "
                                                 f"{attrs['template_sha256']}")
            if "posed_vertices" in handle:
                frames = handle["posed_vertices"].shape[0]
                if frames != entry["frame_count"]:
                    report.add("frame_count", path, f"shard holds {frames} frames, the manifest lists "
                                                    f"{entry['frame_count']}")
    except (OSError, KeyError, TypeError, ValueError, IndexError, RuntimeError, AttributeError, OverflowError) as error:
        # damaged HDF5 surfaces as any of these from h5py: each is a finding, never a crash
        report.add("corrupt", path, f"shard of task {task_id!r} cannot be read as HDF5: {type(error).__name__}: {error}")
    return report.errors


def validate_dataset(root: str | os.PathLike[str], *, check_sha256: bool = True) -> Report:
    """Check a dataset directory; see the module docstring. Never raises on a bad dataset:
    every finding is in the returned Report."""
    root = Path(root)
    report = Report(root)
    if not root.is_dir():
        report.add("missing", root, "dataset directory does not exist")
        return report
    manifest_path = root / MANIFEST_NAME
    if not manifest_path.is_file():
        report.add("missing", manifest_path, "manifest does not exist")
        _find_orphans(root, set(), report)
        return report
    try:
        raw = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        report.add("schema", manifest_path, f"manifest is not valid JSON: {error}")
        return report
    try:
        manifest = Manifest.from_dict(raw, root=root, source=str(manifest_path))
    except ManifestSchemaError as error:
        for schema_error in error.errors:
            report.add("schema", f"{manifest_path}:{schema_error.path}", str(schema_error).split(": ", 1)[1])
        return report

    # Split membership, from the raw JSON (loading the manifest would add missing members).
    entries = {entry["task_id"]: entry for entry in raw["shards"]}
    for index, entry in enumerate(raw["shards"]):
        for split in entry["splits"]:
            if entry["task_id"] not in raw["splits"].get(split, []):
                report.add("split", f"{manifest_path}:$.shards[{index}].splits",
                           f"task {entry['task_id']!r} says it is in split {split!r}, but $.splits.{split} "
                           f"does not list it")
    for split, task_ids in raw["splits"].items():
        for task_id in task_ids:
            entry = entries.get(task_id)
            if entry is None:
                report.add("pending", f"{manifest_path}:$.splits.{split}",
                           f"task {task_id!r} of split {split!r} has no shard listed (generation unfinished?)")
            elif split not in entry["splits"]:
                report.add("split", f"{manifest_path}:$.splits.{split}",
                           f"task {task_id!r} is listed in split {split!r} but its shard entry has splits "
                           f"{entry['splits']}")

    totals = manifest.totals
    for key in ("shards", "bytes", "frames_kept", "frames_dropped"):
        if raw["totals"][key] != totals[key]:
            report.add("totals", f"{manifest_path}:$.totals.{key}",
                       f"is {raw['totals'][key]!r}, the shard entries add up to {totals[key]!r}")

    for entry in manifest.shards:
        for problem in check_shard_file(root, entry, manifest=manifest, check_sha256=check_sha256):
            report.errors.append(problem)
        report.shards_checked += 1
        report.frames_checked += entry["frame_count"]

    listed = {(root / entry["path"]).resolve() for entry in manifest.shards}
    _find_orphans(root, listed, report)
    return report


def _find_orphans(root: Path, listed: set[Path], report: Report) -> None:
    for path in sorted(root.rglob("*")):
        if not path.is_file():
            continue
        if path.name.endswith(TMP_SUFFIX):
            report.add("orphan_tmp", path, "temporary file of an unfinished write (ignored by readers; safe to "
                                           "delete when no job is writing)")
        elif path.suffix == SHARD_SUFFIX and path.resolve() not in listed:
            report.add("orphan_shard", path, "shard not listed in the manifest (ignored by readers; a resumed "
                                             "job rewrites it)")


# ---------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------


def format_table(headers: list[str], rows: list[list[Any]]) -> str:
    """Plain-text table, first column left-aligned and the others right-aligned."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]

    def line(row: list[str]) -> str:
        return "  ".join(cell.ljust(widths[i]) if i == 0 else cell.rjust(widths[i]) for i, cell in enumerate(row))

    rule = "  ".join("-" * width for width in widths)
    return "\n".join([line(cells[0]), rule] + [line(row) for row in cells[1:]])


def _size(count: int) -> str:
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} TiB"


def info(root: str | os.PathLike[str], *, with_problems: bool = False) -> str | tuple[str, list[tuple[str, str]]]:
    """Summary of a dataset from its manifest: identity and provenance, tasks and frames per
    split, frames kept and dropped by reason, size, precision, timings; the integrity of every
    listed shard (missing, or size / sha256 not those the manifest lists; digests cached, see
    ``integrity``), and a generation in progress (its lock); and, from the sound shards' frame
    indices and dropped-frame logs, the kept share by position in the sequence. Raises
    FileNotFoundError / ValueError like ``Manifest.load``. ``with_problems``: also return the
    integrity problems as (kind, message) pairs."""
    from .integrity import IntegrityChecker
    from .lock import read_lock

    manifest = Manifest.load(root)
    totals = manifest.totals
    provenance = manifest.provenance
    checker = IntegrityChecker(root)
    problems: list[tuple[str, str]] = []
    sound = []
    for entry in manifest.shards:
        problem = checker.problem(entry)
        if problem is None:
            sound.append(entry)
        else:
            problems.append(problem)
    shards = manifest.shards
    lines = [
        f"dataset {manifest.name}  (schema {manifest.to_dict()['schema_version']}, precision "
        f"{manifest.precision}, {totals['shards']} shards, {_size(totals['bytes'])})",
        f"spec sha256 {manifest.spec_sha256[:16]}  template sha256 {manifest.template_sha256[:16]}",
        f"code {provenance['code_version']}  device {provenance['device']}  host {provenance['hostname']}",
    ]
    wall_s: float | None = None
    if provenance.get("end_time"):
        wall_s = (parse_time(provenance["end_time"]) - parse_time(provenance["start_time"])).total_seconds()
    lines.append(f"time {provenance['start_time']} -> {provenance.get('end_time') or 'running'}"
                 + (f"  (wall {wall_s:.1f} s)" if wall_s is not None else ""))
    lines.append("")

    split_rows = []
    for split, task_ids in manifest.splits.items():
        done = [entry for entry in shards if split in entry["splits"]]
        split_rows.append([split, len(task_ids), len(done), sum(entry["frame_count"] for entry in done)])
    split_rows.append(["all", len({t for ids in manifest.splits.values() for t in ids} | set(manifest.task_ids)),
                       totals["shards"], totals["frames_kept"]])
    lines.append(format_table(["split", "tasks", "shards", "frames"], split_rows))
    lines.append("")

    dropped = totals["frames_dropped"]
    seen = totals["frames_kept"] + sum(dropped.values())

    def share(count: int) -> str:
        return f"{100.0 * count / seen:.1f} %" if seen else "-"

    frame_rows = [["kept", totals["frames_kept"], share(totals["frames_kept"])]]
    frame_rows += [[f"dropped: {reason}", count, share(count)] for reason, count in dropped.items()]
    frame_rows.append(["total simulated", seen, share(seen)])
    lines.append(format_table(["frames", "count", "share"], frame_rows))
    lines.append("")

    timing_totals: dict[str, float] = {}
    for entry in shards:
        for key, seconds in entry["timings"].items():
            timing_totals[key] = timing_totals.get(key, 0.0) + seconds
    timing_rows = [[key, f"{seconds:.2f}", f"{seconds / max(1, totals['shards']):.3f}"]
                   for key, seconds in sorted(timing_totals.items())]
    if timing_rows:
        lines.append(format_table(["timing", "total s", "per shard s"], timing_rows))
    if wall_s:
        lines.append(f"throughput: {totals['frames_kept'] / wall_s:.2f} kept frames/s, "
                     f"{seen / wall_s:.2f} simulated frames/s over {wall_s:.1f} s wall")
    if manifest.audit is not None:
        lines.extend(_audit_lines(manifest.audit))
    lines.append("")
    if problems:
        missing = sum(kind == "missing" for kind, _ in problems)
        lines.append(f"integrity: {len(problems)} of {len(shards)} shards do not match the manifest "
                     f"({missing} missing, {len(problems) - missing} corrupt); readers refuse them. "
                     f"Rerun generate-dataset to rewrite them, or `drape dataset validate` for details:")
        lines.extend(f"  {kind:<8} {message}" for kind, message in problems)
    else:
        lines.append(f"integrity: all {len(shards)} shards match the manifest (size and sha256)")
    holder = read_lock(root)
    if holder is not None:
        lines.append(f"being written: {holder.describe()}")
    position_rows = _keep_by_position(Path(root), sound)
    if position_rows:
        lines.append("")
        lines.append(format_table(["position in sequence", "frames", "kept", "most dropped for"], position_rows))
    lines.extend(_keep_by_pair(Path(root), shards, sound))
    text = "\n".join(lines).rstrip() + "\n"
    return (text, problems) if with_problems else text


#: Buckets of a frame's position in its task's sequence (frame_index) for ``info``: (first, last).
POSITION_BUCKETS = ((0, 0), (1, 1), (2, 4), (5, 9), (10, 19), (20, 49), (50, None))


def _keep_by_position(root: Path, shards: list[dict]) -> list[list[Any]]:
    """Kept share per position bucket of the target poses in their tasks' sequences, from the
    shards' ``frame_index`` and their ``dropped`` logs; empty unless every shard with dropped frames
    logs them. Tangles carried along a sequence show as a keep rate that falls with the position."""
    kept_idx, dropped_idx, reasons = [], [], []
    for entry in shards:
        try:
            with h5py.File(root / entry["path"], "r") as handle:
                kept_idx.append(handle[FRAME_INDEX][()].astype(np.int64))
                if sum(entry["filter_stats"].values()):
                    log = read_dropped_log(handle)
                    if log is None:
                        return []
                    dropped_idx.append(log["frame_index"])
                    reasons.append(log["reason"])
        except (OSError, KeyError, TypeError, ValueError, IndexError, RuntimeError, AttributeError):
            return []  # validate reports unreadable shards; the summary leaves the table out
    if not dropped_idx:
        return []
    kept = np.concatenate(kept_idx) if kept_idx else np.zeros(0, np.int64)
    dropped = np.concatenate(dropped_idx)
    reasons_arr = np.concatenate(reasons)
    rows = []
    for first, last in POSITION_BUCKETS:
        upper = np.iinfo(np.int64).max if last is None else last
        k = int(((kept >= first) & (kept <= upper)).sum())
        in_bucket = (dropped >= first) & (dropped <= upper)
        d = int(in_bucket.sum())
        if k + d == 0:
            continue
        names, counts = np.unique(reasons_arr[in_bucket], return_counts=True)
        worst = f"{names[counts.argmax()]} ({100.0 * counts.max() / (k + d):.0f} %)" if d else "-"
        label = str(first) if first == last else (f"{first}-{last}" if last is not None else f"{first}+")
        rows.append([label, k + d, f"{100.0 * k / (k + d):.1f} %", worst])
    return rows


#: Task ids of a style-shape pair's posed frames: ``<train|test>_<train|test>-p<pair>[-c<chunk>]``
#: (the canonical split's tasks number their combinations apart and are left out).
_PAIR_TASK = re.compile(r"^(train|test)_(?:train|test)-p(\d+)(?:-c\d+)?$")


def _keep_by_pair(root: Path, shards: list[dict], sound: list[dict], worst: int = 5) -> list[str]:
    """Lines for ``info``: the kept share per style-shape pair (its shards' kept frames over kept
    plus dropped, from the manifest) and the ``worst`` pairs keeping least, each with its style
    index and body shape (read from one sound shard of the pair) and the reason
    most of its frames were dropped for. Empty for fewer than two pairs. Drops that cluster on a
    few pairs leave holes in the (style, shape) space a learner cannot fill."""
    pairs: dict[tuple[str, int], dict[str, Any]] = {}
    for entry in shards:
        match = _PAIR_TASK.match(entry["task_id"])
        if match is None:
            continue
        key = (match.group(1), int(match.group(2)))
        pair = pairs.setdefault(key, {"kept": 0, "dropped": {}, "shards": []})
        pair["kept"] += int(entry["frame_count"])
        for reason, count in entry["filter_stats"].items():
            pair["dropped"][reason] = pair["dropped"].get(reason, 0) + int(count)
        pair["shards"].append(entry)
    if len(pairs) < 2:
        return []
    readable = {entry["task_id"] for entry in sound}

    def targets(pair: dict) -> int:
        return pair["kept"] + sum(pair["dropped"].values())

    shares = {key: pair["kept"] / max(1, targets(pair)) for key, pair in pairs.items()}
    rows = []
    for key in sorted(pairs, key=lambda k: (shares[k], k))[:worst]:
        pair = pairs[key]
        style, shape = "-", "-"
        for entry in pair["shards"]:
            if entry["task_id"] in readable:
                try:
                    with h5py.File(root / entry["path"], "r") as handle:
                        style = json.loads(handle.attrs["task_json"]).get("style_index", "-")
                        shape = " ".join(f"{v:.2f}" for v in np.asarray(handle["shape"][()], np.float64).ravel())
                except (OSError, KeyError, TypeError, ValueError, IndexError):
                    continue
                break
        total = targets(pair)
        reason = "-"
        if pair["dropped"]:
            name, count = max(pair["dropped"].items(), key=lambda item: item[1])
            reason = f"{name} ({100.0 * count / max(1, total):.0f} %)"
        rows.append([f"{key[0]} p{key[1]:03d}", style, shape, total, f"{100.0 * shares[key]:.1f} %", reason])
    values = np.array(list(shares.values()))
    return ["", f"style-shape pairs: {len(pairs)}, kept share median {100.0 * np.median(values):.1f} % "
                f"(lowest {100.0 * values.min():.1f} %, highest {100.0 * values.max():.1f} %); "
                f"the {len(rows)} keeping least:",
            format_table(["pair", "style", "shape", "targets", "kept", "most dropped for"], rows)]


def _audit_lines(audit: dict) -> list[str]:
    """Human-readable lines for the manifest's ``audit`` block (written by generate-dataset)."""
    lines = []
    max_mm, mean_mm = audit.get("max_mm"), audit.get("mean_mm")
    if isinstance(max_mm, dict) and isinstance(mean_mm, dict):
        how = (f"re-solved to their static equilibrium ({audit.get('converged', '?')} converged)"
               if audit.get("reference") == "equilibrium" else f"re-solved at {audit.get('tolerance_mps', '?')} m/s")
        lines.append(f"audit: {audit.get('samples', '?')} kept frames {how}: "
                     f"vertex error max median {max_mm.get('median', float('nan')):.2f} / p90 {max_mm.get('p90', float('nan')):.2f} mm, "
                     f"mean median {mean_mm.get('median', float('nan')):.2f} / p90 {mean_mm.get('p90', float('nan')):.2f} mm")
    sim = audit.get("simulation")
    if isinstance(sim, dict):
        line = (f"simulation: {sim.get('target_frames', '?')} target frames in {sim.get('seconds', float('nan')):.1f} s "
                f"on {sim.get('device', '?')} ({sim.get('worlds', '?')} worlds)")
        phases = sim.get("phases")
        if isinstance(phases, dict):
            line += (f"; stepping {phases.get('sim_s', 0.0):.1f} s, bodies {phases.get('body_s', 0.0):.1f} s, recording "
                     f"{phases.get('record_s', 0.0):.1f} s, {int(phases.get('frames', 0))} simulator frames, "
                     f"{int(phases.get('recoveries', 0))} explosions recovered")
        lines.append(line)
    if not lines:
        lines.append(f"audit: {', '.join(sorted(audit)) or '(empty)'}")
    return lines
