"""Checks of Coordination Ring SP on the paper's whole 10M schedule, trained on a GPU: the population at update
410 (6.7M, gpu_coord_ring_sp_update410/) and at update 610 (10M, gpu_coord_ring_sp/), and its runs-table rows.
sp10_pairs_onions reads the 3M population, where the page sets it beside the 10M one's pairs."""

from __future__ import annotations

import csv
import functools
import itertools
import json
from pathlib import Path

import numpy as np

from .data import both_seats, claim_row, float_or_nan, matrix, md_tables, paper, run, run_size, sp_xp, span, study_wall
from .folders import GPU410, GPU_CR, SP10
from .registry import L, check
from .ten_seed_studies import (
    cell_count,
    failing_pairs,
    final_matrix,
    final_numbers,
    low_pairs,
    pair_rows,
    paired_gap_difference,
    paper_beside_intervals,
    roles_tables,
    snapshot_env_steps,
)

# --- the run's progress, and the population at update 410 (gpu_coord_ring_sp_update410/), cross-played on the CPU


@check("gpu_cr_sp_progress")
def _():
    with (GPU_CR / "sp_metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    last = max(int(r["update"]) for r in rows)
    at_last = sorted((r for r in rows if int(r["update"]) == last), key=lambda r: int(r["seed"]))
    returns = [float_or_nan(r["sparse_return"]) for r in at_last]
    steps = float_or_nan(at_last[0]["env_steps"])
    return [last, L, steps / 1e6, float(np.mean(returns)), len(returns), paper(GPU_CR, "sp")[0], L]


def gpu410() -> np.ndarray:
    return matrix(GPU410 / "matrix.csv")


@functools.cache
def gpu410_block() -> dict:
    """SP, XP, gap and their seed-bootstrap intervals, as a study report computes them."""
    from population.xp import block_summary

    return block_summary(gpu410(), list(range(10)), list(range(10)))


def pot_groups(roles: list) -> dict:
    """Seeds by where seat 0 puts its onions in a roles.md table: only the first pot, only the second, or both."""
    pot = [row[3][0] for row in roles]
    return {
        "first": [k for k, x in enumerate(pot) if x >= 0.95],
        "second": [k for k, x in enumerate(pot) if x <= 0.05],
        "both": [k for k, x in enumerate(pot) if 0.05 < x < 0.95],
    }


def gpu410_pot_groups() -> dict:
    """Seeds at update 410 by where seat 0 puts its onions."""
    return pot_groups(roles_tables(GPU410)[410])


def pot_group_pairs(groups: dict, roles: list, p: np.ndarray) -> list:
    """The "conventions" bullets' numbers: the first-pot seed and its clockwise share, the second-pot and both-pot
    seeds, the pairs within and across those groups (count, mean, range), the first-pot seed's mean with the rest."""
    cw = [row[0] for row in roles]
    second, both, first = groups["second"], groups["both"], groups["first"]
    others = [k for k in range(len(p)) if k not in first]
    same = group_pairs(p, second, second)
    cross = group_pairs(p, second, both)
    within_both = group_pairs(p, both, both)
    with_first = group_pairs(p, first, others)
    return [
        *first, cw[first[0]], *second, *both, len(same), np.mean(same), min(same), max(same),
        len(within_both), *both, np.mean(within_both), len(cross), np.mean(cross), min(cross), max(cross),
        *first, np.mean(with_first),
    ]  # fmt: skip


def group_pairs(p: np.ndarray, a: list[int], b: list[int]) -> list[float]:
    """Both-seat-order scores of the pairs with one seed in ``a`` and the other in ``b`` (each pair once)."""
    return [p[i, j] for i in a for j in b if i != j and (a != b or i < j)]


@check("gpu410_final")
def _():
    block = gpu410_block()
    seeds = len(json.loads((GPU410 / "policies" / "SHA256SUMS.json").read_text()))
    episodes = json.loads((GPU410 / "summary.json").read_text())["episodes_per_pair"]
    return [
        seeds, snapshot_env_steps(410, GPU410), episodes, block["sp_mean"], block["xp_mean"], block["gap"], seeds,
        *block["gap_ci95_interval"], *paper(GPU_CR, "sp"),
    ]  # fmt: skip


@check("gpu410_within")
def _():
    block = gpu410_block()
    sp, xp, gap = paper(GPU_CR, "sp")
    return [sp, *block["sp_ci95_interval"], xp, *block["xp_ci95_interval"], gap]


@check("gpu410_vs_3m")
def _():
    from population.xp import bootstrap_difference

    here, there = gpu410_block()["gap"], run(SP10, "sp")["xp"]["gap"]
    return [here, there, here - there, *bootstrap_difference(final_matrix(), gpu410())["gap"]]


@check("gpu410_vs_3m_paired")
def _():
    return paired_gap_difference(final_matrix(), gpu410())


@check("gpu410_vs_3m_parts")
def _():
    block, cpu = gpu410_block(), run(SP10, "sp")["xp"]
    first = gpu410_pot_groups()["first"]
    keep = [k for k in range(10) if k not in first]
    without = sp_xp(gpu410()[np.ix_(keep, keep)])[1]
    return [block["xp_mean"], cpu["xp_mean"], *first, without, block["sp_mean"], cpu["sp_mean"]]


@check("gpu410_low_pairs")
def _():
    low = failing_pairs(gpu410())
    with6 = [score for i, j, score in low if 6 in (i, j)]
    rest = [pair for pair in low if 6 not in pair[:2]]  # lowest first
    return [len(low), 45, len(with6), 6, min(with6), max(with6), *[x for pair in rest for x in pair]]


@check("gpu410_claim")
def _():
    block = gpu410_block()
    low = len(failing_pairs(gpu410()))
    return [block["sp_mean"], block["xp_mean"], block["gap"], 10, *block["gap_ci95_interval"], low, 45]


@check("gpu410_seed6_early")
def _():
    row = roles_tables(GPU410)[122][6]
    return [122, snapshot_env_steps(122, GPU_CR), 6, row[0], row[3][0]]


def gpu410_snapshot_gaps() -> list:
    """The gap and env steps per seed (millions) of the snapshots cross-played beside update 410 (122, 244, 366)."""
    out = []
    for update in (122, 244, 366):
        out += [sp_xp(matrix(GPU410 / f"xp_update{update}" / "matrix.csv"))[2], snapshot_env_steps(update, GPU_CR)]
    return out


def episodes_per_pair(folder: Path) -> int:
    return json.loads((folder / "summary.json").read_text())["episodes_per_pair"]


@check("gpu410_growth")
def _():
    out, episodes = gpu410_snapshot_gaps(), episodes_per_pair(GPU410 / "xp_update366")
    return [*out[:2], episodes, *out[2:], gpu410_block()["gap"], snapshot_env_steps(410, GPU410)]


@check("gpu410_groups")
def _():
    return pot_group_pairs(gpu410_pot_groups(), roles_tables(GPU410)[410], both_seats(gpu410()))


# --- Coordination Ring SP on the paper's whole 10M schedule (gpu_coord_ring_sp, update 610)


@check("gpu_cr_sp_final")
def _():
    return final_numbers(GPU_CR, "sp")


def gpu_cr_matrix() -> np.ndarray:
    return final_matrix(GPU_CR, "sp")


def group_of(groups: dict, seed: int) -> str:
    """The name of the group of ``pot_groups`` that holds ``seed``."""
    return next(name for name, seeds in groups.items() if seed in seeds)


def roles_pairs(study: Path) -> dict:
    """roles_pairs.md's one table of ordered cross-play pairs (``pair_rows``)."""
    (table,) = md_tables(study / "roles_pairs.md")
    return pair_rows(table)


def gpu_cr_groups() -> dict:
    return pot_groups(roles_tables(GPU_CR)[610])


@check("gpu_cr_sp_within")
def _():
    return paper_beside_intervals(GPU_CR, "sp")


@check("gpu_cr_sp_low_pairs")
def _():
    low = failing_pairs(gpu_cr_matrix())
    first = gpu_cr_groups()["first"]
    with_first = [score for i, j, score in low if first[0] in (i, j)]
    return [len(low), 45, len(with_first), *first, min(with_first), max(with_first)]


@check("gpu_cr_sp_vs_410")
def _():
    before, after = gpu410_block()["gap"], run(GPU_CR, "sp")["xp"]["gap"]
    return [before, 410, after, 610, after - before, *paired_gap_difference(gpu410(), gpu_cr_matrix())]


@check("gpu_cr_sp_claim")
def _():
    return [*claim_row(GPU_CR, "sp"), len(failing_pairs(gpu_cr_matrix())), 45]


@check("gpu_cr_sp_groups")
def _():
    groups, before = gpu_cr_groups(), gpu410_pot_groups()
    changed = sum(group_of(groups, k) != group_of(before, k) for k in range(10))
    numbers = pot_group_pairs(groups, roles_tables(GPU_CR)[610], both_seats(gpu_cr_matrix()))
    return [*numbers, changed, 10, 410]


@check("gpu_cr_sp_without6")
def _():
    from population.xp import block_summary

    first = gpu_cr_groups()["first"]
    keep = [k for k in range(10) if k not in first]
    block = block_summary(gpu_cr_matrix()[np.ix_(keep, keep)], list(range(len(keep))), list(range(len(keep))))
    return [*first, block["sp_mean"], block["xp_mean"], block["gap"], len(keep), *block["gap_ci95_interval"]]


@check("gpu_cr_sp_recovered")
def _():
    now, then = both_seats(gpu_cr_matrix()), both_seats(gpu410())
    groups = gpu_cr_groups()
    both, first = groups["both"], groups["first"]
    others = [k for k in range(10) if k not in first]
    recovered = [(i, j) for i, j, _ in failing_pairs(gpu410()) if not set(first) & {i, j}]
    out = [x for i, j in recovered for x in (i, j, now[i, j], then[i, j])]
    return [
        *out[:4], 410, *out[4:], np.mean(group_pairs(now, both, both)), np.mean(group_pairs(then, both, both)), 410,
        *first, np.mean(group_pairs(now, first, others)), np.mean(group_pairs(then, first, others)), 410,
    ]  # fmt: skip


@check("gpu_cr_sp_seed4")
def _():
    m = gpu_cr_matrix()
    sp = np.diag(m)
    top = int(np.argmax(sp))
    rest = [x for k, x in enumerate(sp) if k != top]
    roles = roles_tables(GPU_CR)[610]
    deliveries = [row[2][3][0] for row in roles]
    others = [x for k, x in enumerate(deliveries) if k != top]
    keep = [k for k in range(10) if k != top]
    rest_sp = sp_xp(m, keep)[0]
    return [
        top, sp[top], min(rest), max(rest), deliveries[top], min(others), max(others), top, rest_sp, sp.mean() - rest_sp,
    ]  # fmt: skip


@check("gpu_cr_sp_growth")
def _():
    at488 = GPU_CR / "xp_update488"
    return [
        *gpu410_snapshot_gaps(), episodes_per_pair(GPU410 / "xp_update366"),
        gpu410_block()["gap"], snapshot_env_steps(410, GPU410), episodes_per_pair(GPU410),
        sp_xp(matrix(at488 / "matrix.csv"))[2], snapshot_env_steps(488, GPU_CR), episodes_per_pair(at488),
        run(GPU_CR, "sp")["xp"]["gap"], snapshot_env_steps(610, GPU_CR), run(GPU_CR, "sp")["xp"]["episodes_per_pair"],
    ]  # fmt: skip


@check("gpu_cr_sp_vs_3m")
def _():
    from population.xp import bootstrap_difference

    here, there = run(GPU_CR, "sp")["xp"]["gap"], run(SP10, "sp")["xp"]["gap"]
    return [
        here, there, here - there, *bootstrap_difference(final_matrix(), gpu_cr_matrix())["gap"],
        *paired_gap_difference(final_matrix(), gpu_cr_matrix()),
    ]  # fmt: skip


@check("gpu_cr_sp_paper_xp")
def _():
    """How many of the 45 pairs would have to fail for the paper's XP, if working and failing pairs scored what
    ours score on average."""
    p = both_seats(gpu_cr_matrix())
    low = {(i, j) for i, j, _ in failing_pairs(gpu_cr_matrix())}
    fail = np.mean([p[i, j] for i, j in low])
    ok = np.mean([p[i, j] for i, j in itertools.combinations(range(10), 2) if (i, j) not in low])
    xp = paper(GPU_CR, "sp")[1]
    return [xp, ok, fail, 45 * (ok - xp) / (ok - fail), 45, len(low)]


@check("gpu_cr_sp_pairs_onions")
def _():
    """Onions into the pots over 32 episodes: ordered cross-play pairs with seed 6 (roles_pairs.md), the seeds' own
    self-play (roles.md), and the ordered pairs among the other seeds read beside them."""
    first = gpu_cr_groups()["first"][0]
    counts = {pair: cell_count(row[2]) for pair, row in roles_pairs(GPU_CR).items()}
    with_first = [n for pair, n in counts.items() if first in pair]
    others = [n for pair, n in counts.items() if first not in pair]
    own = [row[2][0][1] for row in roles_tables(GPU_CR)[610]]
    return [
        len(with_first), first, min(with_first), max(with_first), 32, min(with_first) / 32, max(with_first) / 32,
        min(own), max(own), len(others), min(others), max(others),
    ]  # fmt: skip


# the 3M population's failing pairs, read the same way: the page sets them beside the 10M population's


@check("sp10_pairs_onions")
def _():
    """The 3M population's failing pairs, both seat orders (roles_pairs.md): onions into the pots and soups plated
    over 32 episodes, beside the seeds' own self-play (roles.md, update 183)."""
    rows = roles_pairs(SP10)
    failing = [pair for i, j, _ in low_pairs() for pair in ((i, j), (j, i))]
    onions = [cell_count(rows[pair][2]) for pair in failing]
    soups = [cell_count(rows[pair][4]) for pair in failing]
    own = roles_tables()[183]
    own_onions, own_soups = [row[2][0][1] for row in own], [row[2][2][1] for row in own]
    return [len(failing), min(onions), max(onions), 32, *span(own_onions), *span(soups), *span(own_soups)]


@check("run_gpu_cr")
def _():
    return run_size(GPU_CR, "sp")


@check("run_gpu_cr_rates")
def _():
    with (GPU_CR / "sp_metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["seed"] == "0"]
    gpu = [float_or_nan(r["steps_per_s"]) for r in rows if int(r["update"]) <= 410]
    cpu = [float_or_nan(r["steps_per_s"]) for r in rows if int(r["update"]) > 410]
    return [1, 410, np.median(gpu), 411, 610, np.median(cpu), *study_wall(GPU_CR)]
