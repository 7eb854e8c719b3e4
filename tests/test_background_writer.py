"""data_manifest.background: shard writes on a thread of their own, in order, errors surfaced."""
from __future__ import annotations

import threading

import pytest

from data_manifest.background import BackgroundWriter


def test_calls_run_in_submission_order_on_one_other_thread_and_collected_values_come_back():
    writer = BackgroundWriter(max_pending=4)  # fewer slots than calls: submit waits, order holds
    seen, threads = [], set()

    def step(i):
        seen.append(i)
        threads.add(threading.get_ident())
        return i * 10

    for i in range(50):
        (writer.submit_collect if i % 7 == 0 else writer.submit)(step, i)
    rest = writer.close()
    assert seen == list(range(50))
    assert threads and threading.get_ident() not in threads and len(threads) == 1
    assert rest == [i * 10 for i in range(50) if i % 7 == 0], "only submit_collect's values, in order"
    with pytest.raises(ValueError, match="closed"):
        writer.submit(step, 99)


def test_a_failed_call_stops_later_calls_and_is_raised_in_the_callers_thread():
    writer = BackgroundWriter()
    seen = []

    def fail():
        raise OSError("disk full")

    writer.submit(seen.append, 1)
    writer.submit(fail)
    writer.submit(seen.append, 2)  # may be queued before the failure is known: never run
    with pytest.raises(OSError, match="disk full"):
        writer.close()
    assert seen == [1]
    with pytest.raises(OSError, match="disk full"):
        writer.completed()
    # cleaning up after another error: close does not raise again
    quiet = BackgroundWriter()
    quiet.submit(fail)
    assert quiet.close(raise_error=False) == []


def test_busy_seconds_count_the_time_spent_in_calls():
    import time

    writer = BackgroundWriter()
    for _ in range(3):
        writer.submit(time.sleep, 0.02)
    writer.close()
    assert 0.06 <= writer.busy_s < 5.0, writer.busy_s
