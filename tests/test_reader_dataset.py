"""DatasetReader: returns exactly what was written (float32) or within the float16 bound,
by split; random access agrees with load_split; clear errors; fork-safe in DataLoader workers."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from data_manifest.reader import DatasetReader
from data_manifest.schema import FLOAT16_ERROR_BOUND_M, CorruptShardError, MissingShardError
from data_manifest.shard import ShardWriter, shard_path
from data_manifest.manifest import Manifest, collect_provenance
from data_manifest.schema import template_sha256
from data_manifest.synthetic import synthetic_frame, tube_template

FLOAT16_BODY_TOL_M = 2.0**-12
"""Reader float16 tolerance [m] (0.244 mm): the synthetic garments stay within 1 m of their origin."""


def build(root, precision: str) -> dict[str, dict[str, list]]:
    """Write 3 tasks (train: 2, test: 1) and return what was written, by split."""
    rng = np.random.default_rng(42)
    template = tube_template()
    manifest = Manifest.create(root, name="reader-test", spec={"precision": precision},
                               template_sha256=template_sha256(template), precision=precision,
                               provenance=collect_provenance(device="cpu", seeds=[42]))
    written: dict[str, dict[str, list]] = {}
    # Task ids chosen so that manifest order (sorted ids) differs from writing order.
    for task_id, split, frames in (("z-train", "train", 3), ("a-test", "test", 2), ("m-train", "train", 4)):
        task = {"task_id": task_id, "garment": "tube", "splits": [split], "seed": 1,
                "shape": rng.normal(size=4), "style": rng.normal(size=2)}
        translation = np.array([rng.uniform(-3, 3), 1.0, rng.uniform(-3, 3)])
        store = written.setdefault(split, {}).setdefault(task_id, [])
        with ShardWriter(shard_path(root, task_id), template=template, task=task, precision=precision) as writer:
            for k in range(frames):
                frame = synthetic_frame(template, rng, translation_m=translation)
                writer.write_frame(**frame, frame_index=10 + 2 * k)
                store.append({**frame, "shape": task["shape"], "style": task["style"], "frame_index": 10 + 2 * k})
        manifest.add_shard(writer.record)
    manifest.save()
    return written


def expected_stack(written: dict[str, list], key: str) -> np.ndarray:
    return np.stack([frame[key] for task_id in sorted(written) for frame in written[task_id]]).astype(np.float32)


@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_reader_returns_written_arrays_by_split(tmp_path, precision):
    written = build(tmp_path, precision)
    reader = DatasetReader(tmp_path, verify=True)
    assert sorted(reader.splits) == ["test", "train"]
    assert reader.num_frames("train") == 7 and reader.num_frames("test") == 2
    np.testing.assert_array_equal(reader.index("train"), [[1, 0], [1, 1], [1, 2], [1, 3], [2, 0], [2, 1], [2, 2]])
    for key, value in tube_template().items():
        np.testing.assert_array_equal(reader.template[key], value, err_msg=f"template {key}")
    for split in ("train", "test"):
        loaded = reader.load_split(split)
        for key in ("pose", "shape", "style", "posed_vertices", "unposed_displacements", "body_translation"):
            assert loaded[key].dtype == np.float32, f"{key} dtype {loaded[key].dtype}"
            expected = expected_stack(written[split], key)
            if precision == "float32" or key in ("pose", "shape", "style", "body_translation"):
                np.testing.assert_array_equal(loaded[key], expected, err_msg=f"{split}/{key} differs")
            else:
                error = np.abs(loaded[key] - expected).max()
                assert 0 < error <= FLOAT16_BODY_TOL_M, f"{split}/{key}: float16 error {error * 1e3:.4f} mm"
        np.testing.assert_array_equal(loaded["frame_index"], expected_stack(written[split], "frame_index"))
        penetration = [f["quality"]["penetration_fraction"] for t in sorted(written[split]) for f in written[split][t]]
        np.testing.assert_array_equal(loaded["quality/penetration_fraction"], np.float32(penetration))
        # Random access agrees with the stacked arrays, row for row.
        for i in range(reader.num_frames(split)):
            item = reader.get(split, i)
            for key in ("pose", "shape", "style", "posed_vertices", "unposed_displacements"):
                np.testing.assert_array_equal(item[key], loaded[key][i], err_msg=f"get({split!r}, {i})[{key}]")
            assert item["frame_index"] == loaded["frame_index"][i]
            assert item["task_id"] == reader.shard_entries[loaded["shard_no"][i]]["task_id"]
        last = reader.get(split, -1)
        np.testing.assert_array_equal(last["posed_vertices"], loaded["posed_vertices"][-1])
    reader.close()
    assert FLOAT16_BODY_TOL_M < FLOAT16_ERROR_BOUND_M


def test_reader_errors_are_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing-dir"):
        DatasetReader(tmp_path / "missing-dir")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="manifest.json"):
        DatasetReader(tmp_path / "empty")
    build(tmp_path / "d", "float32")
    reader = DatasetReader(tmp_path / "d")
    with pytest.raises(ValueError, match="split 'val' is not in dataset .*available splits: test, train"):
        reader.load_split("val")
    with pytest.raises(IndexError, match="out of range for split 'test' with 2 frames"):
        reader.get("test", 2)
    # Truncated shard: detected by size before HDF5 is even asked.
    path = shard_path(tmp_path / "d", "m-train")
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(CorruptShardError, match="m-train"):
        DatasetReader(tmp_path / "d").get("train", 0)
    with pytest.raises(CorruptShardError, match="m-train"):
        DatasetReader(tmp_path / "d", verify=True)
    path.unlink()
    with pytest.raises(MissingShardError, match="m-train.*does not exist"):
        DatasetReader(tmp_path / "d").load_split("train")
    # Other splits stay readable.
    assert DatasetReader(tmp_path / "d").load_split("test")["posed_vertices"].shape == (2, 50, 3)


def test_reader_corrupted_chunk_fails_loudly(tmp_path):
    build(tmp_path, "float32")
    path = shard_path(tmp_path, "a-test")
    data = bytearray(path.read_bytes())
    # Flip bytes throughout the file without changing its size: whatever it hits (header,
    # chunk index or a fletcher32-checksummed chunk) must not come back as silent data.
    for offset in range(2048, len(data), 4096):
        data[offset] ^= 0x5A
    path.write_bytes(bytes(data))
    reader = DatasetReader(tmp_path)
    with pytest.raises(CorruptShardError, match="a-test"):
        reader.load_split("test")
    with pytest.raises(CorruptShardError, match="sha256"):
        DatasetReader(tmp_path, verify=True)


def test_reader_pickles_without_handles_and_works_in_forked_workers(tmp_path):
    torch = pytest.importorskip("torch")
    build(tmp_path, "float16")
    reader = DatasetReader(tmp_path, max_open_files=1)
    parent = reader.load_split("train")
    clone = pickle.loads(pickle.dumps(reader))  # open handles must not be pickled
    np.testing.assert_array_equal(clone.get("train", 3)["posed_vertices"], parent["posed_vertices"][3])

    class Frames(torch.utils.data.Dataset):
        def __len__(self):
            return reader.num_frames("train")

        def __getitem__(self, i):
            item = reader.get("train", i)
            return item["posed_vertices"], item["pose"]

    loader = torch.utils.data.DataLoader(Frames(), batch_size=2, num_workers=2, multiprocessing_context="fork")
    posed = torch.cat([batch[0] for batch in loader]).numpy()
    np.testing.assert_array_equal(posed, parent["posed_vertices"], err_msg="forked workers read different data")
    assert len(reader._handles) <= 1, "LRU of open files exceeded max_open_files"


def test_task_with_every_frame_dropped(tmp_path):
    template = tube_template()
    manifest = Manifest.create(tmp_path, name="zero", spec={}, template_sha256=template_sha256(template),
                               precision="float16", provenance=collect_provenance(device="cpu", seeds=0))
    rng = np.random.default_rng(0)
    for task_id, frames in (("a", 0), ("b", 2), ("c", 0)):
        task = {"task_id": task_id, "garment": "tube", "splits": ["train"], "seed": 0,
                "shape": np.zeros(4), "style": np.zeros(2)}
        with ShardWriter(shard_path(tmp_path, task_id), template=template, task=task, precision="float16") as writer:
            for _ in range(frames):
                writer.write_frame(**synthetic_frame(template, rng, translation_m=np.zeros(3)))
            writer.record_dropped("not_converged", 3)
        manifest.add_shard(writer.record)
    manifest.save()
    reader = DatasetReader(tmp_path, verify=True)
    assert reader.num_frames("train") == 2
    np.testing.assert_array_equal(reader.index("train"), [[1, 0], [1, 1]])
    loaded = reader.load_split("train")
    assert loaded["posed_vertices"].shape == (2, 50, 3) and loaded["pose"].shape == (2, 6)
    assert reader.load_task("a")["posed_vertices"].shape == (0, 50, 3)
    assert manifest.totals["frames_dropped"] == {"not_converged": 9}
    assert reader.dropped_frames("train")["pose"].shape == (0, 0), "counted but unlogged drops list no rows"
    from data_manifest.validate import info

    assert "position in sequence" not in info(tmp_path), "without the logs the position table would lie"


def test_reader_lists_the_logged_dropped_frames_by_split(tmp_path):
    from data_manifest.synthetic import write_synthetic_dataset

    write_synthetic_dataset(tmp_path, splits={"train": 2, "test": 1}, frames_per_task=2)
    reader = DatasetReader(tmp_path, verify=True)
    dropped = reader.dropped_frames("train")
    assert dropped["reason"].tolist() == ["nan", "nan"] and dropped["frame_index"].tolist() == [1, 1]
    assert dropped["shard_no"].tolist() == [reader.shard_no("train-000"), reader.shard_no("train-001")]
    assert dropped["pose"].shape == (2, 6) and np.abs(dropped["pose"]).max() <= 0.5
    assert len(reader.dropped_frames("test")["reason"]) == 1
    with pytest.raises(ValueError, match="split"):
        reader.dropped_frames("val")
