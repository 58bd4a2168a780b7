"""The data: the committed files under docs/results/ read into numbers (summary.json, the cross-play matrices,
metrics.csv, per-episode returns, the markdown tables the scripts beside them wrote), and the cells that several
sections of the page write the same way (a block with its intervals, a run's size, a claims-table row)."""

from __future__ import annotations

import csv
import functools
import itertools
import json
import math
import re
from pathlib import Path

import numpy as np

from .folders import CR, GCS


def float_or_nan(x):
    return float(x) if x not in ("", None) else math.nan


@functools.cache
def summary(study: Path) -> dict:
    return json.loads((study / "summary.json").read_text())


def run(study: Path, name: str) -> dict:
    return next(r for r in summary(study)["runs"] if r["name"] == name)


@functools.cache
def matrix(path: Path) -> np.ndarray:
    """A cross-play matrix file (seat 0 = row) as an array."""
    with path.open() as f:
        rows = list(csv.reader(f))[1:]
    return np.array([[float(x) for x in row[1:]] for row in rows])


def both_seats(m: np.ndarray) -> np.ndarray:
    return (m + m.T) / 2


def sp_xp(m: np.ndarray, seeds=None) -> tuple[float, float, float]:
    if seeds is not None:
        m = m[np.ix_(seeds, seeds)]
    same = np.eye(len(m), dtype=bool)
    sp, xp = m[same].mean(), m[~same].mean()
    return sp, xp, sp - xp


def pairs(m: np.ndarray) -> list[float]:
    """Mean of both seat orders of every unordered pair of different seeds."""
    p = both_seats(m)
    return [p[i, j] for i, j in itertools.combinations(range(len(m)), 2)]


def interval(block: dict, key: str) -> list[float]:
    return list(block[f"{key}_ci95_interval"])


def block(study_block: dict) -> list[float]:
    """SP, XP, gap with their intervals: [sp, lo, hi, xp, lo, hi, gap, lo, hi]."""
    out = []
    for key, mean in (("sp", "sp_mean"), ("xp", "xp_mean"), ("gap", "gap")):
        out += [study_block[mean], *interval(study_block, key)]
    return out


def over_training(run_name: str) -> list[dict]:
    return next(o for o in summary(CR)["over_training"] if o["run"] == run_name)["points"]


def point(run_name: str, update: int) -> dict:
    return next(p for p in over_training(run_name) if p["update"] == update)


@functools.cache
def metrics(name: str) -> list[dict]:
    with (GCS / f"{name}_metrics.csv").open() as f:
        return list(csv.DictReader(f))


def metric(name: str, update: int, column: str) -> list[float]:
    """``column`` of every seed at ``update``, seeds in order."""
    rows = sorted((r for r in metrics(name) if int(r["update"]) == update), key=lambda r: int(r["seed"]))
    return [float_or_nan(r[column]) for r in rows]


def chunks(name: str, after: int = 0) -> list[tuple[float, float, int]]:
    """The training chunks of a run from its metrics.csv (every update of a chunk carries the chunk's wall
    time and speed): [(wall_s, env steps per second, updates)] of the chunks whose updates are > ``after``."""
    rows = [r for r in metrics(name) if r["seed"] == "0" and int(r["update"]) > after]
    out = []
    for key, group in itertools.groupby(rows, key=lambda r: (r["wall_s"], r["steps_per_s"])):
        out.append((float(key[0]), float(key[1]), len(list(group))))
    return out


@functools.cache
def episodes(name: str) -> list[dict]:
    with (GCS / f"{name}_xp_episodes.csv").open() as f:
        return [
            {
                "seat0": int(r["seat0"]),
                "seat1": int(r["seat1"]),
                "return": float(r["return"]),
                "recipe": r["start_recipe"],
            }
            for r in csv.DictReader(f)
        ]


def returns(name: str, seat0: int, seat1: int, recipe: str | None = None) -> np.ndarray:
    return np.array(
        [
            e["return"]
            for e in episodes(name)
            if (e["seat0"], e["seat1"]) == (seat0, seat1) and recipe in (None, e["recipe"])
        ]
    )


def pair_se(name: str, a: int, b: int) -> float:
    """Standard error over episodes of a cell written as the mean of both seat orders (the diagonal: one
    order)."""
    if a == b:
        x = returns(name, a, a)
        return x.std(ddof=1) / math.sqrt(len(x))
    x, y = returns(name, a, b), returns(name, b, a)
    return 0.5 * math.sqrt(x.var(ddof=1) / len(x) + y.var(ddof=1) / len(y))


def md_tables(path: Path) -> list[list[list[str]]]:
    """Every markdown table of a file: its body rows as lists of cell strings."""
    return [rows for _, _, rows in _md_table_blocks(path)]


def md_tables_by_heading(path: Path) -> dict[str, list[dict[str, str]]]:
    """Every markdown table of a file by the ``##`` heading above it (one table per heading), each body row as
    {column header: cell}: a reader that names its columns is not shifted by a column added before them."""
    return {
        heading: [dict(zip(header, row, strict=True)) for row in rows]
        for heading, header, rows in _md_table_blocks(path)
    }


def _md_table_blocks(path: Path) -> list[tuple[str | None, list[str], list[list[str]]]]:
    """(the ``##`` heading above it, its header cells, its body rows) of every markdown table of a file."""
    tables, current, heading = [], None, None
    for line in path.read_text().split("\n"):
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if current is None:
                current = []
                tables.append((heading, cells, current))
            elif not all(re.fullmatch(r":?-+:?", c) for c in cells):
                current.append(cells)
        else:
            current = None
            if line.startswith("## "):
                heading = line[3:].strip()
    return tables


@functools.cache
def ring() -> dict:
    """ring_direction.md: {"sp": {update: [(cw seat 0, cw seat 1, return) per seed]}, "probe": ..., "sa": ...,
    "sp_archive"/"sa_archive": {(seat0, seat1): (cw seat 0, cw seat 1, return)}}."""
    sp, sp_archive, probe, sa, sa_archive = md_tables(CR / "ring_direction.md")

    def snapshots(table):
        return {int(row[0]): [tuple(float(x) for x in cell.split(",")) for cell in row[1:]] for row in table}

    def archive(table):
        return {(int(r[0]), int(r[1])): (float(r[2]), float(r[3]), float(r[4])) for r in table}

    return {
        "sp": snapshots(sp),
        "sp_archive": archive(sp_archive),
        "probe": snapshots(probe),
        "sa": snapshots(sa),
        "sa_archive": archive(sa_archive),
    }


@functools.cache
def buttons() -> list[dict]:
    """button_use.md: one dict per (seat 0, seat 1, starting recipe)."""
    (table,) = md_tables(GCS / "button_use.md")
    keys = ("presses", "top", "bottom", "correct", "wrong", "return")
    return [
        {"seat0": r[0], "seat1": r[1], "recipe": r[2], "episodes": int(r[3]), **dict(zip(keys, map(float, r[4:])))}
        for r in table
    ]


def button_rows(seat0=None, seat1=None, recipe=None) -> list[dict]:
    return [
        r
        for r in buttons()
        if seat0 in (None, r["seat0"]) and seat1 in (None, r["seat1"]) and recipe in (None, r["recipe"])
    ]


def mean(rows, key) -> float:
    return float(np.mean([r[key] for r in rows]))


def hm(seconds: float) -> list[int]:
    """A duration as [hours, minutes], rounded to the minute."""
    minutes = round(seconds / 60)
    return [minutes // 60, minutes % 60]


def study_wall(study: Path) -> list:
    """A study's wall time in its record, as hours and minutes."""
    return hm(summary(study)["wall_s"])


def span(values) -> list[float]:
    values = list(values)
    return [min(values), max(values)]


SP, FCP = "sp", "fcp"
SEEDS = ["sp/0", "sp/1", "sp/2", "sp/3"]
LEARNERS = ["fcp/0", "fcp/1", "fcp/2", "fcp/3"]
SP_SP_SA_BC = CR / "xp_coord_ring_sp_sa_human.csv"
GCS_8X8 = GCS / "xp_grounded_coord_simple_sp_fcp.csv"


def cr_sp() -> np.ndarray:
    return matrix(CR / "xp_sp.csv")


def cr_sa() -> np.ndarray:
    return matrix(CR / "xp_sa.csv")


def gcs_sp() -> np.ndarray:
    return matrix(GCS / "xp_sp.csv")


def gcs_fcp() -> np.ndarray:
    return matrix(GCS / "xp_fcp.csv")


def study_block(study: Path, rows: str, cols: str) -> dict:
    return next(b for b in summary(study)["comparisons"][0]["blocks"] if (b["rows"], b["cols"]) == (rows, cols))


def study_pair(study: Path, a: str, b: str) -> dict:
    return next(p for p in summary(study)["comparisons"][0]["pairs"] if (p["a"], p["b"]) == (a, b))


def paper(study: Path, name: str) -> list[float]:
    p = run(study, name)["paper"]
    return [p["sp"]["mean"], p["xp"]["mean"], p["gap"]["mean"]]


def millions(study: Path, name: str) -> float:
    return run(study, name)["env_steps_per_seed"] / 1e6


def run_size(study: Path, name: str) -> list:
    """A run's env steps per seed and its number of updates."""
    r = run(study, name)
    return [r["env_steps_per_seed"], r["update"]]


def claim_row(study: Path, name: str) -> list:
    """The claims table's "ours" cell of a run: seeds x env steps, SP and XP with their std, the gap and its
    interval over the seeds."""
    xp = run(study, name)["xp"]
    return [
        xp["num_policies"],
        millions(study, name),
        xp["sp_mean"],
        xp["sp_std"],
        xp["xp_mean"],
        xp["xp_std"],
        xp["gap"],
        xp["num_policies"],
        *interval(xp, "gap"),
    ]
