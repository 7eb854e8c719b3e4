"""The garment model of seed 002 (Eq. 7-8) and its inverse.

A canonical garment X (unposed, deshaped) is posed for shape beta and pose theta by
T_G = X + B~s(X, beta) (+ B~p(X, theta), zero for anny: see :mod:`learn.collision_aware.fields`)
and M_G = LBS(T_G, W~(X), A(beta, theta)), with the diffused weights evaluated at X itself, so a
garment that slides over the body is skinned by the body part it is on in that frame. The skinning
transforms A come from the body model (``pose_torch(...).skinning_transforms``).

The inverse has no closed form since the weights depend on X; :func:`unpose_garment` solves it by
the fixed-point iteration X <- LBS^-1(M_G, W~(X), A) - B~s(X, beta), which converges in a few
steps where the fields are smooth (the weights change little over the distance X moves).
"""

from __future__ import annotations

import torch

from learn.collision_aware.fields import DiffusedBody
from simulate.body.kinematics import inverse_lbs, lbs


def shape_garment(fields: DiffusedBody, canonical: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
    """T_G = X + B~s(X, beta): canonical vertices [m] (B, V, 3), shape (B, S) -> [m] (B, V, 3)."""
    return canonical + fields.shape_offset(canonical, shape)


def pose_garment(fields: DiffusedBody, canonical: torch.Tensor, shape: torch.Tensor,
                 transforms: torch.Tensor, *, shaped: torch.Tensor | None = None) -> torch.Tensor:
    """M_G(X, beta, theta): canonical vertices [m] (B, V, 3), shape (B, S), skinning transforms
    (B, J, 4, 4) -> posed vertices [m] (B, V, 3). Differentiable in X and in the fields.
    ``shaped``: T_G of :func:`shape_garment` where the caller has it (one evaluation of the shape
    field instead of two)."""
    weights = fields.skinning_weights(canonical)  # (B, V, J)
    if shaped is None:
        shaped = shape_garment(fields, canonical, shape)
    return lbs(shaped, weights, transforms)


def unpose_garment(fields: DiffusedBody, posed: torch.Tensor, shape: torch.Tensor, transforms: torch.Tensor, *,
                   initial: torch.Tensor, iterations: int = 1, edges: torch.Tensor | None = None,
                   max_edge_ratio: float = 3.0) -> torch.Tensor:
    """Canonical X with M_G(X) = ``posed``, by ``iterations`` fixed-point steps from ``initial``.

    posed, initial: [m] (B, V, 3); shape (B, S); transforms (B, J, 4, 4). Returns (B, V, 3).
    ``iterations`` defaults to the projection's (``ProjectionSettings.fixed_point_iterations``).

    Where the diffused weights fold (the armpit: arm and torso weights blend over a few cm), LBS
    maps distant canonical points to the same posed point, and a step can land vertices on the
    wrong one, tens of cm from their neighbours while still reproducing ``posed``. With the mesh's
    ``edges`` (E, 2) (:func:`learn.common.mesh.mesh_edges`) such a step is caught by its edges: an
    edge of the proposal longer than ``max_edge_ratio`` times that edge in ``posed`` (lengths the
    unposing should nearly keep) is cut, and every vertex outside the largest part the remaining
    edges connect (one vertex or a whole patch that strayed) takes, for that step, weights carried
    in from that part across the mesh (:func:`weights_from_main_part`), which keeps it on the
    branch the rest of the garment is on.
    """
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if edges is not None:
        reference = torch.linalg.vector_norm(posed[:, edges[:, 1]] - posed[:, edges[:, 0]], dim=-1)  # (B, E)
    x = initial
    for _ in range(iterations):
        weights = fields.skinning_weights(x)  # (B, V, J)
        offset = fields.shape_offset(x, shape)
        proposal = inverse_lbs(posed, weights, transforms) - offset
        if edges is not None:
            length = torch.linalg.vector_norm(proposal[:, edges[:, 1]] - proposal[:, edges[:, 0]], dim=-1)
            cut = length > max_edge_ratio * reference.clamp_min(1e-6)  # (B, E)
            rows = cut.any(1).nonzero()[:, 0]  # the frames with a cut edge
            if rows.numel():
                weights = weights.index_copy(0, rows, weights_from_main_part(weights[rows], edges, cut[rows]))
                proposal = inverse_lbs(posed, weights, transforms) - offset
        x = proposal
    return x


def mesh_parts(vertex_count: int, edges: torch.Tensor, cut: torch.Tensor) -> torch.Tensor:
    """Connected parts of a mesh without its ``cut`` edges: (B, V) labels, each vertex labelled by
    the smallest vertex index of its part. edges (E, 2); cut (B, E) bool. Minimum-label propagation
    along the kept edges, with pointer jumping, on the edges' device."""
    batch = cut.shape[0]
    labels = torch.arange(vertex_count, device=edges.device).repeat(batch, 1)  # (B, V)
    big = vertex_count
    a = edges[:, 0].expand(batch, -1)
    b = edges[:, 1].expand(batch, -1)
    while True:
        la = torch.where(cut, big, labels.gather(1, a))
        lb = torch.where(cut, big, labels.gather(1, b))
        new = labels.scatter_reduce(1, a, lb, "amin").scatter_reduce(1, b, la, "amin")
        new = new.gather(1, new)  # pointer jumping: a label's own label
        if torch.equal(new, labels):
            return labels
        labels = new


def weights_from_main_part(weights: torch.Tensor, edges: torch.Tensor, cut: torch.Tensor) -> torch.Tensor:
    """``weights`` (B, V, J) with every vertex outside its frame's largest part of the mesh
    without the ``cut`` edges (B, E) given weights carried in from that part: breadth first along
    all edges, each vertex reached takes the mean weights of its neighbours already reached. The
    largest part keeps its own."""
    batch, vertex_count, _ = weights.shape
    labels = mesh_parts(vertex_count, edges, cut)
    sizes = torch.zeros_like(labels).scatter_add_(1, labels, torch.ones_like(labels))
    main = labels == sizes.argmax(1, keepdim=True)  # (B, V)
    if bool(main.all()):
        return weights
    out = weights.clone()
    reached = main.clone()
    while not bool(reached.all()):
        r = reached.to(weights.dtype)  # (B, V)
        count = torch.zeros_like(r).index_add_(1, edges[:, 0], r[:, edges[:, 1]]).index_add_(1, edges[:, 1], r[:, edges[:, 0]])
        front = (count > 0) & ~reached
        if not bool(front.any()):  # a part the mesh does not connect to the main one keeps its weights
            break
        held = out * r[..., None]
        summed = (torch.zeros_like(out).index_add_(1, edges[:, 0], held[:, edges[:, 1]])
                  .index_add_(1, edges[:, 1], held[:, edges[:, 0]]))
        out = torch.where(front[..., None], summed / count.clamp_min(1.0)[..., None], out)
        reached = reached | front
    return out
