"""Motions: pose trajectories sampled at a fixed frame rate (seed 004, section 3.1), from
``.npz`` files or from a seeded procedural generator (walk, arm raise, torso twist, squat).

A motion is ``poses`` (F, 60) float32, axis-angle [rad] of the 20 joints of
:data:`simulate.body.base.POSE_JOINTS` in that order (SMPL's first 20 joints: pelvis,
left_hip, right_hip, spine1, left_knee, right_knee, spine2, left_ankle, right_ankle, spine3,
neck, left_collar, right_collar, head, left_shoulder, right_shoulder, left_elbow, right_elbow,
left_wrist, right_wrist), one row per frame, ``1 / fps`` seconds apart.

Procedural motions move a few joints along one axis each, as smooth periodic functions of time
about the base pose (the body's canonical pose): two-sided channels ``base + A sin(w t + phase)``
and one-sided ones ``base +- A (1 - cos(w t + phase)) / 2``, with ``A`` a share (``amplitude``
times the channel's reach) of the room between the base angle and the joint limit
(:data:`simulate.body.base.JOINT_LIMITS`) on that side (the nearer side for two-sided channels),
so every frame stays within the limits. The seed draws the tempo (x0.8 to x1.2) and each
channel's amplitude (x0.7 to x1.0).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from simulate.body.base import JOINT_LIMITS, POSE_JOINTS, POSE_SIZE

#: Largest axis-angle norm [rad] accepted in a motion file: a rotation needs at most pi; values
#: far beyond it are degrees or another convention.
MAX_ANGLE_RAD = 2.0 * math.pi

#: A channel: (joint, axis 0/1/2 = x/y/z, form, phase [rad], reach). Forms: "two" = base + A
#: sin(w t + phase) with A the room to the nearer limit; "pos" / "neg" = one-sided towards the
#: upper / lower limit, A (1 - cos(w t + phase)) / 2. ``reach`` (0, 1] scales the room: the share
#: of it the channel uses at ``amplitude`` 1 (a walk bends the knee half way, not to its limit).
Channel = tuple

#: Procedural motion kinds: cycle frequency [Hz] and channels. Axes follow the body frame (x the
#: body's left, y up, z forward): a hip flexes forward by a negative x rotation, a knee by a
#: positive one, the spine leans forward by a positive x rotation and twists about y, the left arm
#: rises sideways by a positive z rotation, the left elbow bends by a negative y rotation.
MOTION_KINDS: dict[str, tuple[float, tuple[Channel, ...]]] = {
    "walk": (1.0, (
        ("left_hip", 0, "two", 0.0, 1.0), ("right_hip", 0, "two", math.pi, 1.0),
        ("left_knee", 0, "pos", 0.0, 0.5), ("right_knee", 0, "pos", math.pi, 0.5),
        ("left_shoulder", 0, "two", math.pi, 0.5), ("right_shoulder", 0, "two", 0.0, 0.5),
        ("left_elbow", 1, "neg", 0.0, 0.3), ("right_elbow", 1, "pos", math.pi, 0.3),
        ("spine2", 1, "two", 0.0, 0.5),
    )),
    "arm_raise": (0.5, (
        ("left_shoulder", 2, "pos", 0.0, 1.0), ("right_shoulder", 2, "neg", 0.0, 1.0),
        ("left_collar", 2, "pos", 0.0, 1.0), ("right_collar", 2, "neg", 0.0, 1.0),
    )),
    "torso_twist": (0.5, (
        ("spine1", 1, "two", 0.0, 1.0), ("spine2", 1, "two", 0.0, 1.0), ("spine3", 1, "two", 0.0, 1.0),
        ("neck", 1, "two", math.pi, 0.5),
    )),
    "squat": (0.5, (
        ("left_hip", 0, "neg", 0.0, 1.0), ("right_hip", 0, "neg", 0.0, 1.0),
        ("left_knee", 0, "pos", 0.0, 1.0), ("right_knee", 0, "pos", 0.0, 1.0),
        ("spine1", 0, "pos", 0.0, 1.0),
    )),
}


@dataclass
class Motion:
    """A pose trajectory: ``poses`` (F, 60) float32 axis-angle [rad] in POSE_JOINTS order, one row
    per frame, ``fps`` frames per second; ``name`` says where it came from."""

    poses: np.ndarray
    fps: float
    name: str = ""

    def at_rate(self, fps: float, *, field: str = "motion.fps") -> "Motion":
        """This motion at ``fps``: every k-th frame for a rate k times ``fps`` (k a whole number;
        CLOTH3D downgrades its 120 fps sources the same way). Raises ValueError naming ``field``
        when the rates are not a whole multiple apart."""
        stride = self.fps / float(fps)
        k = int(round(stride))
        if k < 1 or abs(stride - k) > 1e-6 * max(stride, 1.0):
            raise ValueError(f"{field} is {fps:g} but {self.name or 'the motion'} runs at {self.fps:g} fps; the "
                             f"motion's rate must be a whole multiple of {field} (its frames are taken every k-th)")
        return Motion(self.poses[::k].copy(), float(fps), self.name)


def load_motion(path: str | Path, *, field: str = "motion.path") -> Motion:
    """Reads a motion ``.npz``: ``poses`` (F, 20, 3) (or (F, 60)) axis-angle [rad] in
    POSE_JOINTS order and ``fps`` (a number > 0); an optional ``joints`` array of names must
    equal POSE_JOINTS. Raises ValueError naming ``field``, the file, the value and what was
    expected (FileNotFoundError for a missing file)."""
    path = Path(path)
    where = f"{field}: {path}"
    if not path.is_file():
        raise FileNotFoundError(f"{where} does not exist; expected a .npz motion file with poses (F, 20, 3) and fps")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in data.files}
    except (OSError, EOFError, ValueError) as exc:
        raise ValueError(f"{where} is not a readable .npz file ({str(exc).splitlines()[0] if str(exc) else exc})") from None
    for key in ("poses", "fps"):
        if key not in arrays:
            raise ValueError(f"{where} has no array {key!r} (found {sorted(arrays)}); expected poses (F, 20, 3) "
                             f"axis-angle [rad] and fps (frames per second)")
    poses, fps = arrays["poses"], arrays["fps"]
    if "joints" in arrays:
        names = [str(n) for n in np.asarray(arrays["joints"]).reshape(-1)]
        if names != list(POSE_JOINTS):
            raise ValueError(f"{where}: joints is {names[:4]}{'...' if len(names) > 4 else ''} ({len(names)} names); "
                             f"expected the 20 names {', '.join(POSE_JOINTS)} in that order")
    if not np.issubdtype(poses.dtype, np.number) or np.issubdtype(poses.dtype, np.complexfloating):
        raise ValueError(f"{where}: poses must hold real numbers (got dtype {poses.dtype})")
    shape = poses.shape
    if poses.ndim == 2 and shape[1] == POSE_SIZE:
        poses = poses.reshape(len(poses), len(POSE_JOINTS), 3)
    if poses.ndim != 3 or poses.shape[1:] != (len(POSE_JOINTS), 3) or len(poses) == 0:
        hint = ""
        if poses.ndim == 3 and poses.shape[1] in (22, 24) and poses.shape[2] == 3:
            hint = f"; an SMPL pose of {poses.shape[1]} joints starts with these 20: pass poses[:, :20]"
        elif poses.ndim == 2 and poses.shape[1] in (66, 72):
            hint = f"; an SMPL pose of {poses.shape[1] // 3} joints starts with these 20: pass poses[:, :60]"
        raise ValueError(f"{where}: poses must have shape (F, 20, 3) or (F, 60) with F >= 1: axis-angle of "
                         f"{', '.join(POSE_JOINTS)} (got shape {shape}){hint}")
    poses = poses.astype(np.float64)
    if not np.isfinite(poses).all():
        bad = np.argwhere(~np.isfinite(poses))[0]
        raise ValueError(f"{where}: poses must be finite (frame {bad[0]}, joint {POSE_JOINTS[bad[1]]} is "
                         f"{poses[tuple(bad)]})")
    norms = np.linalg.norm(poses, axis=-1)
    if norms.max() > MAX_ANGLE_RAD:
        f, j = np.unravel_index(int(np.argmax(norms)), norms.shape)
        raise ValueError(f"{where}: poses must be axis-angle in radians, each joint's angle at most 2 pi "
                         f"(frame {f}, joint {POSE_JOINTS[j]} turns {norms[f, j]:.3g}; degrees?)")
    if fps.size != 1 or not np.issubdtype(fps.dtype, np.number):
        raise ValueError(f"{where}: fps must be one number, frames per second (got {fps.tolist()!r})")
    rate = float(fps.reshape(-1)[0])
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"{where}: fps must be a number > 0, frames per second (got {rate!r})")
    return Motion(poses.reshape(len(poses), POSE_SIZE).astype(np.float32), rate, path.name)


def procedural_motion(kind: str, frames: int, fps: float, rng: np.random.Generator, *,
                      amplitude: float = 0.5, base_pose: np.ndarray | None = None) -> Motion:
    """A seeded procedural motion of ``kind`` (:data:`MOTION_KINDS`), ``frames`` frames at ``fps``.

    Args:
        kind: walk, arm_raise, torso_twist or squat.
        frames: frame count (>= 1); fps: frames per second (> 0).
        rng: draws the tempo (x0.8 to x1.2 of the kind's frequency) and each channel's amplitude
            (x0.7 to x1.0 of ``amplitude``).
        amplitude: share in (0, 1] of the room between the base angle and the joint limit a
            channel reaches at most.
        base_pose: pose the motion moves about and starts from, (60,) (default zeros); joints the
            kind does not move keep it. Its angles are clipped to the limits first.
    Returns:
        the motion; every moved joint axis stays within :data:`JOINT_LIMITS`.
    """
    if kind not in MOTION_KINDS:
        raise ValueError(f"motion kind {kind!r} is unknown; expected one of {', '.join(MOTION_KINDS)}")
    if isinstance(frames, bool) or int(frames) != frames or frames < 1:
        raise ValueError(f"motion frames must be an integer >= 1 (got {frames!r})")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"motion fps must be a number > 0 (got {fps!r})")
    if not 0.0 < amplitude <= 1.0:
        raise ValueError(f"motion amplitude must be in (0, 1] (got {amplitude!r})")
    base = np.zeros(POSE_SIZE, np.float64) if base_pose is None else np.asarray(base_pose, np.float64).reshape(POSE_SIZE)
    frequency, channels = MOTION_KINDS[kind]
    tempo = rng.uniform(0.8, 1.2)
    scales = rng.uniform(0.7, 1.0, len(channels))
    t = np.arange(int(frames)) / float(fps)
    w = 2.0 * math.pi * frequency * tempo
    poses = np.tile(base.reshape(len(POSE_JOINTS), 3), (int(frames), 1, 1))
    for (joint, axis, form, phase, reach), scale in zip(channels, scales):
        lo, hi = JOINT_LIMITS[joint][axis]
        k = POSE_JOINTS.index(joint)
        b = float(np.clip(base[3 * k + axis], lo, hi))
        a = amplitude * reach * scale
        arg = w * t + phase
        if form == "two":
            angle = b + a * min(hi - b, b - lo) * np.sin(arg)
        elif form == "pos":
            angle = b + a * (hi - b) * (1.0 - np.cos(arg)) / 2.0
        else:
            angle = b - a * (b - lo) * (1.0 - np.cos(arg)) / 2.0
        poses[:, k, axis] = angle
    return Motion(poses.reshape(int(frames), POSE_SIZE).astype(np.float32), float(fps), f"{kind}")
