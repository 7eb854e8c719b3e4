"""Evaluation of a trained learner on one split: errors, collisions, inference time.

Metrics follow the paper and REFERENCE.md: mean per-vertex Euclidean error [mm] on the
unposed displacements (what TailorNet reports) and on the posed garment; collision
rate (fraction of garment vertices more than 1 mm inside the body along the nearest
body face normal) of the posed prediction, without and with the Laplacian-preserving
post-process; inference time per frame at batch 1 and batched.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from learn.common.collision import COLLISION_THRESHOLD_M, BodyMeshes, collision_mask
from learn.common.losses import per_vertex_error_mm
from learn.common.normals import normal_error
from learn.common.postprocess import remove_body_penetration_batch, warm_pool
from learn.tailornet.model import GarmentPoser, UnposedBody, pose_displacements
from learn.tailornet.train import FrameArrays

TIMING_BUDGET_S = 1.0
"""Seconds of timed calls per (model, device, batch size) when one call is slow
(:func:`time_inference`)."""

# (pose (B, P), shape (B, S)) -> posed body vertices [m], (B, Vb, 3).
PosedBodyFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class PosingContext:
    """What posed metrics need, all as injected callables (no body model import here).

    unposed_body: shape -> unposed body vertex under each garment vertex, (B, V, 3).
    garment_poser: (unposed garment vertices, pose, shape) -> posed garment, (B, V, 3).
    posed_body: (pose, shape) -> posed body vertices, (B, Vb, 3).
    body_faces: body triangles, shape (Fb, 3).
    garment_faces: garment triangles, shape (F, 3).
    """

    unposed_body: UnposedBody
    garment_poser: GarmentPoser
    posed_body: PosedBodyFn
    body_faces: np.ndarray
    garment_faces: np.ndarray


def predict_on_device(
    model: torch.nn.Module,
    pose: np.ndarray,
    shape: np.ndarray,
    style: np.ndarray,
    *,
    batch_size: int = 256,
    device: str = "cpu",
) -> torch.Tensor:
    """Unposed displacements [m] for N frames as one float32 tensor on ``device``, (N, V, 3).

    The inputs go to the device once; batches are slices of them and the predictions stay
    there (no host copy per batch). For a model with ``recurrent`` true the N frames are one
    sequence, consecutive frames in order."""
    model = model.to(device).eval()
    if getattr(model, "recurrent", False):  # the rows are one sequence: run in order whatever the batch size
        n = np.asarray(pose).shape[0]
        return model.predict_frames(pose, shape, style, np.zeros(n, np.int64), np.arange(n), batch_size=batch_size,
                                    device=device)
    inputs = [torch.as_tensor(np.asarray(a), dtype=torch.float32).to(device) for a in (pose, shape, style)]
    with torch.no_grad():
        out = [model(*(x[start:start + batch_size] for x in inputs)).float()
               for start in range(0, inputs[0].shape[0], batch_size)]
    return torch.cat(out, dim=0)


@torch.no_grad()
def predict_displacements(
    model: torch.nn.Module,
    pose: np.ndarray,
    shape: np.ndarray,
    style: np.ndarray,
    *,
    batch_size: int = 256,
    device: str = "cpu",
) -> np.ndarray:
    """Unposed displacements [m], shape (N, V, 3), for N frames (model in eval mode)."""
    return predict_on_device(model, pose, shape, style, batch_size=batch_size, device=device).cpu().numpy()


def evaluate_split(model: torch.nn.Module, data: FrameArrays, **options: Any) -> dict[str, Any]:
    """Metrics of ``model`` on the frames of one split: :func:`evaluate_split_models` of it alone,
    with the same keyword options."""
    return evaluate_split_models({"model": model}, data, **options)["model"]


def sequence_root(data: FrameArrays) -> np.ndarray | None:
    """Each frame's root motion [m] (N, 3) for a recurrent model: the root joint plus the frame's
    translation, whichever the split carries (None when neither)."""
    root = data.root_joint
    if data.translation is not None:
        root = data.translation if root is None else root + data.translation
    return root


def _predict_split(model: torch.nn.Module, data: FrameArrays, batch_size: int, device: str) -> torch.Tensor:
    """Unposed displacements of every frame of ``data`` on ``device``, (N, V, 3); a recurrent model
    runs the split's sequences in frame order."""
    if getattr(model, "recurrent", False):  # each sequence through in frame order, state carried across frames
        if data.sequence is None or data.frame_index is None:
            raise ValueError("a recurrent model needs each frame's sequence and frame_index (FrameArrays.sequence, "
                             ".frame_index) to run the split's sequences in order")
        predicted = model.predict_frames(data.pose, data.shape, data.style, data.sequence, data.frame_index,
                                         sequence_root(data),
                                         batch_size=batch_size, device=device)
    else:
        predicted = predict_on_device(model, data.pose, data.shape, data.style, batch_size=batch_size, device=device)
    if tuple(predicted.shape) != data.displacements.shape:
        raise ValueError(
            f"model predicts {predicted.shape[1]} vertices but the data has {data.vertex_count}"
        )
    return predicted


def evaluate_split_models(
    models: dict[str, torch.nn.Module],
    data: FrameArrays,
    *,
    posing: PosingContext | None = None,
    postprocess: bool = True,
    batch_size: int = 256,
    device: str = "cpu",
    collision_device: str | None = None,
    threshold: float = COLLISION_THRESHOLD_M,
    postprocess_frames: int | None = None,
    postprocess_workers: int = 1,
    truth_cache: dict[str, Any] | None = None,
    per_frame: bool = False,
) -> dict[str, dict[str, Any]]:
    """Metrics of each of ``models`` (name -> model) on the frames of one split, by name.

    Each result has ``frames``, ``unposed_error_mm`` (mean over frames of the mean
    per-vertex error), and with ``posing`` given: ``posed_error_mm`` and
    ``normal_error`` (mean 1 - cos of predicted and true vertex normals, seed 001) when
    ``data.posed_vertices`` is set, ``collision_rate`` of predictions and of the ground
    truth, and with ``postprocess`` ``collision_rate_postprocessed`` and
    ``postprocessed_posed_error_mm``. ``data.translation`` (when set) is added to the
    posed garment and body. The post-process (a sparse solve per frame on the CPU, about
    a second for 10k vertices, spread over ``postprocess_workers`` processes) runs on at
    most ``postprocess_frames`` evenly spaced frames when given;
    ``postprocess_frames_evaluated`` reports how many, and the post-processed rates and
    errors refer to those frames (``collision_rate_subset`` and ``posed_error_mm_subset``
    give the raw values on the same frames, for a like-for-like comparison).

    A model with ``recurrent`` true (the collision-aware learner's GRU regressor) predicts with
    ``model.predict_frames``: every sequence of the split run in frame order, the root joint
    (plus ``data.translation``) feeding its root motion.
    Prediction, posing and errors run on ``device`` in batches of ``batch_size`` frames. Each
    batch's body is posed once and its BVHs built once (:class:`learn.common.collision.BodyMeshes`,
    on ``collision_device``) for the ground truth and every model; the collision queries get one
    host copy of each batch. The ground truth's collision count depends on the split only: pass the
    same ``truth_cache`` dict for every call on a split to count it once.
    ``per_frame``: also return ``unposed_error_mm_per_frame`` (N,) as a numpy array (for the
    error analysis; not JSON).
    """
    if postprocess_frames is not None and postprocess_frames < 1:
        raise ValueError(f"postprocess_frames must be >= 1 or None, got {postprocess_frames}")
    if data.frame_count == 0:
        raise ValueError("evaluate_split: the split has no frames")
    if not models:
        raise ValueError("evaluate_split_models: no models")
    if posing is not None and postprocess:
        warm_pool(postprocess_workers)  # the workers start while the models predict
    predicted = {name: _predict_split(model, data, batch_size, device) for name, model in models.items()}
    results: dict[str, dict[str, Any]] = {}
    for name, prediction in predicted.items():
        errors = torch.cat([
            per_vertex_error_mm(prediction[start:start + batch_size],
                                torch.as_tensor(data.displacements[start:start + batch_size]).to(device))
            for start in range(0, data.frame_count, batch_size)
        ])
        results[name] = {"frames": data.frame_count, "unposed_error_mm": float(errors.mean())}
        if per_frame:
            results[name]["unposed_error_mm_per_frame"] = errors.cpu().numpy()
    if posing is None:
        return results
    names = list(models)
    posed_errors: dict[str, list] = {n: [] for n in names}
    normal_errors: dict[str, list] = {n: [] for n in names}
    colliding = dict.fromkeys(names, 0)
    pp_posed: dict[str, list] = {n: [] for n in names}
    pp_colliding = dict.fromkeys(names, 0)
    colliding_truth = vertex_total = 0
    if postprocess_frames is None or postprocess_frames >= data.frame_count:
        pp_selected = np.ones(data.frame_count, dtype=bool)
    else:
        pp_selected = np.zeros(data.frame_count, dtype=bool)
        pp_selected[np.linspace(0, data.frame_count - 1, postprocess_frames).round().astype(np.int64)] = True
    count_truth = data.posed_vertices is not None and (truth_cache is None or "colliding" not in truth_cache)
    pp_body, pp_truth = [], []
    with torch.no_grad():
        for start in range(0, data.frame_count, batch_size):
            stop = start + batch_size
            pose = torch.as_tensor(data.pose[start:stop], dtype=torch.float32).to(device)
            shape = torch.as_tensor(data.shape[start:stop], dtype=torch.float32).to(device)
            body_t = posing.posed_body(pose, shape).to(device)
            shift = None
            if data.translation is not None:
                # A root translation moves body and garment rigidly, after skinning.
                shift = torch.as_tensor(data.translation[start:stop, None, :]).to(device)
                body_t = body_t + shift
            body = body_t.cpu().numpy()
            meshes = BodyMeshes(body, posing.body_faces, device=collision_device)
            vertex_total += body.shape[0] * data.vertex_count
            chosen = np.flatnonzero(pp_selected[start:stop])
            truth = truth_t = None
            if data.posed_vertices is not None:
                truth = data.posed_vertices[start:stop]
                truth_t = torch.as_tensor(truth).to(device)
                if count_truth:
                    colliding_truth += int(collision_mask(truth, None, posing.body_faces, threshold=threshold,
                                                          meshes=meshes).sum())
            if postprocess and chosen.size:
                pp_body.append(body[chosen])
                if truth is not None:
                    pp_truth.append(truth[chosen])
            for name in names:
                posed_t = pose_displacements(predicted[name][start:stop], pose, shape,
                                             garment_poser=posing.garment_poser, unposed_body=posing.unposed_body)
                if shift is not None:
                    posed_t = posed_t + shift
                posed = posed_t.cpu().numpy()
                mask = collision_mask(posed, None, posing.body_faces, threshold=threshold, meshes=meshes)
                colliding[name] += int(mask.sum())
                if truth_t is not None:
                    posed_errors[name].append(per_vertex_error_mm(posed_t, truth_t))
                    normal_errors[name].append(normal_error(posed_t, truth_t, posing.garment_faces))
                if postprocess and chosen.size:
                    pp_posed[name].append(posed[chosen])
                    pp_colliding[name] += int(mask[chosen].sum())
            del meshes
    if data.posed_vertices is not None:
        if count_truth and truth_cache is not None:
            truth_cache["colliding"] = colliding_truth
        if truth_cache is not None:
            colliding_truth = truth_cache["colliding"]
    for name in names:
        result = results[name]
        result["collision_rate"] = colliding[name] / vertex_total
        if data.posed_vertices is not None:
            result["posed_error_mm"] = float(torch.cat(posed_errors[name]).mean())
            result["normal_error"] = float(torch.cat(normal_errors[name]).mean())
            result["ground_truth_collision_rate"] = colliding_truth / vertex_total
        if postprocess:
            started = time.perf_counter()
            posed_chosen, body_chosen = np.concatenate(pp_posed[name]), np.concatenate(pp_body)
            fixed, _, after = remove_body_penetration_batch(
                posed_chosen, posing.garment_faces, body_chosen, posing.body_faces, device=collision_device,
                threshold=threshold, workers=postprocess_workers,
            )
            result["postprocess_seconds"] = round(time.perf_counter() - started, 3)
            pp_vertex_total = posed_chosen.shape[0] * posed_chosen.shape[1]
            result["postprocess_frames_evaluated"] = int(pp_selected.sum())
            result["collision_rate_subset"] = pp_colliding[name] / pp_vertex_total
            result["collision_rate_postprocessed"] = int(after.sum()) / pp_vertex_total
            if pp_truth:
                truth_chosen = torch.from_numpy(np.concatenate(pp_truth))
                result["posed_error_mm_subset"] = float(per_vertex_error_mm(torch.from_numpy(posed_chosen),
                                                                            truth_chosen).mean())
                result["postprocessed_posed_error_mm"] = float(per_vertex_error_mm(torch.from_numpy(fixed),
                                                                                   truth_chosen).mean())
    return results


def _synchronize(device: str) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize(device)


@torch.no_grad()
def time_inference(
    model: torch.nn.Module,
    pose: np.ndarray,
    shape: np.ndarray,
    style: np.ndarray,
    *,
    batch_sizes: tuple[int, ...] = (1, 32),
    device: str = "cpu",
    repeats: int = 20,
    warmup: int = 3,
    budget_s: float = TIMING_BUDGET_S,
) -> dict[str, float]:
    """Inference time [ms per frame] of the unposed prediction at each batch size.

    Frames are cycled from the given arrays (N >= 1); the median over ``repeats`` timed
    calls is reported as ``ms_per_frame_batch_<b>``. A call slower than a tenth of
    ``budget_s`` [s] is warmed up once and timed ``max(3, budget_s / its duration)`` times
    instead, so a slow model on the CPU (uvimage: ~1.3 s per batch of 32) is not timed for
    half a minute.
    """
    if pose.shape[0] == 0:
        raise ValueError("time_inference needs at least one frame")
    model = model.to(device).eval()
    result: dict[str, float] = {}
    for batch in batch_sizes:
        if batch < 1:
            raise ValueError(f"batch sizes must be >= 1, got {batch}")
        index = np.arange(batch) % pose.shape[0]
        inputs = [torch.as_tensor(a[index], dtype=torch.float32, device=device) for a in (pose, shape, style)]
        started = time.perf_counter()
        model(*inputs)
        _synchronize(device)
        first = time.perf_counter() - started
        count = repeats
        if first > 0.1 * budget_s:
            count = max(3, min(repeats, int(budget_s / first)))
        else:
            for _ in range(warmup - 1):
                model(*inputs)
            _synchronize(device)
        times = []
        for _ in range(count):
            started = time.perf_counter()
            model(*inputs)
            _synchronize(device)
            times.append(time.perf_counter() - started)
        result[f"ms_per_frame_batch_{batch}"] = float(np.median(times) * 1000.0 / batch)
    return result


@torch.no_grad()
def predict_vertices(
    model: torch.nn.Module,
    pose: np.ndarray,
    shape: np.ndarray,
    style: np.ndarray,
    *,
    posing: PosingContext | None = None,
    translation: np.ndarray | None = None,
    postprocess: bool = False,
    device: str = "cpu",
    collision_device: str | None = None,
) -> np.ndarray:
    """Garment vertices [m] for N frames, shape (N, V, 3) (what ``drape predict`` writes).

    Without ``posing``: the unposed displacements. With it: the posed garment, shifted by
    ``translation`` [m] (N, 3) when given, and with ``postprocess`` pushed out of the body.
    pose (N, P), shape (N, S), style (N, G); a single frame may be given as 1-D arrays.
    """
    arrays = [np.atleast_2d(np.asarray(a, dtype=np.float32)) for a in (pose, shape, style)]
    displacements = predict_displacements(model, *arrays, device=device)
    if posing is None:
        return displacements
    pose_t, shape_t = (torch.as_tensor(a, device=device) for a in arrays[:2])
    posed = pose_displacements(
        torch.as_tensor(displacements, device=device), pose_t, shape_t,
        garment_poser=posing.garment_poser, unposed_body=posing.unposed_body,
    ).cpu().numpy()
    shift = 0.0 if translation is None else np.atleast_2d(np.asarray(translation, np.float32))[:, None, :]
    posed = posed + shift
    if postprocess:
        body = posing.posed_body(pose_t, shape_t).cpu().numpy() + shift
        posed, _, _ = remove_body_penetration_batch(
            posed, posing.garment_faces, body, posing.body_faces, device=collision_device
        )
    return posed


def evaluate_models(
    models: dict[str, torch.nn.Module],
    splits: dict[str, FrameArrays],
    *,
    posing: PosingContext | None = None,
    postprocess: bool = True,
    postprocess_frames: int | None = None,
    device: str = "cpu",
    timing_devices: tuple[str, ...] = ("cpu",),
    timing_batch_sizes: tuple[int, ...] = (1, 32),
    collision_device: str | None = None,
    postprocess_workers: int = 1,
) -> dict[str, Any]:
    """Every model on every split plus inference timings: the body of ``drape evaluate``.

    Returns ``{"splits": {split: {model: metrics}}, "timing": {model: {device: {...}}}}``
    with metrics from :func:`evaluate_split` and timings from :func:`time_inference`
    (on the first split's frames). JSON-serialisable. A model with ``decoder_only()``
    (the UV-image learners: their full forward also poses the body and unskins) also
    gets ``decoder_ms_per_frame_batch_<b>``: its network alone, as seed 001 times it.
    ``phase_seconds``: the splits' metrics (of them the post-process) and the timings [s].
    """
    if not models or not splits:
        raise ValueError(f"need at least one model and one split, got {sorted(models)} and {sorted(splits)}")
    report: dict[str, Any] = {"splits": {}, "timing": {}}
    started = time.perf_counter()
    for split, data in splits.items():  # every model at once: a batch's body is posed and its BVHs built once
        report["splits"][split] = evaluate_split_models(
            models, data, posing=posing, postprocess=postprocess, postprocess_frames=postprocess_frames,
            device=device, collision_device=collision_device, postprocess_workers=postprocess_workers,
        )
    predicted = time.perf_counter()
    first = next(iter(splits.values()))
    for name, model in models.items():
        report["timing"][name] = {
            timing_device: time_inference(
                model, first.pose, first.shape, first.style, batch_sizes=timing_batch_sizes, device=timing_device
            )
            for timing_device in timing_devices
        }
        if hasattr(model, "decoder_only"):
            for timing_device in timing_devices:
                decoder = time_inference(model.decoder_only(), first.pose, first.shape, first.style,
                                         batch_sizes=timing_batch_sizes, device=timing_device)
                report["timing"][name][timing_device].update({f"decoder_{k}": v for k, v in decoder.items()})
        model.to(device)
    postprocess_s = sum(m.get("postprocess_seconds", 0.0) for per_model in report["splits"].values()
                        for m in per_model.values())
    report["phase_seconds"] = {"splits": round(predicted - started, 2), "postprocess": round(postprocess_s, 2),
                               "timing": round(time.perf_counter() - predicted, 2)}
    return report
