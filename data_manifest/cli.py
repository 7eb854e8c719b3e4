"""``drape dataset`` subcommands: validate, info, export.

``register(subparsers)`` adds the ``dataset`` subcommand to the ``drape`` parser; each leaf
sets ``func(args) -> int`` (the exit status). ``main(argv)`` runs them standalone:
``python -m data_manifest.cli dataset validate DIR``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from .export import EXPORT_FORMATS, export_task
from .integrity import write_error
from .schema import DatasetError
from .validate import info, validate_dataset


#: Exit statuses: 0 sound, 1 the dataset has problems (validate, info), 2 bad input (a missing
#: directory, an unknown task, an output that cannot be written).
EXIT_PROBLEMS, EXIT_USAGE = 1, 2


def _fail(command: str, error: BaseException | str) -> int:
    text = "; ".join(line.strip() for line in str(error).splitlines() if line.strip())
    print(f"drape dataset {command}: error: {text}", file=sys.stderr)
    return EXIT_USAGE


def type_datasets(directory: str | Path) -> list[tuple[str, Path]] | None:
    """The per-type datasets of a multi-type run (``DIR/datasets.json`` beside no manifest.json:
    ``drape generate-dataset`` with a list of garment types), as (type, directory); None for any
    other directory. Raises ValueError naming the file when the index is unreadable."""
    import json

    root = Path(directory)
    index = root / "datasets.json"
    if (root / "manifest.json").exists() or not index.is_file():
        return None
    try:
        entries = json.loads(index.read_text(encoding="utf-8"))["datasets"]
        return [(str(e["type"]), root / str(e["path"])) for e in entries]
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{str(index)!r} is not a datasets index ({error})") from None


def _cmd_validate(args: argparse.Namespace) -> int:
    if not Path(args.dir).is_dir():
        return _fail("validate", f"dataset directory {args.dir!r} does not exist")
    try:
        parts = type_datasets(args.dir)
    except ValueError as error:
        return _fail("validate", error)
    if parts is not None:  # a multi-type run: every listed dataset in turn
        status = 0
        for gtype, path in parts:
            print(f"== {gtype}: {path}")
            if not (path / "manifest.json").is_file():
                print("  not generated yet (no manifest.json; rerun generate-dataset to finish it)")
                status = EXIT_PROBLEMS
                continue
            report = validate_dataset(path, check_sha256=not args.no_checksum)
            print(report)
            status = status if report.ok else EXIT_PROBLEMS
        return status
    report = validate_dataset(args.dir, check_sha256=not args.no_checksum)
    print(report)
    return 0 if report.ok else EXIT_PROBLEMS


def _cmd_info(args: argparse.Namespace) -> int:
    try:
        parts = type_datasets(args.dir)
        if parts is not None:  # a multi-type run: every listed dataset in turn
            status = 0
            for gtype, path in parts:
                print(f"== {gtype}: {path}")
                if not (path / "manifest.json").is_file():
                    print("  not generated yet (no manifest.json)")
                    status = EXIT_PROBLEMS
                    continue
                text, problems = info(path, with_problems=True)
                print(text, end="")
                status = EXIT_PROBLEMS if problems else status
            return status
        text, problems = info(args.dir, with_problems=True)
    except (FileNotFoundError, ValueError, DatasetError) as error:
        return _fail("info", error)
    print(text, end="")
    return EXIT_PROBLEMS if problems else 0


def _check_export_out(out: Path, format: str) -> str | None:
    """Why ``--out`` cannot take the export (None when it can)."""
    one_file = format in ("pc2", "pc16")
    target = out.parent if one_file else out
    if one_file and out.is_dir():
        return f"--out {str(out)!r} is a directory; {format} writes one file (e.g. {str(out / ('task.' + format))!r})"
    if not one_file and out.exists() and not out.is_dir():
        return f"--out {str(out)!r} is a file; {format} writes one file per frame into a directory"
    probe_dir = target
    while not probe_dir.exists() and probe_dir != probe_dir.parent:
        probe_dir = probe_dir.parent
    if not probe_dir.is_dir():
        return f"--out {str(out)!r}: {str(probe_dir)!r} is a file, not a directory"
    error = write_error(probe_dir)
    if error is not None:
        return f"--out {str(out)!r}: {str(probe_dir)!r} is not writable ({error.strerror or error})"
    return None


def _cmd_export(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.sample_rate) and args.sample_rate > 0):
        return _fail("export", f"--sample-rate must be a finite number > 0 (got {args.sample_rate!r})")
    problem = _check_export_out(Path(args.out), args.format)
    if problem:
        return _fail("export", problem)
    try:
        paths = export_task(args.dir, args.task, format=args.format, out=args.out, sample_rate=args.sample_rate)
    except (FileNotFoundError, ValueError, DatasetError) as error:
        return _fail("export", error)
    except OSError as error:
        return _fail("export", f"cannot write {error.filename or args.out}: {error.strerror or error}")
    where = paths[0] if len(paths) == 1 else paths[0].parent if paths else args.out
    print(f"wrote {len(paths)} {args.format} file(s) for task {args.task!r} to {where}")
    return 0


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``dataset {validate,info,export}`` to an argparse subparsers object; returns the
    ``dataset`` parser. Leaves set ``func``; calling ``dataset`` alone prints its help."""
    dataset = subparsers.add_parser("dataset", help="inspect, validate and export generated datasets",
                                    description="Inspect, validate and export drape datasets (shards + manifest).")
    commands = dataset.add_subparsers(dest="dataset_command", metavar="{validate,info,export}")

    def show_help(args: argparse.Namespace) -> int:
        dataset.print_help()
        return 2

    dataset.set_defaults(func=show_help)

    validate = commands.add_parser(
        "validate", help="check manifest schema, checksums and shard layout; exit 1 if anything is wrong",
        description="Check the manifest schema, that every listed shard exists with the listed sha256 and "
                    "size, that its HDF5 layout, template and frame count match, and that splits and totals "
                    "are consistent. Lists orphan .tmp and unlisted shards as warnings. Exits 1 when any "
                    "shard is corrupt or missing.")
    validate.add_argument("dir", help="dataset directory (holding manifest.json), or a multi-type run's (datasets.json)")
    validate.add_argument("--no-checksum", action="store_true", help="skip the sha256 of each shard (faster)")
    validate.set_defaults(func=_cmd_validate)

    info_parser = commands.add_parser("info", help="print a summary table of a dataset",
                                      description="Print tasks and frames per split, frames kept and dropped "
                                                  "by reason, size, precision, provenance and timings.")
    info_parser.add_argument("dir", help="dataset directory (holding manifest.json), or a multi-type run's (datasets.json)")
    info_parser.set_defaults(func=_cmd_info)

    export = commands.add_parser("export", help="export one task's sequence as OBJ, PLY or a PC2 / PC16 point cache",
                                 description="Export the posed garment of every kept frame of one task: "
                                             "obj/ply write one file per frame into the --out directory, pc2 "
                                             "writes one Blender point-cache file, pc16 CLOTH3D's float16 point "
                                             "cache relative to the root joint with NAME.faces.npy (uint16) and "
                                             "NAME.root.npy beside it (docs/motion.md).")
    export.add_argument("dir", help="dataset directory (holding manifest.json)")
    export.add_argument("--task", required=True, help="task id (see `drape dataset info`)")
    export.add_argument("--format", required=True, choices=EXPORT_FORMATS, help="output format")
    export.add_argument("--out", required=True, help="output directory (obj, ply) or file (pc2, pc16)")
    export.add_argument("--sample-rate", type=float, default=1.0, help="PC2 / PC16 frames per sample (default 1)")
    export.set_defaults(func=_cmd_export)
    return dataset


def main(argv: list[str] | None = None) -> int:
    """Standalone entry point with only the ``dataset`` subcommand."""
    parser = argparse.ArgumentParser(prog="drape")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
