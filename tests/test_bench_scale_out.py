"""bench/bench_scale_out.py: the 1-vs-N generation ratio against a Ray run made before."""
from __future__ import annotations

import json

import pytest


def _dataset(path, spec_sha, seconds, kept, shards, ray=None):
    path.mkdir(parents=True)
    simulation = {"seconds": seconds, "target_frames": 2 * kept, "kept_frames": kept, "device": "cuda:0"}
    if ray is not None:
        simulation["ray"] = ray
    manifest = {"spec_sha256": spec_sha, "spec": {"simulation": {"batches": 4}},
                "shards": [{"task_id": t, "sha256": sha, "frame_count": n} for t, (sha, n) in shards.items()],
                "audit": {"simulation": simulation}}
    (path / "manifest.json").write_text(json.dumps(manifest))
    return path


def test_ray_dataset_made_before_gives_the_ratio_on_the_shared_tasks(tmp_path, load_bench):
    bench = load_bench("bench_scale_out")
    local = _dataset(tmp_path / "local", "s", 100.0, 50, {"a": ("x", 5), "b": ("y", 7)})
    ray = _dataset(tmp_path / "ray4", "s", 120.0, 210, {"a": ("x", 5), "b": ("z", 7), "c": ("w", 3)},
                   ray={"workers": 4, "nodes": 1, "gpus": 4})
    rate = 50 / 100.0
    result = bench.ray_from_dataset(ray, local, {"kept_frames_per_s": rate})
    run = result[4]
    assert run["kept_frames_per_s"] == 1.75 and run["speedup"] == 3.5
    assert (run["shards_compared"], run["shards_identical"], run["kept_frames_equal"]) == (2, 1, True)
    assert run["batches"] == 4 and run["gpus"] == 4


def test_ray_dataset_of_another_spec_or_not_of_ray_is_refused(tmp_path, load_bench):
    bench = load_bench("bench_scale_out")
    local = _dataset(tmp_path / "local", "s", 100.0, 50, {})
    other = _dataset(tmp_path / "other", "t", 100.0, 50, {}, ray={"workers": 4, "nodes": 1, "gpus": 4})
    with pytest.raises(SystemExit, match="is not the local run's"):
        bench.ray_from_dataset(other, local, {"kept_frames_per_s": 0.5})
    plain = _dataset(tmp_path / "plain", "s", 100.0, 50, {})
    with pytest.raises(SystemExit, match="records no Ray run"):
        bench.ray_from_dataset(plain, local, {"kept_frames_per_s": 0.5})


def test_world_sizes_pack_side_by_side_on_disjoint_gpus(load_bench):
    bench = load_bench("bench_scale_out")
    assert bench.pack_world_sizes([4, 1, 2], 4) == [[(1, 0), (2, 1)], [(4, 0)]]
    assert bench.pack_world_sizes([1, 2], 2) == [[(1, 0)], [(2, 0)]]
    assert bench.pack_world_sizes([1, 2, 4], 8) == [[(1, 0), (2, 1), (4, 3)]]
    assert bench.pack_world_sizes([1, 8], 4) == [[(1, 0)], [(8, 0)]]


def test_packed_training_runs_share_no_gpu_and_report_each_stage(tmp_path, load_bench, monkeypatch):
    """bench_train with --pack: the world sizes 1 and 2 train at the same time on GPUs 0 and 1-2,
    4 after them on 0-3; each run's stage epoch seconds come from its loss logs (the first epoch
    left out)."""
    import argparse
    import sys

    bench = load_bench("bench_scale_out")
    fake = tmp_path / "fake_train.py"
    fake.write_text(
        "import json, os, sys, time\n"
        "from pathlib import Path\n"
        "run, world = Path(sys.argv[1]), int(sys.argv[2])\n"
        "run.mkdir(parents=True)\n"
        "start = time.time(); time.sleep(1.0)\n"
        "(run / 'hf_loss.csv').write_text('epoch,train_l1,seconds\\n0,1,9.0\\n1,1,0.5\\n2,1,0.7\\n')\n"
        "(run / 'lf_loss.csv').write_text('epoch,train_l1,seconds\\n0,1,2.0\\n')\n"
        "(run / 'run.json').write_text(json.dumps({'seconds': 10.0 / world, 'start': start, 'end': time.time(),\n"
        "    'visible': os.environ.get('CUDA_VISIBLE_DEVICES')}))\n")
    monkeypatch.setattr(bench, "_train_command",
                        lambda args, data, run, world: [sys.executable, str(fake), str(run), str(world)])
    args = argparse.Namespace(learner="tailornet", gpus=[2, 4], processes=[5], pack=True, host_gpus=4,
                              train_device="cuda", out=tmp_path / "out", epochs=None, config=None)
    args.out.mkdir()
    result = bench.bench_train(args, tmp_path)
    info = {w: __import__("json").loads((args.out / f"train-w{w}" / "run.json").read_text()) for w in (1, 2, 4, 5)}
    assert [info[w]["visible"] for w in (1, 2, 4, 5)] == ["0", "1,2", "0,1,2,3", "0,1,2,3"]
    assert info[1]["start"] < info[2]["end"] and info[2]["start"] < info[1]["end"], "1 and 2 side by side"
    assert info[4]["start"] >= max(info[1]["end"], info[2]["end"]), "4 after both"
    assert info[5]["start"] >= info[4]["end"], "5 processes on the 4 GPUs after 4"
    runs = result["world_sizes"]
    assert runs[1]["stage_epoch_s"] == {"hf": 0.6, "lf": 2.0} and runs[1]["beside"] == [2] and runs[4]["beside"] == []
    assert result["speedup_of"] == "run_s" and result["speedup"] == {1: 1.0, 2: 2.0, 4: 4.0, 5: 5.0}


def test_more_processes_than_gpus_only_for_tailornet(load_bench, capsys):
    bench = load_bench("bench_scale_out")
    with pytest.raises(SystemExit):
        bench.main(["--device", "cpu", "--skip-generate", "--gpus", "2", "--processes", "3", "--learner", "baseline"])
    assert "--processes is for --learner tailornet" in capsys.readouterr().err
