"""``drape dataset`` subcommands: validate, info, export.

``register(subparsers)`` adds the ``dataset`` subcommand to the ``drape`` parser; each leaf
sets ``func(args) -> int`` (the exit status). ``main(argv)`` runs them standalone:
``python -m data_manifest.cli dataset validate DIR``.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .export import EXPORT_FORMATS, export_task
from .schema import DatasetError
from .validate import info, validate_dataset


def _cmd_validate(args: argparse.Namespace) -> int:
    report = validate_dataset(args.dir, check_sha256=not args.no_checksum)
    print(report)
    return 0 if report.ok else 1


def _cmd_info(args: argparse.Namespace) -> int:
    try:
        print(info(args.dir), end="")
    except (FileNotFoundError, ValueError) as error:
        print(f"drape dataset info: {error}", file=sys.stderr)
        return 1
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    try:
        paths = export_task(args.dir, args.task, format=args.format, out=args.out, sample_rate=args.sample_rate)
    except (FileNotFoundError, ValueError, DatasetError) as error:
        print(f"drape dataset export: {error}", file=sys.stderr)
        return 1
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
    validate.add_argument("dir", help="dataset directory (holding manifest.json)")
    validate.add_argument("--no-checksum", action="store_true", help="skip the sha256 of each shard (faster)")
    validate.set_defaults(func=_cmd_validate)

    info_parser = commands.add_parser("info", help="print a summary table of a dataset",
                                      description="Print tasks and frames per split, frames kept and dropped "
                                                  "by reason, size, precision, provenance and timings.")
    info_parser.add_argument("dir", help="dataset directory (holding manifest.json)")
    info_parser.set_defaults(func=_cmd_info)

    export = commands.add_parser("export", help="export one task's sequence as OBJ, PLY or a PC2 point cache",
                                 description="Export the posed garment of every kept frame of one task: "
                                             "obj/ply write one file per frame into the --out directory, pc2 "
                                             "writes one Blender point-cache file.")
    export.add_argument("dir", help="dataset directory (holding manifest.json)")
    export.add_argument("--task", required=True, help="task id (see `drape dataset info`)")
    export.add_argument("--format", required=True, choices=EXPORT_FORMATS, help="output format")
    export.add_argument("--out", required=True, help="output directory (obj, ply) or file (pc2)")
    export.add_argument("--sample-rate", type=float, default=1.0, help="PC2 frames per sample (default 1)")
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
