"""Pose sources for datasets: a procedural sampler with per-joint limits (seed 001,
appendix D.3), pruning of self-intersecting poses, pose files, the greedy
nearest-pose visiting order and slerp interpolation between poses (seed 000, 5.3).

Poses are (N, 60) float32 arrays: axis-angle [rad] of :data:`POSE_JOINTS`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from simulate.body.base import JOINT_LIMITS, POSE_JOINTS, POSE_SIZE, BodyModel
from simulate.body.kinematics import axis_angle_to_matrix, matrix_to_axis_angle

#: Joints on the body's centre line: each axis from a mixture of two half-normals.
CENTRE_JOINTS = ("spine1", "spine2", "spine3", "neck", "head")
#: Limb joints: x uniform, z uniform in sin-space, y uniform, applied in x, z, y order.
LIMB_JOINTS = ("left_collar", "right_collar", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
               "left_wrist", "right_wrist", "left_hip", "right_hip", "left_knee", "right_knee",
               "left_ankle", "right_ankle")
#: Joints sampled by default for each garment type (others stay at the canonical pose).
GARMENT_POSE_JOINTS: dict[str, tuple[str, ...]] = {
    "upper": ("spine1", "spine2", "spine3", "neck", "left_collar", "right_collar", "left_shoulder", "right_shoulder",
              "left_elbow", "right_elbow"),
    "lower": ("spine1", "spine2", "left_hip", "right_hip", "left_knee", "right_knee"),
    "all": tuple(j for j in POSE_JOINTS if j != "pelvis"),
}


@dataclass
class PoseSampler:
    """Samples poses joint by joint inside :data:`JOINT_LIMITS` scaled by ``range_scale``.

    Args:
        joints: joints to sample (others are copied from ``base_pose``).
        range_scale: factor in (0, 1] on every limit (smaller = milder poses).
        base_pose: pose the unsampled joints keep, shape (60,) (default zeros).
        half_normal_sigma: sigma of the centre-line half-normals as a fraction of the limit.
    """

    joints: tuple[str, ...] = GARMENT_POSE_JOINTS["upper"]
    range_scale: float = 1.0
    base_pose: np.ndarray | None = None
    half_normal_sigma: float = 0.5

    def __post_init__(self) -> None:
        unknown = [j for j in self.joints if j not in POSE_JOINTS]
        if unknown:
            raise ValueError(f"poses.joints: unknown joint(s) {unknown}; expected names from {', '.join(POSE_JOINTS)}")
        if not 0.0 < self.range_scale <= 1.0:
            raise ValueError(f"poses.range_scale must be in (0, 1], got {self.range_scale}")

    def sample(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Draws ``count`` poses, shape (count, 60)."""
        base = np.zeros(POSE_SIZE, np.float32) if self.base_pose is None else np.asarray(self.base_pose, np.float32)
        poses = np.tile(base.reshape(len(POSE_JOINTS), 3), (count, 1, 1)).astype(np.float64)
        for joint in self.joints:
            limits = np.asarray(JOINT_LIMITS[joint], dtype=np.float64) * self.range_scale  # (3, 2)
            k = POSE_JOINTS.index(joint)
            if joint in CENTRE_JOINTS or joint == "pelvis":
                # one half-normal per direction, the direction picked with equal odds
                side = rng.random((count, 3)) < 0.5
                mag = np.abs(rng.normal(0.0, 1.0, (count, 3))) * self.half_normal_sigma
                angles = np.where(side, mag * limits[:, 1], mag * limits[:, 0])  # limits[:, 0] <= 0
                angles = np.clip(angles, limits[:, 0], limits[:, 1])
                poses[:, k] = angles
            else:
                ax = rng.uniform(limits[0, 0], limits[0, 1], count)
                lo, hi = np.sin(np.clip(limits[2], -np.pi / 2, np.pi / 2))
                az = np.arcsin(rng.uniform(lo, hi, count))  # uniform in sin-space: even over the sphere
                ay = rng.uniform(limits[1, 0], limits[1, 1], count)
                rx = axis_angle_to_matrix(torch.as_tensor(np.stack([ax, 0 * ax, 0 * ax], 1)))
                rz = axis_angle_to_matrix(torch.as_tensor(np.stack([0 * az, 0 * az, az], 1)))
                ry = axis_angle_to_matrix(torch.as_tensor(np.stack([0 * ay, ay, 0 * ay], 1)))
                poses[:, k] = matrix_to_axis_angle(ry @ rz @ rx).numpy()  # x first, then z, then y
        return poses.reshape(count, POSE_SIZE).astype(np.float32)


def sample_poses(
    body: BodyModel, shape: np.ndarray, count: int, sampler: PoseSampler, rng: np.random.Generator,
    *, prune: bool = True, margin: float = 0.01, max_rounds: int = 50, min_clearance: float | None = None,
    clearance_pairs: str = "upper", reasons: list | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``count`` valid poses, pruning self-intersecting ones.

    With ``min_clearance`` [m], poses whose skin clearance (``LimbClearance`` of
    ``CLEARANCE_PAIRS[clearance_pairs]``: arms to torso for tops, between the legs for bottoms)
    falls below it are pruned too: a garment cannot pass between parts that close.

    Returns:
        (poses (count, 60), pruned (M, 60): the rejected poses, recorded for provenance). A list
        passed as ``reasons`` is extended with why each pruned pose went, in order:
        "self_intersection" (capsule test) or "clearance".
    """
    from simulate.body.clearance import CLEARANCE_PAIRS, LimbClearance
    from simulate.body.mesh_utils import SelfIntersectionChecker

    if min_clearance is not None and not (np.isfinite(min_clearance) and min_clearance >= 0.0):
        raise ValueError(f"poses.min_clearance must be a distance >= 0 [m] (got {min_clearance!r})")
    if clearance_pairs not in CLEARANCE_PAIRS:
        raise ValueError(f"clearance pairs {clearance_pairs!r} are unknown; expected one of {', '.join(CLEARANCE_PAIRS)}")
    checker = SelfIntersectionChecker(body, shape, margin=margin) if prune else None
    # clearances are only compared with min_clearance: queries need not look further (much faster)
    clearance = LimbClearance(body, shape, CLEARANCE_PAIRS[clearance_pairs], max_distance=2.0 * float(min_clearance)) \
        if prune and min_clearance else None
    kept, pruned = [], []
    have = 0
    for _ in range(max_rounds):
        if have >= count:
            break
        batch = sampler.sample(max(2 * (count - have), 16), rng)
        if checker is not None:
            bad, _ = checker.check(batch)
            why = np.where(bad, "self_intersection", "")
            if clearance is not None:
                close = clearance.measure(batch[~bad]).min(axis=1) < min_clearance
                why[np.nonzero(~bad)[0][close]] = "clearance"
                bad[~bad] = close
            if reasons is not None:
                reasons.extend(why[bad].tolist())
            pruned.append(batch[bad])
            batch = batch[~bad]
        kept.append(batch)
        have += len(batch)
    poses = np.concatenate(kept)[:count] if kept else np.zeros((0, POSE_SIZE), np.float32)
    if len(poses) < count:
        raise ValueError(f"poses: only {len(poses)} of {count} sampled poses survived self-intersection pruning; "
                         "lower poses.range_scale" + (", poses.min_clearance" if min_clearance else "") + " or the count")
    return poses, (np.concatenate(pruned) if pruned else np.zeros((0, POSE_SIZE), np.float32))


def default_pose_joints(garment_type: str) -> str:
    """The joints a garment type's sampled poses move by default: lower for bottoms, all for the
    full-body dress and jumpsuit, upper for tops."""
    if garment_type in ("pants", "shorts", "skirt"):
        return "lower"
    return "all" if garment_type in ("dress", "jumpsuit") else "upper"


def spec_pose_sampling(poses: dict, garment_type: str, body: BodyModel) -> tuple[PoseSampler, dict]:
    """How a dataset spec samples its poses: the :class:`PoseSampler` of its ``poses`` section
    (``joints``, default :func:`default_pose_joints`; ``range_scale``; the body's canonical pose for
    the other joints) and :func:`sample_poses`'s pruning keywords (``min_clearance``,
    ``clearance_pairs``): ``sample_poses(body, shape, n, sampler, rng, **pruning)`` draws poses as
    the dataset's are drawn."""
    joints = poses["joints"] or default_pose_joints(garment_type)
    joints = GARMENT_POSE_JOINTS[joints] if isinstance(joints, str) else tuple(joints)
    sampler = PoseSampler(joints=joints, range_scale=float(poses["range_scale"]), base_pose=body.canonical_pose)
    kind = poses["joints"] if poses["joints"] in ("upper", "lower", "all") else default_pose_joints(garment_type)
    min_clearance = poses.get("min_clearance")
    return sampler, {"min_clearance": None if min_clearance is None else float(min_clearance), "clearance_pairs": kind}


def load_pose_file(path: str | Path, *, key: str = "poses") -> np.ndarray:
    """Reads poses from an .npz: ``poses`` of shape (N, 60) or (N, 20, 3), axis-angle [rad]."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"poses.path: pose file not found: {path}")
    try:
        with np.load(path) as data:
            if key not in data.files:
                raise ValueError(f"poses.path: {path} has no array {key!r} (found {data.files}); expected (N, {POSE_SIZE}) axis-angle poses")
            poses = np.asarray(data[key], dtype=np.float32)
    except (OSError, EOFError) as exc:
        raise ValueError(f"poses.path: {path} is not a readable .npz file ({exc})") from exc
    if poses.ndim == 3 and poses.shape[1:] == (len(POSE_JOINTS), 3):
        poses = poses.reshape(len(poses), POSE_SIZE)
    if poses.ndim != 2 or poses.shape[1] != POSE_SIZE or len(poses) == 0:
        raise ValueError(f"poses.path: {path}:{key} must have shape (N, {POSE_SIZE}) or (N, 20, 3), got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError(f"poses.path: {path}:{key} contains non-finite values")
    return poses


def joint_angle_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-joint rotation angle [rad] between poses a and b, shapes (..., 60) -> (..., 20)."""
    ra = axis_angle_to_matrix(torch.as_tensor(np.asarray(a, np.float64).reshape(*np.shape(a)[:-1], len(POSE_JOINTS), 3)))
    rb = axis_angle_to_matrix(torch.as_tensor(np.asarray(b, np.float64).reshape(*np.shape(b)[:-1], len(POSE_JOINTS), 3)))
    rel = ra.transpose(-1, -2) @ rb
    trace = rel[..., 0, 0] + rel[..., 1, 1] + rel[..., 2, 2]
    return torch.acos(((trace - 1) / 2).clamp(-1, 1)).numpy()


def greedy_order(poses: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Visiting order: from ``start``, repeatedly the nearest unvisited pose (largest
    per-joint angle change as the distance, as the interpolation criterion uses).

    Each pose's joint rotation matrices are made once; the angle between two rotations falls as
    the trace of their relative rotation, tr(Ra^T Rb) = sum(Ra * Rb), rises, so each step is one
    elementwise product over all poses (2,600 poses: ~2 s on one CPU core; the loop that rebuilt
    the matrices at every step took ~3 s per 1,000 steps).

    Args:
        poses: (N, 60) axis-angle poses [rad].
        start: (60,) pose the order starts from (not part of it).
    Returns:
        (N,) int64 permutation of ``range(N)``.
    """
    n = len(poses)
    if n == 0:
        return np.zeros(0, np.int64)
    both = np.concatenate([np.asarray(start, np.float64).reshape(1, POSE_SIZE), np.asarray(poses, np.float64)])
    flat = axis_angle_to_matrix(torch.as_tensor(both.reshape(n + 1, len(POSE_JOINTS), 3))).reshape(n + 1, -1).numpy()
    rot = np.ascontiguousarray(flat[1:])  # (N, 20 * 9)
    visited = np.zeros(n, bool)
    order = np.empty(n, np.int64)
    current = flat[0]
    for k in range(n):
        trace = (rot * current).reshape(n, len(POSE_JOINTS), 9).sum(-1)  # (N, 20) tr(R_current^T R_pose)
        # the largest joint angle is the smallest trace's: arccos is decreasing
        d = np.arccos(np.clip((trace.min(axis=1) - 1.0) / 2.0, -1.0, 1.0))
        d[visited] = np.inf
        nxt = int(np.argmin(d))
        order[k] = nxt
        visited[nxt] = True
        current = rot[nxt]
    return order


def slerp_segments(starts: np.ndarray, ends: np.ndarray, segment: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Per-joint spherical interpolation along many segments at once: pose ``fractions[m]`` of the
    way from ``starts[segment[m]]`` to ``ends[segment[m]]``; shapes (K, 60), (K, 60), (M,), (M,) -> (M, 60)."""
    k = len(starts)
    ra = axis_angle_to_matrix(torch.as_tensor(np.asarray(starts, np.float64).reshape(k, len(POSE_JOINTS), 3)))
    rb = axis_angle_to_matrix(torch.as_tensor(np.asarray(ends, np.float64).reshape(k, len(POSE_JOINTS), 3)))
    rel = matrix_to_axis_angle(ra.transpose(-1, -2) @ rb)  # (K, 20, 3): rotation taking start to end, per joint
    seg = torch.as_tensor(np.asarray(segment, np.int64))
    f = torch.as_tensor(np.asarray(fractions, np.float64))[:, None, None]
    steps = ra[seg] @ axis_angle_to_matrix(rel[seg] * f)  # (M, 20, 3, 3)
    return matrix_to_axis_angle(steps).reshape(len(seg), POSE_SIZE).numpy().astype(np.float32)


def slerp_poses(a: np.ndarray, b: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Per-joint spherical interpolation from pose a to b, shapes (60,), (60,), (T,) -> (T, 60)."""
    return slerp_segments(np.asarray(a)[None], np.asarray(b)[None], np.zeros(len(fractions), np.int64), fractions)


def interpolate_segments(starts: np.ndarray, ends: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Slerp'ed poses along independent segments, each split into as many equal steps as keep every
    joint's change per step within ``threshold`` [rad], all measured and interpolated in one batched
    call (one segment at a time cost ~1 ms each, most of it in small torch calls).

    Args:
        starts, ends: segment end points, shapes (K, 60).
        threshold: largest allowed per-joint angle change between consecutive poses [rad].
    Returns:
        (poses (M, 60), segment (M,)): segment k's inserted poses in order, then ``ends[k]`` itself,
        for k = 0..K-1 one after another.
    """
    if threshold <= 0:
        raise ValueError(f"simulation.interpolation_threshold must be > 0 rad, got {threshold}")
    ends = np.asarray(ends, np.float32).reshape(-1, POSE_SIZE)
    starts = np.asarray(starts, np.float32).reshape(-1, POSE_SIZE)
    k = len(ends)
    if k == 0:
        return np.zeros((0, POSE_SIZE), np.float32), np.zeros(0, np.int64)
    steps = np.ceil(joint_angle_change(starts, ends).max(axis=1) / threshold).astype(np.int64)  # frames per segment
    inserted = np.maximum(steps - 1, 0)
    segment = np.repeat(np.arange(k), inserted)
    within = np.arange(len(segment)) - np.repeat(np.cumsum(inserted) - inserted, inserted)  # 0.. per segment
    out = np.empty((k + len(segment), POSE_SIZE), np.float32)
    end_row = np.cumsum(inserted + 1) - 1
    is_end = np.zeros(len(out), dtype=bool)
    is_end[end_row] = True
    out[end_row] = ends
    if len(segment):
        out[~is_end] = slerp_segments(starts, ends, segment, (within + 1) / steps[segment])
    return out, np.repeat(np.arange(k), inserted + 1)


def interpolate_sequence(keys: np.ndarray, start: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Inserts slerp'ed poses wherever consecutive poses differ by more than ``threshold`` [rad] at any joint
    (the segments start -> key 0 -> key 1 ... of :func:`interpolate_segments`).

    Args:
        keys: target poses in visiting order, shape (N, 60).
        start: the pose before the first key, shape (60,).
        threshold: largest allowed per-joint angle change between consecutive poses [rad].
    Returns:
        (poses (M, 60), key_index (M,): index into ``keys`` for target poses, -1 for inserted ones).
    """
    keys = np.asarray(keys, np.float32).reshape(-1, POSE_SIZE)
    prev = np.concatenate([np.asarray(start, np.float32).reshape(1, POSE_SIZE), keys[:-1]])
    poses, segment = interpolate_segments(prev, keys, threshold)
    return poses, segment_key_index(segment)


def segment_key_index(segment: np.ndarray) -> np.ndarray:
    """Key index of each row of consecutive segments (``interpolate_segments``' ``segment``, (M,)):
    the segment's index on its last row (its key), -1 on the slerp'ed rows before it."""
    segment = np.asarray(segment)
    is_key = np.ones(len(segment), dtype=bool)
    is_key[:-1] = segment[1:] != segment[:-1]  # a segment's last row is its key
    return np.where(is_key, segment, -1)
