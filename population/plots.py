"""Pictures of results: training curves (mean +- std across seeds) and cross-play heatmaps.

matplotlib is an optional extra (``ocv2[plots]``). Without it ``training_curves`` and ``xp_heatmap``
draw nothing, say so on stderr and return None, so a training run still finishes with its numbers.
"""

from __future__ import annotations

import logging

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


def xp_heatmap(matrix: np.ndarray, path, labels=None, title: str = "", vmax: float | None = None,
               col_labels=None) -> str | None:
    """Cross-play heatmap like the paper's Figure 4: rows = seat 0, columns = seat 1, annotated cells.

    ``labels`` name the rows (and the columns, unless ``col_labels`` is given: a rectangular matrix)."""
    try:
        plt = pyplot()
    except PlotsUnavailable as error:
        skipped(path, error)
        return None
    matrix = np.asarray(matrix, np.float64)
    rows, cols = matrix.shape
    labels = labels or [str(i) for i in range(rows)]
    col_labels = col_labels or (labels if cols == rows else [str(j) for j in range(cols)])
    size = max(3.5, 0.55 * max(rows, cols) + 2)
    fig, ax = plt.subplots(figsize=(size, size * 0.85))
    top = vmax if vmax is not None else max(float(np.nanmax(matrix)) if matrix.size else 1.0, 1.0)
    image = ax.imshow(matrix, cmap="viridis", vmin=min(0.0, float(np.nanmin(matrix))), vmax=top)
    fig.colorbar(image, ax=ax, label="mean team return")
    ax.set_xticks(range(cols), col_labels, rotation=90 if cols > 8 else 0)
    ax.set_yticks(range(rows), labels)
    ax.set_xlabel("policy in seat 1")
    ax.set_ylabel("policy in seat 0")
    if max(rows, cols) <= 16:
        for i in range(rows):
            for j in range(cols):
                value = matrix[i, j]
                ax.text(j, i, f"{value:.0f}", ha="center", va="center", fontsize=8,
                        color="white" if value < 0.6 * top else "black")
    if title:
        ax.set_title(title)
    out = save_figure(fig, path)
    plt.close(fig)
    return out
