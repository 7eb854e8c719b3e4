"""One optimizer step of a learner (zero the gradients, loss, backward, step), replayed as a CUDA
graph on GPUs.

At the paper's batch of 32 frames a TailorNet network's step is bound by kernel launches, not by
the GPU: ~30 launches (gather, three linear layers and their backward, the fused Adam update) from
Python for ~0.3 ms of memory traffic. Recorded once as a CUDA graph, the step is one launch.

The first ``eager_steps`` calls run eagerly on a side stream (real steps of the training: the
optimizer's state and the libraries' workspaces are set up by them), the next call records the
step as a graph and replays it, and every later call whose inputs have the recorded shapes copies
them into the recorded input tensors and replays. A call with other shapes (an epoch's last,
partial batch) runs eagerly, as does every call where the graph is off (CPU, data parallelism,
``enabled=False``). The gradients of a replay live in the graph's memory; nothing outside the step
may read ``param.grad``.

Dropout inside the graph draws from the default CUDA generator (PyTorch advances its offset on
every replay), so a run is reproducible on one device, but its masks differ from an eager run's.
Without dropout a graphed run equals the eager run to float rounding (tested on CUDA).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping

import torch


class TrainingStep:
    """``step(inputs)``: zero the gradients, ``loss = loss_of(inputs)``, ``loss.backward()``,
    ``optimizer.step()``; returns the loss, detached (its tensor is reused by the next replay: add
    it to an accumulator before the next call).

    Args:
        loss_of: inputs (name -> tensor on the device) -> scalar loss tensor.
        optimizer: the optimizer of the trained parameters; on CUDA it must be ``capturable``
            (Adam's ``capturable=True``) for the graph.
        graph: record and replay a CUDA graph (ignored off CUDA).
        eager_steps: eager steps before the graph is recorded (at least 1).
    """

    def __init__(self, loss_of: Callable[[Mapping[str, torch.Tensor]], torch.Tensor],
                 optimizer: torch.optim.Optimizer, *, graph: bool = True, eager_steps: int = 3) -> None:
        if eager_steps < 1:
            raise ValueError(f"eager_steps must be >= 1, got {eager_steps}")
        self.loss_of, self.optimizer = loss_of, optimizer
        self.graph_enabled = bool(graph) and torch.cuda.is_available()
        self.eager_steps = int(eager_steps)
        self.calls = 0
        self.replays = 0
        self._graph: torch.cuda.CUDAGraph | None = None
        self._inputs: dict[str, torch.Tensor] | None = None  # the recorded input tensors
        self._loss: torch.Tensor | None = None  # the recorded loss tensor

    def _eager(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        self.optimizer.zero_grad(set_to_none=True)
        loss = self.loss_of(inputs)
        loss.backward()
        self.optimizer.step()
        return loss.detach()

    def _graphable(self, inputs: Mapping[str, torch.Tensor]) -> bool:
        if not self.graph_enabled or not all(t.is_cuda for t in inputs.values()):
            return False
        if self._inputs is None:
            return True
        return (inputs.keys() == self._inputs.keys()
                and all(inputs[k].shape == t.shape and inputs[k].dtype == t.dtype for k, t in self._inputs.items()))

    def __call__(self, inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        self.calls += 1
        if not self._graphable(inputs):
            return self._eager(inputs)
        if self._inputs is None:
            self._inputs = {k: torch.empty_like(t) for k, t in inputs.items()}
        for k, t in inputs.items():
            self._inputs[k].copy_(t, non_blocking=True)
        if self._graph is None and self.calls <= self.eager_steps:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                loss = self._eager(self._inputs)
            torch.cuda.current_stream().wait_stream(side)
            return loss
        if self._graph is None:
            self.optimizer.zero_grad(set_to_none=True)  # the replays' gradients live in the graph's pool
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                loss = self.loss_of(self._inputs)
                loss.backward()
                self.optimizer.step()
                self._loss = loss.detach()
            self._graph = graph
        self._graph.replay()
        self.replays += 1
        return self._loss
