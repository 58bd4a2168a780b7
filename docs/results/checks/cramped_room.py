"""Checks of the 10-seed Cramped Room SP study at 3M (table1_cramped_room_sp10/): Table 1's control, a layout where
the paper reports almost no gap."""

from __future__ import annotations

import itertools

import numpy as np

from .data import both_seats
from .folders import CRM10
from .registry import check
from .ten_seed_studies import final_matrix, partner_means, training_curve


def pair_ratios() -> list[tuple[int, int, float]]:
    """Each pair's score (both seat orders) over the mean of its two seeds' self-play, lowest first."""
    m = final_matrix(CRM10)
    p = both_seats(m)
    ratios = [(i, j, p[i, j] / ((m[i, i] + m[j, j]) / 2)) for i, j in itertools.combinations(range(len(m)), 2)]
    return sorted(ratios, key=lambda r: r[2])


@check("crm10_pairs")
def _():
    m = final_matrix(CRM10)
    p = both_seats(m)
    scores = [p[i, j] for i, j in itertools.combinations(range(len(m)), 2)]
    lowest = pair_ratios()[0]
    self_play = np.diag(m)
    return [min(scores), max(scores), *lowest, float(self_play.min()), float(self_play.max())]


@check("crm10_curve")
def _():
    """The training return (sparse, mean over the 10 seeds) at the kept snapshots 122, 152 and 183, with their env
    steps: still rising at the stop."""
    return training_curve(CRM10)


@check("crm10_by_seed")
def _():
    """The seed all three lowest pairs (by score, both seat orders) hold, each pair's other seed and score, that
    seed's self-play; how many seeds score more with themselves than with the others (each seed's gap: self-play
    minus its mean with the 9 others, both seats), the largest such gap and its seed; seed 2's self-play beside its
    mean with the others."""
    m = final_matrix(CRM10)
    p = both_seats(m)
    lowest = sorted((p[i, j], i, j) for i, j in itertools.combinations(range(len(m)), 2))[:3]
    (common,) = set.intersection(*({i, j} for _, i, j in lowest))
    with_others = partner_means(p)
    gaps = [m[k, k] - with_others[k] for k in range(len(m))]
    pairs = [x for score, i, j in lowest for x in (({i, j} - {common}).pop(), score)]
    return [
        common, *pairs, m[common, common],
        sum(g > 0 for g in gaps), len(m), max(gaps), int(np.argmax(gaps)),
        2, m[2, 2], with_others[2],
    ]  # fmt: skip
