"""Data-parallel training (learn.distributed) on the CPU: 2 processes with gloo against 1.

The 2-process run deals each global batch of 3 frames out over the ranks (2 + 1 frames, and a
last batch of 1 frame leaves rank 1 a zero-share placeholder), sums the share-weighted gradients
and steps. Its parameters must be bitwise identical on both ranks, and equal to one process's to
float32 rounding: the gradient sum runs in another order (two partial sums instead of one), which
moves the parameters by ~1e-7 of their size after a few Adam steps; 1e-5 absolute leaves room
for Adam's normalised steps without hiding a wrong weighting (a plain mean of the two ranks'
gradients moves them by > 1e-4, checked below). Checkpoints resume on the other process count.
"""
from __future__ import annotations

import os
import socket
from pathlib import Path

import numpy as np
import pytest
import torch

from learn.tailornet.train import FrameArrays, load_checkpoint, train_baseline

FRAMES, VERTICES, POSE = 10, 12, 6
HYPER = {"baseline": {"hidden_size": 16, "dropout": 0.0, "batch_size": 3, "lr": 1e-3, "weight_decay": 0.0},
         "model": {"checkpoint_interval_s": 0.0, "shape_components": 2, "style_components": 2}}
TOLERANCE = 1e-5


def _frames() -> FrameArrays:
    rng = np.random.default_rng(7)
    pose = rng.normal(size=(FRAMES, POSE)).astype(np.float32)
    shape = rng.normal(size=(FRAMES, 2)).astype(np.float32)
    style = rng.normal(size=(FRAMES, 2)).astype(np.float32)
    displacements = (0.01 * np.tanh(pose[:, :3])[:, None, :] + 0.001 * rng.normal(size=(FRAMES, VERTICES, 3)))
    return FrameArrays(pose=pose, shape=shape, style=style, displacements=displacements.astype(np.float32),
                       pair_id=np.zeros(FRAMES, np.int64))


def _train(run_dir: Path, epochs: int) -> torch.Tensor:
    hyper = {k: dict(v) for k, v in HYPER.items()}
    hyper["baseline"]["epochs"] = epochs
    model = train_baseline(_frames(), np.arange(POSE), run_dir=run_dir, hyperparameters=hyper, seed=0, progress=False)
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()])


def _worker(rank: int, world: int, port: int, root: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank),
                      WORLD_SIZE=str(world))
    torch.set_num_threads(1)
    from learn import distributed

    assert distributed.init("cpu") == "cpu" and distributed.active()
    root = Path(root)
    for name, epochs in (("two", 2), ("one_then_two", 4)):
        params = _train(root / name, epochs)
        gathered = [torch.empty_like(params) for _ in range(world)]
        torch.distributed.all_gather(gathered, params)
        if rank == 0:
            torch.save({"params": params, "same_on_every_rank": all(torch.equal(g, params) for g in gathered),
                        "log_rows": len((root / name / "baseline_loss.csv").read_text().splitlines())},
                       root / f"{name}.result")
    # the share weighting matters: with every rank's gradient averaged alike the run differs
    distributed._state["data_parallel"] = True
    real = distributed.shard

    def unweighted(batch):
        out = real(batch)
        distributed._state["share"] = None
        return out

    distributed.shard = unweighted
    params = _train(root / "unweighted", 2)
    if rank == 0:
        torch.save({"params": params}, root / "unweighted.result")
    distributed.finish()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    if not torch.distributed.is_available() or not torch.distributed.is_gloo_available():
        pytest.skip("torch.distributed with gloo is not available")
    root = tmp_path_factory.mktemp("dp")
    # one process trains 2 epochs of the run that two processes resume to 4
    _train(root / "one_then_two", 2)
    torch.multiprocessing.spawn(_worker, args=(2, _free_port(), str(root)), nprocs=2, join=True)
    return root


def test_two_processes_keep_identical_parameters_equal_to_one_process(runs, tmp_path):
    two = torch.load(runs / "two.result")
    assert two["same_on_every_rank"], "the ranks' parameters diverged"
    one = _train(tmp_path / "one", 2)
    assert (two["params"] - one).abs().max() < TOLERANCE, float((two["params"] - one).abs().max())
    unweighted = torch.load(runs / "unweighted.result")["params"]
    assert (unweighted - one).abs().max() > 10 * TOLERANCE, "the test cannot tell a wrong gradient weighting"
    # rank 0 alone wrote the log: one header and one row per epoch
    assert two["log_rows"] == 3


def test_checkpoints_resume_on_another_process_count(runs, tmp_path):
    reference = _train(tmp_path / "four", 4)
    # 1 process -> 2 processes
    resumed = torch.load(runs / "one_then_two.result")
    assert resumed["same_on_every_rank"]
    assert (resumed["params"] - reference).abs().max() < TOLERANCE
    # 2 processes -> 1 process: the checkpoint holds no world size
    checkpoint = load_checkpoint(runs / "two" / "baseline.pt")
    assert checkpoint["epoch"] == 2 and "world_size" not in str(sorted(checkpoint))
    resumed_alone = _train(runs / "two", 4)
    assert (resumed_alone - reference).abs().max() < TOLERANCE
    assert load_checkpoint(runs / "two" / "baseline.pt")["epoch"] == 4


def test_shard_deals_a_batch_and_is_identity_alone():
    from learn import distributed

    batch = torch.arange(7)
    assert torch.equal(distributed.shard(batch), batch)
    assert distributed.sum_over_ranks(2.5) == 2.5 and distributed.sum_over_ranks({"a": 1.0}) == {"a": 1.0}
