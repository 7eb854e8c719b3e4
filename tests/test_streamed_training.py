"""Training from a streamed split (learn.streamed_split, learn.batches) against the in-memory path.

Without shuffling and with workers reading in the training process, a streamed epoch's batches
are the in-memory path's (consecutive frames of the split, in its order), so TailorNet's baseline
and LF stages end with bitwise equal parameters; HF trains on its prototype pairs' frames read into
memory and equals the in-memory HF exactly. With shuffling and forked workers the frame order
necessarily differs (shards are dealt to workers, which fill their own batches): each epoch then
yields every frame exactly once. 2 gloo ranks with unequal shard counts finish and agree.
"""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from data_manifest.synthetic import write_synthetic_dataset
from learn.batches import StreamBatches
from learn.data import DrapeDataset
from learn.streamed_split import StreamedSplit, choose_data_mode
from learn.tailornet.baseline import baseline_model
from learn.tailornet.lf import low_frequency_model
from learn.tailornet.train import fit_tailornet, frame_arrays_from_dataset, train_stage

STAGE = {"lr": 1e-3, "weight_decay": 1e-6, "batch_size": 4, "epochs": 3, "shuffle": False,
         "checkpoint_interval_s": 1e9}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """5 shards of 3 frames (50-vertex tube), so a batch of 4 spans shards."""
    root = tmp_path_factory.mktemp("stream")
    write_synthetic_dataset(root, splits={"train": 5, "test": 1}, frames_per_task=3, seed=5)
    return root


@pytest.fixture(scope="module")
def memory(dataset):
    ds = DrapeDataset(dataset, "train", workers=1)
    ds.reader.close()
    return frame_arrays_from_dataset(ds)


def _params(model: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()])


def _open_files() -> int:
    return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_FILE)


@pytest.mark.parametrize("stage, target", [("baseline", "displacements"), ("lf", "low_frequency")])
def test_unshuffled_stream_trains_the_same_parameters_as_memory(dataset, memory, tmp_path, stage, target):
    split = StreamedSplit(dataset, "train", workers=0)
    assert split.frame_count == memory.frame_count == 15
    np.testing.assert_array_equal(split.pair_id, memory.pair_id)
    if target == "low_frequency":
        split.prepare_low_frequency()
    build = baseline_model if stage == "baseline" else low_frequency_model
    results = []
    for name, data in (("memory", memory), ("stream", split)):
        torch.manual_seed(0)
        model = build(memory.vertex_count, np.arange(memory.pose.shape[1]), hidden_size=16, dropout=0.0)
        start = _params(model).clone()
        trained = train_stage(stage, model, data, target, run_dir=tmp_path / name, hyperparameters=STAGE,
                              fingerprint=None, progress=False)
        results.append(_params(trained))
    assert (results[0] - start).abs().max() > 1e-4, "training moved nothing"
    torch.testing.assert_close(results[1], results[0], atol=0, rtol=0)
    logs = [np.loadtxt(tmp_path / n / f"{stage}_loss.csv", delimiter=",", skiprows=1)[:, 1] for n in ("memory", "stream")]
    np.testing.assert_array_equal(logs[1], logs[0])


def test_streamed_tailornet_prototypes_equal_memory(dataset, memory, tmp_path):
    """fit_tailornet on a streamed split: g and the prototype choice read one frame per pair, HF its
    prototype pairs' frames (the same values, the same per-prototype order draws: equal HF); LF
    streams (shuffled, another order: finite, decreasing loss)."""
    hyper = {stage: {"epochs": 4, "hidden_size": 16, "batch_size": 4, "dropout": 0.0}
             for stage in ("lf", "hf", "shape_style")}
    hyper["model"] = {"prototype_count": 2, "checkpoint_interval_s": 1e9}
    split = StreamedSplit(dataset, "train", workers=0)
    models = {name: fit_tailornet(data, split.template["faces"], run_dir=tmp_path / name, hyperparameters=hyper,
                                  progress=False)
              for name, data in (("memory", memory), ("stream", split))}
    assert split.low_frequency_ready, "fit_tailornet prepared the streamed low-frequency cache"
    assert (tmp_path / "memory" / "prototypes.json").read_text() == (tmp_path / "stream" / "prototypes.json").read_text()
    for part in ("high_frequency", "shape_style"):
        torch.testing.assert_close(_params(getattr(models["stream"], part)), _params(getattr(models["memory"], part)),
                                   atol=0, rtol=0, msg=part)
    lf = np.loadtxt(tmp_path / "stream" / "lf_loss.csv", delimiter=",", skiprows=1)[:, 1]
    assert np.isfinite(lf).all() and lf[-1] < lf[0]


def test_shuffled_forked_epochs_yield_every_frame_once_without_open_files(dataset, monkeypatch):
    split = StreamedSplit(dataset, "train", workers=2)
    source = StreamBatches(split, ("frame", "pose"), batch_size=4, shuffle=True)
    at_fork = []
    real_iter = torch.utils.data.DataLoader.__iter__

    def counting_iter(loader):
        at_fork.append(_open_files())
        return real_iter(loader)

    monkeypatch.setattr(torch.utils.data.DataLoader, "__iter__", counting_iter)
    generator = torch.Generator().manual_seed(0)
    epochs = [[int(f) for batch in source.epoch(generator, None) for f in batch["frame"]] for _ in range(2)]
    assert at_fork == [0, 0], "an HDF5 file was open in the parent when the workers forked"
    for frames in epochs:
        assert sorted(frames) == list(range(15))
    assert epochs[0] != epochs[1], "epochs reshuffle"


def test_data_mode_choice():
    assert choose_data_mode("auto", 40, 100) == "memory"
    assert choose_data_mode("auto", 60, 100) == "stream"
    assert choose_data_mode("memory", 10**15, 100) == "memory"
    with pytest.raises(ValueError, match="data mode must be one of auto, memory, stream \\(got 'disk'\\)"):
        choose_data_mode("disk", 1, 1)


@pytest.mark.parametrize("learner, mode, expected", [
    ("baseline", "disk", "--data-mode 'disk' is not a data mode; expected one of auto, memory, stream"),
    ("collision_aware", "stream", "--data-mode stream: collision_aware trains from memory only"),
    ("gcvae", "stream", "--data-mode stream: gcvae trains from memory only"),
])
def test_bad_data_mode_exits_2_with_one_line(dataset, tmp_path, capsys, learner, mode, expected):
    from pipelines.cli import main

    assert main(["train", learner, "--data", str(dataset), "--out", str(tmp_path / "run"), "--data-mode", mode]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and expected in err, err


# -- two gloo ranks, unequal shard counts ---------------------------------------------------------------


def _rank(rank: int, world: int, port: int, root: str, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank),
                      WORLD_SIZE=str(world))
    torch.set_num_threads(1)
    from learn import distributed

    distributed.init("cpu", timeout_s=60.0)  # a collective one rank never enters fails here instead of hanging
    split = StreamedSplit(root, "train", workers=0)
    source = StreamBatches(split, ("pose",), batch_size=4, shuffle=True)
    dealt = source.dataset(0, rank, world)
    counts = {"steps": source.steps(dealt, world),
              "own": [-(-sum(dealt.frames_for(r, 0, 1)) // 2) for r in range(world)]}
    torch.manual_seed(0)
    model = baseline_model(split.vertex_count, np.arange(split.pose.shape[1]), hidden_size=16, dropout=0.0)
    hyper = {**STAGE, "shuffle": True, "epochs": 2}
    trained = train_stage("baseline", model, split, "displacements", run_dir=Path(out) / "run", hyperparameters=hyper,
                          fingerprint=None, progress=False)
    params = _params(trained)
    gathered = [torch.empty_like(params) for _ in range(world)]
    torch.distributed.all_gather(gathered, params)
    if rank == 0:
        torch.save({"same": all(torch.equal(g, params) for g in gathered), "params": params, "counts": counts},
                   Path(out) / "result.pt")
    distributed.finish()


def test_two_ranks_with_unequal_shard_counts_finish(dataset, tmp_path, spawn_ranks):
    spawn_ranks(_rank, str(dataset), str(tmp_path), what="the 2-rank streamed training")
    result = torch.load(tmp_path / "result.pt")
    # 5 shards of 3 frames, 2 per rank per step: rank 0 reads 3 shards (5 batches), rank 1 two (3)
    assert result["counts"] == {"steps": 5, "own": [5, 3]}, result["counts"]
    assert result["same"], "the ranks' parameters diverged"
    assert torch.isfinite(result["params"]).all()
    log = np.loadtxt(tmp_path / "run" / "baseline_loss.csv", delimiter=",", skiprows=1)
    assert log.shape == (2, 3) and np.isfinite(log[:, 1]).all()


def test_streamed_pca_moments_give_the_svd_basis():
    """The PCA basis from streamed moments (OffsetMoments, batches of 7) equals offset_basis's SVD on
    all frames at once, signs included (both orient each component), to float64 rounding of the
    Gram matrix's eigenvectors (1e-6 on unit vectors for well separated components)."""
    from learn.uvimage.pca import OffsetMoments, offset_basis

    rng = np.random.default_rng(1)
    scales = np.array([8.0, 4.0, 2.0, 1.0, 0.5])[:, None]
    local = (rng.normal(size=(40, 5)) @ (scales * rng.normal(size=(5, 30))) + 0.01 * rng.normal(size=(40, 30)))
    local = torch.as_tensor(local.reshape(40, 10, 3) + 0.3)
    moments = OffsetMoments(10)
    for begin in range(0, 40, 7):
        moments.add(local[begin:begin + 7])
    streamed, reference = moments.basis(4), offset_basis(local, 4)
    for got, expected, name in zip(streamed, reference, ("mean", "basis", "singular values")):
        torch.testing.assert_close(got, expected, atol=1e-6, rtol=1e-6, msg=name)
