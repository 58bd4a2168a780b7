"""The 4-seed bootstrap, exactly: every resample of a 4 x 4 cross-play matrix's seeds that
population.xp.bootstrap_block draws from (the page's "Intervals at 4 seeds")."""

from __future__ import annotations

import itertools
import math

import numpy as np


def resamples(m: np.ndarray) -> np.ndarray:
    """Every ordered resample of the K seeds with replacement that has a cross-play cell (K^K - K of them),
    as rows (sp, xp, gap): the distribution that population.xp.bootstrap_block samples 2,000 times."""
    k = len(m)
    out = []
    for draw in itertools.product(range(k), repeat=k):
        draw = np.array(draw)
        same = draw[:, None] == draw[None, :]
        if same.all():
            continue
        cells = m[draw[:, None], draw[None, :]]
        sp, xp = cells[same].mean(), cells[~same].mean()
        out.append((sp, xp, sp - xp))
    return np.array(out)


def gap_at_most_zero(m: np.ndarray) -> list[int]:
    r = resamples(np.asarray(m, float))
    return [int((r[:, 2] <= 1e-12).sum()), len(r)]


def gap_zero_pattern(m):
    """(seed drawn three times, seed drawn once) of the resamples with a gap at or below 0, when they are one
    such pattern (else NaN, NaN)."""
    m = np.asarray(m, float)
    found = set()
    for draw in itertools.product(range(len(m)), repeat=len(m)):
        draw = np.array(draw)
        same = draw[:, None] == draw[None, :]
        if same.all():
            continue
        cells = m[draw[:, None], draw[None, :]]
        if cells[same].mean() - cells[~same].mean() <= 1e-12:
            counts = np.bincount(draw, minlength=len(m))
            found.add(
                (int(counts.argmax()), int(np.flatnonzero((counts > 0) & (counts < counts.max()))[0]))
                if counts.max() == 3
                else None
            )
    return found.pop() if len(found) == 1 and None not in found else (math.nan, math.nan)
