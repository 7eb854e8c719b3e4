"""learn.data: split tensors match the shards; the low/high-frequency split is cached per shard."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from data_manifest.reader import DatasetReader
from data_manifest.synthetic import write_synthetic_dataset
from learn.common.smoothing import laplacian_smooth
from learn.data import ITERATIONS, SMOOTHNESS, DrapeDataset


def test_dataset_matches_reader_and_caches_low_frequency(tmp_path):
    write_synthetic_dataset(tmp_path, splits={"train": 2, "test": 1}, frames_per_task=3)
    ds = DrapeDataset(tmp_path, "train")
    arrays = DatasetReader(tmp_path).load_split("train")
    assert len(ds) == 6
    np.testing.assert_array_equal(ds.displacements.numpy(), arrays["unposed_displacements"])
    np.testing.assert_array_equal(ds.pose.numpy(), arrays["pose"])
    item = ds[4]
    torch.testing.assert_close(item["low_frequency"] + item["high_frequency"], item["displacements"])
    expected = laplacian_smooth(torch.from_numpy(arrays["unposed_displacements"]), ds.template["faces"],
                                smoothness=SMOOTHNESS, iterations=ITERATIONS)
    torch.testing.assert_close(ds.low_frequency, expected.float(), atol=1e-6, rtol=0)
    cached = sorted((tmp_path / "cache" / "low_frequency").glob("*.npy"))
    assert len(cached) == 2, "one cache file per shard"
    stamp = [p.stat().st_mtime_ns for p in cached]
    DrapeDataset(tmp_path, "train")
    assert [p.stat().st_mtime_ns for p in cached] == stamp, "second load must reuse the cache"
    assert ds.pair.unique().numel() == 2


def test_unknown_split_lists_available(tmp_path):
    write_synthetic_dataset(tmp_path)
    with pytest.raises(ValueError, match="available splits|this dataset has"):
        DrapeDataset(tmp_path, "valid")
