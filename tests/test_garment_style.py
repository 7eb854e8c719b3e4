"""Style parameters (names, ranges, errors), style PCA space (synthetic data), shapes
and prototype selection."""
from __future__ import annotations

import numpy as np
import pytest

from simulate.garment.style import GARMENT_TYPES, STYLE_SPECS, StyleParams, sample_styles
from simulate.garment.style_space import StyleSpace, fit_pca, select_prototypes

ATOL_GAMMA = 1e-8
ATOL_RECON_M = 1e-9


def test_style_defaults_and_parse():
    for t in GARMENT_TYPES:
        s = StyleParams(t)
        assert set(s.values) == set(STYLE_SPECS[t])
        for k, (lo, hi, default, _) in STYLE_SPECS[t].items():
            assert lo <= default <= hi and s[k] == default
    s = StyleParams.parse("tshirt", "length=0.6, looseness=0.02")
    assert s["length"] == 0.6 and s["looseness"] == 0.02 and s["sleeve_length"] == STYLE_SPECS["tshirt"]["sleeve_length"][2]


def test_style_errors_list_allowed_names_and_ranges():
    with pytest.raises(ValueError) as err:
        StyleParams("tshirt", {"colour": 1.0})
    msg = str(err.value)
    assert "colour" in msg and all(name in msg for name in STYLE_SPECS["tshirt"]), msg
    assert "[0.005, 0.05]" in msg, f"allowed ranges missing: {msg}"
    with pytest.raises(ValueError, match=r"looseness=0.2 .* outside its range \[0.005, 0.05\]"):
        StyleParams("pants", {"looseness": 0.2})
    with pytest.raises(ValueError, match="tshirt, shirt, pants, shorts, skirt, top, dress, jumpsuit"):
        StyleParams("gown")
    with pytest.raises(ValueError, match="NAME=VALUE"):
        StyleParams.parse("skirt", "length")
    with pytest.raises(ValueError, match="must be a number"):
        StyleParams.parse("skirt", "length=long")
    with pytest.raises(ValueError, match="leg_length"):
        StyleParams("shorts", {"sleeve_length": 0.5})


def test_sample_styles_in_range_and_seeded():
    a = sample_styles("skirt", 5, seed=3)
    b = sample_styles("skirt", 5, seed=3)
    assert [x.values for x in a] == [x.values for x in b]
    for s in a:
        for k, (lo, hi, _, _) in STYLE_SPECS["skirt"].items():
            assert lo <= s[k] <= hi
    assert a[0].values != sample_styles("skirt", 5, seed=4)[0].values


def _synthetic_displacements(n=30, v=50, rank=4, seed=0):
    rng = np.random.default_rng(seed)
    basis = rng.normal(size=(rank, v, 3))
    coeff = rng.normal(size=(n, rank)) * np.array([1.0, 0.5, 0.25, 0.1])[:rank]
    return 0.01 * (np.einsum("nk,kvd->nvd", coeff, basis) + rng.normal(size=(v, 3)))


def test_pca_reconstruction_decreases_and_gamma_roundtrips(tmp_path):
    disp = _synthetic_displacements()
    errors = []
    for k in range(1, 5):
        mean, comps, var = fit_pca(disp, k)
        space = StyleSpace("tshirt", "test", np.zeros_like(mean), mean, comps, var)
        recon = space.gamma_to_garment(space.garment_to_gamma(disp))
        errors.append(float(np.abs(recon - disp).mean()))
    assert all(b <= a + 1e-12 for a, b in zip(errors, errors[1:])), f"error not decreasing: {errors}"
    assert errors[-1] < ATOL_RECON_M * 1e3, f"rank-4 data not reproduced by 4 components: {errors[-1]}"
    mean, comps, var = fit_pca(disp, 2)
    assert var[0] >= var[1] > 0
    ref = np.random.default_rng(1).normal(size=mean.shape)
    space = StyleSpace("tshirt", "test", ref, mean, comps, var)
    gamma = np.array([[0.3, -0.2], [0.0, 0.1]])
    assert np.allclose(space.garment_to_gamma(space.gamma_to_garment(gamma)), gamma, atol=1e-5)
    path = space.save(tmp_path / "space.npz")
    back = StyleSpace.load(path)
    assert np.allclose(back.components, space.components, atol=1e-6) and back.garment_type == "tshirt"
    with pytest.raises(ValueError, match="gamma must have 2 values"):
        space.gamma_to_garment(np.zeros(3))
    with pytest.raises(ValueError, match=r"shape \(N, V, 3\)"):
        fit_pca(np.zeros((3, 4)), 1)


def test_prototypes_error_non_increasing_and_distinct():
    disp = _synthetic_displacements(n=25, v=40, seed=2)
    choice = select_prototypes(disp, 8)
    idx = list(choice.indices)
    assert len(set(idx)) == len(idx) == 8, f"picks not distinct: {idx}"
    for name in ("mean_error_mm", "max_error_mm"):
        e = np.asarray(getattr(choice, name))
        assert (np.diff(e) <= 1e-9).all(), f"{name} increases with K: {e}"
    assert choice.mean_error_mm[-1] < choice.mean_error_mm[0]


def test_training_shapes(anny_body):
    from simulate.garment.shapes import sample_test_shapes, shape_influence, training_shapes

    infl = shape_influence(anny_body)
    assert set(infl) == set(anny_body.shape_names) and all(v >= 0 for v in infl.values())
    shapes, names = training_shapes(anny_body)
    assert shapes.shape == (9, anny_body.shape_size) and len(names) == 2 and "age" not in names
    assert np.allclose(shapes[0], anny_body.shape_default)
    assert len({tuple(s) for s in shapes}) == 9, "training shapes are not distinct"
    for j, name in enumerate(names):
        i = anny_body.shape_names.index(name)
        levels = shapes[1 + 4 * j:5 + 4 * j, i]
        assert np.allclose(np.diff(levels), levels[1] - levels[0]), "levels not equally spaced"
    ranked = sorted((k for k in infl if k != "age"), key=lambda k: -infl[k])[:2]
    assert names == ranked
    test = sample_test_shapes(anny_body, 6, seed=1)
    assert test.shape == (6, anny_body.shape_size) and np.array_equal(test, sample_test_shapes(anny_body, 6, seed=1))
    with pytest.raises(ValueError, match="unknown shape parameter"):
        training_shapes(anny_body, parameters=("girth", "height"))
