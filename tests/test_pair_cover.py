"""``pairs.cover``: train pairs that wear every train style and shape, so no test pair of seen
styles and shapes (``styles.test: train``, ``shapes.test: train``) is an unseen style to a learner."""
from __future__ import annotations

import numpy as np
import pytest

from pipelines.dataset_plan import covering_pick
from pipelines.spec import SpecError, validate_spec


def spec(styles: int, shapes: int, train: int, test: int, **pairs) -> dict:
    return validate_spec({
        "name": "cover", "garment": {"type": "tshirt", "resolution": 400},
        "styles": {"train": styles, "test": "train"}, "shapes": {"train": shapes, "test": "train"},
        "pairs": {"train": train, "test": test, **pairs}, "poses": {"train_count": 2, "test_count": 1},
        "splits": {"train_train": "all", "train_test": "all", "test_train": 1, "test_test": 1},
        "simulation": {"device": "cpu", "worlds": 4},
    })


@pytest.mark.parametrize("s_count, h_count, want", [(20, 9, 20), (9, 20, 20), (5, 5, 5), (4, 6, 10), (7, 3, 4)])
def test_the_pick_wears_every_style_and_shape(s_count, h_count, want):
    candidates = [(a, b) for a in range(s_count) for b in range(h_count)]
    pick = covering_pick(candidates, s_count, h_count, want, np.random.default_rng(0))
    pairs = [candidates[i] for i in pick]
    assert len(pairs) == len(set(pairs)) == want
    reach = min(want, max(s_count, h_count))
    assert len({a for a, _ in pairs}) >= min(s_count, reach) and len({b for _, b in pairs}) >= min(h_count, reach)
    again = covering_pick(candidates, s_count, h_count, want, np.random.default_rng(0))
    np.testing.assert_array_equal(pick, again)


def test_the_shipped_size_wears_all_20_styles_where_a_random_draw_does_not(anny_body):
    from pipelines.dataset_plan import plan_dataset

    def worn(plan) -> tuple[int, int]:
        train = [(si, hi) for group, si, hi in plan.pairs if group == "train"]
        return len({si for si, _ in train}), len({hi for _, hi in train})

    covered = plan_dataset(spec(20, 9, 20, 20, cover=True), anny_body)
    assert worn(covered) == (20, 9)
    random = plan_dataset(spec(20, 9, 20, 20), anny_body)
    assert worn(random)[0] < 20, "the seed's random draw leaves styles out (the case cover fixes)"
    test = {(si, hi) for group, si, hi in covered.pairs if group == "test"}
    assert len(test) == 20 and not test & {(si, hi) for group, si, hi in covered.pairs if group == "train"}
    assert "cover" not in spec(3, 2, 2, 1)["pairs"], "absent, the key stays out of the resolved spec (and its hash)"


def test_a_bad_cover_names_the_field():
    with pytest.raises(SpecError, match=r"spec.pairs.cover must be true \(every train style and shape in a train "
                                        r"pair\) or false \(got 'yes'\)"):
        spec(3, 2, 2, 1, cover="yes")
