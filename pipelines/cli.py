"""The ``drape`` command line: one entry point, one module per subcommand.

Each module in :data:`SUBCOMMAND_MODULES` exposes ``register(subparsers)``, which adds
its parser and sets ``func(args) -> int``. Modules are imported lazily (only when a
command runs) so ``drape --help`` stays fast.
"""
from __future__ import annotations

import argparse
import importlib
import sys

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


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    known = {name for name, _, _ in SUBCOMMAND_MODULES}
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in known else None)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if not argv or command is None else 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"drape {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
