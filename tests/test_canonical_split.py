"""The canonical split (``splits.canonical: all``): every style-shape combination of a dataset draped
in the body's canonical pose, the A-pose drapes TailorNet's g and prototype choice learn from
(seed 000, Sec. 4.4 and 5.3)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from learn.tailornet.train import (
    FrameArrays,
    canonical_training_frames,
    fit_baseline,
    fit_tailornet,
    train_shape_style,
    with_canonical_frames,
)
from pipelines.spec import SpecError, validate_spec
from tests.test_tailornet_train import FINGERPRINT, HYPER, make_frames

torch.set_num_threads(1)


def spec(**splits) -> dict:
    return validate_spec({
        "name": "canonical", "garment": {"type": "tshirt", "resolution": 400},
        "styles": {"train": 3, "test": "train"}, "shapes": {"train": 2, "test": "train"},
        "pairs": {"train": 2, "test": 2}, "poses": {"train_count": 3, "test_count": 2},
        "splits": {"train_train": "all", "train_test": "all", "test_train": 1, "test_test": 1, **splits},
        "simulation": {"device": "cpu", "worlds": 4},
    })


def test_the_split_plans_one_canonical_frame_per_style_shape_combination(anny_body):
    from pipelines.dataset_plan import plan_dataset

    without, plan = plan_dataset(spec(), anny_body), plan_dataset(spec(canonical="all"), anny_body)
    canonical = [t for t in plan.tasks if t.split == "canonical"]
    combos = {(t.style_index, tuple(t.shape.tolist())) for t in canonical}
    assert len(canonical) == len(combos) == 3 * 2, "one task per combination of the 3 styles and 2 shapes"
    for t in canonical:
        np.testing.assert_array_equal(t.poses, np.asarray(anny_body.canonical_pose, np.float32)[None])
        group, si, hi = plan.pairs[t.pair]
        assert si == t.style_index and np.array_equal(plan.shapes[hi], t.shape)
    # the train and test pairs keep their index (their canonical tasks share it), the rest come after
    assert plan.pairs[:len(without.pairs)] == without.pairs
    assert [g for g, _, _ in plan.pairs[len(without.pairs):]] == ["canonical"] * (6 - len(without.pairs))
    others = [t for t in plan.tasks if t.split != "canonical"]
    assert [(t.task_id, t.pair, t.pose_ids.tolist()) for t in others] == \
        [(t.task_id, t.pair, t.pose_ids.tolist()) for t in without.tasks], "the other tasks are unchanged"
    assert "canonical" not in spec()["splits"], "absent, the key stays out of the resolved spec (and its hash)"


@pytest.mark.parametrize("value, message", [
    (2, "spec.splits.canonical must be all (one canonical-pose frame per style-shape combination) or 0 (got 2)"),
    (True, "spec.splits.canonical must be all (one canonical-pose frame per style-shape combination) or 0 (got True)"),
    ("some", "spec.splits.canonical must be all"),
])
def test_a_bad_value_names_the_field(value, message):
    with pytest.raises(SpecError, match=message.replace("(", r"\(").replace(")", r"\)")):
        spec(canonical=value)


def _canonical(pairs) -> FrameArrays:
    """Each pair's drape in pose 0 (the synthetic frames' field there)."""
    return FrameArrays(pose=np.zeros((len(pairs), 6), np.float32),
                       shape=np.asarray([p[0] for p in pairs], np.float32),
                       style=np.asarray([p[1] for p in pairs], np.float32),
                       displacements=_at_pose_zero(pairs), pair_id=np.arange(len(pairs), dtype=np.int64))


def _at_pose_zero(pairs) -> np.ndarray:
    from learn.common.mesh import grid_mesh
    from tests.test_tailornet_train import GRID

    vertices, _ = grid_mesh(GRID, GRID, spacing=0.05)
    x, y = vertices[:, 0], vertices[:, 1]
    out = []
    for shape, style in pairs:
        dz = 0.02 * (1 + 0.4 * shape[0]) * np.sin(3 * x) + 0.01 * style[0] * np.cos(4 * y) + 0.004 * np.sin(25 * x) * style[0]
        out.append(np.stack([np.zeros_like(x), np.full_like(x, 0.003 * style[0]), dz], axis=-1))
    return np.asarray(out, np.float32)


def test_canonical_frames_come_from_the_split_and_g_sees_every_combination():
    train_pairs = [(np.array([s, 0.3]), np.array([g, -0.2])) for s, g in ((-1.0, -1.0), (1.0, 1.0), (1.0, -1.0))]
    unseen = (np.array([-1.0, 0.3]), np.array([1.0, -0.2]))
    data, _ = make_frames(0, 6, train_pairs)
    canonical = _canonical([train_pairs[0], train_pairs[2], unseen])  # pair 1 has no canonical frame
    pair_frames, g_frames = canonical_training_frames(data, canonical)
    assert pair_frames.frame_count == 3 and g_frames.frame_count == 4
    np.testing.assert_array_equal(pair_frames.displacements[0], canonical.displacements[0])
    np.testing.assert_array_equal(pair_frames.displacements[2], canonical.displacements[1])
    nearest = np.argmin(np.where(data.pair_id == 1, np.linalg.norm(data.pose, axis=1), np.inf))
    np.testing.assert_array_equal(pair_frames.displacements[1], data.displacements[nearest])
    np.testing.assert_array_equal(g_frames.displacements[3], canonical.displacements[2])
    np.testing.assert_array_equal(g_frames.shape[3], unseen[0].astype(np.float32))
    # without a split, the pairs' nearest frames serve both
    alone, g_alone = canonical_training_frames(data, None)
    assert alone.frame_count == g_alone.frame_count == 3


def test_g_predicts_a_combination_it_saw_only_in_the_canonical_split(tmp_path):
    """g learns the unseen combination's canonical drape from the split: its error there falls
    below half of what the same training without the split leaves."""
    train_pairs = [(np.array([s, 0.3]), np.array([g, -0.2])) for s, g in ((-1.0, -1.0), (1.0, 1.0), (1.0, -1.0))]
    unseen = (np.array([-1.0, 0.3]), np.array([1.0, -0.2]))
    data, _ = make_frames(0, 6, train_pairs)
    canonical = _canonical(train_pairs + [unseen])
    truth = torch.as_tensor(_at_pose_zero([unseen]))
    errors = []
    for k, split in enumerate((None, canonical)):
        g = train_shape_style(data, run_dir=tmp_path / str(k), hyperparameters=HYPER, fingerprint=FINGERPRINT,
                              canonical=split, progress=False)
        with torch.no_grad():
            predicted = g.canonical(torch.as_tensor(unseen[0][None], dtype=torch.float32),
                                    torch.as_tensor(unseen[1][None], dtype=torch.float32))
        errors.append(float((predicted - truth).norm(dim=-1).mean()))
    assert errors[1] < 0.5 * errors[0], errors


def test_lf_and_the_baseline_take_the_split_repeat_times(tmp_path):
    train_pairs = [(np.array([s, 0.3]), np.array([g, -0.2])) for s, g in ((-1.0, -1.0), (1.0, 1.0))]
    data, faces = make_frames(0, 4, train_pairs)
    canonical = _canonical(train_pairs + [(np.array([-1.0, 0.3]), np.array([1.0, -0.2]))])
    hyper = {**HYPER, "model": {**HYPER["model"], "canonical_repeat": 3}}
    from learn.tailornet.train import add_low_frequency, merged_hyperparameters

    add_low_frequency(data, faces)
    more = with_canonical_frames(data, canonical, 3, faces, merged_hyperparameters(hyper))
    assert more.frame_count == data.frame_count + 3 * canonical.frame_count
    assert more.low_frequency is not None and more.low_frequency.shape == more.displacements.shape
    np.testing.assert_array_equal(more.displacements[data.frame_count:][-3:], canonical.displacements)
    assert set(more.pair_id[data.frame_count:]) .isdisjoint(set(data.pair_id)), "the added frames are no training pair"
    assert with_canonical_frames(data, canonical, 0, faces, merged_hyperparameters(hyper)) is data
    # the whole fit runs with them (the prototypes stay training pairs)
    model = fit_tailornet(data, faces, run_dir=tmp_path / "tn", hyperparameters=hyper, fingerprint=FINGERPRINT,
                          canonical=canonical, progress=False)
    assert model.high_frequency.prototype_count == 2
    fit_baseline(data, faces, run_dir=tmp_path / "tn", hyperparameters=hyper, fingerprint=FINGERPRINT,
                 canonical=canonical, progress=False)


def test_drape_train_reads_the_canonical_split(tmp_path, capsys):
    """``drape train`` hands a dataset's canonical split to TailorNet and the baseline only, and
    ``model.use_canonical_split: false`` leaves it out."""
    from data_manifest.reader import DatasetReader
    from data_manifest.synthetic import write_synthetic_dataset
    from learn.tailornet.train import DEFAULT_HYPERPARAMETERS
    from pipelines.train import load_canonical_split

    data = tmp_path / "data"
    write_synthetic_dataset(data, splits={"train": 2, "canonical": 3}, frames_per_task=2)
    reader = DatasetReader(data)
    hyper = {**DEFAULT_HYPERPARAMETERS["model"], "canonical_repeat": 2}
    canonical = load_canonical_split(reader, data, "tailornet", hyper)
    assert canonical.frame_count == 6 and canonical.displacements.shape[1:] == (reader.template["faces"].max() + 1, 3)
    assert ("canonical split: 6 style-shape combinations in the canonical pose (g and the prototype choice learn "
            "from them; LF trains on them 2 times (model.canonical_repeat))") in capsys.readouterr().out
    assert load_canonical_split(reader, data, "baseline", {**hyper, "canonical_repeat": 0}) is not None
    assert "the baseline trains on them not (model.canonical_repeat 0)" in capsys.readouterr().out
    assert load_canonical_split(reader, data, "tailornet", hyper, streamed=True) is not None
    assert "LF trains on them not (a streamed split)" in capsys.readouterr().out
    assert load_canonical_split(reader, data, "uvimage", hyper) is None
    assert load_canonical_split(reader, data, "tailornet", {**hyper, "use_canonical_split": False}) is None
    write_synthetic_dataset(tmp_path / "plain", splits={"train": 1}, frames_per_task=2)
    assert load_canonical_split(DatasetReader(tmp_path / "plain"), tmp_path / "plain", "tailornet", hyper) is None
