"""bench/bench_dataset.py's steady rates: over the second half of the run, not from its start."""
from __future__ import annotations

import importlib.util
from pathlib import Path


def _bench():
    path = Path(__file__).parents[1] / "bench" / "bench_dataset.py"
    spec = importlib.util.spec_from_file_location("bench_dataset_under_test", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_steady_rates_skip_the_start_up_burst():
    bench = _bench()
    # nothing for 30 s, a burst of 900 targets by 40 s, then 100 targets/s and 5,000 world-frames/s
    beats = [{"elapsed_s": 0.0, "targets_done": 0, "world_frames": 0, "frames": 0}]
    beats += [{"elapsed_s": float(t), "targets_done": 0 if t < 40 else 900 + 100 * (t - 40),
               "world_frames": 5000 * t, "frames": 20 * t} for t in range(10, 130, 10)]
    steady = bench.steady_rates(beats)
    assert steady == {"from_s": 60.0, "to_s": 120.0, "target_poses_per_s": 100.0, "world_frames_per_s": 5000.0,
                      "frames_per_s": 20.0}
    whole_run = beats[-1]["targets_done"] / beats[-1]["elapsed_s"]
    assert whole_run < 90.0, "the rate from the start mixes in the idle start and the burst"
    assert bench.steady_rates(beats[:2]) is None
    two = bench.steady_rates(beats[:3])  # only two beats past the start: the last pair
    assert (two["from_s"], two["to_s"]) == (10.0, 20.0)
