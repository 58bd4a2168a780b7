"""``ocv2 validate`` / ``ocv2 report`` and the paper configs (configs/paper/*.yaml).

Report tests build run directories by hand (config.yaml, xp/summary.json, xp/matrix.csv, metrics.csv) with
the paper's Table 1 numbers, so every table cell and delta can be checked against hand-computed values.
Three paper configs (one per model kind and method family) are trained for one tiny update each.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from cluster.cli import main
from cluster.cli.report import curve
from cluster.runtime.rundir import read_matrix_csv, write_matrix_csv
from population.config import dump_config, load_config, parse_config

ROOT = Path(__file__).resolve().parents[1]
LAUNCHER_MARK = "# NOT an ocv2 config"  # Ray cluster-launcher files (configs/cluster/ray-*.yaml) say so on line 1
# Study files are not experiment configs: tests/test_study.py loads them.
ALL_CONFIGS = sorted(
    str(p.relative_to(ROOT))
    for p in (ROOT / "configs").rglob("*.yaml")
    if not p.read_text().startswith(LAUNCHER_MARK) and p.parent.name != "studies"
)
PAPER = ROOT / "configs" / "paper"
CLASSIC = ("cramped_room", "asymm_advantages", "coord_ring", "forced_coord", "counter_circuit")
V2 = (
    "grounded_coord_simple",
    "grounded_coord_ring",
    "test_time_simple",
    "test_time_wide",
    "demo_cook_simple",
    "demo_cook_wide",
)
METRICS_HEADER = ["seed", "update", "env_steps", "sparse_return", "shaped_return"]


# ---------------------------------------------------------------------------------------------------
# synthetic run directories
# ---------------------------------------------------------------------------------------------------


def make_run(
    path: Path,
    layout: str,
    method: str,
    summary: dict | None,
    metrics: list[list] | None = None,
    matrix: list[list[float]] | None = None,
    env: dict | None = None,
    model: dict | None = None,
) -> Path:
    path.mkdir(parents=True)
    raw = {
        "env": {"layout": layout, "max_steps": 400, **(env or {})},
        "model": model or {"kind": "cnn"},
        "ppo": {"num_envs": 4, "num_steps": 25, "num_minibatches": 2, "total_timesteps": 300},
        "population": {"method": method, "num_seeds": 2, "sa": {"iterations": 2}},
    }
    dump_config(parse_config(raw), path / "config.yaml")
    (path / "manifest.json").write_text(json.dumps({"status": "finished"}))
    rows = metrics if metrics is not None else [[0, 1, 100, 1.0, 2.0], [0, 2, 200, 3.0, 2.0], [0, 3, 300, 5.0, 2.0]]
    with open(path / "metrics.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(METRICS_HEADER)
        writer.writerows(rows)
    if summary is not None:
        (path / "xp").mkdir()
        full = {
            "sp_ci95": 1.0,
            "xp_ci95": 2.0,
            "num_policies": 2,
            "episodes_per_pair": 500,
            "per_recipe": {},
            **summary,
        }
        (path / "xp" / "summary.json").write_text(json.dumps(full))
        matrix = matrix or [[summary["sp_mean"], summary["xp_mean"]], [summary["xp_mean"], summary["sp_mean"]]]
        with open(path / "xp" / "matrix.csv", "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["seat0\\seat1"] + [f"seed_{j}" for j in range(len(matrix))])
            writer.writerows([[f"seed_{i}"] + row for i, row in enumerate(matrix)])
    return path


def table1(sp, sp_std, xp, xp_std, gap) -> dict:
    return {"sp_mean": sp, "sp_std": sp_std, "xp_mean": xp, "xp_std": xp_std, "gap": gap}


def read_csv(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture
def runs(tmp_path):
    """Paper Table 1 rows for Cramped Room and Coordination Ring (SP and SA), one SA run without
    cross-play, and an SP run of cramped room in another environment (view 2)."""
    base = tmp_path / "runs"
    return {
        "cr_sp": make_run(
            base / "cr_sp",
            "cramped_room",
            "sp",
            table1(259.0, 1.0, 257.0, 2.0, 2.0),
            metrics=[
                [0, 1, 100, 0.0, 1.0],
                [1, 1, 100, "", 1.0],
                [0, 2, 200, 10.0, 1.0],
                [1, 2, 200, 30.0, 1.0],
                [0, 3, 300, 20.0, 1.0],
                [1, 3, 300, 40.0, 1.0],
            ],
        ),
        "cr_sa": make_run(base / "cr_sa", "cramped_room", "sa", table1(259.0, 0.0, 255.0, 6.0, 4.0)),
        "ring_sa": make_run(base / "ring_sa", "coord_ring", "sa", table1(269.0, 44.0, 198.0, 50.0, 71.0)),
        "ring_sp": make_run(base / "ring_sp", "coord_ring", "sp", table1(214.0, 8.0, 96.0, 72.0, 118.0)),
        "fc_sa": make_run(base / "fc_sa", "forced_coord", "sa", None),
        "cr_view": make_run(
            base / "cr_view", "cramped_room", "sa", table1(100.0, 5.0, 50.0, 10.0, 50.0), env={"agent_view_size": 2}
        ),
    }


# ---------------------------------------------------------------------------------------------------
# ocv2 report
# ---------------------------------------------------------------------------------------------------


def test_report_tables_match_hand_computed_values(runs, tmp_path, capsys):
    out = tmp_path / "report"
    order = ["cr_sp", "cr_sa", "ring_sa", "ring_sp", "fc_sa", "cr_view"]
    assert main(["report", *(str(runs[k]) for k in order), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rows = {Path(r["run_dir"]).name: r for r in read_csv(out / "report.csv")}
    assert set(rows) == set(order)

    # grouped by environment, SP first within a group: the ring's SP row precedes its SA row
    names = [Path(r["run_dir"]).name for r in read_csv(out / "report.csv")]
    assert names == ["cr_sp", "cr_sa", "ring_sp", "ring_sa", "fc_sa", "cr_view"]

    def num(row, key):
        return float(row[key]) if row[key] != "" else math.nan

    cr_sp, cr_sa, ring_sa = rows["cr_sp"], rows["cr_sa"], rows["ring_sa"]
    assert (cr_sp["layout"], cr_sp["method"], num(cr_sp, "sp_mean"), num(cr_sp, "xp_std"), num(cr_sp, "gap")) == (
        "cramped_room",
        "sp",
        259.0,
        2.0,
        2.0,
    )
    # deltas against the same environment's SP run; the gap delta is Table 1's bracket: 4 (2), 71 (-47)
    assert (num(cr_sa, "delta_sp"), num(cr_sa, "delta_xp"), num(cr_sa, "delta_gap")) == (0.0, -2.0, 2.0)
    assert (num(ring_sa, "delta_sp"), num(ring_sa, "delta_xp"), num(ring_sa, "delta_gap")) == (55.0, 102.0, -47.0)
    assert Path(ring_sa["baseline_run"]).name == "ring_sp"
    # every seed of these 2-seed matrices scores the same, so every resample of either population gives its
    # gap exactly and the interval of the difference is the point
    assert (num(ring_sa, "delta_gap_ci95_low"), num(ring_sa, "delta_gap_ci95_high")) == (-47.0, -47.0)
    for name in ("cr_sp", "ring_sp", "cr_view", "fc_sa"):  # baselines, other envs, no cross-play: no delta
        assert rows[name]["delta_gap"] == "" and rows[name]["baseline_run"] == ""
        assert rows[name]["delta_gap_ci95_low"] == rows[name]["delta_gap_ci95_high"] == ""
    assert rows["cr_view"]["env"].startswith("view 2") and cr_sp["env"] == "full view"
    assert (cr_sp["num_seeds"], cr_sp["env_steps_per_seed"], cr_sp["updates_done"], cr_sp["num_updates"]) == (
        "2",
        "300",
        "3",
        "3",
    )

    # the run without xp/summary.json is listed with a note, not a crash
    note = f"no cross-play yet: run ocv2 xp {runs['fc_sa']}"
    assert rows["fc_sa"]["note"] == note and rows["fc_sa"]["sp_mean"] == ""
    md = (out / "report.md").read_text()
    assert note in md and note in printed

    # Markdown: the paper's layout of a row, one line per run
    lines = {line.split(" | ")[-1].rstrip(" |"): line for line in md.splitlines() if line.startswith("| ")}
    assert lines[str(runs["cr_sp"])].startswith(
        "| cramped_room | full view | Self-Play | 2 | 300 | 259.0 ± 1.0 | 257.0 ± 2.0 | 2.0 | n/a | n/a | n/a |"
    )
    assert (
        "| coord_ring | full view | State-Augmented | 2 | 300 | 269.0 ± 44.0 | 198.0 ± 50.0 | 71.0 | +55.0 | "
        "+102.0 | -47.0 [-47.0, -47.0] |" in lines[str(runs["ring_sa"])]
    )
    header = md.splitlines()[4]
    assert header.startswith("| Layout | Env | Method | Seeds | Env steps/seed | SP | XP | Gap | Δ SP | Δ XP | Δ Gap |")
    assert "259.0 ± 1.0" in printed and "State-Augmented" in printed

    # pictures: one curve plot per layout, one heatmap per evaluated run
    for layout in ("cramped_room", "coord_ring", "forced_coord"):
        assert (out / f"curves_{layout}.png").stat().st_size > 0
    heatmaps = sorted(p.name for p in out.glob("heatmap_*.png"))
    assert heatmaps == [
        "heatmap_cr_sa.png",
        "heatmap_cr_sp.png",
        "heatmap_cr_view.png",
        "heatmap_ring_sa.png",
        "heatmap_ring_sp.png",
    ]
    assert "curves_cramped_room.png" in md and "heatmap_ring_sp.png" in md


def test_training_curve_is_mean_and_std_across_seeds(runs):
    from cluster.cli.report import load_run

    x, mean, std = curve(load_run(runs["cr_sp"])["metrics"])
    assert x.tolist() == [100, 200, 300]
    assert mean.tolist() == [0.0, 20.0, 30.0]  # update 1: only seed 0 had finished an episode
    assert std.tolist() == [0.0, 10.0, 10.0]


def test_report_without_deltas_has_no_delta_columns(runs, tmp_path, capsys):
    out = tmp_path / "single"
    assert main(["report", str(runs["cr_sp"]), "--out", str(out)]) == 0
    md = (out / "report.md").read_text()
    assert "Δ SP |" not in md and "| 259.0 ± 1.0 | 257.0 ± 2.0 | 2.0 |" in md


def test_a_delta_gap_without_its_interval_says_why(runs, tmp_path, capsys):
    """A cell that is not a number in one matrix, or a run whose matrix.csv is gone: the Δ gap stands, and a
    note says why it has no interval (an interval of fewer resamples than it claims is not shown)."""
    matrix = runs["ring_sa"] / "xp" / "matrix.csv"
    matrix.write_text(matrix.read_text().replace("198.0", "", 1))
    out = tmp_path / "holed"
    assert main(["report", str(runs["ring_sp"]), str(runs["ring_sa"]), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    (row,) = [r for r in read_csv(out / "report.csv") if r["method"] == "sa"]
    assert row["delta_gap"] == "-47.0" and row["delta_gap_ci95_low"] == ""
    note = f"no Δ gap interval: {runs['ring_sa']}/xp/matrix.csv: 1 cell(s) are not numbers"
    assert note in (out / "report.md").read_text() and note in printed
    hole = f"{matrix}: 1 cell(s) without a number (row, column: (0, 1)); the SP and XP shown are summary.json's"
    assert hole in (out / "report.md").read_text() and row["note"].startswith(hole)
    matrix.unlink()
    assert main(["report", str(runs["ring_sp"]), str(runs["ring_sa"]), "--out", str(out)]) == 0
    assert f"no Δ gap interval: no {runs['ring_sa']}/xp/matrix.csv" in (out / "report.md").read_text()


def test_a_matrix_with_a_blank_cell_still_shows_the_summary_numbers_its_note_speaks_of(runs, tmp_path, capsys):
    matrix = runs["cr_sp"] / "xp" / "matrix.csv"
    matrix.write_text(matrix.read_text().replace("257.0", "", 1))
    out = tmp_path / "hole"
    assert main(["report", str(runs["cr_sp"]), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    (row,) = read_csv(out / "report.csv")
    assert row["note"].startswith(f"{matrix}: 1 cell(s) without a number") and "the SP and XP shown" in row["note"]
    md = (out / "report.md").read_text()
    assert "| 259.0 ± 1.0 | 257.0 ± 2.0 | 2.0 |" in md and "259.0 ± 1.0" in printed and "n/a" not in md


def _network_runs(base: Path) -> dict[str, Path]:
    """Cramped Room: a CNN SP run, a CNN SA run, an RNN SP run and an RNN SA run; RNN numbers differ."""
    rnn = {"kind": "rnn"}
    return {
        "cnn_sp": make_run(base / "cnn_sp", "cramped_room", "sp", table1(259.0, 1.0, 257.0, 2.0, 2.0)),
        "cnn_sa": make_run(base / "cnn_sa", "cramped_room", "sa", table1(259.0, 0.0, 255.0, 6.0, 4.0)),
        "rnn_sp": make_run(base / "rnn_sp", "cramped_room", "sp", table1(200.0, 1.0, 150.0, 2.0, 50.0), model=rnn),
        "rnn_sa": make_run(base / "rnn_sa", "cramped_room", "sa", table1(210.0, 1.0, 190.0, 2.0, 20.0), model=rnn),
    }


@pytest.mark.parametrize("order", [("rnn_sp", "cnn_sp", "cnn_sa", "rnn_sa"), ("cnn_sa", "rnn_sa", "cnn_sp", "rnn_sp")])
def test_runs_are_compared_with_the_self_play_run_of_their_own_network_whatever_the_order(order, tmp_path, capsys):
    runs = _network_runs(tmp_path / "runs")
    out = tmp_path / "report"
    assert main(["report", *(str(runs[name]) for name in order), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rows = {Path(r["run_dir"]).name: r for r in read_csv(out / "report.csv")}
    assert Path(rows["cnn_sa"]["baseline_run"]).name == "cnn_sp" and rows["cnn_sa"]["delta_xp"] == "-2.0"
    assert Path(rows["rnn_sa"]["baseline_run"]).name == "rnn_sp" and rows["rnn_sa"]["delta_gap"] == "-30.0"
    assert rows["cnn_sp"]["baseline_run"] == rows["rnn_sp"]["baseline_run"] == ""
    # the table says whose network each row is, since two are reported
    md = (out / "report.md").read_text()
    assert "| Layout | Env | Method | Network | Seeds |" in md and "Network" in printed
    assert "| cramped_room | full view | Self-Play | rnn | 2 |" in md and "State-Augmented │ cnn" in printed


def test_several_self_play_runs_of_one_group_need_a_baseline_named(tmp_path, capsys):
    runs = _network_runs(tmp_path / "runs")
    again = make_run(tmp_path / "runs" / "cnn_sp2", "cramped_room", "sp", table1(250.0, 1.0, 240.0, 2.0, 10.0))
    given = [str(runs["cnn_sp"]), str(runs["cnn_sa"]), str(again), str(runs["rnn_sp"])]
    out = tmp_path / "report"
    assert main(["report", *given, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{runs['cnn_sp']}, {again}: 2 self-play runs of the same game (cramped_room, full view) and network" in err
    assert "--baseline RUN_DIR" in err and "Traceback" not in err and not out.exists()
    assert main(["report", *given, "--baseline", str(again), "--out", str(out)]) == 0
    capsys.readouterr()
    names = [Path(r["run_dir"]).name for r in read_csv(out / "report.csv")]
    rows = {Path(r["run_dir"]).name: r for r in read_csv(out / "report.csv")}
    assert names[:3] == ["cnn_sp2", "cnn_sp", "cnn_sa"]  # the baseline first
    assert Path(rows["cnn_sa"]["baseline_run"]).name == Path(rows["cnn_sp"]["baseline_run"]).name == "cnn_sp2"
    assert (rows["cnn_sp"]["delta_sp"], rows["cnn_sa"]["delta_gap"]) == ("9.0", "-6.0")
    assert rows["rnn_sp"]["baseline_run"] == ""
    for baseline, words in [
        (runs["cnn_sa"], "a sa run; the baseline is a self-play (sp) run"),
        (runs["rnn_sa"], "not one of this report's RUN_DIRs"),
    ]:
        assert main(["report", *given, "--baseline", str(baseline), "--out", str(tmp_path / "r")]) == 2
        assert f"--baseline {baseline}: {words}" in capsys.readouterr().err
    both = ["--baseline", str(again), "--baseline", str(runs["cnn_sp"])]
    assert main(["report", *given, *both, "--out", str(tmp_path / "r")]) == 2
    assert "is the baseline of the same game and network already" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_report_out_replaces_an_earlier_report_whole_and_refuses_any_other_folder(runs, tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["report", str(runs["ring_sp"]), str(runs["ring_sa"]), "--out", str(out)]) == 0
    first = sorted(p.name for p in out.iterdir())
    assert "report.csv" in first and any(name.startswith("heatmap_") for name in first)
    assert main(["report", str(runs["cr_sp"]), "--out", str(out)]) == 0  # an earlier report: replaced whole
    second = sorted(p.name for p in out.iterdir())
    assert not [name for name in second if "ring" in name]  # no earlier picture left beside the new ones
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left
    capsys.readouterr()
    results = tmp_path / "results"
    results.mkdir()
    (results / "report.md").write_text("a published report")
    (results / "curves_coord_ring.png").write_bytes(b"png")
    assert main(["report", str(runs["cr_sp"]), "--out", str(results)]) == 2
    assert "holds files but no report.csv of `ocv2 report`" in capsys.readouterr().err
    (results / "notes.txt").write_text("mine")
    assert main(["report", str(runs["cr_sp"]), "--out", str(results)]) == 2
    assert "holds notes.txt, which `ocv2 report` does not write" in capsys.readouterr().err
    assert (results / "report.md").read_text() == "a published report"


def test_report_names_a_metrics_file_or_matrix_that_is_not_text(runs, tmp_path, capsys):
    matrix = runs["cr_sp"] / "xp" / "matrix.csv"
    matrix.write_bytes(b"\xff\xfe\x00")
    assert main(["report", str(runs["cr_sp"]), "--out", str(tmp_path / "r")]) == 2
    assert f"{matrix}: unreadable cross-play matrix" in capsys.readouterr().err
    metrics = runs["cr_sa"] / "metrics.csv"
    metrics.write_bytes(b"\xff\xfe")
    assert main(["report", str(runs["cr_sa"]), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert f"{metrics}: damaged: byte 0 is not UTF-8 text" in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def test_report_drops_a_metrics_row_whose_numbers_overflow_and_says_so(tmp_path, capsys):
    """``1e400`` reads as inf: its env_steps once ended report in ``int(inf)``'s OverflowError, its update in
    the row check's."""
    rows = [[0, 1, 100, 1.0, 2.0], [0, 2, "1e400", 3.0, 2.0], ["0", "1e400", 300, 5.0, 2.0], [0, 3, 300, 5.0, 2.0]]
    run = make_run(tmp_path / "run", "cramped_room", "sp", table1(259.0, 1.0, 257.0, 2.0, 2.0), metrics=rows)
    assert main(["report", str(run), "--out", str(tmp_path / "r")]) == 0
    err = capsys.readouterr().err
    assert err.count(f"{run / 'metrics.csv'}: the file is damaged: line ") == 2 and "Traceback" not in err, err
    (row,) = read_csv(tmp_path / "r" / "report.csv")
    assert (row["updates_done"], row["env_steps_per_seed"]) == ("3", "300")


def test_report_on_a_non_run_directory_fails_naming_it(tmp_path, capsys):
    empty = tmp_path / "not_a_run"
    empty.mkdir()
    assert main(["report", str(empty), "--out", str(tmp_path / "r")]) != 0
    err = capsys.readouterr().err
    assert str(empty) in err and "not an ocv2 run directory" in err and "Traceback" not in err
    missing = tmp_path / "missing"
    assert main(["report", str(missing)]) != 0
    assert str(missing) in capsys.readouterr().err
    assert not (tmp_path / "r").exists()  # nothing written before the inputs were checked


def test_a_matrix_file_reads_back_as_written_with_nan_for_a_pair_without_a_number(tmp_path):
    values = [[1.25, math.nan, -3.0], [0.0, 2.5, 7.125]]
    write_matrix_csv(tmp_path / "m.csv", values, ["a", "b"], ["x", "y", "z"])
    table = read_matrix_csv(tmp_path / "m.csv")
    assert table.rows == ["a", "b"] and table.cols == ["x", "y", "z"]
    assert table.values.shape == (2, 3) and math.isnan(table.values[0, 1])
    assert table.values[0, 0] == 1.25 and table.values[1, 2] == 7.125 and table.values[0, 2] == -3.0


def test_report_on_a_damaged_matrix_names_file_row_and_column(runs, tmp_path, capsys):
    matrix = runs["cr_sp"] / "xp" / "matrix.csv"
    matrix.write_text("seat0\\seat1,seed_0,seed_1\nseed_0,259.0,25O.0\nseed_1,257.0,259.0\n")
    assert main(["report", str(runs["cr_sp"]), "--out", str(tmp_path / "r")]) != 0
    err = capsys.readouterr().err
    assert str(matrix) in err and "row 2" in err and "'seed_1'" in err and "'25O.0'" in err
    assert "Traceback" not in err and not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    "summary, message",
    [
        ("[1, 2]", "holds a JSON list, not a cross-play summary"),
        (
            '{"sp_mean": "abc", "xp_mean": 1.0, "gap": 1.0}',
            "sp_mean must be a finite number (or null where it has none), found 'abc'",
        ),
        ('{"sp_mean": 1.0, "gap": 1.0}', "no xp_mean (not a cross-play summary ocv2 wrote)"),
        ('{"sp_mean": 1e400, "xp_mean": 1.0, "gap": 1.0}', "sp_mean must be a finite number"),
        ('{"sp_mean": 1.0, "xp_mean": 1.0, "gap": 1.0, "sp_std": "abc"}', "sp_std must be a finite number"),
        ('{"sp_mean": 1.0, "xp_mean": 1.0, "gap": 1.0, "num_policies": "ten"}', "num_policies must be a whole"),
        ('{"sp_mean": 1.0, "xp_mean": 1.0, "gap": 1.0, "episodes_per_pair": [1]}', "episodes_per_pair must be"),
    ],
)
def test_report_names_a_damaged_summary_instead_of_crashing_or_showing_n_a(runs, tmp_path, capsys, summary, message):
    path = runs["cr_sp"] / "xp" / "summary.json"
    path.write_text(summary)
    assert main(["report", str(runs["cr_sp"]), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert f"{path}: {message}" in err and "Traceback" not in err and not (tmp_path / "r").exists()


def test_report_names_a_matrix_of_the_wrong_size(runs, tmp_path, capsys):
    matrix = runs["cr_sp"] / "xp" / "matrix.csv"
    matrix.write_text("seat0\\seat1,seed_0\nseed_0,259.0\n")
    assert main(["report", str(runs["cr_sp"]), "--out", str(tmp_path / "r")]) == 2
    assert f"{matrix}: a 1 x 1 matrix, but the run has 2 seeds (2 x 2)" in capsys.readouterr().err


def test_the_xp_and_report_commands_of_reproducing_md_are_accepted(tmp_path, capsys, monkeypatch):
    """Each ``ocv2 xp`` / ``ocv2 report`` line of docs/REPRODUCING.md gets past its options: run in an empty
    folder, it stops at the run directory that is not there, not at a flag the command refuses."""
    lines = [
        line.partition("#")[0].split()
        for line in (ROOT / "docs" / "REPRODUCING.md").read_text().splitlines()
        if line.startswith(("ocv2 xp ", "ocv2 report "))
    ]
    assert len(lines) >= 2
    monkeypatch.chdir(tmp_path)
    for words in lines:
        assert main(words[1:]) == 2
        err = capsys.readouterr().err
        assert "runs/classic_" in err and ("not an ocv2 run directory" in err or "no such run directory" in err), (
            words,
            err,
        )


def test_report_out_must_be_a_folder(runs, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["report", str(runs["cr_sp"]), "--out", str(blocker)]) != 0
    assert "--out" in capsys.readouterr().err
    assert main(["report", str(runs["cr_sp"]), "--out", str(runs["cr_sa"])]) == 2  # into another run: no
    assert "is a run directory; give a folder of its own" in capsys.readouterr().err
    assert main(["report", str(runs["cr_sp"]), str(runs["cr_sp"]) + "/", "--out", str(tmp_path / "r")]) == 2
    assert "given twice" in capsys.readouterr().err and not (tmp_path / "r").exists()


# ---------------------------------------------------------------------------------------------------
# ocv2 validate
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", ALL_CONFIGS)
def test_every_config_validates(config, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    assert main(["validate", config]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"OK   {config}: ") and "env steps per seed" in out


def test_validate_reports_every_bad_file_and_exits_1(tmp_path, capsys):
    good = tmp_path / "good.yaml"
    good.write_text((ROOT / "configs" / "smoke.yaml").read_text())
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo:\n  learning_rate: 0.1\n")
    worse = tmp_path / "worse.yaml"
    worse.write_text("env: {layout: no_such_kitchen}\n")
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing yet\n")
    assert main(["validate", str(bad), str(good), str(worse), str(empty)]) == 1
    captured = capsys.readouterr()
    assert f"OK   {good}: sp on cramped_room" in captured.out
    assert f"FAIL {bad}: ppo.learning_rate: unknown key" in captured.err
    assert f"FAIL {worse}: env.layout:" in captured.err and "no_such_kitchen" in captured.err
    assert f"FAIL {empty}: empty (only comments or nothing)" in captured.err  # as train refuses it
    assert "3 of 4 config(s) invalid" in captured.err


def test_validate_checks_a_study_file_as_study_run_reads_it(tmp_path, capsys):
    """A study file was refused as a config ("study: unknown section"): it is now read as `ocv2 study run` reads it,
    one OK line per run; a run's bad override and a comparison of two games are named by study file and entry."""
    studies = sorted(str(path) for path in (ROOT / "configs" / "studies").glob("*.yaml"))
    assert main(["validate", *studies]) == 0  # every shipped study
    out = capsys.readouterr().out
    assert all(f"OK   {study}: run " in out for study in studies)
    assert "table1_cramped_room_sa10.yaml: run 'sa': sa on cramped_room (full view, cnn), 10 seeds x 610 updates" in out
    paper = ROOT / "configs" / "paper"
    bad = tmp_path / "bad_study.yaml"
    bad.write_text(
        f"study: bad\nruns:\n- name: sp\n  config: {paper / 'classic_cramped_room_sp.yaml'}\n  set: [ppo.lrr=1]\n"
    )
    mixed = tmp_path / "mixed_study.yaml"
    mixed.write_text(
        f"study: mixed\nruns:\n- name: sp\n  config: {paper / 'classic_cramped_room_sp.yaml'}\n"
        f"- name: ring\n  config: {paper / 'classic_coord_ring_sp.yaml'}\n"
        "comparisons:\n- name: both\n  runs: [sp, ring]\n"
    )
    assert main(["validate", str(bad), str(mixed)]) == 1
    err = capsys.readouterr().err
    assert f"FAIL {bad}: run 'sp'" in err and "ppo.lrr" in err, err
    assert f"FAIL {mixed}: comparison 'both': run 'ring' plays another game than run 'sp'" in err, err


def test_validate_and_train_refuse_the_same_missing_inputs_and_train_leaves_no_run_directory(tmp_path, capsys):
    """validate said OK to SA archives that train refused, and train refused a bad FCP partner run only after
    making the run directory, which then blocked the corrected command as "a run of a different config"."""
    smoke = str(ROOT / "configs" / "smoke.yaml")
    (tmp_path / "notes.mcap").write_text("not an archive")
    (tmp_path / "cut.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)  # a file cut after its magic
    cases = [
        (["population.method=sa", f"population.sa.archives=[{tmp_path / 'nope.mcap'}]"], "population.sa.archives:"),
        (["population.method=sa", f"population.sa.archives=[{tmp_path / 'notes.mcap'}]"], "population.sa.archives:"),
        (["population.method=sa", f"population.sa.archives=[{tmp_path / 'cut.mcap'}]"], "population.sa.archives:"),
        (["population.method=fcp", f"population.fcp.partners={tmp_path / 'none'}"], "population.fcp.partners:"),
    ]
    for overrides, said in cases:
        sets = [part for override in overrides for part in ("--set", override)]
        assert main(["validate", smoke, *sets]) == 1
        assert f"FAIL --set {overrides[-1]}: {said}" in capsys.readouterr().err  # the --set gave it, not the file
        out = tmp_path / "run"
        assert main(["train", smoke, *sets, "--backend", "local", "--no-eval", "--quiet", "--out", str(out)]) == 2
        assert said in capsys.readouterr().err and not out.exists()


def test_validate_lists_every_problem_of_a_file(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo: {lr: -1, lrr: 2}\nbogus: 1\neval: {episodes: 0}\n")
    assert main(["validate", str(bad)]) == 1
    failed = [line for line in capsys.readouterr().err.splitlines() if line.startswith("FAIL")]
    assert failed[0].startswith(f"FAIL {bad}: bogus: unknown section")
    assert [line.split(":")[1].strip() for line in failed[1:]] == ["ppo.lrr", "ppo.lr", "eval.episodes"]
    assert all(line.startswith(f"FAIL {bad}: ") for line in failed)


def test_validate_refuses_hostile_or_ambiguous_yaml_in_one_line_each(tmp_path, capsys):
    """5,000 nested lists (RecursionError), a 5,000-digit integer (ValueError) and a section given twice
    (the second silently won and the file passed)."""
    files = {
        "nested.yaml": ("env: " + "[" * 5000 + "\n", "nested deeper than 64 levels"),
        "digits.yaml": ("eval: {episodes: " + "7" * 5000 + "}\n", "an integer of 5000 digits (at most 100)"),
        "twice.yaml": ("env: {layout: cramped_room}\nenv: {layout: coord_ring}\n", "duplicate key 'env'"),
    }
    for name, (text, _) in files.items():
        (tmp_path / name).write_text(text)
    assert main(["validate", *(str(tmp_path / name) for name in files)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == len(files) + 1 and "3 of 3 config(s) invalid" in err[-1]
    for line, (name, (_, message)) in zip(err, files.items(), strict=False):
        assert line.startswith(f"FAIL {tmp_path / name}: not valid YAML: {message}"), line[:200]


def test_validate_skips_ray_launcher_configs(capsys):
    launcher = str(ROOT / "configs" / "cluster" / "ray-cluster-aws.yaml")
    assert main(["validate", launcher, str(ROOT / "configs" / "smoke.yaml")]) == 0
    assert f"SKIP {launcher}: a Ray cluster launcher config" in capsys.readouterr().out
    assert main(["train", launcher, "--backend", "local"]) == 2
    assert "Ray cluster launcher config" in capsys.readouterr().err


def test_validate_applies_overrides(capsys):
    smoke = str(ROOT / "configs" / "smoke.yaml")
    assert main(["validate", smoke, "--set", "population.num_seeds=3", "--set", "ppo.total_timesteps=1280"]) == 0
    assert "3 seeds x 10 updates x 128 = 1,280 env steps per seed" in capsys.readouterr().out
    assert main(["validate", smoke, "--set", "ppo.num_minibatches=3"]) == 1
    assert "ppo.num_minibatches" in capsys.readouterr().err


def test_validate_refuses_a_population_no_machine_here_can_hold(capsys):
    smoke = str(ROOT / "configs" / "smoke.yaml")
    assert main(["validate", smoke, "--set", "population.num_seeds=1000000000"]) == 1
    err = capsys.readouterr().err
    assert f"FAIL {smoke}: population.num_seeds: the run needs about" in err and "this machine" in err
    assert main(["validate", smoke]) == 0
    assert "memory here ~0." in capsys.readouterr().out  # the estimate for training here, in one process


def test_validate_checks_fcp_partner_directory(tmp_path, capsys):
    config = str(PAPER / "v2_grounded_coord_simple_fcp.yaml")
    assert main(["validate", config, "--set", f"population.fcp.partners={tmp_path}"]) == 1
    assert "population.fcp.partners" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------------
# the paper configs
# ---------------------------------------------------------------------------------------------------


def test_one_paper_config_per_experiment():
    names = sorted(p.stem for p in PAPER.glob("*.yaml"))
    expected = sorted(
        [f"classic_{layout}_{m}" for layout in CLASSIC for m in ("sp", "sa")]
        + [f"adapted_{layout}" for layout in CLASSIC + ("cramped_room_v2", "asymm_advantages_recipes_right")]
        + [f"v2_{layout}_{m}" for layout in V2 for m in ("sp", "sa", "op", "fcp")]
    )
    assert names == expected
    for name in names:
        config = load_config(PAPER / f"{name}.yaml")
        assert config.population.num_seeds == 10 and config.eval.episodes == 500
        assert config.env_kwargs["max_steps"] == 400
        assert (PAPER / f"{name}.yaml").read_text().startswith("# Paper ")  # a header naming the source


def test_v2_configs_follow_appendix_d():
    for layout in V2:
        configs = {m: load_config(PAPER / f"v2_{layout}_{m}.yaml") for m in ("sp", "sa", "op", "fcp")}
        env = configs["sp"].env_kwargs
        assert env["agent_view_size"] == 2 and env["negative_rewards"] and env["random_agent_positions"]
        assert env["sample_recipe_on_delivery"]
        assert env.get("indicate_successful_delivery", False) == layout.startswith("test_time")
        for method, config in configs.items():
            # FCP partners must play the same game with the same network as the SP run passed to them
            assert config.env == configs["sp"].env and config.model == configs["sp"].model, method
        sp, op, fcp = configs["sp"].ppo, configs["op"].ppo, configs["fcp"].ppo
        assert (sp.lr, sp.ent_coef, sp.num_envs, sp.total_timesteps, sp.rew_shaping_horizon) == (
            2.5e-4,
            0.01,
            256,
            30_000_000,
            15_000_000,
        )
        assert configs["sa"].ppo == sp and configs["sa"].population.sa.iterations == 10
        assert (op.num_envs, op.total_timesteps, op.ent_coef, op.rew_shaping_horizon) == (
            64,
            50_000_000,
            0.02,
            25_000_000,
        )
        assert configs["op"].population.op.ingredients == (0, 1)
        assert (fcp.lr, fcp.gae_lambda, fcp.ent_coef) == (7e-4, 0.9, 0.04)
        assert configs["fcp"].population.fcp.partner_seeds == 8
        assert configs["fcp"].population.fcp.checkpoints == ("mid", "final")


SHRINK = [
    "ppo.num_envs=2",
    "ppo.num_steps=8",
    "ppo.num_minibatches=1",
    "ppo.update_epochs=1",
    "ppo.total_timesteps=16",
    "population.num_seeds=2",
    "population.sa.iterations=1",
    "population.sa.rollouts_per_pair=1",
    "env.max_steps=20",
    "model.fc_dim=8",
    "model.gru_dim=8",
    "model.conv_features=[4]",
    "model.conv_kernels=[3]",
    "model.mixer_features=[4]",
    "run.checkpoint_every=1",
    "run.num_checkpoints=2",
]


# One per model kind and method family (FCP is covered by tests/test_train_cli.py):
# CNN + SA (classic, full view), RNN + SP (adapted: view 2, random starts, four recipes),
# RNN + OP (V2: recipe resampling, negative rewards, delivery indicator).
@pytest.mark.parametrize("name", ["classic_counter_circuit_sa", "adapted_cramped_room_v2", "v2_test_time_wide_op"])
def test_paper_config_trains_at_tiny_size(name, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", str(PAPER / f"{name}.yaml"), "--out", str(run), "--quiet", "--no-eval", "--backend", "local"]
    for item in SHRINK:
        args += ["--set", item]
    assert main(args) == 0
    assert json.loads((run / "manifest.json").read_text())["status"] == "finished"
    assert len(read_csv(run / "metrics.csv")) == 2  # 2 seeds x 1 update
    if name == "classic_counter_circuit_sa":  # a real run directory, not yet evaluated: listed with a note
        capsys.readouterr()
        assert main(["report", str(run), "--out", str(tmp_path / "report")]) == 0
        row = read_csv(tmp_path / "report" / "report.csv")[0]
        assert (row["layout"], row["method"], row["updates_done"], row["env_steps_per_seed"]) == (
            "counter_circuit",
            "sa",
            "1",
            "16",
        )
        assert row["note"].startswith("no cross-play yet")
