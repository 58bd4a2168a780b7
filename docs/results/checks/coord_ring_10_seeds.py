"""Checks of the 10-seed Coordination Ring studies at 3M: SP (table1_coord_ring_sp10/, its interim snapshots and
its final cross-play), then SA beside it (table1_coord_ring_sa10/)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from .data import both_seats, interval, matrix, pairs, run, sp_xp
from .folders import SA10, SP10
from .registry import check
from .ten_seed_studies import (
    final_matrix,
    low_pairs,
    partner_means,
    replay_minutes,
    replayed_cells,
    roles_tables,
    snapshot_env_steps,
    sp_sa_low,
    sp_sa_mean,
)

# --- the 10-seed Coordination Ring SP population (table1_coord_ring_sp10/: interim snapshots)


def sp10_xp(update: int) -> list:
    """Snapshot ``update``: its env steps, SP, XP, gap (both seat orders), the lowest pair and its score."""
    m = matrix(SP10 / f"xp_update{update}.csv")
    sp, xp, gap = sp_xp(m)
    p = both_seats(m)
    i, j = min(itertools.combinations(range(len(m)), 2), key=lambda ij: p[ij])
    return [update, snapshot_env_steps(update), sp, xp, gap, i, j, p[i, j]]


def sp10_direction_and_xp(update: int) -> list:
    """Clockwise shares (seat 0) from least to most clockwise seed, and Pearson's r over the 45 pairs between
    a pair's score (both seat orders) and the difference of its seeds' clockwise shares."""
    cw = [row[0] for row in roles_tables()[update]]
    p = both_seats(matrix(SP10 / f"xp_update{update}.csv"))
    ij = list(itertools.combinations(range(len(cw)), 2))
    r = np.corrcoef([abs(cw[i] - cw[j]) for i, j in ij], [p[i, j] for i, j in ij])[0, 1]
    low, high = int(np.argmin(cw)), int(np.argmax(cw))
    return [low, cw[low], high, cw[high], len(ij), r]


def sp10_delivery_shares(update: int) -> list:
    """Seat 0's share of the deliveries per seed: the range over the seeds, then the seed furthest from 0.5."""
    shares = [row[2][3][0] for row in roles_tables()[update]]
    far = max(range(len(shares)), key=lambda k: abs(shares[k] - 0.5))
    rest = [x for k, x in enumerate(shares) if k != far]
    return [min(rest), max(rest), far, shares[far]]


@check("sp10_xp92")
def _():
    return sp10_xp(92)


@check("sp10_xp122")
def _():
    return sp10_xp(122)


@check("sp10_direction")
def _():
    return [*sp10_direction_and_xp(122), sp10_direction_and_xp(92)[-1], 92]


@check("sp10_clockwise_pair")
def _():
    cw = [row[0] for row in roles_tables()[122]]
    p = both_seats(matrix(SP10 / "xp_update122.csv"))
    return [0, 3, cw[0], cw[3], p[0, 3], 122]


@check("sp10_roles")
def _():
    return sp10_delivery_shares(122)


# --- the 10-seed population finished: 3.0M env steps per seed, the study's 10 x 10 cross-play (500 episodes per pair)


def pair_r(measure, study: Path = SP10, method: str = "sp") -> float:
    """Pearson's r over the 45 pairs between a pair's final score and |difference| of ``measure`` (per seed)."""
    p = both_seats(final_matrix(study, method))
    ij = list(itertools.combinations(range(len(p)), 2))
    return np.corrcoef([abs(measure[i] - measure[j]) for i, j in ij], [p[i, j] for i, j in ij])[0, 1]


def seed_measures(update: int = 183, study: Path = SP10) -> dict:
    """Per seed at ``update`` (seat 0): clockwise share, delivery share, share of onions into the first pot."""
    rows = roles_tables(study)[update]
    return {"cw": [r[0] for r in rows], "deliveries": [r[2][3][0] for r in rows], "pot": [r[3][0] for r in rows]}


@check("sp10_growth")
def _():
    return [sp10_xp(92)[4], 92, sp10_xp(122)[4], 122, run(SP10, "sp")["xp"]["gap"], 183]


@check("sp10_cw183")
def _():
    cw = seed_measures()["cw"]
    rest = [x for k, x in enumerate(cw) if k not in (1, 6)]
    return [1, 6, cw[1], cw[6], min(rest), max(rest)]


@check("sp10_interval_vs_pairs")
def _():
    xp = run(SP10, "sp")["xp"]
    every = pairs(final_matrix())
    return [10, *interval(xp, "xp"), min(every), max(every)]


@check("sp10_low_pairs")
def _():
    low = low_pairs()
    return [len(low), 45, *[x for pair in low for x in pair]]


@check("sp10_pots")
def _():
    pot = seed_measures()["pot"]
    first = [k for k, x in enumerate(pot) if x >= 0.95]
    second = [k for k, x in enumerate(pot) if x <= 0.05]
    p = both_seats(final_matrix())
    mixed = [x for x in pot if 0.05 < x < 0.95]
    return [*first, *second, min(mixed), max(mixed), 1, 6, p[1, 6], 0, 3, p[0, 3], 0, 6, p[0, 6]]


@check("sp10_pots_early")
def _():
    pot = seed_measures(92)["pot"]
    single = [k for k, x in enumerate(pot) if x >= 0.95 or x <= 0.05]
    return [*single, snapshot_env_steps(92), 0, pot[0], 92]


@check("sp10_pair_r")
def _():
    m = seed_measures()
    return [pair_r(m["pot"]), pair_r(m["cw"]), pair_r(m["deliveries"])]


@check("sp10_seed3")
def _():
    p = both_seats(final_matrix())
    others = [j for j in range(10) if j != 3]
    means = partner_means(p)
    nxt = sorted(range(10), key=lambda k: means[k])[1]
    return [
        3,
        means[3],
        final_matrix()[3, 3],
        min(p[3, j] for j in others),
        max(p[3, j] for j in others),
        nxt,
        means[nxt],
    ]


# --- the 10-seed SA population (table1_coord_ring_sa10/), beside the 10 SP seeds at the same budget


def sa10_final() -> np.ndarray:
    return final_matrix(SA10, "sa")


@check("sa10_pairs")
def _():
    p = both_seats(sa10_final())
    i, j = min(itertools.combinations(range(10), 2), key=lambda ij: p[ij])
    return [
        len(sa10_low_pairs()),
        45,
        min(pairs(sa10_final())),
        max(pairs(sa10_final())),
        i,
        j,
        min(pairs(final_matrix())),
    ]


def sa10_low_pairs() -> list[tuple[int, int, float]]:
    return low_pairs(SA10, "sa")


@check("sa10_table")
def _():
    sp, sa = run(SP10, "sp")["xp"], run(SA10, "sa")["xp"]
    cw = [seed_measures(183, study)["cw"] for study in (SP10, SA10)]
    return [
        sp["sp_mean"],
        *interval(sp, "sp"),
        sa["sp_mean"],
        *interval(sa, "sp"),
        sp["xp_mean"],
        *interval(sp, "xp"),
        sa["xp_mean"],
        *interval(sa, "xp"),
        sp["gap"],
        *interval(sp, "gap"),
        sa["gap"],
        *interval(sa, "gap"),
        min(pairs(final_matrix())),
        min(pairs(sa10_final())),
        len(low_pairs()),
        45,
        len(sa10_low_pairs()),
        45,
        min(cw[0]),
        max(cw[0]),
        min(cw[1]),
        max(cw[1]),
    ]


def _sa10_pot_groups() -> tuple[list[int], list[int]]:
    """SA seeds (seat 0, update 183) with at most 0.1 of their onions into the first pot, and the rest."""
    pot = seed_measures(183, SA10)["pot"]
    return [k for k, x in enumerate(pot) if x <= 0.1], [k for k, x in enumerate(pot) if x > 0.1]


@check("sa10_pots")
def _():
    pot = seed_measures(183, SA10)["pot"]
    second, mixed = _sa10_pot_groups()
    one_pot_sp = [k for k, x in enumerate(seed_measures()["pot"]) if x >= 0.95]
    return [
        *second,
        min(pot[k] for k in second),
        max(pot[k] for k in second),
        min(pot[k] for k in mixed),
        max(pot[k] for k in mixed),
        len(one_pot_sp),
    ]


@check("sa10_pot_pairs")
def _():
    m = seed_measures(183, SA10)
    p = both_seats(sa10_final())
    second, mixed = _sa10_pot_groups()
    same = np.mean([p[i, j] for i, j in itertools.combinations(second, 2)])
    across = np.mean([p[i, j] for i in second for j in mixed])
    return [pair_r(m["pot"], SA10, "sa"), pair_r(m["cw"], SA10, "sa"), same, across]


@check("sa10_sp_sa")
def _():
    m = sp_sa_mean()
    with_sa = m.mean(axis=1)
    with_sp = partner_means(both_seats(final_matrix()))
    odd = [1, 3, 6]
    rest = [k for k in range(10) if k not in odd]
    low = sp_sa_low()
    return [
        m.size,
        m.mean(),
        len(rest),
        min(with_sa[k] for k in rest),
        max(with_sa[k] for k in rest),
        min(with_sp[k] for k in rest),
        max(with_sp[k] for k in rest),
        *odd,
        *[with_sa[k] for k in odd],
        *[with_sp[k] for k in odd],
        int(low.sum()),
        m.size,
        int(low[1].sum()),
        1,
        int(low[6].sum()),
        6,
        m.min(),
    ]


@check("sp10_replay")
def _():
    """The 10 x 10 matrix played again from the published update-183 files (``replayed_cells``) and the replay's
    minutes."""
    return [*replayed_cells(SP10), replay_minutes(SP10)]
