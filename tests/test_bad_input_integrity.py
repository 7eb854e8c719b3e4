"""Integrity on read: shards are checked against the manifest (size, sha256) before readers,
train and evaluate trust them, with digests cached per file; damaged HDF5 is a CorruptShardError
naming the shard, never a TypeError; dataset info reports missing and corrupt shards; caches go
to the user cache directory when the dataset cannot be written."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import data_manifest.integrity as integrity
from data_manifest.reader import DatasetReader
from data_manifest.schema import CorruptShardError, MissingShardError
from data_manifest.shard import shard_path
from data_manifest.synthetic import write_synthetic_dataset
from data_manifest.validate import info, validate_dataset


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    root = tmp_path_factory.mktemp("pristine")
    write_synthetic_dataset(root, splits={"train": 2, "test": 1}, frames_per_task=3)
    return root


@pytest.fixture
def dataset(pristine, tmp_path, monkeypatch):
    monkeypatch.setenv("DRAPE_CACHE_DIR", str(tmp_path / "user-cache"))
    root = tmp_path / "ds"
    shutil.copytree(pristine, root)
    return root


def flip(path: Path, offsets) -> None:
    data = bytearray(path.read_bytes())
    for offset in offsets:
        data[offset] ^= 0x5A
    path.write_bytes(bytes(data))


def test_flipped_bytes_are_refused_before_they_are_read(dataset):
    path = shard_path(dataset, "train-001")
    flip(path, [len(path.read_bytes()) // 2])  # one byte, size unchanged: HDF5 alone might not notice
    reader = DatasetReader(dataset)
    assert reader.load_split("test")["pose"].shape == (3, 6), "other splits stay readable"
    for read in (lambda: reader.load_split("train"), lambda: reader.load_task("train-001"),
                 lambda: reader.get("train", 5)):
        with pytest.raises(CorruptShardError, match=r"train-001.h5' of task 'train-001' has sha256 .* the manifest lists"):
            read()


def test_the_issue_experiment_flips_every_256th_byte_and_nothing_passes_silently(dataset):
    """One byte flipped at a time, every 256 B of a shard: with the integrity check every read is
    refused; without it (integrity=False), HDF5's own checks raise CorruptShardError or the data
    come back unchanged (fletcher32 chunks), and never anything but CorruptShardError."""
    path = shard_path(dataset, "test-000")
    original = path.read_bytes()
    expected = DatasetReader(dataset).load_task("test-000")
    silent, refused_unchecked = 0, 0
    for offset in range(0, len(original), 256):
        flip(path, [offset])
        with pytest.raises(CorruptShardError, match="test-000"):
            DatasetReader(dataset).load_task("test-000")
        try:
            got = DatasetReader(dataset, integrity=False).load_task("test-000")
        except CorruptShardError:
            refused_unchecked += 1
        else:
            silent += any(not np.array_equal(got[k], expected[k]) for k in expected)
        path.write_bytes(original)
    assert refused_unchecked > 0, "HDF5 damage is reported as CorruptShardError"
    print(f"without the integrity check: {refused_unchecked} refused, {silent} silently different "
          f"of {len(range(0, len(original), 256))} flips")


def test_digests_are_cached_per_file(dataset, monkeypatch):
    hashed: list[str] = []
    real = integrity.file_sha256
    monkeypatch.setattr(integrity, "file_sha256", lambda p: hashed.append(Path(p).name) or real(p))
    saves: list[int] = []
    save = integrity.IntegrityChecker._save
    monkeypatch.setattr(integrity.IntegrityChecker, "_save", lambda self: saves.append(1) or save(self))
    DatasetReader(dataset).load_split("train")
    assert sorted(hashed) == ["train-000.h5", "train-001.h5"]
    assert len(saves) == 1, "a split's new digests are written once, not once per shard"
    cache = json.loads((dataset / "cache" / "integrity.json").read_text())
    assert set(cache["files"]) == {"shards/train-000.h5", "shards/train-001.h5"}
    hashed.clear()
    DatasetReader(dataset).load_split("train")
    assert hashed == [], "a second read of unchanged shards hashes nothing"
    path = shard_path(dataset, "train-000")
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1_000_000))
    DatasetReader(dataset).load_split("train")
    assert hashed == ["train-000.h5"], "a touched shard is hashed again"


def test_missing_and_truncated_shards(dataset):
    shard_path(dataset, "train-000").unlink()
    path = shard_path(dataset, "test-000")
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(MissingShardError, match="train-000.*does not exist"):
        DatasetReader(dataset).load_split("train")
    with pytest.raises(CorruptShardError, match="test-000.*bytes, the manifest lists"):
        DatasetReader(dataset).load_split("test")


def test_dataset_info_reports_missing_and_corrupt_shards(dataset, capsys):
    from pipelines.cli import main

    assert main(["dataset", "info", str(dataset)]) == 0
    assert "integrity: all 3 shards match the manifest (size and sha256)" in capsys.readouterr().out
    shard_path(dataset, "train-000").unlink()
    flip(shard_path(dataset, "test-000"), [5000])
    assert main(["dataset", "info", str(dataset)]) == 1
    out = capsys.readouterr().out
    assert "integrity: 2 of 3 shards do not match the manifest (1 missing, 1 corrupt)" in out, out
    assert "missing  shard" in out and "train-000.h5" in out and "checksum shard" in out and "test-000.h5" in out, out
    text, problems = info(dataset, with_problems=True)
    assert sorted(kind for kind, _ in problems) == ["checksum", "missing"]


def test_validate_reports_damaged_hdf5_and_never_raises(dataset):
    path = shard_path(dataset, "train-001")
    original = path.read_bytes()
    kinds = set()
    for offset in range(0, min(len(original), 4096), 97):  # the superblock, headers, B-tree nodes
        flip(path, [offset])
        report = validate_dataset(dataset)
        assert not report.ok and all(problem.where.endswith("train-001.h5") for problem in report.errors), report
        kinds |= {problem.kind for problem in report.errors}
        path.write_bytes(original)
    assert "checksum" in kinds


def test_train_and_evaluate_refuse_a_corrupt_dataset_in_one_line(dataset, tmp_path, capsys):
    from pipelines.cli import main

    flip(shard_path(dataset, "test-000"), [4000])
    for args in (["train", "baseline", "--data", str(dataset), "--out", str(tmp_path / "run")],
                 ["evaluate", str(tmp_path), "--data", str(dataset)]):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "test-000.h5' of task 'test-000' has sha256" in err, err
        assert "drape dataset validate" in err


def test_read_only_dataset_keeps_its_caches_in_the_user_cache(dataset, tmp_path, monkeypatch):
    """A dataset that cannot be written (a read-only mount, another user's files): the integrity
    digests and the low-frequency cache go to $DRAPE_CACHE_DIR, nothing is written beside the data."""
    from learn.data import DrapeDataset

    before = sorted(str(p.relative_to(dataset)) for p in dataset.rglob("*"))
    if os.geteuid() != 0:
        for p in [dataset, *dataset.rglob("*")]:
            p.chmod(0o555 if p.is_dir() else 0o444)
    else:  # permission bits do not stop root: the dataset reports itself read-only
        real = integrity.directory_is_writable
        monkeypatch.setattr(integrity, "directory_is_writable",
                            lambda d: False if str(Path(d).resolve()).startswith(str(dataset.resolve())) else real(d))
    try:
        ds = DrapeDataset(dataset, "train")
        assert len(ds) == 6 and ds.low_frequency is not None
        again = DrapeDataset(dataset, "train")
        assert np.array_equal(again.low_frequency.numpy(), ds.low_frequency.numpy())
    finally:
        for p in [dataset, *dataset.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
    assert sorted(str(p.relative_to(dataset)) for p in dataset.rglob("*")) == before, "nothing written beside the data"
    user = tmp_path / "user-cache"
    assert len(list((user / "integrity").glob("*.json"))) == 1
    assert len(list((user / "low_frequency").rglob("*.npy"))) == 2, "one low-frequency cache file per shard"


def test_an_unwritable_cache_is_skipped_with_a_warning(dataset, monkeypatch):
    from learn.data import DrapeDataset

    blocked = dataset / "blocked"
    blocked.write_text("a file where the cache directory would go")
    with pytest.warns(RuntimeWarning, match="low-frequency cache not written"):
        ds = DrapeDataset(dataset, "train", cache_dir=blocked / "low")
    assert ds.low_frequency is not None and len(ds) == 6
