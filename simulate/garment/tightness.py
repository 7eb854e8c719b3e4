"""Tightness (seed 004, Sec. 3.2-3.3): a garment is sized for the body shape beta + tau, and
the body is blended from beta + tau to beta before the sequence, so a loose garment (tau > 0)
hangs on the real body and a tight one (tau < 0) is stretched onto it.

tau is two offsets added to the shape parameters named by
:data:`simulate.garment.cloth3d.CLOTH3D` ``.tightness_parameters`` (anny's height and weight:
the stand-ins for SMPL's global size and fatness), each sampled uniformly in
``CLOTH3D.tightness_range``; positive means looser. Shapes are clipped to the body's parameter
ranges.
"""
from __future__ import annotations

import numpy as np

from simulate.garment.cloth3d import CLOTH3D


def tightness_offsets(body, tau) -> np.ndarray:
    """The shape offset (S,) of a tightness ``tau``: a scalar (the same offset on both tightness
    parameters) or a 2-vector (one per parameter, in ``CLOTH3D.tightness_parameters`` order)."""
    t = np.asarray(tau, dtype=np.float64).reshape(-1)
    names = CLOTH3D.tightness_parameters
    if t.size == 1:
        t = np.repeat(t, len(names))
    if t.size != len(names) or not np.isfinite(t).all():
        raise ValueError(f"tightness must be one finite number or {len(names)} ({', '.join(names)}), got {tau!r}")
    missing = [n for n in names if n not in body.shape_names]
    if missing:
        raise ValueError(f"body {body.name!r} has no shape parameter {', '.join(missing)} for the tightness offsets; "
                         f"its parameters: {', '.join(body.shape_names)}")
    out = np.zeros(body.shape_size)
    for name, value in zip(names, t):
        out[body.shape_names.index(name)] = value
    return out


def sized_shape(body, shape, tau) -> np.ndarray:
    """The shape a garment of tightness ``tau`` is sized for: ``shape`` + offsets, clipped to the
    body's parameter ranges, (S,) float32."""
    s = np.asarray(shape, dtype=np.float64).reshape(-1)
    if s.shape != (body.shape_size,):
        raise ValueError(f"shape must have {body.shape_size} values, got {s.shape}")
    lo, hi = body.shape_ranges[:, 0], body.shape_ranges[:, 1]
    return np.clip(s + tightness_offsets(body, tau), lo, hi).astype(np.float32)


def shape_blend(start_shape, shape, frames: int) -> np.ndarray:
    """The body shapes (frames, S) of the transition from ``start_shape`` (beta + tau) to ``shape``
    (beta): frame k (1-based) is start + (shape - start) * k / frames, so the last is ``shape``.
    The same blend as ``simulate.sequence.schedule.build_schedule``'s shape transition."""
    if int(frames) != frames or frames < 1:
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    a = np.asarray(start_shape, np.float64).reshape(1, -1)
    b = np.asarray(shape, np.float64).reshape(1, -1)
    if a.shape != b.shape:
        raise ValueError(f"start_shape and shape must have the same size, got {a.shape[1]} and {b.shape[1]}")
    blend = (np.arange(1, int(frames) + 1) / int(frames))[:, None]
    return (a * (1 - blend) + b * blend).astype(np.float32)


def sample_tightness(count: int, *, seed: int = 0, tightness_range=None) -> np.ndarray:
    """``count`` tightness 2-vectors (count, 2) drawn uniformly (seeded) from ``tightness_range``
    ((lo, hi) per parameter; default ``CLOTH3D.tightness_range``)."""
    ranges = np.asarray(CLOTH3D.tightness_range if tightness_range is None else tightness_range, np.float64)
    rng = np.random.default_rng(seed)
    return rng.uniform(ranges[:, 0], ranges[:, 1], size=(int(count), len(ranges))).astype(np.float32)
