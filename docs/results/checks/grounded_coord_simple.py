"""Checks of the 4-seed Grounded Coord. Simple study (reduced_gcs/): SP, FCP, and what the agents signal with
the recipe buttons (button_use.md)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from .data import (
    FCP,
    GCS_8X8,
    LEARNERS,
    SEEDS,
    SP,
    block,
    both_seats,
    button_rows,
    buttons,
    chunks,
    episodes,
    gcs_fcp,
    gcs_sp,
    hm,
    interval,
    matrix,
    mean,
    metric,
    pair_se,
    paper,
    returns,
    run,
    span,
    study_block,
    study_pair,
    summary,
)
from .folders import GCS
from .four_seed_bootstrap import gap_at_most_zero, gap_zero_pattern
from .four_seed_studies import RESUMED_AT, gcs_seed2_wrong, gcs_training_s, gcs_without_seed2
from .registry import L, check


def paper_numbers(paper: dict) -> list:
    """A run's paper column as the tables write it: SP, XP and gap, each mean then std."""
    return [paper[k][v] for k in ("sp", "xp", "gap") for v in ("mean", "std")]


# --- Grounded Coord. Simple SP


@check("gcs_sp_training")
def _():
    out = []
    for update in (10, 20, 30, 40, 45):
        out.append(metric(SP, update, "env_steps")[0])
        for column in ("sparse_return", "return_recipe_0+0+0", "return_recipe_1+1+1"):
            out += metric(SP, update, column)
    return out


@check("gcs_sp_entropy")
def _():
    last = metric(SP, 45, "entropy")
    return [0, metric(SP, 45, "sparse_return")[0], metric(SP, 10, "entropy")[0], last[0], *span(last[1:])]


@check("gcs_sp_matrix")
def _():
    p = both_seats(gcs_sp())
    return [v for i in range(4) for j in range(4) for v in (p[i, j], pair_se(SP, i, j))]


@check("gcs_sp_table")
def _():
    p = run(GCS, SP)["paper"]
    return [
        *block(run(GCS, SP)["xp"]),
        *paper_numbers(p),
    ]


@check("gcs_sp_four")
def _():
    p = both_seats(gcs_sp())
    ij = list(itertools.combinations(range(4), 2))
    low, high = min(ij, key=lambda x: p[x]), max(ij, key=lambda x: p[x])
    count, total = gap_at_most_zero(gcs_sp())
    return [*low, *high, L, count, total, *gap_zero_pattern(gcs_sp()), L]


@check("gcs_sp_by_recipe")
def _():
    def by(recipe, same):
        return np.mean(
            [e["return"] for e in episodes(SP) if (e["seat0"] == e["seat1"]) == same and e["recipe"] == recipe]
        )

    return [
        by("0+0+0", True),
        by("1+1+1", True),
        by("0+0+0", False),
        by("1+1+1", False),
        2,
        0,
        1,
        returns(SP, 0, 2, "1+1+1").mean(),
        returns(SP, 1, 2, "1+1+1").mean(),
        100 * (returns(SP, 0, 2) < 0).mean(),
        0,
        2,
        L,
    ]


@check("gcs_sp_recipe_held")
def _():
    held = [e for e in episodes(SP) if e["recipe"] == "1+1+1"]
    return [
        max(r["correct"] for r in button_rows(recipe="1+1+1") if r["seat1"] in SEEDS),
        sum(e["return"] > 0 for e in held),
        len(held),
    ]


# --- Grounded Coord. Simple FCP


@check("gcs_fcp_speed")
def _():
    return [
        *span(s for _, s, _ in chunks(FCP, after=RESUMED_AT)),
        *hm(run(GCS, FCP)["wall_s"]),
        *hm(gcs_training_s(FCP)),
        RESUMED_AT,
        len(matrix(GCS_8X8)),
        len(matrix(GCS_8X8)),
        summary(GCS)["comparisons"][0]["wall_s"] / 60,
    ]


@check("gcs_fcp_training")
def _():
    out = []
    for update in (10, 20, 30, 40, 45):
        for column in ("sparse_return", "return_recipe_0+0+0", "return_recipe_1+1+1"):
            out += metric(FCP, update, column)
    return out


@check("gcs_fcp_matrix")
def _():
    return list(gcs_fcp().ravel())


@check("gcs_fcp_between")
def _():
    fs, sf, pair = study_block(GCS, FCP, SP), study_block(GCS, SP, FCP), study_pair(GCS, SP, FCP)
    m = matrix(GCS_8X8)
    return [
        fs["xp_mean"],
        run(GCS, FCP)["seeds"],
        *interval(fs, "xp"),
        sf["xp_mean"],
        *interval(sf, "xp"),
        pair["mean"],
        *pair["mean_ci95_interval"],
        1,
        3,
        *span(m[4 + i, j] for i in range(4) for j in (1, 3)),
        gcs_sp()[1, 1],
        gcs_sp()[3, 3],
    ]


@check("gcs_fcp_table")
def _():
    p = run(GCS, FCP)["paper"]
    return [
        *block(run(GCS, FCP)["xp"]),
        *block(run(GCS, SP)["xp"]),
        *paper_numbers(p),
    ]


# --- what the agents signal


@check("signal_presses")
def _():
    return [max(r["presses"] for r in buttons())]


def _signal(rows):
    return [mean(rows, "top"), mean(rows, "bottom")]


@check("signal_table")
def _():
    out = []
    for seat0 in SEEDS:
        out += _signal(button_rows(seat0, None, "0+0+0")) + _signal(button_rows(seat0, None, "1+1+1"))
    for recipe in ("0+0+0", "1+1+1"):
        learners = [_signal(button_rows(s, None, recipe)) for s in LEARNERS]
        out += [*span(t for t, _ in learners), *span(b for _, b in learners)]
    return out


def _held(seat0, recipe):
    """Rows of ``seat0`` whose cook made no correct delivery: the starting recipe held all episode."""
    return [r for r in button_rows(seat0, None, recipe) if r["correct"] == 0]


def _range(values):
    """One number where all are the same, else the lowest and the highest."""
    values = list(values)
    return [values[0]] if min(values) == max(values) else span(values)


@check("signal_held_table")
def _():
    out = []
    for seat0 in SEEDS:
        for recipe in ("0+0+0", "1+1+1"):
            rows = _held(seat0, recipe)
            out += [len(rows), *_signal(rows)]
    for recipe in ("0+0+0", "1+1+1"):
        learners = [_held(s, recipe) for s in LEARNERS]
        signals = [_signal(rows) for rows in learners]
        out += [*_range(len(rows) for rows in learners), *span(t for t, _ in signals), *span(b for _, b in signals)]
    return out


@check("signal_held_says")
def _():
    learners = [_signal(button_rows(s, None, "0+0+0"))[1] for s in LEARNERS]
    held = [_signal(_held(s, "0+0+0"))[1] for s in LEARNERS]
    return [1, _signal(_held("sp/1", "0+0+0"))[0], *span(learners), *span(held)]


def _cook(seat1, seat0s, recipe, key):
    return float(np.mean([button_rows(s, seat1, recipe)[0][key] for s in seat0s]))


@check("signal_cooks")
def _():
    out = []
    for cook in ("sp/1", "sp/2", "sp/3", "fcp/0"):
        for column, partners in enumerate((["sp/0"], [cook], LEARNERS, ["sp/1"])):
            if column == 3 and cook == "sp/1":
                continue  # "(own)"
            out += [_cook(cook, partners, "0+0+0", "correct"), _cook(cook, partners, "1+1+1", "wrong")]
            if cook == "sp/2" and column in (0, 3):
                out.append(_cook(cook, partners, "1+1+1", "return"))
    cook = "fcp/3"
    out += [_cook(cook, ["sp/0"], "0+0+0", "wrong"), _cook(cook, ["sp/0"], "1+1+1", "correct")]
    out += [_cook(cook, [cook], "0+0+0", key) for key in ("correct", "wrong")] + [
        _cook(cook, [cook], "1+1+1", "correct")
    ]
    for partners in (LEARNERS, ["sp/1"]):
        out += [_cook(cook, partners, "0+0+0", "wrong"), _cook(cook, partners, "1+1+1", "correct")]
    return out


@check("signal_cooks_says")
def _():
    counts = {r["episodes"] for s in ("sp/0", "sp/1") for r in button_rows(s, "sp/2", "1+1+1")}
    return [*gcs_seed2_wrong(), counts.pop() if len(counts) == 1 else math.nan]


@check("signal_verdict_sign")
def _():
    sp = run(GCS, SP)["xp"]
    return [sp["xp_mean"], sp["sp_mean"], sp["gap"], sp["num_policies"], *interval(sp, "gap"), *paper(GCS, SP)]


@check("signal_verdict_seed2")
def _():
    p = both_seats(gcs_sp())
    own = button_rows("sp/2", "sp/2", "1+1+1")[0]["return"]
    return [2, 2, 0, 1, *gcs_seed2_wrong(), 2, *gcs_without_seed2(), 1, 3, p[1, 3], p[1, 1], p[3, 3], 2, own]


@check("signal_verdict_fcp")
def _():
    fcp, sp = run(GCS, FCP)["xp"], run(GCS, SP)["xp"]
    return [fcp["gap"], sp["gap"], fcp["xp_mean"], sp["xp_mean"], paper(GCS, FCP)[2], paper(GCS, SP)[2]]


@check("signal_verdict_fcp_cook")
def _():
    return [study_block(GCS, SP, FCP)["xp_mean"]]


@check("signal_budget")
def _():
    def rate(c):
        return sum(s * w for w, s, _ in c) / sum(w for w, _, _ in c)  # env steps over seconds

    sp_rate, fcp_rate = rate(chunks(SP)), rate(chunks(FCP, after=RESUMED_AT))
    per_seed = run(GCS, SP)["env_steps_per_seed"] / summary(GCS)["budget"]
    seeds = run(GCS, SP)["seeds"]
    return [
        sp_rate,
        fcp_rate,
        seeds,
        per_seed / 1e6,
        per_seed * seeds / sp_rate / 3600,
        per_seed * seeds / fcp_rate / 3600,
    ]
