"""TailorNet-scale dataset throughput: runs a slice of a spec (fewer poses per pair)
through generate-dataset on one device and projects the wall time of the full spec.

    python bench/bench_dataset.py --spec tailornet-tshirt --poses 40 --out /tmp/bench_ds [--device cuda:0]

Prints one JSON line: kept and dropped frames by reason, target frames per second,
phase timings, the projected time for the full spec's target frames at the slice's rate
(``projected_full_s``), the busy world-frames per target and the cost of one world-frame
(``world_frames_per_target``, ``ms_per_world_frame``) with the stepping time they imply for a
full spec whose worlds stay busy (``projected_packed_stepping_s``), the issue's target measure
(``kept_frames_per_s`` and ``projected_target_kept_s``: the time to keep TailorNet's 55,800
frames at the slice's rates, against ``target_s`` = 600), plus the audit's error distribution,
and ``steady``: target poses, world-frames and simulator frames per second over the second half
of the simulation (from the heartbeats; compare runs by these, not by rates from the start).
On CUDA the frame loop delivers one frame's targets while the next steps, so ``sim_s`` and
``ms_per_world_frame`` count only the stepping the host still waited for, not all of it.

    bash bench/device_suite.sh dataset-full OUT   # the whole spec in 30-pose tasks, cut by T seconds
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import signal
import sys
import time
from pathlib import Path

import yaml


def override_library_settings(items: list[str]) -> None:
    """Every run of this process builds its settings with ``items`` (KEY=VALUE) set: library
    fields of ``SimSettings`` or ``SequenceSettings`` that a spec does not expose, for
    side-by-side runs (local executor only)."""
    import dataclasses

    import pipelines.generate_dataset as gd
    from simulate.quasi_static import SimSettings
    from simulate.sequence import SequenceSettings

    sim_fields = {f.name for f in dataclasses.fields(SimSettings)}
    seq_fields = {f.name for f in dataclasses.fields(SequenceSettings)} - {"sim"}
    sim_values, seq_values = {}, {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in sim_fields | seq_fields or not value:
            raise SystemExit(f"--library {item!r}: expected KEY=VALUE with KEY one of {sorted(sim_fields | seq_fields)}")
        (sim_values if key in sim_fields else seq_values)[key] = yaml.safe_load(value)
    base = gd.sequence_settings

    def sequence_settings(spec: dict):
        settings = base(spec)
        return dataclasses.replace(settings, sim=dataclasses.replace(settings.sim, **sim_values), **seq_values)

    gd.sequence_settings = sequence_settings


def override_run_options(spec: dict, args: argparse.Namespace) -> None:
    """``--worlds``, ``--resolution`` and ``--device`` into ``spec`` where given (the dataset
    benches' shared options)."""
    for option, section, key in (("worlds", "simulation", "worlds"), ("resolution", "garment", "resolution"),
                                 ("device", "simulation", "device")):
        if getattr(args, option) is not None:
            spec[section][key] = getattr(args, option)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spec", default="tailornet-tshirt")
    parser.add_argument("--poses", type=int, default=40, help="train poses per train pair in the slice")
    parser.add_argument("--test-poses", type=int, default=10)
    parser.add_argument("--pairs", type=int, default=None, help="train pairs (default: the spec's)")
    parser.add_argument("--test-pairs", type=int, default=None, help="test pairs (default: the spec's)")
    parser.add_argument("--worlds", type=int, default=None)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--device", default=None)
    parser.add_argument("--tolerance", type=float, default=None, help="override simulation.tolerance [m/s]")
    parser.add_argument("--range-scale", type=float, default=None, help="override poses.range_scale")
    parser.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                        help="override any simulation.KEY (repeatable, dots for nested keys), e.g. --sim tolerance=0.02 "
                             "--sim contact.self_contact=true")
    parser.add_argument("--library", action="append", default=[], metavar="KEY=VALUE",
                        help="set a library SimSettings or SequenceSettings field the spec does not expose (repeatable), e.g. "
                             "--library self_contact_bounds=true")
    parser.add_argument("--filter", action="append", default=[], metavar="KEY=VALUE",
                        help="override any filters.KEY (repeatable), e.g. --filter max_self_intersections=50")
    parser.add_argument("--out", default="/tmp/bench_dataset")
    parser.add_argument("--keep", action="store_true", help="keep the output directory")
    parser.add_argument("--heartbeat", type=float, default=20.0, help="seconds between progress lines on stderr")
    parser.add_argument("--stub-frame-writes", action="store_true",
                        help="diagnostic: kept frames' vertex arrays are checked but not written to HDF5 (shards hold "
                             "zeros there); what the shard writes cost the simulation loop")
    parser.add_argument("--switch-interval", type=float, default=None,
                        help="diagnostic: sys.setswitchinterval [s] for the run (Python's default 0.005)")
    parser.add_argument("--sample-stacks", default=None, metavar="JSON",
                        help="diagnostic: sample the main thread's Python stack every --sample-interval seconds and "
                             "write where the wall time went (inclusive and leaf counts per function) to this file")
    parser.add_argument("--sample-interval", type=float, default=0.002,
                        help="seconds between stack samples; Python's thread switch interval is lowered to a quarter "
                             "of it so the sampler gets the GIL in time (at 0.002 s that slowed a full-spec run from 90 "
                             "to 70 target poses/s on an H100; 0.02 leaves Python's default 0.005 s)")
    parser.add_argument("--device-profile", default=None, metavar="JSON",
                        help="diagnostic: record the device's kernels (torch.profiler: torch's and Warp's alike, on "
                             "CUDA; on the CPU only torch's operators, not Warp's kernels) over "
                             "--device-profile-window and write the time per simulator frame by kernel to this file")
    parser.add_argument("--device-profile-window", default="60:20", metavar="START:SECONDS",
                        help="from the first heartbeat at or after START seconds of simulation to the first one "
                             "SECONDS later (or the end of the run)")
    parser.add_argument("--writer", choices=("thread", "process"), default=None,
                        help="the shard writer's worker (default: a process on CUDA, a thread on the CPU; sets "
                             "$DRAPE_SHARD_WRITER, see data_manifest.background)")
    args = parser.parse_args()
    if args.writer is not None:
        os.environ["DRAPE_SHARD_WRITER"] = args.writer
    if args.sample_interval <= 0:
        raise SystemExit(f"--sample-interval must be > 0 s (got {args.sample_interval})")
    sampler = StackSampler(args.sample_stacks, args.sample_interval) if args.sample_stacks else None
    profiler = None
    if args.device_profile:
        start_s, _, window_s = args.device_profile_window.partition(":")
        try:
            profiler = DeviceProfiler(args.device_profile, float(start_s), float(window_s),
                                      cuda=str(args.device or "").startswith("cuda"))
        except ValueError:
            raise SystemExit(f"--device-profile-window: expected START:SECONDS with START >= 0 and SECONDS > 0 "
                             f"(got {args.device_profile_window!r})") from None
    if sampler is not None:
        sampler.start()
    if args.stub_frame_writes:
        if args.writer != "thread":
            raise SystemExit("--stub-frame-writes patches the shard writer in this process: use it with --writer thread")
        stub_frame_writes()
    if args.switch_interval is not None:
        sys.setswitchinterval(args.switch_interval)

    from pipelines.generate_dataset import generate
    from pipelines.spec import OPTIONAL_KEYS, load_spec

    full = load_spec(args.spec)
    full_targets = 0
    n_train, n_test = full["pairs"]["train"], full["pairs"]["test"]
    sizes = {"train_train": full["poses"]["train_count"], "train_test": full["poses"]["test_count"]}
    for split, (group, pose_set) in {"train_train": ("train", "train"), "train_test": ("train", "test"),
                                     "test_train": ("test", "train"), "test_test": ("test", "test")}.items():
        count = full["splits"][split]
        count = sizes.get(split, 0) if count == "all" else count
        full_targets += (n_train if group == "train" else n_test) * int(count)
    spec = copy.deepcopy(full)
    spec["name"] = f"{full['name']}-bench"
    spec["poses"]["train_count"] = args.poses
    spec["poses"]["test_count"] = args.test_poses
    spec["splits"] = {"train_train": "all", "train_test": "all", "test_train": min(args.poses, full["splits"]["test_train"]),
                      "test_test": min(args.test_poses, full["splits"]["test_test"])}
    if args.pairs is not None:
        spec["pairs"]["train"] = args.pairs
    if args.test_pairs is not None:
        spec["pairs"]["test"] = args.test_pairs
    override_run_options(spec, args)
    if args.tolerance is not None:
        spec["simulation"]["tolerance"] = args.tolerance
    for flag, section, items in (("--sim", "simulation", args.sim), ("--filter", "filters", args.filter)):
        for item in items:
            dotted, _, value = item.partition("=")
            *parents, key = dotted.split(".")  # nested fields by dots: contact.self_contact=true
            table = spec[section]
            for name in parents:
                table = table.get(name) if isinstance(table, dict) else None
            optional = OPTIONAL_KEYS.get(section, ()) if not parents else ()
            if not isinstance(table, dict) or (key not in table and key not in optional) or not value:
                known = sorted(set(table) | set(optional)) if isinstance(table, dict) else sorted(spec[section])
                raise SystemExit(f"{flag} {item!r}: expected KEY=VALUE with KEY one of {known}")
            if key not in table:  # an optional key (simulation.targets_from_home): YAML's value
                table[key] = yaml.safe_load(value)
                continue
            old = table[key]
            if isinstance(old, bool):
                table[key] = value.lower() in ("1", "true", "yes")
            elif old is None:  # optional fields (poses_per_task, a rest exclusion): a number, or null
                table[key] = None if value.lower() in ("none", "null") else yaml.safe_load(value)
            else:
                table[key] = type(old)(value)
    if args.range_scale is not None:
        spec["poses"]["range_scale"] = args.range_scale
    if args.library:
        override_library_settings(args.library)
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()

    def log(message: str) -> None:  # to stderr, so stdout stays one JSON line
        print(f"[{time.perf_counter() - t0:7.1f} s] {message}", file=sys.stderr, flush=True)

    last: dict = {}
    beats: list[dict] = []  # every heartbeat, for the steady rates over the run's second half

    def on_heartbeat(beat: dict) -> None:
        last.update(beat)
        beats.append(dict(beat))
        if profiler is not None:
            profiler.on_beat(beat)
    # `timeout` sends SIGTERM: stop like Ctrl-C and still print what was measured (one JSON line,
    # "complete": false, from the last heartbeat), so a device slot that ends mid-run is not lost
    def report_partial() -> None:
        print(json.dumps({**partial_result(args, spec, last, full_targets, time.perf_counter() - t0),
                          "steady": steady_rates(beats)}), flush=True)
        if sampler is not None:  # os._exit below skips atexit
            sampler.write()
        if profiler is not None:
            profiler.finish(last)
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)

    def stop_on_sigterm(signum, frame) -> None:
        # print and leave from the handler itself: an exception raised here can land in a
        # __del__ (Warp arrays are freed all the time) and be swallowed there
        report_partial()
        os._exit(143)

    signal.signal(signal.SIGTERM, stop_on_sigterm)
    try:
        manifest = generate(spec, out, progress=False, log=log, heartbeat_s=args.heartbeat, on_heartbeat=on_heartbeat)
    except KeyboardInterrupt:
        report_partial()
        raise SystemExit(130)
    wall = time.perf_counter() - t0
    if profiler is not None:
        profiler.finish(last)
    sim = manifest.audit.get("simulation", {})
    targets = int(sim.get("target_frames", 0))
    phases = sim.get("phases", {}) or {}
    worlds = int(spec["simulation"]["worlds"])
    tasks = len(list((out / "shards").glob("*.h5")))
    fps = targets / max(sim.get("seconds", wall), 1e-9)
    world_frames_per_target, ms_per_world_frame = work_rates(phases, targets, min(worlds, tasks))
    kept = int(manifest.totals["frames_kept"])
    keep_rate = kept / max(targets, 1)
    kept_fps = kept / max(sim.get("seconds", wall), 1e-9)
    print(json.dumps({
        "bench": "dataset", "spec": args.spec, "device": sim.get("device"), "worlds": spec["simulation"]["worlds"],
        "tolerance": spec["simulation"]["tolerance"], "range_scale": spec["poses"]["range_scale"], "sim_overrides": args.sim, "library_overrides": args.library, "filter_overrides": args.filter,
        "stub_frame_writes": args.stub_frame_writes, "writer": args.writer or "default", "switch_interval": sys.getswitchinterval(),
        "resolution": spec["garment"]["resolution"], "target_frames": targets, "kept_frames": kept,
        "dropped": manifest.totals["frames_dropped"], "simulation_s": sim.get("seconds"), "wall_s": round(wall, 2),
        "target_frames_per_s": round(fps, 2), "keep_rate": round(keep_rate, 3),
        "full_spec_target_frames": full_targets, "full_spec_expected_kept": round(full_targets * keep_rate),
        "projected_full_s": round(full_targets / max(fps, 1e-9), 1),
        "kept_frames_per_s": round(kept_fps, 2), "target_kept_frames": TARGET_KEPT_FRAMES, "target_s": TARGET_S,
        "projected_target_kept_s": round(TARGET_KEPT_FRAMES / kept_fps, 1) if kept_fps > 0 else None,
        # the same with the batch's set-up (visiting orders, cloth model, simulator) paid once, as
        # one batch of the full spec pays it, and the rest scaled to the kept frames asked for
        "projected_target_kept_s_setup_once": setup_once_projection(sim.get("seconds", wall), phases, kept),
        "audit_max_mm": manifest.audit.get("max_mm"), "audit_mean_mm": manifest.audit.get("mean_mm"),
        "phases": sim.get("phases"),
        "steady": steady_rates(beats),
        # busy world-frames per target (transition + hold + each task's start-up, no idle worlds)
        "world_frames_per_target": round(world_frames_per_target, 1),
        # of which: moving toward the next body (shape blend, slerp'ed poses, routes home), holding
        # target poses, settling after the shape blend
        "world_frames_per_target_split": frame_split(phases, targets),
        "ms_per_world_frame": round(ms_per_world_frame, 3),
        # the full spec's stepping time if its worlds were kept busy (poses_per_task) at this
        # slice's cost per world-frame and frames per target (sparser slices overestimate it)
        "projected_packed_stepping_s": round(full_targets * world_frames_per_target * 1e-3 * ms_per_world_frame, 1),
    }))
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)



class StackSampler:
    """Diagnostic wall-clock profiler: a daemon thread samples the main thread's Python stack every
    ``interval_s`` and, at exit, writes how many samples each function was on the stack
    (inclusive), on top of it (leaf) and, per source line, how many samples were in it (lines) to
    ``path`` as JSON. Unlike cProfile it charges waits inside C calls (device syncs, copies, the
    GIL) to the Python function and line that made them."""

    def __init__(self, path: str, interval_s: float = 0.002) -> None:
        import collections
        import threading

        self.path, self.interval_s = path, interval_s
        self.inclusive: collections.Counter = collections.Counter()
        self.leaf: collections.Counter = collections.Counter()
        self.lines: collections.Counter = collections.Counter()  # file:line on the stack (which line of a loop waits)
        self.samples = 0
        self._main = threading.main_thread().ident
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="stack-sampler", daemon=True)

    def start(self) -> None:
        import atexit

        sys.setswitchinterval(min(sys.getswitchinterval(), self.interval_s / 4))  # the sampler gets the GIL promptly
        atexit.register(self.write)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            time.sleep(self.interval_s)
            frame = sys._current_frames().get(self._main)
            names, lines = [], []
            while frame is not None:
                code = frame.f_code
                names.append(f"{Path(code.co_filename).name}:{code.co_name}:{code.co_firstlineno}")
                lines.append(f"{Path(code.co_filename).name}:{frame.f_lineno}")
                frame = frame.f_back
            if names:
                self.samples += 1
                self.leaf[names[0]] += 1
                for name in set(names):
                    self.inclusive[name] += 1
                for line in set(lines):
                    self.lines[line] += 1

    def write(self) -> None:
        if self._stop:  # written already (a run stopped by SIGTERM writes before it leaves)
            return
        self._stop = True
        self._thread.join()
        result = {"interval_s": self.interval_s, "samples": self.samples,
                  "inclusive": self.inclusive.most_common(120), "leaf": self.leaf.most_common(80),
                  "lines": self.lines.most_common(200)}
        Path(self.path).write_text(json.dumps(result, indent=1))


class DeviceProfiler:
    """Diagnostic device profile of a window of the run: ``torch.profiler`` starts at the first
    heartbeat at or after ``start_s`` seconds of simulation and stops at the first one ``window_s``
    later (or at ``finish``). On CUDA it records every kernel on the device (CUPTI: torch's, and
    Warp's inside its frame graphs); on the CPU, torch's operators. Writes ``kernel_table`` of the
    window to ``path`` as JSON: where the device time of a simulator frame goes."""

    def __init__(self, path: str, start_s: float, window_s: float, *, cuda: bool) -> None:
        if not (start_s >= 0.0 and window_s > 0.0):
            raise ValueError(f"start_s must be >= 0 and window_s > 0 (got {start_s}, {window_s})")
        self.path, self.start_s, self.window_s, self.cuda = path, start_s, window_s, cuda
        self._prof = None
        self._first: dict | None = None
        self.done = False

    def on_beat(self, beat: dict) -> None:
        """A heartbeat (``generate(on_heartbeat=...)``): starts or stops the recording."""
        import torch

        elapsed = float(beat.get("elapsed_s", 0.0))
        if self._prof is None and not self.done and elapsed >= self.start_s:
            activities = [torch.profiler.ProfilerActivity.CUDA if self.cuda else torch.profiler.ProfilerActivity.CPU]
            self._prof = torch.profiler.profile(activities=activities)
            self._prof.start()
            self._first = dict(beat)
        elif self._prof is not None and elapsed >= float(self._first.get("elapsed_s", 0.0)) + self.window_s:
            self.finish(beat)

    def finish(self, beat: dict) -> None:
        """Stops a recording in progress and writes its table (once)."""
        if self._prof is None or self.done:
            return
        self._prof.stop()
        self.done = True
        rows = []
        for e in self._prof.key_averages():
            total_us = float(getattr(e, "self_device_time_total", 0.0) if self.cuda else e.self_cpu_time_total)
            if total_us > 0.0:
                rows.append({"name": e.key, "count": int(e.count), "total_ms": total_us / 1e3})
        first = self._first or {}
        table = kernel_table(rows, frames=int(beat.get("frames", 0)) - int(first.get("frames", 0)),
                             seconds=float(beat.get("elapsed_s", 0.0)) - float(first.get("elapsed_s", 0.0)))
        Path(self.path).write_text(json.dumps({"device": "cuda" if self.cuda else "cpu", **table}, indent=1))
        self._prof = None


def kernel_table(rows: list[dict], *, frames: int, seconds: float, top: int = 60) -> dict:
    """Device time of a profiled window per simulator frame, by kernel.

    Args:
        rows: one per kernel (or operator): name, count (launches), total_ms (its own time in the window).
        frames: simulator frames stepped in the window; seconds: the window's wall time [s].
    Returns:
        dict: frames, seconds, busy_ms_per_frame (all rows' time per frame), busy_fraction (of the
        wall time; above 1 where kernels overlap), and kernels: the ``top`` rows by time, each with
        ms_per_frame, launches_per_frame and share of the busy time.
    """
    busy = sum(r["total_ms"] for r in rows)
    per = max(frames, 1)
    kernels = [{"name": r["name"], "ms_per_frame": round(r["total_ms"] / per, 4),
                "launches_per_frame": round(r["count"] / per, 2), "share": round(r["total_ms"] / busy, 4) if busy else 0.0}
               for r in sorted(rows, key=lambda r: -r["total_ms"])[:top]]
    return {"frames": frames, "seconds": round(seconds, 3), "busy_ms_per_frame": round(busy / per, 4),
            "busy_fraction": round(busy / 1e3 / seconds, 4) if seconds > 0 else None, "kernels": kernels}


def stub_frame_writes() -> None:
    """Diagnostic: ``ShardWriter.write_frame`` runs its checks and conversions but its per-frame
    arrays go nowhere (the shards keep zeros in those rows; never use them)."""
    from data_manifest.shard import ShardWriter

    class Sink:
        def __setitem__(self, key, value) -> None:
            pass

        def resize(self, *args, **kwargs) -> None:
            pass

    write = ShardWriter.write_frame

    def write_frame(self, *args, **kwargs):
        real = self._frame_datasets
        self._frame_datasets = {name: Sink() for name in real}
        try:
            return write(self, *args, **kwargs)
        finally:
            created = {name: d for name, d in self._frame_datasets.items() if not isinstance(d, Sink)}
            self._frame_datasets = {**real, **created}

    ShardWriter.write_frame = write_frame


#: Frames of TailorNet's released t-shirt dataset (seed 000: "55800 frames"), the benchmark's goal,
#: and the wall time the issue allows for them on one GPU [s].
TARGET_KEPT_FRAMES = 55_800
TARGET_S = 600.0


def setup_once_projection(seconds: float, phases: dict, kept: int) -> float | None:
    """Seconds for TARGET_KEPT_FRAMES kept frames when the set-up before the frame loop
    (``setup_s`` of run_sequences' statistics) is paid once and the rest scales with the kept
    frames; None without kept frames."""
    setup = float(phases.get("setup_s", 0.0))
    if kept <= 0:
        return None
    return round(setup + (float(seconds) - setup) * TARGET_KEPT_FRAMES / kept, 1)


def work_rates(phases: dict, targets: int, width: int) -> tuple[float, float]:
    """(busy world-frames per target, stepping ms per world-frame) from run_sequences' statistics:
    the stepping time of a frame is spread over the batch's width (``width`` worlds)."""
    per_target = float(phases.get("world_frames", 0)) / max(targets, 1)
    ms = 1e3 * float(phases.get("sim_s", 0.0)) / max(float(phases.get("frames", 0)) * width, 1)
    return per_target, ms


def frame_split(phases: dict, targets: int) -> dict[str, float]:
    """Busy world-frames per target by what the worlds were doing (run_sequences' statistics)."""
    return {k: round(float(phases.get(f"{k}_world_frames", 0)) / max(targets, 1), 2)
            for k in ("transition", "hold", "settle")}


def steady_rates(beats: list[dict]) -> dict | None:
    """Rates over the second half of a run's simulation, from its heartbeats (``generate``'s
    ``on_heartbeat`` dicts: elapsed_s, targets_done, world_frames, frames): the first targets
    finish in a burst once the worlds' first holds end, so rates from the start, or over short
    windows early on, do not compare between runs. From the first heartbeat at or past half the
    last one's elapsed time to the last: target poses, world-frames and simulator frames per
    second of simulation. None with fewer than two heartbeats past the start."""
    beats = [b for b in beats if float(b.get("elapsed_s", 0.0)) > 0.0]
    if len(beats) < 2:
        return None
    end = beats[-1]
    start = next(b for b in beats if float(b["elapsed_s"]) >= float(end["elapsed_s"]) / 2.0)
    if start is end:
        start = beats[-2]
    seconds = float(end["elapsed_s"]) - float(start["elapsed_s"])

    def rate(key: str) -> float:
        return round((float(end.get(key, 0)) - float(start.get(key, 0))) / seconds, 2)

    return {"from_s": round(float(start["elapsed_s"]), 1), "to_s": round(float(end["elapsed_s"]), 1),
            "target_poses_per_s": rate("targets_done"), "world_frames_per_s": rate("world_frames"),
            "frames_per_s": rate("frames")}


#: Heartbeat entries that are progress, not run_sequences statistics.
PROGRESS_KEYS = ("elapsed_s", "targets_done", "targets_total", "shards", "tasks", "kept_in_shards", "dropped_in_shards")


def partial_result(args: argparse.Namespace, spec: dict, beat: dict, full_targets: int, wall: float) -> dict:
    """The bench's JSON for a run stopped before the end, from its last heartbeat (``beat``: see
    ``generate(on_heartbeat=...)``); rates are over the simulation so far, start-up excluded."""
    done, elapsed = int(beat.get("targets_done", 0)), float(beat.get("elapsed_s", 0.0))
    per_target, ms = work_rates(beat, done, min(int(spec["simulation"]["worlds"]), int(beat.get("tasks") or 1)))
    fps = done / elapsed if elapsed > 0 else 0.0
    return {
        "bench": "dataset", "complete": False, "spec": args.spec, "device": spec["simulation"]["device"],
        "worlds": spec["simulation"]["worlds"], "resolution": spec["garment"]["resolution"],
        "sim_overrides": args.sim, "library_overrides": args.library, "filter_overrides": args.filter,
        "stub_frame_writes": args.stub_frame_writes, "writer": args.writer or "default", "switch_interval": sys.getswitchinterval(), "wall_s": round(wall, 2),
        "simulated_s": round(elapsed, 2), "target_frames_done": done, "target_frames": beat.get("targets_total"),
        "shards": beat.get("shards"), "tasks": beat.get("tasks"), "target_frames_per_s": round(fps, 2),
        "projected_full_s": round(full_targets / fps, 1) if fps > 0 else None, "full_spec_target_frames": full_targets,
        # every running count of run_sequences and generate-dataset (the record phase's parts too)
        "phases": {k: round(float(v), 3) for k, v in beat.items()
                   if k not in PROGRESS_KEYS and isinstance(v, (int, float)) and not isinstance(v, bool)},
        "world_frames_per_target": round(per_target, 1) if done else None,
        "ms_per_world_frame": round(ms, 3) if beat.get("frames") else None,
        # the filters' verdicts so far, over the shards already complete (``shards`` of ``tasks``)
        "kept_in_shards": beat.get("kept_in_shards"), "dropped_in_shards": beat.get("dropped_in_shards"),
    }


if __name__ == "__main__":
    main()
