"""Point labels of the error-vs-time plots cover no other label, also where points coincide."""
from __future__ import annotations

import itertools

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from simulate.reports.labels import place_labels  # noqa: E402


def _label_boxes(ax):
    renderer = ax.figure.canvas.get_renderer()
    return [(t.get_text(), t.get_window_extent(renderer)) for t in ax.texts]


def _assert_apart(ax, expected: list[str]):
    boxes = _label_boxes(ax)
    assert sorted(text for text, _ in boxes) == sorted(expected)
    for (a, box_a), (b, box_b) in itertools.combinations(boxes, 2):
        assert not box_a.overlaps(box_b), f"labels {a!r} and {b!r} overlap"


# the quickstart's points: two learners x two batch sizes at the same error, the batch-32 times close
QUICKSTART = [{"label": "tailornet cpu batch 1", "ms_per_frame": 2.1, "error_mm": 14.0},
              {"label": "tailornet cpu batch 32", "ms_per_frame": 2.0, "error_mm": 14.0},
              {"label": "baseline cpu batch 1", "ms_per_frame": 2.2, "error_mm": 14.2},
              {"label": "baseline cpu batch 32", "ms_per_frame": 2.0, "error_mm": 14.1},
              {"label": "simulator (dataset settings)", "ms_per_frame": 2.0, "error_mm": 14.0}]


def test_labels_of_coinciding_points_are_stacked_apart():
    fig, ax = plt.subplots(figsize=(4, 3), dpi=100)
    ax.scatter([1.0] * 6, [1.0] * 6)
    labels = [f"point number {i}" for i in range(6)]
    place_labels(ax, [(1.0, 1.0)] * 6, labels)
    _assert_apart(ax, labels)
    plt.close(fig)


def test_error_vs_runtime_labels_do_not_overlap(tmp_path):
    from learn.tailornet.plots import error_vs_runtime_figure, plot_error_vs_runtime

    fig = error_vs_runtime_figure(QUICKSTART)
    _assert_apart(fig.axes[0], [p["label"] for p in QUICKSTART])
    plt.close(fig)
    assert plot_error_vs_runtime(QUICKSTART, tmp_path / "e.png").stat().st_size > 0


def test_pareto_plot_labels_do_not_overlap(tmp_path, monkeypatch):
    from simulate.reports.pareto import plot_error_vs_time

    figures = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig))
    settings = [{"label": f"xpbd s{s} i{i}", "ms_per_frame": 10.0 + s * i * 0.01, "error_mm": 5.0 / (s * i)}
                for s in (5, 10) for i in (5, 10)]
    settings.append({"label": "exploded", "ms_per_frame": 10.0, "error_mm": float("nan")})
    plot_error_vs_time(settings, tmp_path / "p.png", highlight="xpbd s10 i10", extra_points=QUICKSTART[:4])
    (fig,) = figures
    _assert_apart(fig.axes[0], [p["label"] for p in settings[:-1]] + ["exploded (failed)"]
                  + [p["label"] for p in QUICKSTART[:4]])
    close(fig)


@pytest.mark.parametrize("count", [1, 12])
def test_each_point_gets_its_own_label(count):
    fig, ax = plt.subplots()
    out = place_labels(ax, [(float(i), 1.0) for i in range(count)], [str(i) for i in range(count)])
    assert [a.get_text() for a in out] == [str(i) for i in range(count)]
    assert [a.xy for a in out] == [(float(i), 1.0) for i in range(count)]
    plt.close(fig)
