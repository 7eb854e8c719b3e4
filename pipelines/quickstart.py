"""``drape quickstart``: the whole pipeline on the tiny shipped spec, end to end.

generate-dataset (quickstart.yaml) -> train tailornet (a few epochs) -> evaluate,
then print where the report is. CPU is fine (a few minutes on 2 cores); rerunning
resumes the dataset and the training stages.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path


def run(args: argparse.Namespace) -> int:
    from pipelines.evaluate import evaluate
    from pipelines.generate_dataset import generate
    from pipelines.train import train

    from pipelines.errors import check_number

    check_number(args.epochs, "--epochs", minimum=1, integer=True)  # before minutes of simulation
    out = Path(args.out)
    t0 = time.perf_counter()
    print(f"[1/3] generate-dataset {args.spec} -> {out / 'data'}")
    generate(args.spec, out / "data", device=args.device, progress=not args.no_progress)
    print(f"[2/3] train tailornet ({args.epochs} epochs per stage) -> {out / 'run'}")
    train("tailornet", out / "data", out / "run", device="cuda" if args.device and args.device.startswith("cuda") else "cpu",
          epochs=args.epochs, progress=not args.no_progress)
    print("[3/3] evaluate")
    evaluate(out / "run", out / "data", renders=2, postprocess_frames=4)
    print(f"quickstart done in {time.perf_counter() - t0:.0f} s: report {out / 'run' / 'evaluation' / 'evaluation.json'}, "
          f"plot {out / 'run' / 'evaluation' / 'error_vs_time.png'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quickstart", help="generate the tiny dataset, train briefly, evaluate (end to end)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/quickstart", help="output directory (data/, run/)")
    p.add_argument("--spec", default="quickstart", help="dataset spec (default: the shipped quickstart)")
    p.add_argument("--epochs", type=int, default=200, help="training epochs per stage (tiny data: seconds each)")
    p.add_argument("--device", default=None, help="simulation device override (auto, cpu, cuda:0)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)
