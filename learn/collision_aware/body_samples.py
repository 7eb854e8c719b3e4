"""Points around the canonical body where the distilled fields and the SDF are trained.

Garments live on and just outside the body, so most points are drawn near the surface (an
offset along the normal of an area-uniform surface point, skewed towards small offsets), and a
share uniformly in the body's padded bounding box so the networks stay sane everywhere.
"""

from __future__ import annotations

import numpy as np


def surface_points(vertices: np.ndarray, faces: np.ndarray, count: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points on a triangle mesh and their face normals, (count, 3) each [m]."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    face = rng.choice(f.shape[0], size=count, p=area / area.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    points = (1 - s)[:, None] * a[face] + (s * (1 - r2))[:, None] * b[face] + (s * r2)[:, None] * c[face]
    normals = cross[face] / np.maximum(2.0 * area[face], 1e-12)[:, None]
    return points, normals


def body_bounds(vertices: np.ndarray, *, padding_m: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Padded axis-aligned bounding box (low, high) of the body [m], (3,) each."""
    v = np.asarray(vertices, np.float64)
    return v.min(0) - padding_m, v.max(0) + padding_m


def points_near_body(
    vertices: np.ndarray,
    faces: np.ndarray,
    count: int,
    *,
    min_offset_m: float = -0.01,
    max_offset_m: float = 0.15,
    box_fraction: float = 0.1,
    padding_m: float = 0.2,
    seed: int = 0,
) -> np.ndarray:
    """``count`` training points [m], (count, 3): surface points moved along their normal by an
    offset in [min_offset_m, max_offset_m] (density falling with the offset), plus
    ``box_fraction`` of them uniform in the padded bounding box."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    if not min_offset_m <= max_offset_m:
        raise ValueError(f"min_offset_m ({min_offset_m}) must be <= max_offset_m ({max_offset_m})")
    if not 0.0 <= box_fraction <= 1.0:
        raise ValueError(f"box_fraction must be in [0, 1], got {box_fraction}")
    rng = np.random.default_rng(seed)
    box_count = int(round(box_fraction * count))
    near_count = count - box_count
    points, normals = surface_points(vertices, faces, near_count, rng)
    offset = np.where(rng.random(near_count) < 0.5,
                      rng.uniform(min_offset_m, max_offset_m, near_count),  # half spread over the band
                      np.clip(rng.normal(0.0, 0.01, near_count), min_offset_m, max_offset_m))  # half within ~1 cm
    points = points + offset[:, None] * normals
    low, high = body_bounds(vertices, padding_m=padding_m)
    box = rng.uniform(low, high, size=(box_count, 3))
    return np.concatenate([points, box]).astype(np.float32)
