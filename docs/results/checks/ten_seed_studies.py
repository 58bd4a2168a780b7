"""What several sections of the page read the same way from the 10-seed studies: a snapshot's env steps, the
roles tables, the final matrix and its failing pairs, the headline row, SP x SA, the gap's growth over the
snapshots, the gap difference with the seeds paired, and the cells of the roles tables."""

from __future__ import annotations

import csv
import functools
import itertools
import json
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .data import both_seats, interval, matrix, md_tables, millions, paper, run, sp_xp, summary
from .folders import REPOSITORY, SA10, SP10


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


def final_matrix(study: Path = SP10, method: str = "sp") -> np.ndarray:
    return matrix(study / f"xp_{method}.csv")


#: Where a study's final cross-play, played again from its published files alone, is kept.
REPLAY = "replay_from_policies"
#: What every 10-seed study's cross-play played: episodes per ordered pair and the episode key (``population.seed``).
STUDY_EPISODES, STUDY_KEY = 500, 0


class Replay(NamedTuple):
    cells: np.ndarray  # [rows, cols], row = seat 0
    rows: list[int]  # the seed of each row's file
    cols: list[int]  # the seed of each column's file
    update: int  # the snapshot every file played is
    files: tuple[str, ...]  # the files played (paths from the repository)
    minutes: int  # the replay's wall time (its summary.json's ``wall_s``)


@functools.cache
def replay(study: Path) -> Replay:
    """``study``/``REPLAY``/: an ``ocv2 xp --rows ... [--cols ...]`` of published files. Which seeds and update each
    file is comes from the listing beside it (``SHA256SUMS.json``), and the sha256 the replay recorded for each file
    must be the listing's, so the cells are those of the published bytes; the episodes and key must be the
    study's."""
    record = summary(study / REPLAY)
    if (record["episodes_per_pair"], record["seed"]) != (STUDY_EPISODES, STUDY_KEY):
        raise ValueError(
            f"{study.name}: the replay played {record['episodes_per_pair']} episodes with key "
            f"{record['seed']}, not the study's {STUDY_EPISODES} with key {STUDY_KEY}"
        )
    listed = {}
    for path, played in record["files"].items():
        file = REPOSITORY / path
        listing = json.loads((file.parent / "SHA256SUMS.json").read_text())
        entry = next((e for e in listing if e["file"] == file.name), None)
        if entry is None or entry["sha256"] != played["sha256"]:
            raise ValueError(f"{study.name}: the replay played {path} with bytes its folder's listing does not")
        listed[path] = entry
    (update,) = {entry["update"] for entry in listed.values()}
    return Replay(
        matrix(study / REPLAY / "matrix.csv"),
        [listed[path]["seed"] for path in record["rows"]],
        [listed[path]["seed"] for path in record["cols"]],
        update,
        tuple(listed),
        round(record["wall_s"] / 60),
    )


def replayed_cells(study: Path, method: str = "sp", verdict_csv: Path | None = None) -> list:
    """The study's final matrix (``verdict_csv``: the verdict's matrix file when it is not the folder's
    xp_<method>.csv) played again from the published files (``replay``), whole (``ocv2 xp --rows <the 10 files>
    --episodes 500 --seed 0``) or one seed's row (``--rows <its file> --cols <the 10 files> --seats 0``): how many of
    the cells played equal the study's own, of how many, and the largest difference (each cell a mean of 500 returns in
    steps of 20, so its two decimals are exact: 0.04 per delivery)."""
    again = replay(study)
    own = (matrix(verdict_csv) if verdict_csv is not None else final_matrix(study, method))[
        np.ix_(again.rows, again.cols)
    ]
    return [int((again.cells == own).sum()), own.size, float(np.abs(again.cells - own).max())]


def replay_minutes(study: Path) -> int:
    """The replay's wall time in minutes."""
    return replay(study).minutes


def replay_row(study: Path, method: str = "sp", verdict_csv: Path | None = None) -> list:
    """A row of the table of replays: the update played (checked: the verdict's, and files of its method), the rows
    played, the cells, how many equal the study's, the largest difference and the minutes."""
    again = replay(study)
    final = verdict_update(study, method, verdict_csv)
    if again.update != final:
        raise ValueError(f"{study.name}: the replay played update {again.update}, the verdict is at {final}")
    if not all(Path(path).name.startswith(f"{method}_seed") for path in again.files):
        raise ValueError(f"{study.name}: the replay played files of another method than {method}: {again.files}")
    equal, cells, largest = replayed_cells(study, method, verdict_csv)
    return [again.update, len(again.rows), cells, equal, largest, again.minutes]


def verdict_update(study: Path, method: str, verdict_csv: Path | None) -> int:
    """The update a verdict's matrix was played at: its labels' (``sp/seed_0@410``) when it is an ``ocv2 xp`` file,
    else the study's final update."""
    if verdict_csv is None:
        return run(study, method)["update"]
    with verdict_csv.open() as f:
        (update,) = {int(label.rsplit("@", 1)[1]) for label in next(csv.reader(f))[1:]}
    return update


def partner_means(p: np.ndarray) -> list[float]:
    """Per seed, its mean over every other seed of a both-seat-orders matrix ``p``."""
    return [np.mean([p[k, j] for j in range(len(p)) if j != k]) for k in range(len(p))]


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


def below_half(score, self_play_a, self_play_b):
    """A pair "fails": it scores under half the mean of its two seeds' self-play (numbers, or arrays that
    broadcast: a whole matrix of pairs at once)."""
    return score < (self_play_a + self_play_b) / 4


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


def sp_sa_mean(sa: Path = SA10) -> np.ndarray:
    """SP x SA (``sa``'s xp_sp_sa/matrix_mean.csv): row = SP seed, column = SA seed, mean of both seat orders."""
    return matrix(sa / "xp_sp_sa" / "matrix_mean.csv")


def sp_sa_low(sp: Path = SP10, sa: Path = SA10) -> np.ndarray:
    """The SP x SA pairs (``sp_sa_mean``'s cells) below half of what their two seeds score with themselves."""
    sp_self, sa_self = np.diag(final_matrix(sp)), np.diag(final_matrix(sa, "sa"))
    return below_half(sp_sa_mean(sa), sp_self[:, None], sa_self[None, :])


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


def paired_gap_difference(base: np.ndarray, other: np.ndarray) -> list[float]:
    """95 % interval of ``other``'s gap minus ``base``'s when the two populations' seeds correspond (the same seed
    numbers and config): ``population.xp.paired_difference``, one draw of seed indices used in both matrices,
    where ``population.xp.bootstrap_difference`` resamples each population on its own. 20,000 resamples, as the
    page's paired intervals have always had."""
    from population.xp import paired_difference

    return list(paired_difference(base, other, resamples=20_000)["gap"])


def pair_rows(table: list[list[str]]) -> dict:
    """A roles table of ordered cross-play pairs as {(seat-0 seed, seat-1 seed): the row's cells}."""
    return {tuple(int(k) for k in row[0].split(" × ")): row for row in table}


def seat_shares(cell: str) -> tuple[float, float]:
    """A roles table's "<seat 0>, <seat 1>" cell ("none": that seat did not do it, NaN)."""
    first, second = (math.nan if v.strip() == "none" else float(v) for v in cell.split(","))
    return first, second


def cell_share(cell: str) -> float:
    """The share of a roles table's "<share> of <count>" cell."""
    return float(cell.split(" of ")[0])


def cell_count(cell: str) -> float:
    """The count of a roles table's "<share> of <count>" cell."""
    return float(cell.split(" of ")[1])


def paper_beside_intervals(study: Path, name: str) -> list[float]:
    """The paper's SP, XP and gap, each followed by our 95 % interval over the seeds."""
    xp = run(study, name)["xp"]
    sp, cross, gap = paper(study, name)
    return [sp, *interval(xp, "sp"), cross, *interval(xp, "xp"), gap, *interval(xp, "gap")]


def training_curve(study: Path, updates: tuple[int, ...] = (122, 152, 183), method: str = "sp") -> list:
    """The training return (sparse, mean over the 10 seeds) at each of ``updates``, each followed by the update and
    its env steps in millions: ``<method>_metrics.csv`` of a 10-seed study."""
    with (study / f"{method}_metrics.csv").open() as f:
        rows = [r for r in csv.DictReader(f) if r["sparse_return"]]
    out = []
    for update in updates:
        returns = [float(r["sparse_return"]) for r in rows if int(r["update"]) == update]
        assert len(returns) == 10, (study, update, len(returns))
        out += [np.mean(returns), update, snapshot_env_steps(update, study)]
    return out
