"""Checks of the 10-seed Forced Coord. studies at 3M, SP (table1_forced_coord_sp10/) and SA beside it
(table1_forced_coord_sa10/): the verdicts and the middle counters each seed hands its onions and plates over on."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from .data import both_seats, interval, md_tables, pairs, run, sp_xp
from .folders import FC10, FC_SA10
from .registry import L, check
from .ten_seed_studies import (
    below_half,
    final_matrix,
    gap_growth,
    low_pairs,
    sp_sa_low,
    sp_sa_mean,
)

# --- Forced Coord. SP, 10 seeds at 3M env steps: the verdict and the plate counter each seed hands plates over


def handover_counters(study: Path = FC10, item: str = "plates") -> list[int]:
    """Per seed (the study's roles.md at update 183), the middle counter (0, 1, 2 = (2,1), (2,2), (2,3)) most of its
    onions or plates are handed over on (the first table: the seeds' self-play; a second holds cross-play pairs)."""
    table = md_tables(study / "roles.md")[0]
    column = {"onions": 1, "plates": 3}[item]
    return [int(np.argmax([float(x) for x in row[column].split(" ")[0].split("/")])) for row in table]


def fc10_plate_counters() -> list[int]:
    return handover_counters(FC10, "plates")


def by_convention(m: np.ndarray, convention: list) -> tuple[list[float], list[float]]:
    """Both-seat-order scores of a K x K matrix's pairs: those whose two seeds share ``convention`` (one value per
    seed), and the rest."""
    p, ij = both_seats(m), list(itertools.combinations(range(len(m)), 2))
    same = [p[i, j] for i, j in ij if convention[i] == convention[j]]
    other = [p[i, j] for i, j in ij if convention[i] != convention[j]]
    return same, other


def fc10_by_counter() -> tuple[list[float], list[float]]:
    """Both-seat-order scores of the 45 pairs: those whose seeds hand plates over on the same counter, the rest."""
    return by_convention(final_matrix(FC10), fc10_plate_counters())


@check("fc10_plates")
def _():
    counter = fc10_plate_counters()
    groups = [[k for k in range(10) if counter[k] == c] for c in range(3)]
    same, other = fc10_by_counter()
    low = low_pairs(FC10)
    crossing = sum(counter[i] != counter[j] for i, j, _ in low)
    return [
        L, L, *groups[0], L, L, *groups[1], L, L, *groups[2],  # counter (2,1), (2,2), (2,3): labels
        len(same), np.mean(same), min(same), max(same),
        len(other), np.mean(other), min(other), max(other),
        crossing, len(low),
    ]  # fmt: skip


# --- Forced Coord. SA, 10 seeds at 3M env steps, beside the 10 SP seeds: the verdict and the counters each seed uses


def conventions(study: Path) -> list[tuple[int, int]]:
    """Per seed of a Forced Coord. study, (onion counter, plate counter) it hands over on (0, 1, 2 = (2,1), (2,2),
    (2,3))."""
    return list(zip(handover_counters(study, "onions"), handover_counters(study, "plates"), strict=True))


def onions_on_21(study: Path) -> list[int]:
    """The seeds of a Forced Coord. study that hand their onions over on (2,1)."""
    return [k for k, (onion, _) in enumerate(conventions(study)) if onion == 0]


@check("fc_sa10_conventions")
def _():
    plates = handover_counters(FC_SA10, "plates")
    return [
        *onions_on_21(FC_SA10), L, L, L, L,  # the seeds whose onions cross on (2,1); the others on (2,2)
        sum(onion == 1 for onion, _ in conventions(FC10)), L, L,  # all 10 SP seeds on (2,2)
        *[x for c in range(3) for x in [L, L, *[k for k in range(10) if plates[k] == c]]],
        len(set(conventions(FC_SA10))), 10,
        len(set(conventions(FC10))),
    ]  # fmt: skip


@check("fc_sa10_by_convention")
def _():
    m, seeds = final_matrix(FC_SA10, "sa"), conventions(FC_SA10)
    same, other = by_convention(m, seeds)
    low = low_pairs(FC_SA10, "sa")
    crossing = sum(seeds[i] != seeds[j] for i, j, _ in low)
    return [
        len(same), np.mean(same), min(same), max(same),
        len(other), np.mean(other), min(other), max(other),
        crossing, len(low),
    ]  # fmt: skip


def by_distance(scored: list[tuple[int, float, bool]]) -> list:
    """Pairs given as (distance between their seeds' plate counters, score, failed), by that distance (0: the same
    counter, 1: neighbours, 2: (2,1) against (2,3)): per distance, how many, their mean score and how many fail."""
    out = []
    for distance in range(3):
        group = [(score, failed) for d, score, failed in scored if d == distance]
        far = [L, L, L, L] if distance == 2 else []  # "(2,1) against (2,3)"
        out += [len(group), *far, np.mean([score for score, _ in group]), sum(failed for _, failed in group)]
    return out


def by_plate_distance(study: Path, method: str) -> list:
    """``by_distance`` of the 45 pairs of a Forced Coord. population (scores: both seat orders)."""
    m, plates = final_matrix(study, method), handover_counters(study, "plates")
    p = both_seats(m)
    return by_distance(
        [
            (abs(plates[i] - plates[j]), p[i, j], below_half(p[i, j], m[i, i], m[j, j]))
            for i, j in itertools.combinations(range(len(m)), 2)
        ]
    )


@check("fc_plate_distance")
def _():
    return [*by_plate_distance(FC10, "sp"), *by_plate_distance(FC_SA10, "sa")]


@check("fc_sa10_pair_handovers")
def _():
    rows = md_tables(FC_SA10 / "roles.md")[1]
    onions, plates, returns = ([float(row[k]) for row in rows] for k in (2, 4, 7))
    low, high = slice(0, 6), slice(6, 10)  # three failing pairs in both orders; then 2,4 and 0,7 in both
    return [
        min(onions[low]), max(onions[low]), min(plates[low]), max(plates[low]), max(returns[low]),
        L, L, L, L, min(plates[high]), max(plates[high]), min(returns[high]),  # the pairs 2-4 and 0-7: labels
    ]  # fmt: skip


@check("fc_sa10_table")
def _():
    sp, sa = run(FC10, "sp")["xp"], run(FC_SA10, "sa")["xp"]
    rows = [
        x
        for key, mean in (("sp", "sp_mean"), ("xp", "xp_mean"), ("gap", "gap"))
        for block in (sp, sa)
        for x in (block[mean], *interval(block, key))
    ]
    return [
        *rows,
        min(pairs(final_matrix(FC10))), min(pairs(final_matrix(FC_SA10, "sa"))),
        len(low_pairs(FC10)), 45, len(low_pairs(FC_SA10, "sa")), 45,
        len(set(conventions(FC10))), len(set(conventions(FC_SA10))),
    ]  # fmt: skip


@check("fc_sa10_sp_sa")
def _():
    m, low = sp_sa_mean(FC_SA10), sp_sa_low(FC10, FC_SA10)  # row = SP seed, column = SA seed, both seat orders
    sp, sa = conventions(FC10), conventions(FC_SA10)  # (onion counter, plate counter) per seed
    cells = list(itertools.product(range(len(sp)), range(len(sa))))
    distances = by_distance([(abs(sp[i][1] - sa[j][1]), m[i, j], low[i, j]) for i, j in cells])
    same = [m[i, j] for i, j in cells if sp[i] == sa[j]]
    return [
        m.size, m.mean(), run(FC10, "sp")["xp"]["xp_mean"], run(FC_SA10, "sa")["xp"]["xp_mean"], int(low.sum()), m.size,
        *distances, len(same), np.mean(same), min(same),
    ]  # fmt: skip


@check("fc_sa10_growth")
def _():
    # The SP snapshots' cross-play lies in the SA study's folder.
    return gap_growth((FC10, "sp", FC_SA10), (FC_SA10, "sa", FC_SA10))


def failing_cells(m: np.ndarray) -> int:
    """Ordered cells (i in seat 0, j in seat 1, i != j) of a K x K matrix below half the mean of the two seeds'
    self-play: a pair can fail in one seat order only."""
    d = np.diag(m)
    return int((below_half(m, d[:, None], d[None, :]) & ~np.eye(len(m), dtype=bool)).sum())


@check("fc_sa10_seats")
def _():
    sa, sp = final_matrix(FC_SA10, "sa"), final_matrix(FC10)
    return [failing_cells(sa), 90, failing_cells(sp), 90]


@check("fc_sa10_rest")
def _():
    on_21 = onions_on_21(FC_SA10)
    rest = [k for k in range(10) if k not in on_21]
    return [*on_21, len(rest), sp_xp(final_matrix(FC_SA10, "sa"), rest)[2], run(FC10, "sp")["xp"]["gap"]]
