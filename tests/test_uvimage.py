"""UV-image learner (seed 001): cloth pixels, tangent frames, decoders, training, CLI.

The tiny dataset is written in the real shard format around the real low-resolution
t-shirt template on anny (1,793 vertices): each frame's garment is the template's
default-style garment skinned to a sampled upper-body pose, plus a smooth
pose-dependent bulge along the garment normal (no physics: the point is the data path
and the learner's ability to fit).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from data_manifest.manifest import Manifest, collect_provenance
from data_manifest.schema import template_sha256
from data_manifest.shard import ShardWriter, shard_path

RESOLUTION = 400
#: Round trip (encode -> 256 x 256 images -> bilinear decode) on the posed default-style
#: t-shirt with its synthetic bulge: measured 0.15 mm mean, 1.0 mm 99th percentile,
#: 7.1 mm max (hem vertices whose neighbours' offsets differ by 4 cm within 3 px).
ROUNDTRIP_MEAN_MM = 0.25
ROUNDTRIP_P99_MM = 2.0
FRAME_ATOL = 1e-5
SEED_PARAMETERS = 3_785_322
TINY_HYPER = {"image_size": 32, "padding": 2, "start_channels": 64, "batch_size": 4}


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """The tiny workloads here are faster on one thread than on two contended ones."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tshirt(anny_body):
    from learn.uvimage.garment import dataset_template, garment_template, shard_template

    sha = template_sha256(shard_template(garment_template("tshirt", RESOLUTION, anny_body)))
    template = dataset_template({"garment": {"type": "tshirt", "resolution": RESOLUTION}}, sha, anny_body)
    with pytest.raises(ValueError, match="other template code"):
        dataset_template({"garment": {"type": "tshirt", "resolution": RESOLUTION}}, "0" * 64, anny_body)
    return template


def _poses(rng: np.random.Generator, count: int) -> np.ndarray:
    from learn.uvimage.features import UPPER_BODY_JOINTS
    from simulate.body.base import POSE_JOINTS

    pose = np.zeros((count, len(POSE_JOINTS), 3), np.float32)
    for name in UPPER_BODY_JOINTS:
        pose[:, POSE_JOINTS.index(name)] = rng.uniform(-0.25, 0.25, (count, 3))
    return pose.reshape(count, -1)


def _garments(body, template, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(posed (N, V, 3), unposed displacements (N, V, 3)) [m] of the synthetic drapes."""
    from learn.common.normals import vertex_normals
    from simulate.body.kinematics import lbs

    shape = torch.as_tensor(np.tile(body.shape_default, (len(pose), 1)), dtype=torch.float32)
    posed_body = body.pose_torch(shape, torch.as_tensor(pose))
    rest = torch.as_tensor(template.vertices, dtype=torch.float32)
    n = vertex_normals(rest, template.faces)
    bulge = 0.01 * torch.sin(3.0 * torch.as_tensor(pose[:, None, 42:43]) + 8.0 * rest[None, :, 1:2])  # (N, V, 1)
    unposed = rest[None] + bulge * n[None]
    posed = lbs(unposed, torch.as_tensor(template.skinning_weights), posed_body.skinning_transforms)
    under = posed_body.rest_vertices[:, torch.as_tensor(template.body_vertex_index)]
    return posed.numpy(), (unposed - under).numpy()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, anny_body, tshirt):
    from learn.uvimage.garment import shard_template

    root = tmp_path_factory.mktemp("uvimage_data")
    rng = np.random.default_rng(0)
    template = shard_template(tshirt)
    spec = {"name": "uvtiny", "garment": {"type": "tshirt", "resolution": RESOLUTION},
            "body": {"backend": "anny", "path": None}}
    splits = {"train_train": 12, "test_test": 4}
    manifest = Manifest.create(root, name="uvtiny", spec=spec, template_sha256=template_sha256(template),
                               precision="float32", provenance=collect_provenance(device="cpu", seeds={"spec": 0}),
                               splits={s: [f"{s}-000"] for s in splits})
    for split, count in splits.items():
        pose = _poses(rng, count)
        posed, unposed = _garments(anny_body, tshirt, pose)
        task = {"task_id": f"{split}-000", "garment": "tshirt", "splits": [split], "seed": 0,
                "shape": anny_body.shape_default, "style": np.zeros(2)}
        with ShardWriter(shard_path(root, task["task_id"]), template=template, task=task) as writer:
            for i in range(count):
                writer.write_frame(posed[i], unposed[i], pose[i], {"penetration_fraction": 0.0}, frame_index=i)
            writer.timings["simulate_s"] = 1.0
        manifest.add_shard(writer.record)
    manifest.audit = {"simulation": {"seconds": 16.0, "kept_frames": 16}}
    manifest.finish()
    manifest.save()
    return root


def _layout_learner(tshirt, body, *, kind="image", size=256, padding=4, **kwargs):
    from learn.uvimage.features import UPPER_BODY_JOINTS, PoseFeatures
    from learn.uvimage.model import UVImageLearner, layout_arrays
    from simulate.garment.templates import body_joints

    rest, _ = body_joints(body, body.shape_default)
    layout = layout_arrays(tshirt, rest, body.faces, image_size=size, padding=padding)
    return UVImageLearner(layout, PoseFeatures(UPPER_BODY_JOINTS), kind=kind, image_size=size, padding=padding,
                          **kwargs).attach_body(body)


def test_encode_decode_round_trip_on_a_posed_template_drape(anny_body, tshirt):
    """Offsets -> front/back images (256 x 256 x 6, padded) -> grid_sample at each
    vertex's UV -> garment: the real default-style t-shirt on a posed body comes back."""
    learner = _layout_learner(tshirt, anny_body)
    pose = torch.as_tensor(_poses(np.random.default_rng(1), 2))
    posed, _ = _garments(anny_body, tshirt, pose.numpy())
    x = torch.as_tensor(posed)
    body = learner.pose_body(pose, torch.as_tensor(np.tile(anny_body.shape_default, (2, 1)), dtype=torch.float32))
    points, frames = learner.embedding(body.vertices)
    local = learner.embedding.to_local(x, points, frames)
    exact = learner.embedding.to_world(local, points, frames, learner.pixels.pixel_weight)
    assert (exact - x).abs().max() < 1e-5, "local frames must invert exactly"
    images = learner.pixels.to_images(local)
    assert images.shape == (2, 6, 256, 256)
    mask = learner.pixels.mask
    assert mask.shape == (2, 256, 256) and (mask & ~learner.pixels.covered).any(), "padding must extend the mask"
    assert float((images.abs().sum(1) > 0)[:, ~mask.any(0)].float().mean()) == 0.0, "nothing outside the padded mask"
    back = learner.garment(learner.pixels.sample(images), body.vertices)
    error_mm = 1000 * torch.linalg.vector_norm(back - x, dim=-1)
    assert float(error_mm.mean()) < ROUNDTRIP_MEAN_MM, f"mean round trip {float(error_mm.mean()):.3f} mm"
    assert float(torch.quantile(error_mm.flatten(), 0.99)) < ROUNDTRIP_P99_MM


def test_fields_linear_in_uv_round_trip_exactly_at_the_border(anny_body, tshirt):
    """Rasterize then sample returns the vertex values: a field linear in each panel's UV
    is reproduced at every cloth pixel, border ones included (extrapolated padding)."""
    from learn.uvimage.pixels import ClothPixels

    pixels = ClothPixels(tshirt.faces, tshirt.face_uv, tshirt.face_panel, tshirt.vertex_count)
    uv = pixels.pixel_uv
    values = torch.stack([uv[:, 0], 2 * uv[:, 1] - uv[:, 0], 0.3 + 0 * uv[:, 0]], -1)[None]  # (1, K, 3)
    got = pixels.sample(pixels.to_images(values))
    assert (got - values).abs().max() < 1e-5, float((got - values).abs().max())


def test_tangent_frames_match_the_naive_per_vertex_computation(anny_body, tshirt):
    from learn.uvimage.frames import tangent_frames_naive

    learner = _layout_learner(tshirt, anny_body, size=64, padding=2)
    pose = torch.as_tensor(_poses(np.random.default_rng(2), 1))
    body = learner.pose_body(pose, torch.as_tensor(anny_body.shape_default[None], dtype=torch.float32)).vertices
    points, frames = learner.embedding(body)
    emb = learner.embedding
    naive_points, naive_frames = tangent_frames_naive(
        body[0].numpy(), anny_body.faces, tshirt.body_face, tshirt.body_bary, emb.pixel_vertex.numpy(),
        emb.coefficients.numpy().astype(np.float64))
    assert np.abs(points[0].numpy() - naive_points).max() < FRAME_ATOL
    assert np.abs(frames[0].numpy() - naive_frames).max() < FRAME_ATOL
    gram = frames.transpose(-1, -2) @ frames
    assert (gram - torch.eye(3)).abs().max() < 1e-5 and (torch.linalg.det(frames) > 0.999).all(), "right-handed orthonormal"


def test_decoder_output_shape_and_parameter_count() -> None:
    from learn.uvimage.decoder import ImageDecoder

    torch.manual_seed(0)
    decoder = ImageDecoder(90, 6)
    assert sum(p.numel() for p in decoder.parameters()) == SEED_PARAMETERS  # seed 001: "3.79 million"
    with torch.no_grad():
        assert decoder.eval()(torch.randn(2, 90)).shape == (2, 6, 256, 256)
    with pytest.raises(ValueError, match="power of two"):
        ImageDecoder(90, 6, size=200)


def test_gradient_flows_through_the_sampler_to_the_decoder(anny_body, tshirt):
    learner = _layout_learner(tshirt, anny_body, size=32, padding=2, start_channels=32)
    pose = torch.as_tensor(_poses(np.random.default_rng(3), 2))
    shape = torch.as_tensor(np.tile(anny_body.shape_default, (2, 1)), dtype=torch.float32)
    posed = learner.posed(pose, shape, torch.zeros(2, 2))
    posed.square().sum().backward()
    grads = [p.grad for p in learner.network.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert float(learner.network.stem[0].weight.grad.abs().sum()) > 0, "no gradient reached the first layer"


@pytest.mark.parametrize("kind", ["image", "pca"])
def test_tiny_dataset_overfits(dataset, tmp_path, kind):
    """75 (image) or 270 (PCA) Adam steps on 12 frames: the training loss falls at least 4-fold."""
    from learn.uvimage.garment import uvimage_context
    from learn.uvimage.train import fit_uvimage, fit_uvimage_pca
    from data_manifest.reader import DatasetReader
    from learn.data import DrapeDataset
    from learn.tailornet.train import frame_arrays_from_dataset
    from simulate.body import load_body_model

    data = frame_arrays_from_dataset(DrapeDataset(dataset, "train_train", frequencies=False))
    context = uvimage_context(DatasetReader(dataset), load_body_model("anny"))
    if kind == "image":
        hyper = {"uvimage": {**TINY_HYPER, "epochs": 25, "checkpoint_interval_s": 1e9}}
        fit_uvimage(data, None, run_dir=tmp_path, hyperparameters=hyper, progress=False, **context)
        stage = "uvimage"
    else:
        hyper = {"uvimage_pca": {"image_size": 32, "padding": 2, "batch_size": 4, "epochs": 90,
                                 "components": 8, "checkpoint_interval_s": 1e9}}
        fit_uvimage_pca(data, None, run_dir=tmp_path, hyperparameters=hyper, progress=False, **context)
        stage = "uvimage_pca"
    losses = np.loadtxt(tmp_path / f"{stage}_loss.csv", delimiter=",", skiprows=1)[:, 1]
    assert losses[-1] < losses[0] / 4, f"{stage} loss {losses[0]:.4g} -> {losses[-1]:.4g}"
    assert (tmp_path / f"{stage}_model.pt").is_file()


def test_cli_train_evaluate_predict(dataset, tmp_path, capsys):
    from pipelines.cli import main

    config = tmp_path / "uv.yaml"
    config.write_text(json.dumps({"uvimage": TINY_HYPER}))
    run = tmp_path / "run"
    assert main(["train", "uvimage", "--data", str(dataset), "--out", str(run), "--epochs", "3", "--config", str(config),
                 "--no-progress"]) == 0
    assert main(["evaluate", str(run), "--data", str(dataset), "--renders", "0", "--postprocess-frames", "1"]) == 0
    report = json.loads((run / "evaluation" / "evaluation.json").read_text())
    metrics = report["splits"]["test_test"]["uvimage"]
    for key in ("unposed_error_mm", "posed_error_mm", "normal_error", "collision_rate", "collision_rate_postprocessed"):
        assert np.isfinite(metrics[key]), key
    assert 0.0 <= metrics["normal_error"] <= 2.0
    timing = report["timing"]["uvimage"]["cpu"]
    assert {"ms_per_frame_batch_1", "ms_per_frame_batch_32", "decoder_ms_per_frame_batch_32"} <= set(timing)
    out = tmp_path / "pred.obj"
    assert main(["predict", str(run), "--learner", "uvimage", "--style", "0,0", "--out", str(out)]) == 0
    assert out.is_file()
    assert main(["train", "nosuch", "--data", str(dataset), "--out", str(run)]) == 2
    assert "unknown learner 'nosuch'" in capsys.readouterr().err


def test_streamed_split_trains_the_same_learner_as_memory(dataset, tmp_path, anny_body):
    """Unshuffled, with the reads in this process, a streamed epoch's batches are the in-memory
    path's; the targets are computed per batch instead of in chunks of 64 frames, the same per-frame
    operations (bitwise equal parameters on this CPU; the bound leaves room for a BLAS whose
    blocking follows the batch size). Then ``drape train --data-mode stream`` runs the CLI path
    with forked workers."""
    from data_manifest.reader import DatasetReader
    from learn.data import DrapeDataset
    from learn.streamed_split import StreamedSplit
    from learn.tailornet.train import frame_arrays_from_dataset
    from learn.uvimage.garment import uvimage_context
    from learn.uvimage.train import build_learner, merged_hyperparameters, train_learner
    from pipelines.cli import main

    memory = frame_arrays_from_dataset(DrapeDataset(dataset, "train_train", frequencies=False))
    split = StreamedSplit(dataset, "train_train", workers=0)
    context = uvimage_context(DatasetReader(dataset), anny_body)
    hyper = {**merged_hyperparameters("uvimage", {"uvimage": TINY_HYPER}), "epochs": 2, "shuffle": False,
             "checkpoint_interval_s": 1e9}
    params = []
    for name, data in (("memory", memory), ("stream", split)):
        torch.manual_seed(0)
        learner = build_learner("uvimage", context["template"], anny_body, data, hyper, garment_type="tshirt")
        start = torch.cat([p.detach().reshape(-1) for p in learner.network.parameters()]).clone()
        learner = train_learner("uvimage", learner, data, run_dir=tmp_path / name, hyperparameters=hyper,
                                fingerprint=None, progress=False)
        params.append(torch.cat([p.detach().reshape(-1) for p in learner.network.parameters()]))
    moved = float((params[0] - start).abs().max())
    assert moved > 1e-4 and float((params[1] - params[0]).abs().max()) <= 1e-5 * moved

    run = tmp_path / "run"
    config = tmp_path / "uv.yaml"
    config.write_text(json.dumps({"uvimage": TINY_HYPER}))
    assert main(["train", "uvimage", "--data", str(dataset), "--out", str(run), "--epochs", "1", "--config", str(config),
                 "--data-mode", "stream", "--no-progress"]) == 0
    info = json.loads((run / "run.json").read_text())
    assert info["data_mode"] == "stream" and info["frames"] == 12
    assert np.isfinite(np.loadtxt(run / "uvimage_loss.csv", delimiter=",", skiprows=1)[1])
