"""Training, checkpoints, fingerprints and evaluation of TailorNet on a tiny synthetic dataset.

The synthetic "simulator": a 7 x 7 grid garment whose unposed displacements are a smooth
nonlinear function of pose, shape and style plus a pose- and style-dependent
high-frequency ripple, so both the low- and high-frequency parts have to be learned.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from data_manifest.reader import DatasetReader
from data_manifest.synthetic import tube_template, write_synthetic_dataset
from learn.common.mesh import grid_mesh
from learn.registry import LEARNERS, get_learner
from learn.tailornet.evaluate import (PosingContext, evaluate_split, evaluate_split_models, predict_displacements,
                                      time_inference)
from learn.tailornet.hf import HighFrequencyPrototypes
from learn.tailornet.lf import low_frequency_model
from learn.tailornet.model import TailorNet
from learn.tailornet.train import (
    DatasetFingerprint,
    DatasetMismatchError,
    FrameArrays,
    add_low_frequency,
    dataset_fingerprint,
    file_sha256,
    fit_baseline,
    fit_tailornet,
    fit_tailornet_process,
    frame_arrays_from_split,
    load_learner,
    merged_hyperparameters,
    STAGE_ORDER,
    stages_for_rank,
    hf_part_members,
    hf_part_stage,
    hf_parts_for,
    template_sha256,
    train_hf,
    train_stage,
)

torch.set_num_threads(1)

POSE_SIZE = 6
GRID = 7
# A few epochs must bring the test error below this fraction of the error of
# predicting the training mean displacement.
MEAN_BASELINE_MARGIN = 0.6
ATOL_STACKED_PARAMETER = 1e-4
FINGERPRINT = DatasetFingerprint("a" * 64, "b" * 64)
HYPER = {
    "lf": {"lr": 2e-3, "epochs": 30, "hidden_size": 64, "batch_size": 16},
    "hf": {"lr": 2e-3, "epochs": 60, "hidden_size": 64, "batch_size": 8},
    "shape_style": {"lr": 3e-3, "epochs": 150, "hidden_size": 32, "batch_size": 8},
    "baseline": {"lr": 2e-3, "epochs": 30, "hidden_size": 64, "batch_size": 16},
    "model": {"prototype_count": 4},
}


def _pairs() -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.array([s, 0.3]), np.array([g, -0.2])) for s in (-1.0, 1.0) for g in (-1.0, 1.0)]


def make_frames(
    seed: int, poses_per_pair: int, pairs: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[FrameArrays, np.ndarray]:
    rng = np.random.default_rng(seed)
    vertices, faces = grid_mesh(GRID, GRID, spacing=0.05)
    x, y = vertices[:, 0], vertices[:, 1]
    poses, shapes, styles, displacements, ids = [], [], [], [], []
    for pair_id, (shape, style) in enumerate(pairs):
        for pose in rng.uniform(-1.0, 1.0, size=(poses_per_pair, POSE_SIZE)):
            dz = (0.02 * (1 + 0.4 * shape[0]) * np.sin(3 * x + pose[0])
                  + 0.01 * style[0] * np.cos(4 * y + pose[1] * pose[2])
                  + 0.004 * np.sin(25 * x) * (pose[3] + style[0]))
            dx = 0.01 * shape[0] * y * pose[4] + 0.005 * np.tanh(pose[5]) * x
            displacements.append(np.stack([dx, np.full_like(dx, 0.003 * style[0]), dz], axis=-1))
            poses.append(pose)
            shapes.append(shape)
            styles.append(style)
            ids.append(pair_id)
    frames = FrameArrays(
        pose=np.asarray(poses, np.float32), shape=np.asarray(shapes, np.float32),
        style=np.asarray(styles, np.float32), displacements=np.asarray(displacements, np.float32),
        pair_id=np.asarray(ids, np.int64),
    )
    return frames, faces


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> dict:
    run_dir = tmp_path_factory.mktemp("run")
    train, faces = make_frames(0, 24, _pairs())
    test, _ = make_frames(1, 12, _pairs())
    tailornet = fit_tailornet(train, faces, run_dir=run_dir, hyperparameters=HYPER, fingerprint=FINGERPRINT,
                              progress=False)
    baseline = fit_baseline(train, faces, run_dir=run_dir, hyperparameters=HYPER, fingerprint=FINGERPRINT,
                            progress=False)
    return {"run_dir": run_dir, "train": train, "test": test, "faces": faces,
            "tailornet": tailornet, "baseline": baseline}


def test_training_beats_predicting_the_mean(trained: dict) -> None:
    train, test = trained["train"], trained["test"]
    mean = train.displacements.mean(axis=0, keepdims=True)
    mean_error = float(np.linalg.norm(test.displacements - mean, axis=-1).mean() * 1000.0)
    for name in ("tailornet", "baseline"):
        error = evaluate_split(trained[name], test)["unposed_error_mm"]
        assert error < MEAN_BASELINE_MARGIN * mean_error, (
            f"{name}: test error {error:.2f} mm not below {MEAN_BASELINE_MARGIN} x mean-prediction error "
            f"{mean_error:.2f} mm"
        )
    run_dir = trained["run_dir"]
    stages = ["shape_style", "lf", "hf", "baseline"]
    for stage in stages:
        rows = (run_dir / f"{stage}_loss.csv").read_text().strip().splitlines()
        epochs = merged_hyperparameters(HYPER)[stage]["epochs"]
        assert len(rows) == epochs + 1, f"{stage}: {len(rows) - 1} logged epochs, expected {epochs}"
        first, last = float(rows[1].split(",")[1]), float(rows[-1].split(",")[1])
        assert last < first, f"{stage}: training loss did not decrease ({first} -> {last})"


def test_checkpoint_round_trip_gives_identical_predictions(trained: dict) -> None:
    test = trained["test"]
    for name in ("tailornet", "baseline"):
        entry = get_learner(name)
        loaded = entry.load(trained["run_dir"] / entry.model_file, fingerprint=FINGERPRINT)
        assert isinstance(loaded, TailorNet) == (name == "tailornet")
        expected = predict_displacements(trained[name], test.pose, test.shape, test.style)
        np.testing.assert_array_equal(predict_displacements(loaded, test.pose, test.shape, test.style), expected,
                                      err_msg=f"{name}: reloaded model predicts differently")


def test_mismatched_dataset_raises_clear_error(trained: dict) -> None:
    path = trained["run_dir"] / "tailornet_model.pt"
    other_template = DatasetFingerprint(FINGERPRINT.dataset_manifest_sha256, "c" * 64)
    with pytest.raises(DatasetMismatchError, match="garment template sha256"):
        load_learner(path, fingerprint=other_template)
    other_manifest = DatasetFingerprint("d" * 64, FINGERPRINT.template_sha256)
    with pytest.raises(DatasetMismatchError, match="dataset manifest sha256"):
        load_learner(path, fingerprint=other_manifest)
    load_learner(path, fingerprint=other_manifest, require_same_manifest=False)
    # Resuming a stage against another dataset is refused too.
    with pytest.raises(DatasetMismatchError, match="template"):
        fit_baseline(trained["train"], trained["faces"], run_dir=trained["run_dir"], hyperparameters=HYPER,
                     fingerprint=other_template, progress=False)


def test_resume_reproduces_uninterrupted_training(tmp_path: Path) -> None:
    data, faces = make_frames(2, 10, _pairs()[:2])
    add_low_frequency(data, faces, iterations=10)
    hyper = {"lr": 1e-3, "weight_decay": 1e-6, "batch_size": 8, "epochs": 4}

    def model() -> torch.nn.Module:
        torch.manual_seed(5)
        return low_frequency_model(data.vertex_count, list(range(POSE_SIZE)), hidden_size=16)

    whole = train_stage("lf", model(), data, data.low_frequency, run_dir=tmp_path / "whole", hyperparameters=hyper,
                        fingerprint=FINGERPRINT, seed=3, progress=False)
    train_stage("lf", model(), data, data.low_frequency, run_dir=tmp_path / "split",
                hyperparameters={**hyper, "epochs": 2}, fingerprint=FINGERPRINT, seed=3, progress=False)
    resumed = train_stage("lf", model(), data, data.low_frequency, run_dir=tmp_path / "split",
                          hyperparameters=hyper, fingerprint=FINGERPRINT, seed=3, progress=False)
    for (name, a), b in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), f"parameter {name} differs between resumed and uninterrupted training"
    log = (tmp_path / "split" / "lf_loss.csv").read_text().strip().splitlines()
    assert [row.split(",")[0] for row in log[1:]] == ["1", "2", "3", "4"], log
    with pytest.raises(ValueError, match="configured"):
        train_stage("lf", low_frequency_model(data.vertex_count, [0, 1, 2], hidden_size=16), data,
                    data.low_frequency, run_dir=tmp_path / "split", hyperparameters=hyper,
                    fingerprint=FINGERPRINT, progress=False)


def test_evaluate_posed_metrics_with_synthetic_body(trained: dict) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    body_vertices = torch.as_tensor(np.asarray(sphere.vertices), dtype=torch.float32)
    grid, faces = grid_mesh(GRID, GRID, spacing=0.05)
    # The unposed body under the garment: a sheet through the sphere's top, so the
    # predicted garments partly penetrate it.
    under = torch.as_tensor(grid - grid.mean(axis=0) + np.array([0.0, 0.0, 0.19]), dtype=torch.float32)
    test = trained["test"].subset(np.arange(6))
    posing = PosingContext(
        unposed_body=lambda shape: under.expand(shape.shape[0], -1, -1),
        garment_poser=lambda unposed, pose, shape: unposed + 0.01 * pose[:, None, :3],
        posed_body=lambda pose, shape: body_vertices + 0.01 * pose[:, None, :3],
        body_faces=np.asarray(sphere.faces), garment_faces=faces,
    )
    test.posed_vertices = (posing.garment_poser(under + torch.as_tensor(test.displacements),
                                                torch.as_tensor(test.pose), None)).numpy()
    metrics = evaluate_split(trained["tailornet"], test, posing=posing)
    assert 0.0 < metrics["collision_rate"] <= 1.0, metrics
    assert metrics["collision_rate_postprocessed"] < metrics["collision_rate"], metrics
    assert metrics["postprocess_frames_evaluated"] == 6, metrics
    assert metrics["collision_rate_subset"] == metrics["collision_rate"], metrics
    subset = evaluate_split(trained["tailornet"], test, posing=posing, postprocess_frames=2)
    assert subset["postprocess_frames_evaluated"] == 2, subset
    assert subset["collision_rate_postprocessed"] < subset["collision_rate_subset"], subset
    assert subset["posed_error_mm_subset"] > 0 and subset["postprocessed_posed_error_mm"] > 0, subset
    # Posing is a translation here, so posed and unposed errors coincide.
    assert abs(metrics["posed_error_mm"] - metrics["unposed_error_mm"]) < 1e-3, metrics
    timing = time_inference(trained["tailornet"], test.pose, test.shape, test.style, batch_sizes=(1, 4), repeats=3)
    assert set(timing) == {"ms_per_frame_batch_1", "ms_per_frame_batch_4"} and min(timing.values()) > 0
    # Both models at once (each batch's body posed and its BVHs built once, shared), in batches of
    # 4 frames, give each model's metrics alone.
    both = evaluate_split_models({"tailornet": trained["tailornet"], "baseline": trained["baseline"]}, test,
                                 posing=posing, batch_size=4, postprocess_frames=2)
    for name in ("tailornet", "baseline"):
        alone = evaluate_split(trained[name], test, posing=posing, batch_size=4, postprocess_frames=2)
        for key, value in alone.items():
            assert both[name][key] == pytest.approx(value, rel=1e-6, abs=1e-9) or key == "postprocess_seconds", key


def test_slow_models_are_timed_within_the_budget() -> None:
    """A call slower than a tenth of the budget is warmed up once and timed max(3, budget / call)
    times, and its median is still its duration; a fast model gets the full repeats."""
    from learn.tailornet.evaluate import time_inference

    class Sleeper(torch.nn.Module):
        def __init__(self, seconds: float) -> None:
            super().__init__()
            self.seconds, self.calls = seconds, 0

        def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
            self.calls += 1
            time.sleep(self.seconds)
            return pose

    x = np.zeros((2, 3), np.float32)
    slow = Sleeper(0.05)
    timing = time_inference(slow, x, x, x, batch_sizes=(1,), repeats=20, warmup=3, budget_s=0.2)
    assert 1 + 3 <= slow.calls <= 1 + 4, slow.calls  # 0.2 s / ~0.05 s per call, at least 3
    assert 50.0 <= timing["ms_per_frame_batch_1"] < 150.0, timing
    fast = Sleeper(0.0)
    time_inference(fast, x, x, x, batch_sizes=(1,), repeats=20, warmup=3, budget_s=0.2)
    assert fast.calls == 3 + 20, fast.calls


def test_fingerprint_helpers_and_overrides(tmp_path: Path) -> None:
    template = tube_template()
    digest = template_sha256(template)
    assert digest == template_sha256(dict(template)), "template hash is not deterministic"
    assert digest != template_sha256({**template, "faces": template["faces"][::-1]}), "face order change not detected"
    with pytest.raises(ValueError, match="faces"):
        template_sha256({"rest_vertices": np.zeros((9, 3))})
    manifest = tmp_path / "manifest.json"
    manifest.write_text("{}")
    assert file_sha256(manifest) == "44136fa355b3678a1146ad16f7e8649e94fb4fc21fe77e8310c060f61caaff8a"
    with pytest.raises(FileNotFoundError):
        file_sha256(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="lf.learning_rate"):
        merged_hyperparameters({"lf": {"learning_rate": 1.0}})
    with pytest.raises(ValueError, match="unknown learner"):
        get_learner("nope")
    assert set(LEARNERS) == {"tailornet", "baseline", "uvimage", "uvimage_pca", "collision_aware", "gcvae"}


def test_frame_arrays_from_reader_split_groups_pairs() -> None:
    rng = np.random.default_rng(0)
    shape = np.repeat(np.array([[0.0, 1.0], [1.0, 0.0]], np.float32), 3, axis=0)
    arrays = {
        "pose": rng.normal(size=(6, POSE_SIZE)).astype(np.float32),
        "shape": shape,
        "style": np.zeros((6, 2), np.float32),
        "unposed_displacements": np.zeros((6, 4, 3), np.float32),
    }
    frames = frame_arrays_from_split(arrays)
    assert frames.pair_id.tolist() == [0, 0, 0, 1, 1, 1]
    with pytest.raises(ValueError, match="unposed_displacements"):
        frame_arrays_from_split({k: v for k, v in arrays.items() if k != "unposed_displacements"})


def test_reader_split_trains_and_evaluates_with_translation(tmp_path: Path) -> None:
    """End to end through the real on-disk format: reader -> FrameArrays -> fit -> evaluate."""
    manifest = write_synthetic_dataset(tmp_path / "data", splits={"train": 3, "test": 1}, frames_per_task=4)
    reader = DatasetReader(tmp_path / "data")
    template = reader.template
    fingerprint = dataset_fingerprint(tmp_path / "data", template)
    assert fingerprint.template_sha256 == manifest.template_sha256, "template hash differs from the manifest's"
    train = frame_arrays_from_split(reader.load_split("train"))
    test = frame_arrays_from_split(reader.load_split("test"))
    assert train.pair_id.max() == 2 and train.translation is not None and train.translation.shape == (12, 3)
    model = fit_baseline(train, template["faces"], run_dir=tmp_path / "run", fingerprint=fingerprint,
                         hyperparameters={"baseline": {"epochs": 2, "hidden_size": 16}}, progress=False)
    rest = torch.as_tensor(template["rest_vertices"])
    # Synthetic body: a small box at the origin; skinning stand-in: identity.
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    posing = PosingContext(
        unposed_body=lambda shape: rest.expand(shape.shape[0], -1, -1),
        garment_poser=lambda unposed, pose, shape: unposed,
        posed_body=lambda pose, shape: torch.as_tensor(np.asarray(box.vertices), dtype=torch.float32)
        .expand(pose.shape[0], -1, -1),
        body_faces=np.asarray(box.faces), garment_faces=template["faces"],
    )
    metrics = evaluate_split(model, test, posing=posing, postprocess=False)
    # Posing is identity + translation, so the posed error is the unposed error plus the
    # synthetic sway, which is bounded by 0.1 m * 0.5: check the translation was applied.
    assert metrics["posed_error_mm"] < metrics["unposed_error_mm"] + 60.0, metrics
    test.translation = None
    untranslated = evaluate_split(model, test, posing=posing, postprocess=False)
    assert untranslated["posed_error_mm"] > metrics["posed_error_mm"] + 500.0, (
        "dropping the body translation should put the garments metres off", untranslated, metrics
    )


def test_stacked_prototype_training_equals_independent_trainings(tmp_path: Path) -> None:
    """Full-batch, no dropout: one step sees the same frames in both modes, so the
    K-at-once training must follow the K separate trainings up to float rounding."""
    data, faces = make_frames(4, 8, _pairs()[:3])
    add_low_frequency(data, faces, iterations=10)
    hyper = {"hf": {"lr": 1e-3, "epochs": 5, "batch_size": 8, "hidden_size": 16, "dropout": 0.0}}
    args = dict(hyperparameters=hyper, fingerprint=FINGERPRINT, progress=False, seed=7)
    pairs = np.array([2, 0, 1])
    stacked = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "stacked", stacked=True, **args)
    separate = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "separate", stacked=False, **args)
    # Weights agree to ~1e-8; Adam's g / (|g| + eps) turns rounding of near-zero
    # gradients into differences of up to ~5e-5 in a few output biases.
    for (name, a), b in zip(stacked.state_dict().items(), separate.state_dict().values()):
        torch.testing.assert_close(a, b, atol=ATOL_STACKED_PARAMETER, rtol=0,
                                   msg=f"{name} differs between stacked and separate training")
    assert (tmp_path / "stacked" / "hf.done").exists() and (tmp_path / "separate" / "hf_02.done").exists()


def test_stages_and_prototype_parts_are_spread_over_processes() -> None:
    """Every stage (hf as its parts where split) is trained by exactly one process; with the
    paper's epochs hf goes in halves on 2 processes and in thirds on 4, so the longest process
    trains a part of hf (its cost model: seconds per epoch x epochs, STAGE_EPOCH_SECONDS)."""
    for world in range(1, 7):
        parts = hf_parts_for(world)
        hf_units = [hf_part_stage(i, parts) for i in range(parts)] if parts > 1 else ["hf"]
        units = sum((stages_for_rank(r, world) for r in range(world)), [])
        assert sorted(units) == sorted([s for s in STAGE_ORDER if s != "hf"] + hf_units), (world, units)
    assert hf_parts_for(1) == 1 and hf_parts_for(2) == 2 and hf_parts_for(4) == 3
    assert [stages_for_rank(r, 2) for r in range(2)] == [["hf_1of2", "baseline"], ["hf_2of2", "lf", "shape_style"]]
    assert [stages_for_rank(r, 4) for r in range(4)] == [["hf_1of3"], ["hf_2of3"], ["hf_3of3"],
                                                         ["baseline", "lf", "shape_style"]]
    # a few hf epochs: no process is given a part of it
    assert hf_parts_for(4, {"hf": {"epochs": 10}}) == 1
    assert hf_part_members(20, 1, 3).tolist() == list(range(7, 14)) and hf_part_members(5, 4, 5).tolist() == [4]
    with pytest.raises(ValueError, match="cannot split 2 prototypes into 3 parts"):
        hf_part_members(2, 0, 3)


def _three_prototypes(epochs: int) -> tuple[FrameArrays, dict, np.ndarray]:
    """Frames of 3 pairs with their low-frequency split, ``train_hf``'s keyword arguments (no
    dropout, ``epochs`` epochs) and the prototype pairs."""
    data, faces = make_frames(4, 8, _pairs()[:3])
    add_low_frequency(data, faces, iterations=10)
    hyper = {"hf": {"lr": 1e-3, "epochs": epochs, "batch_size": 4, "hidden_size": 16, "dropout": 0.0}}
    return data, dict(hyperparameters=hyper, fingerprint=FINGERPRINT, progress=False, seed=7), np.array([2, 0, 1])


def test_prototype_parts_trained_apart_equal_the_stacked_stage(tmp_path: Path) -> None:
    """hf split into parts (one per process): each part sees the batches the whole stage gives
    its prototypes, so without dropout the parts, put together, are the stacked stage up to
    float rounding; split over 'ranks' sharing a run directory they assemble the model."""
    data, args, pairs = _three_prototypes(epochs=5)
    whole = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "whole", **args)
    parts = [train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "parts", part=(i, 2), **args)
             for i in range(2)]
    assert [p.prototype_count for p in parts] == [2, 1]
    assert (tmp_path / "parts" / "hf_1of2.done").exists() and (tmp_path / "parts" / "hf_2of2.done").exists()
    joined = HighFrequencyPrototypes.cat(parts)
    for (name, a), b in zip(whole.state_dict().items(), joined.state_dict().values()):
        torch.testing.assert_close(a, b, atol=ATOL_STACKED_PARAMETER, rtol=0, msg=f"{name} differs from the stacked stage")
    # unstacked, a part trains its prototypes as their own stages
    alone = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "unstacked", part=(1, 2), stacked=False, **args)
    assert alone.prototype_count == 1 and sorted(p.name for p in (tmp_path / "unstacked").glob("*.done")) == ["hf_02.done"]
    # fit_tailornet over two 'ranks': the first trains a part and returns without the rest; the
    # second trains the other stages and the other part, then assembles the model
    train, faces = make_frames(0, 12, _pairs())
    hyper = {**HYPER, **{k: {**HYPER[k], "dropout": 0.0} for k in ("lf", "hf", "shape_style")}}
    fit = dict(hyperparameters=hyper, fingerprint=FINGERPRINT, progress=False)
    with pytest.raises(ValueError, match="hf_parts must be an integer >= 1"):
        fit_tailornet(train, faces, run_dir=tmp_path / "bad", hf_parts=0, **fit)
    with pytest.raises(ValueError, match="unknown TailorNet stages"):
        fit_tailornet(train, faces, run_dir=tmp_path / "bad", stages=["hf_1of3"], hf_parts=2, **fit)
    assert fit_tailornet(train, faces, run_dir=tmp_path / "ranks", stages=["hf_2of2"], hf_parts=2, **fit) is None
    # the part smoothed its own prototypes' frames, not the whole split's (which LF needs, not it)
    assert train.low_frequency is None, "an hf part computed the low-frequency split of every frame"
    model = fit_tailornet(train, faces, run_dir=tmp_path / "ranks", stages=["shape_style", "lf", "hf_1of2"],
                          hf_parts=2, **fit)
    # a process other than rank 0 never writes the model, even with every stage finished (ranks
    # that assembled at once raced on the model file)
    (tmp_path / "ranks" / "tailornet_model.pt").unlink()
    assert fit_tailornet(train, faces, run_dir=tmp_path / "ranks", stages=["hf_2of2"], hf_parts=2, assemble=False,
                         wait_timeout_s=60.0, **fit) is None
    assert not (tmp_path / "ranks" / "tailornet_model.pt").exists()
    # rank 0 assembling stages that others finished loads them without preparing their data: no
    # low-frequency split is computed, and the model is the one trained
    fresh, _ = make_frames(0, 12, _pairs())
    assert fresh.low_frequency is None
    again = fit_tailornet(fresh, faces, run_dir=tmp_path / "ranks", stages=[], hf_parts=2, **fit)
    assert fresh.low_frequency is None, "a finished stage prepared its training data"
    np.testing.assert_array_equal(predict_displacements(again, train.pose, train.shape, train.style),
                                  predict_displacements(model, train.pose, train.shape, train.style))
    alone = fit_tailornet(train, faces, run_dir=tmp_path / "alone", **fit)
    test, _ = make_frames(1, 6, _pairs())
    np.testing.assert_allclose(predict_displacements(model, test.pose, test.shape, test.style),
                               predict_displacements(alone, test.pose, test.shape, test.style), atol=1e-5, rtol=0)


def test_a_part_draws_only_its_prototypes_initial_weights(tmp_path: Path, monkeypatch) -> None:
    """A part draws the initial weights of its own prototypes only (each from its own seed, so they
    are the ones the whole stage starts from), and loading a finished part draws none: at K = 20
    and 7.7k vertices each draw is 25 M parameters, seconds of a 4-GPU run's critical path."""
    import learn.tailornet.train as train_module

    drawn = []
    original = train_module.high_frequency_model

    def counting(*args, **kwargs):
        drawn.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(train_module, "high_frequency_model", counting)
    data, args, pairs = _three_prototypes(epochs=2)
    whole = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "whole", **args)
    assert len(drawn) == 3
    drawn.clear()
    trained = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "parts", part=(0, 2), **args)
    assert len(drawn) == 2, f"part 1 of 2 (2 of 3 prototypes) drew {len(drawn)} initial models"
    drawn.clear()
    loaded = train_hf(data, np.arange(POSE_SIZE), pairs, run_dir=tmp_path / "parts", part=(0, 2), **args)
    assert drawn == [], "a finished part drew initial weights"
    for name, value in trained.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name
        # the part's prototypes (the first rows of every stacked tensor, weight3's first 2 x H) started
        # where the whole stage's did and took the same steps
        torch.testing.assert_close(value, whole.state_dict()[name][: value.shape[0]], atol=ATOL_STACKED_PARAMETER,
                                   rtol=0, msg=name)


def test_rank_zero_trains_its_baseline_before_it_waits(tmp_path: Path) -> None:
    """With the paper's epoch ratios on 2 processes rank 0 has half of hf and the baseline. It
    trains both while the other process has not even started, and only then waits for the other's
    stages and assembles (waiting first would leave it idle, then train the baseline alone: ~60 s
    of the 2-GPU run on the full t-shirt spec). The other rank writes no model; rank 0's equals one
    process's."""
    import threading

    train, faces = make_frames(0, 12, _pairs())
    hyper = {"lf": {**HYPER["lf"], "epochs": 2}, "hf": {**HYPER["hf"], "epochs": 16},
             "shape_style": {**HYPER["shape_style"], "epochs": 8}, "baseline": {**HYPER["baseline"], "epochs": 2},
             "model": HYPER["model"]}
    hyper = {k: {**v, "dropout": 0.0} if k != "model" else v for k, v in hyper.items()}
    assert stages_for_rank(0, 2, hyper) == ["hf_1of2", "baseline"], stages_for_rank(0, 2, hyper)
    common = dict(run_dir=tmp_path / "run", hyperparameters=hyper, fingerprint=FINGERPRINT, progress=False)
    result: dict = {}
    rank0 = threading.Thread(target=lambda: result.update(
        model=fit_tailornet_process(train, faces, rank=0, world_size=2, wait_timeout_s=120.0, **common)))
    rank0.start()
    assert _wait_for(lambda: (tmp_path / "run" / "baseline.done").exists(), 60.0), "rank 0 never trained its baseline"
    assert rank0.is_alive() and not (tmp_path / "run" / "tailornet_model.pt").exists()
    assert fit_tailornet_process(train, faces, rank=1, world_size=2, **common) is None
    rank0.join(120.0)
    assert not rank0.is_alive() and result["model"] is not None
    alone = fit_tailornet_process(train, faces, rank=0, world_size=1, **{**common, "run_dir": tmp_path / "alone"})
    assert (tmp_path / "alone" / "baseline.done").exists()
    test, _ = make_frames(1, 6, _pairs())
    np.testing.assert_allclose(predict_displacements(result["model"], test.pose, test.shape, test.style),
                               predict_displacements(alone, test.pose, test.shape, test.style), atol=1e-5, rtol=0)


def _wait_for(condition, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


def test_stages_split_over_processes_assemble_the_same_model(trained: dict, tmp_path: Path) -> None:
    """Two 'ranks' sharing a run directory give the model one process trains alone."""
    with pytest.raises(ValueError, match="rank"):
        stages_for_rank(2, 2)
    train, faces = make_frames(0, 24, _pairs())
    args = dict(run_dir=tmp_path, hyperparameters=HYPER, fingerprint=FINGERPRINT, progress=False)
    assert fit_tailornet(train, faces, stages=["lf", "shape_style"], **args) is None, "assembled without hf"
    model = fit_tailornet(train, faces, stages=["hf"], **args)
    assert model is not None
    test = trained["test"]
    np.testing.assert_array_equal(
        predict_displacements(model, test.pose, test.shape, test.style),
        predict_displacements(trained["tailornet"], test.pose, test.shape, test.style),
        err_msg="stage-split training differs from the single-process run",
    )
    with pytest.raises(ValueError, match="unknown TailorNet stages"):
        fit_tailornet(train, faces, stages=["baseline"], **args)


def test_predict_vertices_and_evaluate_models(trained: dict) -> None:
    from learn.tailornet.evaluate import evaluate_models, predict_vertices

    test = trained["test"].subset(np.arange(3))
    model = trained["tailornet"]
    single = predict_vertices(model, test.pose[0], test.shape[0], test.style[0])
    assert single.shape == (1, GRID * GRID, 3)
    # Batch 1 vs batch 3 differ only by matmul rounding (and which prototypes are skipped).
    np.testing.assert_allclose(single[0], predict_displacements(model, test.pose, test.shape, test.style)[0],
                               atol=1e-6)
    posing = PosingContext(
        unposed_body=lambda shape: torch.zeros(shape.shape[0], GRID * GRID, 3),
        garment_poser=lambda unposed, pose, shape: unposed + 1.0,
        posed_body=lambda pose, shape: torch.zeros(pose.shape[0], 3, 3),
        body_faces=np.array([[0, 1, 2]]), garment_faces=trained["faces"],
    )
    posed = predict_vertices(model, test.pose, test.shape, test.style, posing=posing,
                             translation=np.full((3, 3), 2.0, np.float32))
    np.testing.assert_allclose(posed, predict_displacements(model, test.pose, test.shape, test.style) + 3.0,
                               atol=1e-6)
    report = evaluate_models({"tailornet": model, "baseline": trained["baseline"]}, {"test-test": test},
                             timing_batch_sizes=(1, 2))
    assert set(report["splits"]["test-test"]) == {"tailornet", "baseline"}
    assert set(report["timing"]["baseline"]["cpu"]) == {"ms_per_frame_batch_1", "ms_per_frame_batch_2"}
    phases = report["phase_seconds"]
    assert set(phases) == {"splits", "postprocess", "timing"} and min(phases.values()) >= 0.0, phases
    assert phases["postprocess"] <= phases["splits"], phases
    import json

    json.dumps(report)  # the report must be JSON-serialisable


def test_frame_arrays_from_dataset_object() -> None:
    from types import SimpleNamespace

    from learn.tailornet.train import frame_arrays_from_dataset

    dataset = SimpleNamespace(
        pose=torch.zeros(4, POSE_SIZE), shape=torch.zeros(4, 2), style=torch.ones(4, 2),
        displacements=torch.ones(4, 5, 3), pair=torch.tensor([0, 0, 1, 1]), low_frequency=torch.zeros(4, 5, 3),
        posed_vertices=None,
    )
    frames = frame_arrays_from_dataset(dataset)
    assert frames.frame_count == 4 and frames.low_frequency is not None and frames.posed_vertices is None
    assert frames.pair_id.dtype == np.int64 and frames.pair_id.tolist() == [0, 0, 1, 1]
    with pytest.raises(ValueError, match="pair"):
        frame_arrays_from_dataset(SimpleNamespace(pose=dataset.pose, shape=dataset.shape, style=dataset.style,
                                                  displacements=dataset.displacements))


def test_plots_write_pngs(tmp_path: Path) -> None:
    from learn.tailornet.plots import plot_error_vs_runtime, render_prediction

    points = [{"label": "tailornet gpu b32", "ms_per_frame": 0.05, "error_mm": 11.0},
              {"label": "simulator", "ms_per_frame": 900.0, "error_mm": 0.0}]
    figure = plot_error_vs_runtime(points, tmp_path / "error_vs_runtime.png")
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="ms_per_frame"):
        plot_error_vs_runtime([{"label": "x", "ms_per_frame": 0.0, "error_mm": 1.0}], tmp_path / "bad.png")
    vertices, faces = grid_mesh(5, 5, spacing=0.05)
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    render = render_prediction(vertices + 0.002, vertices, faces, tmp_path / "render.png",
                               body_vertices=np.asarray(sphere.vertices), body_faces=np.asarray(sphere.faces),
                               title="frame 0")
    assert render.stat().st_size > 1000
    with pytest.raises(ValueError, match="shape"):
        render_prediction(vertices[:3], vertices, faces, tmp_path / "bad.png")


def _one_step(model: torch.nn.Module, optimizer: torch.optim.Optimizer) -> float:
    """One optimizer step of a low-frequency model on a zero pose: an epoch of the loop tests."""
    loss = model(torch.zeros(1, POSE_SIZE), torch.zeros(1, 0), torch.zeros(1, 0)).abs().mean()
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return float(loss.detach())


@pytest.mark.parametrize("interval_s, expected_epoch", [(0.0, 2), (1e9, None)])
def test_crash_resumes_from_last_checkpoint(tmp_path: Path, interval_s: float, expected_epoch: int | None) -> None:
    """A crash in epoch 3 leaves the epoch-2 checkpoint when saving every epoch, none
    when the interval has not elapsed; the log keeps only checkpointed epochs on resume."""
    from learn.tailornet.train import load_checkpoint, run_epochs

    calls = []

    def epoch_fn(model: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("simulated crash")
        return _one_step(model, optimizer)

    torch.manual_seed(0)
    model = low_frequency_model(4, list(range(POSE_SIZE)), shape_components=0, style_components=0, hidden_size=8)
    hyper = {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 1, "epochs": 4, "checkpoint_interval_s": interval_s}
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_epochs("stage", model, epoch_fn, run_dir=tmp_path, hyperparameters=hyper, fingerprint=None, progress=False)
    path = tmp_path / "stage.pt"
    if expected_epoch is None:
        assert not path.exists(), "checkpoint written although the interval had not elapsed"
    else:
        assert load_checkpoint(path)["epoch"] == expected_epoch
    assert not (tmp_path / "stage.done").exists()
    run_epochs("stage", model, epoch_fn, run_dir=tmp_path, hyperparameters=hyper, fingerprint=None, progress=False)
    rows = (tmp_path / "stage_loss.csv").read_text().strip().splitlines()[1:]
    assert [r.split(",")[0] for r in rows] == ["1", "2", "3", "4"], rows
    assert load_checkpoint(path)["epoch"] == 4 and (tmp_path / "stage.done").exists()


def test_finished_stage_loads_its_weights_without_the_optimizer_state(tmp_path: Path, monkeypatch) -> None:
    """Loading a finished stage (as rank 0 does with the stages other processes trained) gives
    the trained weights and never reads the optimizer's moments; a stage with epochs left
    resumes with them."""
    from learn.tailornet.train import run_epochs

    def fresh() -> torch.nn.Module:
        torch.manual_seed(0)
        return low_frequency_model(4, list(range(POSE_SIZE)), shape_components=0, style_components=0, hidden_size=8)

    hyper = {"lr": 1e-2, "weight_decay": 0.0, "batch_size": 1, "epochs": 3, "checkpoint_interval_s": 0.0}
    trained = run_epochs("stage", fresh(), lambda m, o, g: _one_step(m, o), run_dir=tmp_path, hyperparameters=hyper,
                         fingerprint=None, progress=False)
    loaded_optimizer_states = []
    original = torch.optim.Adam.load_state_dict

    def recording(self: torch.optim.Optimizer, state: dict) -> None:
        loaded_optimizer_states.append(state)
        original(self, state)

    monkeypatch.setattr(torch.optim.Adam, "load_state_dict", recording)

    def no_epoch(model: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        raise AssertionError("a finished stage ran an epoch")

    loaded = run_epochs("stage", fresh(), no_epoch, run_dir=tmp_path, hyperparameters=hyper, fingerprint=None,
                        progress=False)
    for name, value in trained.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name
    assert not all(torch.equal(value, fresh().state_dict()[name]) for name, value in trained.state_dict().items()), \
        "the training changed no weight: the comparison would not tell loaded from fresh"
    assert loaded_optimizer_states == [], "a finished stage read its optimizer's state"
    run_epochs("stage", fresh(), lambda m, o, g: _one_step(m, o), run_dir=tmp_path,
               hyperparameters={**hyper, "epochs": 4}, fingerprint=None, progress=False)
    assert len(loaded_optimizer_states) == 1 and loaded_optimizer_states[0]["state"], "the resume lost Adam's moments"


def test_slow_checkpoints_are_spaced_by_their_own_duration(tmp_path: Path, monkeypatch) -> None:
    """A save that takes long (the stacked HF checkpoint: GBs) pushes the next one back to
    SAVE_SHARE_INVERSE times its duration, so saves stay a small share of the stage; the last
    epoch is always saved. With interval 0 every epoch is still saved."""
    import learn.tailornet.train as train

    saved = []

    def slow_save(payload: dict, path: Path) -> None:
        time.sleep(0.05)
        saved.append(payload["epoch"])

    def epoch_fn(model: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        time.sleep(0.01)
        return 0.0

    monkeypatch.setattr(train, "atomic_save", slow_save)
    model = low_frequency_model(4, list(range(POSE_SIZE)), shape_components=0, style_components=0, hidden_size=8)
    for interval_s, expected in ((1e-3, [1, 6]), (0.0, [1, 2, 3, 4, 5, 6])):
        saved.clear()
        hyper = {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 1, "epochs": 6, "checkpoint_interval_s": interval_s}
        run_epochs_dir = tmp_path / f"run{interval_s}"
        train.run_epochs("stage", model, epoch_fn, run_dir=run_epochs_dir, hyperparameters=hyper, fingerprint=None,
                         progress=False)
        assert saved == expected, (interval_s, saved)


def test_checkpoints_are_written_while_training_goes_on(tmp_path: Path, monkeypatch) -> None:
    """A save snapshots the state and writes it on a background thread: epochs go on during the
    write, the file holds the state of the epoch it was taken at (training changes the weights in
    place meanwhile), the stage returns with its last checkpoint and .done on disk; a write that
    fails raises in the training; an epoch that fails leaves the write in flight finished."""
    import learn.tailornet.train as train

    original = train.atomic_save
    events: list[tuple[str, int]] = []
    fail_writes: list[bool] = []

    def slow_save(payload: dict, path: Path) -> None:
        events.append(("write", payload["epoch"]))
        time.sleep(0.2)
        if fail_writes:
            raise OSError(28, "No space left on device")
        original(payload, path)
        events.append(("written", payload["epoch"]))

    monkeypatch.setattr(train, "atomic_save", slow_save)
    weights_after: dict[int, torch.Tensor] = {}

    def epoch_fn(model: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        time.sleep(0.01)
        with torch.no_grad():
            for p in model.parameters():
                p.add_(1.0)  # in place, as an optimizer step does
        epoch = sum(1 for kind, _ in events if kind == "epoch") + 1
        weights_after[epoch] = next(model.parameters()).detach().clone()
        events.append(("epoch", epoch))
        return 0.0

    def model() -> torch.nn.Module:
        torch.manual_seed(0)
        return low_frequency_model(4, list(range(POSE_SIZE)), shape_components=0, style_components=0, hidden_size=8)

    hyper = {"lr": 1e-3, "weight_decay": 0.0, "batch_size": 1, "epochs": 12, "checkpoint_interval_s": 1e-3}
    train.run_epochs("stage", model(), epoch_fn, run_dir=tmp_path / "run", hyperparameters=hyper, fingerprint=None,
                     progress=False)
    first = events.index(("write", 1))
    assert ("epoch", 2) in events[first:events.index(("written", 1))], f"no epoch ran during the write: {events}"
    assert events[-1] == ("written", 12) and (tmp_path / "run" / "stage.done").exists()
    saved = train.load_checkpoint(tmp_path / "run" / "stage.pt")
    assert saved["epoch"] == 12
    first_weight = next(name for name, _ in model().named_parameters())
    assert torch.equal(saved["model_state"][first_weight], weights_after[12])

    # the snapshot: epoch 1's write holds epoch 1's weights though epochs 2+ changed them in place
    captured = []
    monkeypatch.setattr(train, "atomic_save", lambda payload, path: (captured.append(payload), slow_save(payload, path)))
    events.clear()
    weights_after.clear()
    train.run_epochs("snap", model(), epoch_fn, run_dir=tmp_path / "snap", hyperparameters={**hyper, "epochs": 4},
                     fingerprint=None, progress=False)
    assert captured[0]["epoch"] == 1
    assert torch.equal(captured[0]["model_state"][first_weight], weights_after[1])
    assert not torch.equal(weights_after[1], weights_after[4])

    monkeypatch.setattr(train, "atomic_save", slow_save)
    fail_writes.append(True)
    events.clear()
    with pytest.raises(OSError, match="No space left"):
        train.run_epochs("full", model(), epoch_fn, run_dir=tmp_path / "full", hyperparameters=hyper,
                         fingerprint=None, progress=False)
    assert not (tmp_path / "full" / "full.done").exists()
    fail_writes.clear()
    events.clear()

    def failing(model: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        if sum(1 for kind, _ in events if kind == "epoch") == 2:
            raise RuntimeError("epoch 3 failed")
        return epoch_fn(model, optimizer, generator)

    with pytest.raises(RuntimeError, match="epoch 3 failed"):
        train.run_epochs("crash", model(), failing, run_dir=tmp_path / "crash", hyperparameters=hyper,
                         fingerprint=None, progress=False)
    assert ("written", 1) in events and train.load_checkpoint(tmp_path / "crash" / "crash.pt")["epoch"] == 1


def test_evaluate_says_why_there_is_no_speed_up(tmp_path: Path) -> None:
    """A dataset whose generate-dataset run did not finish has no simulation time in its manifest:
    evaluate reports no speed-up and says why, instead of a silent null."""
    from types import SimpleNamespace

    from pipelines.evaluate import missing_simulator_time, simulator_ms_per_frame

    manifest = write_synthetic_dataset(tmp_path, splits={"train": 1, "test": 1}, frames_per_task=2)
    assert simulator_ms_per_frame(manifest) is None
    assert "stopped before it finished" in missing_simulator_time(manifest)
    finished = SimpleNamespace(audit={"simulation": {"seconds": 12.0, "kept_frames": 4}})
    assert missing_simulator_time(finished) is None and simulator_ms_per_frame(finished) == pytest.approx(3000.0)
    empty = SimpleNamespace(audit={"simulation": {"seconds": 12.0, "kept_frames": 0}})
    assert "kept no frames" in missing_simulator_time(empty) and simulator_ms_per_frame(empty) is None


def test_mixed_precision_is_switchable_and_keeps_the_error(tmp_path: Path) -> None:
    """bf16 autocast (model.mixed_precision) changes the trained weights but not the error:
    measured 5.663 -> 5.666 mm (baseline) and 6.218 -> 6.221 mm (mixture) on this data."""
    train, faces = make_frames(0, 24, _pairs())
    test, _ = make_frames(1, 12, _pairs())
    errors, predictions = {}, {}
    for mixed in (False, True):
        hyper = {**HYPER, "model": {**HYPER["model"], "mixed_precision": mixed}}
        model = fit_baseline(train, faces, run_dir=tmp_path / str(mixed), hyperparameters=hyper,
                             fingerprint=FINGERPRINT, progress=False)
        errors[mixed] = evaluate_split(model, test)["unposed_error_mm"]
        predictions[mixed] = predict_displacements(model, test.pose, test.shape, test.style)
    assert not np.array_equal(predictions[False], predictions[True]), "mixed_precision had no effect"
    assert abs(errors[True] - errors[False]) < 0.02 * errors[False], errors


def test_error_analysis_splits_the_error_by_pair_and_pose_distance(trained: dict) -> None:
    from learn.tailornet.analysis import error_analysis, format_analysis, nearest_pose_distance

    train, test = trained["train"], trained["test"]
    models = {"tailornet": trained["tailornet"], "baseline": trained["baseline"]}
    report = error_analysis(models, train, {"test": test, "train_again": train}, bins=3, train_frames=None)
    for name in models:
        part = report["splits"]["test"]["models"][name]
        assert part["error_mm"] == pytest.approx(evaluate_split(models[name], test)["unposed_error_mm"], rel=1e-6)
        assert part["generalisation_gap_mm"] == pytest.approx(part["error_mm"] - report["train"][name])
        assert sum(r["frames"] for r in part["per_pair"]) == test.frame_count
        weighted = sum(r["frames"] * r["error_mm"] for r in part["per_pair"]) / test.frame_count
        assert weighted == pytest.approx(part["error_mm"], rel=1e-5), "pair errors do not add up to the split's"
        assert report["splits"]["train_again"]["models"][name]["generalisation_gap_mm"] == pytest.approx(0.0, abs=1e-4)
    bins = report["splits"]["test"]["distance_bins"]
    assert sum(b["frames"] for b in bins) == test.frame_count and len(bins) == 3
    assert all(a["upper_rad"] <= b["lower_rad"] + 1e-9 for a, b in zip(bins, bins[1:])), bins
    assert report["splits"]["train_again"]["median_nearest_pose_rad"] == 0.0, "a training pose is its own nearest"
    # the reference's own poses are at distance 0; a shifted pose at its shift's norm
    shifted = train.pose[:2] + np.array([0.3, 0.4, 0, 0, 0, 0], np.float32)
    distance = nearest_pose_distance(np.concatenate([train.pose[:2], shifted]), train.pose, np.arange(POSE_SIZE))
    assert distance[:2].tolist() == [0.0, 0.0] and (distance[2:] <= 0.5 + 1e-6).all()
    assert "nearest training pose" in format_analysis(report)
    # coverage: a frame whose style (shape) no training frame has counts in that group
    assert set(report["splits"]["test"]["coverage"]) == {"style_and_shape_in_training"}
    other = test.subset(np.arange(8))
    other.style = other.style.copy()
    other.shape = other.shape.copy()
    other.style[:3] += 0.5  # frames 0-2: an unworn style; frames 2-3: an unseen shape
    other.shape[2:4] += 0.5
    from learn.tailornet.analysis import coverage_groups

    assert coverage_groups(train, other).tolist() == [1, 1, 3, 2, 0, 0, 0, 0]
    groups = error_analysis(models, train, {"other": other}, bins=2)["splits"]["other"]["coverage"]
    assert {k: v["frames"] for k, v in groups.items()} == {
        "style_and_shape_in_training": 4, "style_not_in_training": 2, "shape_not_in_training": 1,
        "neither_in_training": 1}
    assert "style not in training" in format_analysis(error_analysis(models, train, {"other": other}, bins=2))


def test_cosine_lr_schedule_anneals_and_resumes_where_it_stopped(tmp_path: Path) -> None:
    """``lr_schedule: cosine`` gives each epoch half a cosine from lr to lr * lr_final (the
    optimizer sees it, not only the formula); a run that crashes and resumes sees the same
    sequence as one that does not; ``constant`` keeps lr; bad values name the key."""
    from learn.tailornet.train import run_epochs, scheduled_lr

    seen: list[float] = []
    crash_at: list[int] = []

    def epoch_fn(model: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        seen.append(float(optimizer.param_groups[0]["lr"]))
        if len(seen) == crash_at[0]:
            raise RuntimeError("simulated crash")
        return _one_step(model, optimizer)

    def model() -> torch.nn.Module:
        torch.manual_seed(0)
        return low_frequency_model(4, list(range(POSE_SIZE)), shape_components=0, style_components=0, hidden_size=8)

    hyper = {"lr": 1e-2, "weight_decay": 0.0, "batch_size": 1, "epochs": 5, "checkpoint_interval_s": 0.0,
             "lr_schedule": "cosine", "lr_final": 0.1}
    expected = [1e-2, 1e-2 * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi / 4))), 1e-2 * 0.55,
                1e-2 * (0.1 + 0.9 * 0.5 * (1 + np.cos(3 * np.pi / 4))), 1e-3]
    crash_at.append(0)
    run_epochs("stage", model(), epoch_fn, run_dir=tmp_path / "whole", hyperparameters=hyper, fingerprint=None,
               progress=False)
    np.testing.assert_allclose(seen, expected, rtol=1e-12)
    assert [scheduled_lr(1e-2, e, 5, "cosine", 0.1) for e in range(5)] == pytest.approx(expected, rel=1e-12)
    seen.clear()
    crash_at[0] = 3
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_epochs("stage", model(), epoch_fn, run_dir=tmp_path / "resumed", hyperparameters=hyper, fingerprint=None,
                   progress=False)
    crash_at[0] = 0
    run_epochs("stage", model(), epoch_fn, run_dir=tmp_path / "resumed", hyperparameters=hyper, fingerprint=None,
               progress=False)
    np.testing.assert_allclose(seen, expected[:3] + expected[2:], rtol=1e-12)  # epoch 3 ran twice
    whole = (tmp_path / "whole" / "stage_loss.csv").read_text().splitlines()
    resumed = (tmp_path / "resumed" / "stage_loss.csv").read_text().splitlines()
    assert [r.split(",")[1] for r in whole] == [r.split(",")[1] for r in resumed]
    assert scheduled_lr(1e-2, 3, 5, "constant") == 1e-2
    for key, value in (("lr_schedule", "step"), ("lr_final", 2.0)):
        with pytest.raises(ValueError, match=key):
            run_epochs("stage", model(), epoch_fn, run_dir=tmp_path / key, fingerprint=None, progress=False,
                       hyperparameters={**hyper, key: value})


def test_a_stage_is_finished_when_its_marker_counts_its_epochs(tmp_path: Path) -> None:
    """stage_finished needs the checkpoint and a .done marker with the configured epochs (a marker
    of fewer epochs is a stage to resume); wait_for_stage returns once another process finishes."""
    import threading

    from learn.tailornet.train import stage_finished, wait_for_stage

    assert not stage_finished(tmp_path, "baseline", 3)
    (tmp_path / "baseline.done").write_text(json.dumps({"stage": "baseline", "epochs": 3}))
    assert not stage_finished(tmp_path, "baseline", 3), "no checkpoint"
    (tmp_path / "baseline.pt").write_bytes(b"x")
    assert stage_finished(tmp_path, "baseline", 3) and not stage_finished(tmp_path, "baseline", 5)
    assert not wait_for_stage(tmp_path, "baseline", 5, timeout_s=0.2, poll_s=0.05)
    later = threading.Timer(0.3, lambda: (tmp_path / "baseline.done").write_text(json.dumps({"epochs": 5})))
    later.start()
    assert wait_for_stage(tmp_path, "baseline", 5, timeout_s=10.0, poll_s=0.05)
    later.join()
