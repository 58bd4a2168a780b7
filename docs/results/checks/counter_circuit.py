"""Checks of the 10-seed Counter Circuit studies at 3M: SP (table1_counter_circuit_sp10/) and SA beside it
(table1_counter_circuit_sa10/)."""

from __future__ import annotations

import csv
import itertools
from pathlib import Path

import numpy as np

from .data import both_seats, claim_row, float_or_nan, matrix, md_tables, millions, run, sp_xp
from .folders import CC10, CC_SA10
from .registry import L, check
from .ten_seed_studies import (
    cell_count,
    failing_pairs,
    final_matrix,
    final_numbers,
    gap_growth,
    low_pair_numbers,
    low_pairs,
    pair_rows,
    paper_beside_intervals,
    snapshot_env_steps,
    sp_sa_low,
    sp_sa_mean,
)

# --- Table 1 Counter Circuit SP, 10 seeds at 3M env steps


@check("cc10_final")
def _():
    return final_numbers(CC10, "sp")


@check("cc10_within")
def _():
    return paper_beside_intervals(CC10, "sp")


@check("cc10_low_pairs")
def _():
    return low_pair_numbers(CC10)


def cc_roles(study: Path = CC10) -> tuple[list[list[str]], dict]:
    """A Counter Circuit study's roles.md: the seeds' rows at its final update and {(seat-0 seed, seat-1 seed): row}
    of its cross-play pairs (its first two tables; the tables of later snapshots follow them)."""
    seeds, pairs = md_tables(study / "roles.md")[:2]
    return seeds, pair_rows(pairs)


def two_shares(cell: str) -> tuple[float, float]:
    """A roles table's "<seat 0>, <seat 1>" cell."""
    first, second = cell.split(",")
    return float(first), float(second)


def cc_conventions(study: Path = CC10) -> list[tuple[str, str]]:
    """Per seed, (pot, direction) of its self-play: "left" where seat 0 puts most of its onions into the left pot,
    "cw" where more than half of seat 0's moves round the island go clockwise."""
    seeds, _ = cc_roles(study)
    return [
        ("left" if two_shares(row[8])[0] >= 0.5 else "right", "cw" if two_shares(row[5])[0] > 0.5 else "ccw")
        for row in seeds
    ]


def cc_pairs_by_convention(study: Path = CC10, method: str = "sp", m: np.ndarray | None = None) -> dict:
    """Every pair's score (both seat orders) and whether it fails, by what its two seeds share: "both", "pot",
    "direction" or "neither" (the conventions of the study's roles.md; the pairs of its final matrix, or of ``m``)."""
    conv = cc_conventions(study)
    m = final_matrix(study, method) if m is None else m
    p = both_seats(m)
    low = {(i, j) for i, j, _ in failing_pairs(m)}
    groups = {"both": [], "pot": [], "direction": [], "neither": []}
    for i, j in itertools.combinations(range(len(conv)), 2):
        pot, way = conv[i][0] == conv[j][0], conv[i][1] == conv[j][1]
        key = "both" if pot and way else "pot" if pot else "direction" if way else "neither"
        groups[key].append((p[i, j], (i, j) in low))
    return groups


@check("cc10_conventions")
def _():
    seeds, _ = cc_roles()
    conv = cc_conventions()
    left = [k for k, c in enumerate(conv) if c[0] == "left"]
    right = [k for k, c in enumerate(conv) if c[0] == "right"]
    ccw = [k for k, c in enumerate(conv) if c[1] == "ccw"]
    cw = [k for k, c in enumerate(conv) if c[1] == "cw"]
    left_share = [two_shares(row[8]) for row in seeds]
    clockwise = [two_shares(row[5])[0] for row in seeds]
    island = [float(row[6].split()[0]) for row in seeds]
    crossing = [k for k in range(10) if island[k] > 0.2]
    return [
        *left, min(min(left_share[k]) for k in left), *right, max(max(left_share[k]) for k in right),
        *ccw, min(clockwise[k] for k in ccw), max(clockwise[k] for k in ccw),
        *cw, min(clockwise[k] for k in cw), max(clockwise[k] for k in cw), L, clockwise[9],  # seed 9: a label
        *crossing, *[island[k] for k in crossing], max(island[k] for k in range(10) if k not in crossing),
    ]  # fmt: skip


@check("cc10_by_convention")
def _():
    groups, out = cc_pairs_by_convention(), []
    for key in ("both", "neither", "pot", "direction"):
        scores = [score for score, _ in groups[key]]
        out += [len(scores), np.mean(scores), min(scores), max(scores), sum(fails for _, fails in groups[key])]
    return out


EXTENSION_UPDATES = (244, 305)  # the 6M extension's snapshots, cross-played (32 episodes) as it trained on


def cc10_snapshot(update: int) -> np.ndarray:
    """The 10 x 10 cross-play of the SP seeds' snapshot at ``update`` (xp_snapshots/, 32 episodes per pair)."""
    return matrix(CC10 / "xp_snapshots" / f"sp_update{update}.csv")


@check("cc10_by_convention_later")
def _():
    def fails(groups, *keys):
        return sum(failed for key in keys for _, failed in groups[key])

    def mean(groups, key):
        return np.mean([score for score, _ in groups[key]])

    final = cc_pairs_by_convention()  # at 3M: the final cross-play
    later = [(snapshot_env_steps(u, CC10), cc_pairs_by_convention(m=cc10_snapshot(u))) for u in EXTENSION_UPDATES]
    every = [(millions(CC10, "sp"), final), *later]
    one = len(final["pot"]) + len(final["direction"])  # the pairs that share one of the two conventions
    out = [one, *[x for steps, groups in every for x in (fails(groups, "pot", "direction"), steps)], one]
    out += [len(final["both"]), max(fails(groups, "both") for _, groups in every)]  # at any of the three
    out += [x for steps, groups in later for x in (mean(groups, "both"), steps)]
    out += [len(final["neither"]), min(fails(groups, "neither") for _, groups in every)]  # at each of the three
    return out + [mean(groups, "neither") for _, groups in later]


@check("cc10_pairs")
def _():
    _, pairs = cc_roles()
    failing = [pairs[k] for k in ((1, 7), (7, 1), (6, 7), (7, 6))]
    sharing = [pairs[k] for k in ((2, 5), (5, 2))]
    onions = [cell_count(row[1]) for row in failing]
    soups = [cell_count(row[3]) for row in failing]
    return [
        L, L, L, L, min(onions), max(onions), min(soups), max(soups),
        L, L, *sorted(cell_count(row[1]) for row in sharing), *sorted(cell_count(row[3]) for row in sharing),
    ]  # fmt: skip


@check("cc10_growth")
def _():
    out = []
    for update in (92, 122, 152):
        sp, xp, gap = sp_xp(cc10_snapshot(update))
        out += [gap, snapshot_env_steps(update, CC10), sp, xp]
    final = run(CC10, "sp")["xp"]
    out += [final["gap"], millions(CC10, "sp"), final["sp_mean"], final["xp_mean"], len(low_pairs(CC10)), 45]
    for update in EXTENSION_UPDATES:
        later = cc10_snapshot(update)
        sp, xp, gap = sp_xp(later)
        out += [gap, snapshot_env_steps(update, CC10), sp, xp, len(failing_pairs(later)), 45]
    return out


@check("cc10_claim")
def _():
    return [*claim_row(CC10, "sp"), len(low_pairs(CC10)), 45]


@check("run_cc10_rate")
def _():
    with (CC10 / "sp_metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["seed"] == "0" and int(r["update"]) > 125]
    return [np.median([float_or_nan(r["steps_per_s"]) for r in rows]), 126, 183]


# --- Table 1 Counter Circuit SA, 10 seeds at 3M env steps, beside the SP seeds


@check("cc_sa10_within")
def _():
    return paper_beside_intervals(CC_SA10, "sa")


@check("cc_sa10_rest")
def _():
    """The seed in every failing SA pair, and the gap of the other 9 seeds with its interval over them."""
    from population.xp import block_summary

    low = low_pairs(CC_SA10, "sa")
    (odd,) = set.intersection(*({i, j} for i, j, _ in low))
    keep = [k for k in range(10) if k != odd]
    m = final_matrix(CC_SA10, "sa")[np.ix_(keep, keep)]
    block = block_summary(m, list(range(len(keep))), list(range(len(keep))))
    return [len(low), len(low), odd, len(keep), block["gap"], *block["gap_ci95_interval"], run(CC10, "sp")["xp"]["gap"]]


@check("cc_sa10_conventions")
def _():
    """The SA seeds' direction round the island and pot use (roles.md's first table, the seeds at update 183)."""
    seeds, _ = cc_roles(CC_SA10)
    clockwise = [two_shares(row[5])[0] for row in seeds]
    left = [two_shares(row[8]) for row in seeds]
    ccw = [k for k in range(10) if clockwise[k] < 0.5]
    cw = [k for k in range(10) if k not in ccw]
    one_pot = [k for k in range(10) if min(left[k]) >= 0.9]
    both = [k for k in range(10) if k not in one_pot]
    return [
        *ccw, *[clockwise[k] for k in ccw], len(cw), min(clockwise[k] for k in cw), max(clockwise[k] for k in cw),
        *one_pot, min(min(left[k]) for k in one_pot), *both, min(min(left[k]) for k in both),
        max(max(left[k]) for k in both), sum(c[1] == "ccw" for c in cc_conventions()),
    ]  # fmt: skip


def seat_count(cell: str) -> tuple[float, float]:
    """A roles table's "<seat 0 share> of <count>" cell."""
    share, count = cell.split(" of ")
    return float(share), float(count)


@check("cc_sa10_pair_roles")
def _():
    """The failing SA pairs (all seed 2's, both seat orders) from roles.md's second table: how seed 2 circles the
    island there beside on its own, the onions the pair pots against its two seeds' self-play mean, and how often
    the partner delivers 0.65 or more of the soups."""
    seeds, pairs = cc_roles(CC_SA10)
    (odd,) = set.intersection(*({i, j} for i, j, _ in low_pairs(CC_SA10, "sa")))  # the seed in every failing pair
    cw, onions, partner = [], [], []
    for (i, j), row in pairs.items():
        seat = 0 if i == odd else 1
        delivered = seat_count(row[4])[0]
        partner.append(1 - delivered if seat == 0 else delivered)
        cw.append(two_shares(row[5])[seat])
        onions.append(seat_count(row[1])[1] / np.mean([seat_count(seeds[k][1])[1] for k in (i, j)]))
    return [
        len(pairs), len(low_pairs(CC_SA10, "sa")), odd, two_shares(seeds[odd][5])[0], min(cw), max(cw),
        min(onions), max(onions), 0.65, sum(p >= 0.65 for p in partner), len(pairs),
    ]  # fmt: skip


@check("cc_sa10_sp_sa")
def _():
    m, low = sp_sa_mean(CC_SA10), sp_sa_low(CC10, CC_SA10)  # row = SP seed, column = SA seed, both seat orders
    ccw = [k for k, c in enumerate(cc_conventions()) if c[1] == "ccw"]  # the SP seeds circling counter-clockwise
    cw = [k for k in range(10) if k not in ccw]
    return [
        m.size, m.mean(), run(CC10, "sp")["xp"]["xp_mean"], run(CC_SA10, "sa")["xp"]["xp_mean"], int(low.sum()), m.size,
        *ccw, m[np.ix_(ccw, range(10))].mean(), m[np.ix_(cw, range(10))].mean(),
    ]  # fmt: skip


@check("cc_sa10_growth")
def _():
    return gap_growth((CC10, "sp", CC10), (CC_SA10, "sa", CC_SA10))
