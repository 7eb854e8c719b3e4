"""Skinning of arbitrary points for numpy or torch callers (one torch implementation)."""
from __future__ import annotations

import numpy as np
import torch

from simulate.body import kinematics as kin


def _run(fn, points, weights, transforms):
    if isinstance(points, torch.Tensor):
        return fn(points, weights.to(points) if isinstance(weights, torch.Tensor) else kin.as_torch(weights, dtype=points.dtype, device=points.device),
                  transforms.to(points) if isinstance(transforms, torch.Tensor) else kin.as_torch(transforms, dtype=points.dtype, device=points.device))
    p = np.asarray(points)
    squeeze = p.ndim == 2
    t = np.asarray(transforms)
    if squeeze:
        p, t = p[None], (t[None] if t.ndim == 3 else t)
    out = fn(kin.as_torch(p, dtype=torch.float64), kin.as_torch(weights, dtype=torch.float64), kin.as_torch(t, dtype=torch.float64))
    out = out.numpy().astype(np.result_type(p.dtype, np.float32))
    return out[0] if squeeze else out


def lbs(points, weights, transforms):
    """Poses rest-space points: (B,N,3) or (N,3) points, (N,J) or (B,N,J) weights, (B,J,4,4) transforms."""
    return _run(kin.lbs, points, weights, transforms)


def inverse_lbs(points, weights, transforms):
    """Unposes posed points (inverse of :func:`lbs` for the same weights and transforms)."""
    return _run(kin.inverse_lbs, points, weights, transforms)
