"""Shard writes off the simulation thread: one background thread runs the submitted calls
(``ShardWriter.write_frame``, ``record_dropped``, ``close``) one after another, in the order
they were submitted.

Why a thread: compressing, checksumming and fsync'ing a shard (HDF5, ~40 ms per shard plus
~1 ms per frame for the t-shirt) otherwise stalls the loop that feeds the GPU. While that loop
waits for the device (Warp's native calls release the GIL) the writer thread does this work.

Every shard is written by the one thread in submission order, so its bytes are those a direct
write gives; a crash or kill leaves at most temporary files, as before (``ShardWriter`` writes
to a temporary name and renames when complete).
"""
from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

#: Calls queued at most before ``submit`` waits (bounds the frames held in memory: a 7.7k-vertex
#: frame with its displacements is ~0.2 MB).
MAX_PENDING = 256


class BackgroundWriter:
    """Runs submitted calls on one background thread, first in, first out.

    The return values of calls queued with :meth:`submit_collect` are collected for
    :meth:`completed` (e.g. the record that ``ShardWriter.close`` returns). The first exception a call raises stops the thread from
    running later calls; :meth:`submit`, :meth:`completed` and :meth:`close` raise it in the
    caller's thread.
    """

    def __init__(self, *, name: str = "shard-writer", max_pending: int = MAX_PENDING) -> None:
        self._calls: queue.Queue = queue.Queue(maxsize=max_pending)
        self._results: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._closed = False
        self.busy_s = 0.0
        """Wall seconds the thread spent running calls (the shard work taken off the caller's loop).
        At full width on the H200 (12-22 s per run) it did not slow the loop: skipping the frames'
        HDF5 writes left the loop's time unchanged."""
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._calls.get()
            if item is None:
                return
            if self._error is not None:
                continue  # after a failure nothing more is written; the caller gets the error
            fn, args, kwargs, collect = item
            t0 = time.perf_counter()
            try:
                result = fn(*args, **kwargs)
            except BaseException as error:  # handed to the caller's thread
                self._error = error
                continue
            finally:
                self.busy_s += time.perf_counter() - t0
            if collect:
                self._results.put(result)

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def _put(self, fn: Callable[..., Any], args: tuple, kwargs: dict, collect: bool) -> None:
        if self._closed:
            raise ValueError("BackgroundWriter is closed; it takes no more calls")
        self._raise()
        self._calls.put((fn, args, kwargs, collect))

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Queues ``fn(*args, **kwargs)``, its return value dropped (waits while ``max_pending``
        calls are queued)."""
        self._put(fn, args, kwargs, False)

    def submit_collect(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Queues ``fn(*args, **kwargs)``; its return value comes back from :meth:`completed`."""
        self._put(fn, args, kwargs, True)

    def completed(self) -> list:
        """Return values collected since the last call (calls still queued are not waited for)."""
        out = []
        while True:
            try:
                out.append(self._results.get_nowait())
            except queue.Empty:
                break
        self._raise()
        return out

    def close(self, *, raise_error: bool = True) -> list:
        """Waits for every queued call; returns the values not yet collected. With
        ``raise_error`` False (cleaning up after another error) a call's failure is not raised."""
        if not self._closed:
            self._closed = True
            self._calls.put(None)
        self._thread.join()
        if raise_error:
            return self.completed()
        out = []
        while not self._results.empty():
            out.append(self._results.get_nowait())
        return out
