"""bench/bench_self_contact.py: with ``--to-rest`` a hold ends at rest and reports its length."""
from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path


def test_to_rest_ends_the_hold_at_rest_and_reports_its_frames(monkeypatch, capsys):
    """The arms-lowered scene at 600 vertices, shoulders turned 0.3 rad in one step: held for
    at least ``--hold-frames`` frames without ``--to-rest``; with it, the hold ends converged, in
    fewer frames."""
    monkeypatch.syspath_prepend(str(Path(__file__).parents[1] / "bench"))  # a dataclass module: imported, not loaded
    bench = importlib.import_module("bench_self_contact")
    frames = {}
    for extra in ([], ["--to-rest"]):
        monkeypatch.setattr(sys, "argv", ["bench_self_contact.py", "--resolution", "600", "--runs", "xpbd", "--angle",
                                          "0.3", "--step", "0.3", "--hold-frames", "40", *extra])
        bench.main()
        record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        frames[bool(extra)] = (record["hold_frames"], record["status"])
    assert frames[False][0] >= 40, frames  # held at least --hold-frames
    assert frames[True][1] == 1 and 2 <= frames[True][0] < 40, frames  # WorldStatus.CONVERGED
