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
    assert a.func is report.run_accuracy_command and a.explosion_stretch is None and a.solvers == "xpbd,mass_spring"
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
