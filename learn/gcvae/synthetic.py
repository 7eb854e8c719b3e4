"""Tiny static sets in the real file format for tests and examples, without garment generation:
each "garment" is a set of body segments (by type) lifted off the body along its smoothed
normals by the sample's tightness plus a smooth ripple, so offsets, masks, shapes and
topologies are real while a sample costs one body posing (milliseconds).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from learn.gcvae.body_mesh import DUAL_TYPES, build_body_mesh, canonical_body_vertices
from learn.gcvae.static_set import FILE_NAME, STYLE_WIDTH, sample_shapes
from simulate.garment import mesh_ops

#: Segments (bone names, by prefix) each synthetic type covers.
SEGMENTS_OF: dict[str, tuple[str, ...]] = {
    "tshirt": ("spine01", "spine02", "spine03", "spine04", "clavicle", "upperarm01", "neck01"),
    "pants": ("spine05", "pelvis", "upperleg", "lowerleg"),
    "skirt": ("spine05", "pelvis", "upperleg01", "upperleg02"),
}


def write_synthetic_static_set(root: str | os.PathLike, body, *, types: tuple[str, ...] = ("tshirt", "pants", "skirt"),
                               count: int = 4, seed: int = 0) -> Path:
    """Writes ``root/static_set.npz`` with ``count`` samples per type (a quarter, at least one,
    in the test split); returns its path."""
    mesh = build_body_mesh(body, subdivisions=0)
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {k: [] for k in ("type", "shape", "tightness", "style", "split", "body_vertices",
                                             "offsets", "mask", "registration_mm")}
    for ti, garment_type in enumerate(types):
        prefixes = SEGMENTS_OF[garment_type]
        covered = np.array([any(n.startswith(p) for p in prefixes) for n in mesh.segment_names])[mesh.segments]
        shapes = sample_shapes(count, rng, body.shape_size)
        test = np.zeros(count, bool)
        test[rng.permutation(count)[:max(1, count // 4)]] = True
        for k in range(count):
            standard = mesh.vertices(canonical_body_vertices(body, shapes[k]))[0]
            _, faces = mesh.topology(garment_type)
            base = mesh.positions_for(garment_type, standard)
            mask = covered.copy()
            if garment_type in DUAL_TYPES:
                mask &= np.isin(np.arange(len(mask)), np.unique(faces))
                mask &= ~(mesh.inner_leg & ~mesh.bridge_vertices())
            tightness = float(rng.uniform(0.005, 0.05))
            normals = mesh_ops.smooth_normals(base, faces, iterations=5)
            ripple = 0.005 * np.sin(20.0 * base[:, 1] + rng.uniform(0, 2 * np.pi))
            offsets = np.where(mask[:, None], base + normals * (tightness + ripple)[:, None] - standard, 0.0)
            style = np.full(STYLE_WIDTH, np.nan, np.float32)
            style[0] = tightness
            for key, value in (("type", ti), ("shape", shapes[k]), ("tightness", tightness), ("style", style),
                               ("split", int(test[k])), ("body_vertices", standard.astype(np.float32)),
                               ("offsets", offsets.astype(np.float32)), ("mask", mask),
                               ("registration_mm", [0.0, 0.0])):
                rows[key].append(value)
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    arrays["types"] = np.array(types)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / FILE_NAME
    tmp = root / f".{FILE_NAME}.{os.getpid()}.tmp.npz"
    meta = {"synthetic": True, "count_per_type": count, "seed": seed}
    np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **arrays, **mesh.arrays())
    os.replace(tmp, path)
    return path
