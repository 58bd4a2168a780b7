"""Checks of the 4-seed Coordination Ring study (table1_coord_ring/): SP, the ring direction its seeds walk
and the 8 more seeds' probe, then SA and the SP x SA x BC human proxy comparison."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np

from .coord_ring_layout import coord_ring_moves
from .data import (
    SP_SP_SA_BC,
    block,
    both_seats,
    cr_sa,
    cr_sp,
    hm,
    interval,
    matrix,
    over_training,
    pairs,
    paper,
    point,
    ring,
    run,
    sp_xp,
    span,
    study_pair,
    summary,
)
from .folders import CR
from .four_seed_bootstrap import gap_at_most_zero, gap_zero_pattern
from .four_seed_studies import CLOCKWISE, EVEN, clockwise_shares, cr_millions, sa_ccw_seed_pairs
from .registry import L, check

# --- Coordination Ring SP


@check("cr_sp_matrix")
def _():
    return list(both_seats(cr_sp()).ravel())


@check("cr_sp_final")
def _():
    xp = run(CR, "sp")["xp"]
    return [xp["num_policies"], *block(xp)]


@check("cr_sp_final_four")
def _():
    count, total = gap_at_most_zero(cr_sp())
    return [count, total, *gap_zero_pattern(cr_sp()), L]


@check("cr_sp_final_note")
def _():
    m = cr_sp()
    p = both_seats(m)
    best = int(np.argmax(np.diag(m)))
    others = sorted((p[best, j], j) for j in range(4) if j != best)
    ordered = m[~np.eye(4, dtype=bool)]
    pp = run(CR, "sp")["paper"]["xp"]
    return [
        best,
        m[best, best],
        others[0][0],
        others[0][1],
        others[1][0],
        others[1][1],
        pp["mean"],
        pp["std"],
        len(ordered),
        ordered.min(),
    ]


def _over_training_rows(name, lowest=True, first=0):
    out = []
    for p in over_training(name):
        if p["update"] < first:
            continue
        row = [
            p["env_steps_per_seed"],
            p["sp_mean"],
            *interval(p, "sp"),
            p["xp_mean"],
            *interval(p, "xp"),
            p["gap"],
            *interval(p, "gap"),
        ]
        if lowest:
            row.append(min(pairs(np.array(p["matrix"]))))
        row.append(gap_at_most_zero(p["matrix"])[0])
        out += row
    return out


@check("cr_sp_over_training")
def _():
    p = run(CR, "sp")["paper"]
    full = run(CR, "sp")["env_steps_per_seed"] / summary(CR)["budget"] / 1e6
    return [
        *_over_training_rows("sp"),
        full,
        p["sp"]["mean"],
        p["sp"]["std"],
        p["xp"]["mean"],
        p["xp"]["std"],
        p["gap"]["mean"],
    ]


@check("cr_sp_over_training_says")
def _():
    gap = {p["update"]: p["gap"] for p in over_training("sp")}
    sp = {p["update"]: p["sp_mean"] for p in over_training("sp")}
    late = [g for u, g in gap.items() if u >= 183]
    worst = 0.0
    for p in over_training("sp")[1:]:
        m = np.array(p["matrix"])
        b = both_seats(m)
        for i, j in itertools.combinations(range(4), 2):
            worst = max(worst, 1 - b[i, j] / max(m[i, i], m[j, j]))
    return [
        gap[30],
        gap[183],
        cr_millions("sp", 183),
        sp[30],
        sp[183],
        *span(late),
        cr_millions("sp", 305),
        sp[305],
        cr_millions("sp", 305),
        100 * worst,
    ]


@check("cr_geometry")
def _():
    g = coord_ring_moves()
    return [v for leg in g["legs"] for v in leg] + [
        g["onion_pot"][0] if g["onion_pot"][0] == g["onion_pot"][1] else math.nan,
        *g["cycle"],
    ]


def _last_looks():
    """Clockwise share of seat 0 at each seed's last look: SP and SA at update 305, the 8 more seeds at 61."""
    return clockwise_shares("sp", 305) + clockwise_shares("sa", 305) + clockwise_shares("probe", 61)


@check("cr_direction_count")
def _():
    shares = _last_looks()
    clockwise = [s for s in shares if s >= CLOCKWISE]
    even = sorted(s for s in shares if EVEN <= s < CLOCKWISE)
    sa_ccw = [(i, s) for i, s in enumerate(clockwise_shares("sa", 305)) if s < EVEN]
    probe_ccw = [(i, s) for i, s in enumerate(clockwise_shares("probe", 61)) if s < EVEN]
    (sa_seed, sa_share), (probe_seed, probe_share) = (
        sa_ccw + probe_ccw if len(sa_ccw + probe_ccw) == 2 else [(math.nan,) * 2] * 2
    )
    return [
        len(clockwise),
        len(shares),
        *span(clockwise),
        len(even),
        *even,
        len(sa_ccw) + len(probe_ccw),
        sa_share,
        sa_seed,
        cr_millions("sa", 305),
        probe_share,
        probe_seed,
        len(clockwise_shares("probe", 61)),
        cr_millions("sp", 61),
    ]


@check("cr_paper_xp")
def _():
    sp, xp = paper(CR, "sp")[:2]
    k = 10

    def xp_with(minority, cross=0.0):
        cells, bad = k * (k - 1), 2 * minority * (k - minority)
        return (sp * (cells - bad) + cross * bad) / cells

    nearest = sorted(range(1, k // 2 + 1), key=lambda n: abs(xp_with(n) - xp))[:2]
    a, b = sorted(nearest)
    cross = float(np.mean(sa_ccw_seed_pairs()[1]))
    return [0, sp, xp, a, b, k, xp_with(a), xp_with(b), cross, k // 2, k // 2, xp_with(k // 2, cross)]


@check("cr_direction_final")
def _():
    out = []
    p = both_seats(cr_sp())
    for seed in range(4):
        cw = ring()["sp_archive"][(seed, seed)]
        partner = min((j for j in range(4) if j != seed), key=lambda j: p[seed, j])
        out += [cw[0], cw[1], p[seed, partner], partner]
    return out


@check("cr_direction_snapshots")
def _():
    return [s for update in (0, 30, 61, 122, 305) for s in clockwise_shares("sp", update)]


@check("cr_direction_seat1")
def _():
    return [max(abs(c[0] - c[1]) for cells in ring()["sp"].values() for c in cells)]


@check("probe_table")
def _():
    out = []
    for update in (30, 50, 61):
        cells = ring()["probe"][update]
        out += [c[0] for c in cells] + [c[2] for c in cells]
    return out


@check("probe_says")
def _():
    at30, at61 = clockwise_shares("probe", 30), clockwise_shares("probe", 61)
    early = [i for i, s in enumerate(at30) if s < 0.5]
    even = [i for i in early if EVEN <= at61[i] < CLOCKWISE]
    ccw = min(range(8), key=lambda i: at61[i])
    firm = [s for s in at61 if s >= 0.68]
    weak = [(i, s) for i, s in enumerate(at61) if CLOCKWISE <= s < 0.68]
    return [
        30,
        len(early),
        61,
        len(even),
        *even,
        *(at61[i] for i in even),
        ccw,
        at30[ccw],
        at61[ccw],
        ring()["probe"][61][ccw][2],
        len(firm),
        *span(firm),
        61,
        len(clockwise_shares("sp", 61)),
        *span(clockwise_shares("sp", 61)),
        *(v for w in weak for v in w),
    ]


def _xp12():
    return json.loads((CR / "xp12_update61" / "summary.json").read_text())


@check("xp12_wall")
def _():
    return [_xp12()["wall_s"]]


@check("xp12_pooled")
def _():
    pooled = _xp12()["pooled"]
    return [pooled["num_rows"], *block(pooled), 4, point("sp", 61)["gap"]]


@check("xp12_row")
def _():
    m = matrix(CR / "xp12_update61" / "matrix_mean.csv")
    i = 4 + int(np.argmin(clockwise_shares("probe", 61)))  # the counter-clockwise seed of the 8 (after the study's 4)
    avg = [(m[j].sum() - m[j, j]) / 11 for j in range(12)]
    others = [a for j, a in enumerate(avg) if j != i]
    return [
        i - 4,
        m[i, i],
        *span(m[i, :4]),
        4,
        avg[i],
        11,
        *span(others),
        np.mean(others) - avg[i],
        cr_millions("sp", 61),
        avg[i],
        np.mean(others),
    ]


# --- Coordination Ring SA


@check("cr_sa_wall")
def _():
    return hm(run(CR, "sa")["wall_s"])


@check("cr_sa_matrix")
def _():
    return list(both_seats(cr_sa()).ravel())


@check("cr_sa_table")
def _():
    out = block(run(CR, "sa")["xp"]) + block(run(CR, "sp")["xp"])
    for name in ("sa", "sp"):
        p = run(CR, name)["paper"]
        out += [p["sp"]["mean"], p["sp"]["std"], p["xp"]["mean"], p["xp"]["std"], p["gap"]["mean"]]
    return out


@check("cr_sa_four")
def _():
    count, total = gap_at_most_zero(cr_sa())
    return [L, count, total, *gap_zero_pattern(cr_sa()), L]


@check("cr_sa_says")
def _():
    sa_diag, sp_diag = np.diag(cr_sa()), np.diag(cr_sp())
    p = both_seats(cr_sa())
    sa, sp = run(CR, "sa"), run(CR, "sp")
    return [
        sa["xp"]["sp_mean"],
        sp["xp"]["sp_mean"],
        int((sa_diag > sp_diag.max()).sum()),
        len(sa_diag),
        sa["paper"]["sp"]["mean"],
        sp["paper"]["sp"]["mean"],
        sa["xp"]["gap"],
        sp["xp"]["gap"],
        1,
        p[1, 1],
        p[1, 3],
        p[1, 2],
        3,
        2,
        p[1, 0],
        0,
        1,
        3,
        *sp_xp(cr_sa(), [0, 2, 3]),
        sp["xp"]["gap"],
        2,
        p[2, 0],
        0,
        max(clockwise_shares("sa", 305)),
    ]


@check("cr_sa_over_training")
def _():
    return _over_training_rows("sa", lowest=False, first=1)


@check("cr_sa_over_training_says")
def _():
    interim = [json.loads((CR / f"xp_sp_sa_update{u}" / "summary.json").read_text()) for u in (152, 244)]
    gaps = [
        next(b for b in s["blocks"] if b["rows"].endswith("/sa") and b["cols"].endswith("/sa"))["gap"] for s in interim
    ]
    late = [p["xp_mean"] for p in over_training("sa") if p["update"] >= 92]
    return [
        cr_millions("sa", 61),
        point("sp", 61)["gap"],
        *span(late),
        cr_millions("sa", 92),
        152,
        244,
        interim[0]["episodes_per_pair"],
        *gaps,
        point("sa", 152)["gap"],
        point("sa", 244)["gap"],
    ]


@check("cr_sa_exclude")
def _():
    points = [p for p in over_training("sa") if p["update"] > 0]
    return [sum(p["gap_ci95_interval"][0] > 0 for p in points), len(points)]


@check("cr_sa_direction_seat1")
def _():
    return [max(abs(c[0] - c[1]) for cells in ring()["sa"].values() for c in cells)]


@check("cr_sa_direction")
def _():
    return [v for update in (30, 61, 122, 183, 244, 305) for cell in ring()["sa"][update] for v in (cell[0], cell[2])]


@check("cr_sa_pairs")
def _():
    a = ring()["sa_archive"]
    out = []
    for partner in (0, 2, 3):
        first, second = a[(1, partner)], a[(partner, 1)]  # seed 1 in seat 0, then in seat 1
        out += [first[1], second[0], first[0], second[1], first[2], second[2]]
    return out


@check("cr_sa_pairs_says")
def _():
    a = ring()["sa_archive"]
    study = both_seats(np.array(point("sa", 244)["matrix"]))
    interim = json.loads((CR / "xp_sp_sa_update244" / "summary.json").read_text())
    look = matrix(CR / "xp_sp_sa_update244" / "matrix_mean.csv")[4:, 4:]  # its SA x SA block
    shares = clockwise_shares("sa", 244)
    return [
        *span([a[(1, 0)][2], a[(0, 1)][2]]),
        *span([a[(1, 3)][2], a[(3, 1)][2]]),
        244,
        0,
        3,
        shares[0] if abs(shares[0] - shares[3]) < 0.005 else math.nan,
        look[0, 1],
        look[3, 1],
        1,
        interim["episodes_per_pair"],
        study[0, 1],
        study[3, 1],
        point("sa", 244)["episodes_per_pair"],
    ]


@check("cr_9x9")
def _():
    return list(both_seats(matrix(SP_SP_SA_BC)).ravel())


@check("cr_9x9_pairs")
def _():
    out = []
    for a, b in (("sp", "sa"), ("sp", "human-proxy:coord_ring"), ("sa", "human-proxy:coord_ring")):
        p = study_pair(CR, a, b)
        out += [p["a_seat0"], p["a_seat0_std"], p["a_seat1"], p["a_seat1_std"], p["mean"], *p["mean_ci95_interval"]]
    return out


@check("cr_9x9_says")
def _():
    p = both_seats(matrix(SP_SP_SA_BC))
    return [
        *span(sa_ccw_seed_pairs()[1]),
        np.mean([p[i, j] for i in range(4) for j in (4, 6, 7)]),
        run(CR, "sp")["xp"]["xp_mean"],
        study_pair(CR, "sp", "human-proxy:coord_ring")["mean"],
        study_pair(CR, "sa", "human-proxy:coord_ring")["mean"],
        p[8, 8],
        *span(p[8, j] for j in range(8) if j != 5),
        p[8, 5],
        0,
        1,
        2,
        p[1, 4],
        1,
        p[3, 4],
        3,
        *span(p[i, j] for i in range(4) for j in (6, 7)),
    ]


@check("cr_sa_verdict")
def _():
    sa, sp = run(CR, "sa")["xp"], run(CR, "sp")["xp"]
    return [
        sa["num_policies"],
        sa["gap"],
        sa["num_policies"],
        *interval(sa, "gap"),
        sp["gap"],
        *interval(sp, "gap"),
        paper(CR, "sa")[2],
        paper(CR, "sp")[2],
    ]


@check("cr_sa_verdict_pairs")
def _():
    own, with_sp = sa_ccw_seed_pairs()
    ccw = [s for s in clockwise_shares("sa", 305) if s < EVEN]
    return [len(cr_sp()), len(ccw), len(cr_sa()), *span(own[1:]), *span(with_sp)]


@check("cr_sa_verdict_one")
def _():
    own, with_sp = sa_ccw_seed_pairs()
    working_sa = [s for s in own[1:] if s > 100]
    working_sp = [s for s in with_sp if s > 100]
    return [len(working_sa), 3, 0, both_seats(cr_sa())[0, 1], len(working_sp), len(with_sp), *span(with_sp)]
