"""Cross-run cross-play (``ocv2 xp --rows/--cols``), per-seat policies in evaluation, greedy play and the
seed-bootstrap confidence intervals."""

from __future__ import annotations

import csv
import dataclasses
import importlib
import json
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from policy_runs import shared_run
from test_methods import COOK_SCRIPT, SCRIPT_STEPS, _table, script_apply

import ocv2
from cluster.cli import main
from cluster.cli.errors import CLIError
from cluster.cli.xp import _check_poolable, _print_blocks
from cluster.runtime import crossplay
from cluster.runtime.rundir import read_matrix_csv
from population import memory
from population import policy as pol
from population.config import ClusterConfig, load_config
from population.evaluation import gather_params, play_row, stack_params
from population.networks import init_params
from population.record import play_recorded_pairs, play_recorded_row
from population.xp import (
    Side,
    bootstrap_block,
    bootstrap_difference,
    cross_play,
    paired_difference,
    summary_difference,
)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return shared_run(tmp_path_factory)


def _episodes(path) -> list[tuple]:
    """(return, start recipe) per row of episodes.csv, in file order (labels dropped)."""
    with open(path, newline="") as handle:
        return [(r["episode"], r["return"], r["start_recipe"]) for r in csv.DictReader(handle)]


def test_cross_run_xp_of_a_run_with_itself_equals_its_in_run_xp(run, tmp_path, capsys):
    pytest.importorskip("mcap", reason="ocv2 xp RUN_DIR writes the cross-play archive: needs mcap (pip install mcap)")
    assert main(["xp", str(run), "--episodes", "8"]) == 0
    out = tmp_path / "xp"
    assert (
        main(
            [
                "xp",
                "--rows",
                str(run),
                "--cols",
                str(run),
                "--episodes",
                "8",
                "--backend",
                "local",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    in_run = read_matrix_csv(run / "xp" / "matrix.csv").values
    np.testing.assert_array_equal(read_matrix_csv(out / "matrix.csv").values, in_run)
    assert (in_run != 0).any() and len(np.unique(in_run)) > 1  # real, policy-dependent numbers
    assert _episodes(out / "episodes.csv") == _episodes(run / "xp" / "episodes.csv")
    summary = json.loads((out / "summary.json").read_text())
    own = json.loads((run / "xp" / "summary.json").read_text())
    (block,) = summary["blocks"]
    for key in ("sp_mean", "xp_mean", "gap", "sp_ci95_interval", "xp_ci95_interval", "gap_ci95_interval"):
        assert block[key] == pytest.approx(own[key])
    # a run against itself: its one matrix holds both seat orders, so it is played once
    assert summary["seats"] == "both" and not (out / "matrix_cols_seat0.csv").exists()
    assert summary["precision"] == "float32"  # the run's run.precision, as its in-run cross-play played at
    np.testing.assert_allclose(read_matrix_csv(out / "matrix_mean.csv").values, (in_run + in_run.T) / 2, atol=1e-4)
    for name in ("matrix.csv", "episodes.csv", "blocks.csv", "summary.json", "heatmap.png", "heatmap_mean.png"):
        assert (out / name).exists()

    # Any source kind can stand for a row: a seed directory and an exported copy of seed 1 give the
    # run's own rows, and the exported copy is recognised as seed 1 itself (its diagonal cell is SP).
    # These rows are other sources than the column, so the second seat order is played too.
    exported = tmp_path / "seed1.ocv2policy"
    assert main(["export", str(run), "--seed", "1", "--out", str(exported)]) == 0
    mixed = tmp_path / "mixed"
    capsys.readouterr()
    assert (
        main(
            [
                "xp",
                "--rows",
                str(run / "checkpoints" / "seed_0"),
                str(exported),
                "--cols",
                str(run),
                "--episodes",
                "8",
                "--backend",
                "local",
                "--out",
                str(mixed),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert printed.count("(mean of rows in seat 0: ") == 2 and ", gap " in printed and "matrix_mean.csv" in printed
    np.testing.assert_array_equal(read_matrix_csv(mixed / "matrix.csv").values, in_run)
    np.testing.assert_array_equal(
        read_matrix_csv(mixed / "matrix_cols_seat0.csv").values, in_run
    )  # the run's seeds in seat 0
    summary = json.loads((mixed / "summary.json").read_text())
    first, second = summary["orders"]["rows_seat0"], summary["orders"]["cols_seat0"]
    assert [b["sp_mean"] for b in first] == pytest.approx([in_run[0, 0], in_run[1, 1]], abs=1e-4)
    assert [b["xp_mean"] for b in first] == pytest.approx([in_run[0, 1], in_run[1, 0]], abs=1e-4)
    assert [b["xp_mean"] for b in second] == pytest.approx([in_run[1, 0], in_run[0, 1]], abs=1e-4)
    assert [(b["rows"], b["cols"]) for b in second] == [(b["rows"], b["cols"]) for b in summary["blocks"]]
    pair = (in_run[0, 1] + in_run[1, 0]) / 2
    assert [b["xp_mean"] for b in summary["blocks"]] == pytest.approx([pair, pair], abs=1e-4)
    with open(mixed / "blocks.csv", newline="") as handle:
        lines = list(csv.DictReader(handle))
    assert [line["order"] for line in lines] == ["rows_seat0"] * 2 + ["cols_seat0"] * 2 + ["mean"] * 2
    assert all(line["row_method"] and line["col_method"] == "sp" for line in lines[:2])
    assert {"gap", "gap_std", "gap_ci95_low", "gap_ci95_high"} <= set(lines[0])

    one = tmp_path / "one_order"  # --seats 0: the rows in seat 0 only, as before
    assert (
        main(
            [
                "xp",
                "--rows",
                str(run / "checkpoints" / "seed_0"),
                "--cols",
                str(run),
                "--seats",
                "0",
                "--episodes",
                "8",
                "--backend",
                "local",
                "--out",
                str(one),
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads((one / "summary.json").read_text())
    assert summary["seats"] == "0" and list(summary["orders"]) == ["rows_seat0"]
    assert summary["blocks"][0]["xp_mean"] == pytest.approx(in_run[0, 1], abs=1e-4)
    assert not (one / "matrix_cols_seat0.csv").exists() and not (one / "matrix_mean.csv").exists()


def _xp(out, *args) -> int:
    return main(["xp", *args, "--episodes", "8", "--backend", "local", "--out", str(out), "--quiet"])


_PLAY = crossplay.CrossPlayPlayer.play


def _stopped_at(monkeypatch, call: int) -> list:
    """Cross-play jobs stop with a Ctrl-C at the ``call``-th (the command line then ends the process: not here);
    returns the list each played job's position is appended to."""
    real, played = _PLAY, []  # the real one, whatever an earlier call of this patched in

    def play(self, *args):
        if len(played) + 1 == call:
            raise KeyboardInterrupt
        played.append(args[-1])
        return real(self, *args)

    monkeypatch.setattr(crossplay.CrossPlayPlayer, "play", play)
    monkeypatch.setattr(importlib.import_module("cluster.cli.main"), "exit_now", lambda code: None)
    return played


def _two_orders(run) -> list[str]:
    """The run's 2 policies against each seed directory: 4 (row policy, column group) pieces with the rows in seat 0,
    played in 2 jobs (the two one-policy directories are one batch of columns), and 2 pieces with the columns."""
    return ["--rows", str(run), "--cols", *(str(run / "checkpoints" / f"seed_{i}") for i in (0, 1))]


def test_a_stopped_cross_play_continues_where_it_stopped_and_ends_as_an_uninterrupted_one(
    run, tmp_path, monkeypatch, caplog
):
    """Each finished job is kept in OUT.unfinished; the same command plays only the others, and the results are
    the uninterrupted command's, file for file. Stopped in the second seat order, so both orders' jobs are read."""
    whole, out = tmp_path / "whole", tmp_path / "stopped"
    assert _xp(whole, *_two_orders(run)) == 0
    _stopped_at(monkeypatch, call=4)  # after both jobs of the first order (4 pieces) and one of the second
    caplog.set_level("WARNING", logger="cluster.cli.xp")
    assert _xp(out, *_two_orders(run)) == 130
    kept = tmp_path / "stopped.unfinished"
    assert not out.exists() and len(list(kept.glob("rows_seat0_*.npz"))) == 4 and len(list(kept.glob("cols*"))) == 1
    assert f"5 of the 6 jobs are played and kept in {kept}: the same command with --out {out} continues" in caplog.text
    caplog.clear()
    (kept / ".rows_seat0_1_1_0.tmp-1-ab12.npz").write_bytes(b"half")  # what a write killed part-way leaves
    played = _stopped_at(monkeypatch, call=0)  # no stop: counts the jobs played
    assert _xp(out, *_two_orders(run)) == 0
    assert len(played) == 1 and not kept.exists()
    assert f"continuing a stopped cross-play: 5 of its 6 jobs were played before ({kept})" in caplog.text
    names = sorted(p.name for p in whole.iterdir())
    assert names == sorted(p.name for p in out.iterdir()) and "matrix_cols_seat0.csv" in names
    for name in ("matrix.csv", "matrix_cols_seat0.csv", "matrix_mean.csv", "episodes.csv", "blocks.csv"):
        assert (out / name).read_bytes() == (whole / name).read_bytes(), name
    ours, theirs = (json.loads((folder / "summary.json").read_text()) for folder in (out, whole))
    assert (ours.pop("jobs_continued"), theirs.pop("jobs_continued")) == (5, 0)
    ours.pop("wall_s"), theirs.pop("wall_s")
    assert ours == theirs


def test_column_groups_of_one_network_are_one_job_per_row_policy_with_the_returns_of_one_job_per_group(
    run, tmp_path, monkeypatch
):
    """Ten exported one-policy files as columns were ten jobs per seat-0 policy; neighbouring column groups of one
    network now join in one job, which pays off because one call plays all its partners stacked, with the episode
    keys of one call per group. A stop kept by one job per group (MAX_BATCH_POLICIES = 1, as before batches) that
    left a batch half played continues with the rest of it one by one and ends as the batched command, file for
    file; and one job per group from the start gives those files too."""
    batched = tmp_path / "batched"
    played = _stopped_at(monkeypatch, call=0)
    assert _xp(batched, *_two_orders(run)) == 0
    assert played == [(0, (0, 1), 0), (0, (0, 1), 1), (0, (0,), 0), (1, (0,), 0)]  # (row group, columns, row)

    monkeypatch.setattr(crossplay, "MAX_BATCH_POLICIES", 1)
    out = tmp_path / "half"
    _stopped_at(monkeypatch, call=2)  # plays (run seed 0, seed_0 directory) only
    assert _xp(out, *_two_orders(run)) == 130
    monkeypatch.setattr(crossplay, "MAX_BATCH_POLICIES", 16)
    played = _stopped_at(monkeypatch, call=0)
    assert _xp(out, *_two_orders(run)) == 0
    assert played == [(0, (1,), 0), (0, (0, 1), 1), (0, (0,), 0), (1, (0,), 0)]

    monkeypatch.setattr(crossplay, "MAX_BATCH_POLICIES", 1)
    one_by_one = tmp_path / "one_by_one"
    played = _stopped_at(monkeypatch, call=0)
    assert _xp(one_by_one, *_two_orders(run)) == 0
    assert len(played) == 6
    for folder in (out, one_by_one):
        for name in ("matrix.csv", "matrix_cols_seat0.csv", "matrix_mean.csv", "episodes.csv", "blocks.csv"):
            assert (folder / name).read_bytes() == (batched / name).read_bytes(), (folder, name)

    # Joined groups of different sizes (a 2-seed run beside a one-policy directory): each piece lands in its
    # own columns.
    monkeypatch.setattr(crossplay, "MAX_BATCH_POLICIES", 16)
    rows = [crossplay.resolve_source(str(run / "checkpoints" / "seed_0"))]
    cols = [crossplay.resolve_source(str(run / "checkpoints" / "seed_1")), crossplay.resolve_source(str(run))]
    assert crossplay.column_batches(rows[0], cols) == [(0, 1)]
    joined = crossplay.play_matrix(rows, cols, crossplay.LocalPlayers(), crossplay.xp_key(0), 3)
    monkeypatch.setattr(crossplay, "MAX_BATCH_POLICIES", 1)
    apart = crossplay.play_matrix(rows, cols, crossplay.LocalPlayers(), crossplay.xp_key(0), 3)
    np.testing.assert_array_equal(joined.returns, apart.returns)
    np.testing.assert_array_equal(joined.start_recipe, apart.start_recipe)

    # One-policy sources against themselves (a whole matrix replayed from exported files): each row is one job,
    # its self-play cell included, with the returns of one job per pair.
    square = ["--rows", *(str(run / "checkpoints" / f"seed_{i}") for i in (0, 1))]
    assert _xp(tmp_path / "square_one_by_one", *square) == 0
    monkeypatch.setattr(crossplay, "MAX_BATCH_POLICIES", 16)
    played = _stopped_at(monkeypatch, call=0)
    assert _xp(tmp_path / "square", *square) == 0
    assert played == [(0, (0, 1), 0), (1, (0, 1), 0)]
    for name in ("matrix.csv", "episodes.csv", "blocks.csv"):
        assert (tmp_path / "square" / name).read_bytes() == (tmp_path / "square_one_by_one" / name).read_bytes()


def test_column_batches_keep_the_row_group_itself_alone_and_never_leave_a_worker_idle():
    spec = ("cnn", "relu", {"layout": "cramped_room"})

    def group(name, n=1, other=spec):
        return SimpleNamespace(ids=tuple(f"{name}{k}" for k in range(n)), spec=other, names=(name,) * n)

    files = [group(f"f{c}") for c in range(5)]
    assert crossplay.column_batches(group("row"), files) == [(0, 1, 2, 3, 4)]
    # the row's own group of several policies plays itself through the in-run path: alone; so does another
    # network's group; a one-policy file joins its neighbours in its own row too
    other = group("x", other=("rnn", "relu", {"layout": "cramped_room"}))
    run = group("run", 2)
    assert crossplay.column_batches(run, [*files[:2], run, *files[2:], other]) == [(0, 1), (2,), (3, 4, 5), (6,)]
    assert crossplay.column_batches(files[2], files) == [(0, 1, 2, 3, 4)]
    assert crossplay.column_batches(group("row"), files, jobs=3) == [(0, 1), (2,), (3, 4)]
    assert crossplay.column_batches(group("row", 2), files, jobs=3) == [(0, 1), (2, 3, 4)]
    limit = crossplay.MAX_BATCH_POLICIES
    assert crossplay.column_batches(group("row"), [group("big", limit - 1), *files[:2]]) == [(0, 1), (2,)]


def test_a_stopped_cross_play_is_not_continued_with_other_settings_or_left_behind_with_nothing_played(
    run, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "stopped"
    kept = tmp_path / "stopped.unfinished"
    _stopped_at(monkeypatch, call=1)  # stopped before any job finished: nothing to keep
    assert _xp(out, *_two_orders(run)) == 130
    assert not kept.exists() and not out.exists()
    _stopped_at(monkeypatch, call=2)
    assert _xp(out, *_two_orders(run)) == 130
    before = sorted(p.name for p in kept.iterdir())
    assert len(before) == 3  # request.json and the two pieces (one per column group) of one job
    capsys.readouterr()
    code = main(["xp", *_two_orders(run), "--episodes", "4", "--backend", "local", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith(f"ocv2 xp: error: --out {out}: {kept} holds the jobs of an unfinished")
    assert "differs in: episodes (8 there, 4 now)" in err and "remove that folder to start again" in err
    swapped = ["--rows", str(run / "checkpoints" / "seed_1"), *_two_orders(run)[2:]]  # other row policies
    assert _xp(out, *swapped) == 2 and "differs in: rows" in capsys.readouterr().err
    assert sorted(p.name for p in kept.iterdir()) == before and not out.exists()
    job = sorted(kept.glob("*.npz"))[0]
    job.write_bytes(job.read_bytes()[:100])  # cut short by a full disk, say
    assert _xp(out, *_two_orders(run)) == 2
    damaged = f"{job}: damaged (BadZipFile: File is not a zip file); remove {kept} to start the cross-play again"
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"ocv2 xp: error: --out {out}: {damaged}"
    assert sorted(p.name for p in kept.iterdir()) == before and not out.exists()


def test_a_stopped_cross_play_of_one_matrix_continues_too(run, tmp_path, monkeypatch):
    """Rows that are the columns: one matrix holds both seat orders and is played once, and continued as such."""
    whole, out = tmp_path / "whole", tmp_path / "stopped"
    assert _xp(whole, "--rows", str(run)) == 0
    _stopped_at(monkeypatch, call=2)
    assert _xp(out, "--rows", str(run)) == 130
    played = _stopped_at(monkeypatch, call=0)
    assert _xp(out, "--rows", str(run)) == 0 and len(played) == 1
    for name in ("matrix.csv", "episodes.csv", "blocks.csv"):
        assert (out / name).read_bytes() == (whole / name).read_bytes(), name


def test_the_journal_reads_past_a_killed_write_and_refuses_a_folder_it_did_not_make(tmp_path):
    from cluster.runtime.xp_journal import JournalMismatch, XPJournal, journal_folder

    folder = journal_folder(tmp_path / "out")
    folder.mkdir()
    (folder / ".request.tmp-1-ab12.json").write_text('{"epis')  # request.json's write, killed part-way
    journal = XPJournal.open(tmp_path / "out", {"episodes": 8, "seats": "both"})
    assert journal.folder == folder and journal.count() == 0
    with pytest.raises(JournalMismatch, match=r"differs in: episodes \(8 there, 4 now\)"):
        XPJournal.open(tmp_path / "out", {"episodes": 4, "seats": "both"})
    other = journal_folder(tmp_path / "elsewhere")
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(JournalMismatch, match="exists and is no unfinished cross-play"):
        XPJournal.open(tmp_path / "elsewhere", {"episodes": 8})
    assert (other / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    "damage",
    [
        "truncated job",
        "job of another name",
        "job out of range",
        "job of another shape",
        "request not JSON",
        "request a list",
    ],
)
def test_a_damaged_journal_is_refused_naming_the_file_and_kept(tmp_path, damage):
    """A journal a full disk or a hand cut short is refused in one line naming the file and saying how to start
    again (the command line turns ``JournalMismatch`` into a usage error), never read as a matrix with holes."""
    from cluster.runtime.xp_journal import JournalMismatch, XPJournal

    request = {"episodes": 3, "seats": "both"}
    journal = XPJournal.open(tmp_path / "out", request)
    order = journal.order("rows_seat0")
    shapes = {(r, 0, 0): (2, 3) for r in range(2)}
    order.record((0, 0, 0), np.zeros((2, 3), np.float32), np.zeros((2, 3), np.int32))
    assert list(order.played(shapes)) == [(0, 0, 0)]
    saved = journal.folder / "rows_seat0_0_0_0.npz"
    if damage == "truncated job":
        saved.write_bytes(saved.read_bytes()[:100])
    elif damage == "job of another name":
        saved.rename(journal.folder / "rows_seat0_a_0_0.npz")
    elif damage == "job out of range":
        saved.rename(journal.folder / "rows_seat0_7_0_0.npz")
    elif damage == "job of another shape":
        order.record((0, 0, 0), np.zeros((2, 4), np.float32), np.zeros((2, 4), np.int32))
    else:
        (journal.folder / "request.json").write_text("{" if damage == "request not JSON" else "[]")
    before = {p.name: p.read_bytes() for p in journal.folder.iterdir()}
    with pytest.raises(JournalMismatch) as refused:
        XPJournal.open(tmp_path / "out", request).order("rows_seat0").played(shapes)
    message = str(refused.value)
    assert "damaged" in message and f"remove {journal.folder} to start the cross-play again" in message
    named = "request.json" if damage.startswith("request") else "rows_seat0_"
    assert message.startswith(str(journal.folder / named)) and "\n" not in message
    assert {p.name: p.read_bytes() for p in journal.folder.iterdir()} == before


def test_the_code_digest_changes_with_a_source_edit_and_not_with_anything_else(tmp_path, monkeypatch):
    from cluster.runtime import xp_journal

    for package in ("ocv2", "population", "cluster"):
        (tmp_path / package / "sub").mkdir(parents=True)
        (tmp_path / package / "__init__.py").write_text("")
        (tmp_path / package / "sub" / "rules.py").write_text("X = 1\n")
    fake = {
        name: SimpleNamespace(__file__=str(tmp_path / name / "__init__.py"))
        for name in ("ocv2", "population", "cluster")
    }
    monkeypatch.setattr(xp_journal.importlib, "import_module", fake.__getitem__)
    before = xp_journal.source_digest()
    (tmp_path / "ocv2" / "README.md").write_text("docs")  # not a source
    assert xp_journal.source_digest() == before
    (tmp_path / "population" / "sub" / "rules.py").write_text("X = 2\n")
    assert xp_journal.source_digest() != before


def test_where_nothing_can_be_kept_beside_out_the_cross_play_still_runs_and_says_so(run, tmp_path, monkeypatch, caplog):
    """An empty mount point given as --out has a parent no one may write to: no journal, a warning, the results.
    Where --out is not such a folder the same refusal is the command's error (a full disk is tested in test_study)."""
    from cluster.runtime import xp_journal

    def refused(cls, out, request):
        raise PermissionError(13, "Permission denied", str(xp_journal.journal_folder(out)))

    monkeypatch.setattr(xp_journal.XPJournal, "open", classmethod(refused))
    caplog.set_level("WARNING", logger="cluster.cli.xp")
    assert _xp(tmp_path / "new", "--rows", str(run)) == 1 and not (tmp_path / "new").exists()
    out = tmp_path / "mount"
    out.mkdir()
    assert _xp(out, "--rows", str(run)) == 0 and (out / "matrix.csv").is_file()
    assert "cannot keep the jobs beside --out" in caplog.text and "a stop will lose those played" in caplog.text


def test_pooled_sources_read_as_one_population(run, tmp_path, capsys):
    """--pool over the run's two seed directories gives the run's own population numbers: the same
    policies, the same matrix, the same seed bootstrap."""
    whole, pooled = tmp_path / "whole", tmp_path / "pooled"
    assert _xp(whole, "--rows", str(run)) == 0
    seeds = [str(run / "checkpoints" / f"seed_{i}") for i in (0, 1)]
    capsys.readouterr()
    assert main(["xp", "--rows", *seeds, "--pool", "--episodes", "8", "--backend", "local", "--out", str(pooled)]) == 0
    assert "pooled (2 policies of 2 sources): SP " in capsys.readouterr().out
    (own,) = json.loads((whole / "summary.json").read_text())["blocks"]
    summary = json.loads((pooled / "summary.json").read_text())
    assert len(summary["blocks"]) == 4  # each source against each, as without --pool
    block = summary["pooled"]
    assert block["sources"] == seeds and block["row_method"] == "sp" and block["num_rows"] == 2
    for key in ("sp_mean", "xp_mean", "gap", "sp_ci95_interval", "xp_ci95_interval", "gap_ci95_interval"):
        assert block[key] == pytest.approx(own[key], abs=1e-4)
    assert list(summary["pooled_orders"]) == ["rows_seat0", "cols_seat0"]
    with open(pooled / "blocks.csv", newline="") as handle:
        lines = [line for line in csv.DictReader(handle) if line["rows"] == "pooled"]
    assert [line["order"] for line in lines] == ["rows_seat0", "cols_seat0", "mean"]
    assert float(lines[-1]["gap"]) == pytest.approx(own["gap"], abs=1e-3)


def test_a_failure_while_writing_leaves_no_folder_and_the_same_command_runs_again(run, tmp_path, monkeypatch, capsys):
    """The results are written whole or not at all: a half folder would make the rerun that main's error message
    advises refuse its --out ("already holds files")."""
    out, real = tmp_path / "xp", crossplay.write_json

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(crossplay, "write_json", full_disk)  # summary.json, after the matrices and episodes
    assert _xp(out, "--rows", str(run)) != 0
    assert "No space left on device" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.glob(".xp.*"))
    monkeypatch.setattr(crossplay, "write_json", real)
    assert _xp(out, "--rows", str(run)) == 0 and (out / "summary.json").is_file()


def test_pool_errors_name_the_problem(run, tmp_path, capsys):
    assert _xp(tmp_path / "bad", "--rows", str(run), "--cols", str(run), "--pool") == 2
    assert "--pool: pools the --rows sources against themselves" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    assert main(["xp", str(run), "--pool"]) == 2
    assert "--pool: only with --rows" in capsys.readouterr().err


def test_one_policy_under_two_sources_is_refused_naming_both(run, tmp_path, capsys):
    """A copy of an exported file, or a run and its own checkpoint file, is one policy: as two sources it would be
    counted as two seeds (--pool) and its self-play cells as cross-play."""
    exported = tmp_path / "e.ocv2policy"
    assert main(["export", str(run), "--seed", "0", "--out", str(exported)]) == 0
    copy = tmp_path / "copy.ocv2policy"
    copy.write_bytes(exported.read_bytes())
    own = run / "checkpoints" / "seed_1" / "update_0000004.msgpack"  # the run's final checkpoint of seed 1
    capsys.readouterr()
    for args, flag, first, second in (
        (["--rows", str(exported), str(copy)], "--rows", exported, copy),
        (["--rows", str(run), str(own), "--pool"], "--rows", run, own),
        (["--rows", str(run), "--cols", str(copy), str(exported)], "--cols", copy, exported),
    ):
        out = tmp_path / "xp"
        assert _xp(out, *args) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"ocv2 xp: error: {flag}: {second} (") and f"is the same policy as {first} (" in err
        assert len(err.splitlines()) == 1 and not out.exists()
    # The same policy as a row and as a column is a cross-play of a source with itself: still allowed.
    assert _xp(tmp_path / "fine", "--rows", str(exported), "--cols", str(copy), "--seats", "0") == 0


def test_different_policies_of_one_name_get_the_part_of_their_path_that_tells_them_apart(run, tmp_path):
    """Two exported files of runs both named ``sp`` (or two runs named ``sp`` in two folders) name their policies
    alike; matrix.csv and episodes.csv must not hold two rows of one label. Labels that do not clash stay as
    they were."""
    first, second = tmp_path / "study_a" / "p.ocv2policy", tmp_path / "study_b" / "p.ocv2policy"
    for seed, path in enumerate((first, second)):
        path.parent.mkdir()
        pol.export_checkpoint(run, path, seed=seed, meta={"name": "sp/seed_0@4"})
    out = tmp_path / "xp"
    assert _xp(out, "--rows", str(first), str(second), "--seats", "0") == 0
    labels = ["study_a/sp/seed_0@4", "study_b/sp/seed_0@4"]
    matrix = read_matrix_csv(out / "matrix.csv")
    assert matrix.rows == labels and matrix.cols == labels
    with open(out / "episodes.csv", newline="") as handle:
        assert {(r["seat0"], r["seat1"]) for r in csv.DictReader(handle)} == {(a, b) for a in labels for b in labels}
    # two runs named sp in different folders; a copy of one policy keeps its one name; other names stay
    a, b = _group("studies/a/runs/sp", ["x0", "x1"], "sp"), _group("studies/b/runs/sp", ["y0", "y1"], "sp")
    a, b = (dataclasses.replace(g, names=("sp/seed_0", "sp/seed_1")) for g in (a, b))
    copy = dataclasses.replace(a, label="elsewhere/sp")
    other = _group("runs/op", ["z0"], "op")
    assert list(crossplay.policy_labels([a, b, other]).values()) == [
        ("a/sp/seed_0", "a/sp/seed_1"),
        ("b/sp/seed_0", "b/sp/seed_1"),
        ("runs/op/z0",),
    ]
    assert list(crossplay.policy_labels([a, copy, other]).values()) == [a.names, a.names, other.names]


def test_checkpoint_is_refused_without_a_run_or_seed_directory_and_each_source_s_update_is_recorded(
    run, tmp_path, capsys
):
    """--checkpoint picks nothing from a file (a checkpoint file is its own update): with file sources only it was
    ignored and recorded in summary.json as if it had been played."""
    checkpoint = run / "checkpoints" / "seed_0" / "update_0000002.msgpack"
    exported = tmp_path / "e.ocv2policy"
    assert main(["export", str(run), "--seed", "1", "--out", str(exported)]) == 0
    capsys.readouterr()
    out = tmp_path / "xp"
    assert _xp(out, "--rows", str(checkpoint), str(exported), "--checkpoint", "init") == 2
    err = capsys.readouterr().err
    assert (
        f"--checkpoint init: picks the checkpoint of a run or seed directory, and no source is one ({checkpoint}, "
        in err
    )
    assert f"{exported}: each one fixed policy); leave it out" in err and not out.exists()
    typo = tmp_path / "runs" / "typo_sp"  # a mistyped run directory: named as missing, --checkpoint not blamed
    assert _xp(out, "--rows", str(typo), "--checkpoint", "mid") == 2
    err = capsys.readouterr().err
    assert str(typo) in err and "--checkpoint mid" not in err, err
    assert _xp(out, "--rows", str(checkpoint), str(exported), "--seats", "0") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["checkpoint"] is None and summary["updates"] == {str(checkpoint): [2], str(exported): [4]}
    mixed = tmp_path / "mixed"
    assert _xp(mixed, "--rows", str(checkpoint), "--cols", str(run), "--checkpoint", "init", "--seats", "0") == 0
    summary = json.loads((mixed / "summary.json").read_text())
    assert summary["checkpoint"] == "init" and summary["updates"] == {str(checkpoint): [2], str(run): [0, 0]}


def test_a_missing_human_proxy_names_the_source_and_the_command_that_makes_it(run, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("OCV2_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "xp"
    assert _xp(out, "--rows", str(run), "--cols", "human-proxy:cramped_room") == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("ocv2 xp: error: human-proxy:cramped_room: no human proxy for cramped_room")
    assert str(tmp_path / "cache" / "human_proxy" / "cramped_room.ocv2policy") in err
    assert "make it with 'ocv2 human proxy cramped_room --source " in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_an_interrupted_in_run_cross_play_says_which_unfinished_archives_it_left(run, tmp_path, monkeypatch, caplog):
    """The writers keep the episodes an interrupted evaluation wrote (docs/archive.md: recoverable); the command
    must say where they are and what to do with them, not only 'interrupted'."""
    pytest.importorskip("mcap", reason="the in-run cross-play archives its episodes: needs mcap (pip install mcap)")
    import shutil

    from cluster.runtime import evaluate

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    real, calls = evaluate.record_episodes, []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # seed 0 in seat 0 has written its episodes with seed 0, seed 1 none yet
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(evaluate, "record_episodes", interrupted)
    caplog.set_level("WARNING", logger="cluster.runtime.evaluate")
    with pytest.raises(KeyboardInterrupt):
        evaluate.evaluate_run(copy, episodes=2, show_progress=False)
    left = copy / "archive" / "xp" / "seat0_seed_0.mcap.partial"
    assert left.is_file() and not (copy / "archive" / "xp" / "seat0_seed_1.mcap.partial").exists()
    (message,) = [r.getMessage() for r in caplog.records if r.name == evaluate.__name__]
    assert f"left 1 unfinished archive(s) of the episodes it played: {left};" in message
    assert f"'ocv2 xp {copy}' plays them again" in message and "'ocv2 archive recover FILE --out" in message
    monkeypatch.setattr(evaluate, "record_episodes", real)
    caplog.clear()
    evaluate.evaluate_run(copy, episodes=2, show_progress=False)  # the rerun replaces it
    assert not left.exists() and not [r for r in caplog.records if r.name == evaluate.__name__]


def test_a_block_of_one_policy_with_itself_prints_its_self_play_only(capsys):
    nan = float("nan")
    own = {"rows": 1, "cols": 1, "sp_mean": 214.6, "xp_mean": nan, "xp_ci95_interval": [nan, nan], "gap": nan}
    other = {
        "rows": 1, "cols": 1, "sp_mean": nan, "xp_mean": 153.8, "xp_ci95_interval": [153.8, 153.8], "gap": nan,
        "gap_std": nan,
    }  # fmt: skip
    _print_blocks({"seats": "0", "blocks": [own, other]})
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["1 x 1: SP 214.6 (self-play only)", "1 x 1: XP 153.8 [153.8, 153.8]"]


def test_pool_refuses_runs_of_different_methods():
    rows = [SimpleNamespace(label="runs/sp", method="sp"), SimpleNamespace(label="runs/sa", method="sa")]
    with pytest.raises(CLIError, match=r"different methods: runs/sp \(sp\), runs/sa \(sa\)"):
        _check_poolable(SimpleNamespace(cols=None), rows)
    _check_poolable(SimpleNamespace(cols=None), rows[:1] * 2)  # one method: fine


class ThreeLocalPlayers(crossplay.LocalPlayers):
    """In-process, but shaped like three workers: jobs are spread and waved as for Ray actors."""

    def __init__(self):
        super().__init__()
        self.shards, self.calls = [[0], [1], [2]], []

    def call(self, method, jobs):
        self.calls.append([shard for shard, _ in jobs])
        return super().call(method, jobs)


def test_cross_play_jobs_spread_over_workers_give_the_same_matrix(run, ray_session):
    rows = [crossplay.resolve_source(str(run))]
    cols = [crossplay.resolve_source(str(run / "checkpoints" / "seed_1")), crossplay.resolve_source(str(run))]
    key = crossplay.xp_key(0)
    here = crossplay.play_matrix(rows, cols, crossplay.LocalPlayers(), key, 3)
    three, seen = ThreeLocalPlayers(), []
    spread = crossplay.play_matrix(rows, cols, three, key, 3, progress=lambda done, total: seen.append(done))
    np.testing.assert_array_equal(spread.returns, here.returns)
    assert three.calls == [[0, 1, 2], [0]]  # 4 jobs (2 rows x 2 column groups) in waves of one per worker
    assert seen == [0, 3, 1]  # the progress bar moves after every wave
    players = crossplay.RayPlayers(1, ClusterConfig(num_cpus=1), "tf32")  # the Ray backend's call, on an actor
    try:
        on_ray = crossplay.play_matrix(rows, cols, players, key, 3)  # TF32 computes float32 on a CPU
        assert crossplay.ray.get(players.actors[0].__ray_call__.remote(lambda player: player.precision)) == "tf32"
    finally:
        players.close()
    np.testing.assert_array_equal(on_ray.returns, here.returns)
    np.testing.assert_array_equal(on_ray.start_recipe, here.start_recipe)


def test_cross_play_traces_at_the_precision_its_runs_trained_with(run, tmp_path, monkeypatch):
    """On a GPU JAX's default matmul precision is TF32: cross-play of runs trained at float32 must not use it."""
    group = crossplay.resolve_source(str(run))
    assert group.precision == "float32"  # the run's run.precision
    assert crossplay.resolve_source(str(run / "checkpoints" / "seed_1")).precision == "float32"  # a checkpoint's meta
    seed_0 = pol.load(run)
    tf32_file = pol.export(
        tmp_path / "tf32.ocv2policy",
        params=seed_0.params,
        model=seed_0.model,
        env=seed_0.env,
        meta={"precision": "tf32"},
    )
    tf32 = crossplay.resolve_source(str(tf32_file))
    unknown = dataclasses.replace(tf32, label="unknown", precision=None)
    assert crossplay.played_precision([group, unknown]) == "float32"
    assert crossplay.played_precision([unknown]) == "float32"  # nothing known: the default
    assert crossplay.played_precision([tf32, unknown]) == "tf32"
    with pytest.raises(crossplay.CrossPlayError, match=r"different run.precision \(.*: float32, .*: tf32\)$"):
        crossplay.played_precision([group, tf32])
    assert crossplay.played_precision([group, tf32], "bf16") == "bf16"
    # The CLI refuses the mix before playing anything, and takes a choice.
    out = tmp_path / "mixed"
    assert main(["xp", "--rows", str(run), "--cols", str(tf32_file), "--backend", "local", "--out", str(out)]) == 2
    assert not out.exists()
    # Each job is traced under the chosen precision (the setting a GPU honours; a CPU computes float32 anyway).
    seen = []

    def recording_cross_play(*args, **kwargs):
        seen.append(jax.config.jax_default_matmul_precision)
        return cross_play(*args, **kwargs)

    monkeypatch.setattr(crossplay, "cross_play", recording_cross_play)
    for precision, jax_name in (("tf32", "tensorfloat32"), ("float32", "float32")):
        crossplay.play_matrix([group], [tf32], crossplay.LocalPlayers(precision), crossplay.xp_key(0), 1)
        assert seen[-1] == jax_name
    assert jax.config.jax_default_matmul_precision is None  # only inside the job
    # ... and the command passes its choice to its players and records it.
    out = tmp_path / "chosen"
    command = ["xp", "--rows", str(run), "--cols", str(tf32_file), "--backend", "local", "--episodes", "1"]
    assert main([*command, "--seats", "0", "--precision", "tf32", "--quiet", "--out", str(out)]) == 0
    assert seen[-1] == "tensorfloat32" and json.loads((out / "summary.json").read_text())["precision"] == "tf32"
    broken = pol.export(tmp_path / "broken.ocv2policy", params=seed_0.params, model=seed_0.model, env=seed_0.env,
                        meta={"precision": "fp16"})  # fmt: skip
    with pytest.raises(crossplay.CrossPlayError, match="meta precision 'fp16' is not one of float32, tf32, bf16"):
        crossplay.resolve_source(str(broken))


def test_sources_of_different_environments_are_refused(run, tmp_path):
    seed_0 = pol.load(run)
    other = pol.export(
        tmp_path / "other.ocv2policy", params=seed_0.params, model=seed_0.model, env={**seed_0.env, "max_steps": 50}
    )
    assert (
        main(["xp", "--rows", str(run), "--cols", str(other), "--backend", "local", "--out", str(tmp_path / "xp")]) == 2
    )
    assert not (tmp_path / "xp").exists()
    with pytest.raises(crossplay.CrossPlayError, match="max_steps"):
        crossplay.check_same_env([crossplay.resolve_source(str(run)), crossplay.resolve_source(str(other))])
    assert main(["xp", "--cols", str(run)]) == 2  # needs --rows or RUN_DIR
    assert main(["xp", "--rows", str(run), "--checkpoint", "best"]) == 2
    assert main(["xp", "--rows", str(run), "--checkpoint", "\u00b2"]) == 2  # "²".isdigit(), yet int("²") fails
    assert main(["xp", str(run), "--greedy", "--backend", "ray"]) == 2  # options of --rows are not ignored


def test_episodes_past_what_the_machine_can_hold_are_refused_before_anything_plays(run, tmp_path, capsys, monkeypatch):
    """--episodes had no upper bound: the per-episode arrays ended xp in a MemoryError (a GiB machine here)."""
    monkeypatch.setattr(memory, "machine_memory_mib", lambda: 1024.0)
    out = tmp_path / "xp"
    argv = ["xp", "--rows", str(run), "--cols", str(run / "checkpoints" / "seed_0"), "--backend", "local"]
    assert main([*argv, "--episodes", str(10**8), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--episodes: a 2 x 1 cross-play of 100,000,000 episodes per pair in 2 seatings" in err, err
    assert main(["xp", str(run), "--episodes", str(10**8)]) == 2
    assert "--episodes: a 2 x 2 cross-play of 100,000,000 episodes per pair keeps" in capsys.readouterr().err
    assert main([*argv, "--episodes", str(2**31), "--out", str(out)]) == 2  # past int32: argparse refuses it
    assert "below 2**31" in capsys.readouterr().err
    assert not out.exists()


def test_settings_written_out_at_their_defaults_are_the_same_environment(run, tmp_path):
    """A run config that leaves max_steps (or negative_rewards) out and one that writes the default ask for the
    same game: cross-play, render and the published-folder check compare the settings with defaults written out."""
    seed_0 = pol.load(run)
    env = {k: v for k, v in seed_0.env.items() if k != "max_steps"}
    written = {**env, "max_steps": 400, "negative_rewards": False}
    assert pol.same_env(env, written) and pol.env_difference(env, written) == ""
    assert pol.env_difference(env, {**written, "max_steps": 40}) == "differs in max_steps: 400 vs 40"
    assert not pol.same_env(env, {**env, "layout": "coord_ring"})
    left_out = pol.export(tmp_path / "left_out.ocv2policy", params=seed_0.params, model=seed_0.model, env=env)
    spelled = pol.export(tmp_path / "spelled.ocv2policy", params=seed_0.params, model=seed_0.model, env=written)
    groups = [crossplay.resolve_source(str(left_out)), crossplay.resolve_source(str(spelled))]
    assert crossplay.check_same_env(groups) == env
    gif = tmp_path / "pair.gif"
    assert main(["render", "--seats", str(left_out), str(spelled), "--out", str(gif), "--steps", "3"]) == 0
    assert gif.exists()


def test_human_proxy_columns_resolve_through_population_human(run, tmp_path, monkeypatch):
    with pytest.raises(
        crossplay.CrossPlayError, match="human-proxy:overcookedv2_demo: layout 'overcookedv2_demo' has no human data"
    ):
        crossplay.resolve_source("human-proxy:overcookedv2_demo")  # the real population.human
    proxy = tmp_path / "proxy.ocv2policy"
    pol.export_checkpoint(run, proxy, seed=0, meta={"name": "human proxy"})
    monkeypatch.setattr(
        crossplay, "proxy_path", lambda layout: proxy if layout == "overcookedv2_demo" else _no_proxy(layout)
    )
    group = crossplay.resolve_source("human-proxy:overcookedv2_demo")
    assert group.names == ("human proxy",) and group.ids == crossplay.resolve_source(str(run)).ids[:1]
    assert group.method == "human-proxy"  # blocks.csv names the method of every source
    with pytest.raises(crossplay.CrossPlayError, match="human-proxy:cramped_room: no proxy"):
        crossplay.resolve_source("human-proxy:cramped_room")


def _no_proxy(layout):
    raise ValueError(f"no proxy for {layout}")


# ---------------------------------------------------------------------------------------------------
# per-seat policies and greedy play, with scripted policies whose returns are known
# ---------------------------------------------------------------------------------------------------


def stay_apply(params, hidden, obs, reset):
    """A different network: always stays, with a hidden state of size 3."""
    logits = 1e4 * jax.nn.one_hot(jnp.full(obs.shape[:2], 4), 6)
    return hidden + 1.0, logits, jnp.zeros(obs.shape[:2], jnp.float32)


def soft_script_apply(params, hidden, obs, reset):
    """The cook script with soft logits: sampling strays from it, argmax follows it."""
    h, logits, value = script_apply(params, hidden, obs, reset)
    return h, logits * 2e-4, value  # logit 2 for the scripted action, 0 for the others


def test_seats_with_different_networks_play_together_and_greedy_takes_the_most_likely_action():
    """A seat-0 script (hidden size 1) with seat-1 stayers of another network (hidden size 3): the cook
    delivers once. Its soft-logit version completes the script only when played greedily."""
    env = ocv2.make("cramped_room", max_steps=SCRIPT_STEPS)
    cook = stack_params([jnp.asarray(_table(COOK_SCRIPT))])
    stay = Side(stay_apply, 3, jnp.zeros((2, 1)))  # two "policies" of another network
    greedy = cross_play(soft_script_apply, 1, env, cook, jax.random.PRNGKey(5), 2, partners=stay, greedy=True)
    assert greedy.returns.shape == (1, 2, 2)
    np.testing.assert_array_equal(greedy.returns, 20.0)  # the cook delivers once, whoever stays
    sampled = cross_play(soft_script_apply, 1, env, cook, jax.random.PRNGKey(5), 2, partners=stay)
    assert (sampled.returns < 20.0).all()  # 40 steps at p ~ 0.6 each: the sampled script never completes


# ---------------------------------------------------------------------------------------------------
# bootstrap over seeds
# ---------------------------------------------------------------------------------------------------


def test_bootstrap_of_two_seeds_is_exact():
    """K = 2: a resample draws seeds (0,0), (0,1), (1,0) or (1,1). SP takes m00, m11 or their mean; XP
    exists only for the two mixed draws and is then always (m01 + m10) / 2."""
    m = np.asarray([[10.0, 2.0], [4.0, 30.0]])
    ci = bootstrap_block(m)
    assert ci["xp"] == (3.0, 3.0)
    assert ci["sp"] == (10.0, 30.0)
    assert ci["gap"][0] == pytest.approx(17.0) and ci["gap"][1] == pytest.approx(17.0)


def test_bootstrap_resamples_seeds_not_cells():
    """Two seeds that never cooperate (XP 0) next to one that always does: the interval reflects three
    seeds' worth of uncertainty, and independent sources are resampled independently."""
    m = np.zeros((3, 3))
    np.fill_diagonal(m, 20.0)
    ci = bootstrap_block(m)
    assert ci["xp"] == (0.0, 0.0) and ci["sp"] == (20.0, 20.0)
    rect = np.asarray([[0.0, 10.0], [20.0, 30.0]])  # rows from one run, columns from another
    low, high = bootstrap_block(rect, ["a", "b"], ["c", "d"])["xp"]
    assert (low, high) == (0.0, 30.0)  # a resample can draw row a twice and column c twice
    assert bootstrap_block(rect, ["a", "b"], ["c", "d"]) == bootstrap_block(rect, ["a", "b"], ["c", "d"])


def test_bootstrap_difference_of_two_seed_populations_is_exact():
    # With 2 seeds a resample has a cross-play cell only when it draws both seeds, and then its gap is the
    # population's own: every difference that exists is the difference of the two gaps.
    base = np.array([[10.0, 4.0], [2.0, 12.0]])  # gap 11 - 3 = 8
    other = np.array([[20.0, 15.0], [13.0, 20.0]])  # gap 20 - 14 = 6
    ci = bootstrap_difference(base, other)
    assert ci["gap"] == pytest.approx((-2.0, -2.0)) and ci["xp"] == pytest.approx((11.0, 11.0))


def test_bootstrap_difference_resamples_each_population_on_its_own():
    rng = np.random.default_rng(3)
    base = rng.normal(100.0, 30.0, size=(6, 6))
    shifted = base.copy()
    shifted[np.eye(6, dtype=bool)] += 50.0  # the same seeds, SP 50 higher: gap 50 higher
    ci = bootstrap_difference(base, shifted)
    # Each population is resampled on its own, so the difference carries both populations' spread: wider
    # than one population's gap interval (a paired resample of the same seeds would give exactly 50).
    low, high = ci["gap"]
    assert low < 50.0 < high and high - low > 10.0
    own = bootstrap_block(base)["gap"]
    assert high - low > own[1] - own[0]
    assert bootstrap_difference(base, shifted) == ci  # fixed seeds: the same matrices, the same interval
    same = bootstrap_difference(base, base)["gap"]
    assert same[0] < 0.0 < same[1]


def test_paired_difference_resamples_the_same_seeds_in_both_matrices():
    rng = np.random.default_rng(3)
    before = rng.normal(100.0, 30.0, size=(6, 6))
    after = before.copy()
    after[np.eye(6, dtype=bool)] += 50.0  # every seed's self-play 50 higher, its cross-play unchanged
    ci = paired_difference(before, after)
    # One draw of seeds serves both matrices, so the spread between seeds cancels: exactly 50, where
    # bootstrap_difference (two populations) gives a wide interval for the same matrices.
    assert ci["sp"] == pytest.approx((50.0, 50.0)) and ci["gap"] == pytest.approx((50.0, 50.0))
    assert ci["xp"] == pytest.approx((0.0, 0.0))
    # One seed's cross-play fell by 60 (10 of the 30 cells, -20 over all): a draw without that seed sees no
    # change at all, so the interval runs from well below -20 up to exactly 0.
    fell = after.copy()
    fell[0, 1:] -= 60.0
    fell[1:, 0] -= 60.0
    low, high = paired_difference(before, fell)["xp"]
    assert low < -20.0 and high == pytest.approx(0.0)
    assert paired_difference(before, fell) == paired_difference(before, fell)  # fixed draws
    with pytest.raises(ValueError, match="before has 6 seeds and after 5: not the same seeds"):
        paired_difference(before, after[:5, :5])
    with pytest.raises(ValueError, match="after: a 5 x 6 matrix"):
        paired_difference(before, after[:5])


def test_bootstrap_difference_refuses_a_cut_or_holed_matrix():
    square = np.ones((4, 4))
    with pytest.raises(ValueError, match="other: a 3 x 4 matrix"):
        bootstrap_difference(square, square[:3])  # a file that lost a row
    holed = square.copy()
    holed[1, 2] = np.nan
    with pytest.raises(ValueError, match="base: 1 cell"):
        bootstrap_difference(holed, square)


def test_summary_difference_subtracts_the_summaries_and_says_why_an_interval_is_missing():
    base = np.array([[10.0, 4.0], [2.0, 12.0]])
    other = np.array([[20.0, 15.0], [13.0, 20.0]])
    sums = [{"sp_mean": 11.0, "xp_mean": 3.0, "gap": 8.0}, {"sp_mean": 20.0, "xp_mean": 14.0, "gap": 6.0}]
    delta = summary_difference(*sums, base, other, names=("sp", "sa"))
    assert (delta.sp, delta.xp, delta.gap, delta.problem) == (9.0, 11.0, -2.0, "")
    assert delta.gap_interval == pytest.approx((-2.0, -2.0))  # bootstrap_difference's interval
    gone = summary_difference(*sums, base, None, names=("sp", "sa"))
    assert gone.gap == -2.0 and np.isnan(gone.gap_interval).all() and gone.problem == "no sa"
    holed = other.copy()
    holed[0, 1] = np.nan
    cut = summary_difference(*sums, base, holed, names=("sp", "sa"))
    assert np.isnan(cut.gap_interval).all() and cut.problem == "sa: 1 cell(s) are not numbers"
    unmeasured = summary_difference({"sp_mean": "", "xp_mean": None}, sums[1], base, other)
    assert np.isnan([unmeasured.sp, unmeasured.xp, unmeasured.gap]).all()


def _random_leaf(rng, path, leaf, num: int):
    """``num`` draws of one parameter at an initialiser's scale: weights ~ N(0, 1 / fan-in), LayerNorm
    scales near 1, biases near 0."""
    shape = (num, *leaf.shape)
    if leaf.ndim >= 2:
        values = rng.normal(0.0, 1.0 / np.sqrt(np.prod(leaf.shape[:-1])), shape)
    else:
        values = float(jax.tree_util.keystr(path).endswith("['scale']")) + rng.normal(0.0, 0.1, shape)
    return jnp.asarray(values, leaf.dtype)


def _rnn_population(num: int, max_steps: int):
    """``num`` random paper RNNs (GRU) and their environment with short episodes.

    Drawn with numpy from the parameter shapes (``jax.eval_shape`` traces the init without compiling it):
    flax's init of this network costs ~10 s to compile or to run op by op, and what is tested holds for
    any parameters."""
    config = load_config(str(Path(__file__).resolve().parents[1] / "configs/paper/v2_grounded_coord_simple_sp.yaml"))
    env = pol.policy_env({**config.env_kwargs, "max_steps": max_steps})
    net = pol.network(config.model, config.ppo.activation, env.num_actions)
    shapes = jax.eval_shape(lambda key: init_params(net, key, env.obs_shape), jax.random.PRNGKey(0))
    rng = np.random.default_rng(0)
    params = jax.tree_util.tree_map_with_path(lambda path, leaf: _random_leaf(rng, path, leaf, num), shapes)
    return net.apply, pol.hidden_size_of(config.model), env, params


def test_a_row_shares_seat_0_and_plays_exactly_the_pairs_of_repeated_copies():
    """cross_play's rows run seat 0 once for all partners (play_row, play_recorded_row); every state,
    action and return must equal the pair form with seat 0 and the key copied per pair (the old, slower
    program). The paper RNN, where seat 0's GRU and dense layers become one matmul over all pairs."""
    apply, hidden, env, params = _rnn_population(3, 60)
    key = jax.random.PRNGKey(11)
    row_fn = jax.jit(
        lambda a, b, k: (
            play_row(apply, hidden, env, a, b, k, 4).returns,
            play_recorded_row(apply, hidden, env, a, b, k, 4),
        )
    )
    pairs_fn = jax.jit(lambda a, b, k: play_recorded_pairs(apply, hidden, env, a, b, k, 4))
    for row in range(3):
        returns, shared = row_fn(jax.tree.map(lambda x: x[row], params), params, key)
        paired = pairs_fn(gather_params(params, [row] * 3), params, jnp.stack([key] * 3))
        for a, b in zip(jax.tree.leaves(shared), jax.tree.leaves(paired)):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(returns, paired.returns)
        assert len(np.unique(np.asarray(paired.actions))) > 1


# ---------------------------------------------------------------------------------------------------
# seat-fair results, without playing: orientation, the mean of both orders, what the files say
# ---------------------------------------------------------------------------------------------------


def _group(label, ids, method):
    return crossplay.PolicyGroup(
        label, tuple(f"{label}/{i}" for i in ids), tuple(ids), None, "relu", {"layout": "cramped_room"}, None, method
    )


def test_seat_fair_orders_are_oriented_rows_by_cols_and_averaged(tmp_path):
    """Row source A (2 policies) against column source B (3) and the human proxy: every number in
    seat 0 is 10 x the seat-0 policy + the seat-1 policy, so each order and the mean are known."""
    a, b = _group("A", ["a0", "a1"], "sp"), _group("B", ["b0", "b1", "b2"], "fcp")
    human = _group("human-proxy:cramped_room", ["h"], crossplay.HUMAN_PROXY_METHOD)
    value = {"a0": 1, "a1": 2, "b0": 3, "b1": 4, "b2": 5, "h": 6}
    episodes = 4

    def matrix(rows, cols):
        names = [i for g in rows for i in g.ids], [i for g in cols for i in g.ids]
        returns = np.asarray([[[10 * value[r] + value[c]] * episodes for c in names[1]] for r in names[0]], np.float32)
        return crossplay.Matrix(returns, np.zeros(returns.shape, np.int32), tuple(rows), tuple(cols))

    result = crossplay.SeatFairMatrix(matrix([a], [b, human]), matrix([b, human], [a]))
    np.testing.assert_array_equal(result.oriented("rows_seat0").matrix, [[13, 14, 15, 16], [23, 24, 25, 26]])
    np.testing.assert_array_equal(result.oriented("cols_seat0").matrix, [[31, 41, 51, 61], [32, 42, 52, 62]])
    np.testing.assert_array_equal(result.mean.matrix, [[22, 27.5, 33, 38.5], [27.5, 33, 38.5, 44]])
    summary = crossplay.summarize_seat_fair(result)
    assert summary["seats"] == "both" and [b["cols"] for b in summary["blocks"]] == ["B", "human-proxy:cramped_room"]
    assert summary["orders"]["rows_seat0"][1]["xp_mean"] == pytest.approx(21)
    assert summary["orders"]["cols_seat0"][1]["xp_mean"] == pytest.approx(61.5)
    assert summary["blocks"][1]["xp_mean"] == pytest.approx(41.25)
    crossplay.write_seat_fair_outputs(result, tmp_path, summary, ocv2.make("cramped_room"))
    with open(tmp_path / "blocks.csv", newline="") as handle:
        lines = list(csv.DictReader(handle))
    assert [(line["order"], line["cols"], line["col_method"]) for line in lines] == [
        (order, cols, method)
        for order in ("rows_seat0", "cols_seat0", "mean")
        for cols, method in (("B", "fcp"), ("human-proxy:cramped_room", "human-proxy"))
    ]
    assert all(line["row_method"] == "sp" for line in lines)
    np.testing.assert_allclose(
        read_matrix_csv(tmp_path / "matrix_cols_seat0.csv").values, [[31, 32], [41, 42], [51, 52], [61, 62]]
    )
    np.testing.assert_allclose(read_matrix_csv(tmp_path / "matrix_mean.csv").values, result.mean.matrix)
    with pytest.raises(ValueError, match="no 'cols_seat0' order"):
        crossplay.SeatFairMatrix(result.rows_seat0).oriented("cols_seat0")


def test_gap_std_is_the_spread_of_each_policy_s_own_gap():
    from population.xp import block_summary

    matrix = np.asarray([[10.0, 4.0, 2.0], [8.0, 9.0, 5.0], [6.0, 6.0, 12.0]])
    summary = block_summary(matrix, [0, 1, 2], [0, 1, 2])
    own = [10 - 3, 9 - 6.5, 12 - 6]  # SP cell minus the mean of the row's XP cells
    assert summary["gap"] == pytest.approx(31 / 3 - 31 / 6)
    assert summary["gap_std"] == pytest.approx(np.std(own, ddof=1))
    low, high = summary["gap_ci95_interval"]
    assert low <= summary["gap"] <= high


def test_seat_pairs_of_a_study_comparison_put_each_order_where_it_belongs():
    """Three sources in one square matrix, as a study's comparison plays them: every cell is 10 x the
    seat-0 policy + the seat-1 policy, so A in seat 0 and A in seat 1 differ and a swapped order is seen."""
    a, b, c = _group("A", ["a0", "a1"], "sp"), _group("B", ["b0", "b1"], "sa"), _group("C", ["c0"], "fcp")
    value = {"a0": 1, "a1": 2, "b0": 3, "b1": 4, "c0": 5}
    names = [i for g in (a, b, c) for i in g.ids]
    returns = np.asarray([[[10 * value[r] + value[s]] * 2 for s in names] for r in names], np.float32)
    played = crossplay.Matrix(returns, np.zeros(returns.shape, np.int32), (a, b, c), (a, b, c))
    pairs = crossplay.seat_pairs(crossplay.summarize_seat_fair(crossplay.SeatFairMatrix(played, played)))
    assert [(p["a"], p["b"], p["a_method"], p["b_method"]) for p in pairs] == [
        ("A", "B", "sp", "sa"),
        ("A", "C", "sp", "fcp"),
        ("B", "C", "sa", "fcp"),
    ]
    ab, ac, bc = pairs
    # A in seat 0 with B: 10 x {1, 2} + {3, 4}; A in seat 1: 10 x {3, 4} + {1, 2}
    assert ab["a_seat0"] == pytest.approx(18.5) and ab["a_seat1"] == pytest.approx(36.5)
    assert ab["a_seat0_std"] == pytest.approx(np.std([13, 14, 23, 24], ddof=1))
    assert ab["a_seat1_std"] == pytest.approx(np.std([31, 32, 41, 42], ddof=1))
    assert ab["mean"] == pytest.approx(27.5)
    low, high = ab["mean_ci95_interval"]
    assert 22 <= low <= 27.5 <= high <= 33
    assert (
        ac["a_seat0"] == pytest.approx(20)
        and ac["a_seat1"] == pytest.approx(51.5)
        and ac["mean"] == pytest.approx(35.75)
    )
    assert bc["a_seat0"] == pytest.approx(40) and bc["a_seat1"] == pytest.approx(53.5)
    assert ac["a_seat1_std"] == pytest.approx(np.std([51, 52], ddof=1))
    with pytest.raises(KeyError):  # one order only: no pairs
        crossplay.seat_pairs(crossplay.summarize_seat_fair(crossplay.SeatFairMatrix(played)))


def test_cross_play_on_workers_plays_waves_of_one_row_per_shard_and_says_so(caplog):
    from cluster.runtime.evaluate import _cross_play_spread
    from cluster.runtime.jobs import InProcessWorkers
    from cluster.runtime.shard import CrossPlayRows

    class Rows:  # a row's returns depend on the row only, as a real shard's do (every row uses the same keys)
        def __init__(self):
            self.calls = []

        def cross_play(self, params, rows, key, episodes, archive_dir):
            self.calls.append(list(rows))
            returns = np.stack([np.full((3, episodes), 10.0 * row + np.arange(3)[:, None]) for row in rows])
            return CrossPlayRows(list(rows), returns, np.zeros_like(returns, np.int32))

    params = {"w": np.zeros((3, 2))}
    for shards in ([[0, 1, 2]], [[0, 1], [2]], [[0], [1], [2]]):
        target, progress = Rows(), []
        result = _cross_play_spread(
            InProcessWorkers(shards, target),
            params,
            jax.random.PRNGKey(0),
            2,
            None,
            on_progress=lambda *a: progress.append(a),
        )
        np.testing.assert_array_equal(result.matrix, 10.0 * np.arange(3)[:, None] + np.arange(3)[None, :])
        width = len(shards)
        assert all(len(call) == 1 for call in target.calls) and sorted(r for c in target.calls for r in c) == [0, 1, 2]
        # 0 first (the bar appears), then one report per wave of up to one row per shard
        expected = [(0, 3)] + [(min(width, 3 - first), 3) for first in range(0, 3, width)]
        assert progress == expected, (shards, progress)
    # In a log (no terminal), each wave is a line: a local study's 20-minute cross-play is no longer silent.
    from cluster.runtime.progress import Bar

    caplog.set_level("INFO", logger="cluster.runtime.progress")
    with Bar("cross-play 3x3, 2 episodes/pair", unit="seat-0 rows") as bar:
        _cross_play_spread(
            InProcessWorkers([[0], [1]], Rows()), params, jax.random.PRNGKey(0), 2, None, on_progress=bar
        )
    lines = [m.split(" (")[0] for m in caplog.messages]
    assert lines == [
        "  cross-play 3x3, 2 episodes/pair: 2/3 seat-0 rows",
        "  cross-play 3x3, 2 episodes/pair: 3/3 seat-0 rows",
    ]
