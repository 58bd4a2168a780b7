"""Studies (``ocv2 study``): two tiny runs on the local backend, one uninterrupted study and one killed
mid-run and resumed; both must report the same numbers, and a finished run is never trained again."""

from __future__ import annotations

import contextlib
import copy
import csv
import dataclasses
import errno
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
import yaml

import ocv2.atomic
from cluster.cli import main
from cluster.runtime import crossplay
from cluster.runtime.environment import CHANGED_NAMED
from cluster.runtime.extend import EVALUATION_DIRS, take_eval_episodes
from cluster.runtime.rundir import DirLock, RunDir, read_matrix_csv
from cluster.runtime.runstate import Schedule
from cluster.study import report
from cluster.study.pack import pack_study, snapshots_still_read
from cluster.study.publish import publish_study
from cluster.study.runner import (
    STEP_KINDS,
    StateFile,
    Step,
    StudyOptions,
    _set_aside_results,
    continue_hint,
    kept_study,
    open_state,
    plan_study,
    read_state,
    result_problem,
    run_study,
    steps_to_run,
    study_status,
)
from cluster.study.spec import StudyError, budget_overrides, load_study, run_config, with_overrides
from cluster.study.state import StepRecord, StudyState
from population import checkpoints as ckpt
from population import policy, ppo, published
from population.config import ConfigError, load_config
from population.xp import bootstrap_difference

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
TIMING_COLUMNS = {"steps_per_s", "wall_s"}
LOCAL = StudyOptions(backend="local")

STUDY = {
    "study": "tiny",
    "description": "two tiny runs",
    "set": ["eval.episodes=2", "eval.gifs=0", "archive.xp=false", "archive.sa_collection=false"],
    "runs": [
        {
            "name": "sp",
            "config": str(SMOKE),
            "set": ["population.method=sp"],
            "paper": {"source": "Table 9, a made-up row", "sp": [123, 4], "xp": 56, "gap": [67, 8]},
        },
        {"name": "sa", "config": str(SMOKE), "set": ["population.method=sa", "ppo.total_timesteps=1024"]},
    ],
    "over_training": ["sp"],
    "comparisons": [{"name": "sp_vs_sa", "runs": ["sp", "sa"]}],
}


def write_study(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """An uninterrupted study (never modified by the tests)."""
    base = tmp_path_factory.mktemp("study")
    study = load_study(write_study(base / "tiny.yaml", STUDY))
    state = run_study(study, base / "out", StudyOptions(backend="local", show_progress=False), say=lambda _: None)
    assert all(step.done for step in state.steps.values())
    return base / "out"


def read_csv(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def numbers(out: Path) -> dict:
    """What a study reports, without wall times and dates."""
    summary = json.loads((out / "summary.json").read_text())
    return {
        "runs": [
            {k: r[k] for k in ("name", "xp", "paper", "fingerprint", "seeds", "env_steps_per_seed")}
            for r in summary["runs"]
        ],
        "comparisons": [{k: c.get(k) for k in ("name", "pairs", "blocks")} for c in summary["comparisons"]],
        "over_training": summary["over_training"],
    }


def _seed_update(row: dict) -> tuple[int, int]:
    """A metrics row's place (a resumed or extended run appends its rows chunk by chunk)."""
    return int(row["seed"]), int(row["update"])


def assert_same_runs(out: Path, reference: Path) -> None:
    for name, seeds, updates in (("sp", 2, 4), ("sa", 2, 8)):
        for seed in range(seeds):  # whole TrainStates, bit for bit
            mine = ckpt.read(ckpt.checkpoint_path(out / "runs" / name, seed, updates))[1]
            theirs = ckpt.read(ckpt.checkpoint_path(reference / "runs" / name, seed, updates))[1]
            for x, y in zip(jax.tree.leaves(mine), jax.tree.leaves(theirs), strict=True):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        rows = sorted(read_csv(out / "runs" / name / "metrics.csv"), key=_seed_update)
        reference_rows = sorted(read_csv(reference / "runs" / name / "metrics.csv"), key=_seed_update)
        assert len(rows) == len(reference_rows) == seeds * updates
        for row, other in zip(rows, reference_rows):
            assert {k: v for k, v in row.items() if k not in TIMING_COLUMNS} == {
                k: v for k, v in other.items() if k not in TIMING_COLUMNS
            }


#: The tiny study's report.md and summary.json as the code wrote them before the study runner was
#: rewritten in plain steps (``normalized_report``): a refactor must not change a byte of either.
GOLDEN = Path(__file__).parent / "data" / "study_golden"
# the time, wall times, and the commits and versions of whoever ran it
_UNSTABLE_KEYS = ("written", "wall_s", "commits", "versions")


def normalized_report(out: Path, study_folder: Path, root: Path = ROOT) -> dict[str, str]:
    """report.md and summary.json of study directory ``out`` without what two runs of the same study
    never share: when it was written, wall times, the commits that trained it, and where the study file
    (``study_folder``) and this repository (``root``) lie."""

    def drop(value):
        if isinstance(value, dict):
            return {k: drop(v) for k, v in value.items() if k not in _UNSTABLE_KEYS}
        return [drop(v) for v in value] if isinstance(value, list) else value

    summary = json.dumps(drop(json.loads((out / "summary.json").read_text())), indent=2) + "\n"
    report = (out / "report.md").read_text()
    for pattern, replacement in (
        (r"wall time: [^;\n]+", "wall time: -"),
        (r"wall [0-9hms]+,", "wall -,"),
        (r"written \S+", "written -"),
        (r"commits [^\n]*", "commits -"),
    ):
        report = re.sub(pattern, replacement, report)
    texts = {"report.md": report, "summary.json": summary}
    for place, name in ((str(study_folder), "<study>"), (str(root), "<repo>")):
        texts = {k: v.replace(place, name) for k, v in texts.items()}
    return texts


def test_the_report_is_byte_for_byte_what_the_code_wrote_before_its_refactor(finished):
    texts = normalized_report(finished, finished.parent)
    for name, text in texts.items():
        assert text == (GOLDEN / name).read_text(), name


def test_the_report_names_the_versions_and_changed_files_each_run_was_trained_with(finished):
    """A reader of a published report could not tell which jax made its numbers, nor what "+dirty" covered."""
    runs = json.loads((finished / "summary.json").read_text())["runs"]
    for run in runs:
        assert [v["jax"] for v in run["versions"]] == [jax.__version__]
        assert run["versions"][0]["jaxlib"] == importlib.metadata.version("jaxlib")
        driver = json.loads((finished / "runs" / run["name"] / "environment.json").read_text())["drivers"][0]
        if driver["git"] is not None:  # a checkout: its changed files are named, not only "+dirty"
            assert len(driver["git"]["changed"]) == min(driver["git"]["changed_count"], CHANGED_NAMED)
    lines = [line for line in (finished / "report.md").read_text().splitlines() if line.startswith("- `")]
    assert len(lines) == 2 and all(line.endswith(f"; jax {jax.__version__}") for line in lines), lines


def _header(study, state) -> str:
    """report.md's budget line for ``study`` and the directory ``state`` (nothing trained)."""
    summary = {"budget": state.budget, "budget_mode": state.budget_mode, "seeds": state.seeds, "backend": "local"}
    summary |= {"wall_s": 0, "set": list(state.overrides), "ci_method": "-", "written": "-", "pictures": []}
    summary |= {"runs": [], "comparisons": [], "over_training": []}
    experiment = report.as_written(study, Path("studies") / study.name, state)
    text = report.markdown(study, summary, state, experiment=experiment)
    return next(line for line in text.splitlines() if line.startswith("- study file:"))


def test_the_report_calls_a_study_the_papers_experiment_only_when_it_runs_the_paper_configs_as_written(tmp_path):
    """Every study at budget 1 was "the paper's experiment", though its file, --set or --seeds had cut the
    steps, the network, the episodes or the seeds."""
    gpu = load_study(ROOT / "configs" / "studies" / "gpu_coord_ring_sp.yaml")
    state = StudyState(study=gpu.name, spec={}, budget=1.0, budget_mode="truncate")
    assert _header(gpu, state).endswith("(the paper's experiment)")
    # run.* cadence, archive and cluster keys, and --seeds of the config's own count, change no experiment
    same = with_overrides(gpu, ["run.checkpoint_every=3", "run.deterministic=false", "archive.xp=true"])
    assert _header(same, dataclasses.replace(state, seeds=10)).endswith("(the paper's experiment)")
    for overrides, seeds, change in (
        ([], 2, "`population.num_seeds=2`"),
        (["eval.episodes=8"], None, "`eval.episodes=8`"),
        (["ppo.total_timesteps=4000000"], None, "`ppo.total_timesteps=4000000`"),
        (["model.conv_features=[8,8,8]"], None, "`model.conv_features=[8, 8, 8]`"),
    ):
        line = _header(with_overrides(gpu, overrides), dataclasses.replace(state, seeds=seeds))
        assert line.endswith(
            f"(**reduced or changed: not the paper's experiment**; the study changes its configs: {change})"
        ), line
    # A reduced budget says so as before, and what else the study changed.
    line = _header(with_overrides(gpu, ["eval.episodes=8"]), dataclasses.replace(state, budget=0.3))
    assert "(**reduced: not the paper's experiment**; each config's schedule as written, stopped after" in line
    assert line.endswith("; the study changes its configs: `eval.episodes=8`)")
    # A config of one's own, as written, is not the paper's either.
    own = {"study": "own", "runs": [{"name": "sp", "config": str(SMOKE)}]}
    assert _header(load_study(write_study(tmp_path / "own.yaml", own)), state).endswith("(the configs as written)")


def test_the_report_puts_the_paper_numbers_beside_ours(finished):
    report = (finished / "report.md").read_text()
    assert "Table 9, a made-up row" in report
    assert "123 ± 4" in report and "| 56" in report and "67 ± 8" in report
    assert "; wall time: " in report and "Not finished" not in report  # not "so far": every step is done
    assert "| 2 x 512 |" in report and "| 2 x 1,024 |" in report  # small step counts exactly, not "0.00M"
    assert "| 256 | " in report  # the over-training snapshot at update 2
    summary = json.loads((finished / "summary.json").read_text())
    assert (
        summary["budget_mode"] == "truncate"
        and "budget: **1 x** the configs' env steps (**reduced or changed" in report
    )
    sp = summary["runs"][0]
    assert sp["paper"]["sp"] == {"mean": 123.0, "std": 4.0} and sp["paper"]["xp"] == {"mean": 56.0, "std": None}
    assert sp["xp"]["sp_ci95_interval"] and sp["xp"]["num_policies"] == 2
    pair = summary["comparisons"][0]["pairs"][0]
    assert (pair["a"].endswith("sp"), pair["b"].endswith("sa")) == (True, True)
    assert {"a_seat0", "a_seat1", "mean", "mean_ci95_interval"} <= set(pair)
    assert [p["update"] for p in summary["over_training"][0]["points"]] == [0, 2, 4]
    for picture in (
        "curves_cramped_room.png",
        "heatmap_sp.png",
        "heatmap_sa.png",
        "heatmap_sp_vs_sa.png",
        "over_training_sp.png",
    ):
        assert (finished / picture).is_file()
    json.loads((finished / "summary.json").read_text(), parse_constant=lambda c: pytest.fail(f"bare {c}"))


def test_a_method_is_compared_with_the_self_play_run_of_its_environment(finished):
    summary = json.loads((finished / "summary.json").read_text())
    (entry,) = summary["against_sp"]  # sa against sp; sp is the baseline, not compared with itself
    runs = {r["name"]: r["xp"] for r in summary["runs"]}
    assert (entry["run"], entry["sp_run"]) == ("sa", "sp")
    assert entry["delta_gap"] == pytest.approx(runs["sa"]["gap"] - runs["sp"]["gap"])
    assert entry["delta_sp"] == pytest.approx(runs["sa"]["sp_mean"] - runs["sp"]["sp_mean"])
    matrices = [read_matrix_csv(finished / "runs" / name / "xp" / "matrix.csv").values for name in ("sp", "sa")]
    assert entry["delta_gap_ci95_interval"] == pytest.approx(list(bootstrap_difference(*matrices)["gap"]))
    assert entry["paper_delta_gap"] is None  # only sp carries the paper's numbers
    assert "## Against self-play" in (finished / "report.md").read_text()


def test_a_comparison_with_self_play_that_cannot_be_made_says_why(finished, tmp_path):
    out = _copy(finished, tmp_path / "study")
    matrix = out / "runs" / "sa" / "xp" / "matrix.csv"
    header, first, *rest = matrix.read_text().splitlines()
    matrix.write_text("\n".join([header, first.rsplit(",", 1)[0] + ",", *rest]) + "\n")  # a cell left empty
    assert main(["study", "report", str(out)]) == 0
    (entry,) = json.loads((out / "summary.json").read_text())["against_sp"]
    assert entry["problem"] == "no interval: sa's: 1 cell(s) are not numbers"
    assert entry["delta_gap_ci95_interval"] == [None, None] and entry["delta_gap"] is not None
    assert "(no interval: sa's: 1 cell(s) are not numbers)" in (out / "report.md").read_text()
    (out / "runs" / "sp" / "xp" / "summary.json").write_text(json.dumps({"study": "tiny"}))  # SP's result foreign
    assert main(["study", "report", str(out)]) == 0
    (entry,) = json.loads((out / "summary.json").read_text())["against_sp"]
    assert entry == {"run": "sa", "sp_run": "sp", "problem": "self-play run sp has no usable cross-play"}
    assert "| sa | sp | n/a (self-play run sp has no usable cross-play) |" in (out / "report.md").read_text()


def test_a_compact_copy_of_the_report(finished, tmp_path, capsys):
    dest = tmp_path / "results"
    assert main(["study", "report", str(finished), "--out", str(dest)]) == 0
    names = {p.name for p in dest.iterdir()}
    assert {
        "report.md",
        "summary.json",
        "xp_sp.csv",
        "xp_sa.csv",
        "xp_sp_vs_sa.csv",
        "heatmap_sp.png",
        "heatmap_sp_vs_sa.png",
        "over_training_sp.png",
        "curves_cramped_room.png",
    } <= names
    assert not any(name.endswith((".msgpack", ".mcap")) for name in names)
    assert numbers(dest) == numbers(finished)


def test_a_finished_study_is_never_trained_again(finished, tmp_path, capsys):
    import shutil

    out = tmp_path / "again"
    shutil.copytree(finished, out)
    before = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*") if p.is_file()}
    study = tmp_path / "tiny.yaml"
    write_study(study, STUDY)
    assert main(["study", "run", str(study), "--backend", "local", "--out", str(out), "--quiet"]) == 0
    after = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*") if p.is_file()}
    assert after == before  # not one file of a finished run written again
    assert numbers(out) == numbers(finished)
    statuses = {e["step"]: e["status"] for e in study_status(out)}
    assert set(statuses.values()) == {"done"} and len(statuses) == 4


def test_cross_play_steps_show_progress_and_a_deleted_result_is_redone_the_same(finished, tmp_path, caplog):
    out = tmp_path / "redo"
    shutil.copytree(finished, out)
    snapshots = sorted((out / "over_training" / "sp").glob("update_*.json"))
    snapshots[-1].unlink()
    (out / "over_training" / "sp" / "done.json").unlink()
    (out / "comparisons" / "sp_vs_sa" / "summary.json").unlink()
    with caplog.at_level("INFO", logger="cluster"):
        run_study(load_study(write_study(tmp_path / "tiny.yaml", STUDY)), out, LOCAL, say=lambda _: None)
    lines = [record.getMessage() for record in caplog.records]
    last = int(snapshots[-1].stem.split("_")[1])
    said = f"over_training sp: snapshot {len(snapshots)}/{len(snapshots)} (update {last}): SP "
    assert [line for line in lines if said in line], lines
    assert [line for line in lines if "sp_vs_sa: 8/8 jobs" in line], lines  # 4 seat-0 policies x 2 column groups
    assert not [line for line in lines if "over_training sp: snapshot 1/" in line]  # kept results are not replayed
    assert numbers(out) == numbers(finished)


def test_a_study_killed_mid_run_resumes_to_the_same_numbers(finished, tmp_path):
    study = write_study(tmp_path / "tiny.yaml", STUDY)
    out = tmp_path / "killed"
    command = [
        sys.executable,
        "-c",
        "import sys; from cluster.cli import main; sys.exit(main(sys.argv[1:]))",
        "study",
        "run",
        str(study),
        "--backend",
        "local",
        "--out",
        str(out),
        "--quiet",
    ]
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    # Kill it while the second run trains: the first run is finished, the second has its update-2
    # checkpoints (of 8 updates).
    target = ckpt.checkpoint_path(out / "runs" / "sa", 1, 2)
    deadline = time.time() + 300
    while not target.exists() and child.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    child.send_signal(signal.SIGKILL)
    child.wait()
    assert target.exists(), child.stderr.read().decode()[-2000:]
    assert not (out / "report.md").exists()  # it really died mid-study
    sa_manifest = json.loads((out / "runs" / "sa" / "manifest.json").read_text())
    assert sa_manifest["status"] != "finished"
    statuses = {e["step"]: e["status"] for e in study_status(out)}
    assert statuses["train sp"] == "done" and statuses["train sa"] in ("interrupted", "left")
    sp_files = {p: p.stat().st_mtime_ns for p in (out / "runs" / "sp").rglob("*") if p.is_file()}
    assert main(["study", "report", str(out), "--out", str(tmp_path / "partial")]) == 0
    partial = (tmp_path / "partial" / "report.md").read_text()
    assert "; wall time so far: " in partial and "## Not finished" in partial and "- train sa: " in partial

    # Carried to another machine as a GPU window's files are: packed in parts, unpacked elsewhere, resumed there.
    record = pack_study(out, tmp_path / "packed", part_bytes=200_000)
    assert len(record["parts"]) > 1 and all(p["bytes"] <= 200_000 for p in record["parts"])
    moved = tmp_path / "elsewhere" / "study"
    assert main(["study", "unpack", str(tmp_path / "packed"), "--out", str(moved)]) == 0
    assert not list(moved.rglob("*.png")) and not (moved / ".lock").exists()
    assert main(["study", "run", str(study), "--backend", "local", "--out", str(moved), "--quiet"]) == 0
    # sp is not trained again: its files keep the times tar kept (whole seconds)
    moved_sp = {p.relative_to(moved): int(p.stat().st_mtime) for p in (moved / "runs" / "sp").rglob("*") if p.is_file()}
    kept = {p.relative_to(out): t // 10**9 for p, t in sp_files.items()}
    assert moved_sp and all(kept[p] == t for p, t in moved_sp.items())
    assert_same_runs(moved, finished)
    assert numbers(moved) == numbers(finished)


def test_a_packed_study_is_checked_before_anything_is_unpacked(finished, tmp_path, capsys):
    packed = tmp_path / "packed"
    assert main(["study", "pack", str(finished), "--out", str(packed)]) == 0
    assert main(["study", "pack", str(finished), "--out", str(packed)]) == 2  # never into what is there
    assert "exists and is not an empty folder" in capsys.readouterr().err
    part = packed / "study.tar.gz.000"
    good = part.read_bytes()
    part.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u")]) == 2
    assert "sha256 does not match pack.json" in capsys.readouterr().err and not (tmp_path / "u").exists()
    part.write_bytes(good)
    assert main(["study", "unpack", str(packed), "--out", str(finished)]) == 2  # nor over an existing study
    assert "exists; unpack into a new directory" in capsys.readouterr().err
    record = json.loads((packed / "pack.json").read_text())
    for change, said in (
        (lambda r: r.pop("files"), "'files' must be a count of 0 or more, found None"),
        (lambda r: r.update(study=""), "'study' must be the study's name"),
        (lambda r: r.update(bytes=r["bytes"] + 1), "bytes, its parts hold"),
        (lambda r: r.update(parts=r["parts"] * 2), "is listed more than once"),
    ):
        damaged = json.loads(json.dumps(record))
        change(damaged)
        (packed / "pack.json").write_text(json.dumps(damaged))
        assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u")]) == 2
        assert said in _one_line(capsys) and not (tmp_path / "u").exists()
    # A folder of the user's that happens to bear a staging-like name is never touched.
    (tmp_path / ".u.unpacking").mkdir()
    (tmp_path / ".u.unpacking" / "keep.txt").write_text("mine")
    (packed / "pack.json").write_text(json.dumps(record))
    assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u")]) == 0
    assert (tmp_path / ".u.unpacking" / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [".u.unpacking"]
    (packed / "pack.json").unlink()
    assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u2")]) == 2
    assert "no pack.json" in capsys.readouterr().err and not (tmp_path / "u2").exists()


def _small_pack(tmp_path: Path) -> Path:
    """A pack of a tiny study directory that has trained nothing yet (study.json alone): quick to make."""
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    StateFile(tmp_path / "study", open_state(study, tmp_path / "study", None, None, "local")).save()
    pack_study(tmp_path / "study", tmp_path / "packed")
    return tmp_path / "packed"


def test_unpack_checks_the_study_and_file_count_pack_json_gives_against_what_is_packed(tmp_path, capsys):
    """A pack.json saying "study": "someother", "files": 999 unpacked as "study 'someother' (999 files)", exit 0."""
    packed = _small_pack(tmp_path)
    record = json.loads((packed / "pack.json").read_text())
    out = tmp_path / "new" / "u"
    for change, said in (
        ({"study": "someother"}, "pack.json: names study 'someother', its packed study.json study 'tiny'"),
        ({"files": 999}, "pack.json: says 999 files, its parts hold 1"),
    ):
        (packed / "pack.json").write_text(json.dumps({**record, **change}))
        assert main(["study", "unpack", str(packed), "--out", str(out)]) == 2
        assert _one_line(capsys).endswith(f"{packed / said}; nothing was written")
        assert not (tmp_path / "new").exists()  # nothing written, not even the folder above
    (packed / "pack.json").write_text(json.dumps(record))
    assert main(["study", "unpack", str(packed), "--out", str(out)]) == 0
    assert f"unpacked study 'tiny' (1 files) into {out}" in capsys.readouterr().out
    assert read_state(out).study == "tiny"


def test_unpack_out_a_file_or_under_one_is_refused_as_the_other_commands_refuse_it(tmp_path, capsys):
    """``--out FILE/x`` said "cannot unpack here (File exists)"."""
    packed = _small_pack(tmp_path)
    (tmp_path / "a_file").write_text("mine")
    for out, said in (
        (tmp_path / "a_file" / "x", f"{tmp_path / 'a_file' / 'x'}: cannot be a study directory: {tmp_path / 'a_file'} "
         "is a file, not a directory"),
        (tmp_path / "a_file", f"{tmp_path / 'a_file'}: is a file, not a study directory"),
    ):  # fmt: skip
        assert main(["study", "unpack", str(packed), "--out", str(out)]) == 2
        assert _one_line(capsys).endswith(said)
    assert (tmp_path / "a_file").read_text() == "mine"


def test_a_study_directory_keeps_its_budget_and_seeds(finished, tmp_path):
    study = write_study(tmp_path / "tiny.yaml", STUDY)
    with pytest.raises(StudyError, match="--budget 1.0"):
        run_study(load_study(study), finished, StudyOptions(budget=0.5, backend="local"), say=lambda _: None)
    with pytest.raises(StudyError, match="was started with no --set"):
        run_study(
            load_study(study),
            finished,
            StudyOptions(backend="local", overrides=("eval.episodes=3",)),
            say=lambda _: None,
        )
    with pytest.raises(StudyError, match="was started with --budget-mode truncate"):
        run_study(
            load_study(study), finished, StudyOptions(backend="local", budget_mode="compress"), say=lambda _: None
        )
    with pytest.raises(StudyError, match=r"was started with no --seeds \(each config's own\); pass the same"):
        run_study(load_study(study), finished, StudyOptions(seeds=3, backend="local"), say=lambda _: None)
    # a directory from before --budget-mode compressed its budget, and keeps doing so
    old = tmp_path / "old"
    shutil.copytree(finished, old)
    state = json.loads((old / "study.json").read_text())
    del state["budget_mode"]
    (old / "study.json").write_text(json.dumps(state))
    with pytest.raises(StudyError, match="was started with --budget-mode compress"):
        open_state(load_study(study), old, None, None, "local", mode="truncate")
    assert open_state(load_study(study), old, None, None, "local").budget == 1.0


def test_another_study_file_of_the_same_name_may_add_to_a_directory_but_not_drop_or_swap_its_runs(tmp_path, capsys):
    """A second file with the same ``study:`` took the directory over: the first file's runs and comparisons
    dropped out of the report, their pictures left stale, and study.json's spec and source were replaced."""
    out = tmp_path / "out"
    first = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    StateFile(out, open_state(first, out, None, None, "local")).save()
    (tmp_path / "other").mkdir()
    # A comparison not yet played may be dropped (one its runs cannot play would otherwise lock the directory)
    unplayed = {**STUDY, "comparisons": []}
    plan_study(load_study(write_study(tmp_path / "other" / "tiny.yaml", unplayed)), out, LOCAL)
    state = json.loads((out / "study.json").read_text())
    state["steps"]["compare sp_vs_sa"] = {"status": "done"}  # ... a played one may not
    (out / "study.json").write_text(json.dumps(state))
    before = (out / "study.json").read_bytes()

    def refused(data: dict, *message: str, retrain: tuple = ()) -> None:
        path = write_study(tmp_path / "other" / "tiny.yaml", data)
        with pytest.raises(StudyError) as error:
            plan_study(load_study(path), out, dataclasses.replace(LOCAL, retrain=retrain))
        assert str(error.value).startswith(f"{path}: ") and all(m in str(error.value) for m in message), error.value
        assert f"{out} holds study 'tiny' run from {tmp_path / 'tiny.yaml'}" in str(error.value)
        command = ["study", "run", str(path), "--backend", "local", "--out", str(out)]
        assert main([*command, *(f"--retrain={name}" for name in retrain)]) == 2
        err = _one_line(capsys)
        assert all(m in err for m in message), err
        assert (out / "study.json").read_bytes() == before  # nothing taken over

    dropped = {**STUDY, "runs": STUDY["runs"][:1], "comparisons": []}
    refused(dropped, "has no run 'sa', comparison 'sp_vs_sa', which ", "add runs and comparisons, not drop them")
    refused({**STUDY, "comparisons": []}, "has no comparison 'sp_vs_sa', which ")
    other = tmp_path / "other" / "smoke.yaml"
    shutil.copy(SMOKE, other)  # the same file elsewhere (another checkout): the same config
    swapped = copy.deepcopy(STUDY)
    swapped["runs"][1]["config"] = str(other)
    plan_study(load_study(write_study(tmp_path / "other" / "tiny.yaml", swapped)), out, LOCAL)
    other.write_text(SMOKE.read_text() + "\n# another config file\n")
    refused(swapped, f"run 'sa' takes config {other}, but ", f"gives it {SMOKE.resolve()}; ", "--retrain sa")
    plan_study(load_study(write_study(tmp_path / "other" / "tiny.yaml", swapped)), out, replace_retrain("sa"))
    # More runs and comparisons, the same configs from another study file: accepted.
    more = copy.deepcopy(STUDY)
    more["runs"].append({"name": "sa2", "config": str(SMOKE), "set": ["population.method=sa"]})
    more["comparisons"].append({"name": "sp_vs_sa2", "runs": ["sp", "sa2"]})
    plan_study(load_study(write_study(tmp_path / "other" / "tiny.yaml", more)), out, LOCAL)
    # The file it was run from is gone (a directory unpacked elsewhere): configs of the same name are the same.
    (tmp_path / "tiny.yaml").unlink()
    moved = copy.deepcopy(STUDY)
    moved["runs"][1]["config"] = "smoke.yaml"
    plan_study(load_study(write_study(tmp_path / "other" / "tiny.yaml", moved)), out, LOCAL)


def replace_retrain(*names: str) -> StudyOptions:
    return dataclasses.replace(LOCAL, retrain=names)


def test_a_study_directory_given_for_a_study_file_says_how_to_continue_it(tmp_path, capsys):
    """``study run DIR`` said "is a directory, not a config file"; ``study run DIR/study.json`` "unknown key 'budget'"."""
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    out = tmp_path / "out dir"
    StateFile(out, open_state(study, out, 0.5, 2, "local", ["eval.episodes=3"])).save()
    command = (
        f"ocv2 study run {tmp_path / 'tiny.yaml'} --out '{out}' --budget 0.5 --budget-mode truncate --seeds 2 "
        "--set eval.episodes=3 --backend local"
    )
    for given, what in ((out, "a study directory"), (out / "study.json", f"the study.json of study directory {out}")):
        assert main(["study", "run", str(given)]) == 2
        assert _one_line(capsys).endswith(
            f"error: {given}: is {what} (study 'tiny'), not a study file; continue it with: {command}"
        )
    # the command continues it: the options it names are the ones the directory keeps
    options = StudyOptions(budget=0.5, budget_mode="truncate", seeds=2, overrides=("eval.episodes=3",), backend="local")
    plan_study(study, out, options)
    # the study file it was run from is gone: where it lay is named
    (tmp_path / "tiny.yaml").unlink()
    assert re.search(r"--backend local \(the study file it was run from, .*tiny.yaml, is gone", continue_hint(out))
    with pytest.raises(StudyError, match="is a study directory .or its study.json., not a study file"):
        load_study(out)  # the Python API refuses it too; the command adds how to continue it
    # what the study command reads is a study file, in its errors too
    for given, message in (
        (tmp_path, "is a directory, not a study file"),
        (tmp_path / "no.yaml", "no such study file"),
    ):
        assert main(["study", "run", str(given)]) == 2
        assert _one_line(capsys).endswith(f"{given}: {message}")


def test_set_overrides_every_run_after_the_study_file_and_the_directory_keeps_it(tmp_path, capsys):
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    out = tmp_path / "out"
    StateFile(out, open_state(study, out, None, None, "local", ["eval.episodes=3"])).save()
    kept = kept_study(read_state(out), out)
    for run in kept.runs:  # the study file sets eval.episodes=2 for every run; --set comes after it
        assert run_config(kept, run, out, 1.0, None).eval.episodes == 3
    assert open_state(study, out, None, None, "local", []).overrides == ("eval.episodes=3",)  # left out: kept
    with pytest.raises(StudyError, match="was started with --set eval.episodes=3; pass the same"):
        open_state(study, out, None, None, "local", ["eval.episodes=4"])
    assert main(["study", "report", str(out)]) == 0
    report = (out / "report.md").read_text()
    assert "- every run also with `eval.episodes=3` (`--set`)" in report
    assert "population.method=sp eval.episodes=3`" in report  # in the run's own list, last


@pytest.mark.parametrize(
    "options, message",
    [
        (["--set", "ppo.lrr=1"], "run 'sp': --set ppo.lrr=1: ppo.lrr: unknown key; did you mean ppo.lr?"),
        # compressed, SA's 2 iterations need 2 updates; 1e-4 of the smoke config's steps is one
        (["--budget", "0.0001", "--budget-mode", "compress"], "run 'sa' at --budget 0.0001: "),
        (
            ["--set", "run.num_checkpoints=1000000000"],
            "run.num_checkpoints: 1,000,000,000 snapshots of a run of 4 updates; at most 100",
        ),
    ],
)
def test_a_bad_set_or_budget_is_a_one_line_error_before_anything_is_written(tmp_path, capsys, options, message):
    path = write_study(tmp_path / "tiny.yaml", STUDY)
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out"), *options]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not (tmp_path / "out").exists()  # so the same command with a good value starts afresh


@pytest.mark.parametrize(
    "where, message",
    [
        ("study", "run 'sp': set: ppo.lrr=1: ppo.lrr: unknown key; did you mean ppo.lr?"),
        ("run", "run 'sp': run 'sp'.set: ppo.lrr=1: ppo.lrr: unknown key; did you mean ppo.lr?"),
    ],
)
def test_a_bad_override_in_the_study_file_is_named_by_its_key_not_as_a_set_never_typed(
    tmp_path, capsys, where, message
):
    data = copy.deepcopy(STUDY)
    (data if where == "study" else data["runs"][0])["set"].append("ppo.lrr=1")
    path = write_study(tmp_path / "tiny.yaml", data)
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "--set" not in err, err
    # the same key given on the command line is still named as the --set it was
    data["runs"][0]["set"].remove("ppo.lrr=1") if where == "run" else data["set"].remove("ppo.lrr=1")
    path = write_study(tmp_path / "tiny.yaml", data)
    assert (
        main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out"), "--set", "ppo.lrr=1"])
        == 2
    )
    assert "run 'sp': --set ppo.lrr=1: ppo.lrr: unknown key" in capsys.readouterr().err


def test_compressed_budget_scales_steps_and_schedules_of_every_stage():
    config = load_config(ROOT / "configs" / "paper" / "v2_grounded_coord_simple_fcp.yaml")
    scaled = load_config(
        ROOT / "configs" / "paper" / "v2_grounded_coord_simple_fcp.yaml", budget_overrides(config, 0.1, "compress")
    )
    assert scaled.ppo.total_timesteps == 3_000_000 and scaled.ppo.rew_shaping_horizon == 1_500_000
    assert not scaled.ppo.truncated
    partner = scaled.population.fcp.partner_ppo
    assert partner.total_timesteps == 3_000_000 and partner.rew_shaping_horizon == 1_500_000
    assert partner.lr == config.population.fcp.partner_ppo.lr  # only the budget changes
    assert budget_overrides(config, 1.0, "compress") == budget_overrides(config, 1.0) == []
    # past the schedule's end: only compress stretches it; truncate says so instead of naming a --set never given
    assert "ppo.total_timesteps=60000000" in budget_overrides(config, 2.0, "compress")
    with pytest.raises(StudyError, match=r"--budget 2: --budget-mode truncate .*cannot run past its end"):
        budget_overrides(config, 2.0)


def test_truncated_budget_is_the_first_part_of_the_paper_schedule():
    """Truncation trains the first 0.1 of the paper's run: the same LR at every optimiser step it reaches,
    the same shaping weight at every env step, SA's iteration starts of the full run that it reaches."""
    path = ROOT / "configs" / "paper" / "v2_grounded_coord_simple_sa.yaml"
    full = load_config(path)
    cut = load_config(path, budget_overrides(full, 0.1))
    assert cut.ppo.total_timesteps == 3_000_000 and cut.ppo.schedule_timesteps == 30_000_000
    assert cut.ppo.rew_shaping_horizon == full.ppo.rew_shaping_horizon and cut.ppo.truncated
    assert cut.ppo.num_updates == full.ppo.num_updates // 10 and cut.ppo.schedule_updates == full.ppo.num_updates
    steps = np.arange(cut.ppo.num_updates * cut.ppo.update_epochs * cut.ppo.num_minibatches)
    np.testing.assert_array_equal(ppo.lr_schedule(cut)(steps), ppo.lr_schedule(full)(steps))
    env_steps = np.arange(0, cut.ppo.total_timesteps, 12_345)
    np.testing.assert_array_equal(ppo.shaping_coef(cut, env_steps), ppo.shaping_coef(full, env_steps))
    full_starts, cut_starts = Schedule.of(full).iteration_starts, Schedule.of(cut).iteration_starts
    assert cut_starts == tuple(s for s in full_starts if s < cut.ppo.num_updates) and len(cut_starts) == 1
    # compressing the same budget decays the LR to 0 by its last step; truncated, it is still near its peak
    squeezed = load_config(path, budget_overrides(full, 0.1, "compress"))
    assert ppo.lr_schedule(squeezed)(steps[-1]) < 1e-9 and ppo.lr_schedule(cut)(steps[-1]) > 0.9 * full.ppo.lr
    with pytest.raises(StudyError, match="--budget-mode: expected one of truncate, compress"):
        budget_overrides(full, 0.1, "squeeze")
    with pytest.raises(ConfigError, match="ppo.schedule_timesteps: 1000 is less than total_timesteps"):
        load_config(path, ["ppo.schedule_timesteps=1000"])


def test_fcp_partners_from_an_earlier_run_of_the_study(tmp_path):
    data = {
        "study": "fcp",
        "runs": [
            {"name": "sp", "config": str(SMOKE)},
            {"name": "fcp", "config": str(SMOKE), "set": ["population.method=fcp"], "partners_from": "sp"},
        ],
    }
    study = load_study(write_study(tmp_path / "s.yaml", data))
    config = run_config(study, study.run("fcp"), tmp_path / "out", budget=1.0, seeds=3)
    fcp = config.population.fcp
    assert (fcp.pool, fcp.partners, fcp.partner_seeds) == ("shared", str(tmp_path / "out" / "runs" / "sp"), 3)


@pytest.mark.parametrize(
    "extra, message",
    [
        (
            "env.layout=coord_ring",
            "run 'fcp'.partners_from: run 'sp' trains another game or network than run 'fcp' (differs in layout: ",
        ),
        ("model.fc_dim=32", "than run 'fcp' (its model section differs)"),
        ("ppo.activation=tanh", "than run 'fcp' (its ppo.activation is 'relu', not 'tanh')"),
        ("population.fcp.checkpoints=[3]", "run 'fcp'.partners_from: population.fcp.checkpoints: "),
    ],
)
def test_an_fcp_run_whose_partner_run_cannot_give_its_pool_is_refused_before_anything_trains(tmp_path, extra, message):
    """Found only when the FCP run started, after its partner run had trained its whole budget."""
    data = {
        "study": "fcp",
        "runs": [
            {"name": "sp", "config": str(SMOKE)},
            {"name": "fcp", "config": str(SMOKE), "set": ["population.method=fcp", extra], "partners_from": "sp"},
        ],
    }
    study = load_study(write_study(tmp_path / "s.yaml", data))
    with pytest.raises(StudyError, match=re.escape(message)) as refused:
        plan_study(study, tmp_path / "out", LOCAL)
    assert str(tmp_path / "s.yaml") in str(refused.value)
    assert not (tmp_path / "out").exists()
    assert main(["validate", str(tmp_path / "s.yaml")]) == 1  # ocv2 validate refuses it as study run does


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d["runs"][0].update(config="nowhere.yaml"), "run 'sp'.config: no such config file nowhere.yaml"),
        (lambda d: d["runs"][0].update(config="."), "run 'sp'.config: . is a folder (at "),
        (  # loop_a -> loop_b -> loop_a, made by the test: Path.resolve raised a RuntimeError on Python 3.11-3.12
            lambda d: d["runs"][0].update(config="loop_a/x.yaml"),
            "run 'sp'.config: ",
        ),
        (
            lambda d: (d.clear(), d.update(env={"layout": "cramped_room"}, ppo={"lr": 0.001})),
            "is an experiment config, not a study file (no 'study' key); run it with `ocv2 train`",
        ),
        (lambda d: d["runs"][1].update(sett=["a=b"]), "run 'sa': unknown key 'sett'; did you mean 'set'?"),
        (lambda d: d.update(comparsons=[]), "unknown key 'comparsons'; did you mean 'comparisons'?"),
        (lambda d: d["runs"][1].update(name="sp"), "run 'sp': duplicate run name (runs[0] has it too)"),
        (lambda d: d["runs"][1].update(name="SP"), "run 'SP': duplicate run name (runs[0] has it too as 'sp': names"),
        (lambda d: d["runs"][0]["paper"].update(note=False), "run 'sp'.paper.note: expected text"),
        (  # train called such a file a study file and study run a config, each sending the user to the other
            lambda d: d.update(env={"layout": "cramped_room"}),
            "holds a study file's study and runs and an experiment config's env: a file is one or the other",
        ),
        (  # partners_from overrode these without a word
            lambda d: d["runs"][1].update(
                partners_from="sp", set=["population.method=fcp", "population.fcp.pool=per_seed"]
            ),
            "run 'sa'.set: 'population.fcp.pool=per_seed' and run 'sa'.partners_from both give population.fcp.pool",
        ),
        (lambda d: d["runs"][0].update(config="/dev/null"), "run 'sp'.config: /dev/null is not a regular file"),
        (
            lambda d: d.update(study="s" * 65),
            "study: expected a name (1-64 letters, digits, _ . -, the first a letter or digit), got 'sss",
        ),
        (lambda d: d["comparisons"][0].update(runs=["sp", "op"]), "comparison 'sp_vs_sa'.runs: no run is named 'op'"),
        (
            lambda d: d["comparisons"].append({"name": "sp_vs_sa", "runs": ["sa", "sp"]}),
            "comparison 'sp_vs_sa': duplicate comparison name (comparisons[0] has it too)",
        ),
        (
            lambda d: d["comparisons"].append({"name": "sa", "runs": ["sa", "sp"]}),
            "comparison 'sa': a run has this name too; give the comparison another name",
        ),
        (lambda d: d["runs"][0].update(set=["ppo.lrr=1"]), "run 'sp': "),
        (lambda d: d["runs"][0]["paper"].update(sp="high"), "run 'sp'.paper.sp: expected a number or [mean, std]"),
        (lambda d: d.update(over_training=["spp"]), "over_training: no run is named 'spp'; did you mean 'sp'?"),
        (lambda d: d.update(over_training=["sp", "sp"]), "over_training: names run 'sp' twice"),
        (
            lambda d: d["runs"][1].update(name="sa\n"),
            "runs[1].name: expected a name (1-64 letters, digits, _ . -, the first a letter or digit), got 'sa\\n'",
        ),
        (lambda d: d.update(study="tiny\n"), "study: expected a name"),
        (lambda d: d["comparisons"][0].update(name="c\n"), "comparisons[0].name: expected a name"),
        (lambda d: d["runs"][1].update(name="plots"), "runs[1].name: 'plots' names the folders a pack leaves out"),
        (lambda d: d["runs"][0]["paper"].update(sp=10**400), "not valid YAML: an integer of 401 digits (at most 100)"),
        # A key that is not a list was a traceback (comparisons: 5) or read as empty (comparisons: false).
        (lambda d: d.update(comparisons=5), "comparisons: expected a list of comparisons, got int"),
        (lambda d: d.update(comparisons=False), "comparisons: expected a list of comparisons, got bool"),
        (lambda d: d.update(over_training={}), "over_training: expected a list of run names"),
        (lambda d: d.update(description=[]), "description: expected text"),
    ],
    ids=lambda v: None if callable(v) else v[:40],
)
def test_bad_study_files_are_one_line_errors_naming_the_entry(tmp_path, capsys, change, message):
    (tmp_path / "loop_a").symlink_to("loop_b")
    (tmp_path / "loop_b").symlink_to("loop_a")
    data = json.loads(json.dumps(STUDY))
    change(data)
    path = write_study(tmp_path / "bad.yaml", data)
    with pytest.raises(StudyError) as error:
        load_study(path)
    assert message in str(error.value) and str(path) in str(error.value)
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "out").exists()  # nothing written
    if "a file is one or the other" in message:  # ocv2 train says the same of it
        assert main(["train", str(path), "--out", str(tmp_path / "out")]) == 2
        assert message in capsys.readouterr().err and not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "tail, message",
    [
        ("runs: []\n", "not valid YAML: duplicate key 'runs' (first at line "),
        ("comparisons: " + "[" * 5000 + "\n", "not valid YAML: nested deeper than 64 levels"),
        ("notes: [" + "1" * 5000 + "]\n", "not valid YAML: an integer of 5000 digits"),
    ],
    ids=["runs-twice", "5000-nested", "5000-digits"],
)
def test_hostile_study_files_are_one_line_errors(tmp_path, capsys, tail, message):
    """A second ``runs:`` used to drop the first silently; deep nesting and huge integers ended in
    RecursionError and ValueError tracebacks."""
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(STUDY, sort_keys=False) + tail)
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and message in err, err[:300]
    assert not (tmp_path / "out").exists()


def test_hostile_set_in_a_study_is_a_one_line_error(tmp_path, capsys):
    path = write_study(tmp_path / "tiny.yaml", STUDY)
    for value, message in (("[" * 5000, "nested deeper than 64 levels"), ("9" * 5000, "an integer of 5000 digits")):
        assert main(["study", "run", str(path), "--out", str(tmp_path / "out"), "--set", f"ppo.lr={value}"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--set ppo.lr=" in err and message in err, err[:300]
    assert not (tmp_path / "out").exists()


def test_status_lists_every_step(finished, capsys):
    assert main(["study", "status", str(finished)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[:3] for line in out[:4]] == [
        ["train", "sp", "done"],
        ["over_training", "sp", "done"],
        ["train", "sa", "done"],
        ["compare", "sp_vs_sa", "done"],
    ]
    assert out[-1].startswith("4 done; training left: 0m00s")


def test_status_gives_an_interrupted_run_an_eta_from_the_measured_throughput(finished, tmp_path):
    out = tmp_path / "study"
    shutil.copytree(finished, out)
    manifest = json.loads((out / "runs" / "sp" / "manifest.json").read_text())
    manifest.update(status="interrupted", update=1)  # 3 of its 4 updates (2 seeds x 128 steps each) left
    (out / "runs" / "sp" / "manifest.json").write_text(json.dumps(manifest))
    walls = {name: step["wall_s"] for name, step in json.loads((out / "study.json").read_text())["steps"].items()}
    entry = {e["step"]: e for e in study_status(out)}["train sp"]
    # measured: sp's 4 x 256 and sa's 8 x 256 env steps in their training steps' wall time (one model kind)
    rate = (4 * 256 + 8 * 256) / (walls["train sp"] + walls["train sa"])
    assert entry["progress"] == "update 1/4 (interrupted)"
    assert entry["eta_s"] > 0 and entry["eta_s"] == pytest.approx(3 * 256 / rate)


def test_a_step_blocked_by_a_missing_human_proxy_exits_1_with_the_command_that_fixes_it(
    finished, tmp_path, capsys, monkeypatch
):
    monkeypatch.setenv("OCV2_CACHE", str(tmp_path / "empty-cache"))  # no human proxy trained here
    out = tmp_path / "study"
    shutil.copytree(finished, out)
    data = {
        **STUDY,
        "comparisons": [*STUDY["comparisons"], {"name": "sp_vs_human", "runs": ["sp"], "human_proxy": True}],
    }
    path = write_study(tmp_path / "tiny.yaml", data)
    assert main(["study", "run", str(path), "--out", str(out), "--backend", "local", "--quiet"]) == 1
    printed = capsys.readouterr()
    assert "not done: compare sp_vs_human:" in printed.out
    hint = "make it with 'ocv2 human proxy cramped_room --source overcooked_ai-1.1.0.tar.gz'"
    assert printed.out.count(hint) == 1, printed.out  # said once (the study added its own copy)
    assert "1 step(s) could not run" in printed.err
    state = json.loads((out / "study.json").read_text())
    assert state["steps"]["compare sp_vs_human"]["status"] == "blocked"
    assert state["steps"]["compare sp_vs_sa"]["status"] == "done"  # the other steps were not redone


@pytest.mark.parametrize(
    "change, message",
    [
        (
            ["env.layout=coord_ring"],
            "comparison 'sp_vs_sa': run 'sa' plays another game than run 'sp' (differs in layout: 'coord_ring' vs "
            "'cramped_room')",
        ),
        (
            ["env.max_steps=50"],
            "comparison 'sp_vs_sa': run 'sa' plays another game than run 'sp' (differs in max_steps",
        ),
        (
            ["run.precision=bf16"],
            "comparison 'sp_vs_sa': its runs train at different run.precision (sp: float32, sa: bf16); give the "
            "compared runs one run.precision (set:)",
        ),
    ],
    ids=["layout", "max_steps", "precision"],
)
def test_a_comparison_that_cannot_be_played_is_refused_before_anything_trains(tmp_path, capsys, change, message):
    data = copy.deepcopy(STUDY)
    data["runs"][1]["set"] += change
    path = write_study(tmp_path / "mixed.yaml", data)
    with pytest.raises(StudyError) as error:
        plan_study(load_study(path), tmp_path / "out", LOCAL)
    assert str(error.value).startswith(f"{path}: ") and message in str(error.value)
    if "precision" not in change[0]:  # another game is no matter of precision
        assert "precision" not in str(error.value)
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out")]) == 2
    assert message in _one_line(capsys)
    assert not (tmp_path / "out").exists()


def test_human_proxy_on_a_layout_without_human_data_is_refused_before_anything_trains(tmp_path, capsys):
    data = copy.deepcopy(STUDY)
    data["set"].append("env.layout=grounded_coord_simple")
    data["comparisons"].append({"name": "sp_vs_human", "runs": ["sp"], "human_proxy": True})
    path = write_study(tmp_path / "v2.yaml", data)
    with pytest.raises(StudyError) as error:
        plan_study(load_study(path), tmp_path / "out", LOCAL)
    assert str(error.value) == (
        f"{path}: comparison 'sp_vs_human': human_proxy: true, but layout 'grounded_coord_simple' has no human data "
        "(a BC human proxy exists only for cramped_room, asymm_advantages, coord_ring, forced_coord, counter_circuit); "
        "set human_proxy: false or compare runs of one of those"
    )
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(tmp_path / "out")]) == 2
    assert "has no human data" in _one_line(capsys)
    assert not (tmp_path / "out").exists()
    data["comparisons"].pop()  # without the proxy the same runs are a study
    plan_study(load_study(write_study(tmp_path / "v2.yaml", data)), tmp_path / "out", LOCAL)


def test_a_step_that_fails_is_recorded_blocked_with_its_reason_and_the_report_still_written(
    finished, tmp_path, capsys, monkeypatch
):
    """A comparison refused while it ran stayed "running" in study.json (status: interrupted) with no report."""
    out = _copy(finished, tmp_path / "study")
    (out / "comparisons" / "sp_vs_sa" / "summary.json").unlink()  # so the comparison runs again
    (out / "report.md").unlink()

    def other_game(groups):
        raise crossplay.CrossPlayError("sa plays another environment than sp (differs in layout: 'a' vs 'b')")

    monkeypatch.setattr(crossplay, "check_same_env", other_game)
    path = write_study(tmp_path / "tiny.yaml", STUDY)
    assert main(["study", "run", str(path), "--out", str(out), "--backend", "local", "--quiet"]) == 1
    printed = capsys.readouterr()
    reason = "comparison 'sp_vs_sa': sa plays another environment than sp (differs in layout: 'a' vs 'b')"
    assert f"not done: compare sp_vs_sa: {reason}" in printed.out and "precision" not in printed.out
    step = json.loads((out / "study.json").read_text())["steps"]["compare sp_vs_sa"]
    assert step["status"] == "blocked" and step["reason"] == reason
    assert f"- compare sp_vs_sa: blocked ({reason})" in (out / "report.md").read_text()
    assert {e["step"]: e["status"] for e in study_status(out)}["compare sp_vs_sa"] == "blocked"


def test_a_damaged_human_proxy_blocks_its_comparison_without_advice_to_train_a_missing_one(
    finished, tmp_path, capsys, monkeypatch
):
    monkeypatch.setenv("OCV2_CACHE", str(tmp_path / "cache"))
    proxy = tmp_path / "cache" / "human_proxy" / "cramped_room.ocv2policy"
    proxy.parent.mkdir(parents=True)
    proxy.write_bytes(b"not a policy")
    out = _copy(finished, tmp_path / "study")
    data = {
        **STUDY,
        "comparisons": [*STUDY["comparisons"], {"name": "sp_vs_human", "runs": ["sp"], "human_proxy": True}],
    }
    path = write_study(tmp_path / "tiny.yaml", data)
    assert main(["study", "run", str(path), "--out", str(out), "--backend", "local", "--quiet"]) == 1
    printed = capsys.readouterr().out
    assert "not done: compare sp_vs_human: " in printed and str(proxy) in printed, printed
    assert "ocv2 human proxy" not in printed  # the file is there: training one is not the fix


def test_a_comparison_against_a_human_proxy_trained_again_is_played_again(finished, tmp_path, monkeypatch):
    """The result records which proxy it was played against; a proxy file holding another policy (``ocv2 human
    proxy`` run again) makes it stale, as other runs or episodes do."""
    monkeypatch.setenv("OCV2_CACHE", str(tmp_path / "cache"))
    proxy = tmp_path / "cache" / "human_proxy" / "cramped_room.ocv2policy"
    proxy.parent.mkdir(parents=True)
    policy.export_checkpoint(finished / "runs" / "sp", proxy, seed=0, meta={"name": "human proxy"})
    out = _copy(finished, tmp_path / "study")
    data = {
        **STUDY,
        "comparisons": [*STUDY["comparisons"], {"name": "sp_vs_human", "runs": ["sp"], "human_proxy": True}],
    }
    study = load_study(write_study(tmp_path / "tiny.yaml", data))
    run_study(study, out, LOCAL, say=lambda line: None)
    configs = plan_study(study, out, LOCAL).configs
    step = Step("compare", "sp_vs_human")
    assert result_problem(step, study, out, configs) is None
    policy.export_checkpoint(finished / "runs" / "sp", proxy, seed=1, meta={"name": "human proxy"})
    assert "played against another human proxy" in result_problem(step, study, out, configs)
    proxy.unlink()  # gone: the result made against it stands (the step would be blocked, not redone)
    assert result_problem(step, study, out, configs) is None


def test_address_needs_the_ray_backend(tmp_path, capsys):
    path = write_study(tmp_path / "tiny.yaml", STUDY)
    command = [
        "study",
        "run",
        str(path),
        "--backend",
        "local",
        "--address",
        "10.0.0.1:6379",
        "--out",
        str(tmp_path / "s"),
    ]
    assert main(command) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_status_of_a_running_step_counts_the_time_since_its_last_save(finished, tmp_path):
    out = tmp_path / "study"
    shutil.copytree(finished, out)
    state = json.loads((out / "study.json").read_text())
    state["steps"]["compare sp_vs_sa"].update(status="running", wall_s=60.0, ticked=time.time() - 120)
    (out / "study.json").write_text(json.dumps(state))
    wall = lambda: {e["step"]: e for e in study_status(out)}["compare sp_vs_sa"]
    assert wall()["status"] == "interrupted" and wall()["wall_s"] == 60.0  # nobody runs it: no time added
    holder = RunDir(out)
    holder.lock()  # as the study process holds it while it runs
    try:
        entry = wall()
        assert entry["status"] == "running" and 180.0 <= entry["wall_s"] < 240.0
    finally:
        holder.close()


def test_status_of_a_folder_that_is_no_study(tmp_path, capsys):
    assert main(["study", "status", str(tmp_path)]) == 2
    assert "not a study directory" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["mine.yaml", "table1_coord_ring_sp10.yaml"])
def test_status_after_the_study_file_is_gone(tmp_path, capsys, name):
    """A study unpacked into another checkout (or its file renamed): its configs are named relative to a file
    that is gone. A shipped study's name resolves them as shipped; another name is one line saying what to do."""
    (tmp_path / "studies").mkdir()
    shutil.copy(SMOKE, tmp_path / "smoke.yaml")
    study_file = write_study(
        tmp_path / "studies" / name,
        {**STUDY, "runs": [{**STUDY["runs"][0], "config": "../smoke.yaml"}], "comparisons": []},
    )
    study, out = load_study(study_file), tmp_path / "out"
    out.mkdir()
    StateFile(out, open_state(study, out, 0.5, None, "local")).save()
    assert main(["study", "status", str(out)]) == 0
    study_file.unlink()
    (tmp_path / "smoke.yaml").unlink()
    if name == "mine.yaml":
        assert main(["study", "status", str(out)]) == 2
        err = _one_line(capsys)
        assert "no such config file ../smoke.yaml" in err and f"{study_file}, which is gone" in err, err
        assert f"run `ocv2 study run STUDY.yaml --out {out.resolve()}` once" in err, err
    else:
        assert main(["study", "status", str(out)]) == 0
        assert kept_study(read_state(out), out).runs[0].config == SMOKE.resolve()


def test_a_step_kind_without_a_done_rule_is_an_error_not_a_finished_step(tmp_path):
    """result_problem names each kind's done rule; an unknown kind must not fall through to another's."""
    assert "nope" not in STEP_KINDS
    with pytest.raises(ValueError, match="unknown study step kind 'nope'"):
        result_problem(Step("nope", "sp"), None, tmp_path, {})


def test_shipped_studies_load(tmp_path):
    studies = sorted((ROOT / "configs" / "studies").glob("*.yaml"))
    assert studies
    for path in studies:
        study = load_study(path)
        for run in study.runs:
            run_config(study, run, tmp_path, budget=0.05, seeds=4)
        assert all(run.paper is not None for run in study.runs), path


def test_study_runs_keep_no_xp_archive_unless_asked(tmp_path):
    """The report reads each run's cross-play scores, not its XP archive (every transition of every scored
    episode, gigabytes at paper sizes): studies train with ``archive.xp=false`` unless a ``set`` asks."""
    data = {**STUDY, "set": ["eval.episodes=2"]}
    data["runs"] = [{**STUDY["runs"][0]}, {**STUDY["runs"][1], "set": [*STUDY["runs"][1]["set"], "archive.xp=true"]}]
    study = load_study(write_study(tmp_path / "archive.yaml", data))
    assert load_config(SMOKE).archive.xp  # the config alone (ocv2 train) archives
    assert [run_config(study, run, tmp_path, 1.0, None).archive.xp for run in study.runs] == [False, True]
    asked = with_overrides(study, ["archive.xp=true"])  # ocv2 study run --set archive.xp=true
    assert [run_config(asked, run, tmp_path, 1.0, None).archive.xp for run in asked.runs] == [True, True]


# ---------------------------------------------------------------------------------------------------
# nothing lost: changed configs, reports and exports never write over results
# ---------------------------------------------------------------------------------------------------


def _copy(finished: Path, to: Path) -> Path:
    shutil.copytree(finished, to)
    return to


def _changed_study(tmp_path: Path, run: int, *extra: str) -> Path:
    data = json.loads(json.dumps(STUDY))
    data["runs"][run]["set"] = [*data["runs"][run]["set"], *extra]
    return write_study(tmp_path / "changed.yaml", data)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_a_trained_run_whose_config_changed_is_refused_and_study_json_kept(finished, tmp_path, capsys):
    """The finished run kept lr 0.001 while the report showed the new overrides and fingerprint beside its
    numbers; study.json's spec was already replaced."""
    out = _copy(finished, tmp_path / "study")
    before = (out / "study.json").read_bytes()
    for extra, difference in (
        (["ppo.lr=0.01"], "ppo.lr: 0.001 in the run, 0.01 now"),
        (["eval.episodes=3", "ppo.lr=0.01"], "ppo.lr: 0.001 in the run, 0.01 now"),  # evaluation alone would do
    ):
        path = _changed_study(tmp_path, 0, *extra)
        assert main(["study", "run", str(path), "--backend", "local", "--out", str(out), "--quiet"]) == 2
        err = _one_line(capsys)
        assert "run 'sp': " in err and difference in err and "--retrain sp" in err, err
        assert (out / "study.json").read_bytes() == before  # the stored spec is not rewritten
    assert main(["study", "run", str(path), "--out", str(out), "--retrain", "nope"]) == 2
    assert "--retrain nope: the study has no run named 'nope'" in _one_line(capsys)
    assert numbers(out) == numbers(finished)


def test_a_changed_eval_episodes_evaluates_the_trained_run_again_without_training_it(finished, tmp_path, capsys):
    """Changing a study's eval.episodes asked for --retrain, though episodes per pair change only the cross-play:
    the run is now evaluated again, its checkpoints untouched and the old evaluation kept."""
    out = _copy(finished, tmp_path / "study")
    checkpoints = {p: p.read_bytes() for p in (out / "runs" / "sp" / "checkpoints").rglob("*") if p.is_file()}
    path = _changed_study(tmp_path, 0, "eval.episodes=3")
    plan = plan_study(load_study(path), out, LOCAL)
    assert (plan.reevaluate, plan.retrain, plan.extend) == (("sp",), (), ())
    assert steps_to_run(plan)  # Ray would be started for it
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "run sp: evaluated again with eval.episodes 3 (was 2;" in said, said
    # The study's cross-play of the run made with 2 episodes per pair is kept too, and played again with 3.
    aside = next((out / "reevaluated").iterdir())
    for kept_result in ("over_training/sp/done.json", "comparisons/sp_vs_sa/summary.json"):
        assert (aside / kept_result).read_bytes() == (finished / kept_result).read_bytes()
    after = {p: p.read_bytes() for p in (out / "runs" / "sp" / "checkpoints").rglob("*") if p.is_file()}
    assert after == checkpoints  # not trained again
    run = out / "runs" / "sp"
    assert load_config(run / "config.yaml").eval.episodes == 3
    assert json.loads((run / "xp" / "summary.json").read_text())["episodes_per_pair"] == 3
    kept = json.loads((run / "reevaluated" / "episodes_2" / "xp" / "summary.json").read_text())
    assert kept == json.loads((finished / "runs" / "sp" / "xp" / "summary.json").read_text())
    assert {e["status"] for e in study_status(out)} == {"done"}
    assert not steps_to_run(plan_study(load_study(path), out, LOCAL))  # a rerun now has nothing to do


def test_a_run_not_evaluated_yet_takes_the_new_episodes_with_nothing_to_set_aside(finished, tmp_path):
    """Re-evaluating a run still training (no xp/ yet): its config takes the count, nothing is moved, a second call
    finds nothing to do."""
    run = tmp_path / "sp"
    shutil.copytree(finished / "runs" / "sp", run)
    for name in EVALUATION_DIRS:
        shutil.rmtree(run / name, ignore_errors=True)
    config = load_config(run / "config.yaml")
    more = dataclasses.replace(config, eval=dataclasses.replace(config.eval, episodes=5))
    assert take_eval_episodes(run, more) == 2
    assert load_config(run / "config.yaml") == more and not (run / "reevaluated").exists()
    assert take_eval_episodes(run, more) is None


def test_whether_the_steps_need_ray_is_decided_under_the_directory_lock(finished, tmp_path, monkeypatch):
    """`study run` chose "no Ray" from a plan made before it took the lock: for a result another driver removed in
    between, the step then started Ray itself, after JAX was running in the driver (Ray's fork after JAX's threads).
    run_study now asks ``session(needed)`` under the lock."""
    out = _copy(finished, tmp_path / "study")
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    asked = []

    @contextlib.contextmanager
    def session(needed):
        asked.append(needed)
        yield

    run_study(study, out, LOCAL, say=lambda _: None, session=session)
    assert asked == [False]  # every step done: a rerun needs no Ray
    assert not steps_to_run(plan_study(study, out, LOCAL))  # a look before the lock: still nothing to do
    acquire = DirLock.acquire

    def acquire_after_a_change(self, *args, **kwargs):  # another driver removes a result just before the lock
        if self.path == out:  # the study's lock, not a run directory's
            (out / "comparisons" / "sp_vs_sa" / "summary.json").unlink(missing_ok=True)
        return acquire(self, *args, **kwargs)

    monkeypatch.setattr(DirLock, "acquire", acquire_after_a_change)
    state = run_study(study, out, LOCAL, say=asked.append, session=session)
    assert state.steps["compare sp_vs_sa"].done
    assert asked[:2] == [False, True]  # asked under the lock, before the step ran (its line comes after)
    assert any("compare sp_vs_sa" in str(line) for line in asked[2:])


def test_a_rerun_with_nothing_to_do_starts_no_ray_and_keeps_the_backend_that_ran_the_steps(
    finished, tmp_path, monkeypatch, capsys
):
    """A no-op rerun of a finished study with --backend ray started Ray and rewrote the report's backend,
    though every step had run on the local backend."""
    out = _copy(finished, tmp_path / "study")
    study = write_study(tmp_path / "tiny.yaml", STUDY)
    started = []

    @contextlib.contextmanager
    def session(backend, cluster):
        started.append(backend)
        yield

    monkeypatch.setattr("cluster.cli.study.ray_backend.session", session)
    assert main(["study", "run", str(study), "--backend", "ray", "--out", str(out), "--quiet"]) == 0, (
        capsys.readouterr()
    )
    assert started == ["local"]  # no Ray: nothing ran
    assert json.loads((out / "summary.json").read_text())["backend"] == "local"
    assert "; backend: local;" in (out / "report.md").read_text()
    # A step that runs again runs on the backend asked for, and the report names each backend with its steps.
    (out / "comparisons" / "sp_vs_sa" / "summary.json").unlink()
    assert steps_to_run(plan_study(load_study(study), out, LOCAL)) == ["compare sp_vs_sa"]
    run_study(load_study(study), out, LOCAL, say=lambda _: None)
    data = json.loads((out / "study.json").read_text())
    assert data["steps"]["compare sp_vs_sa"]["backend"] == "local"
    data["steps"]["train sa"]["backend"] = "ray"  # as if trained by an earlier `study run --backend ray`
    del data["steps"]["over_training sp"]["backend"]  # a step recorded before steps named their backend
    (out / "study.json").write_text(json.dumps(data))
    assert report.backends(read_state(out)) == "local (train sp, over_training sp, compare sp_vs_sa), ray (train sa)"
    assert main(["study", "report", str(out), "--out", str(tmp_path / "report")]) == 0
    assert (
        "; backend: local (train sp, over_training sp, compare sp_vs_sa), ray (train sa);"
        in (tmp_path / "report" / "report.md").read_text()
    )
    # Only steps that made the reported results count: a blocked step on another backend does not.
    data["steps"]["train sa"]["backend"] = "local"
    data["steps"]["compare sp_vs_sa"].update(status="blocked", backend="ray")
    (out / "study.json").write_text(json.dumps(data))
    assert report.backends(read_state(out)) == "local"


def test_the_report_describes_runs_as_they_were_trained(finished, tmp_path, capsys):
    """The report took a run's fingerprint and env steps from today's config files, beside numbers trained with
    another config; it now takes them from the run and says what changed."""
    out = _copy(finished, tmp_path / "study")
    data = json.loads((out / "study.json").read_text())
    data["spec"]["runs"][0]["set"].append("ppo.lr=0.01")  # as if sp's config file had changed since
    (out / "study.json").write_text(json.dumps(data))
    assert main(["study", "report", str(out), "--out", str(tmp_path / "report")]) == 0, capsys.readouterr().err
    runs = json.loads((tmp_path / "report" / "summary.json").read_text())["runs"]
    theirs = json.loads((finished / "summary.json").read_text())["runs"]
    assert (
        runs[0]["fingerprint"]
        == theirs[0]["fingerprint"]
        == load_config(out / "runs" / "sp" / "config.yaml").fingerprint()
    )
    assert runs[0]["config_changed"] == ["ppo.lr: 0.001 in the run, 0.01 now"] and "config_changed" not in runs[1]
    report = (tmp_path / "report" / "report.md").read_text()
    assert "- train sp: its numbers are of the config it was trained with" in report and "--retrain sp" in report


def test_retrain_trains_a_changed_run_again_and_keeps_the_old_one(finished, tmp_path, capsys):
    out = _copy(finished, tmp_path / "study")
    path = _changed_study(tmp_path, 1, "ppo.lr=0.002")  # sa: the run after sp, compared with it
    code = main(["study", "run", str(path), "--backend", "local", "--out", str(out), "--quiet", "--retrain", "sa"])
    assert code == 0, capsys.readouterr().err
    (replaced,) = (out / "replaced").iterdir()
    assert load_config(replaced / "runs" / "sa" / "config.yaml").ppo.lr == 1e-3  # nothing lost
    assert (replaced / "comparisons" / "sp_vs_sa" / "summary.json").is_file()
    assert load_config(out / "runs" / "sa" / "config.yaml").ppo.lr == 2e-3
    summary = json.loads((out / "summary.json").read_text())
    theirs = json.loads((finished / "summary.json").read_text())
    assert summary["runs"][0] == {**theirs["runs"][0], "wall_s": summary["runs"][0]["wall_s"]}  # sp untouched
    assert summary["runs"][1]["fingerprint"] != theirs["runs"][1]["fingerprint"]  # sa trained again ...
    assert read_csv(out / "runs" / "sa" / "metrics.csv") != read_csv(finished / "runs" / "sa" / "metrics.csv")
    compared = [json.loads((d / "comparisons" / "sp_vs_sa" / "summary.json").read_text()) for d in (out, replaced)]
    assert compared[0]["study_inputs"]["runs"]["sa"] != compared[1]["study_inputs"]["runs"]["sa"]  # ... and compared
    assert {e["status"] for e in study_status(out)} == {"done"}
    # The same command again (as after a stop) continues: it set the retrained run aside and trained it anew.
    trained = {p: p.read_bytes() for p in (out / "runs" / "sa").rglob("*") if p.is_file()}
    code = main(["study", "run", str(path), "--backend", "local", "--out", str(out), "--quiet", "--retrain", "sa"])
    assert code == 0, capsys.readouterr().err
    assert [d.name for d in (out / "replaced").iterdir()] == [replaced.name]
    assert {p: p.read_bytes() for p in (out / "runs" / "sa").rglob("*") if p.is_file()} == trained


def test_a_study_too_big_for_this_machine_is_refused_before_anything_is_written(tmp_path, capsys):
    """--seeds 100000 ended in a ConfigError traceback after study.json was written, and the directory
    then refused every other --seeds."""
    path = write_study(tmp_path / "tiny.yaml", STUDY)
    out = tmp_path / "out"
    assert main(["study", "run", str(path), "--backend", "local", "--out", str(out), "--seeds", "100000"]) == 2
    err = _one_line(capsys)
    assert "run 'sp': population.num_seeds: the run needs about" in err and "but it has" in err, err
    assert not out.exists()


def test_report_out_never_writes_over_what_is_there(finished, tmp_path, capsys):
    """--out into a non-empty folder replaced its report.md; --out DIR/runs/a/xp replaced the run's own
    xp/summary.json, after which every report showed n/a and study run never recomputed it."""
    out = _copy(finished, tmp_path / "study")
    full = tmp_path / "full"
    full.mkdir()
    (full / "report.md").write_text("mine")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    for dest, message in (
        (full, "already holds files"),
        (out / "runs" / "sp" / "xp", "already holds files"),
        (out / "new", "lies inside the study directory"),
        (out / "runs" / "sp" / "new", "lies inside the study directory"),
    ):
        assert main(["study", "report", str(out), "--out", str(dest)]) == 2
        assert message in _one_line(capsys)
    assert (full / "report.md").read_text() == "mine"
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    # A report that fails part-way (a metrics file that is not text) leaves no folder and no staging behind; an
    # empty --out folder is filled whole.
    (out / "runs" / "sa" / "metrics.csv").write_bytes(b"\xff\xfe")
    assert main(["study", "report", str(out), "--out", str(tmp_path / "new")]) == 2
    assert "metrics.csv: damaged: byte 0 is not UTF-8 text" in _one_line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "study"]
    (out / "runs" / "sa" / "metrics.csv").write_bytes(before[out / "runs" / "sa" / "metrics.csv"])
    (tmp_path / "empty").mkdir()
    assert main(["study", "report", str(out), "--out", str(tmp_path / "empty")]) == 0
    assert (tmp_path / "empty" / "report.md").is_file() and sorted(p.name for p in tmp_path.iterdir()) == [
        "empty",
        "full",
        "study",
    ]


def test_a_damaged_result_is_reported_and_its_step_redone(finished, tmp_path, capsys, caplog):
    """An unparsable or foreign result counted as done: every report crashed on it (JSONDecodeError) and
    study run never redid the step. Then the report said it only inside report.md, and status said "done"."""
    out = _copy(finished, tmp_path / "study")
    (out / "comparisons" / "sp_vs_sa" / "summary.json").write_text("{not json")
    (out / "runs" / "sp" / "xp" / "summary.json").write_text(json.dumps({"study": "tiny", "runs": []}))
    snapshot = sorted((out / "over_training" / "sp").glob("update_*.json"))[1]
    snapshot.write_text("[" * 100_000)
    caplog.set_level("WARNING", logger="cluster.cli.study")
    assert main(["study", "report", str(out)]) == 0
    report = (out / "report.md").read_text()
    assert "n/a (" in report and "xp/summary.json is not a result of this step (no sp_mean" in report
    assert "comparisons/sp_vs_sa/summary.json is unreadable (" in report
    assert f"over_training sp: {snapshot} is unreadable (JSON nested deeper than" in report
    warned = [record.getMessage() for record in caplog.records]
    assert [line.split(":")[0] for line in warned] == ["train sp", "over_training sp", "compare sp_vs_sa"], warned
    assert all(line.endswith("; its cells say n/a, and `ocv2 study run` redoes the step") for line in warned)
    status = {entry["step"]: (entry["status"], entry["detail"]) for entry in study_status(out)}
    assert status["train sa"] == ("done", "")
    for step, why in [
        ("train sp", "xp/summary.json is not a result of this step (no sp_mean"),
        ("over_training sp", f"{snapshot} is unreadable (JSON nested deeper than"),
        ("compare sp_vs_sa", "comparisons/sp_vs_sa/summary.json is unreadable ("),
    ]:
        assert status[step][0] == "to redo" and why in status[step][1], status[step]
        assert status[step][1].endswith("; `ocv2 study run` does it again")
    said = []
    run_study(load_study(write_study(tmp_path / "tiny.yaml", STUDY)), out, LOCAL, say=said.append)
    again = [line for line in said if "doing the step again" in line]
    assert [line.split(": ")[1] for line in again] == ["train sp", "over_training sp", "compare sp_vs_sa"], said
    assert numbers(out) == numbers(finished)
    assert "Not finished" not in (out / "report.md").read_text()


def test_a_run_summary_of_other_episodes_is_evaluated_again_not_trained_again(finished, tmp_path):
    """``ocv2 xp RUN --episodes 1`` rewrites xp/summary.json in place: the study counted those 1-episode numbers
    as the run's (eval.episodes 2) and reported them."""
    out = _copy(finished, tmp_path / "study")
    run = out / "runs" / "sp"
    summary = json.loads((run / "xp" / "summary.json").read_text())
    assert summary["episodes_per_pair"] == 2 and summary["num_policies"] == 2
    (run / "xp" / "summary.json").write_text(json.dumps({**summary, "episodes_per_pair": 1, "sp_mean": -1.0}))
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    configs = plan_study(study, out, LOCAL).configs
    problem = result_problem(Step("train", "sp"), study, out, configs)
    assert problem is not None and "made with 1 episodes per pair of 2 policies" in problem, problem
    # the report alone (no `study run`) shows the problem, not those numbers as the run's
    assert main(["study", "report", str(out)]) == 0
    report = (out / "report.md").read_text()
    assert "made with 1 episodes per pair of 2 policies" in report and "-1.0" not in report, report
    (run / "xp" / "summary.json").write_text(json.dumps({**summary, "num_policies": 3}))
    assert "of 3 policies, not the run's eval.episodes 2 of its 2 seeds" in result_problem(
        Step("train", "sp"), study, out, configs
    )
    trained = {p: p.read_bytes() for p in (run / "checkpoints").rglob("*") if p.is_file()}
    trained[run / "metrics.csv"] = (run / "metrics.csv").read_bytes()
    said = []
    run_study(study, out, LOCAL, say=said.append)
    assert [line.split(": ")[1] for line in said if "doing the step again" in line] == ["train sp"], said
    assert {p: p.read_bytes() for p in trained} == trained  # evaluated again, not trained again
    assert result_problem(Step("train", "sp"), study, out, configs) is None
    assert numbers(out) == numbers(finished)


def test_a_run_directory_gone_missing_is_reported_as_such_not_as_not_started(finished, tmp_path, capsys):
    out = _copy(finished, tmp_path / "study")
    shutil.rmtree(out / "runs" / "sa")
    assert main(["study", "report", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    sa = next(run for run in summary["runs"] if run["name"] == "sa")
    assert sa["status"] == "damaged" and "missing, though study.json records the step as done" in sa["problem"]
    assert "train sa: " in (out / "report.md").read_text()
    capsys.readouterr()
    assert main(["study", "status", str(out)]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("train sa ")]
    assert "missing" in line and "missing, though study.json records the step as done" in line
    # A pack of it would look resumable and train sa again from update 0: refused, nothing written.
    assert main(["study", "pack", str(out), "--out", str(tmp_path / "packed")]) == 2
    assert "runs/sa: missing, though study.json records its training as done; nothing was packed" in _one_line(capsys)
    assert not (tmp_path / "packed").exists()


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda s: s.pop("spec"), "spec: expected the study file's data (an object), got 'nothing'"),
        (lambda s: s.update(steps=[]), "steps: expected an object of steps, got []"),
        (lambda s: s.update(budget="x"), "budget: expected a number in (0, 100], got 'x'"),
        (lambda s: s.update(budget=10**400), "budget: expected a number in (0, 100], got 1000000"),
        (lambda s: s.update(budget_mode="squeeze"), "budget_mode: expected truncate or compress, got 'squeeze'"),
        (lambda s: s.update(seeds=True), "seeds: expected null or a positive integer, got True"),
        (lambda s: s.update(set="a=b"), "set: expected a list of section.key=value overrides"),
        (lambda s: s["steps"].update(x="done"), "steps['x']: expected an object, got 'done'"),
        (lambda s: s["steps"]["train sp"].update(status="finished"), "steps['train sp'].status: expected left"),
        (lambda s: s["steps"]["train sp"].update(wall_s="1"), "steps['train sp'].wall_s: expected a number"),
        (lambda s: s.update(study="tiny\n"), "study: expected the study's name"),
        ("[" * 40 + "]" * 40, "unreadable (JSON nested deeper than 32 levels)"),
        ("{" + '"a": 1, ' * 3 + "", "unreadable (Expecting property name"),
    ],
    ids=lambda v: None if callable(v) else v[:30],
)
def test_a_damaged_study_json_is_one_line_naming_the_field(finished, tmp_path, capsys, change, message):
    """study.json without spec was a KeyError, steps: [] an AttributeError, budget: "x" a TypeError."""
    out = tmp_path / "study"
    out.mkdir()
    state = json.loads((finished / "study.json").read_text())
    if callable(change):
        change(state)
    text = json.dumps(state) if callable(change) else change
    (out / "study.json").write_text(text)
    study = str(write_study(tmp_path / "tiny.yaml", STUDY))
    for command in (
        ["status", str(out)],
        ["report", str(out)],
        ["run", study, "--out", str(out), "--backend", "local"],
    ):
        assert main(["study", *command]) == 2
        err = _one_line(capsys)
        assert f"{out / 'study.json'}: {message}" in err, err
    assert (out / "study.json").read_text() == text  # nothing rewritten


def test_a_kept_spec_that_no_longer_parses_names_study_json(finished, tmp_path, capsys):
    out = _copy(finished, tmp_path / "study")
    state = json.loads((out / "study.json").read_text())
    state["spec"]["runs"][0]["paper"]["sp"] = 10**400  # JSON holds it; a float cannot (an OverflowError)
    (out / "study.json").write_text(json.dumps(state))
    for command in ("status", "report"):
        assert main(["study", command, str(out)]) == 2
        err = _one_line(capsys)
        assert f"{out / 'study.json'}: spec: " in err and "run 'sp'.paper.sp: expected a number" in err, err[:300]


def test_a_kept_override_that_no_longer_loads_names_study_json_not_the_study_file(finished, tmp_path, capsys):
    """The bad value is in the spec study.json keeps; the error named the study file, which may hold no such value,
    and status said nothing of a run that could not go on."""
    out = _copy(finished, tmp_path / "study")
    state = json.loads((out / "study.json").read_text())
    state["spec"]["set"] = [*state["spec"]["set"], "run.num_checkpoints=abc"]
    del state["steps"]["train sa"]  # sa not trained yet: status plans it
    shutil.rmtree(out / "runs" / "sa")
    (out / "study.json").write_text(json.dumps(state))
    assert main(["study", "report", str(out)]) == 2
    err = _one_line(capsys)
    assert err.startswith(f"ocv2 study: error: {out / 'study.json'} (the spec it keeps from ") and "'abc'" in err
    assert main(["study", "status", str(out)]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("train sa ")]
    assert f"cannot go on: {out / 'study.json'} (the spec it keeps from" in line


def test_paths_that_are_files_are_one_line_errors(finished, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    study = str(write_study(tmp_path / "tiny.yaml", STUDY))
    for command, message in (
        (["run", study, "--out", str(afile), "--backend", "local"], f"{afile}: is a file, not a study directory"),
        (["run", study, "--out", str(afile / "sub"), "--backend", "local"], f"{afile} is a file, not a directory"),
        (
            ["run", study, "--out", os.devnull, "--backend", "local"],
            f"{os.devnull}: is a special file (a device, pipe or socket), not a study directory",
        ),
        (["status", str(afile)], f"{afile}: is a file, not a study directory"),
        (["status", str(afile / "sub")], f"{afile} is a file, not a directory"),
        (["report", str(afile)], f"{afile}: is a file, not a study directory"),
        (["report", str(finished), "--out", str(afile)], f"--out {afile}: is a file; give a new directory"),
        (["report", str(finished), "--out", str(afile / "r")], f"lies under {afile}, which is a file"),
    ):
        assert main(["study", *command]) == 2, command
        assert message in _one_line(capsys), command
    assert afile.read_text() == "mine"
    assert main(["export", str(finished / "runs" / "sp"), "--out", str(afile / "p.policy")]) == 2
    assert f"--out {afile / 'p.policy'}: lies under {afile}, which is a file" in _one_line(capsys)


def test_export_never_writes_over_a_file_unless_forced_nor_into_a_run(finished, tmp_path, capsys):
    """ocv2 export RUN --out RUN/config.yaml replaced the run's config (the run was then unusable)."""
    run = _copy(finished, tmp_path / "study") / "runs" / "sp"
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    for out, message in (
        (run / "config.yaml", "exists; pass --force to replace it"),
        (run / "new.ocv2policy", f"lies inside the run directory {run}"),
        (run / "checkpoints" / "seed_0" / "p.ocv2policy", f"lies inside the run directory {run}"),
    ):
        assert main(["export", str(run), "--out", str(out)]) == 2
        assert message in _one_line(capsys)
    assert main(["export", str(run), "--out", str(run / "config.yaml"), "--force"]) == 2
    assert f"lies inside the run directory {run}" in _one_line(capsys)
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    mine = tmp_path / "mine.ocv2policy"
    mine.write_text("an older export")
    assert main(["export", str(run), "--out", str(mine)]) == 2
    assert "exists; pass --force" in _one_line(capsys) and mine.read_text() == "an older export"
    assert main(["export", str(run), "--out", str(mine), "--force"]) == 0
    assert policy.load(mine).name


def test_export_never_writes_into_a_study_a_published_folder_or_a_pack(finished, tmp_path, capsys):
    """--force let ocv2 export replace a study's study.json (its only state), a published policy that
    SHA256SUMS.json lists, or a pack's pack.json; without it, a new file in a published folder failed ocv2 verify."""
    study = _copy(finished, tmp_path / "study")
    run = study / "runs" / "sp"
    published, packed = tmp_path / "published", tmp_path / "packed"
    assert main(["study", "publish", str(study), "--out", str(published)]) == 0
    assert main(["study", "pack", str(study), "--out", str(packed)]) == 0
    capsys.readouterr()
    listed = next(published.glob("*.ocv2policy"))
    folders = (study, published, packed)
    before = {p: p.read_bytes() for folder in folders for p in folder.rglob("*") if p.is_file()}
    for out, message in (
        (study / "study.json", f"lies inside the study directory {study}"),
        (study / "plots" / "p.ocv2policy", f"lies inside the study directory {study}"),
        (listed, f"{published} is a published policies folder ('ocv2 study publish' writes it) (SHA256SUMS.json)"),
        (published / "new.ocv2policy", f"{published} is a published policies folder"),
        (packed / "pack.json", f"{packed} is a packed study (pack.json)"),
    ):
        assert main(["export", str(run), "--out", str(out), "--force"]) == 2
        assert f"--out {out}: {message}" in _one_line(capsys)
    assert {p: p.read_bytes() for folder in folders for p in folder.rglob("*") if p.is_file()} == before
    assert main(["verify", str(published)]) == 0


@pytest.mark.parametrize("errno_", [errno.ENOSPC, errno.EROFS])
def test_a_full_disk_or_read_only_folder_is_one_line_in_every_command(finished, tmp_path, capsys, monkeypatch, errno_):
    """study run, study report, export and xp --out ended in OSError tracebacks; ocv2 train alone had a
    one-line handler. The failing write is simulated (every file goes through ocv2.atomic)."""
    study = str(write_study(tmp_path / "tiny.yaml", STUDY))
    text = os.strerror(errno_)

    def fails(path):
        raise OSError(errno_, text, str(path))

    monkeypatch.setattr(ocv2.atomic, "_fsync_path", fails)
    commands = [
        ["study", "run", study, "--backend", "local", "--out", str(tmp_path / "s"), "--quiet"],
        ["study", "report", str(finished), "--out", str(tmp_path / "r")],
        ["export", str(finished / "runs" / "sp"), "--out", str(tmp_path / "p.ocv2policy")],
    ]
    for command in commands:
        assert main(command) == 1, command
        err = _one_line(capsys)
        assert err.startswith(f"ocv2 {command[0]}: error: {text} (") and "run the" in err, err
    assert not (tmp_path / "p.ocv2policy").exists()
    # ocv2 xp fails at its first write, the jobs it keeps (OUT.unfinished), before it plays anything
    monkeypatch.setattr(crossplay, "play_seat_fair", lambda *a, **k: pytest.fail("played on a full disk"))
    command = ["xp", "--rows", str(finished / "runs" / "sp"), "--backend", "local", "--out", str(tmp_path / "x")]
    assert main(command) == 1
    assert _one_line(capsys).startswith(f"ocv2 xp: error: {text} ({tmp_path / 'x.unfinished'}/.request.tmp-")
    assert not (tmp_path / "x.unfinished").exists() and not (tmp_path / "x").exists()


def test_a_pack_of_the_latest_checkpoints_only_still_resumes(finished, tmp_path):
    """``latest_only`` leaves the kept snapshots behind (a 10-seed CNN checkpoint is about 13.5 MB): what is
    left is each seed's newest checkpoint, which is what resuming needs."""
    whole = pack_study(finished, tmp_path / "whole")
    latest = pack_study(finished, tmp_path / "latest", latest_only=True)
    assert latest["bytes"] < whole["bytes"] and latest["latest_only"]
    moved = tmp_path / "moved"
    assert main(["study", "unpack", str(tmp_path / "latest"), "--out", str(moved)]) == 0
    for seed in range(2):
        assert ckpt.list_updates(moved / "runs" / "sp", seed) == [4]
        assert ckpt.list_updates(moved / "runs" / "sa", seed) == [8]


def test_a_pack_into_an_empty_folder_stopped_between_moves_leaves_it_empty(finished, tmp_path, monkeypatch):
    """An empty --out is filled in place, one move per file: pack.json went first, so a stop on the next move left
    a folder holding only pack.json, read as a finished pack, which a rerun refused as not empty."""
    dest = tmp_path / "pack"
    dest.mkdir()
    rename, asked = Path.rename, []

    def stopped_on_the_second_move(self, target):
        asked.append(self.name)
        if len(asked) == 2:
            raise KeyboardInterrupt  # SIGTERM, as the CLI sees it
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", stopped_on_the_second_move)
    with pytest.raises(KeyboardInterrupt):
        pack_study(finished, dest)
    monkeypatch.undo()
    assert asked == ["study.tar.gz.000", "pack.json"] and list(dest.iterdir()) == []
    assert main(["study", "pack", str(finished), "--out", str(dest)]) == 0
    assert main(["study", "unpack", str(dest), "--out", str(tmp_path / "unpacked")]) == 0


def test_a_latest_only_pack_after_a_save_cut_short_keeps_the_update_every_seed_has(finished, tmp_path, capsys):
    """Seeds are saved one at a time, so a stop part-way leaves seed 0 one stop ahead of seed 1. The pack kept each
    seed's newest file, which shared no update: its resume started over from update 0, pruning checkpoints and
    cutting metrics.csv back. It now keeps the newest update both have; seeds that share none stop it."""
    study = _copy(finished, tmp_path / "study")
    sa = study / "runs" / "sa"
    ckpt.checkpoint_path(sa, 1, ckpt.list_updates(sa, 1)[-1]).unlink()  # seed 1's last save never happened
    newest, common = ckpt.list_updates(sa, 0)[-1], ckpt.list_updates(sa, 1)[-1]
    pack_study(study, tmp_path / "pack", latest_only=True)
    moved = tmp_path / "moved"
    assert main(["study", "unpack", str(tmp_path / "pack"), "--out", str(moved)]) == 0
    assert [ckpt.list_updates(moved / "runs" / "sa", seed) for seed in range(2)] == [[common], [common]]
    for seed, kept in ((0, newest), (1, common)):  # as a pack of each seed's newest file left them
        for update in ckpt.list_updates(sa, seed):
            if update != kept:
                ckpt.checkpoint_path(sa, seed, update).unlink()
    assert main(["study", "pack", str(study), "--out", str(tmp_path / "refused"), "--latest-only"]) == 2
    err = _one_line(capsys)
    assert f"{sa / 'checkpoints'}: the seeds share no checkpoint update (seed 0: {newest}; seed 1: {common})" in err
    assert "nothing was packed" in err and not (tmp_path / "refused").exists()


def test_pack_refuses_a_study_another_process_is_running(finished, tmp_path, capsys):
    """A running study prunes checkpoints and saves its seeds one at a time: a pack taken meanwhile lost a listed
    file (a raw FileNotFoundError) or caught the seeds at different updates. The study's lock says it runs."""
    study = _copy(finished, tmp_path / "study")
    dest = tmp_path / "pack"
    code = (
        "import sys, time; from cluster.runtime.rundir import DirLock; lock = DirLock(sys.argv[1]); lock.acquire(); "
        "print('held', flush=True); time.sleep(120)"
    )
    holder = subprocess.Popen([sys.executable, "-c", code, str(study)], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        assert main(["study", "pack", str(study), "--out", str(dest), "--latest-only"]) == 2
        err = _one_line(capsys)
        assert f"{study}: in use by another ocv2 process (pid {holder.pid}); stop it first" in err
        assert "nothing was packed" in err and not dest.exists()
    finally:
        holder.kill()
        holder.wait()
    assert main(["study", "pack", str(study), "--out", str(dest), "--latest-only"]) == 0


def kept_and_state(data: dict, out: Path) -> tuple:
    """The study a study.json mapping keeps, and its typed state: what ``snapshots_still_read`` reads."""
    state = StudyState.from_json(data, out / "study.json")
    return kept_study(state, out), state


def test_a_latest_only_pack_keeps_the_snapshots_a_step_to_come_reads(finished, tmp_path, monkeypatch):
    """A study packed before its over_training step ran still has that step's snapshots after unpacking, and the
    step then gives the numbers of the uninterrupted study; an unfinished FCP run keeps its partners' snapshots.
    The snapshot and comparison steps play at the runs' run.precision and record it."""
    before = tmp_path / "before"
    shutil.copytree(finished, before)
    data = json.loads((before / "study.json").read_text())
    data["steps"]["over_training sp"] = {"status": "left", "wall_s": 0.0}
    data["steps"]["compare sp_vs_sa"] = {"status": "left", "wall_s": 0.0}
    (before / "study.json").write_text(json.dumps(data))
    shutil.rmtree(before / "over_training" / "sp")
    shutil.rmtree(before / "comparisons" / "sp_vs_sa")
    players, played_at = crossplay.players, []

    def recording_players(*args, **kwargs):
        played_at.append(kwargs.get("precision"))
        return players(*args, **kwargs)

    monkeypatch.setattr(crossplay, "players", recording_players)
    record = pack_study(before, tmp_path / "pack", latest_only=True)
    assert record["kept_whole"] == ["runs/sp"]
    moved = tmp_path / "moved"
    assert main(["study", "unpack", str(tmp_path / "pack"), "--out", str(moved)]) == 0
    for seed in range(2):
        assert ckpt.list_updates(moved / "runs" / "sp", seed) == ckpt.list_updates(finished / "runs" / "sp", seed)
        assert len(ckpt.list_updates(moved / "runs" / "sp", seed)) > 1
        assert ckpt.list_updates(moved / "runs" / "sa", seed) == [8]  # no step to come reads sa's older ones
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    run_study(study, moved, StudyOptions(backend="local", show_progress=False), say=lambda _: None)
    for path in sorted((finished / "over_training" / "sp").glob("update_*.json")):
        again = json.loads((moved / "over_training" / "sp" / path.name).read_text())
        assert again["matrix"] == json.loads(path.read_text())["matrix"] and again["precision"] == "float32"
    assert played_at == ["float32", "float32"]  # the snapshots', then the comparison's
    compared = json.loads((moved / "comparisons" / "sp_vs_sa" / "summary.json").read_text())
    assert compared["precision"] == "float32"
    assert (
        compared["blocks"] == json.loads((finished / "comparisons" / "sp_vs_sa" / "summary.json").read_text())["blocks"]
    )
    # FCP, while it trains: the partner run its pool comes from, or else its own partner stage.
    fcp = {"name": "fcp", "config": str(SMOKE), "set": ["population.method=fcp"], "partners_from": "sp"}
    data["spec"]["runs"].append(fcp)
    data["steps"]["over_training sp"] = {"status": "done", "wall_s": 1.0}
    data["steps"]["train fcp"] = {"status": "running", "wall_s": 1.0, "update": 2}
    kept = snapshots_still_read(*kept_and_state(data, before), before)
    assert kept == (before / "runs" / "sp",)
    del fcp["partners_from"]
    kept = snapshots_still_read(*kept_and_state(data, before), before)
    assert kept == (before / "runs" / "fcp" / "partners",)
    # A run study.json calls done whose result is damaged is trained again, so what it reads is kept too.
    data["steps"]["train fcp"] = {"status": "done", "wall_s": 1.0}
    kept = snapshots_still_read(*kept_and_state(data, before), before)
    assert kept == (before / "runs" / "fcp" / "partners",)


def test_study_json_reads_into_typed_state_and_writes_back_the_same_shape(finished, tmp_path):
    """The runner works with ``StudyState``; the file keeps the shape it always had, so directories and packs made
    before the typed state resume unchanged (a field this version does not know is kept, not dropped)."""
    data = json.loads((finished / "study.json").read_text())
    state = StudyState.from_json(data, finished / "study.json")
    assert state.study == "tiny" and state.budget_mode == "truncate" and state.overrides == ()
    assert all(isinstance(step, StepRecord) and step.done for step in state.steps.values())
    assert state.steps["train sp"].results == {"update": data["steps"]["train sp"]["update"]}
    assert state.to_json() == data
    older = {**data, "future_field": [1, 2]}
    del older["budget_mode"], older["set"]  # a directory from before --budget-mode and --set
    state = StudyState.from_json(older, tmp_path / "study.json")
    assert state.budget_mode == "compress" and state.overrides == () and state.extra == {"future_field": [1, 2]}
    assert state.to_json()["future_field"] == [1, 2]
    step = StepRecord()
    step.update(status="done", wall_s=3.0, reason=None, update=7)
    assert step.to_json() == {"status": "done", "wall_s": 3.0, "update": 7}


def test_publish_exports_the_kept_snapshots_with_their_sha256_and_never_rewrites_one(finished, tmp_path, capsys):
    """``ocv2 study publish``: every run's kept snapshots (not update 0) as policy files listed in SHA256SUMS.json;
    each loads to the parameters of its checkpoint; a second call adds nothing, and a listed file that changed stops
    it before anything is written."""
    out = tmp_path / "policies"
    assert main(["study", "publish", str(finished), "--out", str(out)]) == 0
    entries = published.read_listing(out)
    config = load_config(finished / "runs" / "sp" / "config.yaml")
    kept = [u for u in ckpt.snapshot_updates(config.ppo.num_updates, config.run.num_checkpoints) if u > 0]
    assert sorted((e.seed, e.update) for e in entries if e.file.startswith("sp_")) == [
        (seed, u) for seed in range(2) for u in kept
    ]
    assert {e.file for e in entries} == {p.name for p in out.glob("*.ocv2policy")}
    published.verify(out, [e.file for e in entries])
    entry = next(e for e in entries if e.file.startswith("sp_seed1_"))
    assert entry.env_steps == entry.update * config.ppo.steps_per_update
    mine = policy.load(out / entry.file).params
    theirs = policy.load(finished / "runs" / "sp", seed=1, checkpoint=entry.update).params
    for x, y in zip(jax.tree.leaves(mine), jax.tree.leaves(theirs), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    listing = (out / published.SUMS).read_bytes()
    assert main(["study", "publish", str(finished), "--out", str(out)]) == 0
    assert "0 policies exported" in capsys.readouterr().out and (out / published.SUMS).read_bytes() == listing
    target = out / entry.file
    target.write_bytes(target.read_bytes()[:-1])
    assert main(["study", "publish", str(finished), "--out", str(out), "--which", "all"]) == 2
    assert f"{target}: not the published file" in capsys.readouterr().err
    assert (out / published.SUMS).read_bytes() == listing
    assert main(["study", "publish", str(tmp_path), "--out", str(tmp_path / "p")]) == 2
    assert "no study.json here" in capsys.readouterr().err


def test_publish_final_takes_each_seeds_last_checkpoint_only(finished, tmp_path):
    added = published.publish_run(finished / "runs" / "sa", tmp_path, which="final")
    assert [(e.seed, e.update) for e in added] == [(0, 8), (1, 8)]
    with pytest.raises(ValueError, match="expected one of snapshots, final, all"):
        published.updates_to_publish(finished / "runs" / "sa", 0, which="best")
    (tmp_path / published.SUMS).write_text('{"not": "a list"}')
    with pytest.raises(policy.PolicyError, match="a list of entries expected"):
        published.read_listing(tmp_path)


def test_publish_into_the_study_or_a_run_directory_is_refused(finished, tmp_path):
    """Policy files beside a run's config.yaml and checkpoints (or anywhere a later pack would hold them)."""
    copy = tmp_path / "study"
    shutil.copytree(finished, copy)
    other = tmp_path / "other_run"
    shutil.copytree(finished / "runs" / "sp", other)
    for out, where in (
        (copy / "runs" / "sp", "study directory"),
        (copy / "pub", "study directory"),
        (other, "run directory"),
        (other / "p", "run directory"),
    ):
        with pytest.raises(StudyError, match=rf"--out {out}: lies inside the {where}"):
            publish_study(copy, out)
        assert not list(out.glob("*.ocv2policy")) and not (out / published.SUMS).exists()


def test_publish_leaves_no_unlisted_file_and_refuses_two_runs_of_one_name(finished, tmp_path, monkeypatch):
    """Interrupted after a file was written but before it was listed, publishing left the file behind (and the
    next publish refused it); two run directories of one name wrote the same file names over each other."""
    out = tmp_path / "policies"
    real = published.sha256_of

    def interrupted(path):
        raise KeyboardInterrupt

    monkeypatch.setattr(published, "sha256_of", interrupted)
    with pytest.raises(KeyboardInterrupt):
        published.publish_run(finished / "runs" / "sa", out, which="final")
    assert not out.exists()  # the file exported before the interrupt went with the folder it made
    monkeypatch.setattr(published, "sha256_of", real)
    twin = _copy(finished / "runs" / "sa", tmp_path / "elsewhere" / "sa")
    with pytest.raises(policy.PolicyError, match=r"both would publish sa_seed0_update8.ocv2policy"):
        published.publish_runs([finished / "runs" / "sa", twin], out, which="final")
    assert not out.exists()


def test_publish_is_all_runs_or_none_and_never_writes_over_a_file(finished, tmp_path, capsys):
    """A file of a name to be written that the listing does not know is refused before anything is written; a listing that is a folder or not text is named; a --which that selects nothing is an error,
    while one whose every file is already listed says so and exits 0."""
    study = _copy(finished, tmp_path / "study")
    out = tmp_path / "policies"
    clash = tmp_path / "clash"
    clash.mkdir()
    (clash / "sa_seed0_update8.ocv2policy").write_text("precious")
    assert main(["study", "publish", str(finished), "--out", str(clash), "--which", "final"]) == 2
    assert "sa_seed0_update8.ocv2policy: exists but is not listed in" in _one_line(capsys)
    assert [p.name for p in clash.iterdir()] == ["sa_seed0_update8.ocv2policy"]
    assert (clash / "sa_seed0_update8.ocv2policy").read_text() == "precious"
    for name, listing, said in (
        ("folder", None, "a folder, not the listing file"),
        ("bytes", b"\xff\xfe", "not UTF-8"),
    ):
        target = tmp_path / name
        (target / published.SUMS).mkdir(parents=True) if listing is None else None
        if listing is not None:
            target.mkdir()
            (target / published.SUMS).write_bytes(listing)
        assert main(["study", "publish", str(finished), "--out", str(target), "--which", "final"]) == 2
        assert said in _one_line(capsys) and len(list(target.iterdir())) == 1
    (study / "runs" / "sp" / "checkpoints").rename(study / "runs" / "sp" / "moved")
    (study / "runs" / "sa" / "checkpoints").rename(study / "runs" / "sa" / "moved")
    assert main(["study", "publish", str(study), "--out", str(out)]) == 2
    assert "nothing to publish: no checkpoint of" in _one_line(capsys) and not out.exists()
    assert main(["study", "publish", str(finished), "--out", str(out), "--which", "final"]) == 0
    assert main(["study", "publish", str(finished), "--out", str(out), "--which", "final"]) == 0
    assert "nothing new; every checkpoint --which final selects is already listed" in capsys.readouterr().out


def test_study_pack_latest_only_from_the_command_line(finished, tmp_path):
    assert main(["study", "pack", str(finished), "--out", str(tmp_path / "p"), "--latest-only"]) == 0
    assert json.loads((tmp_path / "p" / "pack.json").read_text())["latest_only"] is True


def _stop_and_pack():
    spec = importlib.util.spec_from_file_location("stop_and_pack", ROOT / "study_state" / "stop_and_pack.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _sleeper(out, cwd=None, ignore=("SIGINT",)) -> subprocess.Popen:
    """A stand-in for `ocv2 study run ... --out OUT` started in the background: SIGINT ignored, SIGTERM ends it
    (unless ``ignore`` names it too: a chunk in flight that takes longer than the wait)."""
    ignored = "".join(f"signal.signal(signal.{name}, signal.SIG_IGN); " for name in ignore)
    code = f"import signal, time; {ignored}time.sleep(60)"
    argv = [sys.executable, "-c", code, "--out", str(out)]
    return subprocess.Popen(argv, cwd=cwd, stderr=subprocess.DEVNULL)


def test_stop_and_pack_interrupts_the_study_run_of_its_out_folder_and_no_other(tmp_path):
    """study_state/stop_and_pack.py's stop(): a pattern starting with "--out" once went to pgrep as an option, so
    nothing was found, nothing stopped, and a study still training was packed; then a pattern match also took
    `--out <study>_pilot`. The --out argument is now compared as a path (a relative one from the process's own
    working directory)."""
    module = _stop_and_pack()
    out = tmp_path / "study"
    out.mkdir()
    sibling, relative = _sleeper(tmp_path / "study_pilot"), _sleeper("study", cwd=tmp_path)
    try:
        module.stop(out)
        assert relative.wait(timeout=10) != 0  # ended by SIGTERM, well before its 60 s
        assert sibling.poll() is None
    finally:
        sibling.kill()
        relative.kill()


def test_stop_and_pack_kills_a_study_whose_chunk_outlasts_the_wait(tmp_path):
    """On a slower CPU a chunk took 27 minutes, and the wait before SIGKILL was a fixed 10: it is --wait now."""
    module = _stop_and_pack()
    out = tmp_path / "study"
    out.mkdir()
    busy = _sleeper(out, ignore=("SIGINT", "SIGTERM"))
    try:
        time.sleep(1)  # its signal handlers are set
        started = time.monotonic()
        module.stop(out, wait_s=2)
        assert busy.wait(timeout=10) == -signal.SIGKILL
        assert 2 <= time.monotonic() - started < 20
    finally:
        busy.kill()


def test_stop_and_pack_packs_then_publishes_and_packs_again_over_its_last_pack(finished, tmp_path):
    """The whole script, twice: the first pack of a study (no earlier one to set aside once made it fail after
    packing), then a second that replaces it; the policies are published once."""
    study = _copy(finished, tmp_path / "study")
    script = [sys.executable, str(ROOT / "study_state" / "stop_and_pack.py"), str(study)]
    script += ["--into", str(tmp_path / "state"), "--policies", str(tmp_path / "policies")]
    (tmp_path / "state").mkdir()
    for attempt in range(2):
        done = subprocess.run(script, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert "packed " in done.stdout and "no `ocv2 study run" in done.stdout
        assert sorted(p.name for p in (tmp_path / "state").iterdir()) == ["tiny"]  # no .new or .old left
        assert json.loads((tmp_path / "state" / "tiny" / "pack.json").read_text())["latest_only"] is True
        exported = sum(int(line.split(": ")[1].split()[0]) for line in done.stdout.splitlines() if "policies" in line)
        assert (exported > 0) == (attempt == 0)
    published.verify(tmp_path / "policies", [e.file for e in published.read_listing(tmp_path / "policies")])


def test_stop_and_pack_checks_everything_before_it_stops_the_study(finished, tmp_path):
    """A broken run config, or a policies folder that is a file, ends the script before the study is stopped:
    the training goes on and nothing is published or packed."""
    study = _copy(finished, tmp_path / "study")
    script = [sys.executable, str(ROOT / "study_state" / "stop_and_pack.py"), str(study), "--into", str(tmp_path)]
    (tmp_path / "a_file").write_text("x")
    config = next((study / "runs").glob("*/config.yaml"))
    good = config.read_text()
    for problem, extra, expected in [
        ("config", [], f"{config}: not valid YAML"),
        ("policies", ["--policies", str(tmp_path / "a_file")], "a file, not a policies folder"),
    ]:
        config.write_text("ppo: [" if problem == "config" else good)
        training = _sleeper(study)
        try:
            done = subprocess.run([*script, *extra], capture_output=True, text=True, timeout=120)
            assert done.returncode != 0 and expected in done.stderr, done.stderr
            assert "nothing was stopped, published or packed" in done.stderr and "Traceback" not in done.stderr
            assert training.poll() is None
        finally:
            training.kill()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "study"]


def test_pack_checks_the_study_and_every_checkpoint_before_writing(finished, tmp_path, capsys):
    """A damaged study.json, checkpoint, run config or manifest stops `study pack` with the file named and no pack folder made (a pack
    replaces the last good one between sessions); a pack inside the study would be packed into the next one."""
    study = _copy(finished, tmp_path / "study")
    dest = tmp_path / "packed"
    checkpoint = sorted((study / "runs").glob("*/checkpoints/seed_0/update_*.msgpack"))[-1]
    good = checkpoint.read_bytes()
    checkpoint.write_bytes(good[: len(good) // 2])
    assert main(["study", "pack", str(study), "--out", str(dest), "--latest-only"]) == 2
    assert f"{checkpoint}: not a readable ocv2 checkpoint" in _one_line(capsys) and not dest.exists()
    checkpoint.write_bytes(good)
    (study / "study.json").write_text('{"study": ')
    assert main(["study", "pack", str(study), "--out", str(dest)]) == 2
    assert "study.json: unreadable" in _one_line(capsys) and not dest.exists()
    shutil.copy(finished / "study.json", study / "study.json")
    assert main(["study", "pack", str(study), "--out", str(study / "packed")]) == 2
    assert "inside the study directory" in _one_line(capsys) and not (study / "packed").exists()
    for damaged, said in (
        ("config.yaml", "its config.yaml is unusable"),
        ("manifest.json", "manifest.json: is not valid JSON"),
    ):
        path = study / "runs" / "sa" / damaged
        good = path.read_bytes()
        path.write_text("garbage: [")
        assert main(["study", "pack", str(study), "--out", str(dest)]) == 2
        assert said in _one_line(capsys) and not dest.exists()
        path.write_bytes(good)
    assert main(["study", "pack", str(study), "--out", str(dest)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["packed", "study"]  # no staging folder left


def test_unpack_names_a_malformed_pack_json_or_a_cut_stream(finished, tmp_path, capsys):
    packed = tmp_path / "packed"
    assert main(["study", "pack", str(finished), "--out", str(packed)]) == 0
    record = json.loads((packed / "pack.json").read_text())
    for parts in (["study.tar.gz.000"], None, [{"file": "../elsewhere", "sha256": "0"}]):
        (packed / "pack.json").write_text(json.dumps({**record, "parts": parts}))
        assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u")]) == 2
        assert "pack.json" in _one_line(capsys) and not (tmp_path / "u").exists()
    (packed / "pack.json").write_text("[" * 100_000)  # json.loads once ended unpack in a RecursionError
    assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u")]) == 2
    assert "pack.json: unreadable (JSON nested deeper than 32 levels)" in _one_line(capsys)
    cut = (packed / "study.tar.gz.000").read_bytes()[:-200]  # listed with its own sum: only gzip sees the cut
    (packed / "study.tar.gz.000").write_bytes(cut)
    parts = [{"file": "study.tar.gz.000", "bytes": len(cut), "sha256": hashlib.sha256(cut).hexdigest()}]
    (packed / "pack.json").write_text(json.dumps({**record, "parts": parts, "bytes": len(cut)}))
    assert main(["study", "unpack", str(packed), "--out", str(tmp_path / "u")]) == 2
    assert "cannot unpack" in _one_line(capsys) and not (tmp_path / "u").exists()
    assert main(["study", "unpack", str(packed / "pack.json"), "--out", str(tmp_path / "u")]) == 2
    assert "a file, not a pack folder" in _one_line(capsys)


def test_publish_stopped_by_a_damaged_checkpoint_leaves_no_unlisted_file(finished, tmp_path, capsys):
    study = _copy(finished, tmp_path / "study")
    out = tmp_path / "policies"
    last_seed = sorted((study / "runs").glob("*/checkpoints/seed_*"))[-1]
    checkpoint = sorted(last_seed.glob("update_*.msgpack"))[-1]
    checkpoint.write_bytes(checkpoint.read_bytes()[:100])
    assert main(["study", "publish", str(study), "--out", str(out), "--which", "final"]) == 2
    assert f"{checkpoint}" in _one_line(capsys)
    # all runs or none: "sa" (exported before "sp" was reached) and the seeds of "sp" before the damaged one are
    # removed, and so is the folder this command made
    assert not out.exists()
    config = next((study / "runs").glob("*/config.yaml"))
    config.write_text("ppo: [")
    assert main(["study", "publish", str(study), "--out", str(out)]) == 2
    assert "not valid YAML" in _one_line(capsys)
    (tmp_path / "a_file").write_text("x")
    shutil.copy(next((finished / "runs").glob("*/config.yaml")), config)
    assert main(["study", "publish", str(study), "--out", str(tmp_path / "a_file")]) == 2
    assert "a file, not a policies folder" in _one_line(capsys)


#: The tiny study at half its budget: what the --extend tests extend to 1.
HALF = StudyOptions(backend="local", show_progress=False, budget=0.5)


def study_at_half(tmp_path: Path, name: str) -> tuple:
    """The tiny study run at ``HALF`` into ``tmp_path / name``: (the study, its directory, its summary.json)."""
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    out = tmp_path / name
    run_study(study, out, HALF, say=lambda _: None)
    return study, out, json.loads((out / "summary.json").read_text())


def test_an_extended_study_reports_what_the_larger_budget_trained_at_once_gives(finished, tmp_path):
    study, out, before = study_at_half(tmp_path, "extended")
    with pytest.raises(StudyError, match=r"started with --budget 0.5; .*or add --extend to train its runs on"):
        plan_study(study, out, dataclasses.replace(HALF, budget=1.0))
    # As `ocv2 study status` sees it right after the old results were set aside: the runs train on.
    plan = plan_study(study, out, dataclasses.replace(HALF, budget=1.0, extend=True))
    aside = StateFile(out, plan.state)
    shutil.copytree(out, tmp_path / "aside")
    _set_aside_results(study, tmp_path / "aside", 0.5, aside, lambda _: None)
    assert {name: step.status for name, step in aside.state.steps.items()} == {"train sp": "left", "train sa": "left"}
    lines = []
    state = run_study(study, out, dataclasses.replace(HALF, budget=1.0, extend=True), say=lines.append)
    assert all(step.done for step in state.steps.values())
    assert [e["from"] for e in state.extensions] == [0.5] and state.budget == 1.0
    assert any("run sa: extended from update 4 to 8" in line for line in lines), lines
    # The same TrainStates, metrics, cross-play and over-training numbers as the study run at budget 1 at once:
    assert_same_runs(out, finished)
    assert numbers(out) == numbers(finished)
    # and nothing made at 0.5 is lost.
    kept = out / "extended" / "budget_0.5"
    assert json.loads((kept / "summary.json").read_text()) == before
    assert (kept / "over_training").is_dir() and (kept / "comparisons").is_dir()
    assert (out / "runs" / "sp" / "extended" / "update_0000002" / "xp" / "summary.json").is_file()
    assert "trained first to budget 0.5, then on along the same schedules to 1" in (out / "report.md").read_text()
    # What the extension changed, per run: the same seeds at 0.5's stop and at 1's, from the kept cross-play.
    now = json.loads((out / "summary.json").read_text())
    since = {entry["run"]: entry for entry in now["since_extension"]}
    assert [(e["run"], e["from_update"]) for e in now["since_extension"]] == [("sp", 2), ("sa", 4)]
    for run_before, run_now in zip(before["runs"], now["runs"], strict=True):
        entry = since[run_now["name"]]
        assert entry["env_steps_per_seed"] == run_now["env_steps_per_seed"] == 2 * entry["from_env_steps_per_seed"]
        assert entry["before"] == {k: run_before["xp"][k] for k in ("sp_mean", "xp_mean", "gap")}
        assert entry["after"] == {k: run_now["xp"][k] for k in ("sp_mean", "xp_mean", "gap")}
        assert entry["delta_gap"] == pytest.approx(run_now["xp"]["gap"] - run_before["xp"]["gap"])
        # 2 seeds: a draw has cross-play only when it holds both, so the paired interval is the change itself.
        assert entry["delta_gap_ci95_interval"] == pytest.approx([entry["delta_gap"]] * 2)
    assert "## Since the extension: the same seeds at the old stop and trained on" in (out / "report.md").read_text()
    # A kept matrix that lost a row: the numbers stay, the interval is refused with the file named.
    cut = out / "runs" / "sp" / "extended" / "update_0000002" / "xp" / "matrix.csv"
    cut.write_text("\n".join(cut.read_text().splitlines()[:-1]) + "\n")
    assert main(["study", "report", str(out), "--out", str(tmp_path / "cut_report")]) == 0
    entry = json.loads((tmp_path / "cut_report" / "summary.json").read_text())["since_extension"][0]
    assert entry["delta_gap"] == since["sp"]["delta_gap"] and "delta_gap_ci95_interval" not in entry
    assert entry["problem"].startswith(f"no interval: {cut}: a 1 x 2 matrix")
    assert ckpt.list_updates(out / "runs" / "sp", 0) == [0, 1, 2, 4]  # 0.5's snapshot at update 1 stays
    # An extended study still refuses a run whose other settings changed (here its learning rate).
    changed = load_study(write_study(tmp_path / "more.yaml", {**STUDY, "set": [*STUDY["set"], "ppo.lr=0.01"]}))
    with pytest.raises(StudyError, match=r"run 'sp': .* was trained with another config \(ppo.lr: 0.001 in the run"):
        plan_study(changed, out, dataclasses.replace(HALF, budget=1.0))
    # Once extended, the same command (or none of the options) continues it as any study.
    assert run_study(study, out, dataclasses.replace(HALF, budget=1.0, extend=True), say=lambda _: None).budget == 1.0


def test_an_extended_run_whose_snapshots_do_not_nest_plays_the_ones_it_kept(tmp_path):
    """sa at 0.5 keeps snapshots 0, 2, 4; at 0.75 its schedule's are 0, 3, 6, and update 3 lies before the
    earlier stop and was never kept: the over-training step stopped the whole study with "no checkpoint at
    update 3". The earlier stop's snapshots stand in for that stretch."""
    alone = {**STUDY, "runs": STUDY["runs"][1:], "over_training": ["sa"], "comparisons": []}  # sa alone: cheaper
    study = load_study(write_study(tmp_path / "tiny.yaml", alone))
    out = tmp_path / "study"
    run_study(study, out, HALF, say=lambda _: None)
    state = run_study(study, out, dataclasses.replace(HALF, budget=0.75, extend=True), say=lambda _: None)
    assert all(step.done for step in state.steps.values())
    folder = out / "over_training" / "sa"
    assert json.loads((folder / "done.json").read_text())["snapshots"] == [0, 2, 4, 6]
    assert sorted(p.name for p in folder.glob("update_*.json")) == [f"update_{u:07d}.json" for u in (0, 2, 4, 6)]
    assert ckpt.run_snapshots(out / "runs" / "sa", 6, 3) == [0, 2, 4, 6]
    assert ckpt.run_snapshots(out / "runs" / "sa", 8, 3) == [0, 4, 8]  # they nest: the longer schedule's own


def test_extend_with_retrain_sets_the_old_results_aside_too(finished, tmp_path):
    study, out, before = study_at_half(tmp_path, "both")
    both = dataclasses.replace(HALF, budget=1.0, extend=True, retrain=("sa",))
    run_study(study, out, both, say=lambda _: None)
    assert json.loads((out / "extended" / "budget_0.5" / "summary.json").read_text()) == before
    assert_same_runs(out, finished)  # sp extended, sa trained again from update 0: the same numbers
    assert numbers(out) == numbers(finished)


def test_extend_with_changed_eval_episodes_extends_first_then_evaluates_with_the_new_count(finished, tmp_path):
    """--extend and a changed eval.episodes in one command: the runs train on (the old stop's cross-play kept
    under extended/ with its 2 episodes per pair), then every cross-play is made with 3; no run is retrained."""
    study, out, before = study_at_half(tmp_path, "extended_more_episodes")
    more = load_study(write_study(tmp_path / "more.yaml", {**STUDY, "set": [*STUDY["set"], "eval.episodes=3"]}))
    plan = plan_study(more, out, dataclasses.replace(HALF, budget=1.0, extend=True))
    assert plan.retrain == () and set(plan.extend) == set(plan.reevaluate) == {"sp", "sa"}
    lines = []
    state = run_study(more, out, dataclasses.replace(HALF, budget=1.0, extend=True), say=lines.append)
    assert all(step.done for step in state.steps.values()) and state.budget == 1.0
    extended = [i for i, line in enumerate(lines) if "extended from update" in line]
    evaluated = [i for i, line in enumerate(lines) if "evaluated again with eval.episodes 3 (was 2" in line]
    assert len(extended) == len(evaluated) == 2 and max(extended) < min(evaluated), lines
    assert_same_runs(out, finished)  # trained on to budget 1 as a study at 1 from the start
    assert json.loads((out / "extended" / "budget_0.5" / "summary.json").read_text()) == before
    for name, stop in (("sp", 2), ("sa", 4)):
        run = out / "runs" / name
        old = json.loads((run / "extended" / f"update_{stop:07d}" / "xp" / "summary.json").read_text())
        assert old["episodes_per_pair"] == 2  # the old stop's evaluation, as it was made
        assert json.loads((run / "xp" / "summary.json").read_text())["episodes_per_pair"] == 3
        assert load_config(run / "config.yaml").eval.episodes == 3
    assert not steps_to_run(plan_study(more, out, dataclasses.replace(HALF, budget=1.0)))  # nothing left to do


def test_extend_is_refused_where_a_larger_budget_is_another_schedule(tmp_path):
    study = load_study(write_study(tmp_path / "tiny.yaml", STUDY))
    squeezed = tmp_path / "squeezed"
    squeezed.mkdir()
    StateFile(squeezed, open_state(study, squeezed, 0.5, None, "local", mode="compress")).save()
    with pytest.raises(StudyError, match=r"--extend: .* compresses each schedule into its budget"):
        open_state(study, squeezed, 1.0, None, "local", extend=True)
    with pytest.raises(StudyError, match="--budget 0.25 is less than the 0.5"):
        StateFile(squeezed, dataclasses.replace(read_state(squeezed), budget_mode="truncate")).save()
        open_state(study, squeezed, 0.25, None, "local", extend=True)
    with pytest.raises(StudyError, match="--extend needs --budget F"):
        open_state(study, squeezed, None, None, "local", extend=True)
    with pytest.raises(StudyError, match="holds no study yet"):
        open_state(study, tmp_path / "new", 0.5, None, "local", extend=True)


def test_the_since_extension_table_shows_numbers_intervals_and_what_is_missing():
    from cluster.study.report import since_extension_lines

    assert since_extension_lines([]) == []  # a study never extended has no such section
    done = {
        "run": "sp",
        "from_update": 2,
        "from_env_steps_per_seed": 1_000_000,
        "env_steps_per_seed": 2_000_000,
        "before": {"sp_mean": 100.0, "xp_mean": 60.0, "gap": 40.0},
        "after": {"sp_mean": 120.0, "xp_mean": 50.0, "gap": 70.0},
        "delta_sp": 20.0,
        "delta_xp": -10.0,
        "delta_gap": 30.0,
        "delta_sp_ci95_interval": [10.0, 30.0],
        "delta_xp_ci95_interval": [-20.0, -1.0],
        "delta_gap_ci95_interval": [12.5, 45.0],
    }
    waiting = {**{k: done[k] for k in ("from_update", "from_env_steps_per_seed", "env_steps_per_seed")}, "run": "sa"}
    waiting |= {"before": done["before"], "problem": "no cross-play at the new stop yet"}
    lines = since_extension_lines([done, waiting])
    assert lines[-2] == (
        "| sp | 1.00M → 2.00M | 100.0 → 120.0 | 60.0 → 50.0 | 40.0 → 70.0 | +20.0 [+10.0, +30.0] "
        "| -10.0 [-20.0, -1.0] | +30.0 [+12.5, +45.0] |"
    )
    assert lines[-1] == "| sa | 1.00M → 2.00M | n/a (no cross-play at the new stop yet) | | | | | |"
