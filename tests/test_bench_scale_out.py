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
