"""Pictures (population/plots.py): cross-play heatmap labels never overlap, whatever their count and length."""

from __future__ import annotations

import numpy as np
import pytest

from population import plots

pytest.importorskip("matplotlib")


def _label_boxes(monkeypatch, matrix, labels, col_labels=None):
    """Draw ``xp_heatmap`` and return the window extents of its tick labels (x, y) and title."""
    seen = {}

    def capture(fig, path):
        renderer = fig.canvas.get_renderer()
        fig.draw(renderer)
        ax = fig.axes[0]
        seen["x"] = [t.get_window_extent(renderer) for t in ax.get_xticklabels() if t.get_text()]
        seen["y"] = [t.get_window_extent(renderer) for t in ax.get_yticklabels() if t.get_text()]
        seen["fig"] = fig.bbox
        return str(path)

    monkeypatch.setattr(plots, "save_figure", capture)
    plots.xp_heatmap(matrix, "unused.png", labels=labels, col_labels=col_labels, title="a long title " * 12)
    return seen


def _overlaps(boxes) -> list[tuple[int, int]]:
    return [(i, j) for i in range(len(boxes)) for j in range(i + 1, len(boxes)) if boxes[i].overlaps(boxes[j])]


@pytest.mark.parametrize("count, length", [(20, 40), (20, 3), (60, 25), (8, 30), (3, 60)])
def test_heatmap_tick_labels_never_overlap(monkeypatch, count, length):
    rng = np.random.default_rng(0)
    labels = [f"runs/v2_grounded_coord_simple_{i:02d}_seed".ljust(length, "x")[:length] for i in range(count)]
    seen = _label_boxes(monkeypatch, rng.uniform(0, 250, (count, count)), labels)
    assert len(seen["x"]) == len(seen["y"]) == count
    assert _overlaps(seen["x"]) == [] and _overlaps(seen["y"]) == []
    # row labels stay left of every cell column label, column labels below every row label
    assert max(b.x1 for b in seen["y"]) <= min(b.x0 for b in seen["x"]) + 1e-6 or count < 2


def test_heatmap_layout_rotates_only_labels_wider_than_a_cell():
    short = plots.heatmap_layout(["a", "b"], ["x", "y"])
    long = plots.heatmap_layout(["a", "b"], ["a_long_column_label", "another_long_one"])
    assert not short.rotate and long.rotate and long.figsize[1] > short.figsize[1]
    many = plots.heatmap_layout([str(i) for i in range(200)], [str(i) for i in range(200)])
    assert many.font == 4.0 and not many.annotate and many.cell >= plots.LINE_HEIGHT * 4.0 / 72
