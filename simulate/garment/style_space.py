"""TailorNet's style space (seed 000, Sec. 4.2, 5.1): sample styles, drape them on the
canonical body, PCA of the canonical displacements; sample from that PCA, drape again,
recompute the PCA (two rounds by default) and keep the first components as gamma.

Canonical displacement of a body-topology garment: draped vertex minus the body vertex
under it (I, ``template.body_vertex_index``) on the neutral canonical body; of the skirt:
draped vertex minus the mean draped skirt of the first round.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simulate.garment.style import sample_styles
from simulate.garment.templates import GarmentTemplate, body_joints

#: Components kept while alternating sampling and draping (before the final cut).
ROUND_COMPONENTS = 8


def fit_pca(displacements: np.ndarray, components: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA of (N, V, 3) displacements [m]: mean (V, 3), components (K, V, 3) orthonormal
    (flattened), variances (K,) [m^2] of the coefficients; K = min(components, N)."""
    x = np.asarray(displacements, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"displacements must have shape (N, V, 3), got {x.shape}")
    if components < 1:
        raise ValueError(f"components must be >= 1, got {components}")
    n = x.shape[0]
    flat = x.reshape(n, -1)
    mean = flat.mean(0)
    _, s, vt = np.linalg.svd(flat - mean, full_matrices=False)
    k = min(components, len(s))
    var = s[:k] ** 2 / max(n - 1, 1)
    # deterministic sign: largest-magnitude entry of each component positive
    signs = np.sign(vt[np.arange(k), np.argmax(np.abs(vt[:k]), axis=1)])
    signs[signs == 0] = 1
    return mean.reshape(-1, 3), (vt[:k] * signs[:, None]).reshape(k, -1, 3), var


def reference_vertices(template: GarmentTemplate, body) -> np.ndarray:
    """What displacements are measured from: body vertices under the garment (I) on the
    neutral canonical body, (V, 3) [m]; None-like zeros for the skirt (see StyleSpace)."""
    if not template.follows_body_topology:
        return np.zeros((template.vertex_count, 3))
    bv, _ = body_joints(body, body.shape_default)
    return bv[template.body_vertex_index]


@dataclass
class StyleSpace:
    """A garment type's style PCA: vertices = reference + mean + gamma @ components.

    Attributes:
        garment_type, template_hash: which template the space belongs to.
        reference: (V, 3) [m] body vertices under the garment (zeros for the skirt, whose
            ``mean`` is then the mean skirt itself).
        mean: mean displacement (V, 3) [m]; components: (K, V, 3), orthonormal flattened;
        variances: (K,) [m^2]; history: per-round info (styles drawn, statuses, timings).
    """

    garment_type: str
    template_hash: str
    reference: np.ndarray
    mean: np.ndarray
    components: np.ndarray
    variances: np.ndarray
    history: list[dict] = field(default_factory=list)

    @property
    def size(self) -> int:
        return int(len(self.variances))

    def gamma_to_garment(self, gamma) -> np.ndarray:
        """(K,) or (N, K) gamma -> garment vertices (N, V, 3) [m] on the neutral canonical body."""
        g = np.atleast_2d(np.asarray(gamma, dtype=np.float64))
        if g.shape[1] != self.size:
            raise ValueError(f"gamma must have {self.size} values per garment, got shape {np.shape(gamma)}")
        disp = self.mean[None] + np.einsum("nk,kvd->nvd", g, self.components)
        return (self.reference[None] + disp).astype(np.float32)

    def garment_to_gamma(self, vertices) -> np.ndarray:
        """Garment vertices (V, 3) or (N, V, 3) -> gamma (N, K) (least squares = projection)."""
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim == 2:
            v = v[None]
        if v.shape[1:] != self.mean.shape:
            raise ValueError(f"vertices must have shape (N, {self.mean.shape[0]}, 3), got {np.shape(vertices)}")
        disp = (v - self.reference[None] - self.mean[None]).reshape(len(v), -1)
        return disp @ self.components.reshape(self.size, -1).T

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, garment_type=np.array(self.garment_type), template_hash=np.array(self.template_hash),
                            reference=self.reference.astype(np.float32), mean=self.mean.astype(np.float32),
                            components=self.components.astype(np.float32), variances=self.variances,
                            history=np.array(json.dumps(self.history)))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "StyleSpace":
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"style space file {str(path)!r} does not exist")
        with np.load(path, allow_pickle=False) as z:
            return cls(str(z["garment_type"]), str(z["template_hash"]), z["reference"].astype(np.float64),
                       z["mean"].astype(np.float64), z["components"].astype(np.float64), z["variances"],
                       json.loads(str(z["history"])))


def build_style_space(
    template: GarmentTemplate,
    body,
    *,
    samples: int = 20,
    rounds: int = 2,
    components: int = 2,
    seed: int = 0,
    device: str = "cpu",
    drape_options: dict | None = None,
    progress=None,
) -> tuple[StyleSpace, np.ndarray]:
    """Alternates draping and PCA (TailorNet 4.2). Returns (space, final drapes (N, V, 3)).

    Round 1 drapes ``samples`` styles drawn uniformly from the style ranges; each later
    round drapes ``samples`` garments drawn from the previous PCA (gamma ~ N(0, var) over
    the first ROUND_COMPONENTS components). Only converged worlds feed the PCA.
    """
    from simulate.garment.drape import drape_canonical
    from simulate.garment.templates import apply_style

    if samples < 2:
        raise ValueError(f"samples must be >= 2 for a PCA, got {samples}")
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    opts = dict(drape_options or {})
    rng = np.random.default_rng(seed)
    shape = body.shape_default
    reference = reference_vertices(template, body)
    history: list[dict] = []
    garments = [apply_style(template, s, body) for s in sample_styles(template.garment_type, samples, seed=seed)]
    drapes = None
    space = None
    for r in range(rounds):
        t0 = time.perf_counter()
        result = drape_canonical([(template, g) for g in garments], body, shape, device=device, **opts)
        good = np.array([s != "EXPLODED" for s in result.status])
        drapes = np.stack([result.vertices[i] for i in range(len(garments)) if good[i]])
        if len(drapes) < 2:
            raise RuntimeError(f"style space round {r + 1}: only {len(drapes)} of {len(garments)} drapes usable "
                               f"(statuses {result.status})")
        if not template.follows_body_topology and r == 0:
            reference = np.zeros_like(reference)
        keep = components if r == rounds - 1 else ROUND_COMPONENTS
        mean, comps, var = fit_pca(drapes - reference[None], keep)
        space = StyleSpace(template.garment_type, template.content_hash(), reference, mean, comps, var, history)
        history.append({"round": r + 1, "garments": len(garments), "used": int(good.sum()),
                        "statuses": result.status, "seconds": round(time.perf_counter() - t0, 3),
                        "max_penetration_m": float(result.max_penetration_m.max()),
                        "variances": [float(v) for v in var]})
        if progress:
            progress(history[-1])
        if r < rounds - 1:
            gamma = rng.normal(size=(samples, space.size)) * np.sqrt(var)[None]
            garments = [outside_body(template, g, body) for g in space.gamma_to_garment(gamma)]
    return space, drapes


def outside_body(template: GarmentTemplate, vertices: np.ndarray, body, *, shape=None) -> np.ndarray:
    """A garment (V, 3) [m] sampled from the PCA (or moved to another shape) pushed out of
    the canonical body of ``shape`` and relaxed, so the drape starts without deep
    interpenetration (see :func:`simulate.garment.templates.relax_outside`)."""
    from simulate.garment import mesh_ops
    from simulate.garment.templates import relax_outside

    bv, _ = body_joints(body, body.shape_default if shape is None else shape)
    query = mesh_ops.ClosestPointQuery(bv, body.faces)
    return relax_outside(np.asarray(vertices, dtype=np.float64), template.faces, query).astype(np.float32)


def select_prototypes(drapes: np.ndarray, count: int, *, initial=None):
    """Greedy convex-combination prototypes (TailorNet 4.4) via
    ``simulate.garment.prototypes.choose_prototypes``. Returns its PrototypeChoice
    (indices, mean_error_mm, max_error_mm, weights)."""
    from simulate.garment.prototypes import choose_prototypes

    return choose_prototypes(np.asarray(drapes, dtype=np.float64), int(count), initial=initial)
