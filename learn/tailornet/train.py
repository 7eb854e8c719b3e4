"""Training of TailorNet's networks and of the baseline, as library functions.

Each stage (``shape_style``, ``lf``, ``hf`` (stacked, or ``hf_00`` ... ``hf_{K-1}``, or parts
``hf_<i>of<P>`` trained by different processes: :func:`stages_for_rank`), ``baseline``) is trained
with Adam on an L1 displacement loss, with the authors' hyper-parameters as defaults
(:data:`DEFAULT_HYPERPARAMETERS`, overridable per stage by a dict). A stage saves a
checkpoint after every epoch (model, optimizer, epoch, RNG states, dataset fingerprint)
to ``<run_dir>/<stage>.pt``; calling it again resumes where it stopped and, with the same
seed, reproduces the uninterrupted run exactly. Losses go to ``<run_dir>/<stage>_loss.csv``
and a tqdm bar shows progress.

Checkpoints record the dataset manifest's and the garment template's sha256; resuming or
loading against a different dataset raises :class:`DatasetMismatchError`.

The step loops keep everything on the training device: the stage's inputs and targets are
copied there once, each epoch's shuffled order is one host-to-device copy, batches are
gathered by device-side indexing and the epoch's loss is summed on the device and read once
at the epoch's end. On a GPU each in-memory step (gather, forward, loss, backward, Adam) is
replayed as one CUDA graph (:mod:`learn.common.training_step`; ``model.cuda_graphs: false`` turns
it off): the paper's batches of 32 frames are otherwise bound by kernel launches.
``model.mixed_precision`` runs the forward passes under bf16 autocast (weights, Adam's moments and
the L1 loss stay float32). Each step loop is a plain function of
(model, optimizer, frame order): a data-parallel wrapper of the model (DDP) goes around
``model`` before :func:`run_epochs`, and a per-rank shard of the order replaces
``torch.randperm`` in ``epoch_fn``.

The stages take their batches from :mod:`learn.batches`: in memory as above, or streamed from the
shards when ``data`` is a :class:`learn.streamed_split.StreamedSplit` (docs/streaming.md).
"""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tqdm.auto import tqdm

from learn import distributed
from learn.batches import MemoryBatches, batches_for, is_streamed
from learn.data import FrameArrays
from learn.common.hyperparameters import checked_override
from learn.common.losses import l1_displacement_loss
from learn.common.smoothing import LaplacianSmoother, split_frequencies
from learn.common.training_step import TrainingStep
from learn.tailornet.baseline import baseline_model
from learn.tailornet.hf import HighFrequencyPrototypes, high_frequency_model
from learn.tailornet.lf import DisplacementMLP, low_frequency_model
from learn.tailornet.mixture import DEFAULT_SIGMA
from learn.tailornet.model import TailorNet
from learn.tailornet.pose_mask import garment_pose_joints, pose_feature_indices
from simulate.garment.prototypes import canonical_frame_per_pair, choose_prototypes
from learn.tailornet.shape_style import ShapeStyleModel

if TYPE_CHECKING:
    from learn.streamed_split import StreamedSplit

CHECKPOINT_FORMAT = 1
DEFAULT_CHECKPOINT_INTERVAL_S = 60.0
SAVE_SHARE_INVERSE = 20.0
"""A checkpoint waits at least this many times the last one's write: the stacked HF checkpoint of
the 7.7k t-shirt (K = 20, ~6 GB with Adam's moments) took ~12 s to write on an H200 host; written
in the background, saves still keep the disk busy at most ~5 % of the time."""

# The authors' settings (REFERENCE.md): Adam, batch 32, L1 loss.
DEFAULT_HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    "lf": {"lr": 1e-4, "weight_decay": 1e-6, "batch_size": 32, "epochs": 100, "hidden_size": 1024, "dropout": 0.2},
    "hf": {
        "lr": 1e-4, "weight_decay": 1e-6, "batch_size": 32, "epochs": 800, "hidden_size": 1024, "dropout": 0.2,
        "stacked": True,
    },
    "shape_style": {
        "lr": 1e-3, "weight_decay": 1e-5, "batch_size": 32, "epochs": 400, "hidden_size": 128, "dropout": 0.2,
    },
    "baseline": {
        "lr": 1e-4, "weight_decay": 1e-6, "batch_size": 32, "epochs": 100, "hidden_size": 1024, "dropout": 0.2,
    },
    "model": {
        "prototype_count": 20,
        "sigma": DEFAULT_SIGMA,
        "shape_components": 2,
        "style_components": 2,
        "min_joint_weight_sum": 1.0,
        "pose_mask": True,
        "mixed_precision": False,
        "cuda_graphs": True,
        "smoothing_iterations": 80,
        "smoothing_lambda": 0.15,
        "checkpoint_interval_s": DEFAULT_CHECKPOINT_INTERVAL_S,
        # each frame of the dataset's canonical split (every style-shape combination in the
        # canonical pose) joins LF's and the baseline's training frames this many times, so they
        # learn every combination's fit (0: the split trains g and picks the prototypes only, as
        # TailorNet's paper). On a CPU set (docs/benchmarks.md) 0 / 1 / 10 / 40 left 26.8 / 22.5 /
        # 14.0 / 12.7 mm on test pairs; 40 makes the t-shirt spec's LF and baseline epochs ~29 % longer
        "canonical_repeat": 40,
        # false: g and the prototype choice learn from each training pair's frame closest to the
        # canonical pose even where the dataset has a canonical split (the ablation)
        "use_canonical_split": True,
    },
}


class DatasetMismatchError(ValueError):
    """A checkpoint was trained on another dataset manifest or garment template."""


@dataclass(frozen=True)
class DatasetFingerprint:
    """sha256 of the dataset manifest file and of the garment template arrays."""

    dataset_manifest_sha256: str
    template_sha256: str

    def as_dict(self) -> dict[str, str]:
        return {
            "dataset_manifest_sha256": self.dataset_manifest_sha256,
            "template_sha256": self.template_sha256,
        }


# The dataset layer owns file hashing and the manifest's name; fingerprints reuse both so a
# checkpoint's hashes are exactly what the manifest and validator compute.
from data_manifest.schema import MANIFEST_NAME as MANIFEST_FILE  # noqa: E402
from data_manifest.shard import file_sha256  # noqa: E402


def template_sha256(template: Mapping[str, Any]) -> str:
    """The garment template's sha256, computed as the dataset manifest records it.

    ``template``: mapping with ``faces``, ``rest_vertices``, ``skinning_weights``,
    ``body_vertex_index`` (and optional ``uv``), e.g. ``DatasetReader(root).template``.
    """
    from data_manifest.schema import template_sha256 as manifest_template_sha256

    if not isinstance(template, Mapping) or "faces" not in template:
        raise ValueError(
            f"template must be a mapping with 'faces' (and rest_vertices, skinning_weights, "
            f"body_vertex_index), got {type(template).__name__} with keys "
            f"{sorted(template) if isinstance(template, Mapping) else 'none'}"
        )
    return manifest_template_sha256(template)


def dataset_fingerprint(root: str | os.PathLike[str], template: Mapping[str, Any]) -> DatasetFingerprint:
    """Fingerprint of the dataset at ``root``: sha256 of ``root/manifest.json`` and of
    ``template`` (pass ``DatasetReader(root).template``)."""
    return DatasetFingerprint(file_sha256(Path(root) / MANIFEST_FILE), template_sha256(template))


def check_fingerprint(
    saved: Mapping[str, str] | None,
    expected: DatasetFingerprint | None,
    *,
    source: str,
    require_same_manifest: bool = True,
) -> None:
    """Raise :class:`DatasetMismatchError` when a checkpoint's fingerprint differs."""
    if expected is None:
        return
    if saved is None:
        raise DatasetMismatchError(f"{source} records no dataset fingerprint; cannot check it")
    if saved.get("template_sha256") != expected.template_sha256:
        raise DatasetMismatchError(
            f"{source} was trained on garment template sha256 {saved.get('template_sha256')}, "
            f"but this dataset's template has sha256 {expected.template_sha256}: use a run "
            "trained on this dataset (different garment topology or skinning)"
        )
    if require_same_manifest and saved.get("dataset_manifest_sha256") != expected.dataset_manifest_sha256:
        raise DatasetMismatchError(
            f"{source} was trained on dataset manifest sha256 {saved.get('dataset_manifest_sha256')}, "
            f"but this dataset's manifest has sha256 {expected.dataset_manifest_sha256}: "
            "train into a new run directory, or point --data at the original dataset"
        )


def frame_arrays_from_split(arrays: Mapping[str, np.ndarray]) -> FrameArrays:
    """Build :class:`FrameArrays` from ``DatasetReader.load_split`` output.

    Frames are grouped into style-shape pairs by their (shape, style) values, so pairs
    are found even when one pair spans several tasks or shards.
    """
    for name in ("pose", "shape", "style", "unposed_displacements"):
        if name not in arrays:
            raise ValueError(f"split arrays lack '{name}'; got keys {sorted(arrays)}")
    shape = np.asarray(arrays["shape"], dtype=np.float32)
    style = np.asarray(arrays["style"], dtype=np.float32)
    _, pair_id = np.unique(np.concatenate([shape, style], axis=1), axis=0, return_inverse=True)
    return FrameArrays(
        pose=np.asarray(arrays["pose"], dtype=np.float32),
        shape=shape,
        style=style,
        displacements=np.asarray(arrays["unposed_displacements"], dtype=np.float32),
        pair_id=pair_id.reshape(-1).astype(np.int64),
        posed_vertices=(
            None if arrays.get("posed_vertices") is None else np.asarray(arrays["posed_vertices"], dtype=np.float32)
        ),
        translation=(
            None if arrays.get("body_translation") is None
            else np.asarray(arrays["body_translation"], dtype=np.float32)
        ),
    )


def frame_arrays_from_dataset(dataset: Any) -> FrameArrays:
    """Build :class:`FrameArrays` from a ``learn.data.DrapeDataset`` (or any object with
    tensor/array attributes ``pose``, ``shape``, ``style``, ``displacements``, ``pair`` and
    optional ``low_frequency``, ``posed_vertices``, ``translation``, ``sequence``,
    ``frame_index``, ``root_joint``), reusing its cached
    frequency split."""

    def array(name: str, dtype: Any = np.float32) -> np.ndarray | None:
        value = getattr(dataset, name, None)
        if value is None:
            return None
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        return np.asarray(value, dtype=dtype)

    missing = [n for n in ("pose", "shape", "style", "displacements", "pair") if getattr(dataset, n, None) is None]
    if missing:
        raise ValueError(f"dataset lacks {missing}; expected a learn.data.DrapeDataset-like object")
    return FrameArrays(
        pose=array("pose"), shape=array("shape"), style=array("style"), displacements=array("displacements"),
        pair_id=array("pair", np.int64), low_frequency=array("low_frequency"),
        posed_vertices=array("posed_vertices"), translation=array("translation"),
        sequence=array("sequence", np.int64), frame_index=array("frame_index", np.int64),
        root_joint=array("root_joint"),
    )


def add_low_frequency(
    data: FrameArrays,
    faces: np.ndarray,
    *,
    smoothness: float = 0.15,
    iterations: int = 80,
    chunk: int = 256,
    device: str = "cpu",
) -> FrameArrays:
    """Fill ``data.low_frequency`` by boundary-aware smoothing of the displacements."""
    smoother = LaplacianSmoother(faces, data.vertex_count, smoothness=smoothness, iterations=iterations)
    out = np.empty_like(data.displacements)
    for start in range(0, data.frame_count, chunk):
        block = torch.from_numpy(data.displacements[start : start + chunk]).to(device)
        low, _ = split_frequencies(block, smoother)
        out[start : start + chunk] = low.cpu().numpy()
    data.low_frequency = out
    return data


def concat_frames(parts: Sequence[FrameArrays]) -> FrameArrays:
    """The frames of ``parts`` one after another (pose, shape, style, displacements, pair_id and
    low_frequency where every part has it; the optional per-frame fields are dropped)."""
    def cat(name: str) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(f, name)) for f in parts])

    low = cat("low_frequency") if all(f.low_frequency is not None for f in parts) else None
    return FrameArrays(pose=cat("pose"), shape=cat("shape"), style=cat("style"),
                       displacements=cat("displacements").astype(parts[0].displacements.dtype, copy=False),
                       pair_id=cat("pair_id"), low_frequency=low)


def row_keys(*columns: np.ndarray) -> list[bytes]:
    """One exact key per row of the (N, *) arrays ``columns`` side by side, as float32 bytes: the
    same (shape, style) of two splits gives the same key."""
    both = np.concatenate([np.asarray(c, np.float32).reshape(len(c), -1) for c in columns], axis=1)
    return [row.tobytes() for row in np.ascontiguousarray(both)]


def canonical_training_frames(
    data: FrameArrays, canonical: FrameArrays | None, canonical_pose: np.ndarray | None = None,
) -> tuple[FrameArrays, FrameArrays]:
    """(pair_frames, g_frames) for g and the prototype choice.

    pair_frames: one canonical-pose frame per training pair, in pair-id order (X frames): the
    ``canonical`` split's frame of the pair's (shape, style) where it has one, else the pair's frame
    whose pose is closest to ``canonical_pose``. g_frames: those, and every frame of ``canonical``
    of a style-shape combination that is no training pair (TailorNet's g learns from all its
    A-pose drapes, seed 000 Sec. 4.4)."""
    nearest = data.subset(canonical_frame_per_pair(data.pose, data.pair_id, canonical_pose=canonical_pose))
    if canonical is None or canonical.frame_count == 0:
        return nearest, nearest
    lookup = {key: i for i, key in enumerate(row_keys(canonical.shape, canonical.style))}
    found = [lookup.get(key) for key in row_keys(nearest.shape, nearest.style)]
    displacements = nearest.displacements.copy()
    pose = nearest.pose.copy()
    for pair, row in enumerate(found):
        if row is not None:
            displacements[pair] = canonical.displacements[row]
            pose[pair] = canonical.pose[row]
    pair_frames = FrameArrays(pose=pose, shape=nearest.shape, style=nearest.style, displacements=displacements,
                              pair_id=np.arange(nearest.frame_count, dtype=np.int64))
    others = np.setdiff1d(np.arange(canonical.frame_count), [r for r in found if r is not None])
    extra = canonical.subset(others)
    extra = FrameArrays(pose=extra.pose, shape=extra.shape, style=extra.style, displacements=extra.displacements,
                        pair_id=nearest.frame_count + np.arange(extra.frame_count, dtype=np.int64))
    return pair_frames, concat_frames([pair_frames, extra])


def with_canonical_frames(data: FrameArrays, canonical: FrameArrays | None, repeat: int, faces: np.ndarray,
                          hyper: Mapping[str, Mapping[str, Any]], device: str = "cpu", *,
                          low_frequency: bool = True) -> FrameArrays:
    """``data`` followed by ``repeat`` copies of the ``canonical`` split's frames: LF's and the
    baseline's training frames (``model.canonical_repeat``). With ``low_frequency`` (LF) and
    ``data.low_frequency`` set, the added frames get theirs; otherwise the result has none (the
    baseline trains on the displacements). ``data`` itself when there is nothing to add."""
    if canonical is None or canonical.frame_count == 0 or repeat <= 0:
        return data
    extra = FrameArrays(pose=canonical.pose, shape=canonical.shape, style=canonical.style,
                        displacements=canonical.displacements,
                        pair_id=int(data.pair_id.max()) + 1 + np.arange(canonical.frame_count, dtype=np.int64))
    if low_frequency and data.low_frequency is not None:
        add_low_frequency(extra, faces, smoothness=float(hyper["model"]["smoothing_lambda"]),
                          iterations=int(hyper["model"]["smoothing_iterations"]), device=device)
    return concat_frames([data] + [extra] * int(repeat))


def merged_hyperparameters(
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    defaults: Mapping[str, Mapping[str, Any]] = DEFAULT_HYPERPARAMETERS,
) -> dict[str, dict[str, Any]]:
    """``defaults`` (TailorNet's unless given) updated stage by stage from ``overrides``
    (unknown stages or keys raise)."""
    merged = copy.deepcopy(dict(defaults))
    for stage, values in (overrides or {}).items():
        if stage not in merged:
            raise ValueError(f"unknown training stage '{stage}' in overrides; expected one of {sorted(merged)}")
        for key, value in values.items():
            if key not in merged[stage]:
                raise ValueError(
                    f"unknown hyper-parameter '{stage}.{key}'; expected one of {sorted(merged[stage])}"
                )
            merged[stage][key] = checked_override(f"{stage}.{key}", value, merged[stage][key])
    return merged


def _rng_state(generator: torch.Generator) -> dict[str, Any]:
    state = {"torch": torch.get_rng_state(), "shuffle": generator.get_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: Mapping[str, Any], generator: torch.Generator) -> None:
    # RNG states must be CPU byte tensors; a checkpoint loaded with map_location="cuda"
    # brings them back on the GPU.
    torch.set_rng_state(state["torch"].cpu())
    generator.set_state(state["shuffle"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


def _host_copy(obj: Any) -> Any:
    """``obj`` (nested dicts, lists, tuples of tensors and plain values) with every tensor copied to
    host memory: a snapshot that training may go on changing in place."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {key: _host_copy(value) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_host_copy(value) for value in obj)
    return copy.deepcopy(obj)


class CheckpointWriter:
    """Writes checkpoints (:func:`atomic_save`) on a background thread, one at a time, so that
    training goes on while GBs go to disk; ``last_write_s`` is the last write's duration.
    ``wait()`` joins the write in flight and raises its error, if any."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.last_write_s = 0.0

    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, payload: Any, path: Path) -> None:
        """Write ``payload`` (a host snapshot, :func:`_host_copy`) to ``path`` in the background,
        once the write in flight (if any) is done."""
        self.wait()

        def write() -> None:
            started = time.monotonic()
            try:
                atomic_save(payload, path)
            except BaseException as error:  # raised by wait() in the training thread
                self._error = error
            self.last_write_s = time.monotonic() - started

        self._thread = threading.Thread(target=write, name=f"checkpoint {path.name}", daemon=True)
        self._thread.start()

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary file renamed onto ``path``: a crash leaves the previous file or
    none, never half of one. In a data-parallel run (:mod:`learn.distributed`) only rank 0 writes:
    every rank holds the same objects."""
    if not distributed.writes_files():
        return
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | os.PathLike[str], *, map_location: str | torch.device = "cpu",
                    mmap: bool = False) -> dict[str, Any]:
    """Read a checkpoint written by this module. ``mmap``: the tensors stay in the file (mapped,
    ``map_location`` must then be the CPU) and are read only where used, e.g. a finished stage's
    weights without its optimizer's moments (two thirds of an Adam checkpoint)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)


def autocast(device: str | torch.device, enabled: bool) -> torch.autocast:
    """bf16 autocast on ``device``'s type when ``enabled`` (a no-op context otherwise). Matmuls
    run in bf16 with float32 accumulation; callers cast the prediction back to float32 before
    the loss, so the loss and the optimizer see float32."""
    # no weight cache: a step replayed as a CUDA graph must cast its weights inside the graph
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=bool(enabled), cache_enabled=False)


EpochFn = Callable[[torch.nn.Module, torch.optim.Optimizer, torch.Generator], float]

#: ``lr_schedule`` values: ``constant`` keeps ``lr``; ``cosine`` anneals it over the stage's epochs
#: from ``lr`` to ``lr_final * lr`` (half a cosine, one value per epoch).
LR_SCHEDULES = ("constant", "cosine")


def scheduled_lr(lr: float, epoch: int, epochs: int, schedule: str, lr_final: float = 0.01) -> float:
    """The learning rate of ``epoch`` (counted from 0) of ``epochs`` under ``schedule``
    (:data:`LR_SCHEDULES`). A function of the epoch alone, so a resumed stage continues the
    schedule where its checkpoint stopped."""
    if schedule == "constant" or epochs <= 1:
        return lr
    if schedule == "cosine":
        progress = epoch / (epochs - 1)
        return lr * (lr_final + (1.0 - lr_final) * 0.5 * (1.0 + math.cos(math.pi * progress)))
    raise ValueError(f"lr_schedule must be one of {', '.join(LR_SCHEDULES)}, got {schedule!r}")


def _set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Every parameter group's learning rate to ``lr``, in place where it is a tensor."""
    for group in optimizer.param_groups:
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr


def run_epochs(
    stage: str,
    model: torch.nn.Module,
    epoch_fn: EpochFn,
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Any],
    fingerprint: DatasetFingerprint | None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
    checkpoint_interval_s: float = DEFAULT_CHECKPOINT_INTERVAL_S,
    after_epoch: Callable[[torch.nn.Module, int], None] | None = None,
    loss_name: str = "l1_m",
) -> torch.nn.Module:
    """The resumable epoch loop shared by every stage.

    ``epoch_fn(model, optimizer, generator)`` runs one epoch (shuffling with
    ``generator``) and returns its mean training loss, named ``loss_name`` (default ``l1_m``: a
    per-vertex L1 in metres, shown in mm on the bar; a stage whose loss is in other units names
    them, e.g. ``l1_latent``). Each epoch's loss goes to ``<run_dir>/<stage>_loss.csv`` (column
    ``train_<loss_name>``). The model, optimizer, epoch count and RNG states go to
    ``<run_dir>/<stage>.pt`` after an epoch when ``checkpoint_interval_s`` seconds have
    passed since the last save (0: after every epoch), or, with a positive interval,
    :data:`SAVE_SHARE_INVERSE` times the last write's duration if longer, and always after the last
    epoch; then ``<stage>.done`` (JSON) is written. A save copies the state to host memory and,
    but for the last, writes it on a background thread while the epochs go on
    (:class:`CheckpointWriter`; the stacked HF checkpoint of a 7.7k-vertex garment, K = 20, is
    about 6 GB with Adam's moments); no save starts while one is in flight, and the function
    returns (or raises) only once every write is on disk. An existing checkpoint is resumed after checking the
    fingerprint and the model configuration. ``after_epoch(model, epoch)`` (epoch counted
    from 1), when given, runs on every rank after each epoch's log row and before its
    checkpoint (e.g. a held-out loss). Returns the model in eval mode.

    Under torchrun with data parallelism (:mod:`learn.distributed`) every rank runs this loop on
    the same model: ``epoch_fn`` deals each global batch out with ``distributed.shard`` and returns
    this rank's part of the epoch's mean loss (its frames' loss sum / all frames); the optimizer
    sums the gradients over the ranks, the losses are summed, rank 0 writes the log and the
    checkpoint, and the global torch RNG is seeded per (seed, epoch, rank). The checkpoint is the
    one of a single process, so a run resumes on any number of processes.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = run_dir / f"{stage}.pt"
    log_path = run_dir / f"{stage}_loss.csv"
    epochs = int(hyperparameters["epochs"])
    checkpoint_interval_s = float(hyperparameters.get("checkpoint_interval_s", checkpoint_interval_s))
    if epochs < 0 or int(hyperparameters["batch_size"]) < 1:
        raise ValueError(
            f"{stage}: epochs must be >= 0 and batch_size >= 1, got {epochs}, {hyperparameters['batch_size']}"
        )
    schedule = str(hyperparameters.get("lr_schedule", "constant"))
    if schedule not in LR_SCHEDULES:
        raise ValueError(f"{stage}: lr_schedule must be one of {', '.join(LR_SCHEDULES)}, got {schedule!r}")
    lr_final = float(hyperparameters.get("lr_final", 0.01))
    if not 0.0 <= lr_final <= 1.0:
        raise ValueError(f"{stage}: lr_final (a fraction of lr) must be in [0, 1], got {lr_final}")
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    model = model.to(device)
    lr = float(hyperparameters["lr"])
    on_gpu = torch.device(device).type == "cuda"
    optimizer = torch.optim.Adam(
        # a tensor learning rate on GPUs, so that a step replayed as a CUDA graph reads the scheduled value
        model.parameters(), lr=torch.tensor(lr, device=device) if on_gpu and schedule != "constant" else lr,
        weight_decay=float(hyperparameters["weight_decay"]),
        fused=torch.device(device).type == "cuda",  # one kernel per step on GPUs
        capturable=torch.device(device).type == "cuda",  # its step count on the GPU: steps replay as graphs
    )
    start_epoch = 0
    if checkpoint_path.exists():
        # mapped, not read: a finished stage (e.g. trained by another process, loaded to assemble
        # the model) reads its weights only; the optimizer's state is read when epochs are left
        checkpoint = load_checkpoint(checkpoint_path, mmap=True)
        check_fingerprint(checkpoint.get("fingerprint"), fingerprint, source=str(checkpoint_path))
        if checkpoint["model_config"] != model.config:
            raise ValueError(
                f"{checkpoint_path} holds a model configured as {checkpoint['model_config']}, "
                f"not {model.config}: use a new run directory for a new configuration"
            )
        model.load_state_dict(checkpoint["model_state"])
        start_epoch = int(checkpoint["epoch"])
        if start_epoch < epochs:
            optimizer.load_state_dict(checkpoint["optimizer_state"])  # moved to the parameters' device
        _set_rng_state(checkpoint["rng_state"], generator)
        del checkpoint  # unmaps the file
    if start_epoch > epochs:
        raise ValueError(f"{checkpoint_path} already holds {start_epoch} epochs, more than epochs={epochs}")
    parallel = distributed.active()
    if parallel:
        distributed.broadcast_module(model)
        optimizer = distributed.DataParallelOptimizer(optimizer)
    writes = distributed.writes_files()

    # Keep the log consistent with the checkpoint: drop rows of epochs never checkpointed.
    rows: list[list[str]] = []
    if writes and log_path.exists() and start_epoch > 0:
        with log_path.open() as handle:
            rows = [r for r in csv.reader(handle)][1:]
        rows = [r for r in rows if r and int(r[0]) <= start_epoch]
    if writes:
        with log_path.open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["epoch", f"train_{loss_name}", "seconds"])
            writer.writerows(rows)

    bar = tqdm(
        range(start_epoch, epochs), desc=stage, initial=start_epoch, total=epochs, disable=not progress or not writes,
        leave=False,
    )
    last_save = time.monotonic()
    interval_s = checkpoint_interval_s
    writer = CheckpointWriter()
    try:  # a checkpoint in flight reaches the disk before the stage returns or raises
        for epoch in bar:
            model.train()
            started = time.perf_counter()
            if parallel:
                torch.manual_seed(distributed.epoch_seed(seed, epoch))
            if schedule != "constant":
                _set_lr(optimizer, scheduled_lr(lr, epoch, epochs, schedule, lr_final))
            mean_loss = epoch_fn(model, optimizer, generator)
            if parallel:
                mean_loss = distributed.sum_over_ranks(mean_loss)
            if writes:
                with log_path.open("a", newline="") as handle:
                    csv.writer(handle).writerow([epoch + 1, f"{mean_loss:.8g}",
                                                 f"{time.perf_counter() - started:.4f}"])
            shown = ({f"{loss_name}m": f"{mean_loss * 1000:.3f}"} if loss_name.endswith("_m")
                     else {loss_name: f"{mean_loss:.4g}"})
            bar.set_postfix(shown, refresh=False)  # redrawn at tqdm's pace, not per epoch
            if after_epoch is not None:
                after_epoch(model, epoch + 1)
            last = epoch + 1 == epochs
            if checkpoint_interval_s > 0.0 and not writer.busy():  # spaced by the last write's duration
                interval_s = max(checkpoint_interval_s, SAVE_SHARE_INVERSE * writer.last_write_s)
            if not last and (writer.busy() or time.monotonic() - last_save < interval_s):
                continue  # a write in flight: training goes on, the next save comes after it
            if not writes:  # another rank writes the same state (data parallelism)
                last_save = time.monotonic()
                continue
            payload = {
                "format": CHECKPOINT_FORMAT,
                "stage": stage,
                "epoch": epoch + 1,
                "epochs": epochs,
                "model_config": model.config,
                "model_state": model.state_dict(),
                "optimizer_state": optimizer.state_dict(),
                "rng_state": _rng_state(generator),
                "hyperparameters": dict(hyperparameters),
                "seed": seed,
                "fingerprint": None if fingerprint is None else fingerprint.as_dict(),
                f"train_{loss_name}": mean_loss,
            }
            if last:  # written here: the .done marker follows it
                writer.wait()
                atomic_save(payload, checkpoint_path)
            else:
                writer.submit(_host_copy(payload), checkpoint_path)
                if checkpoint_interval_s == 0.0:
                    writer.wait()  # every epoch saved: one write at a time, none skipped
            last_save = time.monotonic()
    except BaseException:
        try:
            writer.wait()
        except Exception:  # noqa: BLE001 - the loop's error is the one to report
            pass
        raise
    writer.wait()
    bar.close()
    if writes:
        (run_dir / f"{stage}.done").write_text(json.dumps({"stage": stage, "epochs": epochs}))
    if parallel:
        distributed.barrier()  # every rank sees the finished stage's files
    return model.eval()


def train_stage(
    stage: str,
    model: DisplacementMLP,
    data: FrameArrays | StreamedSplit,
    target: np.ndarray | str,
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Any],
    fingerprint: DatasetFingerprint | None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
) -> DisplacementMLP:
    """Train ``model`` to map (data.pose, data.shape, data.style) to ``target``: an array (N, V, 3)
    or the name of a frame field (``displacements``, ``low_frequency``, ``high_frequency``; the
    only form a streamed split takes, :mod:`learn.batches`).

    Mini-batches of ``batch_size`` frames in a fresh random order each epoch (the frames' order
    with ``hyperparameters["shuffle"]`` false); see :func:`run_epochs` for checkpoints, logs and
    resuming. Returns the model in eval mode.
    """
    if data.frame_count == 0:
        raise ValueError(f"{stage}: no training frames")
    batch_size = int(hyperparameters["batch_size"])
    mixed = bool(hyperparameters.get("mixed_precision", False))
    graphs = bool(hyperparameters.get("cuda_graphs", True))
    shuffle = bool(hyperparameters.get("shuffle", True))
    if not isinstance(target, str) and target.shape != (data.frame_count, model.vertex_count, 3):
        raise ValueError(
            f"{stage}: target must have shape ({data.frame_count}, {model.vertex_count}, 3), got {target.shape}"
        )
    field = target if isinstance(target, str) else "target"
    sources: list[MemoryBatches | Any] = []  # built at the first epoch: a finished stage only loads

    def batch_source() -> MemoryBatches | Any:
        if not sources:
            if isinstance(target, str):
                sources.append(batches_for(data, ("pose", "shape", "style", target), batch_size=batch_size,
                                           device=device, shuffle=shuffle))
            else:
                sources.append(MemoryBatches({"pose": data.pose, "shape": data.shape, "style": data.style,
                                              "target": target}, batch_size=batch_size, device=device, shuffle=shuffle))
        return sources[0]

    steps: dict[int, TrainingStep] = {}  # by optimizer: the one run_epochs builds for this stage

    def epoch_fn(net: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        source = batch_source()
        total = torch.zeros((), device=device)
        if isinstance(source, MemoryBatches) and not distributed.active():  # one graph per step on a GPU
            if id(optimizer) not in steps:
                def loss_of(inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
                    batch = source.gather(inputs["index"])
                    with autocast(device, mixed):
                        prediction = net(batch["pose"], batch["shape"], batch["style"])
                    return l1_displacement_loss(prediction.float(), batch[field])

                steps[id(optimizer)] = TrainingStep(loss_of, optimizer, graph=graphs)
            step = steps[id(optimizer)]
            for index, frames in source.indices(generator):
                total += step({"index": index}) * frames
            return float(total) / data.frame_count
        for batch in source.epoch(generator, optimizer):  # this rank's frames (all in one process)
            with autocast(device, mixed):
                prediction = net(batch["pose"], batch["shape"], batch["style"])
            loss = l1_displacement_loss(prediction.float(), batch[field])
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * batch.frames
        return float(total) / data.frame_count

    return run_epochs(
        stage, model, epoch_fn, run_dir=run_dir, hyperparameters=hyperparameters, fingerprint=fingerprint,
        device=device, seed=seed, progress=progress,
    )


def train_stacked_prototypes(
    model: HighFrequencyPrototypes,
    data: FrameArrays,
    target: np.ndarray | None,
    frames_per_prototype: list[np.ndarray],
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Any],
    fingerprint: DatasetFingerprint | None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
    stage: str = "hf",
    members: Sequence[int] | None = None,
) -> HighFrequencyPrototypes:
    """Train the K prototype MLPs at once, each on its own frames (stage ``hf``).

    Every step feeds each prototype a batch of ``batch_size`` of its own frames and
    minimises the sum of the K L1 losses. Prototype k's parameters get gradients only
    from its own loss and Adam (with its L2 weight decay) acts element-wise, so this
    is K independent trainings run as batched matmuls. An epoch is
    ceil(max_k n_k / batch_size) full batches per prototype, drawn from a per-prototype
    random order repeated as needed (exactly one pass when all n_k are equal multiples
    of the batch size, as with TailorNet's equal pose sets).

    ``target``: (N, V, 3) for ``data``'s N frames; None only for a stage that has finished
    (:func:`stage_finished`), which loads from its checkpoint.

    ``members``: ``model`` holds only these prototypes of the K that ``frames_per_prototype``
    lists (a part trained by one of several processes). Their batches are those of the whole
    run: every prototype's order is drawn and the step count is the whole run's, so a part's
    prototypes see the frames they would see trained with all K (dropout masks aside).
    """
    members = list(range(len(frames_per_prototype))) if members is None else [int(m) for m in members]
    k = model.prototype_count
    if len(members) != k or not all(0 <= m < len(frames_per_prototype) for m in members):
        raise ValueError(f"the model holds {k} prototypes; members {members} must name as many of the "
                         f"{len(frames_per_prototype)} listed in frames_per_prototype")
    counts = [int(np.asarray(f).size) for f in frames_per_prototype]
    if min(counts) == 0:
        raise ValueError(f"every prototype needs frames; counts per prototype: {counts}")
    batch_size = int(hyperparameters["batch_size"])
    mixed = bool(hyperparameters.get("mixed_precision", False))
    frames = [torch.as_tensor(np.asarray(f), dtype=torch.int64) for f in frames_per_prototype]
    steps = -(-max(counts) // batch_size)
    graphs = bool(hyperparameters.get("cuda_graphs", True))
    training_steps: dict[int, TrainingStep] = {}  # by optimizer: the one run_epochs builds for this stage
    tensors: dict[str, torch.Tensor] = {}  # on the device at the first epoch: a finished stage only loads

    def epoch_fn(net: torch.nn.Module, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        if not tensors:
            if target is None:
                raise ValueError(f"{stage}: no target given, but the stage has epochs left to train")
            tensors["pose"] = torch.as_tensor(data.pose, dtype=torch.float32, device=device)
            tensors["target"] = torch.as_tensor(target, dtype=torch.float32, device=device)
        pose, target_t = tensors["pose"], tensors["target"]
        sequences = []
        for idx in frames:
            order = idx[torch.randperm(idx.numel(), generator=generator)]
            repeats = -(-steps * batch_size // idx.numel())
            sequences.append(order.repeat(repeats)[: steps * batch_size])
        sequence = torch.stack([sequences[m] for m in members]).to(device)  # (K, steps * batch)
        if id(optimizer) not in training_steps:
            def loss_of(inputs: Mapping[str, torch.Tensor]) -> torch.Tensor:
                batch = inputs["index"]  # (K, b)
                with autocast(device, mixed):
                    prediction = net.forward_each(pose[batch])  # (K, b, V, 3)
                # the sum of the K prototypes' mean L1 losses
                return (prediction.float() - target_t[batch]).abs().sum(-1).mean(dim=(1, 2)).sum()

            # a data-parallel optimizer sums gradients over the ranks in its step: eager steps
            training_steps[id(optimizer)] = TrainingStep(loss_of, optimizer, graph=graphs and not distributed.active())
        training_step = training_steps[id(optimizer)]
        total = torch.zeros((), device=device)
        for step in range(steps):
            total += training_step({"index": sequence[:, step * batch_size : (step + 1) * batch_size]})
        return float(total) / (steps * len(members))  # the mean over steps of the prototypes' mean loss

    return run_epochs(
        stage, model, epoch_fn, run_dir=run_dir, hyperparameters=hyperparameters, fingerprint=fingerprint,
        device=device, seed=seed, progress=progress,
    )


def _member_frames(data: FrameArrays, frames_per_prototype: list[np.ndarray],
                   members: Sequence[int]) -> tuple[FrameArrays, list[np.ndarray]]:
    """``data`` cut to the frames of the ``members`` prototypes, and every prototype's frame
    list renumbered into the cut: the members' onto their frames, the others' (same lengths) onto
    frame 0, never read."""
    keep = sorted(int(m) for m in members)
    picked = np.concatenate([frames_per_prototype[m] for m in keep])
    renumbered, start = [], 0
    for k, frames in enumerate(frames_per_prototype):
        if k in keep:
            renumbered.append(np.arange(start, start + frames.size))
            start += frames.size
        else:
            renumbered.append(np.zeros(frames.size, np.int64))
    return data.subset(picked), renumbered


def stage_hyper(hyper: Mapping[str, Any], model_hyper: Mapping[str, Any] | None = None) -> dict[str, Any]:
    stage = {k: hyper[k] for k in ("lr", "weight_decay", "batch_size", "epochs")}
    if model_hyper is not None:
        stage["checkpoint_interval_s"] = float(model_hyper["checkpoint_interval_s"])
        stage["mixed_precision"] = bool(model_hyper.get("mixed_precision", False))
        stage["cuda_graphs"] = bool(model_hyper.get("cuda_graphs", True))
    return stage


def _components(data: FrameArrays, model_hyper: Mapping[str, Any]) -> tuple[int, int]:
    shape_components = min(int(model_hyper["shape_components"]), data.shape.shape[1])
    style_components = min(int(model_hyper["style_components"]), data.style.shape[1])
    if shape_components + style_components == 0:
        raise ValueError("shape_components and style_components are both 0 (or the data has none)")
    return shape_components, style_components


def train_shape_style(
    data: FrameArrays,
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    canonical_pose: np.ndarray | None = None,
    canonical: FrameArrays | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
) -> ShapeStyleModel:
    """Train g(shape, style) on the canonical-pose drapes: every frame of the dataset's ``canonical``
    split, and for a training pair without one its frame closest to ``canonical_pose`` (default 0)
    (:func:`canonical_training_frames`)."""
    hyper = merged_hyperparameters(hyperparameters)
    shape_components, style_components = _components(data, hyper["model"])
    canonical = canonical_training_frames(data, canonical, canonical_pose)[1]
    torch.manual_seed(seed)  # deterministic initial weights
    model = ShapeStyleModel(
        data.vertex_count,
        shape_components=shape_components,
        style_components=style_components,
        hidden_size=int(hyper["shape_style"]["hidden_size"]),
        dropout=float(hyper["shape_style"]["dropout"]),
    )
    return train_stage(
        "shape_style", model, canonical, canonical.displacements, run_dir=run_dir,
        hyperparameters=stage_hyper(hyper["shape_style"], hyper["model"]), fingerprint=fingerprint,
        device=device, seed=seed, progress=progress,
    )


def train_lf(
    data: FrameArrays,
    pose_indices: np.ndarray,
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
) -> DisplacementMLP:
    """Train D_LF(pose, shape, style) on the smoothed displacements (``data.low_frequency``; a
    streamed split reads them from the per-shard cache, :meth:`StreamedSplit.prepare_low_frequency`)."""
    hyper = merged_hyperparameters(hyperparameters)
    finished = stage_finished(run_dir, "lf", int(hyper["lf"]["epochs"]))  # loads without the split
    if not finished and not is_streamed(data) and data.low_frequency is None:
        raise ValueError("data.low_frequency is None: call add_low_frequency(data, faces) first")
    shape_components, style_components = _components(data, hyper["model"])
    torch.manual_seed(seed)  # deterministic initial weights
    model = low_frequency_model(
        data.vertex_count, pose_indices, shape_components=shape_components, style_components=style_components,
        hidden_size=int(hyper["lf"]["hidden_size"]), dropout=float(hyper["lf"]["dropout"]),
    )
    return train_stage(
        "lf", model, data, "low_frequency", run_dir=run_dir, hyperparameters=stage_hyper(hyper["lf"], hyper["model"]),
        fingerprint=fingerprint, device=device, seed=seed, progress=progress,
    )


def train_hf(
    data: FrameArrays,
    pose_indices: np.ndarray,
    prototype_pairs: np.ndarray,
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
    stacked: bool | None = None,
    part: tuple[int, int] | None = None,
    fill_low_frequency: Callable[[FrameArrays], Any] | None = None,
) -> HighFrequencyPrototypes:
    """Train one D_HF(pose) per prototype pair on that pair's frames, target D - D_LF.

    ``stacked`` (default: the ``hf.stacked`` hyper-parameter, True) trains all K at once
    as one stage ``hf`` (:func:`train_stacked_prototypes`, far faster on a GPU);
    otherwise one stage per prototype, ``hf_00``, ``hf_01``, ... Both start from the
    same initial weights. Returns the K models stacked, in eval mode.

    ``part`` = (i, P): only the i-th of P contiguous groups of the prototypes
    (:func:`hf_part_members`), stacked as stage ``hf_<i+1>of<P>`` (:func:`hf_part_stage`) with
    the batches the whole stage would give them, or as their own ``hf_kk`` stages; the P parts,
    trained by different processes, make the K prototypes (``HighFrequencyPrototypes.cat``).

    ``fill_low_frequency(frames)`` (e.g. :func:`add_low_frequency` with the model's smoothing)
    fills ``low_frequency`` of in-memory frames that have none, called on the frames this call
    trains on only (a part's prototypes' frames: the smoothing of the others' is not needed).

    A streamed split (:class:`learn.streamed_split.StreamedSplit`, after its
    ``prepare_low_frequency``) gives the prototype pairs' frames only, read into memory: every
    step feeds each prototype a batch of its own pair's frames, which a stream dealing whole
    shards cannot serve, and they are K of the split's X pairs.
    """
    hyper = merged_hyperparameters(hyperparameters)
    if stacked is None:
        stacked = bool(hyper["hf"]["stacked"])
    stage = "hf" if part is None else hf_part_stage(*part)
    # a finished stage loads from its checkpoint: no low-frequency split needed
    finished = stacked and stage_finished(run_dir, stage, int(hyper["hf"]["epochs"]))
    if not finished and is_streamed(data) and not data.low_frequency_ready:
        raise ValueError("the streamed split's low-frequency cache is not prepared: call data.prepare_low_frequency()")
    if not finished and not is_streamed(data) and data.low_frequency is None and fill_low_frequency is None:
        raise ValueError("data.low_frequency is None: call add_low_frequency(data, faces) first")
    frames_per_prototype = []
    for pair in np.asarray(prototype_pairs).reshape(-1):
        frames = np.flatnonzero(data.pair_id == pair)
        if frames.size == 0:
            raise ValueError(f"prototype pair {pair} has no frames in the training data")
        frames_per_prototype.append(frames)
    if is_streamed(data):
        data = data.subset(np.concatenate(frames_per_prototype))
        ends = np.cumsum([f.size for f in frames_per_prototype])
        frames_per_prototype = [np.arange(end - f.size, end) for f, end in zip(frames_per_prototype, ends)]
    count = len(frames_per_prototype)
    members = list(range(count)) if part is None else hf_part_members(count, *part).tolist()
    hidden, dropout = int(hyper["hf"]["hidden_size"]), float(hyper["hf"]["dropout"])
    initial: dict[int, DisplacementMLP] = {}
    # prototype k's initial weights come from its own seed, so building the members' alone gives
    # each the weights it has in the whole stage; a finished stage reads its weights from its
    # checkpoint and draws none (at K = 20 and 7.7k vertices, 20 x 25 M parameters: seconds)
    for k in [] if finished else members:
        torch.manual_seed(seed + 1 + k)  # deterministic initial weights, same in both modes
        initial[k] = high_frequency_model(data.vertex_count, pose_indices, hidden_size=hidden, dropout=dropout)
    if stacked:
        if part is not None and not finished and not is_streamed(data):
            # a part needs only its prototypes' frames on the device; the others' index lists keep
            # their lengths (their random orders are still drawn, so the members see the batches
            # the whole stage gives them) but point nowhere they are read
            data, frames_per_prototype = _member_frames(data, frames_per_prototype, members)
        if not finished and not is_streamed(data) and data.low_frequency is None:
            fill_low_frequency(data)
        model = (HighFrequencyPrototypes(len(members), data.vertex_count, pose_indices, hidden_size=hidden,
                                         dropout=dropout, device=device) if finished
                 else HighFrequencyPrototypes.from_mlps([initial[k] for k in members]))
        return train_stacked_prototypes(
            model, data,
            None if finished else data.displacements - data.low_frequency, frames_per_prototype, run_dir=run_dir,
            hyperparameters=stage_hyper(hyper["hf"], hyper["model"]), fingerprint=fingerprint, device=device,
            seed=seed + 1, progress=progress, stage=stage, members=members,
        )
    models = []
    for k in members:
        frames, model = frames_per_prototype[k], initial[k]
        subset = data.subset(frames)
        if subset.low_frequency is None:
            fill_low_frequency(subset)
        models.append(
            train_stage(
                f"hf_{k:02d}", model, subset, subset.displacements - subset.low_frequency, run_dir=run_dir,
                hyperparameters=stage_hyper(hyper["hf"], hyper["model"]), fingerprint=fingerprint, device=device,
                seed=seed + 1 + k, progress=progress,
            )
        )
    return HighFrequencyPrototypes.from_mlps(models).eval()


def train_baseline(
    data: FrameArrays,
    pose_indices: np.ndarray,
    *,
    run_dir: str | os.PathLike[str],
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
) -> DisplacementMLP:
    """Train the baseline MLP(pose, shape, style) on the full displacements; saves baseline.pt too."""
    hyper = merged_hyperparameters(hyperparameters)
    shape_components, style_components = _components(data, hyper["model"])
    torch.manual_seed(seed)  # deterministic initial weights
    model = baseline_model(
        data.vertex_count, pose_indices, shape_components=shape_components, style_components=style_components,
        hidden_size=int(hyper["baseline"]["hidden_size"]), dropout=float(hyper["baseline"]["dropout"]),
    )
    model = train_stage(
        "baseline", model, data, "displacements", run_dir=run_dir,
        hyperparameters=stage_hyper(hyper["baseline"], hyper["model"]), fingerprint=fingerprint, device=device, seed=seed,
        progress=progress,
    )
    save_learner(
        model, "baseline", Path(run_dir) / "baseline_model.pt", fingerprint=fingerprint,
        extra={"hyperparameters": hyper},
    )
    return model


def garment_pose_indices(
    skinning_weights: np.ndarray,
    pose_size: int,
    *,
    parents: np.ndarray | None = None,
    posable_joints: np.ndarray | None = None,
    min_weight_sum: float = 1.0,
) -> np.ndarray:
    """Pose entries that move the garment (see :mod:`learn.tailornet.pose_mask`)."""
    joints = garment_pose_joints(skinning_weights, parents=parents, min_weight_sum=min_weight_sum)
    return pose_feature_indices(joints, pose_size, posable_joints=posable_joints)


TAILORNET_STAGES = ("shape_style", "lf", "hf")
# The stages `drape train tailornet` spreads over processes (torchrun ranks), one GPU each.
STAGE_ORDER = ("hf", "lf", "baseline", "shape_style")

#: Seconds per epoch of each stage on one H100 at full scale, steps replayed as CUDA graphs (30,581
#: frames of the 7.7k t-shirt, 20 prototypes stacked; docs/benchmarks.md, "Training and evaluation
#: time at full scale"):
#: with the configured epochs, the cost model that spreads the stages over processes.
STAGE_EPOCH_SECONDS = {"hf": 0.468, "lf": 0.588, "baseline": 0.589, "shape_style": 0.005}

#: More hf parts are taken only where they shorten the longest process by more than this share.
HF_SPLIT_GAIN = 0.1


def _check_part(index: int, parts: int) -> None:
    if parts < 1 or not 0 <= index < parts:
        raise ValueError(f"need 0 <= index < parts, got index={index}, parts={parts}")


def hf_part_stage(index: int, parts: int) -> str:
    """Stage name of part ``index`` (from 0) of hf split into ``parts``: ``hf_<index+1>of<parts>``
    (checkpoints and .done markers; a run resumed with another split trains its parts anew)."""
    _check_part(index, parts)
    return f"hf_{index + 1}of{parts}"


def hf_part_members(prototype_count: int, index: int, parts: int) -> np.ndarray:
    """The prototypes (indices) of part ``index`` of ``parts``: contiguous groups whose sizes
    differ by at most one."""
    _check_part(index, parts)
    if parts > prototype_count:
        raise ValueError(f"cannot split {prototype_count} prototypes into {parts} parts")
    return np.array_split(np.arange(prototype_count), parts)[index]


def _unit_costs(hyperparameters: Mapping[str, Mapping[str, Any]] | None, parts: int) -> dict[str, float]:
    """Each unit's cost [s]: a stage's :data:`STAGE_EPOCH_SECONDS` x its epochs, hf as ``parts``
    equal parts where ``parts`` > 1."""
    hyper = merged_hyperparameters(hyperparameters)
    costs = {stage: STAGE_EPOCH_SECONDS[stage] * int(hyper[stage]["epochs"]) for stage in STAGE_ORDER}
    if parts > 1:
        hf = costs.pop("hf")
        costs.update({hf_part_stage(i, parts): hf / parts for i in range(parts)})
    return costs


def _schedule(costs: Mapping[str, float], world_size: int) -> tuple[list[list[str]], float]:
    """Longest processing time first: each unit to the least loaded process. Returns the units
    per process and the longest process's cost."""
    loads = [0.0] * world_size
    units: list[list[str]] = [[] for _ in range(world_size)]
    for name, cost in sorted(costs.items(), key=lambda item: (-item[1], item[0])):
        r = min(range(world_size), key=lambda i: (loads[i], i))
        loads[r] += cost
        units[r].append(name)
    return units, max(loads)


def hf_parts_for(world_size: int, hyperparameters: Mapping[str, Mapping[str, Any]] | None = None) -> int:
    """How many parts hf is split into over ``world_size`` processes: the fewest (1 to the
    process count, at most the prototype count) whose longest process is within
    :data:`HF_SPLIT_GAIN` of the shortest reachable, with each stage's cost
    :data:`STAGE_EPOCH_SECONDS` x its epochs and a part's cost its share of the prototypes.
    With the paper's epochs: 2 parts on 2-3 processes, 3 on 4-5."""
    hyper = merged_hyperparameters(hyperparameters)
    most = max(1, min(int(world_size), int(hyper["model"]["prototype_count"])))
    spans = {parts: _schedule(_unit_costs(hyper, parts), world_size)[1] for parts in range(1, most + 1)}
    best = min(spans.values())
    return min(p for p, span in spans.items() if span <= best * (1.0 + HF_SPLIT_GAIN))


def stages_for_rank(rank: int, world_size: int,
                    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None) -> list[str]:
    """Stages (of :data:`STAGE_ORDER`, hf possibly as parts ``hf_<i>of<P>``,
    :func:`hf_parts_for`) that process ``rank`` of ``world_size`` trains.

    TailorNet's stages are independent given the data, and so are its prototypes: they
    parallelise across GPUs without gradient exchange. The units go to the processes longest
    first, each to the least loaded (costs: :data:`STAGE_EPOCH_SECONDS` x the configured
    epochs). With the paper's epochs: 2 processes train half of hf each, one with the baseline, the
    other with lf and shape_style; 4 train a third of hf each on three, and lf, the baseline and
    shape_style on the fourth.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"need 0 <= rank < world_size, got rank={rank}, world_size={world_size}")
    parts = hf_parts_for(world_size, hyperparameters)
    return _schedule(_unit_costs(hyperparameters, parts), world_size)[0][rank]


def _done_markers(run_dir: Path, stage: str, prototype_count: int, stacked: bool) -> list[Path]:
    if stage == "hf" and not stacked:
        return [run_dir / f"hf_{k:02d}.done" for k in range(prototype_count)]
    return [run_dir / f"{stage}.done"]


def stage_finished(run_dir: str | os.PathLike[str], stage: str, epochs: int) -> bool:
    """Whether ``stage`` has trained ``epochs`` epochs in ``run_dir``: its ``.done`` marker says
    so and its checkpoint exists. Such a stage loads from the checkpoint without its training
    data being prepared (the stages other processes trained, when rank 0 assembles the model)."""
    marker, checkpoint = Path(run_dir) / f"{stage}.done", Path(run_dir) / f"{stage}.pt"
    if not (marker.is_file() and checkpoint.is_file()):
        return False
    try:
        return int(json.loads(marker.read_text())["epochs"]) == int(epochs)
    except (ValueError, KeyError, TypeError):
        return False


def _wait_until(done: Callable[[], bool], timeout_s: float, poll_s: float = 1.0) -> bool:
    """Poll ``done`` every ``poll_s`` seconds for at most ``timeout_s``; whether it came true."""
    deadline = time.monotonic() + max(0.0, timeout_s)
    while not done():
        if time.monotonic() >= deadline:
            return False
        time.sleep(min(poll_s, max(0.0, deadline - time.monotonic())))
    return True


def wait_for_stage(run_dir: str | os.PathLike[str], stage: str, epochs: int, timeout_s: float,
                   poll_s: float = 1.0) -> bool:
    """Wait until ``stage`` has finished ``epochs`` epochs in ``run_dir`` (:func:`stage_finished`;
    another process trains it), at most ``timeout_s`` seconds. Returns whether it finished."""
    return _wait_until(lambda: stage_finished(run_dir, stage, epochs), timeout_s, poll_s)


def fit_tailornet(
    data: FrameArrays,
    faces: np.ndarray,
    *,
    run_dir: str | os.PathLike[str],
    pose_indices: np.ndarray | None = None,
    canonical_pose: np.ndarray | None = None,
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
    stages: Collection[str] | None = None,
    wait_timeout_s: float = 0.0,
    hf_parts: int = 1,
    canonical: FrameArrays | None = None,
    assemble: bool = True,
) -> TailorNet | None:
    """Train TailorNet's stages on the training split and save ``tailornet_model.pt``.

    Args:
        data: training frames (train style-shapes x train poses).
        faces: garment triangles, shape (F, 3), for the frequency split.
        run_dir: where stage checkpoints, loss logs and the final model go.
        pose_indices: pose entries fed to the networks (default: all); see
            :func:`garment_pose_indices`.
        canonical_pose: the pose garments are draped in (body model's canonical A-pose),
            shape (P,); each pair's frame closest to it trains g and picks prototypes.
        hyperparameters: per-stage overrides of :data:`DEFAULT_HYPERPARAMETERS`.
        stages: the stages of :data:`TAILORNET_STAGES` this call trains (default all).
            The others are expected from other processes sharing ``run_dir``; once all
            are finished (their ``.done`` markers exist, waiting up to
            ``wait_timeout_s`` seconds) the model is assembled and saved, else None is
            returned and a later call (e.g. by rank 0) assembles it.
        assemble: whether this call assembles and saves the model once every stage is
            finished; False returns None after training ``stages`` (the processes other than
            rank 0 of a stage-parallel run: one process writes the model).
        hf_parts: hf is trained as this many parts ``hf_<i>of<P>`` (:func:`train_hf`'s
            ``part``); ``stages`` may name parts, and ``hf`` then means all of them.
        canonical: the dataset's ``canonical`` split (every style-shape combination in the
            canonical pose), or None: g learns from all of it and the prototypes are chosen on
            its drapes of the training pairs (:func:`canonical_training_frames`); with
            ``model.canonical_repeat`` its frames also join LF's training frames (in memory;
            a streamed split trains LF on its own frames).
    Prototypes: the K = min(model.prototype_count, pairs) training pairs chosen greedily
    on their canonical-pose garments (written to ``prototypes.json`` with errors vs K).

    ``data`` may be a :class:`learn.streamed_split.StreamedSplit`: the low-frequency split is
    then computed in one streamed pass into the per-shard cache (its smoothing settings are the
    cache's, :data:`learn.data.SMOOTHNESS` and :data:`learn.data.ITERATIONS`), LF and the baseline
    stream their batches, g and the prototype choice read one frame per pair, and HF reads its
    prototype pairs' frames (:func:`train_hf`).
    """
    started = time.perf_counter()
    hyper = merged_hyperparameters(hyperparameters)
    if is_streamed(data):
        from learn.data import ITERATIONS, SMOOTHNESS

        settings = (float(hyper["model"]["smoothing_lambda"]), int(hyper["model"]["smoothing_iterations"]))
        if settings != (SMOOTHNESS, ITERATIONS):
            raise ValueError(f"model.smoothing_lambda, model.smoothing_iterations = {settings} with streamed data: the "
                             f"streamed low-frequency cache is computed with ({SMOOTHNESS}, {ITERATIONS})")
    if isinstance(hf_parts, bool) or not isinstance(hf_parts, int) or hf_parts < 1:
        raise ValueError(f"hf_parts must be an integer >= 1 (got {hf_parts!r})")
    parts = [hf_part_stage(i, hf_parts) for i in range(hf_parts)] if hf_parts > 1 else []
    stages = list(TAILORNET_STAGES if stages is None else stages)
    unknown = sorted(set(stages) - set(TAILORNET_STAGES) - set(parts))
    if unknown:
        raise ValueError(f"unknown TailorNet stages {unknown}; expected among {list(TAILORNET_STAGES) + parts}")
    if parts and "hf" in stages:
        stages = [s for s in stages if s != "hf"] + [q for q in parts if q not in stages]
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    if pose_indices is None:
        pose_indices = np.arange(data.pose.shape[1])
    pair_frames = canonical_training_frames(data, canonical, canonical_pose)[0]
    pair_count = pair_frames.frame_count
    prototype_count = min(int(hyper["model"]["prototype_count"]), pair_count)
    if hf_parts > prototype_count:
        raise ValueError(f"hf_parts={hf_parts} but the model has {prototype_count} prototypes")
    repeat = int(hyper["model"]["canonical_repeat"])  # a streamed split trains LF on its own frames
    choice = choose_prototypes(pair_frames.displacements, prototype_count)
    (run_dir / "prototypes.json").write_text(
        json.dumps(
            {
                "pair_ids": choice.indices.tolist(),
                "mean_error_mm_vs_k": [None if np.isnan(e) else e for e in choice.mean_error_mm.tolist()],
                "max_error_mm_vs_k": [None if np.isnan(e) else e for e in choice.max_error_mm.tolist()],
            },
            indent=2,
        )
    )
    common = dict(
        run_dir=run_dir, hyperparameters=hyperparameters, fingerprint=fingerprint, device=device, progress=progress
    )

    def smooth(frames: FrameArrays) -> FrameArrays:
        return add_low_frequency(frames, faces, smoothness=float(hyper["model"]["smoothing_lambda"]),
                                 iterations=int(hyper["model"]["smoothing_iterations"]), device=device)

    def train(stage: str) -> torch.nn.Module:
        if stage == "shape_style":
            return train_shape_style(data, canonical_pose=canonical_pose, canonical=canonical, seed=seed, **common)
        epochs = int(hyper["lf" if stage == "lf" else "hf"]["epochs"])
        # trained before, or by another process: it loads from its checkpoint, no split to prepare
        ready = (stage == "lf" or bool(hyper["hf"]["stacked"])) and stage_finished(run_dir, stage, epochs)
        if not ready and is_streamed(data):
            if not data.low_frequency_ready:
                data.prepare_low_frequency(device)
        if stage == "lf":
            if not ready and not is_streamed(data) and data.low_frequency is None:
                smooth(data)
            lf_data = data if ready or is_streamed(data) else with_canonical_frames(data, canonical, repeat, faces,
                                                                                    hyper, device)
            return train_lf(lf_data, pose_indices, seed=seed + 1000, **common)
        part = None if stage == "hf" else (parts.index(stage), hf_parts)
        # in memory, an hf part smooths its own prototypes' frames only (when LF has not smoothed them all)
        return train_hf(data, pose_indices, choice.indices, seed=seed + 2000, part=part, fill_low_frequency=smooth,
                        **common)

    units = [s for s in TAILORNET_STAGES if s != "hf"] + (parts or ["hf"])
    who = f"[rank {distributed.rank()}] " if distributed.env_world_size() > 1 else ""

    def timed(unit: str) -> torch.nn.Module:
        # one line per stage: where a stage-parallel run's time goes (epochs, checkpoints, waiting)
        begun = time.perf_counter()
        module = train(unit)
        print(f"{who}tailornet {unit}: {time.perf_counter() - begun:.1f} s", flush=True)
        return module

    print(f"{who}tailornet: prototypes chosen in {time.perf_counter() - started:.1f} s", flush=True)
    trained = {unit: timed(unit) for unit in units if unit in stages}
    if not assemble:
        return None
    stacked = bool(hyper["hf"]["stacked"])

    def unit_markers(unit: str) -> list[Path]:
        if unit not in parts:
            return _done_markers(run_dir, unit, prototype_count, stacked)
        if stacked:
            return [run_dir / f"{unit}.done"]
        return [run_dir / f"hf_{k:02d}.done" for k in hf_part_members(prototype_count, parts.index(unit), hf_parts)]

    markers = [marker for unit in units if unit not in trained for marker in unit_markers(unit)]
    waited = time.monotonic()
    if not _wait_until(lambda: all(m.exists() for m in markers), wait_timeout_s):
        return None
    if markers:
        print(f"{who}tailornet: waited {time.monotonic() - waited:.1f} s for the other processes' stages", flush=True)
    assembling = time.perf_counter()
    # Stages finished elsewhere load from their complete checkpoints (no further epochs).
    modules = {unit: trained[unit] if unit in trained else train(unit) for unit in units}
    if parts:
        modules["hf"] = HighFrequencyPrototypes.cat([modules[q] for q in parts]).eval()
    model = TailorNet(
        modules["lf"], modules["hf"], modules["shape_style"],
        torch.as_tensor(pair_frames.shape[choice.indices]), torch.as_tensor(pair_frames.style[choice.indices]),
        sigma=float(hyper["model"]["sigma"]),
    ).to(device).eval()
    save_learner(
        model, "tailornet", run_dir / "tailornet_model.pt", fingerprint=fingerprint,
        extra={"hyperparameters": hyper},
    )
    print(f"{who}tailornet: model assembled and saved in {time.perf_counter() - assembling:.1f} s", flush=True)
    return model


def fit_baseline(
    data: FrameArrays,
    faces: np.ndarray,
    *,
    run_dir: str | os.PathLike[str],
    pose_indices: np.ndarray | None = None,
    canonical_pose: np.ndarray | None = None,
    hyperparameters: Mapping[str, Mapping[str, Any]] | None = None,
    fingerprint: DatasetFingerprint | None = None,
    device: str = "cpu",
    seed: int = 0,
    progress: bool = True,
    canonical: FrameArrays | None = None,
) -> DisplacementMLP:
    """Registry-shaped wrapper of :func:`train_baseline` (the baseline does not need
    ``canonical_pose``; it is accepted so every learner fits alike). ``canonical``: the dataset's
    canonical split, whose frames join the training frames ``model.canonical_repeat`` times, as
    they join TailorNet's LF; not for a streamed split."""
    del canonical_pose
    if pose_indices is None:
        pose_indices = np.arange(data.pose.shape[1])
    hyper = merged_hyperparameters(hyperparameters)
    if not is_streamed(data):  # a streamed split trains on its own frames
        data = with_canonical_frames(data, canonical, int(hyper["model"]["canonical_repeat"]), faces, hyper, device,
                                     low_frequency=False)
    return train_baseline(
        data, pose_indices, run_dir=run_dir, hyperparameters=hyperparameters, fingerprint=fingerprint,
        device=device, seed=seed, progress=progress,
    )


def fit_tailornet_process(
    data: FrameArrays,
    faces: np.ndarray,
    *,
    rank: int,
    world_size: int,
    wait_timeout_s: float = 3600.0,
    canonical: FrameArrays | None = None,
    **common: Any,
) -> TailorNet | None:
    """What process ``rank`` of a stage-parallel run of ``world_size`` processes trains: its
    stages (:func:`stages_for_rank`) of TailorNet and, where it has it, the baseline. Rank 0 then
    assembles and saves the model once every stage is done, waiting for the others' (and for the
    baseline, so that the run's time covers every process); the others return None.

    A process trains all its own stages before it waits: rank 0 with the baseline trains it first,
    rather than idle while the others finish and then alone. ``common``: :func:`fit_tailornet`'s
    keyword arguments (``run_dir``, ``hyperparameters``, ``device``, ...). ``world_size`` 1 trains
    everything in one process: TailorNet (assembled) then the baseline."""
    hyper = common.get("hyperparameters")
    stages = stages_for_rank(rank, world_size, hyper)
    parallel = dict(hf_parts=hf_parts_for(world_size, hyper), canonical=canonical, wait_timeout_s=wait_timeout_s)
    who = f"[rank {rank}] " if world_size > 1 else ""
    own = [s for s in stages if s != "baseline"]
    # rank 0 assembles in the call that trains its stages, unless the baseline must come before its
    # wait (the assembling call waits for the others); alone, nothing is waited for
    assemble_now = rank == 0 and (world_size == 1 or "baseline" not in stages)
    model = None
    if own or assemble_now:
        model = fit_tailornet(data, faces, stages=own, assemble=assemble_now, **parallel, **common)
    if "baseline" in stages:
        begun = time.perf_counter()
        fit_baseline(data, faces, canonical=canonical, **common)
        print(f"{who}baseline: {time.perf_counter() - begun:.1f} s", flush=True)
    if rank != 0:
        return None
    if not assemble_now:  # its own stages are finished now and load from their checkpoints
        model = fit_tailornet(data, faces, stages=[], **parallel, **common)
    if model is None:
        raise TimeoutError(f"the stages of the other processes did not finish within {wait_timeout_s} s")
    if "baseline" not in stages:
        epochs = int(merged_hyperparameters(hyper)["baseline"]["epochs"])
        if not wait_for_stage(common["run_dir"], "baseline", epochs, timeout_s=wait_timeout_s):
            raise TimeoutError(f"the baseline trained by another process did not finish within {wait_timeout_s} s")
    return model


def save_learner(
    model: TailorNet | DisplacementMLP,
    learner: str,
    path: str | os.PathLike[str],
    *,
    fingerprint: DatasetFingerprint | None,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Save a trained model with its configuration and dataset fingerprint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_save(
        {
            "format": CHECKPOINT_FORMAT,
            "learner": learner,
            "model_config": model.config,
            "model_state": model.state_dict(),
            "fingerprint": None if fingerprint is None else fingerprint.as_dict(),
            **dict(extra or {}),
        },
        path,
    )
    return path


def load_learner(
    path: str | os.PathLike[str],
    *,
    fingerprint: DatasetFingerprint | None = None,
    require_same_manifest: bool = True,
    device: str = "cpu",
) -> TailorNet | DisplacementMLP:
    """Load a model saved by :func:`save_learner`, checking the dataset fingerprint.

    The template must always match ``fingerprint``; the manifest too unless
    ``require_same_manifest`` is False (e.g. evaluating on a regenerated dataset).
    """
    checkpoint = load_checkpoint(path, map_location=device)
    check_fingerprint(
        checkpoint.get("fingerprint"), fingerprint, source=str(path), require_same_manifest=require_same_manifest
    )
    learner = checkpoint.get("learner")
    if learner == "tailornet":
        model: TailorNet | DisplacementMLP = TailorNet.from_config(checkpoint["model_config"])
    elif learner == "baseline":
        model = DisplacementMLP(**checkpoint["model_config"])
    else:
        raise ValueError(f"{path} holds learner '{learner}', expected 'tailornet' or 'baseline'")
    model.load_state_dict(checkpoint["model_state"])
    return model.to(device).eval()
