"""``drape report`` argument parsing, the production default read from the shipped spec, JSON cleaning."""
from __future__ import annotations

import argparse
import json

import pytest

from pipelines import report
from simulate.reports.accuracy import DEFAULT_SETTING, PRODUCTION_BASE


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="drape")
    report.register(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


def test_subcommands_parse_with_documented_defaults() -> None:
    a = _parse(["report", "accuracy", "--out", "x"])
    assert (a.garment, a.sweep, a.device, a.poses) == ("tshirt", "small", "auto", "arms-up,arms-forward,twist,lean")
    assert a.func is report.run_accuracy_command and a.explosion_stretch is None and a.solvers == "xpbd,vbd,mass_spring"
    bad = _parse(["report", "accuracy", "--out", "x", "--solvers", "mass_spring"])
    with pytest.raises(ValueError, match="--solvers 'mass_spring'.*production default's solver"):
        report.run_accuracy_command(bad)
    s = _parse(["report", "stability", "--out", "y", "--size", "full", "--strict"])
    assert (s.size, s.strict, s.garment) == ("full", True, None) and s.func is report.run_stability_command
    with pytest.raises(SystemExit):
        _parse(["report", "stability", "--out", "y", "--size", "huge"])


def test_production_default_matches_the_shipped_spec() -> None:
    assert report.production_default() == DEFAULT_SETTING, (
        f"tailornet-tshirt.yaml simulation block gives {report.production_default()}, the reports declare {DEFAULT_SETTING}")


def test_production_base_matches_the_shipped_spec() -> None:
    base = report.production_base()
    for field in report.BASE_FIELDS:
        assert getattr(base, field) == getattr(PRODUCTION_BASE, field), (
            f"tailornet-tshirt.yaml gives simulation {field} = {getattr(base, field)}, the accuracy report's "
            f"PRODUCTION_BASE has {getattr(PRODUCTION_BASE, field)}")
    # every sweep setting keeps the base's damping and explosion limits and sets its own swept fields
    s = DEFAULT_SETTING.sim_settings(max_frames=7, base=base)
    assert (s.damping, s.explosion_stretch, s.tolerance, s.max_frames) == (base.damping, base.explosion_stretch, 0.05, 7)


def test_pose_names_and_json_cleaning() -> None:
    assert report._poses("arms-up, twist") == ["arms-up", "twist"]
    with pytest.raises(ValueError, match="unknown pose 'moonwalk'"):
        report._poses("arms-up,moonwalk")
    text = json.dumps(report._clean({"a": [float("inf"), float("nan"), 1.5], "b": {"c": -float("inf")}}))
    assert json.loads(text) == {"a": ["inf", "nan", 1.5], "b": {"c": "-inf"}}
    back = report._unclean(json.loads(text))
    assert back["a"][0] == float("inf") and back["a"][1] != back["a"][1] and back["b"]["c"] == -float("inf")


def test_accuracy_resume_measures_only_what_a_cut_run_missed(tmp_path, capsys) -> None:
    """CLI round trip on the CI capsule: cut the rows file mid-line (a kill while writing), --resume measures
    only the missing rows, keeps the finished ones and does not solve the reference again; a resume
    with other settings is refused, naming the field."""
    argv = ["report", "accuracy", "--body", "capsule", "--resolution", "60", "--poses", "canonical", "--solvers", "xpbd",
            "--max-frames", "200", "--reference-max-frames", "300", "--device", "cpu", "--out", str(tmp_path),
            "--no-progress"]
    a = _parse(argv)
    assert a.resume is False
    assert report.run_accuracy_command(a) == 0
    full = json.loads((tmp_path / "accuracy.json").read_text())
    lines = (tmp_path / "accuracy_rows.jsonl").read_text().splitlines()
    assert json.loads(lines[0])["config"]["poses"] == ["canonical"] and len(lines) == 1 + len(full["rows"])
    keep = 5
    (tmp_path / "accuracy_rows.jsonl").write_text("\n".join(lines[:1 + keep]) + "\n" + lines[1 + keep][:40])
    capsys.readouterr()
    assert report.run_accuracy_command(_parse(argv + ["--resume"])) == 0
    err = capsys.readouterr().err
    assert f"reference and {keep} rows already measured" in err and "(reference)" not in err, err
    resumed = json.loads((tmp_path / "accuracy.json").read_text())
    assert resumed["resumed_rows"] == keep and resumed["reference"] == full["reference"]
    assert [r["label"] for r in resumed["rows"]] == [r["label"] for r in full["rows"]]
    kept = {json.loads(line)["label"] for line in lines[1:1 + keep]}
    for x, y in zip(full["rows"], resumed["rows"]):
        assert x["error_max_mm"] == y["error_max_mm"], x["label"]
        if x["label"] in kept:
            assert x["ms_per_frame"] == y["ms_per_frame"], f"{x['label']}: a finished row was measured again"
    other = _parse([*argv[:argv.index("--max-frames") + 1], "150", *argv[argv.index("--max-frames") + 2:], "--resume"])
    with pytest.raises(ValueError, match="max_frames = 200 there, 150 now"):
        report.run_accuracy_command(other)
