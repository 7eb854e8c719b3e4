"""GCVAE (seed 004): Chebyshev layer, segment-aware pooling, registration, overfitting, CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from learn.gcvae.chebyshev import ChebConv, scaled_laplacian, torch_sparse
from learn.gcvae.pooling import build_hierarchy, cluster_members, copy_unpool, max_pool

torch.set_num_threads(1)


def _tube(rings: int, segments: int, radius: float = 0.1, height: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """Open cylinder (rings * segments vertices) [m], axis y, outward faces."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    y = np.linspace(height / 2, -height / 2, rings)
    v = np.stack([radius * np.cos(a)[None].repeat(rings, 0), y[:, None].repeat(segments, 1),
                  radius * np.sin(a)[None].repeat(rings, 0)], -1).reshape(-1, 3)
    f = []
    for r in range(rings - 1):
        for s in range(segments):
            p, q = r * segments + s, r * segments + (s + 1) % segments
            f += [(p, q, p + segments), (q, q + segments, p + segments)]
    return v, np.asarray(f, np.int64)


def _overfit(model, batch: dict, faces: torch.Tensor, loss: dict, steps: int) -> None:
    """``steps`` Adam steps (lr 3e-3) of the GCVAE loss on one batch, KL off; the model left in eval mode."""
    from learn.gcvae.losses import gcvae_loss

    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(steps):
        out = model(batch["body"], batch["offsets"], batch["mask"], batch["condition"])
        value, _ = gcvae_loss(model, out, batch, faces, faces, loss, 0.0)
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
    model.eval()


def test_chebyshev_layer_matches_dense_spectral_filter() -> None:
    """sum_k T_k(L~) X theta_k from the eigen-decomposition (T_k(l) = cos(k arccos l)) equals
    the sparse recursion, for every order up to 5, and its gradient too."""
    rng = np.random.default_rng(0)
    v, f = _tube(5, 7)
    from learn.common.mesh import mesh_edges

    edges = mesh_edges(f)
    n = len(v)
    lap = scaled_laplacian(edges, n)
    dense = lap.toarray()
    assert np.allclose(dense, dense.T)
    eig, vec = np.linalg.eigh(dense)
    assert eig.min() >= -1 - 1e-6 and eig.max() <= 1 + 1e-4, "L~ must have its spectrum in [-1, 1]"
    x = rng.standard_normal((n, 3, 4))  # (N, B, C)
    for order in (1, 2, 3, 5):
        torch.manual_seed(order)
        conv = ChebConv(4, 6, order)
        with torch.no_grad():
            conv.bias.normal_()
        theta = conv.weight.detach().double().numpy()
        expected = np.zeros((n, 3, 6))
        for k in range(order):
            tk = vec @ np.diag(np.cos(k * np.arccos(np.clip(eig, -1, 1)))) @ vec.T
            expected += np.einsum("ij,jbc,co->ibo", tk, x, theta[k])
        expected += conv.bias.detach().double().numpy()
        xt = torch.tensor(x, dtype=torch.float32, requires_grad=True)
        got = conv(xt, torch_sparse(lap))
        np.testing.assert_allclose(got.detach().numpy(), expected, atol=2e-4, err_msg=f"order {order}")
        # The symmetric backward must equal the dense gradient of sum(y * g).
        g = rng.standard_normal(got.shape)
        (got * torch.tensor(g, dtype=torch.float32)).sum().backward()
        grad = sum(np.einsum("ij,ibo,co->jbc", vec @ np.diag(np.cos(k * np.arccos(np.clip(eig, -1, 1)))) @ vec.T,
                             g, theta[k]) for k in range(order))
        np.testing.assert_allclose(xt.grad.numpy(), grad, atol=2e-4, err_msg=f"gradient, order {order}")
    with pytest.raises(ValueError, match="order"):
        ChebConv(2, 2, 0)


@pytest.fixture(scope="module")
def body_mesh(anny_body):
    from learn.gcvae.body_mesh import build_body_mesh, canonical_body_vertices

    mesh = build_body_mesh(anny_body, subdivisions=0)
    return mesh, mesh.vertices(canonical_body_vertices(anny_body, anny_body.shape_default))[0]


def test_pooling_never_crosses_segments(body_mesh) -> None:
    mesh, vertices = body_mesh
    levels = build_hierarchy(vertices, mesh.edges, mesh.segments, factor=4, levels=3)
    segments = mesh.segments
    for i, level in enumerate(levels):
        assert np.array_equal(level.segments[level.assignment], segments), f"level {i} merges two segments"
        assert np.bincount(level.assignment).min() >= 1, f"level {i} has an empty cluster"
        segments = level.segments
    assert np.array_equal(np.sort(levels[-1].segments), np.arange(mesh.segment_count)), \
        "the last level must hold one vertex per segment"
    assert levels[0].size < mesh.vertex_count / 3, "factor 4 should shrink the first level about fourfold"
    # max-pool is the per-cluster maximum, copy-unpool the cluster's features.
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.standard_normal((mesh.vertex_count, 2, 3)), dtype=torch.float32)
    a = levels[0].assignment
    pooled = max_pool(x, torch.as_tensor(cluster_members(a, levels[0].size)))
    naive = np.stack([x.numpy()[a == c].max(0) for c in range(levels[0].size)])
    np.testing.assert_array_equal(pooled.numpy(), naive)
    np.testing.assert_array_equal(copy_unpool(pooled, torch.as_tensor(a)).numpy(), naive[a])


def test_dual_topology_bridges_the_legs(body_mesh) -> None:
    from simulate.garment import mesh_ops

    mesh, _ = body_mesh
    bridge = mesh.bridge_vertices()
    assert bridge.any() and mesh.inner_leg.any()
    assert mesh_ops.is_manifold(mesh.dual_faces, mesh.vertex_count)[0]
    inner_faces = mesh.inner_leg[mesh.faces].all(1)
    dual_set = {tuple(sorted(x)) for x in mesh.dual_faces.tolist()}
    assert not any(tuple(sorted(x)) in dual_set for x in mesh.faces[inner_faces].tolist()), \
        "inner-leg faces must be gone from the dual topology"
    x = mesh.dual_vertices(np.zeros((mesh.vertex_count, 3)) + 1.0)
    np.testing.assert_allclose(x, 1.0, err_msg="dual smoothing must keep a constant field (rows sum to 1)")
    assert mesh.topology("skirt")[0] == "dual" and mesh.topology("pants")[0] == "standard"


@pytest.mark.parametrize("garment_type", ["tshirt", "skirt"])
def test_registration_round_trip(body_mesh, garment_type: str) -> None:
    """A garment that is a body region lifted 15 mm along the normals registers back to that
    region (mask IoU) and reconstructs to within a millimetre."""
    from learn.gcvae.registration import MAX_OFFSET_M, reconstruct, register, registration_error
    from learn.gcvae.synthetic import SEGMENTS_OF
    from simulate.garment import mesh_ops

    mesh, standard = body_mesh
    topology, faces = mesh.topology(garment_type)
    base = mesh.positions_for(garment_type, standard)
    names = SEGMENTS_OF[garment_type]
    region = np.array([any(n.startswith(p) for p in names) for n in mesh.segment_names])[mesh.segments]
    if topology == "dual":
        region &= ~(mesh.inner_leg & ~mesh.bridge_vertices())
    normals = mesh_ops.smooth_normals(base, faces, iterations=5)
    garment, garment_faces, used = reconstruct(base, faces, 0.015 * normals, region)
    reg = register(garment, garment_faces, base, faces, max_distance=MAX_OFFSET_M[topology])
    iou = (reg.mask & region).sum() / (reg.mask | region).sum()
    assert iou > 0.95, f"mask IoU {iou:.3f} against the lifted region"
    err = registration_error(garment, garment_faces, base, faces, reg)
    assert err["garment_to_registered_mm"] < 1.0 and err["registered_to_garment_mm"] < 0.01, err
    v, f, index = reconstruct(base, faces, reg.offsets, reg.mask)
    assert len(f) > 0.9 * len(garment_faces)
    lifted = np.full((len(base), 3), np.nan)
    lifted[used] = garment
    on = np.isin(index, used)
    assert np.linalg.norm(v[on] - lifted[index[on]], axis=1).mean() < 3e-3, \
        "registered points should slide less than a sixth of a body edge (~2 cm) from their source vertex"


def test_tiny_overfit() -> None:
    """Six garments on a small segmented tube: 200 Adam steps bring the reconstruction error far
    below that of the mean garment, and the masks right."""
    from learn.common.mesh import mesh_edges
    from learn.gcvae.hyperparameters import merged
    from learn.gcvae.model import GCVAE

    v, f = _tube(12, 16)
    edges = mesh_edges(f)
    segments = (np.arange(len(v)) // 16) // 3  # 4 segments of 3 rings
    rng = np.random.default_rng(0)
    count = 6
    condition = rng.uniform(0, 1, (count, 2)).astype(np.float32)
    normals = v * np.array([1.0, 0.0, 1.0]) / 0.1
    offsets, masks = [], []
    for k in range(count):
        lift = 0.01 + 0.03 * condition[k, 1] + 0.005 * np.sin(8 * v[:, 1] + k)
        mask = v[:, 1] > 0.3 - 0.1 * (1 + k)  # garments of different lengths
        offsets.append(np.where(mask[:, None], normals * lift[:, None], 0.0))
        masks.append(mask)
    batch = {"body": torch.tensor(np.repeat(v[None], count, 0), dtype=torch.float32),
             "offsets": torch.tensor(np.stack(offsets), dtype=torch.float32),
             "mask": torch.tensor(np.stack(masks)), "condition": torch.tensor(condition),
             "dual": torch.zeros(count, dtype=torch.bool)}
    hyper = merged({"model": {"channels": [16, 16, 16], "pool_levels": 2, "latent_size": 4, "condition_hidden": 8}})
    torch.manual_seed(0)
    model = GCVAE(edges, v, segments, 2, hyper["model"])
    model.fit_normalisation(batch["body"].numpy(), batch["offsets"].numpy(), batch["mask"].numpy(), condition)
    _overfit(model, batch, torch.as_tensor(f), hyper["loss"], 300)
    with torch.no_grad():
        out = model(batch["body"], batch["offsets"], batch["mask"], batch["condition"], sample=False)
    m = batch["mask"]
    err = ((model.offsets_from(out["offsets"]) - batch["offsets"]).norm(dim=-1)[m]).mean()
    mean_err = ((batch["offsets"].mean(0, keepdim=True) - batch["offsets"]).norm(dim=-1)[m]).mean()
    assert err < 0.2 * mean_err, f"reconstruction {1e3 * err:.2f} mm vs the mean garment's {1e3 * mean_err:.2f} mm"
    assert ((out["mask_logits"] > 0) == m).float().mean() > 0.97


def test_cli_train_evaluate_sample(tmp_path: Path, anny_body, capsys) -> None:
    from learn.gcvae.synthetic import write_synthetic_static_set
    from learn.registry import get_learner
    from pipelines.cli import main

    data = tmp_path / "set"
    write_synthetic_static_set(data, anny_body, types=("tshirt", "skirt"), count=4)
    config = tmp_path / "tiny.yaml"
    config.write_text("model: {channels: [4, 4, 4, 4], latent_size: 2, condition_hidden: 4}\n"
                      "train: {batch_size: 4}\n")
    run = tmp_path / "run"
    assert main(["train", "gcvae", "--data", str(data), "--out", str(run), "--epochs", "2", "--config", str(config),
                 "--no-progress"]) == 0
    entry = get_learner("gcvae")
    assert entry.data == "static_set" and entry.stages == ("train",)
    assert (run / entry.model_file).is_file() and (run / "gcvae_terms.csv").is_file()
    info = json.loads((run / "run.json").read_text())
    assert info["hyperparameters"]["train"]["epochs"] == 2 and info["hyperparameters"]["model"]["latent_size"] == 2
    assert info["train_samples"] + info["validation_samples"] == int((np.load(data / "static_set.npz")["split"] == 0).sum())
    assert len((run / "gcvae_terms.csv").read_text().strip().splitlines()) == 3  # header + 2 epochs
    assert main(["evaluate", str(run), "--data", str(data)]) == 0
    report = json.loads((run / "evaluation" / "evaluation.json").read_text())
    for split in ("test", "train"):
        types = report["splits"][split]["types"]
        assert set(types) == {"tshirt", "skirt"}
        for m in types.values():
            assert m["surface_mm"] > 0 and 0 <= m["mask_iou"] <= 1 and 0 <= m["normal_rad"] <= np.pi and m["kl"] >= 0
    assert "surface mm" in capsys.readouterr().out
    out = tmp_path / "samples"
    assert main(["sample", str(run), "--out", str(out), "--count", "2", "--seed", "3"]) == 0
    assert (out / "samples.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    objs = sorted(p.name for p in out.glob("*.obj"))
    assert objs == ["body.obj", "garment_0.obj", "garment_1.obj"], objs
    first = (out / "garment_0.obj").read_text()
    assert main(["sample", str(run), "--out", str(tmp_path / "again"), "--count", "2", "--seed", "3"]) == 0
    assert (tmp_path / "again" / "garment_0.obj").read_text() == first, "same seed, same garments"
    capsys.readouterr()
    assert main(["sample", str(run), "--out", str(out), "--shape", "0.5,2"]) == 2
    assert "--shape" in capsys.readouterr().err
    config.write_text("train: {learning_rate: 1.0}\n")
    assert main(["train", "gcvae", "--data", str(data), "--out", str(tmp_path / "r2"), "--config", str(config)]) == 2
    assert "train.learning_rate" in capsys.readouterr().err
    assert main(["train", "gcvae", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r3")]) == 2
    assert "static-set" in capsys.readouterr().err
    assert main(["train", "gcvae", "--data", str(data), "--out", str(tmp_path / "r4"), "--prototypes", "3"]) == 2
    assert "--prototypes applies to tailornet only, not gcvae" in capsys.readouterr().err


@pytest.mark.parametrize("option, value", [("--count", "1"), ("--count", "0"), ("--test-fraction", "1.0"),
                                           ("--test-fraction", "0"), ("--test-fraction", "nan")])
def test_cli_static_set_refuses_sizes_before_creating_out(tmp_path: Path, capsys, option: str, value: str) -> None:
    """A set size or test share that leaves a type without a train or a test sample stops with
    exit 2 naming the option and the value, before --out exists."""
    from pipelines.cli import main

    out = tmp_path / "set"
    assert main(["static-set", "--out", str(out), option, value]) == 2
    err = capsys.readouterr().err
    assert option in err and value.lower() in err.lower(), err
    assert not out.exists(), "a refused command leaves no --out directory"
