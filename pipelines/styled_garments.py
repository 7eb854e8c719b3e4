"""The rest geometry of a dataset's garments (``Plan.garments``: a style, sized for a shape), made
by worker processes side by side.

One garment is ~0.2-1 s of NumPy, SciPy and CPU torch (hems slid along the body surface,
``simulate.garment.templates.generate_garment``), and a cloth3d type has 500 of them: one after
another they were most of the time before its first simulator frame. Each garment depends only on
its style, its shape, the template and the body model, so workers make them in any order and the
result is the same array as one process makes: every worker loads the same body model, runs torch
on as many threads as the caller (a CPU reduction's rounding can depend on the thread count) and
returns its garments in plan order.
"""
from __future__ import annotations

import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Callable

import numpy as np

#: Garments per worker at least: a worker's start (imports, the body model) costs a few garments.
GARMENTS_PER_WORKER = 8

_WORKER: dict[str, Any] = {}  # in a worker process: its body model


def _start_worker(backend: str, path: str | None, torch_threads: int) -> None:
    import torch

    from simulate.body import load_body_model

    torch.set_num_threads(torch_threads)
    _WORKER["body"] = load_body_model(backend, path=path)


def _make(gtype: str, template: Any, jobs: list[tuple[Any, np.ndarray | None]], body: Any = None) -> list[np.ndarray]:
    """Rest vertices (V, 3) float32 of each job, on ``body`` (default: this worker's)."""
    from simulate.garment.templates import generate_garment

    body = _WORKER["body"] if body is None else body
    return [np.asarray(generate_garment(gtype, style, body, template=template, shape=shape), np.float32)
            for style, shape in jobs]


def worker_count(garments: int, cpus: int | None = None) -> int:
    """Worker processes for ``garments`` garments: one per ``GARMENTS_PER_WORKER`` garments, at
    most one per CPU; 1 means in this process (also inside a daemon process, which may not start
    any)."""
    cpus = (os.cpu_count() or 1) if cpus is None else int(cpus)
    if multiprocessing.current_process().daemon:
        return 1
    return max(1, min(cpus, garments // GARMENTS_PER_WORKER))


def styled_garments(gtype: str, jobs: list[tuple[Any, np.ndarray | None]], body: Any, template: Any, *,
                    backend: str, body_path: str | None = None, workers: int | None = None,
                    meanwhile: Callable[[], Any] | None = None) -> np.ndarray:
    """Rest vertices [m] of each garment, (n, V, 3) float32, in the order of ``jobs``.

    Args:
        gtype: garment type of the template.
        jobs: (style (StyleParams), shape (S,) it is sized for, or None: the neutral shape) per garment.
        body: the body model (used here when there is one worker).
        template: the type's GarmentTemplate.
        backend, body_path: how workers load the same body model (``load_body_model``).
        workers: worker processes (default ``worker_count``); 1: one after another in this process.
        meanwhile: called in this process while the workers make the garments (not at all
            without workers).
    """
    import torch

    workers = worker_count(len(jobs)) if workers is None else int(workers)
    if workers <= 1 or len(jobs) < 2:
        return np.stack(_make(gtype, template, jobs, body))
    size = math.ceil(len(jobs) / (4 * workers))  # a few chunks per worker: the slow ones even out
    chunks = [jobs[i:i + size] for i in range(0, len(jobs), size)]
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=_start_worker, initargs=(backend, body_path, torch.get_num_threads())) as pool:
        parts = pool.map(_make, [gtype] * len(chunks), [template] * len(chunks), chunks)  # submitted at once
        if meanwhile is not None:
            meanwhile()
        parts = list(parts)
    return np.stack([g for part in parts for g in part])
