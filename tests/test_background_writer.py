"""data_manifest.background: shard writes on a worker of their own (thread or process), in order,
errors surfaced, temporary files removed when the caller fails or dies."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from data_manifest.background import MODE_ENV, BackgroundWriter, resolve_mode

MODES = ["thread", "process"]


class Recorder:
    """An object that lives on the worker (module level, so a worker process can make it)."""

    def __init__(self, marker: str | None = None) -> None:
        self.seen: list[int] = []
        self.where = (os.getpid(), threading.get_ident())
        self.marker = marker

    def add(self, i: int) -> int:
        self.seen.append(i)
        return i * 10

    def report(self) -> tuple:
        return self.seen, self.where

    def fail(self) -> None:
        raise OSError("disk full")

    def abort(self) -> None:
        if self.marker:
            Path(self.marker).write_text("aborted")


@pytest.mark.parametrize("mode", MODES)
def test_calls_run_in_submission_order_on_one_worker_and_collected_values_come_back(mode):
    writer = BackgroundWriter(max_pending=4, mode=mode)  # fewer slots than calls: submit waits, order holds
    writer.create("r", Recorder)
    for i in range(50):
        (writer.call_collect if i % 7 == 0 else writer.call)("r", Recorder.add, i)
    writer.submit_collect(sum, [1, 2, 3])  # a plain call, no object
    writer.call_collect("r", Recorder.report)
    *values, total, (seen, (pid, thread)) = writer.close()
    assert seen == list(range(50))
    assert values == [i * 10 for i in range(50) if i % 7 == 0], "only the collected values, in order"
    assert total == 6
    if mode == "process":
        assert pid != os.getpid()
    else:
        assert pid == os.getpid() and thread != threading.get_ident()
    assert writer.busy_s >= 0.0
    with pytest.raises(ValueError, match="closed"):
        writer.submit(sum, [1])


@pytest.mark.parametrize("mode", MODES)
def test_a_failed_call_stops_later_calls_is_raised_in_the_callers_thread_and_cleanup_still_runs(mode, tmp_path):
    marker = tmp_path / "aborted"
    writer = BackgroundWriter(mode=mode)
    writer.create("r", Recorder, str(marker))
    writer.call("r", Recorder.add, 1)
    writer.call("r", Recorder.fail)
    writer.call_collect("r", Recorder.add, 2)  # may be queued before the failure is known: never run
    with pytest.raises(OSError, match="disk full"):
        writer.close(cleanup=Recorder.abort)
    assert marker.read_text() == "aborted", "the objects still held are cleaned up after a failure"
    with pytest.raises(OSError, match="disk full"):
        writer.completed()
    # cleaning up after another error: close does not raise again
    quiet = BackgroundWriter(mode=mode)
    quiet.create("r", Recorder)
    quiet.call("r", Recorder.fail)
    assert quiet.close(raise_error=False) == []


@pytest.mark.parametrize("mode", MODES)
def test_busy_seconds_count_the_time_spent_in_calls(mode):
    writer = BackgroundWriter(mode=mode)
    for _ in range(3):
        writer.submit(time.sleep, 0.02)
    writer.close()
    assert 0.06 <= writer.busy_s < 5.0, writer.busy_s


def test_a_worker_process_whose_caller_is_killed_cleans_up_and_ends(tmp_path):
    marker = tmp_path / "aborted"
    script = textwrap.dedent(f"""
        import os, signal, sys, time
        sys.path[:0] = {[str(Path(__file__).parent), str(Path(__file__).parents[1])]!r}
        from data_manifest.background import BackgroundWriter
        from test_background_writer import Recorder
        if __name__ == "__main__":
            writer = BackgroundWriter(mode="process")
            writer.create("r", Recorder, {str(marker)!r})
            writer.submit_collect(sum, [1])
            while not writer._values:  # the worker is up and has made the object
                writer._drain()
                time.sleep(0.01)
            print(writer._worker.pid, flush=True)
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    worker = int(proc.stdout.split()[0])
    deadline = time.time() + 30
    while time.time() < deadline and not marker.exists():
        time.sleep(0.05)
    assert marker.read_text() == "aborted", "the orphaned worker must abort what it held (temporary shards)"
    while time.time() < deadline:
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        pytest.fail(f"the orphaned worker {worker} is still running")


def test_mode_comes_from_the_environment_when_set_and_bad_values_are_named(monkeypatch):
    monkeypatch.delenv(MODE_ENV, raising=False)
    assert resolve_mode("process") == "process"
    monkeypatch.setenv(MODE_ENV, "thread")
    assert resolve_mode("process") == "thread"
    monkeypatch.setenv(MODE_ENV, "fork")
    with pytest.raises(ValueError, match=r"DRAPE_SHARD_WRITER.*'fork'"):
        resolve_mode("thread")
    monkeypatch.delenv(MODE_ENV)
    with pytest.raises(ValueError, match=r"mode.*'greenlet'"):
        BackgroundWriter(mode="greenlet")
