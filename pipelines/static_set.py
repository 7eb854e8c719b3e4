"""``drape static-set --out DIR``: GCVAE's static set. For every garment type, COUNT rest-pose
garments of sampled styles on sampled anny bodies (no simulation: the garment fitted to the
body's shape in the canonical pose), registered on the common body mesh as per-vertex offsets
and a mask, in ``DIR/static_set.npz``; prints the registration error per type.
"""
from __future__ import annotations

import argparse


from pipelines.errors import UsageError, check_number, check_output_dir


def run(args: argparse.Namespace) -> int:
    from learn.gcvae.static_set import StaticSet, build_static_set

    types = tuple(t.strip() for t in args.types.split(",") if t.strip())
    check_number(args.seed, "--seed", minimum=0, integer=True)
    # before --out is created: a refused size leaves no empty directory behind
    check_number(args.count, "--count", minimum=2, integer=True)
    if not (isinstance(args.test_fraction, float) and 0.0 < args.test_fraction < 1.0):
        raise UsageError(f"--test-fraction must be in (0, 1), got {args.test_fraction!r}")
    if args.subdivisions is not None:
        check_number(args.subdivisions, "--subdivisions", minimum=0, maximum=2, integer=True)
    rep = {} if args.subdivisions is None else {"subdivisions": args.subdivisions}
    out = check_output_dir(args.out, "--out")
    path = build_static_set(out, types=types, count=args.count, test_fraction=args.test_fraction, seed=args.seed,
                            representation=rep)
    data = StaticSet(path)
    print(f"{'type':<10}{'samples':>8}{'garment->registered mm':>24}{'registered->garment mm':>24}")
    for name, r in data.registration_table().items():
        print(f"{name:<10}{r['samples']:>8}{r['garment_to_registered_mm']:>24.2f}{r['registered_to_garment_mm']:>24.4f}")
    print(f"wrote {path} ({len(data)} samples, body mesh of {data.mesh.vertex_count} vertices, "
          f"{data.mesh.segment_count} segments)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    from simulate.garment.style import TAILORNET_TYPES

    p = sub.add_parser("static-set", help="rest-pose garments on sampled bodies, registered to the body mesh "
                       "(gcvae's data)", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--types", default=",".join(TAILORNET_TYPES), help="comma-separated garment types")
    p.add_argument("--count", type=int, default=160,
                   help="samples per type (160: the size measured to reach mask IoU 0.95 over types, "
                   "docs/learners/gcvae.md)")
    p.add_argument("--test-fraction", type=float, default=0.2, help="share of each type's samples in the test split")
    p.add_argument("--subdivisions", type=int, default=None,
                   help="midpoint subdivisions of the body mesh (default: learn/gcvae/hyperparameters.py)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)
