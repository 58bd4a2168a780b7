"""Checks of the 10-seed Asymm. Advantages SP study at 3M (table1_asymm_advantages_sp10/): Table 1's other control, a
layout where the paper reports no gap, and where our seeds split over how many pots they use (roles.md)."""

from __future__ import annotations

import functools
import itertools
import math
import re

import numpy as np

from .data import both_seats, matrix, md_tables_by_heading
from .folders import AA10
from .registry import check
from .ten_seed_studies import (
    cell_count,
    cell_share,
    final_matrix,
    low_pairs,
    seat_shares,
    snapshot_env_steps,
    training_curve,
)

#: roles.md's columns, by the headers roles.py writes (``table_header``): a column added or moved there changes nothing
#: here, a renamed one fails with its name.
SEED, RETURN = "seed", "return"
ONIONS, DELIVERIES = "onions to pot (seat 0 share)", "deliveries (seat 0 share)"
TOP_FILLED = "onions into the top pot (seat 0, seat 1)"
TOP_PLATED = "soups plated from the top pot (seat 0, seat 1)"
WAITING = "steps a cooked soup waits (top pot, bottom pot)"
PAIRS_HEADING = "Cross-play pairs at update 183"
TWO_POTS = 0.9  # a seed "uses both pots" when its seat 1 puts less than this share of its onions into the top pot
FAILING_SERVER = 150  # the score below which a one-pot seed's seat 0 is said to fail with a two-pot seat 1


@functools.cache
def roles_md() -> dict[str, list[dict[str, str]]]:
    """roles.md's tables by the ``##`` heading above each, every row as {column header: cell}."""
    return md_tables_by_heading(AA10 / "roles.md")


def seed_rows(update: int) -> list[dict[str, str]]:
    """roles.md's table of every seed's self-play at ``update`` (under "## Update <update> ...")."""
    (rows,) = [rows for heading, rows in roles_md().items() if re.fullmatch(rf"Update {update}\b.*", heading)]
    return rows


def pair_table() -> dict[tuple[int, int], dict[str, str]]:
    """roles.md's cross-play pairs at update 183, by (seat-0 seed, seat-1 seed)."""
    return {tuple(int(k) for k in row[SEED].split(" × ")): row for row in roles_md()[PAIRS_HEADING]}


def top_pot_share(row: dict[str, str]) -> float:
    """Seat 1's share of its onions that went into the top pot (the onions are seat 1's in every seed: aa10_roles)."""
    return seat_shares(row[TOP_FILLED])[1]


def two_pot_seeds(update: int = 183) -> list[int]:
    return [int(row[SEED]) for row in seed_rows(update) if top_pot_share(row) < TWO_POTS]


def groups() -> tuple[list[int], list[int]]:
    """(seeds using the top pot only, seeds using both) at update 183."""
    both = two_pot_seeds()
    return [k for k in range(10) if k not in both], both


def failing_servers(m: np.ndarray, one: list[int], both: list[int]) -> list[int]:
    """The top-pot-only seeds whose seat 0 scores below ``FAILING_SERVER`` with every two-pot seed's seat 1."""
    return [k for k in one if m[k, both].max() < FAILING_SERVER]


def pair_scores(m: np.ndarray, a: list[int], b: list[int]) -> list[float]:
    """Both-seat-orders scores of the pairs with one seed from ``a`` and one from ``b`` (``a`` == ``b``: within)."""
    p = both_seats(m)
    if a == b:
        return [p[i, j] for i, j in itertools.combinations(a, 2)]
    return [p[i, j] for i in a for j in b]


@check("aa10_pairs")
def _():
    """Every pair's score (both seat orders): lowest and highest; the lowest pair and its share of its two seeds'
    self-play; the seeds' self-play, lowest and highest."""
    m = final_matrix(AA10)
    p = both_seats(m)
    pairs = sorted((p[i, j], i, j) for i, j in itertools.combinations(range(len(m)), 2))
    score, i, j = pairs[0]
    return [
        score,
        pairs[-1][0],
        i,
        j,
        score / ((m[i, i] + m[j, j]) / 2),
        float(np.diag(m).min()),
        float(np.diag(m).max()),
    ]


@check("aa10_roles")
def _():
    """At update 183, in every seed's self-play: seat 0's largest share of the onions potted, its smallest share of the
    deliveries; the seeds whose seat 1 fills both pots, its top-pot share (lowest, highest), and the others' lowest;
    every seed's seat 0 plates from the pots its seat 1 fills (largest gap between the two shares); the largest share
    of steps a cooked soup waits in either pot."""
    rows = seed_rows(183)
    onions = [cell_share(row[ONIONS]) for row in rows]
    delivered = [cell_share(row[DELIVERIES]) for row in rows]
    both = two_pot_seeds()
    top = {int(row[SEED]): top_pot_share(row) for row in rows}
    plated = {int(row[SEED]): seat_shares(row[TOP_PLATED])[0] for row in rows}
    return [
        max(onions), min(delivered),
        *both, min(top[k] for k in both), max(top[k] for k in both), min(top[k] for k in top if k not in both),
        max(abs(plated[k] - top[k]) for k in top), max(max(seat_shares(row[WAITING])) for row in rows),
    ]  # fmt: skip


@check("aa10_groups")
def _():
    """The self-play (500 episodes) of the seeds using the top pot only and of those using both, lowest and highest;
    the mean pair score within each group and across them; the failing pairs of 45 and how many join the groups."""
    m = final_matrix(AA10)
    one, both = groups()
    self_play = np.diag(m)
    low = low_pairs(AA10)
    across = sum((i in both) != (j in both) for i, j, _ in low)
    return [
        min(self_play[one]), max(self_play[one]), min(self_play[both]), max(self_play[both]),
        np.mean(pair_scores(m, one, one)), np.mean(pair_scores(m, both, both)), np.mean(pair_scores(m, one, both)),
        len(low), math.comb(len(m), 2), across,
    ]  # fmt: skip


@check("aa10_seats")
def _():
    """The cross-group pairs by seat order (row = seat 0): a top-pot-only seed's seat 0 with a two-pot seed's seat 1,
    lowest and highest, and the reverse order, lowest and highest; the top-pot-only seeds whose seat 0 scores below
    150 with every two-pot seed's seat 1, and the highest of those scores."""
    m = final_matrix(AA10)
    one, both = groups()
    plater_one = m[np.ix_(one, both)]
    plater_both = m[np.ix_(both, one)]
    failing = failing_servers(m, one, both)
    return [
        plater_one.min(), plater_one.max(), plater_both.min(), plater_both.max(),
        *failing, FAILING_SERVER, max(m[k, both].max() for k in failing),
    ]  # fmt: skip


def pair_roles(seat0: int, seat1: int) -> list:
    """roles.md's cross-play pair ``seat0 × seat1`` (32 episodes), in the order the page states it: the return, the
    onions potted, seat 1's share of them into the top pot, seat 0's share of its plated soups from the top pot, the
    soups delivered, the share of steps a cooked soup waits in the top pot and in the bottom pot."""
    row = pair_table()[(seat0, seat1)]
    return [
        float(row[RETURN]), cell_count(row[ONIONS]), seat_shares(row[TOP_FILLED])[1], seat_shares(row[TOP_PLATED])[0],
        cell_count(row[DELIVERIES]), *seat_shares(row[WAITING]),
    ]  # fmt: skip


for _pair in ((1, 2), (1, 6)):
    check(f"aa10_pair_{_pair[0]}{_pair[1]}")(functools.partial(pair_roles, *_pair))

#: roles.md's pairs of a one-pot seed serving (seat 0) with a two-pot seed filling (seat 1): seeds 4 and 8, which
#: fail there in the matrix, and seeds 0, 3, 5 and 7, which do not.
SLOW_SERVERS = ((4, 9), (4, 2), (4, 6), (8, 2), (8, 6), (8, 9))
OTHER_SERVERS = ((0, 2), (3, 6), (5, 6), (7, 2))


@check("aa10_servers")
def _():
    """Seeds 4 and 8 serving with a two-pot filler beside seeds 0, 3, 5 and 7 doing the same (roles.md's pairs): the
    share of seat 0's plated soups from the top pot (lowest, highest, each group; the other servers' seeds before
    theirs), the soups delivered in 32 episodes, the return, the share of steps a cooked soup waits in the top pot and
    in the bottom pot (each: lowest, highest, each group)."""
    one, both = groups()
    failing = failing_servers(final_matrix(AA10), one, both)  # as aa10_seats names them
    assert {seat0 for seat0, _ in SLOW_SERVERS} <= set(failing), failing  # seed 1, the third, has its own pairs
    assert {seat0 for seat0, _ in OTHER_SERVERS} == set(one) - set(failing)  # every other one-pot seed serves once
    assert {seat1 for _, seat1 in (*SLOW_SERVERS, *OTHER_SERVERS)} <= set(both)  # every filler fills both pots
    pairs = pair_table()
    out = []
    columns = (
        lambda row: seat_shares(row[TOP_PLATED])[0],
        lambda row: cell_count(row[DELIVERIES]),
        lambda row: float(row[RETURN]),
        lambda row: seat_shares(row[WAITING])[0],
        lambda row: seat_shares(row[WAITING])[1],
    )
    for column in columns:
        for group in (SLOW_SERVERS, OTHER_SERVERS):
            values = [column(pairs[key]) for key in group]
            out += [min(values), max(values)]
    return [*out[:2], *(seat0 for seat0, _ in OTHER_SERVERS), *out[2:]]  # the other servers named before their shares


@check("aa10_reverse")
def _():
    """The other seat order in roles.md (a two-pot seed serving, a one-pot seed filling: 2 × 1, 6 × 1, 9 × 4): the
    filler's lowest top-pot share and the server's lowest share of its plated soups from the top pot."""
    rows = [pair_table()[key] for key in ((2, 1), (6, 1), (9, 4))]
    return [min(seat_shares(row[TOP_FILLED])[1] for row in rows), min(seat_shares(row[TOP_PLATED])[0] for row in rows)]


@check("aa10_emerge")
def _():
    """The two-pot seeds' seat-1 top-pot share at updates 92, 122 and 152 (each seed's, in seed order), each update
    followed by its env steps in millions."""
    out = []
    for update in (92, 122, 152):
        rows = {int(row[SEED]): row for row in seed_rows(update)}
        out += [*(top_pot_share(rows[k]) for k in two_pot_seeds()), snapshot_env_steps(update, AA10)]
    return out


@check("aa10_two_pot_counts")
def _():
    """The share below which a seed counts as using both pots, then how many do at updates 92, 122, 152 and 183."""
    return [TWO_POTS, *(len(two_pot_seeds(u)) for u in (92, 122, 152, 183))]


@check("aa10_curve")
def _():
    """The training return (sparse, mean over the 10 seeds) at the kept snapshots 122, 152 and 183, with their env
    steps."""
    return training_curve(AA10)


@check("aa10_replay_cause")
def replay_cause() -> list:
    """Seed 0 with seed 6, the one cell of the row replay that differs from the study's: in the study's matrix, in the
    replay (``ocv2 xp``, one file against one), and in seed 0's row played with the ten files stacked, as the study
    plays it, without and with recording (as_the_study_played.py's csv)."""
    replayed = AA10 / "replay_from_policies"
    batched = matrix(replayed / "as_the_study_played.csv")
    return [final_matrix(AA10)[0, 6], matrix(replayed / "matrix.csv")[0, 6], batched[0, 6], batched[1, 6]]
