"""Seed 001's regularization split: held-out frames that pick the epoch a run keeps.

Seed 001 (section 7) holds 2k of its 20k poses out of training, "a regularization set (2K
samples to prevent the network from overfitting)", apart from the 2k test poses. A dataset
made with ``poses.regularization_count`` has them as split ``regularization``
(:mod:`pipelines.dataset_plan`). After every epoch the learner's training loss is evaluated
on those frames (eval mode: batch norm's running statistics, no gradient), and the model of
the epoch with the lowest loss is the one saved as ``<stage>_model.pt``: early stopping as
model selection (the run goes through its epochs; the best one is kept).

Files: ``<run>/<stage>_regularization.csv`` (epoch, loss) and ``<run>/<stage>_best.pt``
(the best epoch's model state, written atomically when the loss improves), so a run that
is stopped and resumed keeps the best epoch it had seen.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable
from pathlib import Path

import torch

from learn.tailornet.train import atomic_save, load_checkpoint

SPLIT = "regularization"
"""The split name (``pipelines.dataset_plan.REGULARIZATION_SPLIT``)."""


class BestEpoch:
    """``after_epoch`` hook of :func:`learn.tailornet.train.run_epochs`: scores each epoch
    with ``loss_fn(model) -> float`` (the mean loss over the regularization frames) and keeps
    the state of the lowest. ``writes``: whether this process writes the files (rank 0)."""

    def __init__(self, stage: str, run_dir: str | os.PathLike[str], loss_fn: Callable[[torch.nn.Module], float], *,
                 writes: bool = True) -> None:
        self.loss_fn, self.writes = loss_fn, writes
        self.log_path = Path(run_dir) / f"{stage}_regularization.csv"
        self.best_path = Path(run_dir) / f"{stage}_best.pt"
        self.epoch, self.loss, self.state = 0, float("inf"), None
        self._started = False

    def _resume(self, epoch: int) -> None:
        """Before the first epoch this process runs: the best of the epochs before ``epoch``
        (a resumed run's), dropping what a stopped run logged for the epochs it repeats."""
        self._started = True
        if self.best_path.is_file():
            saved = load_checkpoint(self.best_path)
            if int(saved["epoch"]) < epoch:
                self.epoch, self.loss, self.state = int(saved["epoch"]), float(saved["loss"]), saved["model_state"]
        if not self.writes:
            return
        rows = []
        if self.log_path.is_file() and epoch > 1:
            with self.log_path.open() as handle:
                rows = [r for r in list(csv.reader(handle))[1:] if r and int(r[0]) < epoch]
        with self.log_path.open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["epoch", "regularization_loss"])
            writer.writerows(rows)

    def __call__(self, model: torch.nn.Module, epoch: int) -> None:
        if not self._started:
            self._resume(epoch)
        was_training = model.training
        model.eval()
        with torch.no_grad():
            loss = float(self.loss_fn(model))
        model.train(was_training)
        if self.writes:
            with self.log_path.open("a", newline="") as handle:
                csv.writer(handle).writerow([epoch, f"{loss:.8g}"])
        if loss < self.loss:
            self.epoch, self.loss = epoch, loss
            self.state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
            if self.writes:
                atomic_save({"epoch": epoch, "loss": loss, "model_state": self.state}, self.best_path)

    def restore(self, model: torch.nn.Module) -> dict:
        """Loads the best epoch's state into ``model`` (from the file when this process ran no
        epoch, e.g. a finished run resumed); returns ``{"epoch", "loss"}`` (epoch 0: none)."""
        if self.state is None and self.best_path.is_file():
            saved = load_checkpoint(self.best_path)
            self.epoch, self.loss, self.state = int(saved["epoch"]), float(saved["loss"]), saved["model_state"]
        if self.state is not None:
            model.load_state_dict(self.state)
        return {"epoch": self.epoch, "loss": self.loss}
