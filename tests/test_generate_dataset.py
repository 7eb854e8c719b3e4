"""generate-dataset end to end on CPU: a tiny spec, filters, kill + resume, Ray."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from data_manifest.reader import DatasetReader
from data_manifest.validate import validate_dataset

TINY_SPEC = {
    "name": "tiny",
    "seed": 3,
    "garment": {"type": "tshirt", "resolution": 400},
    "styles": {"train": 1, "test": 1},
    "shapes": {"train": [[0.5, 0.5, 0.5, 0.5, 0.5, 0.5]], "test": [[0.5, 0.5, 0.5, 0.6, 0.5, 0.5]]},
    "pairs": {"train": 1, "test": 1},
    "poses": {"range_scale": 0.25, "train_count": 2, "test_count": 1},
    "splits": {"train_train": "all", "train_test": "all", "test_train": 1, "test_test": 1},
    # tolerance 0.01: the audited frame rests close enough to its equilibrium for the audit's Newton
    # reference to converge (at 0.03 with the library's 10-frame shape transition it stalls)
    "simulation": {"device": "cpu", "worlds": 1, "iterations": 8, "tolerance": 0.01, "max_relax_frames": 40,
                   "interpolation_threshold": 0.25},
    "filters": {"require_converged": False},
    "audit": {"samples": 1},
}


NO_AUDIT = {"audit__samples": 0}
"""For runs whose test does not read the audit: each audited frame costs a Newton solve to its
equilibrium (~15 s for the tiny spec's 1.8k-vertex t-shirt on CPU); the ``reference`` run audits."""


def _with(**changes) -> dict:
    spec = json.loads(json.dumps(TINY_SPEC))
    for dotted, value in changes.items():
        node = spec
        *parents, leaf = dotted.split("__")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return spec


def _shard_hashes(root: Path) -> dict[str, str]:
    manifest = json.loads((root / "manifest.json").read_text())
    return {s["task_id"]: s["sha256"] for s in manifest["shards"]}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    from pipelines.generate_dataset import generate

    out = tmp_path_factory.mktemp("reference")
    generate(_with(), out, progress=False, log=lambda m: None)
    return out


def test_dataset_is_valid_and_frame_counts_add_up(reference):
    report = validate_dataset(reference)
    assert report.ok, report.errors
    manifest = json.loads((reference / "manifest.json").read_text())
    assert {s["task_id"].split("-")[0] for s in manifest["shards"]} == {"train_train", "train_test", "test_train", "test_test"}
    planned = {"train_train": 2, "train_test": 1, "test_train": 1, "test_test": 1}
    for shard in manifest["shards"]:
        dropped = sum(shard["filter_stats"].values())
        assert shard["frame_count"] + dropped == planned[shard["task_id"].split("-")[0]], shard
    kept = sum(s["frame_count"] for s in manifest["shards"])
    assert manifest["totals"]["frames_kept"] == kept > 0, "the tiny spec must keep frames"
    assert manifest["audit"]["samples"] >= 1 and manifest["audit"]["max_mm"]["max"] >= 0.0
    # the audit measures against the static equilibrium of each sampled frame (pipelines/audit.py)
    audit = manifest["audit"]
    assert audit["reference"] == "equilibrium" and audit["friction"] == "stick", audit
    assert audit["converged"] + audit["not_converged"] == audit["samples"] == len(audit["frames"]), audit
    assert audit["converged"] >= 1, f"no audited frame reached its equilibrium in {audit['max_iterations']} iterations"
    for f in audit["frames"]:
        assert f["iterations"] <= audit["max_iterations"] and f["max_mm"] >= f["mean_mm"] > 0.0, f
        if f["converged"]:
            assert f["residual_n"] <= f["tol_force_n"], f
    measured = [f for f in audit["frames"] if f["converged"]]
    assert audit["max_mm"]["max"] == max(f["max_mm"] for f in measured)
    assert audit["mean_mm"]["median"] == float(np.median([f["mean_mm"] for f in measured]))
    with np.load(reference / "pruned_poses.npz") as pruned:
        assert pruned["reason"].shape == (len(pruned["poses"]),), "every pruned pose says why"


def test_reader_returns_what_the_simulation_recorded(reference):
    reader = DatasetReader(reference)
    split = max(reader.splits, key=reader.num_frames)
    arrays = reader.load_split(split)
    v = arrays["posed_vertices"]
    assert len(v) > 0
    assert v.ndim == 3 and np.isfinite(v).all()
    # the garment hangs on a body standing at the origin: it must lie within body height
    assert -0.9 < v[..., 1].min() and v[..., 1].max() < 0.9
    d = arrays["unposed_displacements"]
    assert np.abs(d).max() < 0.2, "unposed displacements are offsets from the body, centimetres not metres"


def test_planted_bad_frame_is_dropped_and_counted(tmp_path, monkeypatch):
    import simulate.sequence as sequence
    from pipelines.generate_dataset import generate

    real = sequence.run_sequences

    def planting(*args, on_frames, **kwargs):
        planted = []

        def corrupt(frames):
            if not planted:  # blow the first recorded frame up: triangle areas grow 4x
                c = frames[0].positions.mean(0)
                frames[0].positions = c + 2.0 * (frames[0].positions - c)
                planted.append(frames[0].key)
            return on_frames(frames)

        return real(*args, on_frames=corrupt, **kwargs)

    monkeypatch.setattr(sequence, "run_sequences", planting)
    spec = _with(pairs__test=0, poses__test_count=0, splits__train_test=0, **NO_AUDIT)
    manifest = generate(spec, tmp_path, progress=False, log=lambda m: None)
    assert manifest.totals["frames_dropped"].get("distortion", 0) >= 1
    # every dropped frame is logged in its shard, with its index in the sequence and its pose
    reader = DatasetReader(tmp_path)
    dropped = reader.dropped_frames("train_train")
    assert len(dropped["reason"]) == sum(manifest.totals["frames_dropped"].values()), dropped
    assert (0, "distortion") in zip(dropped["frame_index"].tolist(), dropped["reason"].tolist()), dropped
    kept = reader.load_split("train_train")
    assert sorted(dropped["frame_index"].tolist() + kept["frame_index"].tolist()) == [0, 1]
    assert dropped["pose"].shape == (len(dropped["reason"]), 60) and np.isfinite(dropped["pose"]).all()
    assert validate_dataset(tmp_path).ok


def test_a_dropped_frame_sends_its_world_home(tmp_path, monkeypatch):
    """The pipeline tells the sequence driver which frames the filters dropped, and with
    SequenceSettings.restart_after_rejects (1) the world goes back to its canonical drape after one."""
    import simulate.sequence as sequence
    from pipelines.generate_dataset import generate

    real = sequence.run_sequences
    verdicts: list[tuple[bool, object]] = []

    def planting(*args, on_frames, **kwargs):
        def corrupt(frames):
            planted = not verdicts
            if planted:  # blow the first target frame up: triangle areas grow 4x
                c = frames[0].positions.mean(0)
                frames[0].positions = c + 2.0 * (frames[0].positions - c)
            answers = on_frames(frames)
            verdicts.extend((planted and i == 0, a) for i, a in enumerate(answers))
            return answers

        return real(*args, on_frames=corrupt, **kwargs)

    monkeypatch.setattr(sequence, "run_sequences", planting)
    spec = _with(pairs__test=0, poses__test_count=0, splits__train_test=0, **NO_AUDIT)
    manifest = generate(spec, tmp_path, progress=False, log=lambda m: None)
    assert verdicts[0] == (True, False), verdicts
    assert all(isinstance(v, bool) for _, v in verdicts), verdicts
    assert sum(v for _, v in verdicts) == manifest.totals["frames_kept"], (verdicts, manifest.totals)
    # the planted frame was the first of the task's two targets: one trip home
    assert manifest.audit["simulation"]["phases"]["restarts_after_rejects"] == 1, manifest.audit["simulation"]["phases"]


@pytest.mark.parametrize("changes, expected", [
    ({}, True),
    ({"simulation__solver": "mass_spring"}, False),  # self-contact is XPBD's
])
def test_canonical_drapes_are_made_with_self_contact(tmp_path, monkeypatch, changes, expected):
    """The canonical style drapes, where every sequence starts and restarts, are relaxed with
    self-contact by default (a CPU drape of two TailorNet-spec styles at 7.7k vertices: 158 and 52
    garment edges through the garment without, 0 and 0 with)."""
    import simulate.sequence as sequence
    from pipelines.generate_dataset import build_context
    from pipelines.spec import validate_spec
    from simulate.quasi_static import WorldStatus

    seen = []

    def fake_drape(body, faces, rest_vertices, *, settings, **kwargs):
        seen.append(settings.self_contact)
        return np.asarray(rest_vertices), np.full(len(rest_vertices), WorldStatus.CONVERGED)

    monkeypatch.setattr(sequence, "drape_static", fake_drape)
    build_context(validate_spec(_with(**changes)), tmp_path, device="cpu", log=lambda m: None)
    assert seen == [expected], seen


def _run_cli(spec_path: Path, out: Path) -> subprocess.Popen:
    env = dict(os.environ, TQDM_DISABLE="1", PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "pipelines.cli", "generate-dataset", str(spec_path), "--out", str(out),
                             "--no-progress"], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def test_kill_then_resume_equals_uninterrupted_run(reference, tmp_path):
    import yaml

    spec_path = tmp_path / "tiny.yaml"
    spec_path.write_text(yaml.safe_dump(_with(**NO_AUDIT)))
    out = tmp_path / "killed"
    proc = _run_cli(spec_path, out)
    deadline = time.time() + 600
    while time.time() < deadline and proc.poll() is None:
        if (out / "manifest.json").is_file() and json.loads((out / "manifest.json").read_text())["shards"]:
            break
        time.sleep(0.2)
    assert proc.poll() is None, f"the run finished before it could be killed:\n{proc.stdout.read().decode()}"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    partial = _shard_hashes(out)
    assert 0 < len(partial) < 5
    report = validate_dataset(out)
    broken = [e for e in report.errors if e.kind != "pending"]
    assert not broken, f"a killed run must leave no listed shard that fails validation: {broken}"
    assert report.errors, "the killed dataset must be reported as unfinished (pending tasks)"
    resumed = _run_cli(spec_path, out)
    log = resumed.communicate(timeout=900)[0].decode()
    assert resumed.returncode == 0, log
    assert "resuming" in log
    assert _shard_hashes(out) == _shard_hashes(reference), "resumed dataset differs from the uninterrupted one"


def test_shards_written_by_a_worker_process_equal_the_threads(reference, tmp_path, monkeypatch):
    from data_manifest.background import MODE_ENV
    from pipelines.generate_dataset import generate

    monkeypatch.setenv(MODE_ENV, "process")  # the GPU runs' writer (the CPU default is a thread)
    manifest = generate(_with(**NO_AUDIT), tmp_path, progress=False, log=lambda m: None)
    assert _shard_hashes(tmp_path) == _shard_hashes(reference)
    assert all(s["timings"]["wall_s"] > 0 for s in manifest.shards), "the worker sets each shard's wall time"
    assert validate_dataset(tmp_path).ok
    assert not list(tmp_path.rglob("*.tmp*")), "no temporary file stays behind"


def test_ray_executor_matches_local(reference, tmp_path, monkeypatch):
    """Two local Ray workers, one of them killed after writing its batch's first shard: the batch
    runs again, and the dataset equals the local run byte for byte (nothing the dead attempt wrote
    is listed; its temporary files are removed). One Ray run checks both: each costs ~15-30 s of
    worker start-up on a 2-core machine."""
    pytest.importorskip("ray")
    from data_manifest.manifest import Manifest
    from pipelines.executors import FAULT_ENV
    from pipelines.generate_dataset import generate

    marker = tmp_path / "killed.txt"
    monkeypatch.setenv(FAULT_ENV, str(marker))
    out = tmp_path / "out"
    lines: list[str] = []
    beats: list[dict] = []
    manifest = generate(_with(**NO_AUDIT), out, executor="ray", ray_cpus=2, progress=False, log=lines.append,
                        heartbeat_s=0.0, on_heartbeat=beats.append)
    assert marker.is_file() and "exited after its first shard" in marker.read_text()
    assert _shard_hashes(out) == _shard_hashes(reference)
    assert validate_dataset(out).ok
    assert not list(out.rglob("*.tmp*")), "no temporary file of the dead attempt stays behind"
    ray = manifest.audit["simulation"]["ray"]
    assert ray["batches_rerun"] == 1 and ray["nodes"] == 1 and ray["gpus"] == 0 and 1 <= ray["workers"] <= 2, ray
    assert any("Ray workers" in m and "1 batch(es) re-run" in m for m in lines), lines
    # when each batch returned (one world: a batch per pair), after the first target pose finished
    assert len(ray["batch_done_s"]) == 2 and 0 < ray["first_target_s"] <= max(ray["batch_done_s"]), ray
    assert any("Ray timeline" in m and "batches returned at" in m for m in lines), lines
    # the driver adds up the statistics of the attempts that finished: those of the local run
    local = Manifest.load(reference).audit["simulation"]["phases"]
    phases = manifest.audit["simulation"]["phases"]
    for key in ("frames", "world_frames", "restarts_after_rejects"):
        assert phases.get(key) == local.get(key), (key, phases, local)
    # progress counts target poses across the workers; a dead attempt's count is taken back
    assert beats[-1]["targets_done"] == beats[-1]["targets_total"] == 5, beats[-1]
    assert all(b["targets_done"] <= 5 for b in beats), [b["targets_done"] for b in beats]
    assert beats[-1]["frames"] == local["frames"], beats[-1]


def test_collider_keeps_the_parts_beyond_the_garment_openings(reference, anny_body):
    from pipelines.generate_dataset import build_context
    from pipelines.spec import validate_spec
    from simulate.garment.drape import COLLISION_PARTS

    ctx = build_context(validate_spec(_with()), reference, device="cpu", log=lambda m: None)
    np.testing.assert_array_equal(ctx.body_faces, anny_body.part_faces(COLLISION_PARTS["tshirt"]))
    legs = set(np.unique(anny_body.part_faces(("legs",))).tolist())
    assert legs & set(np.unique(ctx.body_faces).tolist()), "a t-shirt's collider needs the legs below its hem"


def test_poses_per_task_splits_a_pair_into_consecutive_tasks(anny_body):
    """Chunked tasks cover the same poses in the same visiting order as the unchunked task."""
    from pipelines.dataset_plan import plan_dataset
    from pipelines.spec import validate_spec

    body = anny_body
    whole = plan_dataset(validate_spec(_with()), body)
    chunked = plan_dataset(validate_spec(_with(simulation__poses_per_task=1)), body)
    for task in whole.tasks:
        parts = [t for t in chunked.tasks if t.split == task.split and t.pair == task.pair]
        assert all(len(t.pose_ids) <= 1 for t in parts)
        np.testing.assert_array_equal(np.concatenate([t.pose_ids for t in parts]), task.pose_ids)
        if len(task.pose_ids) > 1:
            assert [t.task_id for t in parts] == [f"{task.task_id}-c{c:03d}" for c in range(len(parts))]


def test_test_pairs_of_seen_styles_and_shapes_are_unseen_combinations(anny_body):
    """styles.test and shapes.test 'train': the test pairs use the train styles and shapes
    (TailorNet's protocol) and are never a train pair; an impossible count names pairs.test."""
    from pipelines.dataset_plan import plan_dataset
    from pipelines.spec import validate_spec

    spec = _with(styles={"train": 3, "test": "train"}, shapes={"train": 2, "test": "train"},
                 pairs={"train": 3, "test": 3})
    plan = plan_dataset(validate_spec(spec), anny_body)
    train = {(si, hi) for g, si, hi in plan.pairs if g == "train"}
    test = {(si, hi) for g, si, hi in plan.pairs if g == "test"}
    assert len(train) == 3 and len(test) == 3 and not train & test, (train, test)
    assert len(plan.styles) == 3 and len(plan.shapes) == 2, "no test styles or shapes of their own"
    assert {si for si, _ in test} <= {0, 1, 2} and {hi for _, hi in test} <= {0, 1}
    mixed = plan_dataset(validate_spec(_with(styles={"train": 2, "test": "train"}, shapes={"train": 2, "test": 2},
                                             pairs={"train": 2, "test": 3})), anny_body)
    assert {si for g, si, _ in mixed.pairs if g == "test"} <= {0, 1}, "seen styles"
    assert {hi for g, _, hi in mixed.pairs if g == "test"} <= {2, 3}, "unseen shapes"
    with pytest.raises(ValueError, match=r"spec.pairs.test = 4 but only 3 test style-shape combinations exist "
                                         r"\(3 styles x 2 shapes, less the 3 train pairs\)"):
        plan_dataset(validate_spec(_with(styles={"train": 3, "test": "train"}, shapes={"train": 2, "test": "train"},
                                         pairs={"train": 3, "test": 4})), anny_body)


def test_min_clearance_reaches_the_plan_and_its_pruned_poses(anny_body):
    """poses.min_clearance prunes the sampled poses by skin clearance (arms to torso for a t-shirt)
    and records them with the capsule test's pruned poses."""
    from pipelines.dataset_plan import plan_dataset
    from pipelines.spec import validate_spec
    from simulate.body.clearance import CLEARANCE_PAIRS, LimbClearance

    spec = _with(poses__range_scale=1.0, poses__train_count=6, poses__min_clearance=0.03)
    plan = plan_dataset(validate_spec(spec), anny_body)
    plain = plan_dataset(validate_spec(_with(poses__range_scale=1.0, poses__train_count=6)), anny_body)
    clearance = LimbClearance(anny_body, anny_body.shape_default, CLEARANCE_PAIRS["upper"])
    poses = np.concatenate([plan.poses["train"], plan.poses["test"]])
    assert clearance.measure(poses).min() >= 0.03
    assert len(plan.pruned_poses) > len(plain.pruned_poses)
    assert (clearance.measure(plan.pruned_poses).min(axis=1) < 0.03).any()
    assert plan.pruned_reasons.shape == (len(plan.pruned_poses),) and set(plan.pruned_reasons) <= {"clearance", "self_intersection"}
    close = plan.pruned_reasons == "clearance"
    assert close.any() and (clearance.measure(plan.pruned_poses[close]).min(axis=1) < 0.03).all()
    from simulate.body.mesh_utils import SelfIntersectionChecker
    assert SelfIntersectionChecker(anny_body, anny_body.shape_default).check(plan.pruned_poses[~close])[0].all()


def test_summary_table_reports_drops_and_where_the_time_went(reference):
    from data_manifest.manifest import Manifest
    from pipelines.generate_dataset import DROP_REASONS, _summary_table

    manifest = Manifest.load(reference)
    phases = manifest.audit["simulation"]["phases"]
    assert phases["frames"] > 0 and phases["sim_s"] > 0 and phases["writer_busy_s"] > 0, phases
    table = _summary_table(manifest, 10.0, 20)
    kept = int(manifest.totals["frames_kept"])
    assert f"frames kept{kept:>6}".replace(" ", "") in table.replace(" ", ""), table
    assert all(f"dropped: {reason}" in table for reason in DROP_REASONS), table
    assert "2.00 target frames/s" in table and "explosions recovered" in table, table
    assert table.split("of them restarted")[1].split()[0] == str(int(phases["restarts"])), table
    assert table.split("tasks of other pairs")[1].split()[0] == str(int(phases["group_switches"])), table
    assert f"over {int(phases['frames'])} simulator frames" in table, table
    parts = [phases[k] for k in ("setup_schedules_s", "setup_model_s", "setup_simulator_s")]
    assert min(parts) >= 0 and abs(sum(parts) - phases["setup_s"]) < 0.01, phases
    assert " / ".join(f"{v:.1f}" for v in parts) + " s" in table, table


def test_chunked_tasks_write_one_valid_shard_per_piece(tmp_path):
    from pipelines.generate_dataset import generate

    lines: list[str] = []
    snapshots: list[dict] = []
    generate(_with(simulation__poses_per_task=1, **NO_AUDIT), tmp_path, progress=False, log=lines.append, heartbeat_s=0.0,
             on_heartbeat=snapshots.append)
    # headless runs log their progress: the plan, then heartbeats counting up to every target pose,
    # with the simulator's running split of the time
    assert any(m.startswith("simulating 5 tasks (5 target poses)") for m in lines), lines
    beats = [m for m in lines if "target poses (" in m]
    assert beats and beats[-1].split(": ")[1].startswith("5/5 target poses"), beats
    assert "stepping / bodies / recording" in beats[-1] and "world-frames" in beats[-1], beats[-1]
    last = snapshots[-1]
    assert (last["targets_done"], last["targets_total"], last["tasks"]) == (5, 5, 5), last
    assert last["frames"] > 0 and last["world_frames"] >= last["frames"] and last["sim_s"] > 0, last
    assert [s["frames"] for s in snapshots] == sorted(s["frames"] for s in snapshots), "running counts must not fall"
    report = validate_dataset(tmp_path)
    assert report.ok, report.errors
    shards = json.loads((tmp_path / "manifest.json").read_text())["shards"]
    ids = sorted(s["task_id"] for s in shards)
    assert ids == ["test_test-p001", "test_train-p001", "train_test-p000", "train_train-p000-c000",
                   "train_train-p000-c001"], ids
    for shard in shards:  # one target pose per piece, kept or dropped
        assert shard["frame_count"] + sum(shard["filter_stats"].values()) == 1, shard
    # the last heartbeat already counts every shard's verdicts (a run cut short still reports them)
    assert last["kept_in_shards"] == sum(s["frame_count"] for s in shards), last
    assert last["kept_in_shards"] + sum(last["dropped_in_shards"].values()) == 5, last
    reader = DatasetReader(tmp_path)
    assert reader.num_frames("train_train") == sum(s["frame_count"] for s in shards if s["task_id"].startswith("train_train"))


def test_dataset_info_reads_out_the_audit(reference):
    from data_manifest.validate import info

    text = info(reference)
    audit = json.loads((reference / "manifest.json").read_text())["audit"]
    assert f"vertex error max median {audit['max_mm']['median']:.2f}" in text, text
    assert f"{audit['simulation']['target_frames']} target frames" in text and "explosions recovered" in text, text


def test_the_manifest_is_saved_after_each_batch_not_after_each_shard(tmp_path, monkeypatch):
    """Saving the whole manifest after every shard made a run quadratic in its shard count; within
    a batch it is saved at most every save_every_s, and always when a batch ends (its shards are
    listed before the next batch starts)."""
    from data_manifest.manifest import Manifest
    from pipelines.generate_dataset import generate

    listed: list[int] = []
    save = Manifest.save

    def spy(self, *args, **kwargs):
        listed.append(len(self.shards))
        return save(self, *args, **kwargs)

    monkeypatch.setattr(Manifest, "save", spy)
    manifest = generate(_with(**NO_AUDIT), tmp_path, progress=False, log=lambda m: None, save_every_s=1e9)
    # 4 tasks of 2 pairs in one world: a batch per pair (its train and test tasks one after the other),
    # one save per batch, then the finished manifest
    assert listed == [2, 4, 4], listed
    assert len(manifest.shards) == 4 and validate_dataset(tmp_path).ok


def test_max_batches_stops_after_the_first_batches_and_the_rest_resumes(reference, tmp_path):
    """``max_batches`` (benchmarks time one GPU on part of a plan): the first batch's shards are
    those of the whole run, listed in a manifest that says the rest is pending, and the same
    command without it finishes the dataset as an uninterrupted run would."""
    from pipelines.generate_dataset import generate

    with pytest.raises(ValueError, match="max_batches must be an integer >= 1"):
        generate(_with(**NO_AUDIT), tmp_path / "bad", progress=False, log=lambda m: None, max_batches=0)
    out = tmp_path / "part"
    whole = _shard_hashes(reference)
    manifest = generate(_with(**NO_AUDIT), out, progress=False, log=lambda m: None, max_batches=1)
    part = _shard_hashes(out)
    # one world: a batch per pair, its train and test tasks (4 tasks, 2 batches)
    assert len(part) == 2 and all(whole[t] == h for t, h in part.items()), (part, whole)
    assert manifest.audit["simulation"]["kept_frames"] == sum(s["frame_count"] for s in manifest.shards)
    assert [e.kind for e in validate_dataset(out).errors] == ["pending"] * 2
    lines: list[str] = []
    generate(_with(**NO_AUDIT), out, progress=False, log=lines.append)
    assert any("resuming: 2 of 4" in m for m in lines), lines
    assert _shard_hashes(out) == whole


def test_a_worker_context_takes_the_drivers_plan_and_template(reference, monkeypatch):
    """A Ray worker builds its context with the driver's plan and template (``prepared``) instead
    of planning again; everything else it rebuilds, the garments from the dataset's cache."""
    import pipelines.dataset_plan as dataset_plan
    import pipelines.generate_dataset as gd
    import simulate.garment.templates as templates

    spec = gd.validate_spec(_with())
    monkeypatch.setattr(gd, "_CONTEXTS", {})
    driver = gd.build_context(spec, reference, log=lambda m: None)
    monkeypatch.setattr(gd, "_CONTEXTS", {})

    def refuse(*args, **kwargs):
        raise AssertionError("planned again")

    monkeypatch.setattr(dataset_plan, "plan_dataset", refuse)
    monkeypatch.setattr(templates, "make_template", refuse)
    worker = gd.build_context(spec, reference, log=lambda m: None, prepared=driver.prepared)
    assert worker.plan is driver.plan and worker.template is driver.template
    np.testing.assert_array_equal(worker.style_start, driver.style_start)


def _cuda_available() -> bool:
    import warp as wp

    wp.init()
    return wp.get_cuda_device_count() > 0


@pytest.mark.skipif(not _cuda_available(), reason="needs a CUDA device")
def test_two_cuda_runs_write_identical_shards(tmp_path):
    """Same spec, same device, two runs: the same shards byte for byte. (On 4 H100s a Ray run and
    a local run of the t-shirt spec kept the same frames but differed at float16 rounding in 181 of
    500 shards, docs/scale-out.md; this is the smallest run that should show such a difference.)"""
    from pipelines.generate_dataset import generate

    spec = _with(**NO_AUDIT, simulation__device="cuda", simulation__worlds=2)
    for name in ("a", "b"):
        generate(spec, tmp_path / name, progress=False, log=lambda m: None)
    assert _shard_hashes(tmp_path / "a") == _shard_hashes(tmp_path / "b")


@pytest.mark.skipif(not _cuda_available(), reason="needs a CUDA device")
def test_cuda_run_from_cached_garments_and_a_prepared_plan_writes_identical_shards(tmp_path):
    """A Ray worker differs from a local run in two ways: its garments come from the run's cache
    and its plan and template from the driver (``prepared``). Each alone, on one device, must give
    the local run's shards byte for byte (on 2 H200s, 76 of 558 shards of a Ray run differed from
    the local run's at float16 rounding, docs/scale-out.md; this tells the two causes apart)."""
    import shutil

    from pipelines import generate_dataset as gd

    spec = _with(**NO_AUDIT, simulation__device="cuda", simulation__worlds=2)
    gd.generate(spec, tmp_path / "fresh", progress=False, log=lambda m: None)
    shutil.copytree(tmp_path / "fresh" / "cache", tmp_path / "cached" / "cache")
    gd._CONTEXTS.clear()
    gd.generate(spec, tmp_path / "cached", progress=False, log=lambda m: None)
    assert _shard_hashes(tmp_path / "cached") == _shard_hashes(tmp_path / "fresh"), "garments from the cache"
    prepared = next(iter(gd._CONTEXTS.values())).prepared
    gd._CONTEXTS.clear()
    out = tmp_path / "prepared"
    shutil.copytree(tmp_path / "fresh" / "cache", out / "cache")
    # the context generate() then takes (keyed by spec and device), built as a Ray worker builds it
    gd.build_context(gd.validate_spec(dict(spec)), out, device=None, log=lambda m: None, prepared=prepared)
    gd.generate(spec, out, progress=False, log=lambda m: None)
    assert _shard_hashes(out) == _shard_hashes(tmp_path / "fresh"), "the driver's plan and template"


@pytest.mark.skipif(not _cuda_available(), reason="needs a CUDA device")
def test_a_ray_gpu_worker_runs_batch_after_batch(tmp_path, monkeypatch):
    """One GPU, two batches: one worker process runs both (Ray's default for a GPU task is a new
    process per call), and every shard keeps the frames of the local run."""
    pytest.importorskip("ray")
    from pipelines.generate_dataset import generate

    spec = _with(**NO_AUDIT, simulation__device="cuda", simulation__worlds=1, simulation__batches=2)
    local = generate(spec, tmp_path / "local", progress=False, log=lambda m: None)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")  # the Ray started for the run sees one GPU
    manifest = generate(spec, tmp_path / "ray", executor="ray", ray_cpus=2, progress=False, log=lambda m: None)
    ray = manifest.audit["simulation"]["ray"]
    assert ray["workers"] == 1 and ray["gpus"] == 1 and len(ray["batch_done_s"]) == 2, ray
    kept = {s["task_id"]: s["frame_count"] for s in manifest.shards}
    assert kept == {s["task_id"]: s["frame_count"] for s in local.shards}


def test_plan_batches_deals_pairs_evenly_over_the_requested_batches():
    """``simulation.batches``: every task is in exactly one batch, no batch has more pairs than
    worlds, the plan does not depend on the task order, and the default (1) keeps the consecutive
    batches the worlds need. With no more pairs than worlds every pair's tasks are dealt over all
    batches (target poses within one task of each other; equal tasks: each pair's count per batch
    within one), else pairs stay whole (target poses within the largest pair's)."""
    from types import SimpleNamespace

    from pipelines.generate_dataset import plan_batches

    rng = np.random.default_rng(3)
    tasks = []
    for pair in range(11):
        for k in range(int(rng.integers(1, 4))):
            tasks.append(SimpleNamespace(task_id=f"p{pair}-t{k}", garment_index=pair % 3, shape=np.full(2, pair // 3, np.float32),
                                         poses=[0] * int(rng.integers(1, 30))))
    pair_of = {t.task_id: (t.garment_index, float(t.shape[0])) for t in tasks}
    size_of = {t.task_id: len(t.poses) for t in tasks}
    pair_sizes: dict = {}
    for t in tasks:
        pair_sizes[pair_of[t.task_id]] = pair_sizes.get(pair_of[t.task_id], 0) + len(t.poses)
    for worlds, batches in ((64, 4), (3, 4), (64, 11), (64, 50)):
        plan = plan_batches(tasks, worlds, batches)
        whole_pairs = len(pair_sizes) > worlds
        expected = min(11, max(batches, -(-11 // worlds))) if whole_pairs else min(batches, len(tasks))
        assert len(plan) == expected, (worlds, batches, len(plan))
        ids = [i for b in plan for i in b]
        assert sorted(ids) == sorted(t.task_id for t in tasks)
        owners = {}
        for n, b in enumerate(plan):
            pairs = {pair_of[i] for i in b}
            assert len(pairs) <= worlds
            if whole_pairs:
                for p in pairs:
                    assert owners.setdefault(p, n) == n, "a pair is split over batches"
        loads = [sum(size_of[i] for i in b) for b in plan]
        assert max(loads) - min(loads) <= (max(pair_sizes.values()) if whole_pairs else max(size_of.values()))
        assert plan == plan_batches(list(reversed(tasks)), worlds, batches), "the plan depends on the task order"
    equal = [SimpleNamespace(task_id=f"p{pair}-c{k:02d}", garment_index=pair, shape=np.zeros(2, np.float32), poses=[0] * 30)
             for pair in range(5) for k in range(9)]
    for b in plan_batches(equal, 256, 4):
        assert b == sorted(b), "a batch lists its tasks pair by pair"
    counts = np.array([[sum(i.startswith(f"p{pair}-") for i in b) for b in plan_batches(equal, 256, 4)]
                       for pair in range(5)])
    assert (counts.max(1) - counts.min(1) <= 1).all(), counts
    one = plan_batches(tasks, 4, 1)
    assert len(one) == 3 and [len({pair_of[i] for i in b}) for b in one] == [4, 4, 3]
