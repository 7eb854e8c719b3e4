"""The collision-aware learner's recurrent regressor (seed 002, Sec. 5) for motion datasets: the
motion descriptor and the GRU are causal, windows of tiny sequences train it to fit them, the
sequences run in frame order whatever order their frames come in, and ``drape train
collision-aware`` picks it on a motion dataset (``--regressor`` chooses, with a one-line error
for gru on a quasi-static dataset) before ``drape evaluate`` and ``drape predict`` run it."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from learn.collision_aware.motion_descriptor import motion_descriptor, sequence_rows
from learn.collision_aware.recurrent_regressor import RecurrentLatentRegressor, sequence_windows
from learn.tailornet.train import FrameArrays

POSE_SIZE, SHAPE_SIZE, STYLE_SIZE, LATENT_SIZE = 60, 3, 2, 4
FPS = 30.0
MOVING = [0, 1, 2, 9, 20, 44]  # pelvis (the root: its motion enters through derivatives) and four joints


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Small GRUs step 30x faster on one thread than on two of a shared 2-core machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _poses(frames: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pose = np.zeros((frames, POSE_SIZE), np.float32)
    t = np.arange(frames) / FPS
    for entry in MOVING:
        pose[:, entry] = 0.4 * np.sin(2 * np.pi * rng.uniform(0.5, 2.0) * t + rng.uniform(0, 2 * np.pi))
    return pose


def _regressor(seed: int = 0, **kwargs) -> RecurrentLatentRegressor:
    torch.manual_seed(seed)
    return RecurrentLatentRegressor(list(range(POSE_SIZE)), SHAPE_SIZE, STYLE_SIZE, LATENT_SIZE, FPS,
                                    hidden_size=16, layers=2, **kwargs).eval()


def test_the_prediction_at_a_frame_depends_on_that_frame_and_earlier_ones_only() -> None:
    frames, t = 12, 6
    regressor = _regressor()
    pose = torch.as_tensor(_poses(frames, seed=1))[None]
    shape, style = torch.full((1, frames, SHAPE_SIZE), 0.5), torch.full((1, frames, STYLE_SIZE), 0.2)
    root = torch.zeros(1, frames, 3)
    with torch.no_grad():
        base = regressor(pose, shape, style, None, root)[0]
        later = pose.clone()
        later[:, t + 1:] += 0.3  # every later frame, root rotation included
        later_root = root.clone()
        later_root[:, t + 1:] += 0.05
        changed = regressor(later, shape, style, None, later_root)[0]
        earlier = pose.clone()
        earlier[:, t - 3, 9] += 0.3  # one earlier frame, three frames back: beyond the finite differences
        history = regressor(earlier, shape, style, None, root)[0]
    assert torch.equal(changed[:, :t + 1], base[:, :t + 1]), "frames after t changed the prediction at t or before"
    assert (changed[:, t + 1:] - base[:, t + 1:]).abs().max() > 1e-3, "the later frames should change their own predictions"
    assert (history[:, t] - base[:, t]).abs().max() > 1e-4, "the state should carry frame t-3 to frame t"
    # the descriptor on its own: velocities and accelerations are backward differences
    time = torch.arange(frames, dtype=torch.float32)[None] / FPS
    gamma, gamma_later = (motion_descriptor(p, time, root, torch.arange(3, POSE_SIZE)) for p in (pose, later))
    assert torch.equal(gamma[:, :t + 1], gamma_later[:, :t + 1])
    theta = pose[0, :, 9]
    velocity = gamma[0, :, 57 + 6]  # d theta / dt follows the 57 theta entries; entry 9 is the 7th (0-2: the root)
    torch.testing.assert_close(velocity[1:], (theta[1:] - theta[:-1]) * FPS)


def test_windows_cover_every_frame_and_the_last_one_ends_each_sequence() -> None:
    windows = sequence_windows([5, 40, 33], window=16, stride=8)
    assert windows[0].tolist() == [0, 0, 5], "a short sequence is one window of its own length"
    for s, n in ((1, 40), (2, 33)):
        mine = windows[windows[:, 0] == s]
        covered = np.zeros(n, bool)
        for _, start, length in mine:
            assert length == 16 and start + length <= n
            covered[start:start + length] = True
        assert covered.all() and mine[:, 1].max() == n - 16
    with pytest.raises(ValueError, match="window and stride must be >= 1"):
        sequence_windows([4], window=0, stride=1)


def _lagged_frames(sequences: int, frames: int) -> tuple[FrameArrays, np.ndarray]:
    """Frames whose latent follows an exponentially lagged pose angle: a function of the
    motion so far, which no function of the current frame alone reproduces."""
    poses, latents, seq, index = [], [], [], []
    for s in range(sequences):
        pose = _poses(frames, seed=10 + s)
        lag = np.empty(frames, np.float32)
        lag[0] = pose[0, 9]
        for f in range(1, frames):
            lag[f] = lag[f - 1] + 0.3 * (pose[f, 9] - lag[f - 1])
        latents.append(np.stack([lag, np.sin(3 * lag), pose[:, 20], lag * pose[:, 44]], axis=1))
        poses.append(pose)
        seq.append(np.full(frames, s))
        index.append(np.arange(frames))
    n = sequences * frames
    data = FrameArrays(pose=np.concatenate(poses), shape=np.full((n, SHAPE_SIZE), 0.5, np.float32),
                       style=np.full((n, STYLE_SIZE), 0.1, np.float32), displacements=np.zeros((n, 1, 3), np.float32),
                       pair_id=np.zeros(n, np.int64), sequence=np.concatenate(seq), frame_index=np.concatenate(index))
    return data, np.concatenate(latents).astype(np.float32)


def test_windows_of_a_tiny_motion_set_train_the_gru_until_it_fits(tmp_path) -> None:
    from learn.collision_aware.train import train_recurrent_regressor

    data, latent = _lagged_frames(sequences=3, frames=40)
    hyper = {"lr": 1e-2, "weight_decay": 0.0, "batch_size": 8, "epochs": 100, "hidden_size": 32, "dropout": 0.0,
             "layers": 1, "window": 16, "stride": 4, "velocity_weight": 1.0, "acceleration_weight": 1.0}
    regressor = train_recurrent_regressor(data, latent, np.array(MOVING), FPS, run_dir=tmp_path,
                                          hyperparameters=hyper, seed=0, progress=False)
    with open(tmp_path / "regressor_loss.csv") as handle:
        losses = [float(row["train_loss"]) for row in csv.DictReader(handle)]  # the epoch's mean Eq. 18 loss
    assert losses[-1] < 0.15 * losses[0], f"window loss fell only from {losses[0]:.3f} to {losses[-1]:.3f}"
    # whole sequences run from their first frame (the state carried past the 16-frame windows)
    rows = sequence_rows(data.sequence, data.frame_index)
    with torch.no_grad():
        pose = torch.as_tensor(np.stack([data.pose[r] for r in rows]))
        shape = torch.as_tensor(np.stack([data.shape[r] for r in rows]))
        style = torch.as_tensor(np.stack([data.style[r] for r in rows]))
        predicted = regressor(pose, shape, style)[0].reshape(-1, LATENT_SIZE).numpy()
    error = np.abs(predicted - latent).sum(1).mean()
    spread = np.abs(latent - latent.mean(0)).sum(1).mean()
    assert error < 0.15 * spread, f"the fitted GRU is off by {error:.3f} (L1 per frame) on its own sequences, spread {spread:.3f}"


def _tiny_model(regressor: RecurrentLatentRegressor):
    from learn.collision_aware.fields import DiffusedBody
    from learn.collision_aware.model import CollisionAwareModel
    from learn.collision_aware.vae import GarmentVAE

    vae = GarmentVAE(10, np.zeros((10, 3)), 0.01, latent_size=LATENT_SIZE, hidden_size=8)
    fields = DiffusedBody(3, [0.5], [0.5], hidden_size=8, layers=1, frequencies=1, scale=0.5)
    template = {"skinning_weights": np.full((10, 3), 1 / 3, np.float32), "body_vertex_index": np.zeros(10, np.int64),
                "rest_vertices": np.zeros((10, 3), np.float32)}
    return CollisionAwareModel(regressor, vae, fields, template, {"backend": "anny", "path": None})


def test_sequences_run_in_frame_order_whatever_order_their_frames_come_in() -> None:
    model = _tiny_model(_regressor(seed=3))
    data, _ = _lagged_frames(sequences=3, frames=7)
    root = np.random.default_rng(0).normal(0, 0.01, (data.frame_count, 3)).astype(np.float32)
    latent = model.sequence_latents(data.pose, data.shape, data.style, data.sequence, data.frame_index, root)
    alone = [model.sequence_latents(data.pose[r], data.shape[r], data.style[r], data.sequence[r], data.frame_index[r],
                                    root[r]) for r in sequence_rows(data.sequence, data.frame_index)]
    np.testing.assert_allclose(latent, np.concatenate(alone), atol=1e-6)  # sequences padded together = run alone
    shuffled = np.random.default_rng(1).permutation(data.frame_count)
    again = model.sequence_latents(data.pose[shuffled], data.shape[shuffled], data.style[shuffled],
                                   data.sequence[shuffled], data.frame_index[shuffled], root[shuffled])
    np.testing.assert_allclose(again, latent[shuffled], atol=1e-6)
    # forward reads its rows as one sequence of consecutive frames: the first sequence's run
    with torch.no_grad():
        first = model.latent(*(torch.as_tensor(a[:7]) for a in (data.pose, data.shape, data.style))).numpy()
    no_root = model.sequence_latents(data.pose[:7], data.shape[:7], data.style[:7], data.sequence[:7], data.frame_index[:7])
    np.testing.assert_allclose(first, no_root, atol=1e-6)


def test_cli_trains_the_gru_on_a_motion_dataset_then_evaluates_and_predicts(tmp_path, anny_body, capsys) -> None:
    from collision_aware_data import write_band_dataset, write_tiny_config

    from learn.collision_aware.train import load_collision_aware
    from pipelines.cli import main

    data = tmp_path / "motion"
    write_band_dataset(data, anny_body, splits={"train_train": 2, "test_test": 1}, frames_per_task=6, motion_fps=FPS)
    run = tmp_path / "run"
    posed = write_tiny_config(tmp_path / "posed.yaml", layers=1, posed_collision=10.0)
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--config", posed,
                 "--epochs", "2", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "regressor.posed_collision is for the mlp regressor" in err and "Traceback" not in err, err
    assert not (run / "fields.pt").exists(), "no stage should run before the posed term's regressor is checked"
    config = write_tiny_config(tmp_path / "tiny.yaml", layers=1, window=4, stride=2)
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--config", config,
                 "--epochs", "2", "--no-progress"]) == 0
    model = load_collision_aware(run / "collision_aware_model.pt", body=anny_body)
    assert model.recurrent and model.config["regressor_kind"] == "gru" and model.regressor.config["fps"] == FPS
    assert main(["evaluate", str(run), "--data", str(data), "--postprocess-frames", "1", "--renders", "1"]) == 0
    report = json.loads((run / "evaluation" / "evaluation.json").read_text())
    metrics = report["splits"]["test_test"]["collision_aware"]
    assert metrics["frames"] == 6
    for key in ("unposed_error_mm", "posed_error_mm", "collision_rate", "collision_rate_postprocessed"):
        assert np.isfinite(metrics[key]), (key, metrics)
    assert report["timing"]["collision_aware"]["cpu"]["ms_per_frame_batch_1"] > 0

    from learn.data import DrapeDataset
    from learn.tailornet.evaluate import evaluate_split
    from learn.tailornet.train import frame_arrays_from_dataset

    frames = frame_arrays_from_dataset(DrapeDataset(data, "test_test", frequencies=False))
    in_order = evaluate_split(model, frames, postprocess=False)["unposed_error_mm"]
    assert in_order == pytest.approx(metrics["unposed_error_mm"], rel=1e-5), "evaluate runs the sequence in order"
    reversed_rows = np.arange(frames.frame_count)[::-1].copy()  # the harness orders frames by frame_index itself
    assert evaluate_split(model, frames.subset(reversed_rows), postprocess=False)["unposed_error_mm"] == pytest.approx(in_order, rel=1e-5)

    motion = tmp_path / "motion.npy"
    np.save(motion, frames.pose)
    capsys.readouterr()
    assert main(["predict", str(run), "--learner", "collision_aware", "--style=" + ",".join(map(str, frames.style[0])),
                 "--shape=" + ",".join(map(str, frames.shape[0])), "--pose", str(motion), "--unposed",
                 "--out", str(tmp_path / "pred.obj")]) == 0
    written = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["out"]
    assert len(written) == 6 and all((tmp_path / f"pred_{k:04d}.obj").is_file() for k in range(6))
    import trimesh

    last = np.asarray(trimesh.load(tmp_path / "pred_0005.obj", process=False).vertices)
    expected = model.predict_frames(frames.pose, frames.shape, frames.style, np.zeros(6, np.int64), np.arange(6))[-1]
    np.testing.assert_allclose(last, expected.numpy(), atol=1e-5)  # the sequence's last frame, state carried


def test_gru_asked_for_a_quasi_static_dataset_exits_2_naming_the_option(tmp_path, anny_body, capsys) -> None:
    from collision_aware_data import write_band_dataset

    from pipelines.cli import main

    data = tmp_path / "static"
    write_band_dataset(data, anny_body, splits={"train": 1}, frames_per_task=2)
    run = tmp_path / "run"
    capsys.readouterr()
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--regressor", "gru",
                 "--epochs", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--regressor gru" in err and "quasi-static" in err and "Traceback" not in err, err
    assert not (run / "fields.pt").exists(), "no stage should run before the regressor kind is checked"
    assert main(["train", "baseline", "--data", str(data), "--out", str(tmp_path / "b"), "--regressor", "mlp"]) == 2
    assert "--regressor applies to collision_aware only" in capsys.readouterr().err
    config = tmp_path / "voxel.yaml"
    config.write_text("sdf: {kind: voxel}\n")
    assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--config", str(config),
                 "--epochs", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "sdf.kind must be grid or mlp, got 'voxel'" in err and "Traceback" not in err, err
    assert not (run / "fields.pt").exists(), "no stage should run before the SDF kind is checked"
    for text, message in (("projection: {warm_lr: -1.0}", "projection.warm_lr must be > 0 (got -1.0)"),
                          ("projection: {steps: -5}", "projection.steps must be >= 0 (got -5)"),
                          ("projection: {steps: ten}", "projection.steps must be an integer (got 'ten')"),
                          ("projection: {batch_sequences: 0}", "projection.batch_sequences must be an integer >= 1 (got 0)"),
                          ("fields: {data_share: 1.5}", "fields.data_share must be in [0, 1] (got 1.5)"),
                          ("fields: {shape_basis: 999}", "fields.shape_basis must be in [0, fields.shapes = 512]"),
                          ("regressor: {posed_collision: -1.0}", "regressor.posed_collision must be >= 0 (got -1.0)")):
        config.write_text(text + "\n")
        assert main(["train", "collision-aware", "--data", str(data), "--out", str(run), "--config", str(config),
                     "--epochs", "1", "--no-progress"]) == 2, text
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err and "Traceback" not in err, err
        assert not (run / "fields.pt").exists(), f"no stage should run before {text} is checked"
