"""Dataset spec validation: defaults, shipped specs, and errors naming the field path."""
from __future__ import annotations

import pytest

from pipelines.spec import SpecError, load_spec, validate_spec


def test_shipped_specs_validate():
    quick = load_spec("quickstart")
    assert quick["garment"]["type"] == "tshirt" and quick["simulation"]["solver"] == "xpbd"
    full = load_spec("tailornet-tshirt")
    assert full["pairs"] == {"train": 20, "test": 20, "cover": True} and full["poses"]["train_count"] == 2600
    assert full["splits"]["canonical"] == "all"  # 20 styles x 9 shapes in the canonical pose
    frames = 20 * 2600 + 20 * 179 + 20 * full["splits"]["test_train"] + 20 * full["splits"]["test_test"] + 20 * 9
    assert frames == 59_080


@pytest.mark.parametrize("patch, path", [
    ({"poses": {"train_count": 0}}, "spec.poses.train_count must be an integer >= 1 (got 0)"),
    ({"garment": {"type": "cape"}}, "spec.garment.type must be one of tshirt"),
    ({"simulation": {"tolerance": -1}}, "spec.simulation.tolerance must be a number > 0.0"),
    ({"simulation": {"contact": {"self_contact": "yes"}}}, "spec.simulation.contact.self_contact must be true or false"),
    ({"output": {"precision": "float8"}}, "spec.output.precision must be one of float32, float16"),
    ({"poses": {"source": "file"}}, "spec.poses.path must be a .npz pose file"),
    ({"poses": {"min_clearance": -0.01}}, "spec.poses.min_clearance must be a number >= 0.0 and <= 0.2 (got -0.01)"),
    ({"poses": {"min_clearance": "2cm"}}, "spec.poses.min_clearance must be a number >= 0.0"),
    ({"poses": {"source": "file", "path": "p.npz", "min_clearance": 0.02}},
     "spec.poses.min_clearance must be null when poses.source is file"),
    ({"shapes": {"test": "tailornet9"}},
     "spec.shapes.test must be a count >= 1, a non-empty list of shape vectors or 'train' (got 'tailornet9')"),
    ({"filters": {"max_area_shrink": 1.5}}, "spec.filters.max_area_shrink must be a number > 0.0 and <= 1.0"),
    ({"colour": "red"}, "spec.colour is not a known field"),
    ({"simulation": {"poses_per_task": 0}}, "spec.simulation.poses_per_task must be an integer >= 1"),
    ({"simulation": {"max_relax_frames": 0}}, "spec.simulation.max_relax_frames must be an integer >= 1"),
    ({"simulation": {"contact": {"primary_bodies": 1}}}, "spec.simulation.contact.primary_bodies must be true or false"),
    ({"simulation": {"interpolation_threshold": 4}},
     "spec.simulation.interpolation_threshold must be a number > 0.0 and <= 3.2"),
    ({"splits": {"test_test": "some"}}, "spec.splits.test_test must be an integer >= 0 or one of ('all',)"),
])
def test_malformed_fields_name_their_path(patch, path):
    raw = {"name": "t", "garment": {"type": "tshirt"}}
    for key, value in patch.items():
        raw[key] = {**raw.get(key, {}), **value} if isinstance(value, dict) else value
    with pytest.raises(SpecError) as exc:
        validate_spec(raw, source="t.yaml")
    assert path in str(exc.value) and "in t.yaml" in str(exc.value)


def test_missing_spec_file_lists_shipped(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"shipped specs: (.*, )?quickstart, .*tailornet-tshirt"):
        load_spec(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed")
    with pytest.raises(SpecError, match="not valid YAML"):
        load_spec(bad)


def test_the_spec_defaults_are_the_library_defaults():
    """A spec that sets no simulation field runs with SequenceSettings() and SimSettings() as they
    are: the library's defaults are the settings generate-dataset uses."""
    from pipelines.generate_dataset import sequence_settings
    from simulate.quasi_static import SimSettings
    from simulate.sequence import SequenceSettings

    settings = sequence_settings(validate_spec({"name": "t", "garment": {"type": "tshirt"}}))
    assert settings == SequenceSettings() and settings.sim == SimSettings(), settings
    assert (SimSettings().damping, SimSettings().explosion_stretch, SimSettings().patience) == (20.0, 50.0, 3)


PRODUCTION = {"frame_dt": 1.0 / 45.0, "substeps": 15, "iterations": 5, "tolerance": 0.05, "max_frames": 60,
              "outlier_fraction": 0.02, "limit_cycle_window": 8, "self_contact_detect_every": 1,
              "body_contact_detect_every": 5, "restart_after_rejects": 1, "shape_transition_frames": 10,
              "contact_thickness": 0.004}
"""The production settings (docs/dataset.md), SimSettings and SequenceSettings fields."""


def test_the_library_defaults_are_the_production_settings():
    """The TailorNet spec, which sets no stepping, runs with these; so does every library user."""
    from pipelines.generate_dataset import sequence_settings
    from simulate.quasi_static import SimSettings
    from simulate.sequence import SequenceSettings

    sim, seq = SimSettings(), SequenceSettings()
    got = {k: getattr(sim, k) if hasattr(sim, k) else getattr(seq, k) for k in PRODUCTION}
    assert got == PRODUCTION
    full = sequence_settings(load_spec("tailornet-tshirt"))
    assert full.sim == sim and full.self_contact and full.solver == "xpbd", full


SIMULATION_LEAVES = ("solver", "device", "worlds", "batches", "frame_dt", "substeps", "iterations", "tolerance", "max_relax_frames",
                     "interpolation_threshold", "poses_per_task", "contact.self_contact", "contact.primary_bodies")
"""The spec's simulation fields, as its docstring lists them."""


def _leaves(node: dict, prefix: str = "") -> list[str]:
    return [leaf for key, value in node.items()
            for leaf in (_leaves(value, f"{prefix}{key}.") if isinstance(value, dict) else [f"{prefix}{key}"])]


def test_the_simulation_section_has_the_documented_leaves():
    import pipelines.spec as spec_module

    resolved = validate_spec({"name": "t", "garment": {"type": "tshirt"}})
    assert sorted(_leaves(resolved["simulation"])) == sorted(SIMULATION_LEAVES)
    doc = spec_module.__doc__
    section = doc[doc.index("    simulation:"):doc.index("    filters:")]
    for leaf in SIMULATION_LEAVES:
        assert f" {leaf.rpartition('.')[2]}:" in section, f"simulation.{leaf} is not in the spec docstring"


@pytest.mark.parametrize("key, library, default", [
    ("outlier_fraction", "SimSettings.outlier_fraction", "0.02"),
    ("limit_cycle_window", "SimSettings.limit_cycle_window", "8"),
    ("restart_after_rejects", "SequenceSettings.restart_after_rejects", "1"),
    ("shape_transition_frames", "SequenceSettings.shape_transition_frames", "10"),
    ("contact.thickness", "SequenceSettings.contact_thickness", "0.004"),
    ("contact.self_contact_detect_every", "SimSettings.self_contact_detect_every", "1"),
    ("contact.body_contact_detect_every", "SimSettings.body_contact_detect_every", "5"),
])
def test_a_library_setting_in_a_spec_names_the_setting_that_applies(key, library, default):
    section, _, name = key.rpartition(".")
    sim = {name: 3} if not section else {section: {name: 3}}
    with pytest.raises(SpecError) as exc:
        validate_spec({"name": "t", "garment": {"type": "tshirt"}, "simulation": sim}, source="t.yaml")
    assert str(exc.value) == (f"invalid dataset spec: spec.simulation.{key} is not a spec field: the library's "
                              f"{library} ({default}) applies (in t.yaml)")


def test_a_library_setting_in_a_spec_file_exits_2_with_one_line(tmp_path, capsys):
    from pipelines.cli import main

    path = tmp_path / "s.yaml"
    path.write_text("name: s\ngarment: {type: tshirt}\nsimulation: {outlier_fraction: 0.01}\n")
    assert main(["generate-dataset", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "spec.simulation.outlier_fraction is not a spec field: the library's " \
                              "SimSettings.outlier_fraction (0.02) applies (in s.yaml)" in err[0], err


def test_a_manifest_spec_with_library_settings_resolves_without_them():
    from pipelines.spec import without_library_settings

    raw = {"name": "t", "garment": {"type": "tshirt"},
           "simulation": {"tolerance": 0.02, "outlier_fraction": 0.005, "contact": {"thickness": 0.004, "self_contact": True}}}
    spec = validate_spec(without_library_settings(raw))
    assert spec["simulation"]["tolerance"] == 0.02 and spec["simulation"]["contact"]["self_contact"]
    assert raw["simulation"]["outlier_fraction"] == 0.005, "the caller's dict is left as it is"


@pytest.mark.parametrize("key", ["damping", "explosion_stretch", "patience", "xpbd_mode", "min_hold_frames",
                                 "body_lookahead", "cross_group_tasks", "restart_to", "home_between_targets",
                                 "gs_relaxation", "contact.friction", "contact.self_contact_during",
                                 "contact.self_contact_rest_exclusion", "contact.canonical_self_contact"])
def test_library_settings_are_not_spec_fields(key):
    section, _, name = key.rpartition(".")
    sim = {name: 1} if not section else {section: {name: 1}}
    with pytest.raises(SpecError, match=f"spec.simulation.{key} is not a known field"):
        validate_spec({"name": "t", "garment": {"type": "tshirt"}, "simulation": sim})
