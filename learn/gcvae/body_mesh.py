"""The common body mesh every garment is written on (seed 004, Sec. 4.1): anny's torso, arms
and legs (head, hands and feet removed), midpoint-subdivided ``subdivisions`` times, with

- ``segments``: one id per vertex, the bone with the largest skinning weight (interpolated
  weights for subdivision vertices); segments under ``min_segment_vertices`` join their
  parent bone's. Pooling never merges across segments (learn.gcvae.pooling);
- the **dual topology** for skirt-like garments: the inner-leg faces (leg faces whose
  normals point toward the other leg) are removed and faces bridging the legs are added
  between the two holes (left/right mirror pairs; anny is mirror-symmetric to 1e-5 m), so
  the legs become one tube a skirt can be registered on. The bridge's vertices are then
  Laplacian-smoothed (seed Fig. 5b) into a hull; inner-leg vertices inside the holes belong
  to no dual face (a skirt never covers them);
- ``edges``: the graph of the convolutions, the union of both topologies' edges.

Vertices of a shape come from anny's canonical-pose (A-pose, ``pose = 0``) vertices through
a fixed sparse ``interpolation`` (N, V_anny): selection, then edge midpoints.

Frame: metres, y up, facing +z, left +x.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from learn.common.mesh import mesh_edges
from simulate.body.base import PARTS
from simulate.body.mesh_utils import vertex_normals
from simulate.garment import mesh_ops

#: Body parts kept on the common mesh.
KEPT_PARTS: tuple[str, ...] = ("torso", "arms", "legs")
#: Garment types registered on the dual topology.
DUAL_TYPES: frozenset[str] = frozenset({"skirt", "dress"})
#: Largest distance [m] between a vertex's mirror image and its mirror partner.
MIRROR_TOLERANCE_M = 1.0e-4


@dataclass
class BodyMesh:
    """The common body mesh (N vertices). Arrays only, so it saves into any ``.npz``.

    Attributes:
        interpolation: sparse (N, V_anny): body vertices = interpolation @ anny vertices.
        faces: standard topology, (F, 3), outward.
        dual_faces: dual topology (skirts), (F_d, 3), outward.
        dual_smoothing: sparse (N, N): dual positions = dual_smoothing @ standard positions.
        segments: segment id per vertex, (N,), ids 0..S-1.
        segment_names: bone name of each segment, length S.
        edges: graph edges (E, 2), i < j, union of both topologies.
        inner_leg: vertices of the removed inner-leg faces, (N,) bool.
        subdivisions: midpoint subdivisions applied.
    """

    interpolation: sparse.csr_matrix
    faces: np.ndarray
    dual_faces: np.ndarray
    dual_smoothing: sparse.csr_matrix
    segments: np.ndarray
    segment_names: list[str]
    edges: np.ndarray
    inner_leg: np.ndarray
    subdivisions: int

    @property
    def vertex_count(self) -> int:
        return int(self.interpolation.shape[0])

    @property
    def segment_count(self) -> int:
        return len(self.segment_names)

    def vertices(self, anny_vertices: np.ndarray) -> np.ndarray:
        """Body-mesh vertices (..., N, 3) [m] from anny vertices (..., V_anny, 3)."""
        a = np.asarray(anny_vertices, dtype=np.float64)
        flat = a.reshape(-1, a.shape[-2], 3)
        out = np.stack([self.interpolation @ x for x in flat])
        return out.reshape(*a.shape[:-2], self.vertex_count, 3)

    def dual_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """Dual-topology positions (N, 3) [m] of standard positions (N, 3)."""
        return np.asarray(self.dual_smoothing @ np.asarray(vertices, dtype=np.float64))

    def topology(self, garment_type: str) -> tuple[str, np.ndarray]:
        """("dual", dual_faces) for skirt-like types, ("standard", faces) otherwise."""
        return ("dual", self.dual_faces) if garment_type in DUAL_TYPES else ("standard", self.faces)

    def bridge_vertices(self) -> np.ndarray:
        """(N,) bool: vertices of the faces only the dual topology has (the bridge)."""
        standard = {tuple(sorted(f)) for f in self.faces.tolist()}
        out = np.zeros(self.vertex_count, bool)
        for f in self.dual_faces.tolist():
            if tuple(sorted(f)) not in standard:
                out[f] = True
        return out

    def topology_of_mask(self, mask: np.ndarray) -> str:
        """"dual" when a mask covers the bridge but not the inner legs (skirt-like), else
        "standard": what a sampled garment of unknown type is reconstructed with."""
        mask = np.asarray(mask, bool)
        bridge = self.bridge_vertices()
        inside = self.inner_leg & ~bridge
        if bridge.any() and inside.any() and mask[bridge].mean() > 0.5 and mask[inside].mean() < 0.5:
            return "dual"
        return "standard"

    def positions_for(self, garment_type: str, vertices: np.ndarray) -> np.ndarray:
        """Positions (N, 3) [m] of the topology ``garment_type`` registers on."""
        return self.dual_vertices(vertices) if garment_type in DUAL_TYPES else np.asarray(vertices, np.float64)

    # ------------------------------------------------------------------ io
    def arrays(self, prefix: str = "body_") -> dict[str, np.ndarray]:
        p, d = self.interpolation.tocoo(), self.dual_smoothing.tocoo()
        return {
            f"{prefix}interpolation": np.stack([p.row, p.col]).astype(np.int64),
            f"{prefix}interpolation_values": p.data.astype(np.float64),
            f"{prefix}interpolation_shape": np.array(p.shape, np.int64),
            f"{prefix}dual_smoothing": np.stack([d.row, d.col]).astype(np.int64),
            f"{prefix}dual_smoothing_values": d.data.astype(np.float64),
            f"{prefix}faces": self.faces.astype(np.int64), f"{prefix}dual_faces": self.dual_faces.astype(np.int64),
            f"{prefix}segments": self.segments.astype(np.int64),
            f"{prefix}segment_names": np.array(self.segment_names),
            f"{prefix}edges": self.edges.astype(np.int64), f"{prefix}inner_leg": self.inner_leg,
            f"{prefix}subdivisions": np.array(self.subdivisions),
        }

    @classmethod
    def from_arrays(cls, z, prefix: str = "body_") -> "BodyMesh":
        shape = tuple(int(x) for x in z[f"{prefix}interpolation_shape"])
        ij = z[f"{prefix}interpolation"]
        dij = z[f"{prefix}dual_smoothing"]
        return cls(
            interpolation=sparse.csr_matrix((z[f"{prefix}interpolation_values"], (ij[0], ij[1])), shape=shape),
            faces=np.asarray(z[f"{prefix}faces"]), dual_faces=np.asarray(z[f"{prefix}dual_faces"]),
            dual_smoothing=sparse.csr_matrix((z[f"{prefix}dual_smoothing_values"], (dij[0], dij[1])),
                                             shape=(shape[0], shape[0])),
            segments=np.asarray(z[f"{prefix}segments"]), segment_names=[str(s) for s in z[f"{prefix}segment_names"]],
            edges=np.asarray(z[f"{prefix}edges"]), inner_leg=np.asarray(z[f"{prefix}inner_leg"]).astype(bool),
            subdivisions=int(z[f"{prefix}subdivisions"]))


def canonical_body_vertices(body, shapes: np.ndarray) -> np.ndarray:
    """anny vertices (B, V_anny, 3) [m] of shapes (B, S) in the canonical pose (garments' rest)."""
    shapes = np.atleast_2d(np.asarray(shapes, dtype=np.float32))
    pose = np.tile(np.asarray(body.canonical_pose, np.float32), (len(shapes), 1))
    return body.pose(shapes, pose).vertices.astype(np.float64)


def _subdivide(interp: sparse.csr_matrix, faces: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray]:
    """One midpoint subdivision: each edge gets its midpoint, each face becomes four."""
    edges, face_edge = mesh_ops.unique_edges(faces)
    n = interp.shape[0]
    mid = 0.5 * (interp[edges[:, 0]] + interp[edges[:, 1]])
    h = n + face_edge  # (F, 3): midpoint of edge (c0,c1), (c1,c2), (c2,c0)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    new_faces = np.concatenate([np.stack([a, h[:, 0], h[:, 2]], 1), np.stack([h[:, 0], b, h[:, 1]], 1),
                                np.stack([h[:, 2], h[:, 1], c], 1), np.stack([h[:, 0], h[:, 1], h[:, 2]], 1)])
    return sparse.vstack([interp, mid]).tocsr(), new_faces


def _segments(weights: np.ndarray, parents: np.ndarray, names: list[str], minimum: int) -> tuple[np.ndarray, list[str]]:
    bone = weights.argmax(1)
    while True:
        ids, counts = np.unique(bone, return_counts=True)
        small = [(c, i) for i, c in zip(ids, counts) if c < minimum and parents[i] >= 0]
        if not small:
            break
        _, i = min(small)
        bone[bone == i] = parents[i]
    ids = np.unique(bone)
    return np.searchsorted(ids, bone).astype(np.int64), [names[i] for i in ids]


def build_body_mesh(body, *, subdivisions: int = 0, min_segment_vertices: int = 40, inner_leg_cosine: float = 0.45,
                    dual_smoothing_iterations: int = 10) -> BodyMesh:
    """The common body mesh of ``body`` (a simulate.body model; anny by default)."""
    if int(subdivisions) < 0 or int(subdivisions) > 2:
        raise ValueError(f"representation.subdivisions must be 0, 1 or 2, got {subdivisions}")
    anny_v = canonical_body_vertices(body, body.shape_default)[0]
    parts = np.asarray(body.vertex_parts)
    kept_parts = [PARTS.index(p) for p in KEPT_PARTS]
    faces = np.asarray(body.faces, np.int64)
    faces = faces[np.isin(parts[faces], kept_parts).all(1)]
    used = np.unique(faces)
    remap = np.full(len(anny_v), -1, np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[faces]
    interp = sparse.csr_matrix((np.ones(len(used)), (np.arange(len(used)), used)), shape=(len(used), len(anny_v)))
    for _ in range(int(subdivisions)):
        interp, faces = _subdivide(interp, faces)
    v = np.asarray(interp @ anny_v)
    n = len(v)
    weights = np.asarray(interp @ body.skinning_weights.astype(np.float64))
    segments, segment_names = _segments(weights, np.asarray(body.joint_parents), list(body.joint_names),
                                        int(min_segment_vertices))
    # Leg vertices: bones whose vertices are mostly in anny's "legs" part.
    bone = np.asarray(body.skinning_weights).argmax(1)
    leg_bones = {j for j in np.unique(bone) if np.mean(parts[bone == j] == PARTS.index("legs")) > 0.5}
    leg = np.isin(weights.argmax(1), list(leg_bones))
    mirror_d, mirror = cKDTree(v).query(v * np.array([-1.0, 1.0, 1.0]))
    if mirror_d.max() > MIRROR_TOLERANCE_M:
        raise ValueError(f"the body mesh is not mirror-symmetric (a vertex's mirror is {mirror_d.max():.2e} m from "
                         f"any vertex; expected <= {MIRROR_TOLERANCE_M}); the dual topology needs left/right pairs")
    normals = vertex_normals(v, faces)
    inner = leg & (-np.sign(v[:, 0]) * normals[:, 0] > inner_leg_cosine)
    inner = inner | inner[mirror]
    removed = inner[faces].all(1)
    kept = faces[~removed]
    removed_edges = {tuple(e) for e in np.sort(np.concatenate([faces[removed][:, [0, 1]], faces[removed][:, [1, 2]],
                                                               faces[removed][:, [2, 0]]]), axis=1)}
    half = mesh_ops.boundary_edges_directed(kept)
    bridge = []
    for a, b in half:
        if (min(a, b), max(a, b)) in removed_edges and v[a, 0] > 0 and v[b, 0] > 0:
            ma, mb = mirror[a], mirror[b]
            bridge += [(b, a, ma), (b, ma, mb)]
    bridge = np.asarray(bridge, np.int64).reshape(-1, 3)
    bridge = bridge[(bridge[:, 0] != bridge[:, 1]) & (bridge[:, 1] != bridge[:, 2]) & (bridge[:, 0] != bridge[:, 2])]
    dual_faces = np.concatenate([kept, bridge])
    moving = np.zeros(n, bool)
    moving[np.unique(bridge)] = True
    lap = mesh_ops.uniform_laplacian(dual_faces, n, boundary_aware=False)
    step = sparse.identity(n, format="csr") + 0.5 * sparse.diags(moving.astype(np.float64)) @ lap
    smoothing = sparse.identity(n, format="csr")
    for _ in range(int(dual_smoothing_iterations)):
        smoothing = (step @ smoothing).tocsr()
    smoothing.eliminate_zeros()
    edges = mesh_edges(np.concatenate([faces, dual_faces]))
    return BodyMesh(interpolation=interp.tocsr(), faces=faces, dual_faces=dual_faces, dual_smoothing=smoothing,
                    segments=segments, segment_names=segment_names, edges=edges, inner_leg=inner,
                    subdivisions=int(subdivisions))
