"""The body-model interface shared by every backend (anny default, SMPL-family files).

Frame: metres, y up, the body faces +z, its left is +x (the SMPL convention).
``shape`` and ``pose`` are plain arrays: ``shape`` has ``shape_size`` entries
(backend-specific meaning, see ``shape_names``), ``pose`` has one axis-angle vector
[rad] for each of the 20 posable joints in :data:`POSE_JOINTS` (flattened to 60
numbers, or shaped (20, 3)), in the same order for every backend, so pose files and
samplers carry over between anny and SMPL.
"""
from __future__ import annotations

import abc
import contextlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch

from simulate.body import kinematics as kin


@contextlib.contextmanager
def one_thread_on_cpu(device: torch.device | str):
    """Torch's intra-op threads pinned to 1 while the block runs on the CPU (nothing changes on
    CUDA). A shape blend is a long reduction over blend shapes whose rounding depends on how torch
    splits it over threads: anny's rest body differed by ulps between 1 and 2 threads, so a dataset
    made by a Ray worker (1 thread) or a test process that had set 1 thread differed from one made
    by a default process. Pinned, a body depends only on its inputs."""
    if torch.device(device).type != "cpu" or torch.get_num_threads() == 1:
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)

#: Posable joints, in SMPL's order (SMPL's feet and hands are fixed here).
POSE_JOINTS: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
POSE_JOINT_COUNT = len(POSE_JOINTS)
POSE_SIZE = 3 * POSE_JOINT_COUNT
#: Shaped rest bodies a model keeps per device (BodyModel._rest_kept); ~0.17 MB each for anny.
REST_CACHE_SIZE = 1024

#: Default joint limits [rad] per axis (x, y, z) of the body frame, (min, max), used by
#: pose samplers and range checks. x is the body's left, y up, z forward: flexing a hip
#: forward is a negative x rotation, raising the left arm sideways a positive z rotation.
JOINT_LIMITS: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "pelvis": ((-0.3, 0.3), (-0.5, 0.5), (-0.2, 0.2)),
    "left_hip": ((-1.6, 0.5), (-0.6, 0.6), (-0.2, 0.8)),
    "right_hip": ((-1.6, 0.5), (-0.6, 0.6), (-0.8, 0.2)),
    "spine1": ((-0.3, 0.5), (-0.3, 0.3), (-0.25, 0.25)),
    "left_knee": ((0.0, 2.3), (-0.05, 0.05), (-0.05, 0.05)),
    "right_knee": ((0.0, 2.3), (-0.05, 0.05), (-0.05, 0.05)),
    "spine2": ((-0.3, 0.4), (-0.3, 0.3), (-0.25, 0.25)),
    "left_ankle": ((-0.6, 0.6), (-0.3, 0.3), (-0.3, 0.3)),
    "right_ankle": ((-0.6, 0.6), (-0.3, 0.3), (-0.3, 0.3)),
    "spine3": ((-0.2, 0.3), (-0.3, 0.3), (-0.2, 0.2)),
    "neck": ((-0.5, 0.6), (-0.7, 0.7), (-0.4, 0.4)),
    "left_collar": ((-0.2, 0.2), (-0.3, 0.3), (-0.2, 0.4)),
    "right_collar": ((-0.2, 0.2), (-0.3, 0.3), (-0.4, 0.2)),
    "head": ((-0.5, 0.5), (-0.6, 0.6), (-0.4, 0.4)),
    # arms no closer to the torso than ~15 deg (cloth trapped under a pressed arm has no
    # quasi-static answer without self-contact)
    "left_shoulder": ((-1.2, 1.2), (-1.0, 1.0), (-0.5, 1.9)),
    "right_shoulder": ((-1.2, 1.2), (-1.0, 1.0), (-1.9, 0.5)),
    "left_elbow": ((-0.2, 0.2), (-2.3, 0.1), (-0.2, 0.2)),
    "right_elbow": ((-0.2, 0.2), (-0.1, 2.3), (-0.2, 0.2)),
    "left_wrist": ((-0.6, 0.6), (-0.4, 0.4), (-0.6, 0.6)),
    "right_wrist": ((-0.6, 0.6), (-0.4, 0.4), (-0.6, 0.6)),
}

#: Body regions used to cull what a garment cannot touch.
PARTS: tuple[str, ...] = ("torso", "arms", "legs", "head", "hands", "feet")


@dataclass
class PosedBody:
    """A batch of posed bodies. Arrays are numpy or torch, matching the call.

    Attributes:
        vertices: posed vertices [m], shape (B, V, 3).
        faces: triangles, shape (F, 3), int.
        joints: posed joint positions [m], shape (B, J, 3) (all backend joints).
        joint_transforms: joint-to-world transforms, shape (B, J, 4, 4).
        skinning_transforms: rest-to-posed transforms, shape (B, J, 4, 4).
        skinning_weights: per-vertex weights, shape (V, J).
        rest_vertices: shaped, unposed vertices [m], shape (B, V, 3).
        rest_joints: shaped, unposed joint positions [m], shape (B, J, 3).
    """

    vertices: np.ndarray | torch.Tensor
    faces: np.ndarray
    joints: np.ndarray | torch.Tensor
    joint_transforms: np.ndarray | torch.Tensor
    skinning_transforms: np.ndarray | torch.Tensor
    skinning_weights: np.ndarray | torch.Tensor
    rest_vertices: np.ndarray | torch.Tensor
    rest_joints: np.ndarray | torch.Tensor


class BodyModel(abc.ABC):
    """A parametric body: rest(shape), pose(shape, pose), skinning of arbitrary points.

    Subclasses set the attributes below in ``__init__`` and implement
    :meth:`_rest_torch` (and may override :meth:`_pose_correctives`).

    Attributes:
        name: backend name used in configs ("anny", "smpl").
        faces: triangles, shape (F, 3), int64.
        joint_names: every joint of the backend's skeleton, length J.
        joint_parents: parent index per joint, shape (J,), -1 for the root.
        pose_joint_indices: skeleton index of each of :data:`POSE_JOINTS`, shape (20,).
        shape_names: names of the shape parameters, length S.
        shape_ranges: (min, max) of each shape parameter, shape (S, 2).
        shape_default: the mean / neutral shape, shape (S,).
        skinning_weights_t: per-vertex skinning weights (torch, float32), shape (V, J).
        vertex_parts: index into :data:`PARTS` per vertex, shape (V,).
        canonical_pose: the canonical (A-)pose garments are draped in, shape (60,).
    """

    name: str
    faces: np.ndarray
    joint_names: list[str]
    joint_parents: np.ndarray
    pose_joint_indices: np.ndarray
    shape_names: list[str]
    shape_ranges: np.ndarray
    shape_default: np.ndarray
    skinning_weights_t: torch.Tensor
    vertex_parts: np.ndarray
    canonical_pose: np.ndarray
    _weights_on: torch.Tensor | None = None

    # ------------------------------------------------------------------ sizes
    @property
    def vertex_count(self) -> int:
        return int(self.skinning_weights_t.shape[0])

    @property
    def joint_count(self) -> int:
        return len(self.joint_names)

    @property
    def shape_size(self) -> int:
        return len(self.shape_names)

    @property
    def pose_size(self) -> int:
        return POSE_SIZE

    @property
    def skinning_weights(self) -> np.ndarray:
        """Per-vertex skinning weights, shape (V, J), float32."""
        return self.skinning_weights_t.numpy()

    # ------------------------------------------------------------ validation
    def check_shape(self, shape, *, field: str = "shape", move: bool = True) -> torch.Tensor:
        """Returns shape as a float32 tensor (B, S) on the model's device (``move=False``: where it
        was given, the CPU for numpy); raises naming the expected length. Host values are checked
        on the host and reach a GPU model without a host-device synchronisation."""
        t = kin.as_torch(shape) if not isinstance(shape, torch.Tensor) else shape.float()
        given = tuple(t.shape)
        if t.dim() == 1:
            t = t[None]
        if t.dim() != 2 or t.shape[-1] != self.shape_size:
            raise ValueError(
                f"{field} must have {self.shape_size} values ({', '.join(self.shape_names)}) "
                f"per body, shape ({self.shape_size},) or (B, {self.shape_size}); got shape {given}"
            )
        if not torch.isfinite(t).all():
            raise ValueError(f"{field} contains non-finite values")
        return kin.to_device_async(t, getattr(self, "device", t.device)) if move else t

    def check_pose(self, pose, *, field: str = "pose") -> torch.Tensor:
        """Returns pose as a float32 tensor (B, 20, 3) on the model's device; accepts (60,), (20,3),
        (B,60), (B,20,3). Host values are checked on the host and reach a GPU model without a
        host-device synchronisation."""
        t = kin.as_torch(pose) if not isinstance(pose, torch.Tensor) else pose.float()
        given = tuple(t.shape)
        if t.dim() == 1 or (t.dim() == 2 and t.shape == (POSE_JOINT_COUNT, 3)):
            t = t[None]
        if t.dim() == 2 and t.shape[-1] == POSE_SIZE:
            t = t.reshape(t.shape[0], POSE_JOINT_COUNT, 3)
        if t.dim() != 3 or t.shape[1:] != (POSE_JOINT_COUNT, 3):
            raise ValueError(
                f"{field} must be axis-angle rotations [rad] of the {POSE_JOINT_COUNT} joints "
                f"{POSE_JOINTS[0]}..{POSE_JOINTS[-1]}: shape ({POSE_SIZE},), ({POSE_JOINT_COUNT}, 3), "
                f"(B, {POSE_SIZE}) or (B, {POSE_JOINT_COUNT}, 3); got shape {given}"
            )
        if not torch.isfinite(t).all():
            raise ValueError(f"{field} contains non-finite values")
        return kin.to_device_async(t, getattr(self, "device", t.device))

    def pose_from_dict(self, rotations: dict[str, object]) -> np.ndarray:
        """Builds a (60,) pose from {joint name: axis-angle (3,)}; unknown names raise."""
        pose = np.zeros((POSE_JOINT_COUNT, 3), dtype=np.float32)
        for name, value in rotations.items():
            if name not in POSE_JOINTS:
                raise ValueError(f"unknown joint name {name!r}; expected one of {', '.join(POSE_JOINTS)}")
            vec = np.asarray(value, dtype=np.float32)
            if vec.shape != (3,):
                raise ValueError(f"rotation of joint {name!r} must be an axis-angle vector of 3 values, got shape {vec.shape}")
            pose[POSE_JOINTS.index(name)] = vec
        return pose.reshape(-1)

    # ------------------------------------------------------------ torch core
    @abc.abstractmethod
    def _rest_torch(self, shape: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shaped rest vertices (B, V, 3) and joints (B, J, 3) [m] for shape (B, S)."""

    def _pose_correctives(self, local_rotations: torch.Tensor) -> torch.Tensor | None:
        """Pose-dependent vertex offsets (B, V, 3) added before skinning; None if none."""
        return None

    def rest_torch(self, shape) -> tuple[torch.Tensor, torch.Tensor]:
        """Differentiable shaped rest mesh: vertices (B, V, 3) and joints (B, J, 3) [m]."""
        shape_t = self.check_shape(shape)
        with one_thread_on_cpu(getattr(self, "device", "cpu")):
            return self._rest_torch(shape_t)

    def local_rotations_torch(self, pose) -> torch.Tensor:
        """All-joint local rotations (B, J, 3, 3) from a posable-joint pose (identity elsewhere)."""
        pose_t = self.check_pose(pose)
        batch = pose_t.shape[0]
        rot = torch.eye(3, dtype=pose_t.dtype, device=pose_t.device).repeat(batch, self.joint_count, 1, 1)
        rot[:, self._indices_on(pose_t.device)["pose_joints"]] = kin.axis_angle_to_matrix(pose_t)
        return rot

    def on_device(self, device: str | torch.device) -> "BodyModel":
        """This body model with its tensors on torch ``device`` (``self`` when already there).

        Posing runs where the model's tensors live, whatever device the inputs are on, so a GPU
        pipeline poses with ``body.on_device("cuda")``; the numpy API stays on the CPU model."""
        device = torch.device(device)
        here = torch.device(getattr(self, "device", "cpu"))
        if device.type == here.type and (device.index is None or device.index == (here.index or 0)):
            return self
        return self._copy_on(device)

    @abc.abstractmethod
    def _copy_on(self, device: torch.device) -> "BodyModel":
        """A copy of this model with its tensors on ``device`` (each backend builds its own)."""

    def _rest_kept(self, shapes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``_rest_torch`` of each row (B, S), each blended alone the first time and then kept per
        device (up to ``REST_CACHE_SIZE`` shapes, more after ``keep_rest``, the least recently used going first: a motion
        run's shape transitions blend thousands of shapes used for a frame or two, which must not
        push out the shapes its worlds pose every frame): a dataset run poses a few hundred shapes
        thousands of times, and anny's blend was ~8 ms of a ~12 ms batched posing call on the
        H200, mostly per-call overhead. Blending a row alone makes it independent of the batch it
        arrives in, so a body does not depend on which run or batch first asked for its shape."""
        hits = self._kept_rows(shapes.detach().cpu().numpy(), shapes.dtype, shapes.device)
        return torch.stack([v for v, _ in hits]), torch.stack([j for _, j in hits])

    def _kept_rows(self, rows: np.ndarray, dtype: torch.dtype,
                   given_on: torch.device | str = "cpu") -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(rest vertices (V, 3), rest joints (J, 3)) of each row of ``rows`` (B, S) from the cache,
        blending the missing ones alone (see ``_rest_kept``); ``given_on``: where the shapes came
        from (the blend's input is made there)."""
        cache = self.__dict__.setdefault("_rest_cache", OrderedDict())
        capacity = max(REST_CACHE_SIZE, self.__dict__.get("_rest_capacity", 0))
        device = str(getattr(self, "device", given_on))
        hits = []
        for row in rows:
            key = (device, str(dtype), row.tobytes())
            hit = cache.get(key)
            if hit is None:
                while len(cache) >= capacity:  # the least recently used goes: a run's task shapes
                    cache.popitem(last=False)  # stay while its one-frame blend shapes pass through
                with one_thread_on_cpu(getattr(self, "device", "cpu")):
                    v, j = self._rest_torch(torch.as_tensor(row[None], dtype=dtype, device=given_on))
                hit = cache[key] = (v[0], j[0])
            else:
                cache.move_to_end(key)
            hits.append(hit)
        return hits

    def keep_rest(self, shapes) -> int:
        """Blends the rest bodies of ``shapes`` (B, S) now, each alone as posing blends them, and
        keeps them: the cache grows to hold these and ``REST_CACHE_SIZE`` more. A dataset run knows
        every shape its schedules will pose (shape transitions included) before it simulates, and
        blends them while worker processes make its garments, instead of one by one between frames.
        Returns the number of shapes blended (those not kept already)."""
        rows = self.check_shape(shapes, field="shapes", move=False).detach().cpu().numpy()
        rows = rows[np.sort(np.unique(rows, axis=0, return_index=True)[1])]
        cache = self.__dict__.setdefault("_rest_cache", OrderedDict())
        self.__dict__["_rest_capacity"] = max(self.__dict__.get("_rest_capacity", 0), len(rows) + REST_CACHE_SIZE)
        device = str(getattr(self, "device", "cpu"))
        missing = sum((device, str(torch.float32), row.tobytes()) not in cache for row in rows)
        self._kept_rows(rows, torch.float32)
        return missing

    def pose_torch(self, shape, pose, translation=None) -> PosedBody:
        """Differentiable posing in torch; shape (B,S) or (S,), pose (B,60) or (60,) broadcast."""
        shape_t = self.check_shape(shape, move=False)
        pose_t = self.check_pose(pose)
        batch = max(shape_t.shape[0], pose_t.shape[0])
        if shape_t.shape[0] not in (1, batch) or pose_t.shape[0] not in (1, batch):
            raise ValueError(f"shape batch ({shape_t.shape[0]}) and pose batch ({pose_t.shape[0]}) must match or be 1")
        if not shape_t.requires_grad:
            # batches repeat shapes (a dataset world poses one shape through many poses): the shape
            # blend runs once per distinct shape and is kept (see _rest_kept). Shapes given on the
            # host are told apart there: on a GPU, unique() waits for the device
            distinct, inverse = torch.unique(shape_t, dim=0, return_inverse=True)
            rest_vertices, rest_joints = self._rest_kept(distinct)
            inverse = kin.to_device_async(inverse, rest_vertices.device)
            rest_vertices, rest_joints = rest_vertices[inverse], rest_joints[inverse]
        else:
            shape_t = kin.to_device_async(shape_t, getattr(self, "device", shape_t.device))
            with one_thread_on_cpu(getattr(self, "device", "cpu")):
                rest_vertices, rest_joints = self._rest_torch(shape_t)
        rest_vertices = rest_vertices.expand(batch, -1, -1)
        rest_joints = rest_joints.expand(batch, -1, -1)
        rot = self.local_rotations_torch(pose_t.expand(batch, -1, -1))
        trans = None
        if translation is not None:
            trans = kin.as_torch(translation, device=rot.device)
            if trans.dim() == 1:
                trans = trans[None]
            if trans.shape[-1] != 3:
                raise ValueError(f"translation must have 3 values [m] per body, got shape {tuple(trans.shape)}")
            trans = trans.expand(batch, 3)
        ix = self._indices_on(rot.device)
        world, skin = kin.forward_kinematics(rot, rest_joints, ix["parents"], translation=trans, levels=ix["levels"])
        correctives = self._pose_correctives(rot)
        shaped = rest_vertices if correctives is None else rest_vertices + correctives
        if self._weights_on is None or self._weights_on.device != shaped.device:
            self._weights_on = self.skinning_weights_t.to(shaped.device)
        vertices = kin.lbs(shaped, self._weights_on, skin)
        return PosedBody(
            vertices=vertices, faces=self.faces, joints=world[..., :3, 3], joint_transforms=world,
            skinning_transforms=skin, skinning_weights=self.skinning_weights_t, rest_vertices=rest_vertices,
            rest_joints=rest_joints,
        )

    def posed_joints(self, shape, pose, translation=None) -> np.ndarray:
        """Posed joint positions only (no skinning; fast), shape (B, J, 3) [m], numpy."""
        with torch.no_grad():
            shape_t = self.check_shape(shape)
            rot = self.local_rotations_torch(pose)
            with one_thread_on_cpu(getattr(self, "device", "cpu")):
                _, rest_joints = self._rest_torch(shape_t)
            trans = None if translation is None else kin.as_torch(translation, device=rot.device).reshape(-1, 3).expand(rot.shape[0], 3)
            ix = self._indices_on(rot.device)
            world, _ = kin.forward_kinematics(rot, rest_joints.expand(rot.shape[0], -1, -1), ix["parents"],
                                              translation=trans, levels=ix["levels"])
        return world[..., :3, 3].cpu().numpy()

    def posed_vertices(self, shape, pose, indices) -> np.ndarray:
        """Posed positions [m] of the vertices ``indices`` only, (B, len(indices), 3) numpy: the same
        skinning as :meth:`pose` without skinning every other vertex (pose pruning measures a few
        thousand vertices of tens of thousands of poses). One shape (S,) or (1, S) for all poses."""
        idx = torch.as_tensor(np.asarray(indices, np.int64))
        with torch.no_grad():
            shape_t = self.check_shape(shape)
            if shape_t.shape[0] != 1:
                raise ValueError(f"posed_vertices takes one shape for all poses (got {shape_t.shape[0]})")
            rest_vertices, rest_joints = self._rest_kept(shape_t)
            rot = self.local_rotations_torch(pose)
            ix = self._indices_on(rot.device)
            _, skin = kin.forward_kinematics(rot, rest_joints.expand(rot.shape[0], -1, -1), ix["parents"],
                                             levels=ix["levels"])
            correctives = self._pose_correctives(rot)
            idx = idx.to(rest_vertices.device)
            shaped = rest_vertices[:, idx] if correctives is None else (rest_vertices + correctives)[:, idx]
            weights = self.skinning_weights_t.to(shaped.device)[idx]
            return kin.lbs(shaped.expand(rot.shape[0], -1, -1), weights, skin).cpu().numpy()

    # ------------------------------------------------------------ numpy API
    def rest(self, shape) -> tuple[np.ndarray, np.ndarray]:
        """Shaped rest vertices (B, V, 3) and joints (B, J, 3) [m], numpy float32."""
        with torch.no_grad():
            v, j = self.rest_torch(shape)
        return v.cpu().numpy(), j.cpu().numpy()

    def pose(self, shape, pose, translation=None) -> PosedBody:
        """Poses a batch of bodies (numpy in, numpy out); see :meth:`pose_torch`."""
        with torch.no_grad():
            posed = self.pose_torch(shape, pose, translation)
        return PosedBody(**{k: (v.cpu().numpy() if isinstance(v, torch.Tensor) else v) for k, v in posed.__dict__.items()})

    # --------------------------------------------------------- conveniences
    @property
    def _levels(self) -> list[np.ndarray]:
        if getattr(self, "_levels_cache", None) is None:
            self._levels_cache = kin.kinematic_levels(self.joint_parents)
        return self._levels_cache

    def _indices_on(self, device: torch.device) -> dict:
        """The skeleton's index arrays as int64 tensors on ``device``, made once per device:
        {"parents": (J,), "levels": kinematic levels, "pose_joints": (20,)}. Copying them from
        numpy at every call synchronised host and GPU once per array (18 times per posing call
        for anny)."""
        cache = self.__dict__.setdefault("_indices_cache", {})
        key = str(device)
        if key not in cache:
            def on(a):
                return torch.as_tensor(np.asarray(a, np.int64), device=device)

            cache[key] = {"parents": on(self.joint_parents), "levels": [on(i) for i in self._levels],
                          "pose_joints": on(self.pose_joint_indices)}
        return cache[key]

    def part_vertex_mask(self, parts) -> np.ndarray:
        """Boolean (V,) mask of the vertices in the named parts (see :data:`PARTS`)."""
        wanted = []
        for p in parts:
            if p not in PARTS:
                raise ValueError(f"unknown body part {p!r}; expected one of {', '.join(PARTS)}")
            wanted.append(PARTS.index(p))
        return np.isin(self.vertex_parts, wanted)

    def part_faces(self, parts) -> np.ndarray:
        """Faces (F', 3) whose three vertices all lie in the named parts (body culling)."""
        mask = self.part_vertex_mask(parts)
        return self.faces[mask[self.faces].all(axis=1)]
