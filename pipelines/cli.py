"""The ``drape`` command line: one entry point, one module per subcommand.

Each module in :data:`SUBCOMMAND_MODULES` exposes ``register(subparsers)``, which adds
its parser and sets ``func(args) -> int``. Modules are imported lazily (only when a
command runs) so ``drape --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback

#: (command name, module, one-line help). Modules register their own arguments.
SUBCOMMAND_MODULES: list[tuple[str, str, str]] = [
    ("quickstart", "pipelines.quickstart", "generate the tiny dataset, train briefly, evaluate (end to end)"),
    ("info", "pipelines.info", "versions, devices and kernel cache location"),
    ("body", "pipelines.body", "pose and shape a body, write OBJ/PLY and a PNG preview"),
    ("generate-dataset", "pipelines.generate_dataset", "simulate a dataset spec into sharded HDF5 + manifest"),
    ("dataset", "data_manifest.cli", "validate, summarize and export generated datasets"),
    ("train", "pipelines.train", "train a learner (tailornet, baseline, gcvae) on a dataset"),
    ("evaluate", "pipelines.evaluate", "errors, collisions and timings of a trained run on a dataset's test splits"),
    ("static-set", "pipelines.static_set", "rest-pose garments on sampled bodies, registered to the body mesh (gcvae's data)"),
    ("sample", "pipelines.sample", "draw new garments from a trained gcvae's latent space and write meshes"),
    ("predict", "pipelines.predict", "predict one garment with a trained model and write OBJ/PLY"),
    ("garment", "pipelines.garment", "generate a garment style, drape it on a body, write OBJ/PLY + PNG"),
    ("style-space", "pipelines.garment", "build a garment style PCA space and choose prototypes"),
    ("report", "pipelines.report", "accuracy (error vs run time) and stability reports of the simulator"),
]


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="drape",
        description="Garment drape datasets with a Warp cloth simulator, and the learners trained on them.",
    )
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error (also accepted after the command, or DRAPE_DEBUG=1)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    registered: set[str] = set()
    for name, module, help_text in SUBCOMMAND_MODULES:
        if only is None or only == name:
            if module not in registered:
                importlib.import_module(module).register(sub)
                registered.add(module)
    for name, module, help_text in SUBCOMMAND_MODULES:
        if name not in sub.choices:
            sub.add_parser(name, help=help_text)
    return parser


#: Commands that pick up where an interrupted run stopped when run again.
RESUMABLE = ("generate-dataset", "train", "quickstart")


def main(argv: list[str] | None = None) -> int:
    """Runs one command; returns its exit status (see :mod:`pipelines.errors`): errors are one
    line on stderr, the traceback only with ``--debug`` (anywhere on the line) or DRAPE_DEBUG=1."""
    from pipelines.errors import (EXIT_SIGINT, EXIT_SIGTERM, Terminated, describe, hdf5_files_left_open, is_disk_full,
                                  install_signal_handlers, raise_if_interrupted, restore_signals)

    program = argv is None  # the process is drape itself (console script, python -m)
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("DRAPE_DEBUG", "") not in ("", "0")
    argv = [a for a in argv if a != "--debug"]
    known = {name for name, _, _ in SUBCOMMAND_MODULES}
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in known else None)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if not argv or command is None else 2
    previous = install_signal_handlers()
    try:
        status = int(args.func(args) or 0)
        raise_if_interrupted()  # a signal whose exception a finalizer swallowed still ends the run as one
        return status
    except KeyboardInterrupt as exc:
        if debug:
            traceback.print_exc()
        hint = "; rerun the same command to resume" if args.command in RESUMABLE else ""
        print(f"drape {args.command}: interrupted{hint}", file=sys.stderr)
        return EXIT_SIGTERM if isinstance(exc, Terminated) else EXIT_SIGINT
    except Exception as exc:  # every error ends as one line; --debug shows where it came from
        if debug:
            traceback.print_exc()
        code, message = describe(exc)
        print(f"drape {args.command}: error: {message}", file=sys.stderr)
        if program and is_disk_full(exc) and hdf5_files_left_open():
            # a write that failed inside HDF5 (a full disk) leaves files the library cannot close;
            # its exit handler would crash on them (SIGSEGV): end here, the cleanup is done
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
        return code
    finally:
        restore_signals(previous)


if __name__ == "__main__":
    sys.exit(main())
