"""The dynamic GCVAE (seed 004's DVAE): motion frames as offsets and masks on the body mesh,
conditioned on the poses of several frames."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

torch.set_num_threads(1)

FRAMES, STRIDE = 2, 2
TINY = {"model": {"channels": [4, 4, 4, 4], "latent_size": 4, "condition_hidden": 8}}


@pytest.fixture(scope="module")
def motion(tmp_path_factory, anny_body):
    from learn.gcvae.dynamic_set import DynamicSet
    from learn.gcvae.synthetic import write_synthetic_motion_dataset

    root = write_synthetic_motion_dataset(tmp_path_factory.mktemp("motion"), anny_body, frames=5)
    return root, DynamicSet(root, frames=FRAMES, frame_stride=STRIDE, body=anny_body)


def test_context_frames_take_the_nearest_kept_frame_before_each_wanted_one() -> None:
    from learn.gcvae.dynamic_set import context_frames

    # kept frames 0, 1, 3, 4, 7 (2, 5, 6 dropped); T = 3 frames every 2
    rows = context_frames(np.array([0, 1, 3, 4, 7]), 3, 2)
    # frame 4 wants 0, 2, 4 -> rows of frames 0, 1 (nearest kept before 2), 4; frame 0 clamps to itself
    assert rows.tolist() == [[0, 0, 0], [0, 0, 1], [0, 1, 2], [0, 1, 3], [2, 3, 4]]


def test_dynamic_set_registers_each_sequence_once_and_follows_every_frame(motion, anny_body) -> None:
    from data_manifest.reader import DatasetReader
    from learn.gcvae.body_mesh import canonical_body_vertices

    root, data = motion
    assert data.types == ["tshirt", "skirt"] and data.skipped == []
    assert data.layout == {"shape": 6, "tightness": 2, "pose": 60, "frames": FRAMES, "frame_stride": STRIDE}
    assert data.condition.shape == (len(data), 6 + 2 + FRAMES * 60)
    for s in np.unique(data.sequence):
        rows = np.flatnonzero(data.sequence == s)
        assert (data.mask[rows] == data.mask[rows[0]]).all(), "one registration, one mask per sequence"
        assert data.frame_index[rows].tolist() == list(range(5))
        moved = np.abs(data.offsets[rows[1:]] - data.offsets[rows[:1]])[:, data.mask[rows[0]]].max()
        assert moved > 2e-3, "each frame's offsets follow that frame's garment"
    # the frames' garments are rebuilt: body + offsets on the masked vertices lie on the unposed garment
    with DatasetReader(root / "tshirt") as reader:
        task = reader.splits["train_train"][0]
        arrays = reader.load_task(task)
        template = reader.template
    first = np.flatnonzero((data.type == 0) & (data.split == 0))[:5]
    shape = arrays["shape"][0]
    under = canonical_body_vertices(anny_body, shape)[0][template["body_vertex_index"]]
    for t, row in enumerate(first):
        garment = under + arrays["unposed_displacements"][t]
        rebuilt = (data.body_vertices[row] + data.offsets[row])[data.mask[row]]
        from scipy.spatial import cKDTree

        assert cKDTree(garment).query(rebuilt)[0].mean() < 0.02  # within a body edge of the garment's vertices
        # condition: shape, tightness, then the poses of frames t - 2 (clamped to 0) and t
        c = data.condition[row]
        np.testing.assert_allclose(c[:6], shape)
        np.testing.assert_allclose(c[8:68], arrays["pose"][max(t - STRIDE, 0)])
        np.testing.assert_allclose(c[68:128], arrays["pose"][t])
    # skirts register on the dual topology: no inner-leg vertex inside the holes is covered
    inside = data.mesh.inner_leg & ~data.mesh.bridge_vertices()
    assert not data.mask[data.type == 1][:, inside].any() and data.mask[data.type == 1].sum(1).min() > 100


def test_dynamic_model_output_shapes_and_dependence_on_the_frames(motion) -> None:
    from learn.gcvae.hyperparameters import merged
    from learn.gcvae.train import build_model, tensors

    _, data = motion
    hyper = merged(TINY)
    torch.manual_seed(0)
    model = build_model(data, hyper["model"], data.indices("train")).eval()
    b = tensors(data, data.indices("test")[:3])
    with torch.no_grad():
        out = model(b["body"], b["offsets"], b["mask"], b["condition"], sample=False)
        n = data.mesh.vertex_count
        assert out["offsets"].shape == (3, n, 3) and out["mask_logits"].shape == (3, n)
        assert out["mu"].shape == (3, 4) and out["condition_regressed"].shape == (3, data.condition.shape[1])
        z = torch.randn(3, 4, generator=torch.Generator().manual_seed(1))
        base, _ = model.decode(z, b["condition"], b["body"])
        assert torch.equal(base, model.decode(z, b["condition"], b["body"])[0]), "same inputs, same output"
        earlier = b["condition"].clone()
        earlier[:, 8:68] += 0.3  # only the earlier frame's pose changes
        changed, _ = model.decode(z, earlier, b["body"])
        later = b["condition"].clone()
        later[:, 68:128] += 0.3  # only the current frame's pose changes
        changed_later, _ = model.decode(z, later, b["body"])
    assert (changed - base).abs().max() > 1e-5 and (changed_later - base).abs().max() > 1e-5


def test_tiny_motion_set_overfits() -> None:
    """Four sequences of four frames on a small segmented tube, each frame's garment rippling with a
    phase set by the poses of the frame and of the frame before: with both frames' poses in the
    condition (T = 2, stride 1, as the dynamic set builds it) 200 Adam steps fit the frames far
    below the mean garment's error, and the fit leans on the earlier frame's pose: giving the
    decoder another earlier pose moves its output."""
    from learn.common.mesh import mesh_edges
    from learn.gcvae.dynamic_set import context_frames
    from learn.gcvae.hyperparameters import merged
    from learn.gcvae.model import GCVAE

    from tests.test_gcvae import _overfit, _tube

    v, f = _tube(12, 16)
    edges = mesh_edges(f)
    segments = (np.arange(len(v)) // 16) // 3
    rng = np.random.default_rng(0)
    normals = v * np.array([1.0, 0.0, 1.0]) / 0.1
    mask = v[:, 1] > -0.1
    offsets, conditions = [], []
    for _ in range(4):
        poses = np.cumsum(rng.normal(0.0, 0.4, (4, 3)), 0)
        rows = context_frames(np.arange(4), 2, 1)
        for t in range(4):
            phase = poses[t, 0] + 2.0 * poses[rows[t, 0], 1]
            lift = 0.02 + 0.01 * np.sin(10 * v[:, 1] + phase)
            offsets.append(np.where(mask[:, None], normals * lift[:, None], 0.0))
            conditions.append(poses[rows[t]].reshape(-1))
    count = len(offsets)
    condition = np.asarray(conditions, np.float32)
    batch = {"body": torch.tensor(np.repeat(v[None], count, 0), dtype=torch.float32),
             "offsets": torch.tensor(np.stack(offsets), dtype=torch.float32),
             "mask": torch.tensor(np.repeat(mask[None], count, 0)), "condition": torch.tensor(condition),
             "dual": torch.zeros(count, dtype=torch.bool)}
    hyper = merged({"model": {"channels": [16, 16, 16], "pool_levels": 2, "latent_size": 4, "condition_hidden": 16}})
    torch.manual_seed(0)
    model = GCVAE(edges, v, segments, condition.shape[1], hyper["model"])
    model.fit_normalisation(batch["body"].numpy(), batch["offsets"].numpy(), batch["mask"].numpy(), condition)
    _overfit(model, batch, torch.as_tensor(f), hyper["loss"], 200)
    m = batch["mask"]
    with torch.no_grad():
        out = model(batch["body"], batch["offsets"], batch["mask"], batch["condition"], sample=False)
        err = ((model.offsets_from(out["offsets"]) - batch["offsets"]).norm(dim=-1)[m]).mean()
        other = batch["condition"].clone()
        other[:, :3] = other[torch.roll(torch.arange(count), 4), :3]  # another sequence's earlier pose
        moved, _ = model.decode(out["mu"], other, batch["body"])
        shift = ((model.offsets_from(moved) - model.offsets_from(out["offsets"])).norm(dim=-1)[m]).mean()
    mean_err = ((batch["offsets"].mean(0, keepdim=True) - batch["offsets"]).norm(dim=-1)[m]).mean()
    assert err < 0.25 * mean_err, f"reconstruction {1e3 * err:.2f} mm vs the mean garment's {1e3 * mean_err:.2f} mm"
    assert ((out["mask_logits"] > 0) == m).float().mean() > 0.97
    print(f"overfit: {1e3 * err:.2f} mm, mean garment {1e3 * mean_err:.2f} mm, shift {1e3 * shift:.2f} mm")
    assert shift > 0.5 * err, f"another earlier pose moves the output by {1e3 * shift:.2f} mm only"


def test_cli_train_dynamic_evaluate_and_the_errors(motion, tmp_path: Path, anny_body, capsys) -> None:
    from learn.gcvae.synthetic import write_synthetic_static_set
    from pipelines.cli import main

    root, data = motion
    config = tmp_path / "tiny.yaml"
    config.write_text(json.dumps({**TINY, "train": {"batch_size": 8}, "dynamic": {"frames": FRAMES,
                                                                                  "frame_stride": STRIDE}}))
    run = tmp_path / "run"
    assert main(["train", "gcvae", "--dynamic", "--data", str(root), "--out", str(run), "--epochs", "2",
                 "--config", str(config), "--no-progress"]) == 0
    info = json.loads((run / "run.json").read_text())
    assert info["dynamic"] == data.layout and info["types"] == ["tshirt", "skirt"]
    # whole sequences validate: 1 of the 4 training sequences (20 %, rounded)
    assert (info["train_samples"], info["validation_samples"]) == (15, 5)
    assert main(["evaluate", str(run), "--data", str(root)]) == 0
    printed = capsys.readouterr().out
    assert "seed Table 4" in printed and "33.2 / 0.88" in printed  # the seed's skirt, 4 frames
    report = json.loads((run / "evaluation" / "evaluation.json").read_text())
    assert report["dynamic"]["frames"] == FRAMES
    for split in ("test", "train"):
        types = report["splits"][split]["types"]
        assert set(types) == {"tshirt", "skirt"}
        for m in types.values():
            assert m["surface_mm"] > 0 and 0 <= m["mask_iou"] <= 1 and 0 <= m["normal_rad"] <= np.pi and m["kl"] >= 0
    # the errors: --dynamic on a static set, a dynamic run on a static set, sampling a dynamic run
    static = tmp_path / "set"
    write_synthetic_static_set(static, anny_body, types=("tshirt",), count=2)
    assert main(["train", "gcvae", "--dynamic", "--data", str(static), "--out", str(tmp_path / "r2")]) == 2
    err = capsys.readouterr().err
    assert "--dynamic needs a motion dataset" in err and str(static) in err and len(err.strip().splitlines()) == 1
    assert main(["evaluate", str(run), "--data", str(static)]) == 2
    assert "holds a dynamic gcvae" in capsys.readouterr().err
    assert main(["sample", str(run), "--out", str(tmp_path / "s")]) == 2
    assert "dynamic gcvae" in capsys.readouterr().err
    assert main(["train", "tailornet", "--dynamic", "--data", str(root / "tshirt"), "--out", str(tmp_path / "r3")]) == 2
    assert "--dynamic applies to gcvae only, not tailornet" in capsys.readouterr().err
