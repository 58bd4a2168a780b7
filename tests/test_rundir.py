"""The run directory without training: the lock, bad directories and manifests, stale temporaries,
torn metrics rows, checksummed checkpoints, the environment record, the key derivations, and the
import rules of ``cluster/runtime/``. (Resume, fallback and full-disk runs: tests/test_train_cli.py.)
"""

from __future__ import annotations

import ast
import json
import os
import re
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from cluster.cli import main
from cluster.runtime.environment import git_state
from cluster.runtime.rundir import DirLock, RunDir, RunDirError, write_json
from population import checkpoints as ckpt
from population.config import load_config
from population.keys import OFFSETS, derive_key

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "configs" / "smoke.yaml")


@pytest.fixture(scope="module")
def config():
    return load_config(SMOKE)


def test_a_second_opener_is_refused_naming_the_holder(tmp_path, config):
    first, resuming = RunDir.open(tmp_path / "run", config)
    assert not resuming
    with pytest.raises(RunDirError, match=rf"in use by another ocv2 process \(pid {os.getpid()}\)"):
        RunDir.open(tmp_path / "run", config, resume=True)
    first.close()  # (a killed holder releases it the same way: the kernel closes its file)
    second, resuming = RunDir.open(tmp_path / "run", config, resume=True)
    assert resuming
    second.close()


def test_a_run_dir_that_is_a_file_is_a_one_line_error(tmp_path, capsys):
    target = tmp_path / "run"
    target.write_text("not a directory")
    assert main(["train", SMOKE, "--out", str(target), "--quiet", "--backend", "local"]) == 2
    err = capsys.readouterr().err
    assert "is a file, not a run directory" in err and len(err.strip().splitlines()) == 1
    assert target.read_text() == "not a directory"
    assert main(["xp", str(target)]) == 2
    assert "is a file" in capsys.readouterr().err


@pytest.mark.parametrize("sub", ["run", "deeper/run"])
def test_out_below_a_file_names_the_file(tmp_path, config, capsys, sub):
    parent = tmp_path / "notes.txt"
    parent.write_text("x")
    with pytest.raises(RunDirError, match=rf"{parent} is a file, not a directory"):
        RunDir.open(parent / sub, config)
    assert main(["train", SMOKE, "--out", str(parent / sub), "--quiet", "--backend", "local"]) == 2
    err = capsys.readouterr().err
    assert f"{parent} is a file, not a directory" in err and "--resume" not in err
    assert len(err.strip().splitlines()) == 1
    assert parent.read_text() == "x"


@pytest.mark.parametrize("backend", ["local", "ray"])
def test_a_population_this_machine_cannot_hold_is_refused_before_any_file(tmp_path, capsys, backend):
    out = tmp_path / "run"
    assert (
        main(
            [
                "train",
                SMOKE,
                "--out",
                str(out),
                "--quiet",
                "--backend",
                backend,
                "--set",
                "population.num_seeds=1000000000",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "the run needs about" in err and "of memory on this machine" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_the_python_entry_point_refuses_it_too(tmp_path, config):
    import cluster
    from population.config import ConfigError, parse_config

    huge = parse_config(config.to_dict(), ["population.num_seeds=1000000000"])
    with pytest.raises(ConfigError, match="of memory on this machine"):
        cluster.train_population(huge, tmp_path / "run", backend="local", show_progress=False)
    assert not (tmp_path / "run").exists()


def test_a_refused_directory_is_left_as_it_was(tmp_path, config):
    (tmp_path / "stuff.txt").write_text("x")
    with pytest.raises(RunDirError, match="not an ocv2 run directory"):
        RunDir.open(tmp_path, config)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stuff.txt"]  # no .lock left behind
    with pytest.raises(RunDirError, match="nothing to resume"):
        RunDir.open(tmp_path / "missing", config, resume=True)
    assert not (tmp_path / "missing").exists()


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "is empty"),
        ('{"status": ', "is not valid JSON"),
        ("[1, 2]", "holds a JSON list, not an object"),
        ("[" * 100_000 + "]" * 100_000, "nested deeper than 32 levels"),
    ],
)
def test_an_empty_or_invalid_manifest_is_reported(tmp_path, config, capsys, text, message):
    run, _ = RunDir.open(tmp_path / "run", config)
    run.close()
    run.manifest_path.write_text(text)
    with pytest.raises(RunDirError, match=message) as error:
        RunDir.open(tmp_path / "run", config, resume=True)
    assert "manifest.json" in str(error.value)
    assert main(["xp", str(tmp_path / "run")]) == 2
    assert message in capsys.readouterr().err


def test_an_empty_config_yaml_in_a_run_is_damage_not_the_default_config(tmp_path, config, capsys):
    """An empty config.yaml read as the all-defaults config: export said "no checkpoint at update 457" and
    --resume listed 28 changed keys, where the file itself was the problem."""
    run, _ = RunDir.open(tmp_path / "run", config)
    run.close()
    run.config_path.write_text("\n")
    with pytest.raises(RunDirError, match=r"config.yaml: empty \(damaged\)"):
        RunDir.existing(tmp_path / "run").load_config()
    assert main(["export", str(tmp_path / "run"), "--out", str(tmp_path / "p.ocv2policy")]) == 2
    assert "config.yaml: empty (damaged)" in capsys.readouterr().err


def test_stale_temporaries_are_removed_when_a_run_is_opened(tmp_path, config, caplog):
    run, _ = RunDir.open(tmp_path / "run", config)
    run.close()
    stale = [
        run.path / ".manifest.tmp-123-abcdef01.json",
        run.path / "checkpoints" / "seed_0" / ".update_0000002.tmp-123-abcdef01.msgpack",
    ]
    for path in stale:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"half")
    keep = run.path / "checkpoints" / "seed_0" / "notes.txt"
    keep.write_text("mine")
    run, _ = RunDir.open(run.path, config, resume=True)
    run.close()
    assert not any(path.exists() for path in stale) and keep.exists()
    assert "interrupted write" in caplog.text


def test_torn_metrics_rows_are_dropped_and_the_file_repaired(tmp_path, caplog):
    run = RunDir(tmp_path)
    header = "seed,update,sparse_return"
    # an appending writer killed twice: once mid-row (then appended again), once mid-last-row
    damaged = f"{header}\n0,1,0.5\n0,2\n1,1,0.25\n1,2,0."
    (tmp_path / "metrics.csv").write_text(damaged)
    assert [(r["seed"], r["update"]) for r in run.read_metrics()] == [("0", "1"), ("1", "1")]
    # ocv2 rewrites metrics.csv atomically: a bad row before the last is damage, not a torn append
    assert "the file is damaged: line 3 (row 2) is not a complete metrics row (0,2)" in caplog.text
    assert "line 5 is incomplete (an interrupted write)" in caplog.text
    assert not any("line 3" in line and "interrupted" in line for line in caplog.text.splitlines())
    fields = header.split(",")
    # a resume refuses the damage, naming the line, and leaves the file as it was
    with pytest.raises(RunDirError, match=r"line 3 \(row 2\) is not a complete metrics row \(0,2\)"):
        run.metrics_to_resume(fields)
    assert (tmp_path / "metrics.csv").read_text() == damaged
    # a torn last row alone is what a kill leaves: reported; the resume drops it once its checks pass
    (tmp_path / "metrics.csv").write_text(f"{header}\n0,1,0.5\n1,1,0.25\n1,2,0.")
    caplog.clear()
    found = run.metrics_to_resume(fields)
    assert "line 4 is incomplete (an interrupted write)" in caplog.text
    assert [r["update"] for r in found.rows] == ["1", "1"]
    run.restart_metrics(fields, found.rows)
    caplog.clear()
    assert (tmp_path / "metrics.csv").read_text().splitlines() == [header, "0,1,0.5", "1,1,0.25"]
    run.append_metrics([{"seed": 0, "update": 2, "sparse_return": 1.0}, {"seed": 1, "update": 2, "sparse_return": ""}])
    assert [(r["seed"], r["update"]) for r in run.read_metrics()] == [("0", "1"), ("1", "1"), ("0", "2"), ("1", "2")]
    assert caplog.records == []


def test_a_resume_refuses_a_metrics_header_of_other_columns_naming_line_1(tmp_path):
    run = RunDir(tmp_path)
    text = "seed,update,sparse_return,lr\r\n0,1,0.5,0.1\r\n"
    (tmp_path / "metrics.csv").write_bytes(text.encode())
    with pytest.raises(RunDirError, match=r"line 1, the header, has columns \['lr'\] this run does not write"):
        run.metrics_to_resume(["seed", "update", "sparse_return"])
    assert (tmp_path / "metrics.csv").read_bytes() == text.encode()


def test_resumed_metrics_keep_the_runs_column_order_and_unchanged_files_are_not_rewritten(tmp_path):
    run = RunDir(tmp_path)
    fields = ["seed", "update", "sparse_return", "lr"]
    # rows restored from a checkpoint's meta come back with their keys sorted
    restored = [{"lr": 0.1, "seed": 0, "sparse_return": 0.5, "update": 1}]
    run.restart_metrics(fields, restored)
    assert (tmp_path / "metrics.csv").read_text().splitlines()[0] == "seed,update,sparse_return,lr"
    before = (tmp_path / "metrics.csv").stat().st_mtime_ns
    RunDir(tmp_path).restart_metrics(fields, RunDir(tmp_path).metrics_to_resume(fields).rows)
    assert (tmp_path / "metrics.csv").stat().st_mtime_ns == before  # the same bytes: not written again
    RunDir(tmp_path / "new").restart_metrics(fields, [])
    assert not (tmp_path / "new" / "metrics.csv").exists()  # nothing to write before the first chunk


def test_metrics_are_not_touched_by_a_write_that_fails(tmp_path, monkeypatch):
    run = RunDir(tmp_path)
    run.append_metrics([{"seed": 0, "update": 1, "loss": 0.5}])
    before = run.metrics_path.read_bytes()

    def full_disk(path):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr("ocv2.atomic._fsync_path", full_disk)
    with pytest.raises(OSError, match="No space left"):
        run.append_metrics([{"seed": 0, "update": 2, "loss": 0.25}])
    assert run.metrics_path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.csv"]  # the temporary is gone too


def test_a_damaged_checkpoint_fails_its_checksum(tmp_path):
    state = {"w": np.arange(64, dtype=np.float32), "step": np.int32(3)}
    path = ckpt.save(tmp_path / "update_0000001.msgpack", state, "fp", update=1)
    meta, raw = ckpt.read(path, "fp")
    assert meta["version"] == ckpt.FORMAT_VERSION
    np.testing.assert_array_equal(raw["w"], state["w"])
    data = bytearray(path.read_bytes())
    data[-20] ^= 0xFF  # one flipped bit pattern inside the array bytes: msgpack still parses it
    path.write_bytes(bytes(data))
    with pytest.raises(ckpt.CorruptCheckpointError, match="checksum mismatch"):
        ckpt.read(path, "fp")
    path.write_bytes(bytes(data[: len(data) // 2]))
    with pytest.raises(ckpt.CorruptCheckpointError, match="not a readable ocv2 checkpoint"):
        ckpt.read(path, "fp")


def test_a_checkpoint_moved_to_another_seed_or_update_is_refused_naming_both(tmp_path):
    """Its metadata says which seed and update it holds: a copy under another seed's folder or a renamed update would
    otherwise be exported, cross-played or resumed as that one without a word."""
    state = {"w": np.arange(4, dtype=np.float32)}
    written = ckpt.save(ckpt.checkpoint_path(tmp_path, 1, 4), state, "fp", seed=1, update=4)
    assert ckpt.read(written, "fp")[0]["seed"] == 1
    for seed, update, wrong in [(0, 4, "seed 1 (its place names 0)"), (1, 2, "update 4 (its place names 2)"),
                                (0, 2, "seed 1 (its place names 0) and update 4 (its place names 2)")]:  # fmt: skip
        moved = ckpt.checkpoint_path(tmp_path, seed, update)
        moved.parent.mkdir(parents=True, exist_ok=True)
        moved.write_bytes(written.read_bytes())
        with pytest.raises(ckpt.CheckpointError, match=re.escape(f"{moved}: holds {wrong}: a file copied")) as refused:
            ckpt.load(moved, state, "fp")
        assert type(refused.value) is ckpt.CheckpointError  # not damage, for which a resume takes an older one
        moved.unlink()
    elsewhere = ckpt.save(tmp_path / "kept.msgpack", state, "fp", seed=1, update=4)  # no place to compare with
    assert ckpt.read(elsewhere, "fp")[0]["update"] == 4
    (tmp_path / "7").mkdir()  # a folder that is no seed's: only the update is compared
    assert ckpt.read(ckpt.save(tmp_path / "7" / "update_0000004.msgpack", state, "fp", seed=1, update=4))[0]


def test_every_run_dir_records_versions_commit_devices_and_argv(tmp_path, config):
    run, _ = RunDir.open(tmp_path / "run", config)
    run.close()
    run, _ = RunDir.open(tmp_path / "run", config, resume=True)
    run.close()
    drivers = json.loads(run.environment_path.read_text())["drivers"]
    assert len(drivers) == 2  # the creating driver and the resuming one
    record = drivers[-1]
    assert {"python", "ocv2", "jax", "jaxlib", "flax", "optax", "numpy", "ray"} <= set(record["versions"])
    assert record["versions"]["jax"] == jax.__version__
    assert record["argv"] == sys.argv
    assert record["devices"] == [str(d) for d in jax.devices()]
    git = record["git"]
    assert git is None or (len(git["commit"]) == 40 and isinstance(git["dirty"], bool))
    assert git_state(tmp_path) is None  # not a checkout (nor the root of one)


def test_git_state_names_the_changed_files_so_a_reader_can_tell_edited_code_from_edited_docs(tmp_path):
    """ "+dirty" alone said a run's checkout had uncommitted changes, not whether they touched the training code."""
    import subprocess

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    git("config", "user.email", "t@example.org")
    git("config", "user.name", "t")
    not_utf8 = os.fsdecode(b"bad\xff.txt")
    for name in ("a.py", "b c.md", "old.txt", "README.md", "moved.py", not_utf8):
        (tmp_path / name).write_text("1\n")
    git("add", ".")
    git("commit", "-q", "-m", "first")
    clean = git_state(tmp_path)
    assert (clean["dirty"], clean["changed"], clean["changed_count"]) == (False, [], 0)
    (tmp_path / "b c.md").write_text("2\n")  # unstaged, a space in its name
    (tmp_path / "a.py").write_text("2\n")
    git("add", "a.py")  # staged
    git("mv", "old.txt", "new.txt")  # a staged rename: the new name only
    (tmp_path / "README.md").rename(tmp_path / "READ_ME.md")  # a rename in the work tree only, its old name
    git("add", "-N", "READ_ME.md")  # starting with R, as a status letter does
    (tmp_path / "moved.py").write_text("2\n")
    (tmp_path / not_utf8).write_text("2\n")  # a name that is not UTF-8: named with an escape, not an error
    (tmp_path / "untracked.py").write_text("")  # not tracked: not a change of the checkout's code
    state = git_state(tmp_path)
    assert state["changed"] == ["READ_ME.md", "a.py", "b c.md", "bad\\xff.txt", "moved.py", "new.txt"], state
    assert state["dirty"] and state["changed_count"] == 6


def test_every_key_is_the_derivation_results_were_made_with():
    """Stored runs and published numbers depend on these exact keys: the one function must keep them."""
    fold, root = jax.random.fold_in, jax.random.PRNGKey(7)
    same = lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    same(derive_key(7, "seed", 3), fold(root, 3))
    same(derive_key(7, "sa_restart", 1, member=3), fold(fold(root, 3), (1 << 20) + 1))
    same(derive_key(7, "sa", 1), fold(root, (1 << 20) + 1))
    same(derive_key(7, "xp"), fold(root, 1 << 21))
    same(derive_key(7, "gif", member=2), fold(fold(root, 1 << 22), 2))
    same(derive_key(7, "train_archive", 40, member=1), fold(fold(root, (1 << 23) + 40), 1))
    assert sorted(OFFSETS.values()) == [0, 1 << 20, 1 << 21, 1 << 22, 1 << 23]
    with pytest.raises(ValueError, match="unknown key purpose 'bogus'"):
        derive_key(7, "bogus")


RUNTIME = ROOT / "cluster" / "runtime"
PROJECT = ("ocv2", "population", "cluster")


def _project_imports(tree) -> list[tuple[str, int, bool]]:
    """(module, line, at module level?) of every project import in a parsed module."""
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module == "cluster.runtime":  # its submodules
            names = [f"cluster.runtime.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""]
        else:
            continue
        for name in names:
            if name.split(".")[0] in PROJECT:
                found.append((name, node.lineno, id(node) in top))
    return found


def test_runtime_imports_are_one_way_and_at_module_top():
    graph = {}
    for path in sorted(RUNTIME.glob("*.py")):
        imports = _project_imports(ast.parse(path.read_text()))
        local = [f"{path.name}:{line} {name}" for name, line, at_top in imports if not at_top]
        assert not local, f"function-local project imports: {local}"
        graph[f"cluster.runtime.{path.stem}"] = {name for name, _, _ in imports if name.startswith("cluster.runtime.")}

    def visit(module, trail):
        assert module not in trail, f"import cycle: {' -> '.join([*trail, module])}"
        for target in graph.get(module, ()):
            visit(target, [*trail, module])

    for module in graph:
        visit(module, [])


def test_xp_of_a_run_in_use_is_refused_naming_the_holder_not_asking_to_resume(tmp_path, config, capsys):
    """The trainer (or another ``ocv2 xp``) holds the lock: xp must not write xp/ beside it, and a run
    that is still training has no reason to be resumed."""
    holder, _ = RunDir.open(tmp_path / "run", config)
    try:
        assert main(["xp", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err
        assert f"in use by another ocv2 process (pid {os.getpid()})" in err and "--wait" in err
        assert "resume" not in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "run" / "xp").exists()
    finally:
        holder.close()


def test_xp_wait_blocks_until_the_holder_lets_go(tmp_path, config, capsys):
    import threading

    holder, _ = RunDir.open(tmp_path / "run", config)
    release = threading.Timer(0.5, holder.close)
    release.start()
    try:
        # no checkpoints in this run: once the lock is free, the evaluation says the run must be resumed
        assert main(["xp", str(tmp_path / "run"), "--wait"]) == 2
    finally:
        release.join()
    err = capsys.readouterr().err
    assert f"(pid {os.getpid()}); waiting for it to finish" in err
    assert "has not finished training" in err and "resume the run first" in err
    assert (tmp_path / "run" / ".lock").read_text() == f"{os.getpid()}\n"  # the pid, not a hole before it
    assert main(["xp", "--rows", str(tmp_path / "run"), "--wait"]) == 2  # --wait is for RUN_DIR


@pytest.mark.parametrize("kind", ["file", "under_a_file", "full_dir"])
def test_xp_out_that_exists_is_refused_before_any_work(tmp_path, capsys, kind):
    blocker = tmp_path / "results"
    if kind == "full_dir":
        blocker.mkdir()
        (blocker / "matrix.csv").write_text("earlier results")
        out = blocker
    else:
        blocker.write_text("earlier results")
        out = blocker if kind == "file" else blocker / "xp"
    # the source does not even exist: the --out check comes first, before loading any policy
    assert main(["xp", "--rows", str(tmp_path / "no_such_run"), "--backend", "local", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ocv2 xp: error: --out {out}: ") and len(err.strip().splitlines()) == 1
    assert {"file": "is a file", "under_a_file": "which is a file", "full_dir": "already holds files"}[kind] in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]
    assert (blocker / "matrix.csv" if kind == "full_dir" else blocker).read_text() == "earlier results"


def test_json_files_are_strict_json_with_null_for_undefined_numbers(tmp_path):
    def refuse(constant):
        raise ValueError(f"bare {constant} in a JSON file")

    data = {
        "sp_mean": np.float32(3.5),
        "gap_ci95_interval": [float("nan"), np.float64("inf")],
        "n": np.int64(2),
        "cells": np.array([1.0, np.nan]),
    }
    write_json(tmp_path / "summary.json", data)
    assert json.loads((tmp_path / "summary.json").read_text(), parse_constant=refuse) == {
        "sp_mean": 3.5,
        "gap_ci95_interval": [None, None],
        "n": 2,
        "cells": [1.0, None],
    }


def test_asking_whether_a_lock_is_held_writes_nothing(tmp_path):
    """``study status`` asked by taking the lock: it created .lock, wrote its own pid over the holder's, and in a
    directory it could not write reported a crashed step as running for ever."""
    assert not DirLock(tmp_path).held_elsewhere() and not (tmp_path / ".lock").exists()
    holder = DirLock(tmp_path)
    holder.acquire()
    written = (tmp_path / ".lock").read_bytes()
    (tmp_path / ".lock").write_bytes(b"4242\n")  # as if another process held it
    tmp_path.chmod(0o555)
    (tmp_path / ".lock").chmod(0o444)
    try:
        asker = DirLock(tmp_path)  # another open file description: flock tells the two apart
        assert asker.held_elsewhere()
        assert (tmp_path / ".lock").read_bytes() == b"4242\n"
        holder.release()
        assert not asker.held_elsewhere()  # read-only and free: not "running"
        assert (tmp_path / ".lock").read_bytes() == b"4242\n"
    finally:
        tmp_path.chmod(0o755)
        (tmp_path / ".lock").chmod(0o644)
    assert written == f"{os.getpid()}\n".encode()
