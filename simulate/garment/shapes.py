"""TailorNet's 9 training shapes (seed 000, Sec. 5.2) re-expressed for a body model:
the two most influential shape parameters at 4 levels each (others neutral), plus the
neutral shape; and a seeded sampler of test shapes.

Influence of parameter i = mean over rest-mesh vertices of |v(x + d e_i) - v(x - d e_i)|
/ (2 d) around the neutral shape x [m per unit parameter]. For anny the levels are the
centres of 4 equal bins of the parameter range, (0.125, 0.375, 0.625, 0.875): equally
spaced like TailorNet's, symmetric about neutral (0.5, added once as the 9th shape) and
short of anny's most extreme blends.
"""
from __future__ import annotations

import numpy as np

#: Finite-difference step for the influence measurement [parameter units].
INFLUENCE_STEP = 0.1
LEVEL_COUNT = 4
#: Parameters not used as shape axes by default: anny's age blends child -> elderly
#: bodies (measured as the most influential parameter, 0.88 m/unit, but a change of
#: person class, not an adult body-shape variation like SMPL's first betas).
EXCLUDED_BY_DEFAULT: tuple[str, ...] = ("age",)


def shape_influence(body, *, step: float = INFLUENCE_STEP) -> dict[str, float]:
    """{parameter name: mean vertex displacement [m] per unit change} around neutral."""
    base = np.asarray(body.shape_default, dtype=np.float32)
    lo, hi = body.shape_ranges[:, 0], body.shape_ranges[:, 1]
    batch = []
    for i in range(body.shape_size):
        for sgn in (1, -1):
            s = base.copy()
            s[i] = np.clip(s[i] + sgn * step, lo[i], hi[i])
            batch.append(s)
    verts, _ = body.rest(np.stack(batch))
    out = {}
    for i, name in enumerate(body.shape_names):
        plus, minus = verts[2 * i], verts[2 * i + 1]
        dx = float(batch[2 * i][i] - batch[2 * i + 1][i])
        out[name] = float(np.linalg.norm(plus - minus, axis=1).mean() / max(dx, 1e-12))
    return out


def training_shapes(body, *, parameters: tuple[str, str] | None = None) -> tuple[np.ndarray, list[str]]:
    """The 9 training shapes (9, S) and the two varied parameter names.

    Order: neutral first, then parameter A at the 4 levels, then parameter B.
    ``parameters`` defaults to the two most influential ones (:func:`shape_influence`)
    outside :data:`EXCLUDED_BY_DEFAULT`.
    """
    if parameters is None:
        infl = {k: v for k, v in shape_influence(body).items() if k not in EXCLUDED_BY_DEFAULT}
        parameters = tuple(sorted(infl, key=lambda k: -infl[k])[:2])
    for p in parameters:
        if p not in body.shape_names:
            raise ValueError(f"unknown shape parameter {p!r}; expected one of {', '.join(body.shape_names)}")
    base = np.asarray(body.shape_default, dtype=np.float32)
    shapes = [base.copy()]
    for p in parameters:
        i = body.shape_names.index(p)
        lo, hi = body.shape_ranges[i]
        for k in range(LEVEL_COUNT):
            s = base.copy()
            s[i] = lo + (hi - lo) * (k + 0.5) / LEVEL_COUNT
            shapes.append(s)
    return np.stack(shapes).astype(np.float32), list(parameters)


def sample_test_shapes(body, n: int, *, seed: int = 0, parameters: tuple[str, str] | None = None,
                       vary_all: bool = False) -> np.ndarray:
    """``n`` test shapes (n, S): the two training parameters drawn uniformly within the
    training levels' span (others neutral), or every parameter when ``vary_all``."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    _, names = training_shapes(body, parameters=parameters)
    rng = np.random.default_rng(seed)
    base = np.asarray(body.shape_default, dtype=np.float32)
    out = np.tile(base, (n, 1))
    idx = range(body.shape_size) if vary_all else [body.shape_names.index(p) for p in names]
    for i in idx:
        lo, hi = body.shape_ranges[i]
        a = lo + (hi - lo) * 0.5 / LEVEL_COUNT
        b = lo + (hi - lo) * (LEVEL_COUNT - 0.5) / LEVEL_COUNT
        out[:, i] = rng.uniform(a, b, size=n)
    return out.astype(np.float32)
