"""``drape sample RUN --out DIR``: new garments drawn from a trained GCVAE's latent space
(z ~ N(0, I), seeded) for one body shape and tightness, written as ``garment_<k>.obj`` with the
body as ``body.obj``."""
from __future__ import annotations

import argparse
from pathlib import Path

from pipelines.errors import UsageError, check_number, check_output_dir, check_torch_device


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from learn.gcvae.sample import sample_garments
    from learn.registry import get_learner

    entry = get_learner("gcvae")
    run_dir = Path(args.run)
    if not run_dir.is_dir():
        raise UsageError(f"RUN {str(run_dir)!r} is not a directory (a run directory from drape train gcvae)")
    path = run_dir / entry.model_file
    if not path.is_file():
        raise UsageError(f"RUN {str(run_dir)!r} has no {entry.model_file} (train one with drape train gcvae)")
    check_number(args.seed, "--seed", minimum=0, integer=True)
    check_torch_device(args.device)
    shape = None
    if args.shape is not None:
        try:
            shape = np.array([float(x) for x in args.shape.replace(",", " ").split()], np.float32)
        except ValueError:
            raise UsageError(f"--shape must be numbers separated by commas, got {args.shape!r}") from None
    out = check_output_dir(args.out, "--out")
    model = entry.load(path, device=args.device)
    if getattr(model, "dynamic", None):
        raise UsageError(f"RUN {str(run_dir)!r} holds a dynamic gcvae (trained on motion frames, conditioned on "
                         f"poses); drape sample draws static garments: give a run trained on a drape static-set "
                         f"directory")
    paths = sample_garments(model, out, count=args.count, shape=shape, tightness=args.tightness, seed=args.seed)
    print(f"wrote {len(paths) - 1} garments and the body to {args.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sample", help="draw new garments from a trained gcvae's latent space and write meshes",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="run directory from drape train gcvae")
    p.add_argument("--out", required=True, help="directory for the OBJ files")
    p.add_argument("--count", type=int, default=4, help="garments to draw")
    p.add_argument("--shape", default=None, help="anny shape: 6 values in [0, 1] (gender, age, muscle, weight, "
                   "height, proportions); default all 0.5")
    p.add_argument("--tightness", type=float, default=None, help="looseness [m] (default: the training mean)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.set_defaults(func=run)
