"""bench/bench_pose_clearance.py: its rank correlation against scipy's, and its dataset reading."""
from __future__ import annotations

import numpy as np


def test_rank_correlation_matches_scipy_with_ties(load_bench):
    from scipy.stats import spearmanr

    rng = np.random.default_rng(4)
    clearance = rng.uniform(0, 0.05, 200)
    kept = (clearance + rng.normal(0, 0.01, 200)) > 0.025  # a binary verdict: many ties
    bench = load_bench("bench_pose_clearance")
    assert abs(bench.rank_correlation(clearance, kept) - spearmanr(clearance, kept).correlation) < 1e-12
    assert bench.rank_correlation(clearance, kept) > 0.5
    assert np.isnan(bench.rank_correlation(clearance, np.ones(200)))


def test_dataset_verdicts_read_kept_and_logged_dropped_frames(tmp_path, load_bench):
    from data_manifest.manifest import Manifest, collect_provenance
    from data_manifest.schema import template_sha256
    from data_manifest.shard import ShardWriter, shard_path
    from data_manifest.synthetic import synthetic_frame, tube_template

    rng = np.random.default_rng(0)
    template = tube_template()
    manifest = Manifest.create(tmp_path, name="unit", spec={"name": "unit"}, template_sha256=template_sha256(template),
                               precision="float32", provenance=collect_provenance(device="cpu", seeds=[0]),
                               splits={"train": ["a"]})
    task = {"task_id": "a", "garment": "tube", "splits": ["train"], "seed": 0, "shape": np.zeros(4), "style": np.zeros(2)}
    frames = [synthetic_frame(template, rng, translation_m=np.zeros(3)) for _ in range(3)]
    with ShardWriter(shard_path(tmp_path, "a"), template=template, task=task) as writer:
        writer.write_frame(**frames[0], frame_index=0)
        writer.record_dropped("self_intersection", frame_index=1, pose=frames[1]["pose"])
        writer.write_frame(**frames[2], frame_index=2)
    manifest.add_shard(writer.record)
    manifest.save()
    poses, verdicts = load_bench("bench_pose_clearance").dataset_verdicts(tmp_path)
    assert verdicts.tolist() == ["kept", "kept", "self_intersection"]
    np.testing.assert_allclose(poses, np.stack([frames[k]["pose"] for k in (0, 2, 1)]), rtol=0, atol=1e-6)
