"""A learner's optimizer step replayed as a CUDA graph (learn/common/training_step.py) trains the
same parameters as the eager step; the TailorNet stages take it on GPUs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from learn.common.training_step import TrainingStep
from learn.tailornet.train import add_low_frequency, fit_baseline, train_hf

from test_tailornet_train import FINGERPRINT, POSE_SIZE, _pairs, make_frames

HAS_CUDA = torch.cuda.is_available()
needs_cuda = pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device")


def _regression(device: str, *, graph: bool, steps: int, batch: int, last: int, dropout: float = 0.0,
                seed: int = 0) -> tuple[torch.nn.Module, TrainingStep, list[float]]:
    """A small MLP fitted by ``steps`` batches of ``batch`` frames, then one of ``last`` frames."""
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(5, 32), torch.nn.ReLU(), torch.nn.Dropout(dropout),
                              torch.nn.Linear(32, 7)).to(device)
    cuda = torch.device(device).type == "cuda"
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-2, fused=cuda, capturable=cuda)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(200, 5, generator=g).to(device)
    y = torch.sin(0.5 * x @ torch.randn(5, 7, generator=g).to(device))
    order = torch.randint(0, 200, (steps * batch + last,), generator=g).to(device)

    def loss_of(inputs):
        index = inputs["index"]
        return (net(x[index]) - y[index]).abs().mean()

    step = TrainingStep(loss_of, optimizer, graph=graph)
    losses = [float(step({"index": order[i * batch:(i + 1) * batch]})) for i in range(steps)]
    losses.append(float(step({"index": order[steps * batch:]})))  # another shape: eager
    return net, step, losses


def test_off_cuda_every_step_is_eager_and_trains() -> None:
    net, step, losses = _regression("cpu", graph=True, steps=120, batch=16, last=5)
    assert step.replays == 0 and step.calls == 121
    assert np.mean(losses[-6:-1]) < 0.6 * np.mean(losses[:5])


def test_eager_steps_must_be_positive() -> None:
    with pytest.raises(ValueError, match="eager_steps"):
        TrainingStep(lambda inputs: torch.zeros(()), torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0),
                     eager_steps=0)


@needs_cuda
def test_graph_replays_train_the_eager_parameters() -> None:
    graphed, step, g_losses = _regression("cuda", graph=True, steps=20, batch=16, last=5)
    eager, eager_step, e_losses = _regression("cuda", graph=False, steps=20, batch=16, last=5)
    assert step.replays == 20 - step.eager_steps and eager_step.replays == 0
    np.testing.assert_allclose(g_losses, e_losses, rtol=1e-5, atol=1e-7)
    for a, b in zip(graphed.parameters(), eager.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


@needs_cuda
def test_graph_with_dropout_is_reproducible_and_trains() -> None:
    a, step, losses_a = _regression("cuda", graph=True, steps=120, batch=16, last=5, dropout=0.2, seed=3)
    b, _, losses_b = _regression("cuda", graph=True, steps=120, batch=16, last=5, dropout=0.2, seed=3)
    assert step.replays == 120 - step.eager_steps
    assert losses_a == losses_b
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.equal(p, q)
    assert np.mean(losses_a[-6:-1]) < 0.6 * np.mean(losses_a[:5])


@needs_cuda
@pytest.mark.parametrize("stage", ["baseline", "hf"])
def test_tailornet_stage_with_graphs_equals_it_without(tmp_path: Path, stage: str) -> None:
    """No dropout: a stage trained with its steps replayed as graphs ends with the eager stage's
    parameters (the epochs' last batch is partial, so eager and replayed steps mix)."""
    data, faces = make_frames(4, 21, _pairs()[:3])
    add_low_frequency(data, faces, iterations=10)
    models = {}
    for graphs in (True, False):
        hyper = {stage: {"lr": 1e-3, "epochs": 4, "batch_size": 8, "hidden_size": 32, "dropout": 0.0},
                 "model": {"cuda_graphs": graphs}}
        args = dict(hyperparameters=hyper, fingerprint=FINGERPRINT, progress=False, seed=7, device="cuda",
                    run_dir=tmp_path / str(graphs))
        if stage == "baseline":
            models[graphs] = fit_baseline(data, faces, pose_indices=np.arange(POSE_SIZE), **args)
        else:
            models[graphs] = train_hf(data, np.arange(POSE_SIZE), np.array([2, 0, 1]), stacked=True, **args)
    for (name, a), b in zip(models[True].state_dict().items(), models[False].state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=f"{stage} {name} differs with graphs")
