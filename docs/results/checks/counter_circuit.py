"""Checks of the 10-seed Counter Circuit studies at 3M: SP (table1_counter_circuit_sp10/) and SA beside it
(table1_counter_circuit_sa10/); and of the same SP seeds trained on to 6M (table1_counter_circuit_sp10_6m/)."""

from __future__ import annotations

import csv
import itertools
from pathlib import Path

import numpy as np

from .data import both_seats, claim_row, float_or_nan, matrix, md_tables, millions, run, sp_xp
from .folders import CC10, CC10_6M, CC_SA10, CC_SA10_6M
from .registry import L, check
from .ten_seed_studies import (
    cell_count,
    failing_pairs,
    final_matrix,
    gap_growth,
    low_pairs,
    pair_rows,
    paper_beside_intervals,
    seat_shares,
    snapshot_env_steps,
    sp_sa_low,
    sp_sa_mean,
)

# --- Table 1 Counter Circuit SP, 10 seeds at 3M env steps


def cc_roles(study: Path = CC10) -> tuple[list[list[str]], dict]:
    """A Counter Circuit study's roles.md: the seeds' rows at its final update and {(seat-0 seed, seat-1 seed): row}
    of its cross-play pairs (its first two tables; the tables of later snapshots follow them)."""
    seeds, pairs = md_tables(study / "roles.md")[:2]
    return seeds, pair_rows(pairs)


def cc_conventions(study: Path = CC10) -> list[tuple[str, str]]:
    """Per seed, (pot, direction) of its self-play: "left" where seat 0 puts most of its onions into the left pot,
    "cw" where more than half of seat 0's moves round the island go clockwise."""
    seeds, _ = cc_roles(study)
    return [
        ("left" if seat_shares(row[8])[0] >= 0.5 else "right", "cw" if seat_shares(row[5])[0] > 0.5 else "ccw")
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
    left_share = [seat_shares(row[8]) for row in seeds]
    clockwise = [seat_shares(row[5])[0] for row in seeds]
    island = [float(row[6].split()[0]) for row in seeds]
    crossing = [k for k in range(10) if island[k] > 0.2]
    return [
        *left, min(min(left_share[k]) for k in left), *right, max(max(left_share[k]) for k in right),
        *ccw, min(clockwise[k] for k in ccw), max(clockwise[k] for k in ccw),
        *cw, min(clockwise[k] for k in cw), max(clockwise[k] for k in cw), L, clockwise[9],  # seed 9: a label
        *crossing, *[island[k] for k in crossing], max(island[k] for k in range(10) if k not in crossing),
    ]  # fmt: skip


def convention_numbers(groups: dict) -> list:
    """Per group of ``cc_pairs_by_convention`` (both, neither, pot, direction): how many pairs, their mean, lowest
    and highest score, and how many of them fail."""
    out = []
    for key in ("both", "neither", "pot", "direction"):
        scores = [score for score, _ in groups[key]]
        out += [len(scores), np.mean(scores), min(scores), max(scores), sum(fails for _, fails in groups[key])]
    return out


@check("cc10_by_convention")
def _():
    return convention_numbers(cc_pairs_by_convention())


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


@check("run_cc10_rate")
def _():
    with (CC10 / "sp_metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["seed"] == "0" and int(r["update"]) > 125]
    return [np.median([float_or_nan(r["steps_per_s"]) for r in rows]), 126, 183]


# --- the same 10 SP seeds trained on to 6M (--extend), cross-played at 500 episodes per ordered pair


def since_3m(early: Path, late: Path, method: str) -> list:
    """The gap at 3M and at 6M (each with its env steps per seed); SP's, XP's and the gap's change with their 95 %
    intervals, the same seeds resampled at both stops (recomputed from the two matrices, as the study report does);
    the gap's change with each stop resampled on its own, as if the two were unrelated populations."""
    from population.xp import bootstrap_difference, paired_difference

    before, after = final_matrix(early, method), final_matrix(late, method)
    gaps = [run(study, method)["xp"]["gap"] for study in (early, late)]
    changes = {key: run(late, method)["xp"][key] - run(early, method)["xp"][key] for key in ("sp_mean", "xp_mean")}
    paired = paired_difference(before, after)
    return [
        gaps[0], millions(early, method), gaps[1], millions(late, method), gaps[1] - gaps[0], *paired["gap"],
        changes["sp_mean"], *paired["sp"], -changes["xp_mean"], *paired["xp"],  # "fell by": written positive
        *bootstrap_difference(before, after)["gap"],
    ]  # fmt: skip


@check("cc10_6m_vs_3m")
def _():
    return since_3m(CC10, CC10_6M, "sp")


@check("cc10_6m_by_convention")
def _():
    """The pairs of the 6M cross-play grouped by their seeds' 3M conventions (each seed keeps them: roles.md at
    update 366)."""
    return convention_numbers(cc_pairs_by_convention(m=final_matrix(CC10_6M)))


def seed_sp_xp(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per seed, its self-play and the mean of its cross-play cells with the other seeds in both seat orders."""
    p = both_seats(m)
    off = ~np.eye(len(m), dtype=bool)
    return np.diag(m), np.array([p[k][off[k]].mean() for k in range(len(m))])


@check("cc10_6m_seeds")
def _():
    """Seeds 3 and 8 from 3M to 6M: self-play and cross-play (mean of its cells with the other seeds, both seat
    orders); the pairs failing at 6M and not at 3M, and how many of them hold seed 3 or 8."""
    (sp3, xp3), (sp6, xp6) = seed_sp_xp(final_matrix(CC10)), seed_sp_xp(final_matrix(CC10_6M))
    new = {(i, j) for i, j, _ in low_pairs(CC10_6M)} - {(i, j) for i, j, _ in low_pairs(CC10)}
    out = [L, L]
    for k in (3, 8):
        out += [L, sp3[k], sp6[k], xp3[k], xp6[k]]
    both = sum(3 in pair or 8 in pair for pair in new)
    return out + [len(new), millions(CC10_6M, "sp"), millions(CC10, "sp"), both, L, L]


@check("cc10_6m_roles")
def _():
    """roles.md at update 366 (its fifth table) beside the earlier ones: how many seeds keep their 3M pot and their
    3M direction; seed 9's clockwise share at 183 and 366 (the one that changes side, by a hair); seed 4's
    clockwise share and onions over the island at 244 and 366; seed 8's seat-0 share of the dishes at 305 and 366;
    seed 9's at 366."""
    tables = md_tables(CC10 / "roles.md")
    at = {183: tables[0], 244: tables[2], 305: tables[3], 366: tables[4]}
    conv = cc_conventions()
    pots = sum(("left" if seat_shares(row[8])[0] >= 0.5 else "right") == c[0] for row, c in zip(at[366], conv))
    ways = sum(("cw" if seat_shares(row[5])[0] > 0.5 else "ccw") == c[1] for row, c in zip(at[366], conv))
    island = {u: float(at[u][4][6].split()[0]) for u in (244, 366)}
    dishes = {u: float(at[u][8][2].split()[0]) for u in (305, 366)}
    return [pots, millions(CC10, "sp"), ways, L, seat_shares(at[183][9][5])[0], seat_shares(at[366][9][5])[0],
            L, seat_shares(at[366][4][5])[0], island[366], island[244], snapshot_env_steps(244, CC10),
            L, dishes[366], dishes[305], snapshot_env_steps(305, CC10), L, float(at[366][9][2].split()[0])]  # fmt: skip


@check("cc10_6m_claim")
def _():
    row = claim_row(CC10_6M, "sp")
    return [*row[:2], millions(CC10, "sp"), *row[2:], len(low_pairs(CC10_6M)), 45]


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
    clockwise = [seat_shares(row[5])[0] for row in seeds]
    left = [seat_shares(row[8]) for row in seeds]
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
        cw.append(seat_shares(row[5])[seat])
        onions.append(seat_count(row[1])[1] / np.mean([seat_count(seeds[k][1])[1] for k in (i, j)]))
    return [
        len(pairs), len(low_pairs(CC_SA10, "sa")), odd, seat_shares(seeds[odd][5])[0], min(cw), max(cw),
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


SA_EXTENSION_UPDATES = (244, 305)  # the SA seeds' 6M extension's snapshots cross-played so far (32 episodes per pair)


@check("cc_sa10_extension")
def _():
    """The SA seeds' gap at 3M (the final cross-play) and at each extension snapshot (SP, XP, gap, failing pairs),
    beside the SP seeds' gap at the same snapshot."""
    final = run(CC_SA10, "sa")["xp"]
    out = [final["gap"], millions(CC_SA10, "sa"), final["sp_mean"], final["xp_mean"]]
    for update in SA_EXTENSION_UPDATES:
        later = matrix(CC_SA10 / "xp_snapshots" / f"sa_update{update}.csv")
        sp, xp, gap = sp_xp(later)
        out += [gap, snapshot_env_steps(update, CC_SA10), sp, xp, len(failing_pairs(later)), 45]
        out += [snapshot_env_steps(update, CC10), sp_xp(cc10_snapshot(update))[2]]
    return out


# --- the same 10 SA seeds trained on to 6M (--extend), beside the SP seeds at 6M (their SA_BESIDE_SP rows are
# registered in ten_seed_rows: cc_sa10_6m_final, _delta, _paired, _low_pairs, _claim)


@check("cc_sa10_6m_within")
def _():
    return paper_beside_intervals(CC_SA10_6M, "sa")


@check("cc_sa10_6m_vs_3m")
def _():
    """``since_3m`` of the SA seeds, whose cross-play rose: its change written as it is, not as a fall."""
    out = since_3m(CC_SA10, CC_SA10_6M, "sa")
    out[10] = -out[10]
    return out


@check("cc_sa10_6m_odd_seed")
def _():
    """The seed in every failing SA pair at 3M: its self-play and cross-play (mean with the other nine, both seat
    orders) at 3M and at 6M; the lowest pair score of the 6M matrix (both seat orders) as a share of its two seeds'
    self-play mean; how many of the 5 lowest pairs hold the seed with the lowest cross-play at 6M, which seed that
    is, the 5 pairs' range of shares, and its cross-play beside the 3M odd seed's."""
    (odd,) = set.intersection(*({i, j} for i, j, _ in low_pairs(CC_SA10, "sa")))
    (sp3, xp3), (sp6, xp6) = seed_sp_xp(final_matrix(CC_SA10, "sa")), seed_sp_xp(final_matrix(CC_SA10_6M, "sa"))
    m = final_matrix(CC_SA10_6M, "sa")
    pairs = both_seats(m)
    shares = [pairs[i, j] / ((m[i, i] + m[j, j]) / 2) for i, j in itertools.combinations(range(len(m)), 2)]
    steps = millions(CC_SA10, "sa"), millions(CC_SA10_6M, "sa")
    weak = int(np.argmin(xp6))  # the seed with the lowest cross-play at 6M
    lowest = sorted(zip(shares, itertools.combinations(range(len(m)), 2)))[:5]
    held = sum(weak in pair for _, pair in lowest)
    # "The 5 lowest pairs all hold seed W": the 5 written is how many of them hold it
    return [odd, steps[0], sp3[odd], sp6[odd], xp3[odd], xp6[odd], steps[1], min(shares),
            held, weak, lowest[0][0], lowest[-1][0], xp6[weak], odd, xp6[odd]]  # fmt: skip


@check("cc_sa10_6m_widening")
def _():
    """SA's gap minus SP's at 3M and at 6M, and the change between them with its 95 % interval, one draw of seed
    indices used in all four matrices (seed k: the same SP seed at both stops, the same SA seed at both, and SA seed
    k starts from SP seed k's initial parameters, as the paired intervals above take them); 20,000 resamples."""
    from population.xp import bootstrap_samples

    def gap_samples(study: Path, method: str) -> np.ndarray:
        sp, xp = bootstrap_samples(final_matrix(study, method), resamples=20_000)  # the same seed: the same draws
        return sp - xp

    widening = (gap_samples(CC_SA10_6M, "sa") - gap_samples(CC10_6M, "sp")) - (
        gap_samples(CC_SA10, "sa") - gap_samples(CC10, "sp")
    )
    gap = {study: run(study, method)["xp"]["gap"] for study, method in
           ((CC10, "sp"), (CC_SA10, "sa"), (CC10_6M, "sp"), (CC_SA10_6M, "sa"))}  # fmt: skip
    before, after = gap[CC_SA10] - gap[CC10], gap[CC_SA10_6M] - gap[CC10_6M]
    steps = millions(CC_SA10, "sa"), millions(CC_SA10_6M, "sa")
    return [before, steps[0], after, steps[1], after - before, *np.percentile(widening, [2.5, 97.5])]


@check("cc_sa10_6m_sp_sa")
def _():
    """SP x SA at 6M (the update-366 policies, both seat orders): the mean of the 100 pairs beside SP's and SA's
    own cross-play at 6M, how many fail, the pairs of the SP seeds that circle counter-clockwise (their 3M
    convention, which every SP seed kept: cc10_6m_roles) beside the others', and the SA seed they all score best
    with (a set: one number where they agree)."""
    m, low = sp_sa_mean(CC_SA10_6M), sp_sa_low(CC10_6M, CC_SA10_6M)
    ccw = [k for k, c in enumerate(cc_conventions()) if c[1] == "ccw"]
    cw = [k for k in range(10) if k not in ccw]
    return [
        m.size, m.mean(), run(CC10_6M, "sp")["xp"]["xp_mean"], run(CC_SA10_6M, "sa")["xp"]["xp_mean"],
        int(low.sum()), m.size, *ccw, m[np.ix_(ccw, range(10))].mean(), m[np.ix_(cw, range(10))].mean(),
        *{int(np.argmax(m[k])) for k in ccw},  # the SA seed each counter-clockwise SP seed scores best with: one
    ]  # fmt: skip


@check("cc_sa10_6m_roles")
def _():
    """roles.md of the SA seeds at update 366 (its third table) beside 183 (its first): the seed in every failing
    3M pair, its clockwise share (seat 0) at 6M and at 3M, and the other nine's range at 6M."""
    tables = md_tables(CC_SA10 / "roles.md")
    at = {183: tables[0], 366: tables[2]}
    (odd,) = set.intersection(*({i, j} for i, j, _ in low_pairs(CC_SA10, "sa")))
    others = [seat_shares(row[5])[0] for k, row in enumerate(at[366]) if k != odd]
    steps = millions(CC_SA10_6M, "sa"), millions(CC_SA10, "sa")
    return [
        seat_shares(at[366][odd][5])[0],
        steps[0],
        seat_shares(at[183][odd][5])[0],
        steps[1],
        min(others),
        max(others),
    ]
