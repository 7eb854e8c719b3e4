"""bench/bench_hf_epoch.py on the CPU: one JSON line with a row per prototype count, epochs timed
from the stage's own log, and a linear fit whose slope is the cost of one more prototype."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bench_hf_epoch_prints_rows_and_a_fit() -> None:
    out = subprocess.run([sys.executable, "bench/bench_hf_epoch.py", "--prototypes", "1,3", "--frames-per-prototype",
                          "40", "--vertices", "100", "--epochs", "2"], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert [r["prototypes"] for r in result["rows"]] == [1, 3]
    assert all(r["steps_per_epoch"] == 2 and r["epoch_s"] > 0 for r in result["rows"])
    assert result["rows"][1]["epoch_s"] > result["rows"][0]["epoch_s"], "three prototypes took no longer than one"
    assert result["linear_fit"]["epoch_s_per_prototype"] > 0
    assert result["gpu"] is None and result["rows"][0]["gpu_kernel_ms_per_epoch"] is None


def test_bench_hf_epoch_rejects_bad_counts() -> None:
    out = subprocess.run([sys.executable, "bench/bench_hf_epoch.py", "--prototypes", "0,2"], cwd=ROOT,
                         capture_output=True, text=True)
    assert out.returncode == 2 and "--prototypes" in out.stderr and "Traceback" not in out.stderr
