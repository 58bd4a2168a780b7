"""Checks of the page's opening sections: the top of the page, "Intervals at 4 seeds", "What is being run, and
why this budget" and the 4-seed studies' rows of the claims table."""

from __future__ import annotations

import itertools
import math

import numpy as np

from .data import (
    FCP,
    SP,
    block,
    both_seats,
    chunks,
    claim_row,
    cr_sa,
    cr_sp,
    gcs_fcp,
    gcs_sp,
    hm,
    interval,
    millions,
    over_training,
    pairs,
    paper,
    ring,
    run,
    run_size,
    sp_xp,
    span,
    study_pair,
    study_wall,
    summary,
)
from .folders import CR, GCS
from .four_seed_bootstrap import gap_at_most_zero, resamples
from .four_seed_studies import (
    CLOCKWISE,
    EVEN,
    RESUMED_AT,
    clockwise_shares,
    cr_millions,
    gcs_seed2_wrong,
    gcs_training_s,
    gcs_without_seed2,
    sa_ccw_seed_pairs,
)
from .registry import L, check

# --- top of the page


@check("top_cr_sp_size")
def _():
    return [run(CR, "sp")["seeds"], millions(CR, "sp")]


@check("top_cr_sp")
def _():
    xp = run(CR, "sp")["xp"]
    return [xp["sp_mean"], xp["xp_mean"], xp["gap"], xp["num_policies"], *interval(xp, "gap"), *paper(CR, "sp")]


@check("top_cr_sp_worst")
def _():
    p = both_seats(cr_sp())
    i, j = min(itertools.combinations(range(4), 2), key=lambda ij: p[ij])
    return [i, j, p[i, j]]


@check("top_cr_sp_growth")
def _():
    gap = {p["update"]: p["gap"] for p in over_training("sp")}
    late = [g for u, g in gap.items() if u >= 183]
    return [
        gap[30],
        cr_millions("sp", 30),
        gap[122],
        cr_millions("sp", 122),
        gap[183],
        cr_millions("sp", 183),
        *span(late),
        cr_millions("sp", 183),
        cr_millions("sp", 305),
    ]


@check("top_probe")
def _():
    early = [s for s in clockwise_shares("probe", 30) if s < 0.5]
    at61 = clockwise_shares("probe", 61)
    ccw = min(range(8), key=lambda i: at61[i])
    even = sorted(s for s in at61 if EVEN <= s < CLOCKWISE)
    firm = [s for s in at61 if s >= 0.68]
    (weak,) = [i for i, s in enumerate(at61) if CLOCKWISE <= s < 0.68]
    ccw_count = sum(s < EVEN for s in at61)
    return [
        cr_millions("sp", 30),
        len(early),
        *span(early),
        cr_millions("sp", 61),
        ccw_count,
        ccw,
        at61[ccw],
        ring()["probe"][61][ccw][2],
        len(even),
        *even,
        len(firm),
        *span(firm),
        weak,
        at61[weak],
    ]


@check("top_twelve")
def _():
    k = 12
    sp, xp, _ = sp_xp(cr_sp())
    cells, bad = k * (k - 1), 2 * (k - 1)
    xp12 = xp * (cells - bad) / cells
    return [k, bad, cells, 0, xp, len(cr_sp()), xp12, sp - xp12, paper(CR, "sp")[2]]


@check("top_cr_sa")
def _():
    xp = run(CR, "sa")["xp"]
    return [xp["sp_mean"], xp["xp_mean"], xp["gap"], xp["num_policies"], *interval(xp, "gap"), *paper(CR, "sa")]


@check("top_cr_sa_seed1")
def _():
    own, with_sp = sa_ccw_seed_pairs()
    return [own[0], *own[1:3], 2, own[3], *span(with_sp)]


@check("top_bc")
def _():
    return [
        study_pair(CR, "sp", "human-proxy:coord_ring")["mean"],
        study_pair(CR, "sa", "human-proxy:coord_ring")["mean"],
    ]


@check("top_gcs_sp_size")
def _():
    return [run(GCS, SP)["seeds"], millions(GCS, SP)]


@check("top_gcs_sp")
def _():
    xp = run(GCS, SP)["xp"]
    return [xp["sp_mean"], xp["xp_mean"], xp["gap"], xp["num_policies"], *interval(xp, "gap"), *paper(GCS, SP)]


@check("top_gcs_sp_story")
def _():
    return [2, 0, 1, *gcs_seed2_wrong(), 2, *gcs_without_seed2(), 1, 3, both_seats(gcs_sp())[1, 3]]


@check("top_gcs_sp_ratio")
def _():
    xp = run(GCS, SP)["xp"]
    p = paper(GCS, SP)
    return [p[0] / xp["sp_mean"], p[1] / xp["xp_mean"], p[2] / xp["gap"]]


@check("top_gcs_fcp_size")
def _():
    return [run(GCS, FCP)["seeds"], millions(GCS, FCP)]


@check("top_gcs_fcp")
def _():
    xp = run(GCS, FCP)["xp"]
    return [xp["sp_mean"], xp["xp_mean"], xp["gap"], xp["num_policies"], *interval(xp, "gap"), *paper(GCS, FCP)]


# --- intervals at 4 seeds


@check("four_seed_resamples")
def _():
    k = len(cr_sp())
    return [k, len(resamples(cr_sp())), k, k, k**k, k**k - len(resamples(cr_sp())), k]


@check("four_seed_pairs")
def _():
    k = len(cr_sp())
    draws = list(itertools.product(range(k), repeat=k))
    alone = sum(1 for d in draws if set(d) == {0, 1})
    total = len(resamples(cr_sp()))
    return [alone, k * (k - 1) // 2, alone * k * (k - 1) // 2, total, alone, total, 2.5]


@check("four_seed_exact")
def _():
    blocks = [(p["matrix"], p, p["update"]) for name in ("sp", "sa") for p in over_training(name) if p["update"] > 0]
    blocks += [(gcs_sp(), run(GCS, SP)["xp"], None), (gcs_fcp(), run(GCS, FCP)["xp"], None)]
    ends, differ = 0, []
    for m, b, update in blocks:
        r = resamples(np.asarray(m, float))
        for column, key in enumerate(("sp", "xp", "gap")):
            for exact, sampled in zip(np.percentile(r[:, column], [2.5, 97.5]), b[f"{key}_ci95_interval"]):
                ends += 1
                if round(exact, 1) != round(sampled, 1):
                    differ.append((update, sampled, exact))
    worst = max(abs(e - s) for _, s, e in differ)
    return [ends, 4, ends - len(differ), 252, len(differ), worst, *(v for d in differ for v in d)]


def _finals():
    return [cr_sp(), cr_sa(), gcs_sp()]


@check("four_seed_gap_zero")
def _():
    counts = [gap_at_most_zero(m) for m in _finals()]
    count = counts[0][0] if len({tuple(c) for c in counts}) == 1 else math.nan
    total = counts[0][1]
    snapshots = [p for name in ("sp", "sa") for p in over_training(name) if p["update"] > 0]
    low = [(gap_at_most_zero(p["matrix"])[0], p["gap_ci95_interval"][0] > 0) for p in snapshots]
    excluded = [c for c, excludes in low if c <= 6 and excludes]
    included = [c for c, excludes in low if c > 6 and not excludes]
    agree = len(excluded) + len(included) == len(low)  # else the page's "excludes"/"includes" is wrong
    updates = [p["update"] for p in snapshots]
    return [
        count,
        total,
        L,
        L,
        math.floor(0.025 * total),
        2.5,
        total,
        0.025 * total,
        len(low),
        min(updates),
        max(updates),
        len(excluded) if agree else math.nan,
        *span(excluded),
        L,
        len(included) if agree else math.nan,
        *span(included),
    ]


# --- what is being run


@check("run_cr_size")
def _():
    return run_size(CR, "sp")


@check("run_cr_wall")
def _():
    return study_wall(CR)


@check("run_gcs_size")
def _():
    return run_size(GCS, SP)


@check("run_gcs_sp_time")
def _():
    return [*hm(run(GCS, SP)["wall_s"]), *hm(gcs_training_s(SP)), *span(s for _, s, _ in chunks(SP))]


@check("run_gcs_fcp_time")
def _():
    return [
        *hm(run(GCS, FCP)["wall_s"]),
        *hm(gcs_training_s(FCP)),
        *span(s for _, s, _ in chunks(FCP, after=RESUMED_AT)),
    ]


@check("run_gcs_comparison")
def _():
    return [summary(GCS)["comparisons"][0]["wall_s"] / 60]


@check("run_gcs_wall")
def _():
    return study_wall(GCS)


@check("run_gcs_chunk")
def _():
    return span(w / 60 for w, _, n in chunks(SP) if n == 5)


@check("compute_gcs_speed")
def _():
    return span(s for _, s, _ in chunks(SP))


@check("compute_cr_sp_wall")
def _():
    return hm(run(CR, "sp")["wall_s"])


@check("compute_cr_sa_wall")
def _():
    return hm(run(CR, "sa")["wall_s"])


@check("compute_cr_comparison")
def _():
    return [summary(CR)["comparisons"][0]["wall_s"] / 60]


# --- claims table


@check("claim_cr_sp")
def _():
    return [*claim_row(CR, "sp"), min(pairs(cr_sp()))]


@check("claim_cr_sa")
def _():
    xp = run(CR, "sa")["xp"]
    return [xp["num_policies"], millions(CR, "sa"), xp["num_policies"], *block(xp), run(CR, "sp")["xp"]["gap"]]


@check("claim_cr_sa_verdict")
def _():
    own, with_sp = sa_ccw_seed_pairs()
    return [*span(with_sp), *span(own[1:])]


@check("claim_cr_sa_sp")
def _():
    return [run(CR, "sa")["xp"]["sp_mean"], run(CR, "sp")["xp"]["sp_mean"]]


@check("claim_gcs_sp")
def _():
    xp = run(GCS, SP)["xp"]
    return [xp["num_policies"], millions(GCS, SP), xp["num_policies"], *block(xp)]


@check("claim_gcs_sp_verdict")
def _():
    p = both_seats(gcs_sp())
    return [2, 0, 1, p[0, 2], p[1, 2], *gcs_seed2_wrong(), 2, *gcs_without_seed2(), 1, 3, p[1, 3], p[1, 1], p[3, 3]]


@check("claim_gcs_sp_size")
def _():
    return [run(GCS, SP)["xp"]["sp_mean"], paper(GCS, SP)[0]]


@check("claim_gcs_fcp")
def _():
    xp = run(GCS, FCP)["xp"]
    pair = study_pair(GCS, SP, FCP)
    final = run(GCS, SP)["update"]
    return [
        xp["num_policies"],
        millions(GCS, FCP),
        run(GCS, SP)["seeds"],
        final // 2,
        final,
        xp["num_policies"],
        *block(xp),
        pair["mean"],
        *pair["mean_ci95_interval"],
    ]


@check("claim_gcs_fcp_verdict")
def _():
    return [run(GCS, FCP)["xp"]["gap"], run(GCS, SP)["xp"]["gap"]]
