"""bench/bench_self_contact_newton.py: the stopping rule it puts around Newton is our simulator's,
and its holds end as ``run_sequences`` ends them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import warp as wp


@pytest.fixture
def bench(load_bench, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "bench"))  # its sibling imports
    return load_bench("bench_self_contact_newton")


def test_rest_rule_gives_the_quasi_static_verdicts(bench):
    """The same particle states through QuasiStaticSimulator's metrics and status update and
    through RestRule: the same RUNNING / CONVERGED / EXPLODED per frame (outliers, limit cycles, patience)."""
    from simulate.cloth import ClothBuilder
    from simulate.quasi_static import QuasiStaticSimulator, SimSettings, WorldStatus

    n = 6
    u, v = np.meshgrid(np.arange(n), np.arange(n))
    vertices = np.stack([u.ravel() * 0.02, v.ravel() * 0.02, np.zeros(n * n)], axis=1)
    faces = np.array([[i * n + j, i * n + j + 1, (i + 1) * n + j] for i in range(n - 1) for j in range(n - 1)]
                     + [[i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j] for i in range(n - 1) for j in range(n - 1)])
    builder = ClothBuilder()
    builder.add_garment(vertices, faces)
    model = builder.finalize("cpu")
    settings = SimSettings(tolerance=0.05, patience=3, outlier_fraction=0.1, limit_cycle_window=4, use_cpu_graph=False)
    rng = np.random.default_rng(3)
    count = n * n  # 36 particles: 3 may stay fast (floor(0.1 * 36))
    for trial in range(4):
        sim = QuasiStaticSimulator(model, None, solver="xpbd", settings=settings)
        rule = bench.RestRule(settings, count, wp.get_device("cpu"))
        q = wp.zeros(count, dtype=wp.vec3, device="cpu")
        qd = wp.zeros(count, dtype=wp.vec3, device="cpu")
        base = vertices.astype(np.float32)
        verdicts = []
        for frame in range(12):
            if frame < 3 + trial:  # busy
                fast = rng.random(count) < 0.3
            else:  # exactly the allowed outliers (3), and in trial 1 one more on odd frames
                fast = np.zeros(count, bool)
                fast[rng.choice(count, 4 if trial == 1 and frame % 2 else 3, replace=False)] = True
            speed = np.where(fast, 0.2, 0.01)[:, None]
            cycle = (frame % 2) * 1e-4 * (rng.random(count) < 0.5)[:, None]  # small 2-frame limit cycles
            drift = np.where(fast, 0.2 * settings.frame_dt * frame, 0.0)[:, None]  # the fast ones move on
            x = (base + cycle + drift).astype(np.float32)
            xd = (rng.normal(size=(count, 3)) * speed / np.sqrt(3)).astype(np.float32)
            if trial == 3 and frame == 6:
                xd[0] = (100.0, 0.0, 0.0)  # faster than the explosion speed
            for arr, val in ((sim.state_0.particle_q, x), (sim.state_0.particle_qd, xd), (q, x), (qd, xd)):
                arr.assign(val)
            sim._sync_active()
            sim._launched_running = sim.status == WorldStatus.RUNNING
            sim._measure()
            ours = WorldStatus(int(sim.finish_frame()[0]))
            theirs = rule.frame(q, qd)
            assert theirs == ours, (trial, frame)
            verdicts.append(ours)
            if ours != WorldStatus.RUNNING:
                break
        expected = {0: WorldStatus.CONVERGED, 1: WorldStatus.RUNNING, 2: WorldStatus.CONVERGED, 3: WorldStatus.EXPLODED}
        assert verdicts[-1] == expected[trial], verdicts  # trial 1: never 3 calm frames in a row
        assert len(verdicts) >= 3  # not converged before `patience` calm frames


def test_hold_ends_as_run_sequences_ends_a_hold(bench):
    from simulate.quasi_static import WorldStatus as S

    def scripted(verdicts):
        it = iter(verdicts)
        restarts = []
        return (lambda: next(it)), (lambda: restarts.append(1)), restarts

    step, restart, restarts = scripted([S.CONVERGED, S.RUNNING, S.CONVERGED, S.CONVERGED])
    assert bench.hold_to_rest(step, restart, 3, 10) == (3, S.CONVERGED)  # at rest before 3 frames: held on
    assert len(restarts) == 2  # the hold's start, and the early rest
    step, restart, _ = scripted([S.RUNNING] * 5)
    assert bench.hold_to_rest(step, restart, 2, 5) == (5, S.MAX_STEPS)
    step, restart, _ = scripted([S.RUNNING, S.EXPLODED])
    assert bench.hold_to_rest(step, restart, 4, 9) == (2, S.EXPLODED)
