"""The pooling hierarchy (seed 004, Sec. 4.2, Fig. 6): coarser and coarser graphs whose
vertices are clusters of the finer graph's vertices **of one body segment**, ending at one
vertex per segment; max-pooling over a cluster and copy-unpooling back.

The seed simplifies the mesh with quadric edge collapses forbidden across segments. Here each
level clusters within each segment directly: ``ceil(n / factor)`` centres per segment by
farthest-point sampling, every vertex joining the centre nearest along the segment's own
edges (Dijkstra on edge lengths; a vertex its segment's edges do not reach joins the
Euclidean-nearest centre of its segment). Clusters are connected where the segment is, sizes
even, and no cluster ever holds two segments, by construction. A coarse vertex sits at its
cluster's mean; coarse edges join clusters that any fine edge joins.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import sparse
from scipy.sparse.csgraph import dijkstra


@dataclass
class Level:
    """One coarsening: ``assignment`` (N_fine,) coarse vertex of each fine vertex; the coarse
    graph's ``edges`` (E, 2), ``segments`` (N_coarse,) and ``positions`` (N_coarse, 3) [m]."""

    assignment: np.ndarray
    edges: np.ndarray
    segments: np.ndarray
    positions: np.ndarray

    @property
    def size(self) -> int:
        return int(len(self.segments))


def _farthest_points(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` farthest-point samples, starting nearest the centroid (deterministic)."""
    first = int(np.argmin(np.linalg.norm(points - points.mean(0), axis=1)))
    chosen = [first]
    distance = np.linalg.norm(points - points[first], axis=1)
    for _ in range(1, count):
        nxt = int(np.argmax(distance))
        chosen.append(nxt)
        distance = np.minimum(distance, np.linalg.norm(points - points[nxt], axis=1))
    return np.asarray(chosen, np.int64)


def coarsen(positions: np.ndarray, edges: np.ndarray, segments: np.ndarray, factor: float,
            *, one_per_segment: bool = False) -> Level:
    """One level of the hierarchy (see the module docstring)."""
    positions = np.asarray(positions, np.float64)
    n = len(positions)
    same = segments[edges[:, 0]] == segments[edges[:, 1]]
    e = edges[same]
    length = np.linalg.norm(positions[e[:, 0]] - positions[e[:, 1]], axis=1) + 1e-12
    graph = sparse.csr_matrix((np.concatenate([length, length]), (np.concatenate([e[:, 0], e[:, 1]]),
                                                                   np.concatenate([e[:, 1], e[:, 0]]))), shape=(n, n))
    assignment = np.full(n, -1, np.int64)
    next_id = 0
    out_segments = []
    for seg in np.unique(segments):
        members = np.flatnonzero(segments == seg)
        count = 1 if one_per_segment else max(1, int(np.ceil(len(members) / factor)))
        centres = members[_farthest_points(positions[members], count)]
        if count == 1:
            local = np.zeros(len(members), np.int64)
        else:
            sub = graph[members][:, members]
            centre_local = np.searchsorted(members, centres)
            dist = dijkstra(sub, indices=centre_local, min_only=False)  # (count, m)
            local = np.argmin(dist, axis=0)
            unreached = ~np.isfinite(dist.min(0))
            if unreached.any():
                d = np.linalg.norm(positions[members[unreached]][:, None] - positions[centres][None], axis=2)
                local[unreached] = np.argmin(d, axis=1)
            # Renumber so ids are contiguous even if a centre lost all its members to another.
            _, local = np.unique(local, return_inverse=True)
        assignment[members] = next_id + local
        used = int(local.max()) + 1
        out_segments += [seg] * used
        next_id += used
    coarse_segments = np.asarray(out_segments, np.int64)
    counts = np.bincount(assignment, minlength=next_id)
    coarse_positions = np.stack([np.bincount(assignment, positions[:, k], minlength=next_id) / counts
                                 for k in range(3)], 1)
    ce = np.sort(assignment[edges], axis=1)
    ce = np.unique(ce[ce[:, 0] != ce[:, 1]], axis=0)
    return Level(assignment=assignment, edges=ce, segments=coarse_segments, positions=coarse_positions)


def build_hierarchy(positions: np.ndarray, edges: np.ndarray, segments: np.ndarray, *, factor: float,
                    levels: int) -> list[Level]:
    """``levels`` coarsenings; the last leaves one vertex per segment."""
    if levels < 1:
        raise ValueError(f"model.pool_levels must be >= 1, got {levels}")
    if factor <= 1:
        raise ValueError(f"model.pool_factor must be > 1, got {factor}")
    out = []
    pos, e, seg = np.asarray(positions, np.float64), np.asarray(edges, np.int64), np.asarray(segments, np.int64)
    for level in range(levels):
        lv = coarsen(pos, e, seg, factor, one_per_segment=level == levels - 1)
        out.append(lv)
        pos, e, seg = lv.positions, lv.edges, lv.segments
    return out


def cluster_members(assignment: np.ndarray, coarse_count: int) -> np.ndarray:
    """(N_coarse, S) fine vertices of each cluster, padded with N_fine (S: the largest cluster)."""
    assignment = np.asarray(assignment, np.int64)
    order = np.argsort(assignment, kind="stable")
    counts = np.bincount(assignment, minlength=coarse_count)
    members = np.full((coarse_count, int(counts.max())), len(assignment), np.int64)
    slot = np.arange(len(assignment)) - np.repeat(np.cumsum(counts) - counts, counts)
    members[assignment[order], slot] = order
    return members


def max_pool(x: torch.Tensor, members: torch.Tensor) -> torch.Tensor:
    """(N_fine, ...) -> (N_coarse, ...) (vertex-major features): the maximum over each
    cluster; ``members`` from :func:`cluster_members` (a gather and a max: several times
    faster than a scatter-max)."""
    padded = torch.cat([x, x.new_full((1,) + tuple(x.shape[1:]), float("-inf"))], 0)
    # index_select: its backward is an index_add, where advanced indexing's sorts its indices.
    gathered = padded.index_select(0, members.reshape(-1))
    return gathered.view(members.shape[0], members.shape[1], *x.shape[1:]).amax(1)


def copy_unpool(x: torch.Tensor, assignment: torch.Tensor) -> torch.Tensor:
    """(N_coarse, ...) -> (N_fine, ...): each fine vertex gets its cluster's features."""
    return x.index_select(0, assignment)
