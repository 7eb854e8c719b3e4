"""bench/bench_dataset.py's steady rates: over the second half of the run, not from its start."""
from __future__ import annotations


def test_steady_rates_skip_the_start_up_burst(load_bench):
    bench = load_bench("bench_dataset")
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


def test_kernel_table_gives_device_time_per_frame(load_bench):
    bench = load_bench("bench_dataset")
    rows = [{"name": "sweep", "count": 100, "total_ms": 300.0}, {"name": "query", "count": 20, "total_ms": 30.0},
            {"name": "filters", "count": 40, "total_ms": 70.0}]
    table = bench.kernel_table(rows, frames=10, seconds=0.5)
    assert table["busy_ms_per_frame"] == 40.0 and table["busy_fraction"] == 0.8
    assert [k["name"] for k in table["kernels"]] == ["sweep", "filters", "query"]
    assert table["kernels"][0] == {"name": "sweep", "ms_per_frame": 30.0, "launches_per_frame": 10.0, "share": 0.75}
    assert len(bench.kernel_table(rows, frames=10, seconds=0.5, top=1)["kernels"]) == 1


def test_device_profiler_records_its_window_only(tmp_path, load_bench):
    import json

    import torch

    bench = load_bench("bench_dataset")
    path = tmp_path / "profile.json"
    prof = bench.DeviceProfiler(str(path), start_s=10.0, window_s=5.0, cuda=False)
    prof.on_beat({"elapsed_s": 0.0, "frames": 0})  # before the window: nothing recorded
    torch.ones(4, 4) @ torch.ones(4, 4)
    prof.on_beat({"elapsed_s": 10.0, "frames": 40})  # starts
    a = torch.ones(64, 64)
    for _ in range(3):
        a = a @ a / 64.0
    prof.on_beat({"elapsed_s": 12.0, "frames": 50})  # still inside the window
    assert not path.exists()
    prof.on_beat({"elapsed_s": 15.0, "frames": 60})  # stops and writes
    table = json.loads(path.read_text())
    assert table["frames"] == 20 and table["seconds"] == 5.0 and table["device"] == "cpu"
    mm = [k for k in table["kernels"] if k["name"] == "aten::mm"]
    assert mm and mm[0]["launches_per_frame"] == 3 / 20, "the window's three products, not the one before it"
    prof.finish({"elapsed_s": 20.0, "frames": 80})  # written once
    assert json.loads(path.read_text())["frames"] == 20
    try:
        bench.DeviceProfiler(str(path), start_s=0.0, window_s=0.0, cuda=False)
    except ValueError as e:
        assert "window_s" in str(e)
    else:
        raise AssertionError("a zero-length window was accepted")
