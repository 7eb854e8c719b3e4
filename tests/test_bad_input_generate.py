"""generate-dataset under faults: a second writer, a stale lock, SIGINT/SIGTERM (also during the
audit) and resume, a full disk, unwritable or wrong --out, --device without CUDA.

The simulation is replaced by a stand-in (module ``FAKE`` below) that writes synthetic frames
through the real ShardWriter into the real manifest, so the pipeline's locking, signal,
cleanup, resume and audit bookkeeping run as in production while a run takes a second, not
the minutes of the cloth simulator. Run as a script, this file is ``drape`` with the stand-in
(the tests start it as a subprocess to signal it).
"""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SPEC = {"name": "fake", "seed": 1, "garment": {"type": "tshirt"}, "styles": {"train": 1, "test": 1},
        "shapes": {"train": 1, "test": 1}, "pairs": {"train": 1, "test": 1},
        "poses": {"train_count": 3, "test_count": 2}, "simulation": {"device": "cpu", "worlds": 1},
        "audit": {"samples": 0}}
#: Environment of the stand-in: seconds per frame, seconds the audit takes, file touched when the audit starts.
DELAY_ENV, AUDIT_SLEEP_ENV, AUDIT_MARK_ENV = "FAKE_FRAME_DELAY_S", "FAKE_AUDIT_SLEEP_S", "FAKE_AUDIT_MARK"


# -- the stand-in simulation ---------------------------------------------------------------------


def fake_context(spec, out_dir, *, device=None, log=print):
    from data_manifest.synthetic import tube_template

    rng = np.random.default_rng(int(spec["seed"]))
    tasks = []  # pipelines.dataset_plan.Task's fields; one style-shape pair (a batch of one world) each
    for k, (split, count) in enumerate((("train_train", 3), ("train_test", 2), ("test_train", 1), ("test_test", 1))):
        poses = rng.uniform(-0.3, 0.3, (count, 6)).astype(np.float32)
        tasks.append(SimpleNamespace(task_id=f"{split}-p000", split=split, pair=k, style_index=0,
                                     shape=np.full(4, 0.1 * k, np.float32), style_vector=np.zeros(2, np.float32),
                                     pose_ids=np.arange(count), poses=poses, motion_steps=0, motion="",
                                     fabric="cotton", garment_index=0, tightness=None, start_shape=None))
    plan = SimpleNamespace(tasks=tasks, pruned_poses=np.zeros((0, 6), np.float32), pruned_reasons=np.zeros(0, str))
    return SimpleNamespace(spec=spec, device="cpu", template_dict=tube_template(), plan=plan,
                           tasks={t.task_id: t for t in tasks}, phases={})


def fake_run_local(ctx, out_dir, batches, *, on_shard, on_progress, on_batch=None, skip=frozenset(), simulate_batch=None):
    from data_manifest.shard import ShardWriter, shard_path
    from data_manifest.synthetic import synthetic_frame

    delay = float(os.environ.get(DELAY_ENV, "0"))
    for batch in batches:
        for task_id in batch:
            task = ctx.tasks[task_id]
            rng = np.random.default_rng(abs(hash(task_id)) % 2**32)
            if task_id in skip:
                continue
            meta = {"task_id": task_id, "garment": "tube", "splits": [task.split], "seed": 1,
                    "shape": task.shape, "style": task.style_vector}
            with ShardWriter(shard_path(out_dir, task_id), template=ctx.template_dict, task=meta) as writer:
                for k in range(len(task.poses)):
                    writer.write_frame(**synthetic_frame(ctx.template_dict, rng, translation_m=np.zeros(3)),
                                       frame_index=k)
                    on_progress(1)
                    time.sleep(delay)
            on_shard(writer.record)
        if on_batch is not None:
            on_batch()


def fake_audit(ctx, out_dir, manifest, *, log=print):
    mark = os.environ.get(AUDIT_MARK_ENV)
    if mark:
        Path(mark).write_text("audit started")
    time.sleep(float(os.environ.get(AUDIT_SLEEP_ENV, "0")))
    return {"reference": "equilibrium", "samples": int(ctx.spec["audit"]["samples"]), "frames": []}


def install_fakes(monkeypatch=None) -> None:
    """Replaces the simulator, its executor and the audit by the stand-ins."""
    import pipelines.executors as executors
    import pipelines.generate_dataset as gd

    audit = ModuleType("pipelines.audit")
    audit.audit_dataset = fake_audit
    if monkeypatch is not None:
        monkeypatch.setattr(gd, "build_context", fake_context)
        monkeypatch.setattr(executors, "run_local", fake_run_local)
        monkeypatch.setitem(sys.modules, "pipelines.audit", audit)
    else:
        gd.build_context, executors.run_local = fake_context, fake_run_local
        sys.modules["pipelines.audit"] = audit


if __name__ == "__main__":  # drape with the stand-in simulation
    sys.path.insert(0, str(REPO))
    install_fakes()
    from pipelines.cli import main

    sys.exit(main(sys.argv[1:]))


# -- helpers ------------------------------------------------------------------------------------------


def write_spec(tmp_path: Path, **changes) -> Path:
    spec = json.loads(json.dumps(SPEC))
    for dotted, value in changes.items():
        node = spec
        *parents, leaf = dotted.split("__")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def start(spec: Path, out: Path, **env) -> subprocess.Popen:
    environment = {**os.environ, "PYTHONPATH": str(REPO), "TQDM_DISABLE": "1", **{k: str(v) for k, v in env.items()}}
    return subprocess.Popen([sys.executable, __file__, "generate-dataset", str(spec), "--out", str(out), "--no-progress"],
                            env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(condition, timeout_s: float = 30.0) -> None:
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout_s, "timed out"
        time.sleep(0.02)


def temporaries(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".tmp") or ".tmp." in p.name]


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    from pipelines.cli import main

    code = main(args)
    return code, capsys.readouterr().err


# -- tests ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_leaves_no_temporary_and_a_rerun_completes(tmp_path, signum, code):
    spec, out = write_spec(tmp_path), tmp_path / "ds"
    proc = start(spec, out, **{DELAY_ENV: 0.2})
    # in flight: a shard listed in the saved manifest (after the first batch) and the next one open
    wait_for(lambda: (out / "manifest.json").is_file() and any((out / "shards").glob("*.tmp")))
    proc.send_signal(signum)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == code, stderr
    lines = stderr.strip().splitlines()
    assert lines == ["drape generate-dataset: interrupted; rerun the same command to resume"], stderr
    assert not temporaries(out), temporaries(out)
    assert not (out / "writer.lock").exists(), "the lock is released"
    from data_manifest.validate import validate_dataset

    report = validate_dataset(out)
    assert {p.kind for p in report.errors} <= {"pending"}, report.errors  # listed shards are whole
    proc = start(spec, out)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    assert validate_dataset(out).ok
    assert "resuming" in stdout or len(json.loads((out / "manifest.json").read_text())["shards"]) == 4


def test_kill_during_the_audit_then_resume_completes_the_audit_block(tmp_path):
    spec, out = write_spec(tmp_path, audit__samples=2), tmp_path / "ds"
    mark = tmp_path / "audit-started"
    proc = start(spec, out, **{AUDIT_SLEEP_ENV: 60, AUDIT_MARK_ENV: mark})
    wait_for(mark.exists)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 143, stderr
    audit = json.loads((out / "manifest.json").read_text()).get("audit") or {}
    assert "simulation" in audit and "samples" not in audit, audit  # the simulation's record survived
    proc = start(spec, out)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    audit = json.loads((out / "manifest.json").read_text())["audit"]
    assert audit["samples"] == 2 and audit["reference"] == "equilibrium" and audit["simulation"]["target_frames"] == 7, audit


def test_second_writer_refused_naming_the_first_which_then_finishes(tmp_path, capsys):
    spec, out = write_spec(tmp_path), tmp_path / "ds"
    first = start(spec, out, **{DELAY_ENV: 0.15})
    wait_for(lambda: (out / "manifest.json").is_file() and any((out / "shards").glob("*.tmp")))
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"pid {first.pid}" in err and "being written by another run" in err, err
    assert any((out / "shards").glob("*.tmp")), "the second run must leave the first's open shard alone"
    # the dataset summary names the writer while it runs
    from data_manifest.validate import info

    assert f"being written: host {os.uname().nodename}, pid {first.pid}" in info(out)
    _, stderr = first.communicate(timeout=60)
    assert first.returncode == 0, "the second run must not disturb the first: " + stderr
    from data_manifest.validate import validate_dataset

    assert validate_dataset(out).ok


def test_stale_lock_of_a_dead_run_is_taken_over(tmp_path, monkeypatch, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    spec, out = write_spec(tmp_path), tmp_path / "ds"
    out.mkdir()
    (out / "writer.lock").write_text(json.dumps({"host": os.uname().nodename, "pid": dead.pid,
                                                 "start_time": "2020-01-01T00:00:00+00:00", "command": "drape"}))
    install_fakes(monkeypatch)
    from pipelines.generate_dataset import generate

    lines: list[str] = []
    generate(str(spec), out, progress=False, log=lines.append)
    assert any(f"took over the writer lock of an ended run (host {os.uname().nodename}, pid {dead.pid}" in m
               for m in lines), lines
    assert not (out / "writer.lock").exists()


@pytest.mark.parametrize("use_flock", [True, False])
def test_lock_refuses_a_live_holder_and_takes_over_a_dead_one(tmp_path, monkeypatch, use_flock):
    import data_manifest.lock as lock
    from data_manifest.lock import DatasetLock, DatasetLockedError

    if not use_flock:  # the lock of file systems without flock: the file and the holder's pid
        monkeypatch.setattr(lock, "fcntl", None)
    first = DatasetLock(tmp_path).acquire()
    with pytest.raises(DatasetLockedError, match=f"pid {os.getpid()}, started"):
        DatasetLock(tmp_path).acquire()
    first.release()
    with DatasetLock(tmp_path) as again:
        assert again.took_over is None
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / "writer.lock").write_text(json.dumps({"host": os.uname().nodename, "pid": dead.pid,
                                                      "start_time": "t0"}))
    with DatasetLock(tmp_path) as taken:
        assert taken.took_over is not None and taken.took_over.pid == dead.pid
    if not use_flock:  # a lock of another host is never taken over from here
        (tmp_path / "writer.lock").write_text(json.dumps({"host": "elsewhere", "pid": 1, "start_time": "t0"}))
        with pytest.raises(DatasetLockedError, match="host elsewhere"):
            DatasetLock(tmp_path).acquire()


def test_disk_full_while_writing_is_one_message_and_a_rerun_resumes(tmp_path, monkeypatch, capsys):
    from data_manifest.shard import ShardWriter
    from data_manifest.validate import validate_dataset

    install_fakes(monkeypatch)
    spec, out = write_spec(tmp_path), tmp_path / "ds"
    real = ShardWriter.write_frame
    calls = {"n": 0}

    def full(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 5:  # the second shard's second frame
            raise OSError(errno.ENOSPC, "No space left on device", str(self.tmp_path))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ShardWriter, "write_frame", full)
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(out), "--no-progress"], capsys)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "disk of" in err and "is full: writing" in err and ".h5." in err and "B free" in err, err
    assert "rerun the same command to resume" in err, err
    assert not temporaries(out) and not (out / "writer.lock").exists()
    report = validate_dataset(out)
    assert {p.kind for p in report.errors} <= {"pending"}, report.errors  # nothing half-written is listed
    monkeypatch.setattr(ShardWriter, "write_frame", real)
    assert run_cli(["generate-dataset", str(spec), "--out", str(out), "--no-progress"], capsys)[0] == 0
    assert validate_dataset(out).ok


def test_not_enough_space_is_refused_before_simulating(tmp_path, monkeypatch, capsys):
    import pipelines.errors as errors

    install_fakes(monkeypatch)
    monkeypatch.setattr(errors, "free_bytes", lambda path: 1000)
    spec, out = write_spec(tmp_path), tmp_path / "ds"
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(out)], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert "not enough free space in" in err and "1000 B are free" in err and "need about" in err, err
    assert not list((out / "shards").glob("*")) if (out / "shards").exists() else True


def test_background_writer_on_a_full_disk_removes_the_temporary(tmp_path, monkeypatch):
    """The production path (simulate_batch): shard writes on the background worker; a failed
    write reaches the caller, whose cleanup aborts every open shard."""
    from data_manifest.background import BackgroundWriter
    from data_manifest.shard import ShardWriter, ShardWriterSet
    from data_manifest.synthetic import synthetic_frame, tube_template

    template = tube_template()

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    background = BackgroundWriter(mode="thread")
    background.create("s", ShardWriterSet, tmp_path, template)
    background.call("s", ShardWriterSet.open, 0, {"task_id": "t0", "garment": "tube", "splits": ["train"], "seed": 0,
                                                  "shape": np.zeros(4), "style": np.zeros(2)})
    frame = synthetic_frame(template, np.random.default_rng(0), translation_m=np.zeros(3))
    background.call("s", ShardWriterSet.write_frame, 0, **frame, frame_index=0)
    monkeypatch.setattr(ShardWriter, "write_frame", full)
    background.call("s", ShardWriterSet.write_frame, 0, **frame, frame_index=1)
    with pytest.raises(OSError, match="No space left"):
        background.close()
    background.close(raise_error=False, cleanup=ShardWriterSet.abort)
    assert not list(tmp_path.rglob("*.tmp"))


def test_out_problems_and_device_name_the_option(tmp_path, capsys):
    spec = write_spec(tmp_path)
    a_file = tmp_path / "file"
    a_file.write_text("x")
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(a_file)], capsys)
    assert code == 2 and "--out" in err and "is a file; expected a directory" in err, err
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(a_file / "sub")], capsys)
    assert code == 2 and "--out" in err and "a parent of it is a file" in err, err
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(tmp_path / "d"), "--device", "gpu"], capsys)
    assert code == 2 and "--device must be auto, cpu, cuda or cuda:N (got 'gpu')" in err, err
    import warp as wp

    if wp.get_cuda_device_count() == 0:
        code, err = run_cli(["generate-dataset", str(spec), "--out", str(tmp_path / "d"), "--device", "cuda"], capsys)
        assert code == 2 and "--device is 'cuda' but Warp finds no CUDA device" in err, err
    for text in (err,):
        assert "Traceback" not in text and text.count("\n") == 1


def test_unwritable_out_is_refused_before_work(tmp_path, capsys, unwritable_dir):
    spec = write_spec(tmp_path)
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(unwritable_dir / "ds")], capsys)
    assert code == 2 and err.count("\n") == 1 and "--out" in err, err
    assert "cannot be created" in err or "is not writable" in err, err


def test_debug_shows_the_traceback(tmp_path, capsys):
    spec = write_spec(tmp_path, simulation__substep=3)
    code, err = run_cli(["generate-dataset", str(spec), "--out", str(tmp_path / "d")], capsys)
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1
    assert "spec.simulation.substep is not a known field (did you mean substeps?)" in err, err
    code, err = run_cli(["--debug", "generate-dataset", str(spec), "--out", str(tmp_path / "d")], capsys)
    assert code == 2 and "Traceback (most recent call last)" in err and "SpecError" in err, err
    assert not (tmp_path / "d").exists(), "a bad spec creates nothing"
