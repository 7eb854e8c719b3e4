"""Tests of the TailorNet modules: kernel mixture, stacked prototypes, prototypes choice, pose mask."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from learn.tailornet.hf import HighFrequencyPrototypes, high_frequency_model
from learn.tailornet.lf import DisplacementMLP, low_frequency_model
from learn.tailornet.mixture import kernel_weights, prototype_distances
from learn.tailornet.model import TailorNet
from learn.tailornet.pose_mask import garment_pose_joints, pose_feature_indices
from simulate.garment.prototypes import canonical_frame_per_pair, choose_prototypes, convex_fit
from learn.tailornet.shape_style import ShapeStyleModel

torch.set_num_threads(1)

DEVICES = ["cpu"] + (["cuda:0"] if torch.cuda.is_available() else [])
ATOL_FLOAT32_M = 1e-6
VERTEX_COUNT = 10
POSE_SIZE = 12


def test_kernel_weights_sum_to_one_and_pick_nearest_as_sigma_shrinks() -> None:
    generator = torch.Generator().manual_seed(0)
    prototypes = torch.randn(5, VERTEX_COUNT, 3, generator=generator) * 0.02
    query = prototypes[[3, 1]] + 0.002 * torch.randn(2, VERTEX_COUNT, 3, generator=generator)
    distances = prototype_distances(query, prototypes)
    naive = 1000.0 * ((query[:, None] - prototypes[None]) ** 2).sum(-1).mean(-1)
    torch.testing.assert_close(distances, naive, rtol=1e-4, atol=1e-7, msg="dist != 1000 x mean squared distance")
    for sigma in (10.0, 0.1, 0.01, 1e-4, 1e-9):
        weights = kernel_weights(distances, sigma=sigma)
        assert torch.isfinite(weights).all(), f"non-finite weights at sigma={sigma}"
        torch.testing.assert_close(weights.sum(1), torch.ones(2), msg=f"weights do not sum to 1 at sigma={sigma}")
    tiny = kernel_weights(distances, sigma=1e-9)
    assert tiny.argmax(1).tolist() == [3, 1], f"nearest prototypes not picked: {tiny.argmax(1).tolist()}"
    assert torch.all(tiny.max(1).values > 1 - 1e-6), "weights are not one-hot as sigma -> 0"
    wide = kernel_weights(distances, sigma=1e6)
    torch.testing.assert_close(wide, torch.full_like(wide, 0.2), atol=1e-5, rtol=0, msg="wide kernel is not uniform")
    with pytest.raises(ValueError, match="sigma"):
        kernel_weights(distances, sigma=0.0)


def _mlps(count: int) -> list[DisplacementMLP]:
    torch.manual_seed(0)
    return [high_frequency_model(VERTEX_COUNT, [0, 1, 2, 6, 7, 8], hidden_size=16).eval() for _ in range(count)]


@pytest.mark.parametrize("device", DEVICES)
def test_stacked_prototypes_match_loop_over_mlps(device: str) -> None:
    mlps = [m.to(device) for m in _mlps(4)]
    stacked = HighFrequencyPrototypes.from_mlps(mlps)
    pose = torch.randn(3, POSE_SIZE, device=device)
    empty = torch.zeros(3, 0, device=device)
    with torch.no_grad():
        each = torch.stack([m(pose, empty, empty) for m in mlps], dim=1)  # (B, K, V, 3)
        torch.testing.assert_close(stacked.forward_all(pose), each, atol=ATOL_FLOAT32_M, rtol=1e-5)
        weights = torch.softmax(torch.randn(3, 4, device=device), dim=1)
        mixed = (weights[..., None, None] * each).sum(1)
        torch.testing.assert_close(stacked(pose, weights), mixed, atol=ATOL_FLOAT32_M, rtol=1e-5,
                                   msg="folded mixture differs from the weighted loop")


def _tailornet(device: str = "cpu") -> TailorNet:
    torch.manual_seed(1)
    lf = low_frequency_model(VERTEX_COUNT, list(range(POSE_SIZE)), hidden_size=16)
    g = ShapeStyleModel(VERTEX_COUNT, hidden_size=8)
    hf = HighFrequencyPrototypes.from_mlps(_mlps(3))
    shapes = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    styles = torch.tensor([[0.0, 0.5], [0.5, 0.0], [-1.0, 0.0]])
    return TailorNet(lf, hf, g, shapes, styles, sigma=0.01).to(device).eval()


@pytest.mark.parametrize("device", DEVICES)
def test_tailornet_forward_is_lf_plus_mixture_and_differentiable(device: str) -> None:
    model = _tailornet(device)
    pose = torch.randn(4, POSE_SIZE, device=device, requires_grad=True)
    shape = model.prototype_shape[[0, 1, 2, 0]].clone()
    style = model.prototype_style[[0, 1, 2, 0]].clone()
    parts = model.components(pose, shape, style)
    assert parts["displacements"].shape == (4, VERTEX_COUNT, 3)
    # At a prototype's own style-shape, dist = 0 and the others are farther: it dominates.
    assert parts["weights"].argmax(1).tolist() == [0, 1, 2, 0], parts["weights"]
    expected = parts["low_frequency"] + model.high_frequency(pose, parts["weights"])
    torch.testing.assert_close(parts["displacements"], expected)
    parts["displacements"].sum().backward()
    assert pose.grad is not None and torch.isfinite(pose.grad).all() and pose.grad.abs().sum() > 0

    def poser(unposed: torch.Tensor, pose_: torch.Tensor, shape_: torch.Tensor) -> torch.Tensor:
        return unposed + pose_[:, None, :3]  # a translation standing in for skinning

    def body(shape_: torch.Tensor) -> torch.Tensor:
        return shape_[:, None, :1].expand(-1, VERTEX_COUNT, 3)

    posed = model.pose_garment(pose.detach(), shape, style, garment_poser=poser, unposed_body=body)
    with torch.no_grad():
        torch.testing.assert_close(posed, model(pose, shape, style) + body(shape) + pose[:, None, :3])


def test_tailornet_config_round_trip() -> None:
    model = _tailornet()
    rebuilt = TailorNet.from_config(model.config)
    rebuilt.load_state_dict(model.state_dict())
    rebuilt.eval()
    pose, shape, style = torch.randn(2, POSE_SIZE), torch.randn(2, 2), torch.randn(2, 2)
    with torch.no_grad():
        torch.testing.assert_close(rebuilt(pose, shape, style), model(pose, shape, style), rtol=0, atol=0)


def test_displacement_mlp_input_checks() -> None:
    model = DisplacementMLP(VERTEX_COUNT, pose_indices=[0, 1, 2], shape_components=2, style_components=3, hidden_size=8)
    with pytest.raises(ValueError, match="style"):
        model(torch.zeros(1, 3), torch.zeros(1, 2), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="pose"):
        model(torch.zeros(1, 2), torch.zeros(1, 2), torch.zeros(1, 3))
    with pytest.raises(ValueError, match="no pose"):
        ShapeStyleModel(VERTEX_COUNT, pose_indices=(0,))


def test_prototype_choice_error_non_increasing_and_distinct() -> None:
    rng = np.random.default_rng(3)
    # 12 pairs: mixtures of 4 "extreme" garments plus noise, so a few prototypes suffice.
    extremes = rng.normal(scale=0.02, size=(4, 30, 3))
    mixing = rng.dirichlet(np.ones(4), size=8)
    garments = np.concatenate([extremes, np.einsum("xk,kvc->xvc", mixing, extremes)])
    garments += rng.normal(scale=1e-4, size=garments.shape)
    choice = choose_prototypes(garments, 8)
    assert len(set(choice.indices.tolist())) == 8, f"prototypes repeat: {choice.indices}"
    for name, errors in (("mean", choice.mean_error_mm), ("max", choice.max_error_mm)):
        assert np.all(np.diff(errors) <= 1e-12), f"{name} error increases with K: {errors}"
    # The default first pick is the garment nearest the mean (a mixture); after it, the
    # greedy rule must add the 4 extremes, since every other garment is their mixture.
    assert {0, 1, 2, 3} <= set(choice.indices[:5].tolist()), (
        f"the 4 extreme garments should be picked right after the first: {choice.indices}"
    )
    assert choice.max_error_mm[4] < 0.05 * choice.max_error_mm[0], choice.max_error_mm
    seeded = choose_prototypes(garments, 4, initial=[0])
    assert sorted(seeded.indices.tolist()) == [0, 1, 2, 3], seeded.indices
    np.testing.assert_allclose(choice.weights.sum(1), 1.0, atol=1e-12)
    assert (choice.weights >= 0).all()
    with pytest.raises(ValueError, match="prototype_count"):
        choose_prototypes(garments, 13)


def test_convex_fit_recovers_weights() -> None:
    rng = np.random.default_rng(4)
    basis = rng.normal(size=(3, 40))
    weights = np.array([0.2, 0.0, 0.8])
    np.testing.assert_allclose(convex_fit(basis, weights @ basis), weights, atol=1e-6)


def test_convex_fit_on_the_gram_matrix_solves_the_full_problem() -> None:
    """The Gram-matrix form reaches the same residual as NNLS on all D rows with the
    sum-to-one row (the direct form), for a target outside the basis' hull."""
    from scipy.optimize import nnls

    rng = np.random.default_rng(5)
    basis = rng.normal(size=(6, 300)) + 2.0 * rng.normal(size=(1, 300))  # correlated, as garments are
    target = 0.5 * basis[1] + 0.5 * basis[4] + 0.3 * rng.normal(size=300)
    heavy = 1e3 * np.abs(basis).max() * np.sqrt(300)
    direct, _ = nnls(np.vstack([basis.T, np.full((1, 6), heavy)]), np.concatenate([target, [heavy]]))
    direct /= direct.sum()
    weights = convex_fit(basis, target)
    assert (weights >= 0).all() and abs(weights.sum() - 1.0) < 1e-12
    residual = np.linalg.norm(weights @ basis - target)
    assert residual <= np.linalg.norm(direct @ basis - target) * (1 + 1e-9), (residual, direct, weights)


def test_canonical_frame_per_pair() -> None:
    pose = np.array([[0.5, 0.0], [0.1, 0.0], [0.0, 0.3], [0.9, 0.9]])
    pair = np.array([0, 0, 1, 1])
    assert canonical_frame_per_pair(pose, pair).tolist() == [1, 2]
    assert canonical_frame_per_pair(pose, pair, canonical_pose=np.array([1.0, 1.0])).tolist() == [0, 3]


def test_pose_mask_keeps_moving_joints_and_ancestors() -> None:
    # Skeleton: 0 root -> 1 spine -> 2 shoulder -> 3 elbow; 0 -> 4 hip -> 5 knee.
    parents = np.array([-1, 0, 1, 2, 0, 4])
    weights = np.zeros((6, 6))
    weights[:3, 2] = 1.0  # three garment vertices on the shoulder
    weights[3:, 3] = 1.0  # three on the elbow
    joints = garment_pose_joints(weights, parents=parents)
    assert joints.tolist() == [0, 1, 2, 3], f"expected shoulder, elbow and their ancestors, got {joints}"
    assert garment_pose_joints(weights, min_weight_sum=2.5).tolist() == [2, 3]
    # Pose slots map to skeleton joints 0, 2, 3, 5 (joint 1, 4 not posable).
    indices = pose_feature_indices(joints, 12, posable_joints=np.array([0, 2, 3, 5]))
    assert indices.tolist() == list(range(9)), indices
    with pytest.raises(ValueError, match="no posable joint"):
        pose_feature_indices(np.array([1]), 12, posable_joints=np.array([0, 2, 3, 5]))
    with pytest.raises(ValueError, match="multiple of 3"):
        pose_feature_indices(joints, 10)


@pytest.mark.parametrize("device", DEVICES)
def test_forward_each_matches_each_mlp_and_applies_dropout_in_training(device: str) -> None:
    mlps = [m.to(device) for m in _mlps(3)]
    stacked = HighFrequencyPrototypes.from_mlps(mlps).eval()
    pose = torch.randn(3, 5, POSE_SIZE, device=device)
    empty = torch.zeros(5, 0, device=device)
    with torch.no_grad():
        each = torch.stack([m(pose[k], empty, empty) for k, m in enumerate(mlps)])
        torch.testing.assert_close(stacked.forward_each(pose), each, atol=ATOL_FLOAT32_M, rtol=1e-5)
        stacked.train()
        assert not torch.allclose(stacked.forward_each(pose), each, atol=1e-4), "dropout inactive in train mode"
    with pytest.raises(ValueError, match="pose must have shape"):
        stacked.forward_each(pose[:2])


def test_weight_floor_skips_negligible_prototypes_within_bound() -> None:
    stacked = HighFrequencyPrototypes.from_mlps(_mlps(4))
    pose = torch.randn(3, POSE_SIZE)
    weights = torch.tensor([[1.0 - 2e-7, 1e-7, 1e-7, 0.0], [0.5, 0.5 - 1e-7, 1e-7, 0.0], [0.0, 1.0, 0.0, 0.0]])
    with torch.no_grad():
        exact = stacked(pose, weights)
        skipped = stacked(pose, weights, weight_floor=1e-6)  # prototypes 2, 3 skipped
        kept_only = stacked(pose, weights * torch.tensor([1.0, 1.0, 0.0, 0.0]))
        bound = 4 * 1e-6 * stacked.forward_all(pose).abs().max()
    assert (skipped - exact).abs().max() <= bound, "skipping exceeded its error bound"
    torch.testing.assert_close(skipped, kept_only, atol=ATOL_FLOAT32_M, rtol=1e-5,
                               msg="subset path differs from the full path with zeroed weights")


@pytest.mark.parametrize("device", DEVICES)
def test_batched_prototypes_give_the_gradients_of_independent_mlps(device: str) -> None:
    """Same weights -> same per-prototype outputs and the same gradients: the batched network's
    summed loss gives prototype k exactly the gradient of MLP k's own loss on its own batch."""
    torch.manual_seed(3)
    mlps = [high_frequency_model(VERTEX_COUNT, [0, 1, 2, 6, 7, 8], hidden_size=16, dropout=0.0).to(device).train()
            for _ in range(3)]
    stacked = HighFrequencyPrototypes.from_mlps(mlps).train()
    pose = torch.randn(3, 5, POSE_SIZE, device=device)
    target = torch.randn(3, 5, VERTEX_COUNT, 3, device=device) * 0.01
    empty = torch.zeros(5, 0, device=device)
    batched = stacked.forward_each(pose)
    (batched - target).abs().sum(-1).mean(dim=(1, 2)).sum().backward()
    for k, mlp in enumerate(mlps):
        out = mlp(pose[k], empty, empty)
        torch.testing.assert_close(batched[k].detach(), out.detach(), atol=ATOL_FLOAT32_M, rtol=1e-5)
        (out - target[k]).abs().sum(-1).mean().backward()
        first, second, last = mlp.mlp.layers[0], mlp.mlp.layers[3], mlp.mlp.layers[5]
        h = stacked.hidden_size
        pairs = [(stacked.weight1.grad[k], first.weight.grad.T), (stacked.bias1.grad[k], first.bias.grad),
                 (stacked.weight2.grad[k], second.weight.grad.T), (stacked.bias2.grad[k], second.bias.grad),
                 (stacked.weight3.grad[k * h:(k + 1) * h], last.weight.grad.T), (stacked.bias3.grad[k], last.bias.grad)]
        for i, (got, expected) in enumerate(pairs):
            assert expected.abs().sum() > 0, f"prototype {k}: parameter {i} of the MLP got no gradient"
            torch.testing.assert_close(got, expected, atol=1e-6, rtol=1e-4,
                                       msg=f"prototype {k}: gradient of parameter {i} differs from its own MLP's")


def test_stacked_prototypes_are_made_where_they_are_used() -> None:
    """The K stacked networks' parameters and buffer are made on the given device (``meta`` here:
    no memory), and cat joins parts on their device: at K = 20 and 7.7k vertices the model is 2 GB,
    which assembling a stage-parallel run made on the host and then copied over."""
    made = HighFrequencyPrototypes(3, 5, [0, 2], hidden_size=4, dropout=0.0, device="meta")
    assert {t.device.type for t in [*made.parameters(), *made.buffers()]} == {"meta"}
    parts = [HighFrequencyPrototypes(k, 5, [0, 2], hidden_size=4, dropout=0.0) for k in (2, 1)]
    for part in parts:
        with torch.no_grad():
            for p in part.parameters():
                p.normal_()
    joined = HighFrequencyPrototypes.cat(parts)
    assert joined.prototype_count == 3 and joined.weight3.device == parts[0].weight3.device
    assert torch.equal(joined.weight3, torch.cat([parts[0].weight3, parts[1].weight3]))
