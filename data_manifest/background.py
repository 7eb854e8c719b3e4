"""Shard writes off the simulation thread: one background worker runs the submitted calls
(``ShardWriter.write_frame``, ``record_dropped``, ``close``) one after another, in the order
they were submitted.

Why: compressing, checksumming and fsync'ing a shard (HDF5, ~40 ms per shard plus ~1 ms per
frame for the t-shirt) otherwise stalls the loop that feeds the GPU.

Two kinds of worker, one behaviour:

- ``mode="thread"``: a thread of this process. Cheap to start; right when the loop is compute
  bound (the CPU runs). But h5py holds the GIL while it compresses and writes, and the GPU frame
  loop releases and takes the GIL back at every torch op and Warp launch: each time it found the
  writer holding it, it waited up to Python's switch interval (5 ms).
- ``mode="process"``: a process of its own (spawned), which owns the shard writers: the objects
  are made there (:meth:`BackgroundWriter.create`) and called there by key (:meth:`call`); the
  arguments travel pickled. The simulation process then never waits for the writer's GIL.

``WriterLanes`` runs several such workers, each shard's calls on one of them (its lane).
Every shard is written by one worker in submission order, so its bytes are those a direct
write gives; a crash or kill leaves at most temporary files, as before (``ShardWriter`` writes
to a temporary name and renames when complete).
"""
from __future__ import annotations

import multiprocessing
import os
import queue
import threading
import time
import traceback
from typing import Any, Callable, Hashable

#: Calls queued at most before ``submit`` waits (bounds the frames held in memory: a 7.7k-vertex
#: frame with its displacements is ~0.2 MB).
MAX_PENDING = 256
#: Shard-writing workers of one batch at most (``WriterLanes``).
MAX_LANES = 4
MODES = ("thread", "process")
#: Environment variable that overrides the caller's choice of worker ("thread" or "process").
MODE_ENV = "DRAPE_SHARD_WRITER"

_CREATE, _CALL = "create", "call"


def resolve_mode(default: str) -> str:
    """The worker kind: ``$DRAPE_SHARD_WRITER`` when set, else ``default``; raises naming the value."""
    mode = os.environ.get(MODE_ENV, "").strip() or default
    if mode not in MODES:
        source = f"${MODE_ENV}" if os.environ.get(MODE_ENV, "").strip() else "mode"
        raise ValueError(f"{source} must be one of {MODES} (got {mode!r})")
    return mode


def _serve(calls, results, caller_alive: Callable[[], bool] | None = None) -> None:
    """The worker's loop (thread or process): runs the calls in order. ``calls`` items are
    (op, key, fn, args, kwargs, collect), or ("stop", cleanup): ``cleanup(obj)`` (when not None)
    runs on every object still held, see ``close``. ``results`` gets ("value", v) for collected
    calls, ("error", exception, traceback) once, and ("busy", seconds) at the end. A worker
    process whose caller died (``caller_alive``) runs nothing more: it cleans up and ends, as the
    thread would have died with its process."""
    objects: dict[Hashable, Any] = {}
    failed = False
    busy = 0.0
    while True:
        try:
            # a worker process looks up every second whether its caller still lives (the queue
            # does not tell: this end holds the pipe's write end too)
            item = calls.get() if caller_alive is None else calls.get(timeout=1.0)
        except queue.Empty:
            item = None
        except (EOFError, OSError):  # the caller's end of the queue is gone
            item = ("stop", _abort_quietly)
        if caller_alive is not None and not caller_alive():
            item = ("stop", _abort_quietly)
        if item is None:
            continue
        if item[0] == "stop":
            cleanup = item[1]
            if cleanup is not None:  # e.g. ShardWriter.abort: leave no temporary file behind
                for obj in objects.values():
                    try:
                        cleanup(obj)
                    except Exception:
                        pass
            try:
                results.put(("busy", busy))
            except (EOFError, OSError, ValueError):
                pass
            return
        if failed:
            continue  # after a failure nothing more is written; the caller gets the error
        op, key, fn, args, kwargs, collect = item
        t0 = time.perf_counter()
        try:
            if op == _CREATE:
                objects[key] = result = fn(*args, **kwargs)
            elif key is None:
                result = fn(*args, **kwargs)
            else:
                result = fn(objects[key], *args, **kwargs)
        except BaseException as error:  # handed to the caller
            failed = True
            results.put(("error", error, traceback.format_exc()))
            continue
        finally:
            busy += time.perf_counter() - t0
        if collect:
            results.put(("value", result))


def _abort_quietly(obj: Any) -> None:
    """Cleanup of the objects of a worker whose caller died: ``obj.abort()`` where it has one."""
    abort = getattr(obj, "abort", None)
    if callable(abort):
        abort()


def _serve_process(calls, results) -> None:
    """Process entry: errors that cannot be pickled come back as RuntimeError with their text.
    Ctrl-C reaches the whole process group; the worker leaves it to its caller, which then stops
    it with a cleanup (or dies, which the worker notices)."""
    import pickle
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)

    class _Results:
        def put(self, item):
            if item[0] == "error":
                try:
                    pickle.dumps(item[1])
                except Exception:
                    item = ("error", RuntimeError(f"{type(item[1]).__name__}: {item[1]}"), item[2])
            results.put(item)

    parent = multiprocessing.parent_process()
    _serve(calls, _Results(), caller_alive=None if parent is None else parent.is_alive)


class BackgroundWriter:
    """Runs submitted calls on one background worker, first in, first out.

    Plain calls: :meth:`submit` / :meth:`submit_collect` (``fn`` must be picklable in process
    mode: a module-level function or a method of a module-level class). Objects that live on the
    worker (shard writers in process mode): :meth:`create` makes one under a key, :meth:`call` /
    :meth:`call_collect` run ``fn(object, ...)`` on it. The return
    values of collected calls come back from :meth:`completed`. The first exception a call raises
    stops the worker from running later calls; :meth:`submit`, :meth:`completed` and
    :meth:`close` raise it in the caller's thread (in process mode with the worker's traceback
    as a note).
    """

    def __init__(self, *, name: str = "shard-writer", max_pending: int = MAX_PENDING, mode: str = "thread") -> None:
        self.mode = resolve_mode(mode)
        self._error: BaseException | None = None
        self._closed = False
        self._values: list = []
        self._busy_s = 0.0
        self._busy_final = False
        if self.mode == "thread":
            self._calls: Any = queue.Queue(maxsize=max_pending)
            self._results: Any = queue.SimpleQueue()
            self._worker: Any = threading.Thread(target=_serve, args=(self._calls, self._results), name=name, daemon=True)
        else:
            ctx = multiprocessing.get_context("spawn")  # no fork of a process that holds CUDA and threads
            self._calls = ctx.Queue(maxsize=max_pending)
            self._results = ctx.Queue()
            self._worker = ctx.Process(target=_serve_process, args=(self._calls, self._results), name=name, daemon=True)
        self._worker.start()

    @property
    def busy_s(self) -> float:
        """Wall seconds the worker spent running calls (the shard work taken off the caller's
        loop); in process mode known once :meth:`close` returns."""
        return self._busy_s

    # -- the caller's side ----------------------------------------------------------------

    def _drain(self, block: bool = False) -> None:
        """Moves what the worker sent back into ``_values`` / ``_error`` / ``busy_s``."""
        while not self._busy_final:  # after "busy" nothing more comes
            try:
                item = self._results.get(timeout=1.0) if block else self._results.get_nowait()
            except queue.Empty:
                if block and self._worker.is_alive():
                    continue
                return
            if item[0] == "value":
                self._values.append(item[1])
            elif item[0] == "error":
                if self._error is None:
                    self._error = item[1]
                    if self.mode == "process" and hasattr(item[1], "add_note"):
                        item[1].add_note(f"in the shard-writer process:\n{item[2]}")
            else:  # ("busy", seconds): the worker's last message
                self._busy_s, self._busy_final = float(item[1]), True

    def _raise(self) -> None:
        if self._error is None and not self._worker.is_alive() and not self._closed:
            self._error = RuntimeError(f"the shard-writer {self.mode} ended unexpectedly "
                                       f"(exit code {getattr(self._worker, 'exitcode', None)})")
        if self._error is not None:
            raise self._error

    def _put(self, item: tuple) -> None:
        if self._closed:
            raise ValueError("BackgroundWriter is closed; it takes no more calls")
        self._drain()
        self._raise()
        while True:
            try:
                self._calls.put(item, timeout=1.0)
                return
            except queue.Full:  # the worker is behind: wait, unless it died
                self._drain()
                self._raise()

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Queues ``fn(*args, **kwargs)``, its return value dropped (waits while ``max_pending``
        calls are queued)."""
        self._put((_CALL, None, fn, args, kwargs, False))

    def submit_collect(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Queues ``fn(*args, **kwargs)``; its return value comes back from :meth:`completed`."""
        self._put((_CALL, None, fn, args, kwargs, True))

    def create(self, key: Hashable, factory: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Makes ``factory(*args, **kwargs)`` on the worker and keeps it under ``key``."""
        self._put((_CREATE, key, factory, args, kwargs, False))

    def call(self, key: Hashable, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Queues ``fn(obj, *args, **kwargs)`` on the object kept under ``key``, result dropped."""
        self._put((_CALL, key, fn, args, kwargs, False))

    def call_collect(self, key: Hashable, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Queues ``fn(obj, *args, **kwargs)`` on the object under ``key``; its return value comes
        back from :meth:`completed`."""
        self._put((_CALL, key, fn, args, kwargs, True))

    def completed(self) -> list:
        """Return values collected since the last call (calls still queued are not waited for)."""
        self._drain()
        out, self._values = self._values, []
        self._raise()
        return out

    def close(self, *, raise_error: bool = True, cleanup: Callable[[Any], Any] | None = None) -> list:
        """Waits for every queued call; returns the values not yet collected. ``cleanup(obj)`` runs
        on every object still kept (after a failure too), e.g. ``ShardWriter.abort``. With
        ``raise_error`` False (cleaning up after another error) a call's failure is not raised."""
        if not self._closed:
            self._closed = True
            if self._worker.is_alive():
                while True:
                    try:
                        self._calls.put(("stop", cleanup), timeout=1.0)
                        break
                    except queue.Full:
                        if not self._worker.is_alive():
                            break
                self._drain(block=True)
            self._worker.join()
            if self.mode == "process":
                self._calls.close()
                self._results.close()
            if not self._busy_final and self._error is None:
                self._error = RuntimeError(f"the shard-writer {self.mode} ended before it finished its calls "
                                           f"(exit code {getattr(self._worker, 'exitcode', None)})")
        out, self._values = self._values, []
        if raise_error and self._error is not None:
            raise self._error
        return out


def lane_count(mode: str, cpus: int | None = None) -> int:
    """Workers for a batch's shards: in process mode one per two CPUs beyond the caller's two, at
    most ``MAX_LANES``; in thread mode one (h5py holds the GIL while it writes, so more threads
    would only take turns)."""
    cpus = (os.cpu_count() or 1) if cpus is None else int(cpus)
    return 1 if mode == "thread" else max(1, min(MAX_LANES, (cpus - 2) // 2))


class WriterLanes:
    """Several :class:`BackgroundWriter` workers side by side, the calls about one lane (a shard)
    always on the same one, in submission order; so every shard's bytes are those one worker
    gives. One worker wrote a cloth3d batch's 30,000 frames at ~1-2 ms each (HDF5 chunks,
    compression, two fsyncs per shard), which the frame loop then waited for.

    ``create`` makes the object on every worker; ``lane(k)`` is the worker of lane ``k`` (an
    integer); ``completed`` and ``close`` gather all workers' values (lane by lane)."""

    def __init__(self, lanes: int, *, mode: str = "thread", **options: Any) -> None:
        if int(lanes) != lanes or lanes < 1:
            raise ValueError(f"lanes must be an integer >= 1 (got {lanes!r})")
        self.writers: list[BackgroundWriter] = []
        try:
            for k in range(int(lanes)):
                self.writers.append(BackgroundWriter(mode=mode, **options))
        except BaseException:
            for writer in self.writers:
                writer.close(raise_error=False)
            raise
        self.mode = self.writers[0].mode

    def __len__(self) -> int:
        return len(self.writers)

    @property
    def busy_s(self) -> float:
        """Wall seconds the workers spent running calls, summed (see ``BackgroundWriter.busy_s``)."""
        return sum(writer.busy_s for writer in self.writers)

    def lane(self, k: int) -> BackgroundWriter:
        """The worker of lane ``k``."""
        return self.writers[int(k) % len(self.writers)]

    def create(self, key: Hashable, factory: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """``BackgroundWriter.create`` on every worker."""
        for writer in self.writers:
            writer.create(key, factory, *args, **kwargs)

    def completed(self) -> list:
        """Return values collected since the last call, from every worker."""
        return [value for writer in self.writers for value in writer.completed()]

    def close(self, *, raise_error: bool = True, cleanup: Callable[[Any], Any] | None = None) -> list:
        """``BackgroundWriter.close`` on every worker (all of them, whichever fails); raises the
        first failure when ``raise_error``."""
        out, error = [], None
        for writer in self.writers:
            try:
                out.extend(writer.close(raise_error=raise_error, cleanup=cleanup))
            except BaseException as caught:  # the other workers still finish and clean up
                error = error or caught
        if error is not None:
            raise error
        return out
