"""The ``ocv2`` command line, called in-process through ``cluster.cli.main``."""

from __future__ import annotations

import argparse
import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from cluster.cli import main
from cluster.cli.main import COMMANDS, build_parser, version
from ocv2 import LAYOUTS


def test_layouts_lists_every_layout(capsys):
    assert main(["layouts"]) == 0
    out = capsys.readouterr().out
    assert len(LAYOUTS) == 24
    for name in LAYOUTS:
        assert name in out
    lines = {line.split()[1]: line for line in out.splitlines() if len(line.split()) > 1}
    row = lines["cramped_room_v2"]
    assert "4x5" in row and "[0, 0, 1]" in row
    assert "[0, 0, 2], [1, 1, 3]" in lines["fun_coordination"]


def test_layouts_show(capsys):
    assert main(["layouts", "--show", "cramped_room"]) == 0
    out = capsys.readouterr().out
    assert LAYOUTS["cramped_room"].to_string() in out


def test_layouts_show_unknown(capsys):
    assert main(["layouts", "--show", "no_such_kitchen"]) == 2
    captured = capsys.readouterr()
    assert "unknown layout 'no_such_kitchen'" in captured.err and "Traceback" not in captured.err


def test_render_writes_gif(tmp_path, capsys):
    out = tmp_path / "ep.gif"
    code = main(
        [
            "render",
            "cramped_room",
            "--steps",
            "3",
            "--out",
            str(out),
            "--seed",
            "1",
            "--fps",
            "4",
            "--tile-size",
            "8",
            "--view-radius",
            "1",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "4 frames" in printed
    with Image.open(out) as im:
        assert im.size == (5 * 8, 4 * 8)
        assert im.n_frames == 4 and im.info["loop"] == 0 and im.info["duration"] == 250


def test_render_unknown_layout(tmp_path, capsys):
    out = tmp_path / "x.gif"
    assert main(["render", "cramped_rom", "--steps", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "unknown layout 'cramped_rom'" in err and "cramped_room" in err and "Traceback" not in err
    assert not out.exists()


def test_usage_errors_return_2(tmp_path, capsys):
    assert main([]) == 2
    assert main(["render", "cramped_room", "--steps", "2"]) == 2  # --out missing
    assert main(["render", "cramped_room", "--out", str(tmp_path / "x.gif"), "--fps", "0"]) == 2
    assert main(["render", "cramped_room", "--out", str(tmp_path / "x.txt")]) == 2
    assert main(["render", "cramped_room", "--out", str(tmp_path / "x.gif"), "--seed", str(2**32)]) == 2  # would wrap
    assert main(["render", "cramped_room", "--out", str(tmp_path / "x.gif"), "--view-radius", "99999999999"]) == 2
    assert "argument --view-radius: expected a non-negative integer below 2**31" in capsys.readouterr().err
    assert main(["archive", "info", str(tmp_path / "x.mcap"), "--limit", "-5"]) == 2  # -1 is "all"; -5 means nothing
    assert main(["human", "proxy", "cramped_room", "--source", str(tmp_path), "--lr", "-1"]) == 2  # the flag named
    assert "argument --lr: expected a learning rate in (0, 1], got -1" in capsys.readouterr().err
    assert main(["--help"]) == 0
    capsys.readouterr()
    assert os.listdir(tmp_path) == []


def test_a_symbolic_link_loop_is_named_by_every_command_that_resolves_a_path(tmp_path, capsys, monkeypatch):
    """``Path.resolve`` raises a RuntimeError on a link loop (Python 3.11-3.12): xp, report, export, train and the
    study commands once ended in its traceback."""
    monkeypatch.chdir(tmp_path)
    Path("a").symlink_to("b")
    Path("b").symlink_to("a")
    for argv in (
        ["xp", "--rows", "a"],
        ["xp", "--rows", str(tmp_path), "--out", "a"],
        ["report", "a", "--out", "r"],
        ["export", "missing", "--out", "a/x.ocv2policy"],
        ["train", "configs/smoke.yaml", "--out", "a/run"],
        ["study", "run", "a"],
        ["study", "pack", "a", "--out", "packed"],
        ["study", "unpack", "a", "--out", "unpacked"],
        ["study", "publish", "a", "--out", "policies"],
        ["study", "report", "a"],
        ["render", "cramped_room", "--out", "a/x.gif"],
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "its symbolic links cannot be followed" in err and "Traceback" not in err, (argv, err)
    assert sorted(os.listdir(tmp_path)) == ["a", "b"]


def test_render_creates_missing_output_folder(tmp_path):
    """README's main job writes runs/demo.gif on a fresh clone, where runs/ does not exist yet."""
    out = tmp_path / "runs" / "nested" / "demo.gif"
    assert main(["render", "cramped_room", "--steps", "3", "--out", str(out)]) == 0
    assert out.exists()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["render", "cramped_room", "--steps", "3", "--out", str(blocker / "demo.gif")]) == 2


def test_render_never_replaces_a_file_unless_forced(tmp_path, capsys):
    out = tmp_path / "kept.gif"
    out.write_text("precious")
    assert main(["render", "cramped_room", "--steps", "2", "--out", str(out)]) == 2
    assert "exists; pass --force to replace it" in capsys.readouterr().err and out.read_text() == "precious"
    assert main(["render", "cramped_room", "--steps", "2", "--out", str(out), "--force"]) == 0
    assert out.read_bytes()[:3] == b"GIF"


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "configs/smoke.yaml"],
        ["xp", "--rows", "x"],
        ["report", "x"],
        ["study", "pack", "x"],
        ["render", "cramped_room"],
    ],
)
def test_an_empty_out_is_refused_rather_than_falling_back_to_the_default(argv, capsys):
    """`--out "$OUT"` with OUT unset once trained into runs/<layout>_<method>_<time> without a word."""
    assert main([*argv, "--out", ""]) == 2
    assert "--out: an empty path (an unset variable?)" in capsys.readouterr().err


def test_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"ocv2 {version()}"
    assert version()[0].isdigit()  # the test environment has the package installed


def test_layouts_show_has_a_legend_of_the_characters_used(capsys):
    assert main(["layouts", "--show", "grounded_coord_ring"]) == 0
    legend_lines = capsys.readouterr().out.split("legend:\n", 1)[1].splitlines()
    meanings = {line.split()[0]: line.split(None, 1)[1] for line in legend_lines}
    assert meanings["W"] == "counter" and meanings["L"] == "button recipe indicator"
    assert meanings["(space)"] == "floor" and meanings["2"] == "pile of ingredient 2"
    assert "O" not in meanings and "3" not in meanings  # only what the map uses
    for char in set(LAYOUTS["grounded_coord_ring"].to_string()) - {" ", "\n"}:
        assert char in meanings


def test_render_refuses_an_episode_too_big_for_memory(tmp_path, capsys):
    out = tmp_path / "huge.gif"
    assert main(["render", "cramped_room", "--steps", "2000000000", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--steps 2000000000" in err and "GiB" in err and len(err.strip().splitlines()) == 1
    assert main(["render", "cramped_room", "--steps", "10000000000", "--out", str(out)]) == 2  # past int32 at once
    assert "argument --steps: expected a non-negative integer below 2**31" in capsys.readouterr().err
    assert not out.exists()


def test_command_help_in_the_table_matches_each_command_parser():
    """``ocv2 --help`` lists the table's one-liners without importing the command modules."""
    full = build_parser(full=True)
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    assert {action.dest: action.help for action in sub._choices_actions} == {c.name: c.help for c in COMMANDS}


def _python(code: str) -> subprocess.CompletedProcess:
    """``code`` run by a fresh interpreter that imports this checkout (its output captured; a failure raises)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)


def test_layouts_does_not_import_the_trainer():
    code = (
        "import sys; from cluster.cli import main; main(['layouts']); "
        "print(sorted(m for m in ('cluster.api', 'cluster.runtime.coordinator', 'optax', 'ray', 'population.ppo') if m in sys.modules))"
    )
    out = _python(code).stdout
    assert out.strip().splitlines()[-1] == "[]"


def test_import_ocv2_loads_no_learning_code():
    code = "import sys, ocv2; print(sorted(m for m in ('optax', 'population') if m in sys.modules))"
    out = _python(code).stdout
    assert out.strip().splitlines()[-1] == "[]"


def _imports(path: Path):
    """(module imported, whether inside a function) for every import statement of a source file."""
    tree = ast.parse(path.read_text())
    local = {
        id(node)
        for fn in ast.walk(tree)
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
        for node in ast.walk(fn)
        if isinstance(node, (ast.Import, ast.ImportFrom))
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from ((alias.name, id(node) in local) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module, id(node) in local


def test_imports_point_down_and_the_cli_imports_at_module_top():
    """ocv2 <- population <- cluster; nothing imports cluster.cli; cluster/cli imports project code at the top."""
    root = Path(__file__).resolve().parents[1]
    forbidden = {"ocv2": ("population", "cluster"), "population": ("cluster",), "cluster": ("cluster.cli",)}
    problems = []
    for package, banned in forbidden.items():
        for path in (root / package).rglob("*.py"):
            inside_cli = path.is_relative_to(root / "cluster" / "cli")
            for module, in_function in _imports(path):
                if any(module == b or module.startswith(b + ".") for b in banned) and not inside_cli:
                    problems.append(f"{path.relative_to(root)} imports {module}")
                project = module.split(".")[0] in ("ocv2", "population", "cluster")
                if inside_cli and in_function and project:
                    problems.append(f"{path.relative_to(root)} imports {module} inside a function")
    assert problems == []


def test_no_module_imports_private_names_from_another():
    """The commands share helpers through a module of their own (cluster/cli/args.py), never as ``_name``."""
    root = Path(__file__).resolve().parents[1]
    problems = []
    for package in ("cluster",):
        for path in (root / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if (
                    isinstance(node, ast.ImportFrom)
                    and node.module
                    and node.module.split(".")[0] in ("ocv2", "population", "cluster")
                ):
                    problems += [
                        f"{path.relative_to(root)}: {alias.name} from {node.module}"
                        for alias in node.names
                        if alias.name.startswith("_") and not alias.name.startswith("__")
                    ]
    assert problems == []


def test_button_game_without_matplotlib_writes_the_numbers(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as when the plots extra is not installed
    out = tmp_path / "bg"
    assert main(["button-game", "--seeds", "2", "--out", str(out), "--buttons", "2", "--episodes", "20"]) == 0
    captured = capsys.readouterr()
    assert "pip install 'ocv2[plots]'" in captured.err and "button_game_xp.png" not in captured.out
    assert os.listdir(out) == ["button_game_xp.csv"]


def test_commands_import_without_the_ray_extra():
    # Ray is an extra: --backend local, ocv2 xp --backend local and play must not need it to import,
    # and asking for Ray without it is one line naming the extra.
    code = (
        "import sys; sys.modules['ray'] = None\n"
        "import cluster.api, cluster.cli.train, cluster.cli.xp, cluster.cli.play\n"
        "from cluster.runtime.ray_backend import RayBackendError, connect\n"
        "from population.config import ClusterConfig\n"
        "try:\n"
        "    connect(ClusterConfig())\n"
        "except RayBackendError as error:\n"
        "    print(error)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "Ray is not installed: pip install 'ocv2[ray]', or use --backend local"


def test_comments_say_why_instead_of_citing_spec_sections_or_issues():
    """A reader of the code has neither the project's spec nor its issue tracker: say the reason."""
    import re

    root = Path(__file__).resolve().parents[1]
    pattern = re.compile(r"spec sections?\b|\bspec \d|\bthe issue\b|\bissues? #?\d", re.IGNORECASE)
    hits = [
        f"{path.relative_to(root)}:{number}"
        for package in ("ocv2", "population", "cluster", "tests", "bench")
        for path in (root / package).rglob("*.py")
        if path.name != "test_cli.py"
        for number, line in enumerate(path.read_text().splitlines(), start=1)
        if pattern.search(line)
    ]
    assert hits == []


def test_library_code_never_prints():
    """Only the command line writes to stdout/stderr itself; the packages log through module loggers."""
    root = Path(__file__).resolve().parents[1]
    problems = []
    for package in ("ocv2", "population", "cluster"):
        for path in (root / package).rglob("*.py"):
            if path.is_relative_to(root / "cluster" / "cli"):
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                    problems.append(f"{path.relative_to(root)}:{node.lineno}")
    assert problems == []


def _log_at_every_level():
    import logging

    for level in (logging.DEBUG, logging.INFO, logging.WARNING):
        logging.getLogger("cluster.runtime.progress").log(level, "message at %s", logging.getLevelName(level))


@pytest.fixture
def log_levels():
    """The package loggers' levels as they were before the test (main() sets them for the process)."""
    import logging

    from cluster.cli.main import PACKAGE_LOGGERS

    levels = {name: logging.getLogger(name).level for name in PACKAGE_LOGGERS}
    yield
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)


@pytest.mark.parametrize(
    "flags, shown", [([], ["INFO", "WARNING"]), (["-q"], ["WARNING"]), (["-v"], ["DEBUG", "INFO", "WARNING"])]
)
def test_global_verbosity_flags_set_what_the_packages_log_to_stderr(capsys, log_levels, flags, shown):
    assert main([*flags, "layouts"]) == 0
    capsys.readouterr()
    _log_at_every_level()
    captured = capsys.readouterr()
    assert captured.out == ""
    assert [line.rsplit(" ", 1)[-1] for line in captured.err.splitlines()] == shown
    assert "warning: message at WARNING" in captured.err.splitlines()


def test_each_log_line_is_written_once_even_after_a_library_configures_logging():
    # optax logs through absl, which calls logging.basicConfig() when the root logger has no handler: a
    # second handler there would repeat every line of ours in its own format.
    code = (
        "import logging, optax\n"
        "from cluster.cli import main\n"
        "main(['layouts'])\n"
        "optax.polynomial_schedule(1.0, 0.0, 1, transition_steps=0)\n"
        "logging.getLogger('cluster.runtime.progress').info('progress line')\n"
        "logging.getLogger('some.library').info('library detail')\n"
        "logging.getLogger('some.library').warning('library warning')\n"
    )
    err = _python(code).stderr
    assert err.splitlines() == ["progress line", "warning: library warning"]


def test_global_q_turns_the_command_quiet_on_and_contradicting_flags_are_refused(capsys):
    parser = build_parser(["train"])
    args = parser.parse_args(["-q", "train", "c.yaml"])
    assert args.log_quiet and not args.quiet  # main() turns the command's --quiet on from -q
    assert main(["-v", "-q", "layouts"]) == 2
    assert "contradict" in capsys.readouterr().err


def test_durations_round_as_the_results_page_writes_them():
    """report.md said 14h58m for 53,930 s (14 h 58.8 min), where docs/RESULTS.md says 14 h 59 min."""
    from cluster.runtime.progress import duration

    times = (53_930, 3_599.6, 7_199.9, 246.5, 247.5, 59.4, 3_630, 3_689.5)  # halves go up, each from the time itself
    assert [duration(s) for s in times] == ["14h59m", "1h00m", "2h00m", "4m07s", "4m08s", "0m59s", "1h01m", "1h01m"]
    assert duration(None) == duration(float("nan")) == "?"


def test_the_progress_header_counts_env_steps_per_seed(caplog):
    import logging

    from cluster.runtime.progress import PopulationProgress

    caplog.set_level(logging.INFO, logger="cluster")
    with PopulationProgress("SP cramped_room", num_seeds=3, total_updates=10, steps_per_update=128):
        pass
    assert caplog.messages == ["SP cramped_room: 3 seeds x 10 updates x 128 = 1,280 env steps per seed"]


def _record_ray_first(monkeypatch, events):
    """``ray_backend.connect`` records itself (and starts nothing): what a command does before it."""
    from cluster.runtime import ray_backend

    def connect(cluster):
        events.append("ray")
        return False

    monkeypatch.setattr(ray_backend, "connect", connect)


@pytest.mark.parametrize("backend, expected", [("ray", ["ray", "load"]), ("local", ["load"])])
def test_xp_starts_ray_before_loading_policies_starts_jax(monkeypatch, tmp_path, backend, expected):
    # Ray forks its processes; once JAX runs in this process that fork draws JAX's deadlock warning.
    from cluster.runtime import crossplay

    events = []
    _record_ray_first(monkeypatch, events)

    def resolve_source(source, checkpoint):
        events.append("load")
        raise crossplay.CrossPlayError(f"{source}: stop here")

    monkeypatch.setattr(crossplay, "resolve_source", resolve_source)
    args = ["xp", "--rows", "somewhere", "--out", str(tmp_path / "xp"), "--backend", backend]
    assert main(args) == 2
    assert events == expected


@pytest.mark.parametrize("command", ["train", "study"])
def test_train_and_study_start_ray_once_before_any_work(monkeypatch, tmp_path, command):
    import cluster.cli.study as study_cli
    import cluster.cli.train as train_cli

    events = []
    _record_ray_first(monkeypatch, events)
    monkeypatch.setattr(train_cli, "train_population", lambda *a, **k: events.append("work") or {"run_dir": "r"})
    from cluster.study.state import StudyState

    done = StudyState(study="s", spec={}, report={"report": "r"})

    def run_study(*args, session, **kwargs):
        with session(True):  # as run_study enters it under the directory's lock, before any step runs
            events.append("work")
        return done

    monkeypatch.setattr(study_cli, "run_study", run_study)
    root = Path(__file__).resolve().parents[1] / "configs"
    argv = {
        "train": ["train", str(root / "quickstart.yaml")],
        "study": ["study", "run", str(root / "studies" / "table1_coord_ring.yaml")],
    }[command]
    assert main([*argv, "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert events == ["ray", "work"]


def test_a_dead_worker_in_a_study_says_to_rerun_the_study_not_ocv2_train(monkeypatch, tmp_path, capsys):
    """A study's run trains with the study's budget and overrides: `ocv2 train CONFIG --resume` would not match its
    fingerprint, so the study command names itself as the way to continue."""
    import pickle

    import cluster.cli.study as study_cli
    from cluster.runtime.ray_backend import TRAIN_RESUME_HINT, RayBackendError

    error = RayBackendError("worker for seeds [0] died and cannot be restarted. Its checkpoints ...", resumable=True)
    assert str(error).endswith(f"; {TRAIN_RESUME_HINT}")  # what `ocv2 train` prints
    assert str(pickle.loads(pickle.dumps(error))) == str(error)  # as Ray sends it between processes

    def dead_worker(*args, **kwargs):
        raise error

    monkeypatch.setattr(study_cli, "run_study", dead_worker)
    study = Path(__file__).resolve().parents[1] / "configs" / "studies" / "table1_coord_ring.yaml"
    assert main(["study", "run", str(study), "--backend", "local", "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "continue with the same `ocv2 study run` command" in err and "ocv2 train" not in err, err


def test_the_eta_is_measured_after_the_first_chunk_which_compiled(caplog, monkeypatch):
    """The first chunk of a resumed SA run (compiling, collecting states) took three times a later one's time, and
    the ETA it gave (12 h for 4 h) counted it; the ETA now starts at the end of that chunk."""
    import logging
    from types import SimpleNamespace

    from cluster.runtime import progress

    clock = iter([0.0, 1000.0, 1100.0, 1200.0])  # a 1,000 s first chunk, then 100 s chunks
    monkeypatch.setattr(progress, "time", SimpleNamespace(perf_counter=lambda: next(clock)))
    monkeypatch.setattr(progress, "_bar", lambda *columns: None)  # the log lines, even on a terminal (pytest -s)
    rows = [{"seed": 0, "sparse_return": "10.0", "shaped_return": "2.0"}]
    caplog.set_level(logging.INFO, logger="cluster")
    with progress.PopulationProgress("SA asymm", num_seeds=1, total_updates=40, steps_per_update=100) as bar:
        bar.advance_to(10, None)  # where a resume starts
        for update, steps_per_s in ((20, 1.0), (30, 10.0), (40, 10.0)):
            bar.advance_to(update, rows, steps_per_s)
    assert caplog.messages[1:] == [
        "  update 20/40  1 env steps/s (first chunk, with start-up)  return 10.0+-0.0  shaped 2.0+-0.0  ETA after the "
        "next chunk (this one started up)",
        "  update 30/40  10 env steps/s  return 10.0+-0.0  shaped 2.0+-0.0  ETA 1m40s",
        "  update 40/40  10 env steps/s  return 10.0+-0.0  shaped 2.0+-0.0  ETA 0m00s",
    ]
