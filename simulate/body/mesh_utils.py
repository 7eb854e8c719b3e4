"""Body-mesh utilities the simulator and pose samplers need: normals, culling by
part, and a fast self-intersection test for pruning poses (arm inside torso, legs
crossing)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulate.body.base import POSE_JOINTS, BodyModel


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals.

    Args:
        vertices: positions [m], shape (V, 3) or (B, V, 3).
        faces: triangles, shape (F, 3).
    Returns:
        normals, same shape as ``vertices``; zero for vertices in no face.
    """
    v = np.asarray(vertices, dtype=np.float64)
    batched = v.ndim == 3
    if not batched:
        v = v[None]
    tri = v[:, faces]  # (B, F, 3, 3)
    face_n = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])  # area-weighted, (B, F, 3)
    normals = np.zeros_like(v)
    for corner in range(3):
        np.add.at(normals, (slice(None), faces[:, corner]), face_n)
    norm = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)
    normals = normals.astype(np.float32)
    return normals if batched else normals[0]


def cull_mesh(vertices: np.ndarray, faces: np.ndarray, keep_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keeps only the given faces and the vertices they use.

    Args:
        vertices: (V, 3) or (B, V, 3); faces: (F, 3); keep_faces: bool (F,) or face indices.
    Returns:
        (vertices', faces' re-indexed, vertex_map (V',) original indices).
    """
    sub = faces[keep_faces]
    used = np.unique(sub)
    remap = np.full(int(faces.max()) + 1, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(vertices)[..., used, :], remap[sub], used


# ---------------------------------------------------------------- self-intersection
#: Capsules along posable-joint segments: name -> (start joint, end joint, part, side).
CAPSULES: dict[str, tuple[str, str, str, int]] = {
    "torso": ("pelvis", "neck", "torso", 0),
    "left_upper_arm": ("left_shoulder", "left_elbow", "arms", 1),
    "left_forearm": ("left_elbow", "left_wrist", "arms", 1),
    "right_upper_arm": ("right_shoulder", "right_elbow", "arms", -1),
    "right_forearm": ("right_elbow", "right_wrist", "arms", -1),
    "left_thigh": ("left_hip", "left_knee", "legs", 1),
    "left_shin": ("left_knee", "left_ankle", "legs", 1),
    "right_thigh": ("right_hip", "right_knee", "legs", -1),
    "right_shin": ("right_knee", "right_ankle", "legs", -1),
}
#: Capsule pairs that must not interpenetrate (non-adjacent body segments).
CAPSULE_PAIRS: tuple[tuple[str, str], ...] = tuple(
    [(arm, "torso") for arm in ("left_upper_arm", "left_forearm", "right_upper_arm", "right_forearm")]
    + [(a, b) for a in ("left_forearm", "left_upper_arm") for b in ("right_forearm", "right_upper_arm")]
    + [(a, b) for a in ("left_forearm", "right_forearm", "left_upper_arm", "right_upper_arm")
       for b in ("left_thigh", "right_thigh", "left_shin", "right_shin")]
    + [(a, b) for a in ("left_thigh", "left_shin") for b in ("right_thigh", "right_shin")]
)


def _closest_segment_distance(p0, p1, q0, q1) -> np.ndarray:
    """Distance between segments [p0,p1] and [q0,q1], batched over leading dims (..., 3)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    f = (d2 * r).sum(-1)
    c = (d1 * r).sum(-1)
    b = (d1 * d2).sum(-1)
    denom = a * e - b * b
    s = np.where(denom > 1e-12, np.clip((b * f - c * e) / np.maximum(denom, 1e-12), 0.0, 1.0), 0.0)
    t = (b * s + f) / np.maximum(e, 1e-12)
    t_clamped = np.clip(t, 0.0, 1.0)
    s = np.where(t != t_clamped, np.clip((b * t_clamped - c) / np.maximum(a, 1e-12), 0.0, 1.0), s)
    diff = (p0 + d1 * s[..., None]) - (q0 + d2 * t_clamped[..., None])
    return np.linalg.norm(diff, axis=-1)


@dataclass
class SelfIntersectionChecker:
    """Approximates limbs and torso by capsules fitted to one body shape's rest mesh.

    A pose self-intersects when two non-adjacent capsules overlap by more than
    ``margin`` [m]. Radii are a low percentile of the vertices' distances to each
    segment axis (so touching skin is allowed, an arm inside the torso is not).
    Cheap enough to screen tens of thousands of poses per second.
    """

    body: BodyModel
    shape: np.ndarray
    margin: float = 0.01
    radius_percentile: float = 25.0

    def __post_init__(self) -> None:
        rest_v, rest_j = self.body.rest(self.shape)
        rest_v, rest_j = rest_v[0], rest_j[0]
        joints = rest_j[self.body.pose_joint_indices]
        self._ends = np.array([[POSE_JOINTS.index(a), POSE_JOINTS.index(b)] for a, b, _, _ in CAPSULES.values()])
        radii = []
        for name, (a, b, part, side) in CAPSULES.items():
            p0, p1 = joints[POSE_JOINTS.index(a)], joints[POSE_JOINTS.index(b)]
            mask = self.body.part_vertex_mask([part])
            if side:
                mask &= np.sign(rest_v[:, 0]) == side
            pts = rest_v[mask]
            axis = p1 - p0
            t = ((pts - p0) @ axis) / max(float(axis @ axis), 1e-12)
            inner = (t > 0.2) & (t < 0.8)
            dist = np.linalg.norm(pts[inner] - (p0 + t[inner, None] * axis), axis=1)
            radii.append(np.percentile(dist, self.radius_percentile) if len(dist) else 0.02)
        self.radii = np.array(radii, dtype=np.float64)
        names = list(CAPSULES)
        self._pairs = np.array([[names.index(a), names.index(b)] for a, b in CAPSULE_PAIRS])

    def penetration(self, pose_joints: np.ndarray) -> np.ndarray:
        """Overlap depth [m] per capsule pair (positive = interpenetrating).

        Args:
            pose_joints: posed positions of the 20 POSE_JOINTS [m], shape (B, 20, 3).
        Returns:
            shape (B, len(CAPSULE_PAIRS)).
        """
        seg = pose_joints[:, self._ends]  # (B, C, 2, 3)
        a, b = seg[:, self._pairs[:, 0]], seg[:, self._pairs[:, 1]]  # (B, P, 2, 3)
        dist = _closest_segment_distance(a[..., 0, :], a[..., 1, :], b[..., 0, :], b[..., 1, :])
        return self.radii[self._pairs[:, 0]] + self.radii[self._pairs[:, 1]] - dist

    def check(self, pose: np.ndarray, *, batch_size: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """Tests poses (B, 60) for self-intersection.

        Returns:
            (intersects (B,) bool, depth (B,) [m]: the deepest capsule overlap).
        """
        pose = np.asarray(pose, dtype=np.float32).reshape(-1, len(POSE_JOINTS) * 3)
        depth = np.empty(len(pose))
        for s in range(0, len(pose), batch_size):
            joints = self.body.posed_joints(self.shape, pose[s:s + batch_size])
            joints = joints[:, self.body.pose_joint_indices].astype(np.float64)
            depth[s:s + batch_size] = self.penetration(joints).max(axis=1)
        return depth > self.margin, depth
