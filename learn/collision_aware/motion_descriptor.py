"""The motion descriptor gamma of seed 002 (Sec. 5, Eq. 17), per frame of a motion sequence.

    gamma_t = {theta_t, dtheta/dt, d2theta/dt2, dH/dt, d2H/dt2, dK/dt, d2K/dt2}

- theta: the garment-relevant pose entries [rad] (the MLP regressor's ``pose_indices``) less the
  root joint's. Seed 002 compresses the SMPL pose into a learned 10-d descriptor [52]; no such
  descriptor exists for the body models here, so the axis-angle entries are fed as they are;
- K: the root joint's (pelvis') rotation as Euler angles [rad] (R = Rz Ry Rx), through its
  derivatives only, as in the seed: the canonical garment depends on how the root turns, not on
  where it faces;
- H: the root joint's position [m] (``root_joint`` of motion shards, plus ``body_translation``
  where a dataset stores one), through its derivatives only.

Derivatives are backward finite differences over the frames' times ``frame_index / fps`` [s]
(dropped frames leave a longer step), so gamma_t depends on frames t, t-1, t-2 only: the
descriptor, like the GRU reading it, is causal. The first frame of a sequence has zero
velocity and acceleration, the second zero acceleration. Euler angle differences are wrapped to
(-pi, pi], so a turn across the angles' branch cut is a small step, not 2 pi.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from simulate.body.kinematics import axis_angle_to_matrix

#: Pose vector entries of the root joint (pelvis, ``POSE_JOINTS[0]``): its axis-angle [rad].
ROOT_POSE_ENTRIES = (0, 1, 2)


def descriptor_pose_indices(pose_indices: Any) -> list[int]:
    """The pose entries theta of the descriptor: ``pose_indices`` without the root's."""
    return [int(i) for i in np.asarray(pose_indices).reshape(-1) if int(i) not in ROOT_POSE_ENTRIES]


def descriptor_size(pose_entries: int) -> int:
    """Width of gamma for ``pose_entries`` theta entries: 3 per entry, 12 for the root."""
    return 3 * int(pose_entries) + 12


def euler_xyz(axis_angle: torch.Tensor) -> torch.Tensor:
    """Euler angles (x, y, z) [rad] of R = Rz Ry Rx for axis-angle rotations (..., 3)."""
    r = axis_angle_to_matrix(axis_angle)
    x = torch.atan2(r[..., 2, 1], r[..., 2, 2])
    y = torch.asin((-r[..., 2, 0]).clamp(-1.0, 1.0))
    z = torch.atan2(r[..., 1, 0], r[..., 0, 0])
    return torch.stack([x, y, z], dim=-1)


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2.0 * math.pi) - math.pi


def _derivatives(x: torch.Tensor, dt: torch.Tensor, *, angles: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Backward first and second differences of x (B, T, C) over steps dt (B, T) [s] (dt[:, 0]
    unused); zero where the frames before are missing."""
    step = x[:, 1:] - x[:, :-1]
    if angles:
        step = _wrap(step)
    zero = torch.zeros_like(x[:, :1])
    velocity = torch.cat([zero, step / dt[:, 1:, None]], dim=1)
    acceleration = torch.cat([zero, zero, (velocity[:, 2:] - velocity[:, 1:-1]) / dt[:, 2:, None]], dim=1)
    return velocity, acceleration[:, :x.shape[1]]


def motion_descriptor(pose: torch.Tensor, time: torch.Tensor, root: torch.Tensor | None,
                      pose_indices: torch.Tensor) -> torch.Tensor:
    """gamma (B, T, 3 P' + 12) of B sequences of T frames.

    pose: (B, T, P) axis-angle [rad]; time: (B, T) [s], increasing along each sequence (padding
    after a sequence's end may hold anything that keeps the steps non-zero); root: (B, T, 3) root
    joint position [m] or None (a body that does not translate); pose_indices: (P',) the theta
    entries (:func:`descriptor_pose_indices`).
    """
    if pose.ndim != 3 or time.shape != pose.shape[:2]:
        raise ValueError(f"motion_descriptor expects pose (B, T, P) and time (B, T), got {tuple(pose.shape)} "
                         f"and {tuple(time.shape)}")
    dt = torch.cat([torch.ones_like(time[:, :1]), time[:, 1:] - time[:, :-1]], dim=1)
    if bool((dt[:, 1:] <= 0).any()):
        raise ValueError("motion_descriptor: frame times must increase along each sequence")
    theta = pose[..., pose_indices]
    d_theta, dd_theta = _derivatives(theta, dt)
    root_h = torch.zeros_like(pose[..., :3]) if root is None else root.to(pose.dtype)
    d_h, dd_h = _derivatives(root_h, dt)
    d_k, dd_k = _derivatives(euler_xyz(pose[..., list(ROOT_POSE_ENTRIES)]), dt, angles=True)
    return torch.cat([theta, d_theta, dd_theta, d_h, dd_h, d_k, dd_k], dim=-1)


def motion_fps(spec: Any) -> float | None:
    """Frame rate [1/s] of a dataset whose spec (``manifest.spec``) has ``poses.source:
    motion`` (docs/motion.md; ``motion.fps``, default 15); None for a quasi-static dataset."""
    if not isinstance(spec, dict) or (spec.get("poses") or {}).get("source") != "motion":
        return None
    return float((spec.get("motion") or {}).get("fps", 15))


def sequence_rows(sequence: np.ndarray, frame_index: np.ndarray) -> list[np.ndarray]:
    """Rows of each sequence, in frame order: one array per distinct ``sequence`` value (N,)
    (in order of first appearance), its rows sorted by ``frame_index`` (N,), which must not
    repeat within a sequence."""
    sequence, frame_index = np.asarray(sequence).reshape(-1), np.asarray(frame_index).reshape(-1)
    if sequence.shape != frame_index.shape:
        raise ValueError(f"sequence ({sequence.shape}) and frame_index ({frame_index.shape}) must have one value per frame")
    _, first = np.unique(sequence, return_index=True)
    out = []
    for value in sequence[np.sort(first)]:
        rows = np.flatnonzero(sequence == value)
        rows = rows[np.argsort(frame_index[rows], kind="stable")]
        if np.any(np.diff(frame_index[rows]) <= 0):
            raise ValueError(f"sequence {value} repeats a frame_index: frames of a sequence must have distinct indices")
        out.append(rows)
    return out


def padded(rows: list[np.ndarray], values: np.ndarray, fill: float = 0.0) -> np.ndarray:
    """``values`` (N, ...) gathered into (len(rows), T_max, ...) by ``rows``, ``fill`` after each
    sequence's end."""
    length = max(len(r) for r in rows)
    out = np.full((len(rows), length, *values.shape[1:]), fill, dtype=values.dtype)
    for k, r in enumerate(rows):
        out[k, :len(r)] = values[r]
    return out


def padded_times(rows: list[np.ndarray], frame_index: np.ndarray, fps: float) -> np.ndarray:
    """Frame times [s] (len(rows), T_max) of each sequence, continued one frame step at a time
    after its end (so that padding keeps the steps positive)."""
    length = max(len(r) for r in rows)
    out = np.empty((len(rows), length), np.float64)
    for k, r in enumerate(rows):
        t = np.asarray(frame_index, np.float64)[r]
        out[k, :len(r)] = t
        out[k, len(r):] = t[-1] + np.arange(1, length - len(r) + 1)
    return (out / float(fps)).astype(np.float32)
