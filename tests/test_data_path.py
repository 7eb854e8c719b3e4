"""The shared data path: process-parallel split reads equal the reader's; the batched, cached
low-frequency split equals the per-shard function; the streaming dataset deals every frame
exactly once over ranks and workers, reproducibly, and opens no HDF5 file before forking."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from data_manifest.parallel_read import load_split_parallel
from data_manifest.reader import DatasetReader
from data_manifest.synthetic import write_synthetic_dataset
from learn.common.smoothing import LaplacianSmoother
from learn.data import ITERATIONS, SMOOTHNESS, DrapeDataset, low_frequency_for_split, low_frequency_for_task
from learn.streaming import StreamingDrapeDataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    write_synthetic_dataset(root, splits={"train": 5, "test": 1}, frames_per_task=3, seed=3)
    return root


def _open_files() -> int:
    return h5py.h5f.get_obj_count(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_FILE)


def test_parallel_read_equals_the_reader(dataset):
    expected = DatasetReader(dataset).load_split("train")
    got = load_split_parallel(dataset, "train", workers=2, min_parallel_bytes=0)
    assert sorted(got) == sorted(expected)
    for key in expected:
        assert got[key].dtype == expected[key].dtype, key
        np.testing.assert_array_equal(got[key], expected[key], err_msg=key)
    with pytest.raises(ValueError, match="workers must be an integer >= 1"):
        load_split_parallel(dataset, "train", workers=0)
    with pytest.raises(ValueError, match="available splits: test, train"):
        load_split_parallel(dataset, "val", workers=2, min_parallel_bytes=0)


def test_a_read_of_some_per_vertex_arrays_equals_the_whole_read_without_the_others(dataset):
    """``per_vertex`` leaves the unnamed (N, V, 3) arrays on disk and changes nothing else, in this
    process and in the pool; ``DrapeDataset(posed=False)`` (TailorNet's and the baseline's
    training) reads the displacements alone; a name that is no per-vertex array is refused."""
    whole = DatasetReader(dataset).load_split("train")
    assert "posed_vertices" in whole and "unposed_displacements" in whole
    for workers in (1, 2):
        got = load_split_parallel(dataset, "train", workers=workers, min_parallel_bytes=0,
                                  per_vertex=("unposed_displacements",))
        assert sorted(got) == sorted(k for k in whole if k not in ("posed_vertices", "velocities")), workers
        for key, value in got.items():
            np.testing.assert_array_equal(value, whole[key], err_msg=key)
    for bad in (("posed",), "posed_vertices"):
        with pytest.raises(ValueError, match="per_vertex must name arrays among posed_vertices"):
            load_split_parallel(dataset, "train", workers=2, min_parallel_bytes=0, per_vertex=bad)
    lean, full = DrapeDataset(dataset, "train", workers=1, posed=False), DrapeDataset(dataset, "train", workers=1)
    assert lean.posed_vertices is None and full.posed_vertices is not None
    assert torch.equal(lean.displacements, full.displacements) and torch.equal(lean.low_frequency, full.low_frequency)
    assert "posed_vertices" not in lean[0] and torch.equal(full[0]["posed_vertices"], full.posed_vertices[0])


def test_parallel_read_checks_integrity(dataset, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("cache"))
    shard = copy / "shards" / "train-002.h5"
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    from data_manifest.schema import CorruptShardError

    with pytest.raises(CorruptShardError, match="train-002.h5' of task 'train-002' has sha256"):
        load_split_parallel(copy, "train", workers=2, min_parallel_bytes=0)


def test_batched_cached_low_frequency_equals_per_shard_function(dataset, tmp_path):
    """Float tolerance: 1e-7 m (float32 rounding of one sparse product order against another;
    the displacements are ~1 cm)."""
    reader = DatasetReader(dataset)
    arrays = reader.load_split("train")
    smoother = LaplacianSmoother(reader.template["faces"], arrays["unposed_displacements"].shape[1],
                                 smoothness=SMOOTHNESS, iterations=ITERATIONS)
    old = np.concatenate([low_frequency_for_task(reader, e["task_id"], smoother, cache_dir=tmp_path / "old")
                          for e in reader.shard_entries if "train" in e["splits"]])
    # half the shards cached, half fresh: the batch gathers rows from non-adjacent shards
    cache = tmp_path / "new"
    for e in reader.shard_entries[1::2]:
        if "train" in e["splits"]:
            low_frequency_for_task(reader, e["task_id"], smoother, cache_dir=cache)
    fresh = low_frequency_for_split(reader, "train", arrays["unposed_displacements"], smoother, cache_dir=cache)
    assert len(list(cache.glob("*.npy"))) == 5
    stamps = {p: p.stat().st_mtime_ns for p in cache.glob("*.npy")}
    cached = low_frequency_for_split(reader, "train", arrays["unposed_displacements"], smoother, cache_dir=cache)
    assert {p: p.stat().st_mtime_ns for p in cache.glob("*.npy")} == stamps, "the second call reads the cache"
    np.testing.assert_allclose(fresh, old, atol=1e-7, rtol=0)
    np.testing.assert_array_equal(cached, fresh)
    assert np.abs(old).max() > 1e-3, "the comparison is not between zeros"


def _frames_of_worker(dataset: StreamingDrapeDataset, worker: int, num_workers: int) -> list[int]:
    """Frames ``dataset`` yields in ``worker`` of a DataLoader with ``num_workers`` workers."""
    from torch.utils.data._utils import worker as worker_module

    worker_module._worker_info = worker_module.WorkerInfo(id=worker, num_workers=num_workers, seed=0, dataset=dataset)
    try:
        return [int(item["frame"]) for item in dataset]
    finally:
        worker_module._worker_info = None


def test_streaming_deals_every_frame_once_over_ranks_and_workers(dataset):
    def factory(rank, world):
        return StreamingDrapeDataset(dataset, "train", shuffle=True, seed=7, rank=rank, world_size=world)

    seen = [frame for rank in range(2) for worker in range(2) for frame in _frames_of_worker(factory(rank, 2), worker, 2)]
    assert sorted(seen) == list(range(15)), "each of the 15 frames exactly once over 2 ranks x 2 workers"
    order = [int(item["frame"]) for item in factory(0, 1)]
    assert order == [int(item["frame"]) for item in factory(0, 1)], "same seed, same order"
    other = StreamingDrapeDataset(dataset, "train", shuffle=True, seed=7)
    other.set_epoch(1)
    assert sorted(order) == list(range(15)) and [int(i["frame"]) for i in other] != order, "epochs reshuffle"
    assert order != list(range(15))


def test_streaming_items_equal_drape_dataset_in_forked_workers(dataset, tmp_path):
    cache = tmp_path / "low"
    reference = DrapeDataset(dataset, "train", cache_dir=cache)
    reference.reader.close()
    before = _open_files()
    stream = StreamingDrapeDataset(dataset, "train", frequencies=True, cache_dir=cache, shuffle=True, seed=1)
    loader = torch.utils.data.DataLoader(stream, batch_size=None, num_workers=2,
                                         multiprocessing_context="fork")
    items = list(loader)
    assert _open_files() == before and not stream.reader._handles, "no HDF5 file opened in the parent"
    assert sorted(int(i["frame"]) for i in items) == list(range(len(reference)))
    for item in items:
        expected = reference[int(item["frame"])]
        assert set(item) == set(expected) | {"frame"}
        for key, value in expected.items():
            torch.testing.assert_close(item[key], value, atol=0, rtol=0, msg=key)


def test_streaming_bad_arguments(dataset):
    with pytest.raises(ValueError, match="rank must be < world_size=2 \\(got 2\\)"):
        StreamingDrapeDataset(dataset, "train", rank=2, world_size=2)
    with pytest.raises(ValueError, match="world_size must be an integer >= 1"):
        StreamingDrapeDataset(dataset, "train", rank=0, world_size=0)
    with pytest.raises(ValueError, match="available splits"):
        StreamingDrapeDataset(dataset, "valid")
