"""Checks of the 10-seed Cramped Room studies at 3M: Table 1's control, a layout where the paper reports almost no
gap with either method. SP (table1_cramped_room_sp10/) and its SA half at the same budget (table1_cramped_room_sa10/)."""

from __future__ import annotations

import functools
import itertools
from pathlib import Path

import numpy as np

from .data import both_seats, run
from .folders import CRM10, CRM_SA10
from .registry import check
from .ten_seed_studies import (
    final_matrix,
    paper_beside_intervals,
    partner_means,
    replay_minutes,
    replayed_cells,
    sp_sa_low,
    sp_sa_mean,
    training_curve,
)


def pair_ratios(study: Path, method: str) -> list[tuple[int, int, float]]:
    """Each pair's score (both seat orders) over the mean of its two seeds' self-play, lowest first."""
    m = final_matrix(study, method)
    p = both_seats(m)
    ratios = [(i, j, p[i, j] / ((m[i, i] + m[j, j]) / 2)) for i, j in itertools.combinations(range(len(m)), 2)]
    return sorted(ratios, key=lambda r: r[2])


def pair_range(study: Path, method: str) -> list:
    """The lowest and highest pair score (both seat orders), the pair lowest beside its seeds' self-play (its seeds
    and share), and the lowest and highest self-play."""
    m = final_matrix(study, method)
    p = both_seats(m)
    scores = [p[i, j] for i, j in itertools.combinations(range(len(m)), 2)]
    self_play = np.diag(m)
    return [min(scores), max(scores), *pair_ratios(study, method)[0], float(self_play.min()), float(self_play.max())]


def seed_gaps(m: np.ndarray) -> list[float]:
    """Per seed of a final matrix ``m``: its self-play minus its mean with the others (both seat orders)."""
    with_others = partner_means(both_seats(m))
    return [m[k, k] - with_others[k] for k in range(len(m))]


check("crm10_pairs")(functools.partial(pair_range, CRM10, "sp"))


check("crm10_replay")(functools.partial(replayed_cells, CRM10, "sp"))
check("crm10_replay_wall")(lambda: [replay_minutes(CRM10)])
check("crm_sa10_pairs")(functools.partial(pair_range, CRM_SA10, "sa"))
check("crm_sa10_within")(functools.partial(paper_beside_intervals, CRM_SA10, "sa"))


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
    gaps = seed_gaps(m)
    pairs = [x for score, i, j in lowest for x in (({i, j} - {common}).pop(), score)]
    return [
        common, *pairs, m[common, common],
        sum(g > 0 for g in gaps), len(m), max(gaps), int(np.argmax(gaps)),
        2, m[2, 2], with_others[2],
    ]  # fmt: skip


@check("crm_sa10_by_seed")
def _():
    """How many SA seeds score more with themselves than with the others (``seed_gaps``), the largest such gap and
    its seed; the seeds that score more with the others, then by how much each; the same count for the SP seeds."""
    gaps = seed_gaps(final_matrix(CRM_SA10, "sa"))
    sp_gaps = seed_gaps(final_matrix(CRM10))
    below = [k for k, g in enumerate(gaps) if g < 0]
    return [
        sum(g > 0 for g in gaps), len(gaps), max(gaps), int(np.argmax(gaps)), *below, *(-gaps[k] for k in below),
        sum(g > 0 for g in sp_gaps),
    ]  # fmt: skip


@check("crm_sa10_curve")
def _():
    """SA's training return (sparse, mean over the 10 seeds) at the kept snapshots 122, 152 and 183, with their env
    steps (its episodes start from the state buffer's states too, so it is not SP's measure)."""
    return training_curve(CRM_SA10, method="sa")


@check("crm_sa10_sp_sa")
def _():
    """SP x SA (both seat orders): the 100 pairs' mean beside SP's and SA's cross-play, how many fall below half
    their seeds' self-play, the lowest and highest pair, and the pair lowest beside its two seeds' self-play (its
    share, SP seed, SA seed)."""
    m, low = sp_sa_mean(CRM_SA10), sp_sa_low(CRM10, CRM_SA10)  # row = SP seed, column = SA seed
    sp_self, sa_self = np.diag(final_matrix(CRM10)), np.diag(final_matrix(CRM_SA10, "sa"))
    share = m / ((sp_self[:, None] + sa_self[None, :]) / 2)
    sp_seed, sa_seed = np.unravel_index(int(share.argmin()), share.shape)
    return [
        m.size, m.mean(), run(CRM10, "sp")["xp"]["xp_mean"], run(CRM_SA10, "sa")["xp"]["xp_mean"], int(low.sum()), m.size,
        m.min(), m.max(), share.min(), int(sp_seed), int(sa_seed),
    ]  # fmt: skip
