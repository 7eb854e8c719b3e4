"""Scenes shared by the self-contact tests."""
from __future__ import annotations

import numpy as np

from simulate.cloth import ClothBuilder, Features
from simulate.scenes import grid_cloth


def folded_sheet_worlds(seed: int, jitter: float):
    """A 16 cm sheet (9 x 9 vertices) folded onto itself along x = 8 cm, the folded half 3 mm above
    the other, every vertex jittered by ``jitter`` [m] (normal, seeded), in two worlds, the second
    shifted 0.5 m along x.

    Returns (model on the CPU with self-contact on and no body, positions (2 x 81, 3) float32 [m])."""
    v, f = grid_cloth(9, 9, 0.16, 0.16, plane="xz")
    rng = np.random.default_rng(seed)
    folded = v.astype(np.float64).copy()
    top = folded[:, 0] > 0.08 + 1e-6  # the half past the fold line lies back over the other half
    folded[top, 0] = 0.16 - folded[top, 0]
    folded[top, 1] = 0.003
    folded += rng.normal(0.0, jitter, folded.shape)
    builder = ClothBuilder()
    for _ in range(2):
        builder.add_garment(v, f, fabric="cotton")
    model = builder.finalize("cpu", features=Features(self_contact=True, body_contact=False))
    return model, np.concatenate([folded, folded + np.array([0.5, 0.0, 0.0])]).astype(np.float32)
