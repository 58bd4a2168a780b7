"""Checks that every 10-seed study has, most registered by a loop rather than written out: each SP study's headline
rows (``<name>_final``, ``_within``, ``_low_pairs``, ``_claim``), each SA study's rows beside its
SP seeds (``<name>_final``, ``_delta``, ``_paired``, ``_low_pairs``, ``_claim``) and the runs table's size and
wall-time cells (``run_<name>``, ``run_<name>_wall``), and the table of every 10-seed verdict's matrix played again from
its published files (``replays``, with their sum: ``replays_total``)."""

from __future__ import annotations

import functools
from pathlib import Path

from .data import claim_row, paper, run, run_size, study_wall
from .folders import (
    AA10,
    CC10,
    CC10_6M,
    CC_SA10,
    CC_SA10_6M,
    CRM10,
    CRM_SA10,
    FC10,
    FC_SA10,
    GPU410,
    GPU_CR,
    SA10,
    SP10,
)
from .registry import check
from .ten_seed_studies import (
    final_matrix,
    final_numbers,
    low_pair_numbers,
    low_pairs,
    paired_gap_difference,
    paper_beside_intervals,
    replay_row,
)

# --- what every 10-seed SA study beside its 10 SP seeds at the same budget reports


@functools.cache
def study_delta(base: Path, base_method: str, other: Path, other_method: str) -> dict:
    """``other``'s SP, XP and gap minus ``base``'s (two finished 10-seed studies), with 95 % intervals, both
    populations' seeds resampled each on its own: the function ``ocv2 report`` and the study report use (imported
    here, so JAX loads only for these checks)."""
    from population.xp import bootstrap_difference

    return bootstrap_difference(final_matrix(base, base_method), final_matrix(other, other_method))


def gap_delta_numbers(base: Path, base_method: str, other: Path, other_method: str) -> list:
    """[other's gap minus base's, its 95 % interval (``study_delta``), the paper's gap difference]."""
    here, there = run(other, other_method)["xp"]["gap"], run(base, base_method)["xp"]["gap"]
    paper_delta = paper(other, other_method)[2] - paper(base, base_method)[2]
    return [here - there, *study_delta(base, base_method, other, other_method)["gap"], paper_delta]


def sa_final(sp: Path, sa: Path) -> list:
    """The SA population's SP, XP and gap with intervals (``final_numbers``)."""
    return final_numbers(sa, "sa")


def sa_delta(sp: Path, sa: Path) -> list:
    """SA's gap, SP's gap, their difference with its interval and the paper's difference."""
    return [run(sa, "sa")["xp"]["gap"], run(sp, "sp")["xp"]["gap"], *gap_delta_numbers(sp, "sp", sa, "sa")]


def sa_paired(sp: Path, sa: Path) -> list:
    """The gap difference's interval with the same seeds resampled in both populations."""
    return paired_gap_difference(final_matrix(sp), final_matrix(sa, "sa"))


def sa_low_pairs(sp: Path, sa: Path) -> list:
    """SA's failing pairs (``low_pair_numbers``) beside SP's count."""
    return [*low_pair_numbers(sa, "sa"), len(low_pairs(sp)), 45]


def sa_claim(sp: Path, sa: Path) -> list:
    """The claims table's row: SA's numbers, the gap difference and the failing pairs."""
    return [*claim_row(sa, "sa"), *gap_delta_numbers(sp, "sp", sa, "sa")[:3], len(low_pairs(sa, "sa")), 45]


SA_BESIDE_SP = {"final": sa_final, "delta": sa_delta, "paired": sa_paired, "low_pairs": sa_low_pairs, "claim": sa_claim}


def register_sa_beside_sp() -> None:
    """``<name>_final``, ``_delta``, ``_paired``, ``_low_pairs`` and ``_claim`` of each SA study beside its SP seeds
    (the Coordination Ring section, written first, states its failing pairs in a check of its own: sa10_pairs)."""
    studies = {
        "sa10": (SP10, SA10, ("final", "delta", "paired", "claim")),
        "fc_sa10": (FC10, FC_SA10, tuple(SA_BESIDE_SP)),
        "cc_sa10": (CC10, CC_SA10, tuple(SA_BESIDE_SP)),
        "cc_sa10_6m": (CC10_6M, CC_SA10_6M, tuple(SA_BESIDE_SP)),
        "crm_sa10": (CRM10, CRM_SA10, tuple(SA_BESIDE_SP)),
    }
    for name, (sp, sa, kinds) in studies.items():
        for kind in kinds:
            check(f"{name}_{kind}")(functools.partial(SA_BESIDE_SP[kind], sp, sa))


register_sa_beside_sp()

# --- what every 10-seed SP study reports at its stop


def sp_claim(study: Path) -> list:
    """The claims table's row: the headline (``claim_row``) and the failing pairs of 45."""
    return [*claim_row(study, "sp"), len(low_pairs(study)), 45]


SP_ROWS = {
    "final": lambda study: final_numbers(study, "sp"),
    "within": lambda study: paper_beside_intervals(study, "sp"),
    "low_pairs": low_pair_numbers,
    "claim": sp_claim,
}


def register_sp_rows() -> None:
    """``<name>_final``, ``_within``, ``_low_pairs`` and ``_claim`` of each 10-seed SP study, those its sections
    state (Coordination Ring's failing pairs are worded with their counts by convention: sp10_low_pairs; the 6M
    Counter Circuit claim names both budgets: cc10_6m_claim)."""
    studies = {
        "sp10": (SP10, ("final", "claim")),
        "fc10": (FC10, ("final", "low_pairs", "claim")),
        "cc10": (CC10, tuple(SP_ROWS)),
        "cc10_6m": (CC10_6M, ("final", "within", "low_pairs")),
        "crm10": (CRM10, tuple(SP_ROWS)),
        "aa10": (AA10, tuple(SP_ROWS)),
    }
    for name, (study, kinds) in studies.items():
        for kind in kinds:
            check(f"{name}_{kind}")(functools.partial(SP_ROWS[kind], study))


register_sp_rows()


def register_run_rows() -> None:
    """The runs table's size and wall-time cells of each 10-seed CPU study: ``run_<name>`` (env steps per seed and
    updates) and ``run_<name>_wall`` (hours and minutes in the study's record)."""
    studies = {
        "sp10": (SP10, "sp"),
        "sa10": (SA10, "sa"),
        "fc10": (FC10, "sp"),
        "fc_sa10": (FC_SA10, "sa"),
        "cc10": (CC10, "sp"),
        "cc_sa10": (CC_SA10, "sa"),
        "cc10_6m": (CC10_6M, "sp"),
        "cc_sa10_6m": (CC_SA10_6M, "sa"),
        "crm10": (CRM10, "sp"),
        "crm_sa10": (CRM_SA10, "sa"),
        "aa10": (AA10, "sp"),
    }
    for name, (study, method) in studies.items():
        check(f"run_{name}")(functools.partial(run_size, study, method))
        check(f"run_{name}_wall")(functools.partial(study_wall, study))


register_run_rows()


#: Every 10-seed verdict's matrix, in the order of the page's sections: (study folder, method, the verdict's
#: matrix file when it is not the folder's xp_<method>.csv).
VERDICT_MATRICES = (
    (SP10, "sp", None),
    (GPU410, "sp", GPU410 / "matrix.csv"),
    (GPU_CR, "sp", None),
    (SA10, "sa", None),
    (FC10, "sp", None),
    (FC_SA10, "sa", None),
    (CC10, "sp", None),
    (CC10_6M, "sp", None),
    (CC_SA10, "sa", None),
    (CC_SA10_6M, "sa", None),
    (CRM10, "sp", None),
    (CRM_SA10, "sa", None),
    (AA10, "sp", None),
)


@check("replays")
def replays() -> list:
    """Per verdict, its matrix played again from the published files (``replay_row``)."""
    return [number for row in replay_rows() for number in row]


@check("replays_total")
def replays_total() -> list:
    """All the replays together: the cells played again, how many equal the study's, how many differ."""
    cells, equal = sum(row[2] for row in replay_rows()), sum(row[3] for row in replay_rows())
    return [cells, equal, cells - equal]


@functools.cache
def replay_rows() -> tuple[list, ...]:
    return tuple(replay_row(study, method, verdict_csv) for study, method, verdict_csv in VERDICT_MATRICES)
