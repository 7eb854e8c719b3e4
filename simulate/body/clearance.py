"""Skin clearance between body parts of posed bodies: how much room a garment has between an
arm and the torso, or between the legs.

Seed 001 (appendix D.3) prunes sampled poses whose arm vertices fall inside the torso. The
capsule test of :class:`~simulate.body.mesh_utils.SelfIntersectionChecker` catches an arm deep in
the torso but lets skin touch; a garment needs more than that. Two layers of cloth (sleeve and
torso side) each held a contact thickness off their skin cannot pass between an arm and a torso
that are closer than about twice that, and the one-sided body contact then pushes the layers
through each other. Measured on the H200 (TailorNet t-shirt spec, 6,700 targets at full width):
targets whose arm came within 2 cm of the torso (11.6 % of the sampled poses) kept 7.8 % of their
frames, against 55.8 % for the rest; 2-2.5 cm kept 30 %, 3-4 cm 59 %, above 4 cm 72 %.

The clearance of a pair (A, B) is the smallest distance [m] from a vertex of part A to the
surface of part B (closest point on B's triangles), over A's vertices that lie farther than
``rest_exclusion`` from B in the rest pose (so the shoulder, where arm and torso meet, does not
count). An arm inside the torso has clearance ~0 too: its skin crosses the torso's surface.
"""
from __future__ import annotations

import numpy as np
import torch
import warp as wp

from simulate.body.base import BodyModel
from simulate.quality import MeshSlots, query_body_signed_distance

__all__ = ["CLEARANCE_PAIRS", "CLEARANCE_PARTS", "LimbClearance"]

#: Body parts a clearance pair can name: a part of :data:`simulate.body.base.PARTS`, split by side
#: (the body's left is +x).
CLEARANCE_PARTS: dict[str, tuple[str, int]] = {
    "left_arm": ("arms", 1), "right_arm": ("arms", -1), "torso": ("torso", 0),
    "left_leg": ("legs", 1), "right_leg": ("legs", -1),
}

#: Pairs (part whose vertices are measured, part whose surface they are measured to) per
#: garment kind: tops need room between each arm and the torso, bottoms between the legs.
CLEARANCE_PAIRS: dict[str, tuple[tuple[str, str], ...]] = {
    "upper": (("left_arm", "torso"), ("right_arm", "torso")),
    "lower": (("left_leg", "right_leg"),),
}
CLEARANCE_PAIRS["all"] = CLEARANCE_PAIRS["upper"] + CLEARANCE_PAIRS["lower"]


def _part_mask(body: BodyModel, rest_vertices: np.ndarray, name: str) -> np.ndarray:
    if name not in CLEARANCE_PARTS:
        raise ValueError(f"clearance part {name!r} is unknown; expected one of {', '.join(CLEARANCE_PARTS)}")
    part, side = CLEARANCE_PARTS[name]
    mask = body.part_vertex_mask([part])
    return mask & (np.sign(rest_vertices[:, 0]) == side) if side else mask


class LimbClearance:
    """Skin clearance of each pair in ``pairs`` for poses of one body shape.

    Args:
        body: body model.
        shape: the body shape the poses are measured on, (S,).
        pairs: (measured part, surface part) names from :data:`CLEARANCE_PARTS`, e.g.
            ``CLEARANCE_PAIRS["upper"]``.
        rest_exclusion: vertices of the measured part within this distance [m] of the other
            part's vertices in the rest pose are not measured (where the parts join).
        max_distance: clearances are capped at this [m] (the search radius).
        device: Warp / torch device of the queries.
    """

    def __init__(self, body: BodyModel, shape: np.ndarray, pairs, *, rest_exclusion: float = 0.06,
                 max_distance: float = 0.5, device: str = "cpu") -> None:
        self.body = body
        self.shape = np.asarray(shape, np.float32).reshape(-1)
        self.pairs = tuple((str(a), str(b)) for a, b in pairs)
        if not self.pairs:
            raise ValueError("clearance pairs must name at least one (part, part) pair")
        if not (np.isfinite(rest_exclusion) and rest_exclusion >= 0.0):
            raise ValueError(f"clearance rest_exclusion must be >= 0 [m] (got {rest_exclusion!r})")
        self.max_distance = float(max_distance)
        self.device = device
        rest = body.rest(self.shape[None])[0][0]
        self._points: list[np.ndarray] = []  # measured vertex indices per pair
        self._surface_of: list[str] = []  # surface part per pair
        self._surfaces: dict[str, tuple[np.ndarray, MeshSlots]] = {}  # part -> (vertex indices, per-body meshes)
        self.surface_faces: dict[str, np.ndarray] = {}
        """Body triangles (F, 3) of each surface part the pairs measure to."""
        for a, b in self.pairs:
            mask_a, mask_b = _part_mask(body, rest, a), _part_mask(body, rest, b)
            faces = body.faces[mask_b[body.faces].all(axis=1)]
            if not mask_a.any() or not len(faces):
                raise ValueError(f"clearance pair ({a!r}, {b!r}): the body has no vertices of {a!r} or no faces of {b!r}")
            near = torch.cdist(torch.as_tensor(rest[mask_a], dtype=torch.float64),
                               torch.as_tensor(rest[mask_b], dtype=torch.float64)).min(dim=1).values.numpy()
            self._points.append(np.nonzero(mask_a)[0][near > rest_exclusion])
            self._surface_of.append(b)
            self.surface_faces[b] = faces
            if b not in self._surfaces:  # pairs that share a surface (both arms to the torso) share its meshes
                used = np.unique(faces)
                local = np.full(body.vertex_count, -1, np.int64)
                local[used] = np.arange(len(used))
                self._surfaces[b] = (used, MeshSlots(local[faces], len(used), device))
        # the vertices any pair reads, posed together (BodyModel.posed_vertices), and where each lies there
        self._posed = np.unique(np.concatenate(self._points + [used for used, _ in self._surfaces.values()]))
        self._slot = np.full(body.vertex_count, -1, np.int64)
        self._slot[self._posed] = np.arange(len(self._posed))

    def measure(self, poses: np.ndarray, *, batch_size: int = 128) -> np.ndarray:
        """Clearance [m] of each pair for each pose: (B, 60) poses -> (B, len(pairs))."""
        poses = np.asarray(poses, np.float32).reshape(-1, self.body.pose_size)
        out = np.empty((len(poses), len(self.pairs)))
        for s in range(0, len(poses), batch_size):
            chunk = poses[s:s + batch_size]
            n = len(chunk)
            v = self.body.posed_vertices(self.shape, chunk, self._posed)  # (n, len(_posed), 3)
            ids = {name: slots.load(wp.array(np.ascontiguousarray(v[:, self._slot[used]]).reshape(-1, 3), dtype=wp.vec3,
                                             device=self.device), n)
                   for name, (used, slots) in self._surfaces.items()}  # each surface refit once per chunk
            for k, (measured, surface) in enumerate(zip(self._points, self._surface_of)):
                p = np.ascontiguousarray(v[:, self._slot[measured]]).reshape(-1, 3)
                m = len(p)
                signed = wp.empty(m, dtype=float, device=self.device)
                closest = wp.empty(m, dtype=wp.vec3, device=self.device)
                normal = wp.empty(m, dtype=wp.vec3, device=self.device)
                wp.launch(query_body_signed_distance, dim=m, device=self.device,
                          inputs=[ids[surface], wp.array(p, dtype=wp.vec3, device=self.device), len(measured),
                                  self.max_distance], outputs=[signed, closest, normal])
                # the Euclidean distance to the closest point; a zero normal marks no surface within max_distance
                dist = np.where(np.any(normal.numpy() != 0.0, axis=1), np.linalg.norm(p - closest.numpy(), axis=1),
                                self.max_distance)
                out[s:s + n, k] = dist.reshape(n, len(measured)).min(axis=1)
        # a capped clearance is max_distance itself, not its float32 rounding (which can sit below it)
        out[out >= np.float32(self.max_distance)] = self.max_distance
        return out
