"""``cluster.train_population``: the on_chunk events and the TensorBoard / W&B loggers it feeds; missing extras.

One smoke run (configs/smoke.yaml, 2 seeds x 4 updates, 3 cross-play episodes per pair: the same programs
as tests/test_train_cli.py's run, so they come from the session's compilation cache) with both loggers.
W&B is a stand-in module recording its calls (no network, no account); TensorBoard's event files are
read back from disk.
"""

from __future__ import annotations

import json
import struct
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from tensorboardX.proto import event_pb2

import cluster
from cluster.cli import main
from cluster.runtime import evaluate
from cluster.runtime.loggers import MissingExtraError, measurements, scalar_tag
from cluster.runtime.rundir import MetricsRow, RunDir
from population.config import load_config

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")


class FakeWandbRun:
    def __init__(self, **init):
        self.init, self.logged, self.summary, self.finished = init, [], {}, False

    def log(self, data, step=None):
        self.logged.append((step, data))

    def finish(self):
        self.finished = True


def fake_wandb() -> types.ModuleType:
    module = types.ModuleType("wandb")
    module.runs = []

    def init(**kwargs):
        module.runs.append(FakeWandbRun(**kwargs))
        return module.runs[-1]

    module.init = init
    module.Image = lambda path: ("image", path)
    module.login = lambda **kwargs: module.logged_in
    module.logged_in = True
    return module


def read_events(folder: Path) -> list:
    """Every event of a TensorBoard event file (TFRecord framing: length, crc, payload, crc)."""
    (path,) = folder.glob("events.out.tfevents.*")
    data, offset, events = path.read_bytes(), 0, []
    while offset < len(data):
        (length,) = struct.unpack("<Q", data[offset : offset + 8])
        event = event_pb2.Event()
        event.ParseFromString(data[offset + 12 : offset + 12 + length])
        events.append(event)
        offset += 12 + length + 4
    return events


class _Events(list):
    reads: list[int]  # for each read of metrics.csv during the run: how many chunk events came before it


@pytest.fixture(scope="module")
def logged_run(tmp_path_factory):
    wandb = fake_wandb()
    events, reads = _Events(), []
    read = RunDir._read_metrics

    def counted(self):
        reads.append(len(events))  # how many chunk events had been seen when metrics.csv was read
        return read(self)

    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(sys.modules, "wandb", wandb)
        patch.setattr(RunDir, "_read_metrics", counted)
        run_dir = tmp_path_factory.mktemp("runs") / "logged"
        summary = cluster.train_population(
            load_config(SMOKE, ["eval.episodes=3"]),
            run_dir,
            backend="local",
            show_progress=False,
            on_chunk=events.append,
            loggers=["tensorboard", "wandb"],
        )
    (run,) = wandb.runs
    events.reads = reads
    return run_dir, summary, events, run


def test_on_chunk_sees_every_metrics_row_once(logged_run):
    run_dir, summary, events, _ = logged_run
    assert [(e.update, e.num_updates) for e in events] == [(2, 4), (4, 4)]  # run.checkpoint_every=2
    rows = [MetricsRow.of(row) for row in RunDir(run_dir).read_metrics()]
    assert len(rows) == 2 * 4 and all(isinstance(r, MetricsRow) for e in events for r in e.rows)
    assert [(r.seed, r.update, r.env_steps) for e in events for r in e.rows] == [
        (r.seed, r.update, r.env_steps) for r in rows
    ]
    assert [measurements(r) for e in events for r in e.rows] == [measurements(r) for r in rows]  # CSV floats round-trip
    assert all(e.run_dir == run_dir.resolve() for e in events)
    assert summary["updates"] == 4 and "xp" in summary


def test_chunk_events_do_not_read_metrics_csv_back(logged_run):
    """The rows come from the coordinator: a chunk costs the same at update 10 and at update 10,000."""
    _, _, events, _ = logged_run
    assert len(events) == 2
    # Reads before the first chunk (the coordinator's table) and after the last (plots) only.
    assert [n for n in events.reads if 0 < n < len(events)] == []


def test_tensorboard_holds_every_metric_of_every_row_and_the_cross_play(logged_run):
    run_dir, summary, _, _ = logged_run
    scalars, images = {}, []
    for event in read_events(run_dir / "tensorboard"):
        for value in event.summary.value:
            if value.WhichOneof("value") == "simple_value":
                scalars[(value.tag, event.step)] = value.simple_value
            elif value.WhichOneof("value") == "image":
                images.append(value.tag)
    expected = {
        (scalar_tag(name, row.seed), row.env_steps): number
        for row in map(MetricsRow.of, RunDir(run_dir).read_metrics())
        for name, number in measurements(row).items()
    }
    assert {k: v for k, v in scalars.items() if not k[0].startswith("xp/")} == pytest.approx(expected)
    assert {"sparse_return/seed_1", "return_recipe_0_0_0/seed_0"} <= {tag for tag, _ in expected}
    written = json.loads((run_dir / "xp" / "summary.json").read_text())
    assert scalars[("xp/sp_mean", 512)] == pytest.approx(written["sp_mean"])
    assert scalars[("xp/xp_mean", 512)] == pytest.approx(written["xp_mean"])
    assert images == ["xp/heatmap"]


def test_wandb_gets_one_step_per_update_and_the_cross_play(logged_run):
    run_dir, _, _, run = logged_run
    assert run.init["id"] == run_dir.name and run.init["resume"] == "allow"
    assert run.init["config"]["ppo"]["num_envs"] == 4 and run.finished
    steps = [step for step, _ in run.logged if step is not None]
    assert steps == [1, 2, 3, 4]
    by_step = {step: data for step, data in run.logged if step is not None}
    for row in map(MetricsRow.of, RunDir(run_dir).read_metrics()):
        logged = by_step[row.update]
        assert logged["env_steps"] == row.env_steps
        for name, number in measurements(row).items():
            assert logged[scalar_tag(name, row.seed)] == pytest.approx(number)
    assert run.summary["xp/gap"] == pytest.approx(json.loads((run_dir / "xp" / "summary.json").read_text())["gap"])
    assert run.logged[-1] == (None, {"xp/heatmap": ("image", str(run_dir / "xp" / "heatmap.png"))})


@pytest.mark.parametrize(
    "blocked, argv, message",
    [
        ("ray", [], "pip install 'ocv2[ray]', or use --backend local"),
        ("tensorboardX", ["--backend", "local", "--logger", "tensorboard"], "pip install 'ocv2[tensorboard]'"),
        ("wandb", ["--backend", "local", "--logger", "wandb"], "pip install 'ocv2[wandb]'"),
    ],
)
def test_missing_extra_is_one_line_before_the_run_starts(tmp_path, capsys, monkeypatch, blocked, argv, message):
    monkeypatch.setitem(sys.modules, blocked, None)  # import raises ImportError, as when not installed
    out = tmp_path / "run"
    assert main(["train", SMOKE, "--out", str(out), "--quiet", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    with pytest.raises(MissingExtraError):
        cluster.train_population(
            SMOKE, out, backend="ray" if blocked == "ray" else "local", loggers=[] if blocked == "ray" else [argv[-1]]
        )


def test_wandb_without_credentials_is_one_line_before_the_run_starts(tmp_path, capsys, monkeypatch):
    """wandb.init failed at the first logged chunk, leaving a half-trained run; W&B's offline mode needs no key."""
    from cluster.runtime.loggers import LoggerSetupError, check_loggers

    wandb = fake_wandb()
    wandb.logged_in = False
    monkeypatch.setitem(sys.modules, "wandb", wandb)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    out = tmp_path / "run"
    assert main(["train", SMOKE, "--out", str(out), "--quiet", "--backend", "local", "--logger", "wandb"]) == 2
    err = capsys.readouterr().err
    assert "--logger wandb: no W&B API key; run `wandb login`" in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and not wandb.runs
    with pytest.raises(LoggerSetupError):
        check_loggers(["wandb"])
    monkeypatch.setenv("WANDB_MODE", "offline")
    assert check_loggers(["wandb"]) == ["wandb"]


def test_the_logger_help_is_made_from_the_table(monkeypatch):
    """``--logger``'s help names every logger of ``_CLASSES`` with where it logs and its extra, so a new logger
    cannot be left out of it; a logger that imports nothing beyond the core names no extra."""
    import argparse

    from cluster.cli.main import build_parser
    from cluster.runtime import loggers

    parsers = next(a for a in build_parser(full=True)._actions if isinstance(a, argparse._SubParsersAction))
    action = next(a for a in parsers.choices["train"]._actions if a.dest == "loggers")
    assert action.help == loggers.logger_help() and action.choices == loggers.LOGGERS
    for name, cls in loggers._CLASSES.items():
        assert f"{name} ({cls.about}; needs ocv2[{cls.extra}])" in action.help

    class PlainLogger:  # no package, no extra
        def __init__(self, run_dir, config):
            self.run_dir = run_dir

    monkeypatch.setitem(loggers._CLASSES, "plain", PlainLogger)
    assert loggers.logger_help().endswith(", plain")


def test_a_logger_without_a_package_needs_no_extra(tmp_path, monkeypatch):
    from cluster.runtime import loggers

    class PlainLogger:
        about = "lines in RUN_DIR/plain.txt"

        def __init__(self, run_dir, config):
            self.run_dir = run_dir

    monkeypatch.setitem(loggers._CLASSES, "plain", PlainLogger)
    assert loggers.check_loggers(["plain", "plain"]) == ["plain"]
    [made] = loggers.make_loggers(["plain"], tmp_path, load_config(SMOKE))
    assert isinstance(made, PlainLogger) and made.run_dir == tmp_path
    assert "plain (lines in RUN_DIR/plain.txt)" in loggers.logger_help()


def test_without_matplotlib_plots_are_skipped_with_a_warning(logged_run, tmp_path, caplog, monkeypatch):
    run_dir, _, _, _ = logged_run
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert evaluate.write_training_plot(run_dir) is None
    assert [r.levelname for r in caplog.records] == ["WARNING"] and "pip install 'ocv2[plots]'" in caplog.text
    from population.plots import xp_heatmap

    assert xp_heatmap(np.eye(2), tmp_path / "h.png") is None
    assert not (tmp_path / "h.png").exists()
