"""``drape report``: fidelity (error against run time) and stability reports of the simulator.

``drape report accuracy`` sweeps solver settings on a garment on the default body and writes
``accuracy.json`` and ``accuracy_pareto.png``; ``drape report stability`` runs the stiff/extreme
case matrix and writes ``stability.json`` and ``stability_heatmap.png``. See
:mod:`simulate.reports.accuracy` and :mod:`simulate.reports.stability` for the protocols.
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
DEFAULT_CONFIG = "tailornet-tshirt.yaml"


def resolve_device(device: str) -> str:
    """"auto" -> "cuda:0" when Warp sees a GPU, else "cpu"; "cuda" -> "cuda:0"."""
    import warp as wp

    if device == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    if device.startswith("cuda") and wp.get_cuda_device_count() == 0:
        raise ValueError(f"--device is {device!r} but Warp finds no CUDA device; use auto or cpu")
    return "cuda:0" if device == "cuda" else device


def production_default(config: Path | None = None):
    """The production default Setting of a shipped spec (tailornet-tshirt) with its defaults filled in."""
    from pipelines.spec import load_spec
    from simulate.reports.accuracy import Setting

    sim = load_spec(config or CONFIG_DIR / DEFAULT_CONFIG)["simulation"]
    return Setting(solver=sim["solver"], mode="gauss_seidel", substeps=int(sim["substeps"]),
                   iterations=int(sim["iterations"]), tolerance=float(sim["tolerance"]), precision="float32")


BASE_FIELDS = ("frame_dt", "damping", "patience", "outlier_fraction", "explosion_speed", "explosion_stretch")
"""SimSettings fields the accuracy sweep takes from the spec rather than varying."""


def production_base(config: Path | None = None):
    """SimSettings of a shipped spec (tailornet-tshirt) with its defaults filled in: the base of every
    accuracy setting (only :data:`BASE_FIELDS` matter; the sweep sets the rest)."""
    from pipelines.generate_dataset import sequence_settings
    from pipelines.spec import load_spec
    from simulate.quasi_static import SimSettings

    sim = sequence_settings(load_spec(config or CONFIG_DIR / DEFAULT_CONFIG)).sim
    return SimSettings(**{f: getattr(sim, f) for f in BASE_FIELDS})


def _json_default(value: Any) -> Any:
    if hasattr(value, "item"):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def _clean(value: Any) -> Any:
    """inf/NaN -> strings so the JSON stays standard."""
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def _unclean(value: Any) -> Any:
    """Inverse of :func:`_clean`: the strings "nan", "inf", "-inf" back to floats."""
    if isinstance(value, str) and value in ("nan", "inf", "-inf"):
        return float(value)
    if isinstance(value, dict):
        return {k: _unclean(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_unclean(v) for v in value]
    return value


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_clean(data), indent=2, default=_json_default))
    tmp.replace(path)


def _poses(text: str) -> list[str]:
    from simulate.reports.scenes import ACCURACY_POSES, EXTREME_POSES

    names = [p.strip() for p in text.split(",") if p.strip()]
    known = {**ACCURACY_POSES, **EXTREME_POSES}
    for name in names:
        if name not in known:
            raise ValueError(f"--poses: unknown pose {name!r}; expected names from {', '.join(known)}")
    if not names:
        raise ValueError("--poses must name at least one pose")
    return names


def _jsonable(x: Any) -> Any:
    """``x`` as it reads back from JSON (tuples as lists), for comparing saved and current configs."""
    return json.loads(json.dumps(x, default=_json_default))


def _load_resume(rows_path: Path, ref_path: Path, config: dict) -> Any:
    """The :class:`~simulate.reports.accuracy.Resume` of an earlier run in the same folder, or None when it
    saved no reference yet; raises when that run measured something else."""
    from simulate.reports.accuracy import Resume

    if not ref_path.exists():
        print(f"  --resume: no saved reference in {ref_path.parent}; starting from scratch", file=sys.stderr)
        return None
    try:
        with np.load(ref_path) as z:
            saved = json.loads(str(z["config"]))
            positions, status, summary = z["positions"], z["status"], json.loads(str(z["summary"]))
    except Exception as exc:
        raise ValueError(f"--resume: {ref_path} is not a readable reference ({type(exc).__name__}: {exc}); delete it "
                         f"or run without --resume") from exc
    diff = [f"{k} = {saved.get(k)!r} there, {v!r} now" for k, v in config.items() if saved.get(k) != v]
    if diff:
        raise ValueError(f"--resume: {ref_path.parent} was measured with other settings ({'; '.join(diff)}); use another "
                         f"--out or run without --resume")
    rows: dict[str, dict] = {}
    if rows_path.exists():
        for line in rows_path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:  # a line cut by a kill mid-write: that row is measured again
                continue
            if isinstance(row, dict) and "label" in row:
                rows[row["label"]] = _unclean(row)
    return Resume(reference=summary, reference_positions=positions, reference_status=status, rows=rows)


def run_accuracy_command(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from simulate.quasi_static import WorldStatus
    from simulate.reports.accuracy import REFERENCE_FRICTION, REFERENCE_SETTINGS, SOLVERS, format_table, run_accuracy, sweep_settings
    from simulate.reports.pareto import plot_error_vs_time
    from simulate.reports.scenes import build_scene

    default = production_default()
    solvers = [x.strip() for x in args.solvers.split(",") if x.strip()]
    bad = [x for x in solvers if x not in SOLVERS] or ([] if default.solver in solvers else [default.solver])
    if bad or not solvers:
        raise ValueError(f"--solvers {args.solvers!r}: expected a comma list of {', '.join(SOLVERS)} including the "
                         f"production default's solver ({default.solver})")
    from pipelines.errors import check_output_dir

    device = resolve_device(args.device)
    out = check_output_dir(args.out, "--out")
    poses = _poses(args.poses)
    t0 = time.perf_counter()
    scene = build_scene(args.garment, body=args.body, resolution=args.resolution, device=device)
    settings = [s for s in sweep_settings(args.sweep, default=default) if s.solver in solvers]
    reference = REFERENCE_SETTINGS[args.sweep]
    reference_max_frames = args.reference_max_frames or 4 * args.max_frames
    sims = len({s.simulation_key() for s in settings}) + 3  # + canonical drape + reference start + equilibrium
    bar = tqdm(total=sims, desc="accuracy: settings", unit="setting", file=sys.stderr, disable=args.no_progress)

    def progress(label: str, run: Any) -> None:
        # One log line per simulation, so a long sweep shows where its time goes even without a bar.
        status = collections.Counter(WorldStatus(int(s)).name.lower() for s in run.status)
        unit = "Newton iterations" if label.startswith("equilibrium") else "frames"  # the reference solve
        tqdm.write(f"  {label}: {run.wall_s:.1f} s, {unit} mean {float(run.frames.mean()):.0f} max "
                   f"{int(run.frames.max())}, {', '.join(f'{k} {v}' for k, v in sorted(status.items()))}",
                   file=sys.stderr)
        bar.set_postfix_str(label[:40])
        bar.update(1)

    rows_path = out / "accuracy_rows.jsonl"
    ref_path = out / "accuracy_reference.npz"
    config = _jsonable({"scene": scene.name, "vertices": scene.vertex_count, "poses": poses, "fabric": args.fabric,
                        "sweep": args.sweep, "reference": reference.label, "reference_kind": "equilibrium",
                        "reference_friction": REFERENCE_FRICTION, "base": dataclasses.asdict(production_base()),
                        "max_frames": args.max_frames, "reference_max_frames": reference_max_frames,
                        "reference_max_iterations": args.reference_max_iterations,
                        "explosion_stretch": args.explosion_stretch, "device": str(device)})
    resume = _load_resume(rows_path, ref_path, config) if args.resume else None
    if resume is None:
        rows_path.unlink(missing_ok=True)
        ref_path.unlink(missing_ok=True)
        with open(rows_path, "w") as f:
            f.write(json.dumps({"config": config}) + "\n")
    else:
        tqdm.write(f"  resuming {out}: reference and {len(resume.rows)} rows already measured", file=sys.stderr)

    def row_done(row: dict) -> None:
        if "reference" in row:  # saved with its positions by reference_done
            return
        with open(rows_path, "a") as f:
            f.write(json.dumps(_clean(row), default=_json_default) + "\n")

    def reference_done(summary: dict, positions: np.ndarray, status: np.ndarray) -> None:
        tmp = ref_path.with_name(ref_path.name + ".partial")
        with open(tmp, "wb") as f:
            np.savez(f, positions=np.asarray(positions, np.float64), status=np.asarray(status, np.int32),
                     summary=json.dumps(_clean(summary), default=_json_default), config=json.dumps(config))
        os.replace(tmp, ref_path)

    report = run_accuracy(scene, poses=poses, settings=settings, reference=reference, default=default, device=device,
                          base=production_base(), fabric=args.fabric, max_frames=args.max_frames,
                          reference_max_frames=reference_max_frames, reference_max_iterations=args.reference_max_iterations,
                          explosion_stretch=args.explosion_stretch,
                          on_progress=progress, on_row=row_done, on_reference=reference_done, resume=resume)
    bar.close()
    report["sweep"] = args.sweep
    report["wall_s"] = time.perf_counter() - t0
    title = f"{scene.name} ({scene.vertex_count} vertices), {', '.join(poses)} on {device}"
    png = plot_error_vs_time(report["rows"], out / "accuracy_pareto.png", highlight=report["default"],
                             title=f"{title}: max vertex error vs time")
    png_mean = plot_error_vs_time(report["rows"], out / "accuracy_pareto_mean.png", highlight=report["default"],
                                  title=f"{title}: mean vertex error vs time", error_key="error_mean_mm",
                                  ylabel="mean vertex error against the reference [mm]")
    report["plot"], report["plot_mean"] = str(png), str(png_mean)
    _write_json(out / "accuracy.json", report)
    print(format_table(report))
    print(f"\nsummary: {len(report['rows'])} settings on {scene.name} ({scene.vertex_count} vertices), "
          f"{len(poses)} poses, {device}; front: {len(report['front'])} settings (max error), "
          f"{len(report['front_mean'])} (mean error)")
    for name, suffix in (("max", ""), ("mean", "_mean")):
        where = ("on" if report[f"default_on_front{suffix}"] else "near" if report[f"default_near_front{suffix}"]
                 else "NOT near")
        print(f"  production default {report['default']} is {where} the {name}-error Pareto front (its time / time "
              f"of the fastest front setting within {100 * report['near_front_error_slack']:g} % of its {name} error = "
              f"{report[f'default_time_ratio{suffix}']:.2f}; near means <= {report['near_front_time_factor']})")
    print(f"  wrote {out / 'accuracy.json'}, {png} and {png_mean} in {report['wall_s']:.1f} s")
    return 0


def run_stability_command(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from simulate.reports.scenes import build_scene
    from simulate.reports.stability import (DEFAULT_SCENE, failing_supported, format_table, plot_heatmap,
                                            run_stability, stability_cases, unexpected_passes)

    from pipelines.errors import check_output_dir

    device = resolve_device(args.device)
    out = check_output_dir(args.out, "--out")
    garment = args.garment or DEFAULT_SCENE.split("@")[0]
    scene = build_scene(garment, body="anny", resolution=args.resolution, device=device)
    cases = stability_cases(scene, args.size)
    bar = tqdm(total=len(cases), desc="stability: cells", unit="cell", file=sys.stderr, disable=args.no_progress)
    report = run_stability(scene, cases, device=device, explosion_stretch=args.explosion_stretch, on_progress=bar.update)
    bar.close()
    report["size"] = args.size
    png = plot_heatmap(report, out / "stability_heatmap.png")
    report["plot"] = str(png)
    bad = failing_supported(report)
    stale = unexpected_passes(report)
    report["failing_supported"] = [c["cell"] for c in bad]
    report["unexpected_passes"] = [c["cell"] for c in stale]
    _write_json(out / "stability.json", report)
    print(format_table(report))
    cells = report["cells"]
    sup = [c for c in cells if c["supported"]]
    print(f"\nsummary: {len(cells)} cells on {scene.name} ({scene.vertex_count} vertices), {device}, "
          f"{report['wall_s']:.1f} s; canonical drape {report['canonical_drape']['status']}")
    print(f"  passed {sum(c['passed'] for c in cells)}/{len(cells)}; supported cells passed "
          f"{sum(c['passed'] for c in sup)}/{len(sup)}")
    for c in bad:
        print(f"  SUPPORTED CELL FAILED: {c['cell']}: {'; '.join(c['reasons'])}")
    for c in stale:
        print(f"  unsupported cell passed this time: {c['cell']} ({c['note']})")
    print(f"  wrote {out / 'stability.json'} and {png}")
    if bad or (args.strict and any(not c["passed"] for c in cells)):
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="fidelity (error vs run time) and stability reports of the simulator",
                       description="Simulator reports: 'accuracy' sweeps solver settings against a tight reference "
                       "(table, JSON, Pareto PNG); 'stability' runs the stiff/extreme case matrix (table, JSON, "
                       "heat-map PNG) and fails when a supported cell fails.")
    rs = p.add_subparsers(dest="report", metavar="REPORT")
    a = rs.add_parser("accuracy", help="error against run time over solver settings",
                      description="Drapes a garment on the default body, moves it to each pose and relaxes it with "
                      "every setting of the sweep (solver: xpbd, vbd, mass_spring; substeps, iterations, tolerance, "
                      "float precision); measures wall time per converged frame and the error against the reference: "
                      "each pose's static equilibrium of the model's energy (float64 Newton on the CPU) started from "
                      "a tight XPBD run, with the contacts of that run held (stick).")
    a.add_argument("--garment", default="tshirt",
                   help="tshirt, shirt, pants, shorts, skirt or shawl (default tshirt)")
    a.add_argument("--body", default="anny", choices=["anny", "capsule"], help="body (capsule: tiny CI stand-in)")
    a.add_argument("--resolution", type=int, default=None, help="target cloth vertex count")
    a.add_argument("--poses", default="arms-up,arms-forward,twist,lean",
                   help="comma-separated pose names (canonical, arms-up, arms-forward, twist, lean, tilt, or an "
                   "extreme pose of the stability report)")
    a.add_argument("--fabric", default="cotton", help="fabric preset (default cotton)")
    a.add_argument("--sweep", default="small", choices=["small", "full"], help="settings grid (default small)")
    a.add_argument("--solvers", default="xpbd,vbd,mass_spring",
                   help="solvers swept (comma list of xpbd, vbd, mass_spring; mass-spring's explicit substeps are the "
                        "slowest rows: ~87 s per setting on an H200, far more on CPU)")
    a.add_argument("--max-frames", type=int, default=600, help="relaxation frame budget per setting")
    a.add_argument("--reference-max-frames", type=int, default=None,
                   help="frame budget of the tight XPBD run that starts the reference equilibrium (default 4x "
                        "--max-frames; at 40x100 iterations a GPU frame of 4 worlds takes ~0.6 s, so bound it on slow "
                        "devices)")
    a.add_argument("--reference-max-iterations", type=int, default=200,
                   help="Newton iterations per pose at most for the reference equilibrium (CPU, float64; default 200)")
    a.add_argument("--explosion-stretch", type=float, default=None,
                   help="triangle stretch ratio that flags a world EXPLODED (default: the production spec's, 50, as "
                   "the dataset pipeline uses it)")
    a.add_argument("--device", default="auto", help="auto, cpu or cuda:N")
    a.add_argument("--out", required=True, help="output folder (accuracy.json, accuracy_pareto.png)")
    a.add_argument("--no-progress", action="store_true", help="no progress bar")
    a.add_argument("--resume", action="store_true",
                   help="reuse the reference and the rows an earlier run of the same command saved in --out "
                        "(accuracy_reference.npz, accuracy_rows.jsonl) and measure only what is missing")
    a.set_defaults(func=run_accuracy_command)
    s = rs.add_parser("stability", help="stiff and extreme case matrix",
                      description="Runs stretch/bending stiffness decades, large time steps, light-to-heavy fabrics, "
                      "extreme poses and shapes and fast transitions; exits 1 if a cell declared supported "
                      "(simulate.reports.stability.SUPPORTED, README 'Reports') fails; --strict: if any cell fails.")
    s.add_argument("--size", default="small", choices=["small", "full"], help="matrix size (default small)")
    s.add_argument("--garment", default=None, help="cloth on the default body (default: the shawl; see README)")
    s.add_argument("--resolution", type=int, default=None, help="target cloth vertex count")
    s.add_argument("--explosion-stretch", type=float, default=None,
                   help="triangle stretch ratio that flags a world EXPLODED (default: the simulator's, as the dataset "
                   "pipeline uses it; the garment layer's canonical drape uses 10)")
    s.add_argument("--device", default="auto", help="auto, cpu or cuda:N")
    s.add_argument("--out", required=True, help="output folder (stability.json, stability_heatmap.png)")
    s.add_argument("--strict", action="store_true", help="exit 1 when any cell fails, supported or not")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=run_stability_command)
    from pipelines.floor import register_report as register_floor

    register_floor(rs)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
