"""Dataset specs: every problem at every nesting level names its field path, the value and what
was expected; the command line says it in one line with exit 2. Healthy specs resolve as before."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipelines.spec import SpecError, load_spec, spec_hash, validate_spec


def check(patch: dict) -> str:
    raw = {"name": "t", "garment": {"type": "tshirt"}}
    for key, value in patch.items():
        raw[key] = {**raw[key], **value} if isinstance(value, dict) and isinstance(raw.get(key), dict) else value
    with pytest.raises(SpecError) as exc:
        validate_spec(raw, source="t.yaml")
    return str(exc.value)


@pytest.mark.parametrize("patch, expected", [
    ({"simulaton": {}}, "spec.simulaton is not a known field (did you mean simulation?)"),
    ({"simulation": {"substep": 3}}, "spec.simulation.substep is not a known field (did you mean substeps?)"),
    ({"filters": {"max_self_intersection": 3}},
     "spec.filters.max_self_intersection is not a known field (did you mean max_self_intersections?)"),
    ({"simulation": {"contact": {"self_contct": True}}},
     "spec.simulation.contact.self_contct is not a known field (did you mean self_contact?)"),
    ({"garment": {"resolutoin": 800}}, "spec.garment.resolutoin is not a known field (did you mean resolution?)"),
    ({"poses": {"trian_count": 3}}, "spec.poses.trian_count is not a known field (did you mean train_count?)"),
    ({"audit": {"sample": 3}}, "spec.audit.sample is not a known field (did you mean samples?)"),
    ({"output": {"zzz": 1}}, "spec.output.zzz is not a known field; known fields of spec.output: compression, precision"),
])
def test_unknown_keys_at_every_level_name_the_path_and_the_nearest_name(patch, expected):
    assert expected in check(patch)


@pytest.mark.parametrize("patch, expected", [
    ({"simulation": 3}, "spec.simulation must be a mapping of fields such as batches, contact, device (got 3)"),
    ({"simulation": {"contact": [1]}}, "spec.simulation.contact must be a mapping of fields such as"),
    ({"filters": "strict"}, "spec.filters must be a mapping of fields such as collision_depth"),
    ({"garment": "tshirt"}, "spec.garment must be a mapping of fields such as fabric, resolution, type (got 'tshirt')"),
    ({"simulation": {"tolerance": float("inf")}}, "spec.simulation.tolerance must be a number > 0.0 (got inf)"),
    ({"simulation": {"frame_dt": float("nan")}}, "spec.simulation.frame_dt must be a number > 0.0 and <= 1.0 (got nan)"),
    ({"simulation": {"worlds": float("inf")}}, "spec.simulation.worlds must be an integer >= 1 (got inf)"),
    ({"simulation": {"batches": 0}}, "spec.simulation.batches must be an integer >= 1 (got 0)"),
    ({"filters": {"max_area_growth": float("-inf")}}, "spec.filters.max_area_growth must be a number > 0.0 (got -inf)"),
    ({"garment": {"resolution": 55}}, "spec.garment.resolution must be an integer >= 64 and <= 200000 (got 55)"),
    ({"garment": {"resolution": 10**9}}, "spec.garment.resolution must be an integer >= 64 and <= 200000"),
    ({"styles": {"train": [{"lenght": 0.5}]}},
     "spec.styles.train[0].lenght is not a style parameter of a tshirt (did you mean length?)"),
    ({"styles": {"test": [{"length": 0.5}, {"looseness": 9}]}}, "spec.styles.test[1].looseness must be a number >= "),
    ({"styles": {"train": [{"length": float("nan")}]}}, "spec.styles.train[0].length must be a number >= 0 and <= 1 (got nan)"),
    ({"styles": {"space": "space.npz"}}, "spec.styles.space must be null"),
    ({"shapes": {"train": [[0.5, float("nan"), 0.5, 0.5, 0.5, 0.5]]}}, "spec.shapes.train must be a count, 'tailornet9'"),
    ({"shapes": {"test": [[]]}}, "spec.shapes.test must be a count"),
    ({"shapes": {"test": "seen"}}, "spec.shapes.test must be a count >= 1, a non-empty list of shape vectors or 'train' "
                                   "(got 'seen')"),
    ({"styles": {"test": "seen"}}, "spec.styles.test must be a count >= 1, a non-empty list of {param: value} mappings "
                                   "or 'train' (got 'seen')"),
    ({"poses": {"joints": ["left_shoulder", "left_elbw"]}},
     "spec.poses.joints[1] must be a posable joint name (did you mean left_elbow?)"),
    ({"poses": {"path": 3}}, "spec.poses.path must be the path of a .npz pose file (a string) or null (got 3)"),
    ({"simulation": {"targets_from_home": "yes"}}, "spec.simulation.targets_from_home must be true or false (got 'yes')"),
    ({"seed": -1}, "spec.seed must be an integer >= 0 (got -1)"),
    ({"seed": True}, "spec.seed must be an integer >= 0 (got True)"),
    ({"name": ""}, "spec.name must be a non-empty string (got '')"),
])
def test_bad_values_name_path_value_and_expectation(patch, expected):
    text = check(patch)
    assert expected in text and "in t.yaml" in text, text
    assert "\n" not in text, "one line"


def test_every_problem_is_reported_at_once():
    text = check({"simulation": {"substep": 3, "tolerance": -1}, "filters": 3})
    assert "spec.simulation.substep" in text and "spec.simulation.tolerance" in text and "spec.filters must" in text


def test_null_sections_are_empty_and_healthy_specs_resolve_unchanged():
    base = {"name": "t", "garment": {"type": "tshirt"}}
    assert validate_spec({**base, "filters": None, "audit": None}) == validate_spec(base)
    shipped = sorted(p.stem for p in (Path(__file__).parents[1] / "pipelines" / "configs").glob("*.yaml"))
    assert "cloth3d" in shipped and "tailornet-tshirt" in shipped
    for name in shipped:
        spec = load_spec(name)
        assert validate_spec(spec) == spec, "a resolved spec validates to itself"
        assert spec_hash(validate_spec(spec)) == spec_hash(spec)


def test_spec_files_that_are_not_yaml_specs(tmp_path):
    npz = tmp_path / "poses.npz"
    np.savez(npz, poses=np.zeros((2, 60)))
    with pytest.raises(SpecError, match=r"poses.npz is not a YAML dataset spec \(it is a binary file, an .npz archive"):
        load_spec(npz)
    broken = tmp_path / "broken.yaml"
    broken.write_text("name: t\ngarment:\n  type: [tshirt\n")
    with pytest.raises(SpecError, match=r"broken.yaml is not valid YAML at line \d+ column \d+"):
        load_spec(broken)
    for text, kind in (("", "NoneType"), ("- a\n- b\n", "list"), ("just words\n", "str")):
        (tmp_path / "x.yaml").write_text(text)
        with pytest.raises(SpecError, match=f"must be a YAML mapping of fields .* \\(got {kind}\\)"):
            load_spec(tmp_path / "x.yaml")


@pytest.mark.parametrize("text, expected", [
    ("name: t\ngarment: {type: tshirt}\nsimulation: {substep: 3}\n", "spec.simulation.substep is not a known field"),
    ("name: t\ngarment: {type: tshirt}\nsimulation: {tolerance: .inf}\n", "spec.simulation.tolerance must be a number > 0.0 (got inf)"),
    ("name: t\ngarment: {type: tshirt}\nsimulation: 3\n", "spec.simulation must be a mapping"),
    ("name: t\ngarment: {type: tshirt, resolution: abc}\n", "spec.garment.resolution must be an integer >= 64"),
])
def test_cli_reports_spec_problems_in_one_line(tmp_path, capsys, text, expected):
    from pipelines.cli import main

    spec = tmp_path / "s.yaml"
    spec.write_text(text)
    assert main(["generate-dataset", str(spec), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("drape generate-dataset: error: invalid dataset spec: ") and expected in err, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists(), "nothing is created for a bad spec"


def test_explicit_shapes_outside_the_body_range_name_the_entry(anny_body):
    from pipelines.dataset_plan import plan_dataset

    spec = validate_spec({"name": "t", "garment": {"type": "tshirt"},
                          "shapes": {"train": [[0.5] * 6, [0.5, 0.5, 0.5, 0.5, 1.7, 0.5]], "test": 1}})
    with pytest.raises(ValueError, match=r"spec.shapes.train\[1\]\[4\] \(height\) must be in \[0, 1\] for the anny body \(got 1.7\)"):
        plan_dataset(spec, anny_body)
