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


@wp.kernel
def _closest_distance(
    mesh_ids: wp.array(dtype=wp.uint64),
    points: wp.array(dtype=wp.vec3),
    points_per_body: int,
    max_distance: float,
    # Out:
    distance_out: wp.array(dtype=float),
):
    """Euclidean distance [m] of each point to the closest point of its body's mesh (capped)."""
    tid = wp.tid()
    mesh_id = mesh_ids[tid // points_per_body]
    p = points[tid]
    query = wp.mesh_query_point_no_sign(mesh_id, p, max_distance)
    distance_out[tid] = max_distance
    if query.result:
        distance_out[tid] = wp.length(p - wp.mesh_eval_position(mesh_id, query.face, query.u, query.v))


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
        self._surfaces: list[tuple[np.ndarray, np.ndarray]] = []  # (vertex indices, local faces) per pair
        for a, b in self.pairs:
            mask_a, mask_b = _part_mask(body, rest, a), _part_mask(body, rest, b)
            faces = body.faces[mask_b[body.faces].all(axis=1)]
            if not mask_a.any() or not len(faces):
                raise ValueError(f"clearance pair ({a!r}, {b!r}): the body has no vertices of {a!r} or no faces of {b!r}")
            near = torch.cdist(torch.as_tensor(rest[mask_a], dtype=torch.float64),
                               torch.as_tensor(rest[mask_b], dtype=torch.float64)).min(dim=1).values.numpy()
            self._points.append(np.nonzero(mask_a)[0][near > rest_exclusion])
            used = np.unique(faces)
            local = np.full(body.vertex_count, -1, np.int64)
            local[used] = np.arange(len(used))
            self._surfaces.append((used, local[faces].astype(np.int32)))
        self._meshes: dict[int, tuple[list[wp.array], list[wp.Mesh], wp.array]] = {}
        # the vertices any pair reads, posed together (BodyModel.posed_vertices), and where each lies there
        self._posed = np.unique(np.concatenate(self._points + [used for used, _ in self._surfaces]))
        self._slot = np.full(body.vertex_count, -1, np.int64)
        self._slot[self._posed] = np.arange(len(self._posed))

    def _mesh_ids(self, pair: int, surfaces: np.ndarray) -> wp.array:
        """Loads (n, Vs, 3) surface points into per-body meshes of ``pair`` (built once, refit later)."""
        points, meshes, _ = self._meshes.get(pair, ([], [], None))
        _, faces = self._surfaces[pair]
        for i, s in enumerate(surfaces):
            if i < len(meshes):
                points[i].assign(s)
                meshes[i].refit()
            else:
                points.append(wp.array(s, dtype=wp.vec3, device=self.device))
                meshes.append(wp.Mesh(points[-1], wp.array(faces.ravel(), dtype=wp.int32, device=self.device)))
        ids = wp.array(np.array([m.id for m in meshes], np.uint64), dtype=wp.uint64, device=self.device)
        self._meshes[pair] = (points, meshes, ids)
        return ids[: len(surfaces)]

    def measure(self, poses: np.ndarray, *, batch_size: int = 128) -> np.ndarray:
        """Clearance [m] of each pair for each pose: (B, 60) poses -> (B, len(pairs))."""
        poses = np.asarray(poses, np.float32).reshape(-1, self.body.pose_size)
        out = np.empty((len(poses), len(self.pairs)))
        for s in range(0, len(poses), batch_size):
            chunk = poses[s:s + batch_size]
            v = self.body.posed_vertices(self.shape, chunk, self._posed)  # (n, len(_posed), 3)
            for k, (measured, (used, _)) in enumerate(zip(self._points, self._surfaces)):
                ids = self._mesh_ids(k, np.ascontiguousarray(v[:, self._slot[used]]))
                pts = wp.array(np.ascontiguousarray(v[:, self._slot[measured]]).reshape(-1, 3), dtype=wp.vec3,
                               device=self.device)
                dist = wp.empty(len(chunk) * len(measured), dtype=float, device=self.device)
                wp.launch(_closest_distance, dim=len(chunk) * len(measured), device=self.device,
                          inputs=[ids, pts, len(measured), self.max_distance], outputs=[dist])
                out[s:s + len(chunk), k] = dist.numpy().reshape(len(chunk), len(measured)).min(axis=1)
        # a capped clearance is max_distance itself, not its float32 rounding (which can sit below it)
        out[out >= np.float32(self.max_distance)] = self.max_distance
        return out
