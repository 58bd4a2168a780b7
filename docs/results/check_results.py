"""Recompute the numbers of docs/RESULTS.md from the files under docs/results/ and compare them with the page.

    python docs/results/check_results.py [--doc docs/RESULTS.md] [--quiet]

Design. A number on the page is checked when it stands inside a tagged span,

    <!-- check:NAME -->SP 219.9, XP 209.4, gap 10.6 (95 % interval over 4 seeds: 1.4 to 29.0)<!-- /check -->

and this script has a function registered as NAME (``@check("NAME")`` below) that recomputes, from the
committed files, the numbers that the span writes, in the order it writes them. A span may be a few words
inside a sentence or a table cell, or a whole table (tag lines around it): in a table's lines the header row,
the separator row and the first cell of every row are labels and are not read. Every other number in the span
is read: digits with optional sign, thousands commas and decimals ("-3.1", "4,997,120", "5.0M" reads 5.0,
"29.8x" reads 29.8); a hyphen after a digit is a range ("0.68-0.72" reads 0.68 and 0.72); "95 %" (the interval
level), recipe names such as 0+0+0 and digits inside identifiers (seed_0) are not numbers. A function returns
one value per number read; ``None`` marks a label that the span must contain but that is not compared.

A number matches at the precision it is written: written with d decimals, it must lie within half a unit of
its last digit of the recomputed value (so 9.648 may be written 9.6 or 9.65 but not 9.7; a tie such as 9.5
may be written 9 or 10). Durations written "X h Y min" are compared as hours and whole minutes of the rounded
total. The script prints one line per number (``--quiet``: only the mismatches) and exits 1 on any mismatch,
on a span whose count of numbers differs from its function's, on a tag without a function and on a function
without a tag (so a check cannot silently drop out of the page). tests/test_results_doc.py runs it.

What it reads: the two studies' summary.json, the cross-play matrices (xp_*.csv), the GCS runs' metrics.csv and
per-episode cross-play returns, the interim cross-plays (xp12_update61/, xp_sp_sa_update152/ and 244/), the
tables of ring_direction.md and button_use.md (written by the scripts beside them from the lost run
directories), the Coordination Ring layout in ocv2/layouts.py (parsed as text), and the 10-seed SP and SA studies'
folders (summary.json, xp_*.csv, roles.md, the policies' SHA256SUMS.json), and the GPU study's folders
(gpu_coord_ring_sp/ and its update-410 cross-play, gpu_coord_ring_sp_update410/). JAX is imported for the checks
that take an interval the way the reports do: study_delta and gpu410_vs_3m (population.xp.bootstrap_difference)
and the gpu410 checks (population.xp.block_summary).

What it cannot check, and why (the page says so where they stand): the Coordination Ring training-return
tables and every Coordination Ring speed (no metrics.csv of those runs was committed; their run directories
were lost with the machine), the 1.5M pilot of the Coordination Ring SP run, the first GCS start's speed, the
per-snapshot cross-play durations, the 8 more seeds' loss at update 70, and the session times of day; no file
under docs/results/ records them.
"""

from __future__ import annotations

import argparse
import ast
import csv
import functools
import itertools
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # the repository, for population.xp (study_delta) outside an install
DOC = HERE.parent / "RESULTS.md"
LAYOUTS = HERE.parents[1] / "ocv2" / "layouts.py"
CR = HERE / "table1_coord_ring"
GCS = HERE / "reduced_gcs"
SP10 = HERE / "table1_coord_ring_sp10"
SA10 = HERE / "table1_coord_ring_sa10"
FC10 = HERE / "table1_forced_coord_sp10"
FC_SA10 = HERE / "table1_forced_coord_sa10"  # its SA half at the same budget
GPU_CR = HERE / "gpu_coord_ring_sp"  # Table 1 Coordination Ring SP on the paper's 10M schedule, trained on a GPU
GPU410 = HERE / "gpu_coord_ring_sp_update410"  # that study at update 410 (6.7M), cross-played on the CPU
CC10 = HERE / "table1_counter_circuit_sp10"  # Table 1 Counter Circuit SP, 10 seeds, the 10M schedule truncated at 3M
CC_SA10 = HERE / "table1_counter_circuit_sa10"  # its SA half at the same budget

# ------------------------------------------------------------------------------------------ reading the page

SPAN = re.compile(r"<!--\s*check:([\w.-]+)\s*-->(.*?)<!--\s*/check\s*-->", re.S)
TAG = re.compile(r"<!--\s*/?check[^>]*-->")
NUMBER = re.compile(r"-?\d+(?:,\d{3})*(?:\.\d+)?")
NOT_NUMBERS = [
    re.compile(r"\d\+\d\+\d"),  # recipe names
    re.compile(r"95 %"),  # the interval level
    re.compile(r"\bseat \d\b"),  # seat 0, seat 1: labels
    re.compile(r"\[[^\]]*\]\([^)]*\)"),  # markdown links
]


def read_numbers(text: str) -> list[str]:
    """The numbers of one span as written (see the module docstring for what counts)."""
    lines, table_started = [], False
    for line in text.split("\n"):
        stripped = line.strip()
        if stripped.startswith("|"):
            if not table_started:  # header row
                table_started = True
                continue
            if re.fullmatch(r"[|\s:-]+", stripped):  # separator row
                continue
            line = stripped[1:].split("|", 1)[1] if stripped.count("|") > 1 else ""  # drop the label cell
        else:
            table_started = False
        lines.append(line)
    text = "\n".join(lines)
    for pattern in NOT_NUMBERS:
        text = pattern.sub(" ", text)
    found = []
    for match in NUMBER.finditer(text):
        start, token = match.start(), match.group()
        before = text[start - 1] if start > 0 else " "
        after = text[match.end()] if match.end() < len(text) else " "
        if token.startswith("-") and (before.isdigit() or before == "."):
            token = token[1:]  # a range "a-b", not a sign
        elif before.isalpha() or before in "_.":
            continue  # inside an identifier such as seed_0 or sp10
        if (after.isalpha() and after not in "Mx") or after == "_":
            continue
        found.append(token)
    return found


def decimals(token: str) -> int:
    return len(token.split(".")[1]) if "." in token else 0


def matches(token: str, value: float) -> bool:
    written = float(token.replace(",", ""))
    return abs(written - value) <= 0.5 * 10 ** -decimals(token) + 1e-6


# ------------------------------------------------------------------------------------------ the data


def _float(x):
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
    return [_float(r[column]) for r in rows]


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
    tables, current = [], None
    for line in path.read_text().split("\n"):
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if current is None:
                current = []
                tables.append(current)
                continue  # header
            if all(re.fullmatch(r":?-+:?", c) for c in cells):
                continue
            current.append(cells)
        else:
            current = None
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


# ------------------------------------------------------------------------------------------ 4-seed bootstrap


def resamples(m: np.ndarray) -> np.ndarray:
    """Every ordered resample of the K seeds with replacement that has a cross-play cell (K^K - K of them),
    as rows (sp, xp, gap): the distribution that population.xp.bootstrap_block samples 2,000 times."""
    k = len(m)
    out = []
    for draw in itertools.product(range(k), repeat=k):
        draw = np.array(draw)
        same = draw[:, None] == draw[None, :]
        if same.all():
            continue
        cells = m[draw[:, None], draw[None, :]]
        sp, xp = cells[same].mean(), cells[~same].mean()
        out.append((sp, xp, sp - xp))
    return np.array(out)


def gap_at_most_zero(m: np.ndarray) -> list[int]:
    r = resamples(np.asarray(m, float))
    return [int((r[:, 2] <= 1e-12).sum()), len(r)]


# ------------------------------------------------------------------------------------------ the layout


@functools.cache
def coord_ring_moves() -> dict:
    """Moves along Coordination Ring's one-cell-wide ring between the cells where an agent works each
    station, clockwise and counter-clockwise as the layout is drawn (y down; clockwise = rising
    atan2(y - cy, x - cx) about the centre counter, as ring_direction.py counts it)."""
    tree = ast.parse(LAYOUTS.read_text())
    text = None
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == "coord_ring":
                    text = ast.literal_eval(value)[0]
    grid = text.split("\n")
    floor = [(x, y) for y, row in enumerate(grid) for x, c in enumerate(row) if c in " A"]
    cx = np.mean([x for x, _ in floor])
    cy = np.mean([y for _, y in floor])
    ring_cells = sorted(floor, key=lambda p: math.atan2(p[1] - cy, p[0] - cx))
    index = {cell: i for i, cell in enumerate(ring_cells)}

    def work_cell(chars):
        cells = {
            (x + dx, y + dy)
            for y, row in enumerate(grid)
            for x, c in enumerate(row)
            if c in chars
            for dx, dy in ((0, 1), (1, 0), (0, -1), (-1, 0))
            if (x + dx, y + dy) in index
        }
        (cell,) = cells  # every station of this layout is worked from one ring cell
        return index[cell]

    n = len(ring_cells)
    station = {"plate": work_cell("B"), "pot": work_cell("P"), "serve": work_cell("X"), "onion": work_cell("O0")}

    def moves(a, b):
        clockwise = (station[b] - station[a]) % n
        return clockwise, n - clockwise

    legs = [("plate", "pot"), ("pot", "serve"), ("serve", "plate")]
    cycle_cw = sum(moves(a, b)[0] for a, b in legs)
    cycle_ccw = sum(moves(a, b)[1] for a, b in legs)
    return {
        "legs": [moves(a, b) for a, b in legs],
        "onion_pot": moves("onion", "pot"),
        "cycle": (cycle_cw, cycle_ccw),
        "ring": n,
    }


# ------------------------------------------------------------------------------------------ the checks

CHECKS: dict = {}


def check(name: str):
    def register(function):
        CHECKS[name] = function
        return function

    return register


L = None  # a label: present in the span, not compared


# --- top of the page


def paper_numbers(paper: dict) -> list:
    """A run's paper column as the tables write it: SP, XP and gap, each mean then std."""
    return [paper[k][v] for k in ("sp", "xp", "gap") for v in ("mean", "std")]


@check("gpu_cr_sp_progress")
def _():
    with (GPU_CR / "sp_metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    last = max(int(r["update"]) for r in rows)
    at_last = sorted((r for r in rows if int(r["update"]) == last), key=lambda r: int(r["seed"]))
    returns = [_float(r["sparse_return"]) for r in at_last]
    steps = _float(at_last[0]["env_steps"])
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


def paired_gap_difference(base: np.ndarray, other: np.ndarray, resamples: int = 20_000, seed: int = 0) -> list[float]:
    """95 % interval of ``other``'s gap minus ``base``'s when the two populations' seeds correspond (the same seed
    numbers and config): each resample draws one set of seed indices and uses it in both matrices, where
    population.xp.bootstrap_difference resamples each population on its own."""
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(base), size=(resamples, len(base)))
    gaps = []
    for draw in draws:
        same = draw[:, None] == draw[None, :]
        if same.all():
            continue
        gap = [m[draw[:, None], draw[None, :]] for m in (base, other)]
        gaps.append((gap[1][same].mean() - gap[1][~same].mean()) - (gap[0][same].mean() - gap[0][~same].mean()))
    return list(np.percentile(gaps, [2.5, 97.5]))


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


def _steps(name, update):
    return point(name, update)["env_steps_per_seed"] / 1e6


@check("top_cr_sp_growth")
def _():
    gap = {p["update"]: p["gap"] for p in over_training("sp")}
    late = [g for u, g in gap.items() if u >= 183]
    return [
        gap[30],
        _steps("sp", 30),
        gap[122],
        _steps("sp", 122),
        gap[183],
        _steps("sp", 183),
        *span(late),
        _steps("sp", 183),
        _steps("sp", 305),
    ]


def _shares(table, update):
    """Clockwise share of seat 0 per seed at ``update`` of a ring_direction.md snapshot table."""
    return [cell[0] for cell in ring()[table][update]]


CLOCKWISE, EVEN = 0.58, 0.45  # a share above 0.58: clockwise; 0.45-0.58: about even; below 0.45: counter-clockwise


@check("top_probe")
def _():
    early = [s for s in _shares("probe", 30) if s < 0.5]
    at61 = _shares("probe", 61)
    ccw = min(range(8), key=lambda i: at61[i])
    even = sorted(s for s in at61 if EVEN <= s < CLOCKWISE)
    firm = [s for s in at61 if s >= 0.68]
    (weak,) = [i for i, s in enumerate(at61) if CLOCKWISE <= s < 0.68]
    ccw_count = sum(s < EVEN for s in at61)
    return [
        _steps("sp", 30),
        len(early),
        *span(early),
        _steps("sp", 61),
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


def _sa_ccw():
    """SA seed 1 (the counter-clockwise seed): [self-play, sorted pairs with the other SA seeds], [pairs
    with the 4 SP seeds] (means of both seat orders)."""
    sa = both_seats(cr_sa())
    big = both_seats(matrix(SP_SP_SA_BC))
    return [sa[1, 1], *sorted(sa[1, j] for j in (0, 2, 3))], [big[5, j] for j in range(4)]


@check("top_cr_sa_seed1")
def _():
    own, with_sp = _sa_ccw()
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


def _seed2_wrong():
    """Return per 1+1+1 episode of SP seed 2 cooking for SP seeds 0 and 1 in seat 0 (button_use.md)."""
    return [button_rows(s, "sp/2", "1+1+1")[0]["return"] for s in ("sp/0", "sp/1")]


def _without_seed2():
    return list(sp_xp(gcs_sp(), [0, 1, 3]))


@check("top_gcs_sp_story")
def _():
    return [2, 0, 1, *_seed2_wrong(), 2, *_without_seed2(), 1, 3, both_seats(gcs_sp())[1, 3]]


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


def _gap_zero_pattern(m):
    """(seed drawn three times, seed drawn once) of the resamples with a gap at or below 0, when they are one
    such pattern (else NaN, NaN)."""
    m = np.asarray(m, float)
    found = set()
    for draw in itertools.product(range(len(m)), repeat=len(m)):
        draw = np.array(draw)
        same = draw[:, None] == draw[None, :]
        if same.all():
            continue
        cells = m[draw[:, None], draw[None, :]]
        if cells[same].mean() - cells[~same].mean() <= 1e-12:
            counts = np.bincount(draw, minlength=len(m))
            found.add(
                (int(counts.argmax()), int(np.flatnonzero((counts > 0) & (counts < counts.max()))[0]))
                if counts.max() == 3
                else None
            )
    return found.pop() if len(found) == 1 and None not in found else (math.nan, math.nan)


# --- what is being run


def run_size(study: Path, name: str) -> list:
    """A run's env steps per seed and its number of updates."""
    r = run(study, name)
    return [r["env_steps_per_seed"], r["update"]]


@check("run_cr_size")
def _():
    return run_size(CR, "sp")


@check("run_cr_wall")
def _():
    return study_wall(CR)


@check("run_gcs_size")
def _():
    return run_size(GCS, SP)


def _training_s(name):
    return sum(w for w, _, _ in chunks(name))


RESUMED_AT = 10  # FCP's resume point (the run's manifest: resumed_from 10)


@check("run_gcs_sp_time")
def _():
    return [*hm(run(GCS, SP)["wall_s"]), *hm(_training_s(SP)), *span(s for _, s, _ in chunks(SP))]


@check("run_gcs_fcp_time")
def _():
    return [*hm(run(GCS, FCP)["wall_s"]), *hm(_training_s(FCP)), *span(s for _, s, _ in chunks(FCP, after=RESUMED_AT))]


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


@check("claim_cr_sp")
def _():
    return [*claim_row(CR, "sp"), min(pairs(cr_sp()))]


@check("claim_cr_sa")
def _():
    xp = run(CR, "sa")["xp"]
    return [xp["num_policies"], millions(CR, "sa"), xp["num_policies"], *block(xp), run(CR, "sp")["xp"]["gap"]]


@check("claim_cr_sa_verdict")
def _():
    own, with_sp = _sa_ccw()
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
    return [2, 0, 1, p[0, 2], p[1, 2], *_seed2_wrong(), 2, *_without_seed2(), 1, 3, p[1, 3], p[1, 1], p[3, 3]]


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
    return [count, total, *_gap_zero_pattern(cr_sp()), L]


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
        _steps("sp", 183),
        sp[30],
        sp[183],
        *span(late),
        _steps("sp", 305),
        sp[305],
        _steps("sp", 305),
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
    return _shares("sp", 305) + _shares("sa", 305) + _shares("probe", 61)


@check("cr_direction_count")
def _():
    shares = _last_looks()
    clockwise = [s for s in shares if s >= CLOCKWISE]
    even = sorted(s for s in shares if EVEN <= s < CLOCKWISE)
    sa_ccw = [(i, s) for i, s in enumerate(_shares("sa", 305)) if s < EVEN]
    probe_ccw = [(i, s) for i, s in enumerate(_shares("probe", 61)) if s < EVEN]
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
        _steps("sa", 305),
        probe_share,
        probe_seed,
        len(_shares("probe", 61)),
        _steps("sp", 61),
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
    cross = float(np.mean(_sa_ccw()[1]))
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
    return [s for update in (0, 30, 61, 122, 305) for s in _shares("sp", update)]


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
    at30, at61 = _shares("probe", 30), _shares("probe", 61)
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
        len(_shares("sp", 61)),
        *span(_shares("sp", 61)),
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
    i = 4 + int(np.argmin(_shares("probe", 61)))  # the counter-clockwise seed of the 8 (after the study's 4)
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
        _steps("sp", 61),
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
    return [L, count, total, *_gap_zero_pattern(cr_sa()), L]


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
        max(_shares("sa", 305)),
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
        _steps("sa", 61),
        point("sp", 61)["gap"],
        *span(late),
        _steps("sa", 92),
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
    shares = _shares("sa", 244)
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
        *span(_sa_ccw()[1]),
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
    own, with_sp = _sa_ccw()
    ccw = [s for s in _shares("sa", 305) if s < EVEN]
    return [len(cr_sp()), len(ccw), len(cr_sa()), *span(own[1:]), *span(with_sp)]


@check("cr_sa_verdict_one")
def _():
    own, with_sp = _sa_ccw()
    working_sa = [s for s in own[1:] if s > 100]
    working_sp = [s for s in with_sp if s > 100]
    return [len(working_sa), 3, 0, both_seats(cr_sa())[0, 1], len(working_sp), len(with_sp), *span(with_sp)]


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
    return [*low, *high, L, count, total, *_gap_zero_pattern(gcs_sp()), L]


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
        *hm(_training_s(FCP)),
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
    return [*_seed2_wrong(), counts.pop() if len(counts) == 1 else math.nan]


@check("signal_verdict_sign")
def _():
    sp = run(GCS, SP)["xp"]
    return [sp["xp_mean"], sp["sp_mean"], sp["gap"], sp["num_policies"], *interval(sp, "gap"), *paper(GCS, SP)]


@check("signal_verdict_seed2")
def _():
    p = both_seats(gcs_sp())
    own = button_rows("sp/2", "sp/2", "1+1+1")[0]["return"]
    return [2, 2, 0, 1, *_seed2_wrong(), 2, *_without_seed2(), 1, 3, p[1, 3], p[1, 1], p[3, 3], 2, own]


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


# ------------------------------------------------------------------------------------------ running


def compare(doc: str) -> tuple[list[tuple], list[str]]:
    """[(name, index, written, recomputed, ok)], [errors]"""
    rows, errors, seen = [], [], set()
    for match in SPAN.finditer(doc):
        name, text = match.group(1), match.group(2)
        if "<!--" in TAG.sub("", text) and "check:" in text:
            errors.append(f"{name}: a check span inside another")
        line = doc.count("\n", 0, match.start()) + 1
        if name in seen:
            errors.append(f"{name} (line {line}): tagged twice")
        seen.add(name)
        if name not in CHECKS:
            errors.append(f"{name} (line {line}): no check of that name in {Path(__file__).name}")
            continue
        written = read_numbers(TAG.sub("", text))
        expected = [None if v is None else float(v) for v in CHECKS[name]()]
        if len(written) != len(expected):
            errors.append(
                f"{name} (line {line}): the span writes {len(written)} numbers {written}, the check recomputes {len(expected)}"
            )
            continue
        for k, (token, value) in enumerate(zip(written, expected)):
            ok = value is None or matches(token, value)
            rows.append((name, k, token, value, ok))
    for name in CHECKS:
        if name not in seen:
            errors.append(f"{name}: no <!-- check:{name} --> span on the page")
    return rows, errors


# --- the 10-seed Coordination Ring SP population (table1_coord_ring_sp10/: interim snapshots)


def snapshot_env_steps(update: int, study: Path = SP10) -> float:
    """Env steps per seed of snapshot ``update``, in millions, from the published policies' SHA256SUMS.json."""
    sums = json.loads((study / "policies" / "SHA256SUMS.json").read_text())
    return next(entry["env_steps"] for entry in sums if entry["update"] == update) / 1e6


@functools.cache
def roles_tables(study: Path = SP10) -> dict:
    """roles.md: {update: [(cw seat 0, cw seat 1, [seat-0 share, count] per job, first-pot share per seat, return)
    per seed]}."""
    tables = md_tables(study / "roles.md")
    updates = [int(m) for m in re.findall(r"^## update (\d+)$", (study / "roles.md").read_text(), re.M)]
    parsed = {}
    for update, table in zip(updates, tables, strict=True):
        rows = []
        for row in table:
            cw = tuple(float(x) for x in row[1].split(","))
            jobs = [tuple(float(x) for x in cell.split(" of ")) for cell in row[2:6]]
            pot = tuple(float(x) for x in row[6].split(","))
            rows.append((*cw, jobs, pot, float(row[-1])))
        parsed[update] = rows
    return parsed


def sp10_xp(update: int) -> list:
    """Snapshot ``update``: its env steps, SP, XP, gap (both seat orders), the lowest pair and its score."""
    m = matrix(SP10 / f"xp_update{update}.csv")
    sp, xp, gap = sp_xp(m)
    p = both_seats(m)
    i, j = min(itertools.combinations(range(len(m)), 2), key=lambda ij: p[ij])
    return [update, snapshot_env_steps(update), sp, xp, gap, i, j, p[i, j]]


def sp10_direction_and_xp(update: int) -> list:
    """Clockwise shares (seat 0) from least to most clockwise seed, and Pearson's r over the 45 pairs between
    a pair's score (both seat orders) and the difference of its seeds' clockwise shares."""
    cw = [row[0] for row in roles_tables()[update]]
    p = both_seats(matrix(SP10 / f"xp_update{update}.csv"))
    ij = list(itertools.combinations(range(len(cw)), 2))
    r = np.corrcoef([abs(cw[i] - cw[j]) for i, j in ij], [p[i, j] for i, j in ij])[0, 1]
    low, high = int(np.argmin(cw)), int(np.argmax(cw))
    return [low, cw[low], high, cw[high], len(ij), r]


def sp10_delivery_shares(update: int) -> list:
    """Seat 0's share of the deliveries per seed: the range over the seeds, then the seed furthest from 0.5."""
    shares = [row[2][3][0] for row in roles_tables()[update]]
    far = max(range(len(shares)), key=lambda k: abs(shares[k] - 0.5))
    rest = [x for k, x in enumerate(shares) if k != far]
    return [min(rest), max(rest), far, shares[far]]


@check("sp10_xp92")
def _():
    return sp10_xp(92)


@check("sp10_xp122")
def _():
    return sp10_xp(122)


@check("sp10_direction")
def _():
    return [*sp10_direction_and_xp(122), sp10_direction_and_xp(92)[-1], 92]


@check("sp10_clockwise_pair")
def _():
    cw = [row[0] for row in roles_tables()[122]]
    p = both_seats(matrix(SP10 / "xp_update122.csv"))
    return [0, 3, cw[0], cw[3], p[0, 3], 122]


@check("sp10_roles")
def _():
    return sp10_delivery_shares(122)


# --- the 10-seed population finished: 3.0M env steps per seed, the study's 10 x 10 cross-play (500 episodes per pair)


def final_matrix(study: Path = SP10, method: str = "sp") -> np.ndarray:
    return matrix(study / f"xp_{method}.csv")


def low_pairs(study: Path = SP10, method: str = "sp") -> list[tuple[int, int, float]]:
    """A study's final matrix's failing pairs (``failing_pairs``)."""
    return failing_pairs(final_matrix(study, method))


def failing_pairs(m: np.ndarray) -> list[tuple[int, int, float]]:
    """Pairs (both seat orders) of a K x K matrix scoring below half the mean of their two seeds' self-play, lowest
    first."""
    p = both_seats(m)
    low = [
        (i, j, p[i, j]) for i, j in itertools.combinations(range(len(m)), 2) if below_half(p[i, j], m[i, i], m[j, j])
    ]
    return sorted(low, key=lambda pair: pair[2])


def pair_r(measure, study: Path = SP10, method: str = "sp") -> float:
    """Pearson's r over the 45 pairs between a pair's final score and |difference| of ``measure`` (per seed)."""
    p = both_seats(final_matrix(study, method))
    ij = list(itertools.combinations(range(len(p)), 2))
    return np.corrcoef([abs(measure[i] - measure[j]) for i, j in ij], [p[i, j] for i, j in ij])[0, 1]


def seed_measures(update: int = 183, study: Path = SP10) -> dict:
    """Per seed at ``update`` (seat 0): clockwise share, delivery share, share of onions into the first pot."""
    rows = roles_tables(study)[update]
    return {"cw": [r[0] for r in rows], "deliveries": [r[2][3][0] for r in rows], "pot": [r[3][0] for r in rows]}


def low_pair_numbers(study: Path, method: str = "sp") -> list:
    """A 10-seed study's failing pairs: how many of the 45, then the three lowest as (seed, seed, score)."""
    low = low_pairs(study, method)
    return [len(low), 45, *[x for pair in low[:3] for x in pair]]


def final_numbers(study: Path, method: str) -> list:
    """A 10-seed study's headline: seeds x env steps, episodes per pair, SP, XP, gap with its interval over the
    seeds, and the paper's SP / XP / gap."""
    xp = run(study, method)["xp"]
    return [
        xp["num_policies"],
        millions(study, method),
        xp["episodes_per_pair"],
        xp["sp_mean"],
        xp["xp_mean"],
        xp["gap"],
        xp["num_policies"],
        *interval(xp, "gap"),
        *paper(study, method),
    ]


def below_half(score, self_play_a, self_play_b):
    """A pair "fails": it scores under half the mean of its two seeds' self-play (numbers, or arrays that
    broadcast: a whole matrix of pairs at once)."""
    return score < (self_play_a + self_play_b) / 4


def partner_means(p: np.ndarray) -> list[float]:
    """Per seed, its mean over every other seed of a both-seat-orders matrix ``p``."""
    return [np.mean([p[k, j] for j in range(len(p)) if j != k]) for k in range(len(p))]


@check("gpu_cr_sp_final")
def _():
    return final_numbers(GPU_CR, "sp")


@check("sp10_final")
def _():
    return final_numbers(SP10, "sp")


@check("sp10_growth")
def _():
    return [sp10_xp(92)[4], 92, sp10_xp(122)[4], 122, run(SP10, "sp")["xp"]["gap"], 183]


@check("sp10_claim")
def _():
    return [*claim_row(SP10, "sp"), len(low_pairs()), 45]


@check("sp10_cw183")
def _():
    cw = seed_measures()["cw"]
    rest = [x for k, x in enumerate(cw) if k not in (1, 6)]
    return [1, 6, cw[1], cw[6], min(rest), max(rest)]


@check("sp10_interval_vs_pairs")
def _():
    xp = run(SP10, "sp")["xp"]
    every = pairs(final_matrix())
    return [10, *interval(xp, "xp"), min(every), max(every)]


@check("sp10_low_pairs")
def _():
    low = low_pairs()
    return [len(low), 45, *[x for pair in low for x in pair]]


@check("sp10_pots")
def _():
    pot = seed_measures()["pot"]
    first = [k for k, x in enumerate(pot) if x >= 0.95]
    second = [k for k, x in enumerate(pot) if x <= 0.05]
    p = both_seats(final_matrix())
    mixed = [x for x in pot if 0.05 < x < 0.95]
    return [*first, *second, min(mixed), max(mixed), 1, 6, p[1, 6], 0, 3, p[0, 3], 0, 6, p[0, 6]]


@check("sp10_pots_early")
def _():
    pot = seed_measures(92)["pot"]
    single = [k for k, x in enumerate(pot) if x >= 0.95 or x <= 0.05]
    return [*single, snapshot_env_steps(92), 0, pot[0], 92]


@check("sp10_pair_r")
def _():
    m = seed_measures()
    return [pair_r(m["pot"]), pair_r(m["cw"]), pair_r(m["deliveries"])]


@check("sp10_seed3")
def _():
    p = both_seats(final_matrix())
    others = [j for j in range(10) if j != 3]
    means = partner_means(p)
    nxt = sorted(range(10), key=lambda k: means[k])[1]
    return [
        3,
        means[3],
        final_matrix()[3, 3],
        min(p[3, j] for j in others),
        max(p[3, j] for j in others),
        nxt,
        means[nxt],
    ]


# --- the 10-seed SA population (table1_coord_ring_sa10/), beside the 10 SP seeds at the same budget


def sa10_final() -> np.ndarray:
    return final_matrix(SA10, "sa")


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


@check("sa10_pairs")
def _():
    p = both_seats(sa10_final())
    i, j = min(itertools.combinations(range(10), 2), key=lambda ij: p[ij])
    return [
        len(sa10_low_pairs()),
        45,
        min(pairs(sa10_final())),
        max(pairs(sa10_final())),
        i,
        j,
        min(pairs(final_matrix())),
    ]


def sa10_low_pairs() -> list[tuple[int, int, float]]:
    return low_pairs(SA10, "sa")


@check("sa10_table")
def _():
    sp, sa = run(SP10, "sp")["xp"], run(SA10, "sa")["xp"]
    cw = [seed_measures(183, study)["cw"] for study in (SP10, SA10)]
    return [
        sp["sp_mean"],
        *interval(sp, "sp"),
        sa["sp_mean"],
        *interval(sa, "sp"),
        sp["xp_mean"],
        *interval(sp, "xp"),
        sa["xp_mean"],
        *interval(sa, "xp"),
        sp["gap"],
        *interval(sp, "gap"),
        sa["gap"],
        *interval(sa, "gap"),
        min(pairs(final_matrix())),
        min(pairs(sa10_final())),
        len(low_pairs()),
        45,
        len(sa10_low_pairs()),
        45,
        min(cw[0]),
        max(cw[0]),
        min(cw[1]),
        max(cw[1]),
    ]


def _sa10_pot_groups() -> tuple[list[int], list[int]]:
    """SA seeds (seat 0, update 183) with at most 0.1 of their onions into the first pot, and the rest."""
    pot = seed_measures(183, SA10)["pot"]
    return [k for k, x in enumerate(pot) if x <= 0.1], [k for k, x in enumerate(pot) if x > 0.1]


@check("sa10_pots")
def _():
    pot = seed_measures(183, SA10)["pot"]
    second, mixed = _sa10_pot_groups()
    one_pot_sp = [k for k, x in enumerate(seed_measures()["pot"]) if x >= 0.95]
    return [
        *second,
        min(pot[k] for k in second),
        max(pot[k] for k in second),
        min(pot[k] for k in mixed),
        max(pot[k] for k in mixed),
        len(one_pot_sp),
    ]


@check("sa10_pot_pairs")
def _():
    m = seed_measures(183, SA10)
    p = both_seats(sa10_final())
    second, mixed = _sa10_pot_groups()
    same = np.mean([p[i, j] for i, j in itertools.combinations(second, 2)])
    across = np.mean([p[i, j] for i in second for j in mixed])
    return [pair_r(m["pot"], SA10, "sa"), pair_r(m["cw"], SA10, "sa"), same, across]


def sp_sa_mean(sa: Path = SA10) -> np.ndarray:
    """SP x SA (``sa``'s xp_sp_sa/matrix_mean.csv): row = SP seed, column = SA seed, mean of both seat orders."""
    return matrix(sa / "xp_sp_sa" / "matrix_mean.csv")


def sp_sa_low(sp: Path = SP10, sa: Path = SA10) -> np.ndarray:
    """The SP x SA pairs (``sp_sa_mean``'s cells) below half of what their two seeds score with themselves."""
    sp_self, sa_self = np.diag(final_matrix(sp)), np.diag(final_matrix(sa, "sa"))
    return below_half(sp_sa_mean(sa), sp_self[:, None], sa_self[None, :])


@check("sa10_sp_sa")
def _():
    m = sp_sa_mean()
    with_sa = m.mean(axis=1)
    with_sp = partner_means(both_seats(final_matrix()))
    odd = [1, 3, 6]
    rest = [k for k in range(10) if k not in odd]
    low = sp_sa_low()
    return [
        m.size,
        m.mean(),
        len(rest),
        min(with_sa[k] for k in rest),
        max(with_sa[k] for k in rest),
        min(with_sp[k] for k in rest),
        max(with_sp[k] for k in rest),
        *odd,
        *[with_sa[k] for k in odd],
        *[with_sp[k] for k in odd],
        int(low.sum()),
        m.size,
        int(low[1].sum()),
        1,
        int(low[6].sum()),
        6,
        m.min(),
    ]


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


@check("fc10_final")
def _():
    return final_numbers(FC10, "sp")


@check("fc10_low_pairs")
def _():
    return low_pair_numbers(FC10)


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


def gap_growth(*studies: tuple[Path, str, Path]) -> list:
    """For each (study, method, folder of its snapshot cross-play): the gap at updates 92, 122 and 152 (32 episodes
    per pair, ``<folder>/xp_snapshots/<method>_update<u>.csv``) with their env steps, then the final gap and
    env steps in millions."""
    out = []
    for study, method, folder in studies:
        for update in (92, 122, 152):
            snapshot = matrix(folder / "xp_snapshots" / f"{method}_update{update}.csv")
            out += [sp_xp(snapshot)[2], snapshot_env_steps(update, study)]
        out += [run(study, method)["xp"]["gap"], millions(study, method)]
    return out


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


@check("fc10_claim")
def _():
    return [*claim_row(FC10, "sp"), len(low_pairs(FC10)), 45]


# --- Coordination Ring SP on the paper's whole 10M schedule (gpu_coord_ring_sp, update 610)


def gpu_cr_matrix() -> np.ndarray:
    return final_matrix(GPU_CR, "sp")


def group_of(groups: dict, seed: int) -> str:
    """The name of the group of ``pot_groups`` that holds ``seed``."""
    return next(name for name, seeds in groups.items() if seed in seeds)


def pair_rows(table: list[list[str]]) -> dict:
    """A roles table of ordered cross-play pairs as {(seat-0 seed, seat-1 seed): the row's cells}."""
    return {tuple(int(k) for k in row[0].split(" × ")): row for row in table}


def roles_pairs(study: Path) -> dict:
    """roles_pairs.md's one table of ordered cross-play pairs (``pair_rows``)."""
    (table,) = md_tables(study / "roles_pairs.md")
    return pair_rows(table)


def cell_count(cell: str) -> float:
    """The count of a roles table's "<share> of <count>" cell."""
    return float(cell.split(" of ")[1])


def paper_beside_intervals(study: Path, name: str) -> list[float]:
    """The paper's SP, XP and gap, each followed by our 95 % interval over the seeds."""
    xp = run(study, name)["xp"]
    sp, cross, gap = paper(study, name)
    return [sp, *interval(xp, "sp"), cross, *interval(xp, "xp"), gap, *interval(xp, "gap")]


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
    gpu = [_float(r["steps_per_s"]) for r in rows if int(r["update"]) <= 410]
    cpu = [_float(r["steps_per_s"]) for r in rows if int(r["update"]) > 410]
    return [1, 410, np.median(gpu), 411, 610, np.median(cpu), *study_wall(GPU_CR)]


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
    of its cross-play pairs."""
    seeds, pairs = md_tables(study / "roles.md")
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


def cc_pairs_by_convention(study: Path = CC10, method: str = "sp") -> dict:
    """Every pair's score (both seat orders) and whether it fails, by what its two seeds share: "both", "pot",
    "direction" or "neither"."""
    conv = cc_conventions(study)
    p = both_seats(final_matrix(study, method))
    low = {(i, j) for i, j, _ in low_pairs(study, method)}
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
        sp, xp, gap = sp_xp(matrix(CC10 / "xp_snapshots" / f"sp_update{update}.csv"))
        out += [gap, snapshot_env_steps(update, CC10), sp, xp]
    final = run(CC10, "sp")["xp"]
    out += [final["gap"], millions(CC10, "sp"), final["sp_mean"], final["xp_mean"]]
    later = matrix(CC10 / "xp_snapshots" / "sp_update244.csv")  # the 6M extension's first snapshot
    sp, xp, gap = sp_xp(later)
    return [*out, gap, snapshot_env_steps(244, CC10), sp, xp, len(failing_pairs(later)), 45]


@check("cc10_claim")
def _():
    return [*claim_row(CC10, "sp"), len(low_pairs(CC10)), 45]


@check("run_cc10_rate")
def _():
    with (CC10 / "sp_metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["seed"] == "0" and int(r["update"]) > 125]
    return [np.median([_float(r["steps_per_s"]) for r in rows]), 126, 183]


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


# --- what every 10-seed SA study beside its 10 SP seeds at the same budget reports


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
    (the Coordination Ring section, written first, states its failing pairs and no paired interval: sa10_pairs)."""
    studies = {
        "sa10": (SP10, SA10, ("final", "delta", "claim")),
        "fc_sa10": (FC10, FC_SA10, tuple(SA_BESIDE_SP)),
        "cc_sa10": (CC10, CC_SA10, tuple(SA_BESIDE_SP)),
    }
    for name, (sp, sa, kinds) in studies.items():
        for kind in kinds:
            check(f"{name}_{kind}")(functools.partial(SA_BESIDE_SP[kind], sp, sa))


register_sa_beside_sp()


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
    }
    for name, (study, method) in studies.items():
        check(f"run_{name}")(functools.partial(run_size, study, method))
        check(f"run_{name}_wall")(functools.partial(study_wall, study))


register_run_rows()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--doc", type=Path, default=DOC, help="the page to check (default docs/RESULTS.md)")
    parser.add_argument("--quiet", action="store_true", help="print only mismatches and errors")
    args = parser.parse_args(argv)
    rows, errors = compare(args.doc.read_text())
    print("| check | # | written | recomputed | |\n|---|---:|---:|---:|---|")
    for name, k, token, value, ok in rows:
        if ok and args.quiet:
            continue
        shown = "label" if value is None else f"{value:.4f}".rstrip("0").rstrip(".")
        print(f"| {name} | {k} | {token} | {shown} | {'ok' if ok else 'MISMATCH'} |")
    bad = [r for r in rows if not r[4]]
    for error in errors:
        print(f"ERROR {error}")
    checked = sum(1 for r in rows if r[3] is not None)
    print(
        f"{checked} numbers in {len({r[0] for r in rows})} spans compared with the files under docs/results/: "
        f"{len(bad)} mismatches, {len(errors)} errors"
    )
    return 1 if bad or errors else 0


if __name__ == "__main__":
    sys.exit(main())
