"""collision_aware over two gloo ranks on the CPU (``torchrun --nproc-per-node 2 -m pipelines.cli
train collision-aware``): the ranks project disjoint shares of the training shards, each writes
its shards' cache files, and every rank reads the others' back before the VAE trains.

A projection written under a wrong shard's name, a shard projected by no rank, or a rank that
trains on a stale or empty canonical array would pass a run that merely finishes; the test
recomputes every cached projection in one process from the run's own fields and SDF and asserts
each file holds its own shard's result, and that each rank's VAE trained on all of them.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

SHARDS = 3  # over 2 ranks: 2 + 1, so the ranks' shares are unequal


def _rank(rank: int, world: int, port: int, data: str, run: str, config: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank),
                      WORLD_SIZE=str(world))
    torch.set_num_threads(1)
    import learn.collision_aware.train as stages
    from pipelines.cli import main

    train_vae = stages.train_vae

    def keeping_canonical(canonical, *args, **kwargs):  # what this rank's VAE trains on
        np.save(Path(run, f"canonical{rank}.npy"), canonical)
        return train_vae(canonical, *args, **kwargs)

    stages.train_vae = keeping_canonical

    code = main(["train", "collision-aware", "--data", data, "--out", run, "--config", config, "--epochs", "2",
                 "--device", "cpu", "--no-progress"])
    Path(run, f"rank{rank}.rc").write_text(str(code))


def _stage(module: torch.nn.Module, path: Path) -> torch.nn.Module:
    from learn.tailornet.train import load_checkpoint

    module.load_state_dict(load_checkpoint(path, map_location="cpu")["model_state"])
    return module.eval()


def test_two_ranks_project_their_own_shards_and_share_them(tmp_path, anny_body, spawn_ranks):
    import yaml
    from collision_aware_data import write_band_dataset, write_tiny_config

    from learn.collision_aware.canonicalize import ProjectionSettings, project_split
    from learn.collision_aware.fields import DiffusedBody
    from learn.collision_aware.sdf import sdf_from_config
    from learn.data import DrapeDataset
    from learn.tailornet.train import frame_arrays_from_dataset, load_checkpoint

    data, run = tmp_path / "data", tmp_path / "run"
    write_band_dataset(data, anny_body, splits={"train": SHARDS, "test_test": 1}, frames_per_task=2)
    config = write_tiny_config(tmp_path / "tiny.yaml")
    tiny = yaml.safe_load(Path(config).read_text())
    tiny["sdf"]["kind"] = "mlp"  # the SDF network trains data-parallel over the ranks too
    Path(config).write_text(yaml.safe_dump(tiny))
    run.mkdir()
    spawn_ranks(_rank, str(data), str(run), config, timeout_s=300.0, what="the 2-rank collision_aware training")
    assert [(run / f"rank{r}.rc").read_text() for r in range(2)] == ["0", "0"]
    assert (run / "collision_aware_model.pt").is_file() and (run / "projection.json").is_file()
    cached = sorted((data / "cache" / "canonical").glob("*.npy"))
    assert len(cached) == SHARDS, f"expected one cached projection per training shard, got {cached}"

    # every shard again in one process, from the run's fields and SDF, into a fresh cache
    fields = _stage(DiffusedBody(**load_checkpoint(run / "fields.pt")["model_config"]).use_body(anny_body),
                    run / "fields.pt")
    sdf = _stage(sdf_from_config(load_checkpoint(run / "sdf.pt")["model_config"]), run / "sdf.pt")
    with np.load(run / "template.npz") as loaded:
        template = {k: loaded[k] for k in loaded.files}
    dataset = DrapeDataset(data, "train", frequencies=False)
    frames = frame_arrays_from_dataset(dataset)
    fresh = tmp_path / "fresh"
    one, _ = project_split(dataset.reader, "train", frames, body=anny_body, fields=fields, sdf=sdf, template=template,
                           settings=ProjectionSettings(steps=tiny["projection"]["steps"]), cache_dir=fresh)
    assert sorted(p.name for p in fresh.glob("*.npy")) == [p.name for p in cached], \
        "the ranks' cache files are not named after the run's fields, SDF and shards"
    for path in cached:
        ranks, alone = np.load(path), np.load(fresh / path.name)
        assert ranks.shape == alone.shape
        # one process batches the 3 shards together, the ranks 2 and 1: float32 rounding apart
        assert np.abs(ranks - alone).max() < 1e-5, (path.name, float(np.abs(ranks - alone).max()))
    # and the shards really differ, so a file holding another shard's frames would fail above
    arrays = [np.load(p) for p in cached]
    assert min(np.abs(a[0] - b[0]).max() for i, a in enumerate(arrays) for b in arrays[i + 1:]) > 1e-3
    # each rank trained its VAE on every shard's projection: its own and the other rank's
    for r in range(2):
        seen = np.load(run / f"canonical{r}.npy")
        assert seen.shape == one.shape and np.abs(seen - one).max() < 1e-5, (r, float(np.abs(seen - one).max()))
