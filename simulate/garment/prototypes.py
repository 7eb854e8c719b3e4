"""Greedy choice of K prototype style-shapes (TailorNet Sec. 4.4, "Choosing K prototypes").

Given the canonical-pose garment displacements of X style-shape pairs, start from an
initial pool and repeatedly add the pair that the current pool approximates worst, where
each pair is approximated by the best convex combination of the pool's garments. The
convex fit is non-negative least squares with the sum-to-one constraint imposed by an
appended heavily weighted row; the weights are then renormalised to sum exactly to one,
so every reported error is that of a true convex combination. A pair's best combination
so far is kept when a refit with a larger pool is numerically worse (the old weights,
padded with a zero, are still feasible), which makes the error non-increasing in K.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

SUM_TO_ONE_WEIGHT = 1.0e3
METERS_TO_MM = 1000.0


@dataclass
class PrototypeChoice:
    """indices: chosen pairs in pick order, shape (K,); mean_error_mm[k] / max_error_mm[k]:
    mean and worst over all X pairs of the mean per-vertex error [mm] of their best convex
    approximation by the first k + 1 prototypes, shape (K,); weights: convex weights of
    every pair over the K prototypes, shape (X, K)."""

    indices: np.ndarray
    mean_error_mm: np.ndarray
    max_error_mm: np.ndarray
    weights: np.ndarray


def convex_fit(basis: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Convex weights w (w >= 0, sum 1), shape (M,), minimising ||basis.T w - target||.

    basis: shape (M, D); target: shape (D,). Solved on the M x M Gram matrix
    (:func:`convex_fit_gram`), so the cost does not grow with D.
    """
    basis = np.asarray(basis, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    return convex_fit_gram(basis @ basis.T, basis @ target)


def convex_fit_gram(gram: np.ndarray, correlation: np.ndarray) -> np.ndarray:
    """:func:`convex_fit` from ``gram`` = basis basis.T, shape (M, M), and ``correlation`` =
    basis target, shape (M,).

    ||basis.T w - target||^2 = w.T G w - 2 c.T w + const; with G = U diag(s) U.T this is
    ||diag(s)^1/2 U.T w - diag(s)^-1/2 U.T c||^2 + const over the eigen-directions the basis
    spans (s above 1e-12 of the largest; c has no part along the others), a non-negative least
    squares problem of M unknowns and at most M rows. Sum-to-one is an appended row weighted
    relative to the data scale, then exact renormalisation. A problem with D rows of data
    (23,232 for the 7.7k t-shirt) took scipy's NNLS seconds to minutes per fit on it directly.
    """
    gram = np.asarray(gram, dtype=np.float64)
    correlation = np.asarray(correlation, dtype=np.float64)
    m = gram.shape[0]
    values, vectors = np.linalg.eigh(0.5 * (gram + gram.T))
    top = max(float(values.max()), 0.0)
    keep = values > 1e-12 * top if top > 0.0 else np.zeros(m, dtype=bool)
    root = np.sqrt(values[keep])
    a = root[:, None] * vectors[:, keep].T  # (K, M)
    b = (vectors[:, keep].T @ correlation) / root if keep.any() else np.zeros(0)
    heavy = SUM_TO_ONE_WEIGHT * max(np.sqrt(top), 1e-12)
    weights, _ = nnls(np.vstack([a, np.full((1, m), heavy)]), np.concatenate([b, [heavy]]), maxiter=50 * m + 100)
    total = weights.sum()
    if total <= 0:
        return np.full(m, 1.0 / m)
    return weights / total


def _vertex_error_mm(approx: np.ndarray, target: np.ndarray) -> float:
    return float(np.linalg.norm((approx - target).reshape(-1, 3), axis=1).mean() * METERS_TO_MM)


def choose_prototypes(
    canonical_displacements: np.ndarray,
    prototype_count: int,
    *,
    initial: np.ndarray | list[int] | None = None,
) -> PrototypeChoice:
    """Greedily pick ``prototype_count`` prototypes among X style-shape pairs.

    Args:
        canonical_displacements: garment displacements [m] in the canonical pose, one per
            pair, shape (X, V, 3).
        prototype_count: K, 1 <= K <= X.
        initial: indices forming the starting pool (TailorNet starts from the body shapes
            of one common style); default: the single pair closest to the mean garment.
    """
    data = np.asarray(canonical_displacements, dtype=np.float64)
    if data.ndim != 3 or data.shape[-1] != 3:
        raise ValueError(
            f"canonical_displacements must have shape (X, V, 3), got {data.shape}"
        )
    pair_count = data.shape[0]
    if not 1 <= prototype_count <= pair_count:
        raise ValueError(
            f"prototype_count must be in [1, {pair_count}] (the number of pairs), got {prototype_count}"
        )
    flat = data.reshape(pair_count, -1)  # (X, 3V)
    if initial is None or len(initial) == 0:
        pool = [int(np.argmin(np.linalg.norm(flat - flat.mean(0), axis=1)))]
    else:
        pool = [int(i) for i in initial]
        if len(set(pool)) != len(pool) or min(pool) < 0 or max(pool) >= pair_count:
            raise ValueError(f"initial must hold distinct indices in [0, {pair_count}), got {pool}")
        if len(pool) > prototype_count:
            raise ValueError(
                f"initial pool has {len(pool)} pairs, more than prototype_count={prototype_count}"
            )
    best_weights = np.zeros((pair_count, pair_count))  # over all pairs, zero off the pool
    best_error = np.full(pair_count, np.inf)
    mean_errors: list[float] = []
    max_errors: list[float] = []
    fitted_pool_size = 0

    gram = flat @ flat.T  # (X, X): every fit works on its pool's block

    def refit() -> None:
        basis = flat[pool]  # (M, 3V)
        for x in range(pair_count):
            w = convex_fit_gram(gram[np.ix_(pool, pool)], gram[pool, x])
            error = _vertex_error_mm(w @ basis, flat[x])
            if error < best_error[x]:
                best_error[x] = error
                best_weights[x] = 0.0
                best_weights[x, pool] = w

    while True:
        refit()
        # Record one error per pool size reached (the initial pool may hold several).
        while fitted_pool_size < len(pool):
            fitted_pool_size += 1
            if fitted_pool_size == len(pool):
                mean_errors.append(float(best_error.mean()))
                max_errors.append(float(best_error.max()))
            else:
                mean_errors.append(np.nan)
                max_errors.append(np.nan)
        if len(pool) >= prototype_count:
            break
        candidates = np.setdiff1d(np.arange(pair_count), pool)
        pool.append(int(candidates[np.argmax(best_error[candidates])]))
    indices = np.asarray(pool, dtype=np.int64)
    return PrototypeChoice(
        indices=indices,
        mean_error_mm=np.asarray(mean_errors),
        max_error_mm=np.asarray(max_errors),
        weights=best_weights[:, indices],
    )


def canonical_frame_per_pair(
    pose: np.ndarray, pair_ids: np.ndarray, *, canonical_pose: np.ndarray | None = None
) -> np.ndarray:
    """For each pair id 0..X-1, the frame whose pose is closest to the canonical pose.

    pose: axis-angle poses, shape (N, P); pair_ids: shape (N,) with values 0..X-1;
    canonical_pose: the pose garments are draped in (the body model's A-pose), shape (P,),
    default zeros. Returns frame indices, shape (X,).
    """
    pose = np.asarray(pose)
    pair_ids = np.asarray(pair_ids)
    if pose.ndim != 2 or pair_ids.shape != (pose.shape[0],):
        raise ValueError(
            f"pose must be (N, P) and pair_ids (N,), got {pose.shape} and {pair_ids.shape}"
        )
    reference = np.zeros(pose.shape[1]) if canonical_pose is None else np.asarray(canonical_pose).reshape(-1)
    if reference.shape[0] != pose.shape[1]:
        raise ValueError(f"canonical_pose must have {pose.shape[1]} values, got {reference.shape[0]}")
    norms = np.linalg.norm(pose - reference[None], axis=1)
    pair_count = int(pair_ids.max()) + 1
    frames = np.empty(pair_count, dtype=np.int64)
    for pair in range(pair_count):
        members = np.flatnonzero(pair_ids == pair)
        if members.size == 0:
            raise ValueError(f"pair id {pair} has no frames; pair ids must be 0..X-1 without gaps")
        frames[pair] = members[np.argmin(norms[members])]
    return frames
