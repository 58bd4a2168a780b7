"""``ocv2 report``: tabulate run directories after their runs (``ocv2 validate``, which checks configs
before, is ``cluster/cli/validate.py``).

    ocv2 report RUN_DIR [RUN_DIR ...] [--out DIR] [--baseline RUN_DIR ...]

``report`` reads run directories (``config.yaml``, ``xp/summary.json``, ``metrics.csv``, ``xp/matrix.csv``)
and writes, into ``--out`` (default ``reports/``):

* ``report.md`` / ``report.csv``: one row per run in the paper's Table 1 / Table 2 format -- layout,
  method, SP mean +- std, XP mean +- std, gap. Runs of the same game (the same ``env`` settings, defaults
  written out) and the same network (``model`` section up to its kernel choice, and ``ppo.activation``) are
  compared with that group's self-play run: delta SP, delta XP and delta gap (the last is the number in
  brackets in the paper's Table 1, "Gap (delta)"), the last with a 95 % interval by bootstrap over each
  population's seeds (``population.xp.bootstrap_difference``). A group with several self-play runs is
  refused unless ``--baseline`` names the one the others are compared with: which run the deltas are
  against must be a choice, not an accident of the argument order. When the runs have more than one
  network, the table says which each row's is (a Network column).
* ``curves_<layout>.png``: sparse return (mean +- std across seeds) against env steps, one line per run.
* ``heatmap_<run>.png``: the cross-play matrix of every evaluated run, redrawn from ``xp/matrix.csv``.

A run without ``xp/summary.json`` is listed with a note instead of numbers.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
from rich.console import Console
from rich.table import Table

from cluster.cli.args import resolved
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from cluster.runtime.rundir import RunDir, RunDirError, float_or_nan, read_matrix_csv, seed_curves
from ocv2 import boundedjson
from ocv2.atomic import atomic_write, staged_folder
from population.config import METHOD_TABLE, METHODS
from population.plots import PlotsUnavailable, across_seeds, pyplot, save_figure, skipped, xp_heatmap
from population.policy import comparable_key, network_settings
from population.xp import summary_difference

METHOD_NAMES = {method.name: method.long_name for method in METHOD_TABLE}
NO_XP_NOTE = "no cross-play yet: run ocv2 xp {run}"
CSV_FIELDS = (
    "layout",
    "method",
    "env",
    "run_dir",
    "status",
    "num_seeds",
    "updates_done",
    "num_updates",
    "env_steps_per_seed",
    "sp_mean",
    "sp_std",
    "xp_mean",
    "xp_std",
    "gap",
    "sp_ci95",
    "xp_ci95",
    "num_policies",
    "episodes_per_pair",
    "baseline_run",
    "delta_sp",
    "delta_xp",
    "delta_gap",
    "delta_gap_ci95_low",
    "delta_gap_ci95_high",
    "note",
)


# ---------------------------------------------------------------------------------------------------
# reading run directories
# ---------------------------------------------------------------------------------------------------


def load_run(path) -> dict:
    """Everything ``report`` needs from one run directory; ``CLIError`` if it is not one."""
    if not Path(path).exists():
        raise CLIError(f"{path}: no such run directory")
    try:
        run = RunDir.existing(path)
        config = run.load_config()
    except RunDirError as error:
        raise CLIError(str(error)) from None
    summary = None
    summary_path = run.path / "xp" / "summary.json"
    if summary_path.is_file():
        summary = _checked_summary(summary_path)
    try:
        metrics = run.read_metrics()
    except RunDirError as error:  # names the file
        raise CLIError(str(error)) from None
    except (OSError, csv.Error) as error:
        raise CLIError(f"{run.metrics_path}: unreadable: {error}") from None
    matrix = None
    matrix_path = run.path / "xp" / "matrix.csv"
    if matrix_path.is_file():
        try:
            matrix = read_matrix_csv(matrix_path).values.tolist()
        except (OSError, ValueError) as error:
            raise CLIError(f"{matrix_path}: unreadable cross-play matrix: {error}") from None
        seeds = config.population.num_seeds
        if len(matrix) != seeds or any(len(row) != seeds for row in matrix):
            shape = f"{len(matrix)} x {len(matrix[0]) if matrix else 0}"
            raise CLIError(f"{matrix_path}: a {shape} matrix, but the run has {seeds} seeds ({seeds} x {seeds})")
    return {
        "path": str(path),
        "name": run.path.resolve().name,
        "config": config,
        "summary": summary,
        "metrics": metrics,
        "matrix": matrix,
        "status": run.read_manifest().get("status", ""),
        "matrix_note": _holes(matrix_path, matrix),
    }


def _holes(path: Path, matrix: list | None) -> str:
    """Why the table's numbers are not the whole matrix's: cells with no number ("" when there is none). A blank
    cell is a pair that was never played or lost; the SP and XP shown are summary.json's all the same."""
    if matrix is None:
        return ""
    cells = np.argwhere(~np.isfinite(np.asarray(matrix, np.float64)))
    if not len(cells):
        return ""
    shown = ", ".join(f"({row}, {col})" for row, col in cells[:5].tolist()) + (", ..." if len(cells) > 5 else "")
    return (
        f"{path}: {len(cells)} cell(s) without a number (row, column: {shown}); the SP and XP shown are "
        "summary.json's, which may have been computed before they were lost"
    )


SUMMARY_NUMBERS = ("sp_mean", "xp_mean", "gap", "sp_std", "xp_std", "sp_ci95", "xp_ci95")  # what the report reads
SUMMARY_COUNTS = ("num_policies", "episodes_per_pair")


def _checked_summary(path: Path) -> dict:
    """A run's xp/summary.json, or ``CLIError`` naming the file and the key that is not what ocv2 writes (a
    value that is not a number once showed as n/a without a word, a list crashed the report)."""
    try:
        summary = boundedjson.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise CLIError(f"{path}: unreadable cross-play summary: {error}") from None
    if not isinstance(summary, dict):
        raise CLIError(f"{path}: holds a JSON {type(summary).__name__}, not a cross-play summary (an object)")
    for key in SUMMARY_NUMBERS:
        value = summary.get(key)
        if key in SUMMARY_NUMBERS[:3] and key not in summary:
            raise CLIError(f"{path}: no {key} (not a cross-play summary ocv2 wrote)")
        if value is None:
            continue  # null: nothing to show (e.g. no cross-play pair)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise CLIError(f"{path}: {key} must be a finite number (or null where it has none), found {value!r}")
    for key in SUMMARY_COUNTS:
        value = summary.get(key, 0)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise CLIError(f"{path}: {key} must be a whole number of 0 or more, found {value!r}")
    return summary


def env_label(config) -> str:
    """Short description of the env section: view radius and the flags that are switched on."""
    env = config.env_kwargs
    parts = ["full view" if env.get("agent_view_size") is None else f"view {env['agent_view_size']}"]
    flags = {
        "random_agent_positions": "random starts",
        "negative_rewards": "negative rewards",
        "sample_recipe_on_delivery": "recipe resampling",
        "indicate_successful_delivery": "delivery indicator",
    }
    parts += [label for key, label in flags.items() if env.get(key)]
    others = sorted(
        k
        for k, v in env.items()
        if k not in flags and k not in ("layout", "agent_view_size") and not (k == "max_steps" and v == 400)
    )
    parts += [f"{k}={env[k]}" for k in others]
    return ", ".join(parts)


def group_key(run: dict) -> str:
    """What makes runs comparable (``population.policy.comparable_key``): the same game and the same network."""
    return comparable_key(run["config"])


def network_labels(runs: list[dict]) -> dict[str, str]:
    """Run path -> a short name of its network (the kind, then the settings in which it differs from the other
    networks of that kind), or {} when every run trains the same network."""
    settings = {run["path"]: network_settings(run["config"]) for run in runs}
    if len({json.dumps(s, sort_keys=True, default=list) for s in settings.values()}) < 2:
        return {}
    labels = {}
    for path, mine in settings.items():
        same_kind = [other for other in settings.values() if other["kind"] == mine["kind"]]
        differ = sorted(k for k in mine if k != "kind" and any(other[k] != mine[k] for other in same_kind))
        labels[path] = " ".join([mine["kind"], *(f"{k}={_plain(mine[k])}" for k in differ)])
    return labels


def _plain(value) -> str:
    return ",".join(str(v) for v in value) if isinstance(value, list | tuple) else str(value)


def run_groups(runs: list[dict]) -> dict[str, list[dict]]:
    """``runs`` by ``group_key``, groups in the order of their first run."""
    groups: dict[str, list[dict]] = {}
    for run in runs:
        groups.setdefault(group_key(run), []).append(run)
    return groups


def pick_baselines(runs: list[dict], chosen: list[str] | None = None) -> dict[str, dict | None]:
    """Group key -> the self-play run (with cross-play) the group's other runs are compared with, or None.
    ``chosen``: the ``--baseline`` runs, one per group at most. ``CLIError`` for a ``--baseline`` that is not one
    of ``runs``, not self-play or without cross-play, two for one group, and for a group with several self-play
    runs none of which was chosen."""
    groups = run_groups(runs)
    by_path = {Path(run["path"]).resolve(): run for run in runs}
    picked: dict[str, dict | None] = {}
    for text in chosen or ():
        run = by_path.get(resolved(text, "--baseline"))
        if run is None:
            raise CLIError(f"--baseline {text}: not one of this report's RUN_DIRs; give it as a RUN_DIR too")
        method = run["config"].population.method
        if method != "sp":
            raise CLIError(f"--baseline {text}: a {method} run; the baseline is a self-play (sp) run")
        if not run["summary"]:
            raise CLIError(f"--baseline {text}: {NO_XP_NOTE.format(run=text)}")
        key = group_key(run)
        if picked.get(key, run) is not run:
            raise CLIError(
                f"--baseline {text}: {picked[key]['path']} is the baseline of the same game and network already; "
                "give one --baseline per group"
            )
        picked[key] = run
    labels = network_labels(runs)
    for key, members in groups.items():
        if key in picked:
            continue
        candidates = [r for r in members if r["config"].population.method == "sp" and r["summary"]]
        if len(candidates) > 1:
            config = candidates[0]["config"]
            network = labels.get(candidates[0]["path"], config.model.kind)
            raise CLIError(
                f"{', '.join(r['path'] for r in candidates)}: {len(candidates)} self-play runs of the same game "
                f"({config.env_kwargs['layout']}, {env_label(config)}) and network ({network}); name the one the "
                "others are compared with: --baseline RUN_DIR"
            )
        picked[key] = candidates[0] if candidates else None
    return picked


def report_rows(runs: list[dict], baselines: dict[str, dict | None] | None = None) -> list[dict]:
    """One row per run, grouped by game and network, the baseline first, then SP, then the other methods; deltas
    vs the group's baseline (``pick_baselines``: computed here when not given, refusing a choice it cannot make)."""
    baselines = pick_baselines(runs) if baselines is None else baselines
    labels = network_labels(runs)
    rows = []
    for key, members in run_groups(runs).items():
        baseline = baselines.get(key)
        members = sorted(members, key=lambda r: (r is not baseline, METHODS.index(r["config"].population.method)))
        for run in members:
            config, summary = run["config"], run["summary"]
            updates = [
                int(float_or_nan(r.get("update")))
                for r in run["metrics"]
                if not math.isnan(float_or_nan(r.get("update")))
            ]
            steps = [float_or_nan(r.get("env_steps")) for r in run["metrics"]]
            steps = [s for s in steps if not math.isnan(s)]
            row = {
                "layout": config.env_kwargs["layout"],
                "method": config.population.method,
                "env": env_label(config),
                "network": labels.get(run["path"], ""),
                "run_dir": run["path"],
                "status": run["status"],
                "num_seeds": config.population.num_seeds,
                "updates_done": max(updates) if updates else 0,
                "num_updates": config.ppo.num_updates,
                "env_steps_per_seed": int(max(steps)) if steps else 0,
                "baseline_run": "",
                "delta_sp": math.nan,
                "delta_xp": math.nan,
                "delta_gap": math.nan,
                "delta_gap_ci95_low": math.nan,
                "delta_gap_ci95_high": math.nan,
                "delta_note": "",
                "note": "",
            }
            for key in ("sp_mean", "sp_std", "xp_mean", "xp_std", "gap", "sp_ci95", "xp_ci95"):
                row[key] = float_or_nan(summary.get(key)) if summary else math.nan
            row["num_policies"] = int(summary.get("num_policies", 0)) if summary else 0
            row["episodes_per_pair"] = int(summary.get("episodes_per_pair", 0)) if summary else 0
            if summary and run["matrix_note"]:
                row["note"] = run["matrix_note"]
            if not summary:
                row["note"] = NO_XP_NOTE.format(run=run["path"])
            elif baseline is not None and run is not baseline:
                row["baseline_run"] = baseline["path"]
                delta = summary_difference(
                    baseline["summary"],
                    summary,
                    baseline["matrix"] or None,
                    run["matrix"] or None,
                    names=(f"{baseline['path']}/xp/matrix.csv", f"{run['path']}/xp/matrix.csv"),
                )
                row["delta_sp"], row["delta_xp"], row["delta_gap"] = delta.sp, delta.xp, delta.gap
                row["delta_gap_ci95_low"], row["delta_gap_ci95_high"] = delta.gap_interval
                row["delta_note"] = f"no Δ gap interval: {delta.problem}" if delta.problem else ""
            rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------------
# formatting
# ---------------------------------------------------------------------------------------------------


def fmt(value, signed: bool = False) -> str:
    """``value`` with one decimal (a leading sign if ``signed``), or ``n/a`` for None or NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    return f"{value:+.1f}" if signed else f"{value:.1f}"


def fmt_pm(mean, std) -> str:
    """``mean ± std`` with one decimal each, or ``n/a`` if ``mean`` is NaN."""
    if math.isnan(mean):
        return "n/a"
    return f"{mean:.1f} ± {fmt(std)}"


def _steps(value: int) -> str:
    return f"{value / 1e6:.2f}M" if value >= 1e6 else f"{value:,}"


def delta_gap_cell(row: dict) -> str:
    """Δ Gap with its 95 % interval over both populations' seeds where both matrices gave one."""
    cell = fmt(row["delta_gap"], True)
    low, high = row["delta_gap_ci95_low"], row["delta_gap_ci95_high"]
    if math.isnan(low) or math.isnan(high):
        return cell
    return f"{cell} [{fmt(low, True)}, {fmt(high, True)}]"


def table_cells(rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Header and string cells shared by the rich and the Markdown tables."""
    deltas = any(not math.isnan(r["delta_gap"]) or not math.isnan(r["delta_xp"]) for r in rows)
    networks = any(r["network"] for r in rows)  # the runs train more than one network: say which is whose
    header = [
        "Layout",
        "Env",
        "Method",
        *(["Network"] if networks else []),
        "Seeds",
        "Env steps/seed",
        "SP",
        "XP",
        "Gap",
    ]
    if deltas:
        header += ["Δ SP", "Δ XP", "Δ Gap"]
    header.append("Run")
    cells = []
    for r in rows:
        line = [
            r["layout"],
            r["env"],
            METHOD_NAMES.get(r["method"], r["method"]),
            *([r["network"]] if networks else []),
            str(r["num_seeds"]),
            _steps(r["env_steps_per_seed"])
            + ("" if r["updates_done"] >= r["num_updates"] else f" ({r['updates_done']}/{r['num_updates']} updates)"),
        ]
        # NaN where there are no numbers (no cross-play yet): a note on a matrix's blank cells keeps summary.json's
        line += [fmt_pm(r["sp_mean"], r["sp_std"]), fmt_pm(r["xp_mean"], r["xp_std"]), fmt(r["gap"])]
        if deltas:
            line += [fmt(r["delta_sp"], True), fmt(r["delta_xp"], True), delta_gap_cell(r)]
        line.append(r["run_dir"] + (f" -- {r['note']}" if r["note"] else ""))
        cells.append(line)
    return header, cells


def markdown_table(header: list[str], cells: list[list[str]]) -> str:
    """``header`` and the rows of ``cells`` as a Markdown table, with any ``|`` in a cell escaped."""

    def esc(text: str) -> str:
        """``text`` with every ``|`` escaped for a Markdown table cell."""
        return text.replace("|", "\\|")

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in cells]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------
# pictures
# ---------------------------------------------------------------------------------------------------


def curve(metrics: list[dict], field: str = "sparse_return"):
    """(env steps, mean, std) across seeds per update; None if no finished episode was recorded."""
    curves = seed_curves(metrics, (field,))
    mean, std = across_seeds(curves.values[field])
    recorded = ~np.isnan(mean)
    if not recorded.any():
        return None
    return curves.env_steps[recorded], mean[recorded], std[recorded]


def write_curves(runs: list[dict], out: Path) -> list[str]:
    """Draw ``out/curves_<layout>.png`` for each layout of ``runs``: every run's sparse return (mean ±
    std across seeds) against env steps. Returns the paths written; a layout with no finished episode, or
    every layout when matplotlib is missing (a warning says so), gets none."""
    by_layout: dict[str, list[dict]] = {}
    for run in runs:
        by_layout.setdefault(run["config"].env_kwargs["layout"], []).append(run)
    paths = []
    for layout, members in by_layout.items():
        lines = [(run, curve(run["metrics"])) for run in members]
        lines = [(run, c) for run, c in lines if c is not None]
        if not lines:
            continue
        try:
            plt = pyplot()
        except PlotsUnavailable as error:
            skipped(out / f"curves_{layout}.png", error)
            continue
        fig, ax = plt.subplots(figsize=(6.5, 4))
        for run, (x, mean, std) in lines:
            config = run["config"]
            label = (
                f"{config.population.method.upper()} ({env_label(config)}, {config.population.num_seeds} "
                f"seeds): {run['name']}"
            )
            (line,) = ax.plot(x, mean, label=label)
            ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        ax.set_xlabel("environment steps per seed")
        ax.set_ylabel("sparse return (mean ± std across seeds)")
        ax.set_title(layout)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=7)
        paths.append(save_figure(fig, out / f"curves_{layout}.png"))
        plt.close(fig)
    return paths


def write_heatmaps(runs: list[dict], out: Path) -> dict[str, str]:
    """Draw ``out/heatmap_<run>.png`` (numbered when two runs share a name) for every run of ``runs`` with a
    cross-play matrix. Returns the run's path -> the picture's path, for those drawn (none without
    matplotlib)."""
    paths, used = {}, set()
    for run in runs:
        if not run["matrix"]:
            continue
        config = run["config"]
        stem = f"heatmap_{run['name']}"
        name, k = stem, 2
        while name in used:
            name, k = f"{stem}_{k}", k + 1
        used.add(name)
        summary = run["summary"] or {}
        title = f"{config.population.method.upper()} {config.env_kwargs['layout']}"
        if summary:
            title += f": SP {fmt(float_or_nan(summary.get('sp_mean')))}, XP {fmt(float_or_nan(summary.get('xp_mean')))}"
        path = xp_heatmap(np.asarray(run["matrix"], np.float64), out / f"{name}.png", title=title)
        if path is not None:  # None: matplotlib missing (xp_heatmap said so)
            paths[run["path"]] = path
    return paths


# ---------------------------------------------------------------------------------------------------
# ocv2 report
# ---------------------------------------------------------------------------------------------------


def add_report(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 report`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "report",
        help="paper-style SP/XP tables, curves and heatmaps of run directories",
        description="Read run directories and write report.md, report.csv (one row per run: "
        "SP, XP, gap and, against the self-play run of the same environment and network, the "
        "deltas), curves_<layout>.png and heatmap_<run>.png into --out.",
    )
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR")
    parser.add_argument(
        "--out",
        default="reports",
        help="folder to write into (default reports/): new, empty, or an earlier report's, which is replaced whole",
    )
    parser.add_argument(
        "--baseline",
        action="append",
        metavar="RUN_DIR",
        help="the self-play run (one of the RUN_DIRs) the other runs of its environment and network are compared "
        "with; needed where several self-play runs share one, and may be given once per such group",
    )
    return parser


def run_report(args) -> int:
    """Tabulate ``args.run_dirs`` into ``args.out`` (report.md, report.csv, curves, heatmaps) and print
    the table. Returns ``EXIT_OK``; raises ``CLIError`` for an unreadable run or an ``--out`` that is a file."""
    seen: dict[Path, str] = {}
    for path in args.run_dirs:
        where = resolved(path)
        if where in seen:
            raise CLIError(f"{path}: given twice (also as {seen[where]}); each run is one row")
        seen[where] = path
    runs = [load_run(path) for path in args.run_dirs]
    baselines = pick_baselines(runs, args.baseline)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CLIError(f"--out: {out} exists and is not a folder")
    if (out / "config.yaml").is_file() or resolved(out, "--out") in seen:
        raise CLIError(f"--out {out}: is a run directory; give a folder of its own for the report")
    check_replaceable(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CLIError(f"--out: cannot create {out}: {error}", EXIT_FAILURE) from None
    # An OSError (a full disk) is main's one line, nothing left; the report's own files move in last, as written.
    with staged_folder(out, ".report", markers=["report.csv", "report.md"]) as staging:
        written = write_report_files(runs, staging, baselines)
    table = Table(title=f"{len(written.rows)} run(s)")
    for name in written.header:
        table.add_column(name, justify="right" if name not in ("Layout", "Env", "Method", "Network", "Run") else "left")
    for line in written.cells:
        table.add_row(*line)
    stream = sys.stdout
    Console(file=stream, width=None if stream.isatty() else 240, highlight=False, soft_wrap=False).print(table)
    for run, note in written.notes:
        print(f"{run}: {note}")
    print(
        f"wrote {out / 'report.md'}, {out / 'report.csv'}, {written.curves} curve plot(s), "
        f"{written.heatmaps} heatmap(s)"
    )
    return EXIT_OK


REPORT_FILES = ("report.md", "report.csv")  # and curves_*.png, heatmap_*.png


def check_replaceable(out: Path) -> None:
    """``--out`` must be new, empty, or an earlier ``ocv2 report``'s folder (its report.csv has this report's
    columns and it holds nothing else than a report writes): that one is replaced whole. Anything else is
    refused, so a report never writes over other results nor leaves an earlier report's pictures beside its own."""
    if not out.is_dir():
        return
    present = sorted(p.name for p in out.iterdir())
    if not present:
        return
    foreign = [
        name
        for name in present
        if name not in REPORT_FILES and not (name.endswith(".png") and name.startswith(("curves_", "heatmap_")))
    ]
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise CLIError(f"--out {out}: holds {shown}, which `ocv2 report` does not write; give a new folder")
    try:
        header = (out / "report.csv").read_text().splitlines()[:1]
    except (OSError, UnicodeDecodeError):
        header = []
    if header != [",".join(CSV_FIELDS)]:
        raise CLIError(f"--out {out}: holds files but no report.csv of `ocv2 report`; give a new folder")


class WrittenReport(NamedTuple):
    """What ``write_report_files`` wrote, for the console."""

    rows: list[dict]
    header: list[str]
    cells: list[list[str]]
    notes: list[tuple[str, str]]  # (run directory, note)
    curves: int
    heatmaps: int


def write_report_files(runs: list[dict], out: Path, baselines: dict | None = None) -> WrittenReport:
    """Write report.csv, report.md and the pictures into the folder ``out``; ``baselines``: ``pick_baselines``'s."""
    rows = report_rows(runs, baselines)
    header, cells = table_cells(rows)
    curves = write_curves(runs, out)
    heatmaps = write_heatmaps(runs, out)

    buffer = io.StringIO(newline="")
    writer = csv.DictWriter(buffer, fieldnames=CSV_FIELDS)
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if isinstance(row[k], float) and math.isnan(row[k]) else row[k]) for k in CSV_FIELDS})
    atomic_write(out / "report.csv", buffer.getvalue())
    md = [
        "# ocv2 report",
        "",
        "SP: mean ± std over the self-play cells (diagonal) of the cross-play matrix; XP: mean ± std over the "
        "off-diagonal ordered pairs; Gap = SP - XP (the paper's Tables 1 and 2). Δ: this run minus the self-play "
        "run of the same environment and network (Δ Gap is the paper's Table 1 bracket; in brackets after it, its "
        "95 % interval by bootstrap over each population's seeds, the two populations resampled independently).",
        "",
        markdown_table(header, cells),
        "",
    ]
    notes = [(r["run_dir"], r["note"]) for r in rows if r["note"]]
    notes += [(r["run_dir"], r["delta_note"]) for r in rows if r["delta_note"]]
    if notes:
        md += ["## Notes", ""] + [f"- {run}: {note}" for run, note in notes] + [""]
    if curves:
        md += ["## Training curves", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in curves] + [""]
    if heatmaps:
        md += ["## Cross-play matrices", ""]
        md += [f"{run}:\n\n![{Path(p).stem}]({Path(p).name})\n" for run, p in heatmaps.items()]
    atomic_write(out / "report.md", "\n".join(md))
    return WrittenReport(rows, header, cells, notes, len(curves), len(heatmaps))
