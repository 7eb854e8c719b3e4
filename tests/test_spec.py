"""Dataset spec validation: defaults, shipped specs, and errors naming the field path."""
from __future__ import annotations

import pytest

from pipelines.spec import SpecError, load_spec, validate_spec


def test_shipped_specs_validate():
    quick = load_spec("quickstart")
    assert quick["garment"]["type"] == "tshirt" and quick["simulation"]["solver"] == "xpbd"
    full = load_spec("tailornet-tshirt")
    assert full["pairs"] == {"train": 20, "test": 20} and full["poses"]["train_count"] == 2600
    frames = 20 * 2600 + 20 * 179 + 20 * full["splits"]["test_train"] + 20 * full["splits"]["test_test"]
    assert frames == 58_900


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
    ({"shapes": {"test": "tailornet9"}}, "spec.shapes.test must be an integer >= 1"),
    ({"filters": {"max_area_shrink": 1.5}}, "spec.filters.max_area_shrink must be a number > 0.0 and <= 1.0"),
    ({"colour": "red"}, "spec.colour is not a known field"),
    ({"simulation": {"poses_per_task": 0}}, "spec.simulation.poses_per_task must be an integer >= 1"),
    ({"simulation": {"restart_after_rejects": -1}}, "spec.simulation.restart_after_rejects must be an integer >= 0"),
    ({"simulation": {"contact": {"body_contact_detect_every": 0}}},
     "spec.simulation.contact.body_contact_detect_every must be an integer >= 1"),
    ({"simulation": {"outlier_fraction": 0.9}}, "spec.simulation.outlier_fraction must be a number >= 0.0 and <= 0.5"),
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


@pytest.mark.parametrize("key", ["damping", "explosion_stretch", "patience", "xpbd_mode", "min_hold_frames",
                                 "body_lookahead", "cross_group_tasks", "restart_to", "home_between_targets",
                                 "gs_relaxation", "contact.friction", "contact.self_contact_during",
                                 "contact.self_contact_rest_exclusion", "contact.canonical_self_contact"])
def test_library_settings_are_not_spec_fields(key):
    section, _, name = key.rpartition(".")
    sim = {name: 1} if not section else {section: {name: 1}}
    with pytest.raises(SpecError, match=f"spec.simulation.{key} is not a known field"):
        validate_spec({"name": "t", "garment": {"type": "tshirt"}, "simulation": sim})
