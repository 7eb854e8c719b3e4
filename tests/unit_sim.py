"""SimSettings of the solver and contact unit tests.

Their small scenes are judged at a light damping (5/s, so motion is not damped away before the
property under test shows), a tight explosion limit (3x triangle stretch: a unit scene has no
first-contact transients, so any larger stretch is a solver failure), convergence by the fastest
particle alone (no outliers, no limit cycles) below 0.01 m/s for 5 frames, a 600-frame budget, and
frames of 1/60 s in 10 substeps of 10 iterations with the body queried on every substep, and no
untangling unless a test asks for it; the library's defaults are the dataset's."""
from __future__ import annotations

from simulate.quasi_static import SimSettings

UNIT_SIM = dict(damping=5.0, explosion_stretch=3.0, patience=5, outlier_fraction=0.0, limit_cycle_window=0, max_frames=600,
                frame_dt=1.0 / 60.0, substeps=10, iterations=10, tolerance=0.01, body_contact_detect_every=1,
                untangle=False)


def unit_settings(**fields) -> SimSettings:
    """SimSettings with :data:`UNIT_SIM` under the given fields."""
    return SimSettings(**{**UNIT_SIM, **fields})
