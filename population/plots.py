"""Pictures of results: training curves (mean +- std across seeds) and cross-play heatmaps.

matplotlib is an optional extra (``ocv2[plots]``). Without it ``training_curves`` and ``xp_heatmap``
draw nothing, say so on stderr and return None, so a training run still finishes with its numbers.
"""

from __future__ import annotations

import logging
import textwrap
from typing import NamedTuple

import numpy as np

from ocv2.atomic import atomic_path

log = logging.getLogger(__name__)

MISSING_MATPLOTLIB = "matplotlib is not installed: pip install 'ocv2[plots]'"


class PlotsUnavailable(ImportError):
    """matplotlib (the ``plots`` extra) is not installed."""


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend; ``PlotsUnavailable`` without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        raise PlotsUnavailable(MISSING_MATPLOTLIB) from None

    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path) -> str:
    """Save atomically (temporary name, then rename); creates missing folders."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    return str(path)


def skipped(path, error: PlotsUnavailable) -> None:
    log.warning("%s not drawn: %s", path, error)


def across_seeds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) of [S, U] ``values`` over the seeds that have a value at each update; NaN where none has."""
    values = np.asarray(values, np.float64)
    count = (~np.isnan(values)).sum(0)
    with np.errstate(all="ignore"):
        mean = np.where(count > 0, np.nansum(values, 0) / np.maximum(count, 1), np.nan)
        std = np.sqrt(np.where(count > 0, np.nansum((values - mean) ** 2, 0) / np.maximum(count, 1), np.nan))
    return mean, std


def training_curves(steps: np.ndarray, curves: dict[str, np.ndarray], path, title: str = "") -> str | None:
    """``curves[name]`` is [S, U] (seeds x updates, NaN where no episode had finished yet)."""
    try:
        plt = pyplot()
    except PlotsUnavailable as error:
        skipped(path, error)
        return None
    fig, axes = plt.subplots(1, len(curves), figsize=(5 * len(curves), 3.6), squeeze=False)
    for ax, (name, values) in zip(axes[0], curves.items()):
        values = np.asarray(values, np.float64)
        mean, std = across_seeds(values)
        ax.plot(steps, mean, color="tab:blue", label=f"mean of {values.shape[0]} seeds")
        ax.fill_between(steps, mean - std, mean + std, color="tab:blue", alpha=0.25, label="+- std")
        ax.set_xlabel("environment steps")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    out = save_figure(fig, path)
    plt.close(fig)
    return out


class HeatmapLayout(NamedTuple):
    """Sizes that keep a heatmap's labels apart: ``font`` (points) of tick labels and cell values,
    ``cell`` (inches per row/column), ``rotate`` the column labels by 90 degrees, ``figsize`` (inches),
    ``annotate`` the cells with their values."""

    font: float
    cell: float
    rotate: bool
    figsize: tuple[float, float]
    annotate: bool


CHAR_WIDTH = 0.62  # a character's width in font sizes (DejaVu Sans, matplotlib's default, is narrower)
LINE_HEIGHT = 1.5  # the room a label needs across its line, in font sizes: a little more than its glyphs


def heatmap_layout(row_labels, col_labels) -> HeatmapLayout:
    """How large to draw a heatmap of these labels so that no two labels overlap.

    The font shrinks from 8 pt with the number of rows/columns beyond 40 (never below 4 pt); each
    cell is at least one label line tall and wide (0.45 in while values are written in the cells,
    which they are up to 24 rows and columns); column labels turn vertical when the longest is
    wider than a cell; the figure grows with the cell count and the longest labels.
    """
    count = max(len(row_labels), len(col_labels), 1)
    font = 8.0 if count <= 40 else max(4.0, 8.0 * 40 / count)
    annotate = count <= 24
    line = LINE_HEIGHT * font / 72
    cell = max(line, 0.45 if annotate else 0.0)
    row_width = max((len(str(label)) for label in row_labels), default=1) * CHAR_WIDTH * font / 72
    col_width = max((len(str(label)) for label in col_labels), default=1) * CHAR_WIDTH * font / 72
    rotate = col_width > 0.9 * cell
    width = row_width + len(col_labels) * cell + 2.2  # + axis title, colour bar and its label
    height = len(row_labels) * cell + (col_width if rotate else line) + 1.4  # + axis and figure titles
    return HeatmapLayout(font, cell, rotate, (max(width, 3.5), max(height, 3.0)), annotate)


def xp_heatmap(
    matrix: np.ndarray,
    path,
    labels=None,
    title: str = "",
    vmax: float | None = None,
    col_labels=None,
    row_title: str = "policy in seat 0",
    col_title: str = "policy in seat 1",
) -> str | None:
    """Cross-play heatmap like the paper's Figure 4: rows = seat 0, columns = seat 1, annotated cells.

    ``labels`` name the rows (and the columns, unless ``col_labels`` is given: a rectangular matrix).
    Font, rotation and figure size follow the label count and length (``heatmap_layout``), so labels
    never overlap; long titles wrap to the figure's width."""
    try:
        plt = pyplot()
    except PlotsUnavailable as error:
        skipped(path, error)
        return None
    matrix = np.asarray(matrix, np.float64)
    rows, cols = matrix.shape
    labels = list(labels) if labels is not None else [str(i) for i in range(rows)]
    col_labels = (
        list(col_labels) if col_labels is not None else (labels if cols == rows else [str(j) for j in range(cols)])
    )
    layout = heatmap_layout(labels, col_labels)
    fig, ax = plt.subplots(figsize=layout.figsize, layout="constrained")
    top = vmax if vmax is not None else max(float(np.nanmax(matrix)) if matrix.size else 1.0, 1.0)
    image = ax.imshow(matrix, cmap="viridis", vmin=min(0.0, float(np.nanmin(matrix))), vmax=top)
    fig.colorbar(image, ax=ax, label="mean team return", shrink=min(1.0, max(0.3, 4.0 / layout.figsize[1])))
    ax.set_xticks(range(cols), col_labels, rotation=90 if layout.rotate else 0, fontsize=layout.font)
    ax.set_yticks(range(rows), labels, fontsize=layout.font)
    ax.set_xlabel(col_title)
    ax.set_ylabel(row_title)
    if layout.annotate:
        for i in range(rows):
            for j in range(cols):
                value = matrix[i, j]
                ax.text(
                    j,
                    i,
                    f"{value:.0f}",
                    ha="center",
                    va="center",
                    fontsize=layout.font,
                    color="white" if value < 0.6 * top else "black",
                )
    if title:
        ax.set_title(textwrap.fill(title, max(20, int(layout.figsize[0] * 72 / (CHAR_WIDTH * 10)))), fontsize=10)
    out = save_figure(fig, path)
    plt.close(fig)
    return out
