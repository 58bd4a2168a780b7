"""bench/gpu_run.py's plan and bench/gpu_report.py's tables, on made-up measurements (the whole script is
rehearsed end to end by .ci/run's Python 3.12 leg: GPU_RUN_SMOKE=1 bash bench/gpu_run.sh)."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import json
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _bench_module(name: str):
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


gpu_run = _bench_module("gpu_run")
gpu_report = _bench_module("gpu_report")
FULL_STEPS = 10 * 10_000_000  # 10 seeds x the paper's Coordination Ring schedule


def test_a_fast_gpu_trains_the_whole_schedule_then_sa_in_what_is_left():
    steps = gpu_run.plan({"cnn_sp_10": {"env_steps_per_s": 1_000_000}}, seconds_left=400, smoke=False)
    assert [s.study for s in steps] == ["gpu_coord_ring_sp", "gpu_coord_ring_sa"] and steps[0].budget == 1.0
    assert steps[0].train_s == pytest.approx(FULL_STEPS / 1_000_000)
    assert 0.1 <= steps[1].budget <= 1.0
    assert [s.rate_case for s in steps] == ["cnn_sp_10", "cnn_sp_10"]  # gpu_run.json's plan names the rate it used


def test_a_slow_gpu_truncates_the_schedule_and_never_compresses_it(tmp_path):
    rate = 100_000
    (step,) = gpu_run.plan({"cnn_sp_10": {"env_steps_per_s": rate}}, seconds_left=390, smoke=False)
    assert step.study == "gpu_coord_ring_sp" and step.budget == pytest.approx((390 - 90) * rate / FULL_STEPS, abs=1e-3)
    command = step.command(tmp_path, smoke=False)
    assert command[command.index("--budget-mode") + 1] == "truncate"
    assert command[command.index("--seeds") + 1] == "10" and "--backend" in command
    assert "gpu_coord_ring_sp.yaml" in command[command.index("run") + 1]
    # nothing measured: a tenth, and the deadline stops it if that is too much
    guess = gpu_run.plan({"cnn_sp_10": {"error": "boom"}}, 390, smoke=False)[0]
    assert guess.budget == 0.1 and guess.rate_case == ""


def made_up_bench() -> dict:
    trainer = {
        "config": "classic_coord_ring_sp.yaml",
        "model": "cnn",
        "kernels": "auto",
        "precision": "float32",
        "seeds": 10,
        "env_steps_per_s": 400_000.0,
        "model_tflops": 5.0,
        "compile_plus_first_s": 31.0,
    }
    return {
        "environment": {
            "devices": ["gpu: NVIDIA H100 80GB HBM3"],
            "nvidia_smi": "NVIDIA H100 80GB HBM3, 580.159.04, 81559 MiB, 1980 MHz",
            "python": "3.12.3",
            "versions": {"jax": "0.11.2", "mcap": None},
            "XLA_FLAGS": "--xla_gpu_deterministic_ops=true",
        },
        "results": {
            "matmul_f32": {"size": 8192, "tflops": 50.0},
            "matmul_tf32": {"size": 8192, "tflops": 200.0},
            "matmul_bf16": {"size": 8192, "tflops": 500.0},
            "cnn_sp_10": trainer,
            "cnn_sp_10_tf32": {**trainer, "precision": "tf32", "env_steps_per_s": 800_000.0, "model_tflops": 10.0},
            "rnn_sp_10_xla": {"skipped": "the measuring time was spent"},
            "env_ocv2": {"batch": 16384, "steps": 400, "env_steps_per_s": 9e7},
            "env_jaxmarl": {"batch": 16384, "steps": 400, "env_steps_per_s": 3e7},
        },
    }


def test_the_benchmark_block_states_shares_of_the_measured_peaks():
    block = gpu_report.benchmark_block(made_up_bench())
    assert block.startswith(gpu_report.START) and block.endswith(gpu_report.END)
    assert "gpu: NVIDIA H100 80GB HBM3" in block and "jax 0.11.2" in block and "mcap" not in block
    # each share is of the matmul rate at the row's own precision
    assert (
        "| cnn_sp_10 (classic_coord_ring_sp.yaml) | 10 | auto | float32 | 400,000 | 5.000 | 10.00 % | 31.0 |" in block
    )
    assert (
        "| cnn_sp_10_tf32 (classic_coord_ring_sp.yaml) | 10 | auto | tf32 | 800,000 | 10.000 | 5.00 % | 31.0 |" in block
    )
    assert "Not measured (the measuring time was spent): rnn_sp_10_xla." in block
    assert "default (TF32)" not in block  # every row says its precision
    # a row of the first windows, measured at JAX's default precision: said so, and shared of the TF32 rate
    old = made_up_bench()
    del old["results"]["cnn_sp_10"]["precision"]
    block = gpu_report.benchmark_block(old)
    assert "| cnn_sp_10 (classic_coord_ring_sp.yaml) | 10 | auto | default (TF32) | 400,000 | 5.000 | 2.50 % |" in block
    assert "at JAX's own default, which is TF32 on an H100" in block
    assert "ratio: **3.00x** (target: at least 3x)" in block


def test_returned_results_unpack_into_docs_results_with_checked_sums(tmp_path):
    files, staging = tmp_path / "files", tmp_path / "results"
    report, policies = staging / "study_gpu_coord_ring_sp_report", staging / "study_gpu_coord_ring_sp_policies"
    for folder in (files, report, policies):
        folder.mkdir(parents=True)
    (report / "report.md").write_text("# Study\n")
    (policies / "sp_seed0_update610.ocv2policy").write_bytes(b"policy bytes")
    listing = [{"file": "sp_seed0_update610.ocv2policy", "seed": 0, "update": 610, "sha256": "0" * 64}]
    (policies / "SHA256SUMS.json").write_text(json.dumps(listing))
    (staging / "study_gpu_coord_ring_sp_sp_metrics.csv").write_text("update\n1\n")
    unfinished = [{"step": "train sp", "status": "partial"}, {"step": "xp sp", "status": "left"}]
    (staging / "study_gpu_coord_ring_sp_status.json").write_text(json.dumps(unfinished))
    (files / "gpu_run.json").write_text(json.dumps(made_up_bench()))

    def pack():
        with tarfile.open(files / "results.tar.gz", "w:gz") as tar:
            tar.add(staging, arcname="results")

    pack()
    with pytest.raises(SystemExit, match="sha256"):  # a policy that is not what was exported is refused
        gpu_report.unpack_results(files, tmp_path / "docs")
    assert not (tmp_path / "docs").exists()
    listing[0]["sha256"] = hashlib.sha256(b"policy bytes").hexdigest()
    (policies / "SHA256SUMS.json").write_text(json.dumps(listing))
    pack()
    (dest,) = gpu_report.unpack_results(files, tmp_path / "docs2")
    assert dest.name == "gpu_coord_ring_sp"
    assert (dest / "report.md").is_file() and (dest / "policies" / "sp_seed0_update610.ocv2policy").is_file()
    assert (dest / "sp_metrics.csv").is_file() and (dest / "gpu_run.json").is_file()
    assert json.loads((dest / "study_status.json").read_text()) == unfinished
    assert not gpu_report.index_lists(dest)  # the report then asks for its row in docs/results/README.md
    (dest.parent / "README.md").write_text(f"| [{dest.name}/]({dest.name}/) | ... |\n")
    assert gpu_report.index_lists(dest)
    # a later window's results of the same study replace an unfinished one; a finished one is never overwritten
    finished = [{"step": "train sp", "status": "done"}, {"step": "xp sp", "status": "done"}]
    (staging / "study_gpu_coord_ring_sp_status.json").write_text(json.dumps(finished))
    pack()
    assert gpu_report.unpack_results(files, tmp_path / "docs2") == [dest]
    assert gpu_run.finished_here("gpu_coord_ring_sp", tmp_path / "docs2")
    assert not gpu_run.finished_here("gpu_grounded_coord_simple_sp", tmp_path / "docs2")
    with pytest.raises(SystemExit, match="exists and holds a finished study"):
        gpu_report.unpack_results(files, tmp_path / "docs2")


def test_once_table1_has_finished_table2_trains_its_whole_schedule_the_fastest_measured_way(tmp_path):
    f32 = {"precision": "float32"}
    measured = {
        "cnn_sp_10": {"env_steps_per_s": 500_000, **f32},
        "rnn_sp_10_xla": {"env_steps_per_s": 50_000, "kernels": "xla", "gru_backward": "auto", "gru_unroll": 1, **f32},
        "rnn_sp_10_xla_hand_unroll8": {
            "env_steps_per_s": 80_000, "kernels": "xla", "gru_backward": "hand", "gru_unroll": 8, **f32,
        },
        "rnn_sp_10_cpu": {"error": "boom"},
        "rnn_sp_1_xla_hand_unroll32": {
            "env_steps_per_s": 90_000, "kernels": "xla", "gru_backward": "hand", "gru_unroll": 32, **f32,
        },
        # faster, but at a precision the study does not train at: never the plan's rate or variant
        "rnn_sp_10_xla_hand_unroll32_tf32": {
            "env_steps_per_s": 200_000, "kernels": "xla", "gru_backward": "hand", "gru_unroll": 32, "precision": "tf32",
        },
    }  # fmt: skip
    (step,) = gpu_run.plan(measured, seconds_left=400, smoke=False, table1_done=True)
    assert step.study == "gpu_grounded_coord_simple_sp" and step.budget == 1.0 and step.seeds == 10
    assert step.sets == ("model.kernels=xla", "model.gru_backward=hand", "model.gru_unroll=8")
    assert step.train_s == pytest.approx(10 * 30_000_000 / 80_000, rel=0.01)  # at the chosen variant's rate
    assert step.rate_case == "rnn_sp_10_xla_hand_unroll8"
    command = step.command(tmp_path, smoke=False)
    assert "gpu_grounded_coord_simple_sp.yaml" in command[command.index("run") + 1]
    assert command[command.index("--set") + 1] == "model.kernels=xla"
    # nothing measured at float32: the best known variant, since a study keeps its --set for its whole schedule
    assert gpu_run.best_rnn_sets({}, 10) == ["model.kernels=xla", "model.gru_backward=hand", "model.gru_unroll=8"]
    assert gpu_run.plan({}, 400, smoke=False, table1_done=True)[0].rate_case == ""
    # Table 1 first, until it has finished
    assert gpu_run.plan(measured, 400, smoke=False)[0].study == "gpu_coord_ring_sp"


def test_the_rnn_variants_are_measured_first_when_table2_is_next():
    first = [name for name, _ in gpu_run.measurements(smoke=False, rnn_first=True)][:7]
    # the float32 matmul rate (a second), then the best known variant: the plan trains the fastest one measured
    assert first[:2] == ["matmul_f32", "rnn_sp_10_xla_hand_unroll8"]
    assert all(name.startswith("rnn_sp_10_") for name in first[1:])
    assert [name for name, _ in gpu_run.measurements(smoke=False)][:2] == ["matmul_f32", "cnn_sp_10"]


def test_the_next_windows_input_is_checked_against_what_travels(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    (state / "part").write_bytes(b"x" * 1000)
    assert "TOO MUCH" not in gpu_report.travel_check(state)
    (state / "big").write_bytes(b"\0" * (gpu_report.TRAVEL_BYTES + 1))
    assert "TOO MUCH" in gpu_report.travel_check(state)


def _repo_with_a_policy(root: Path) -> Path:
    """A git repository holding one committed published policy (1 MiB), one committed study pack (2 MiB) with
    study_state/README.md beside it, and bench/gpu_slim.sh."""
    policy = root / "docs" / "results" / "study" / "policies" / "sp_seed0_update9.ocv2policy"
    policy.parent.mkdir(parents=True)
    policy.write_bytes(b"p" * (1 << 20))
    pack = root / "study_state" / "study" / "study.tar.gz.000"
    pack.parent.mkdir(parents=True)
    pack.write_bytes(b"s" * (2 << 20))
    (root / "study_state" / "README.md").write_text("packs\n")
    (root / "bench").mkdir()
    shutil.copy(ROOT / "bench" / "gpu_slim.sh", root / "bench" / "gpu_slim.sh")
    for command in (["init", "-q"], ["add", "."], ["-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "x"]):
        subprocess.run(["git", *command], cwd=root, check=True)
    return policy


def test_a_window_that_fits_without_the_published_policies_is_told_to_slim(tmp_path):
    root = tmp_path / "repo"
    _repo_with_a_policy(root)
    state = tmp_path / "state"
    state.mkdir()
    (state / "part").write_bytes(b"\0" * (gpu_report.TRAVEL_BYTES - (1 << 19)))
    line = gpu_report.travel_check(state, root)
    assert "TOO MUCH" not in line and "bash bench/gpu_slim.sh" in line
    assert "published policies 1.0 and study_state/ packs 2.0" in line
    (state / "more").write_bytes(b"\0" * (3 << 20))  # more than the policies and the pack together
    assert "TOO MUCH" in gpu_report.travel_check(state, root)
    (state / "more").unlink()
    (root / ".whl").mkdir()  # 4 MiB of wheels: slimmed, the window fits only if it carries none (training needs none)
    (root / ".whl" / "mcap-1.whl").write_bytes(b"w" * (4 << 20))
    line = gpu_report.travel_check(state, root)
    assert "TOO MUCH" not in line and "bash bench/gpu_slim.sh" in line and "without .whl it fits" in line


def test_gpu_slim_takes_committed_policies_and_packs_out_of_the_work_tree_and_index_and_restores_them(tmp_path):
    root = tmp_path / "repo"
    policy = _repo_with_a_policy(root)
    pack = root / "study_state" / "study" / "study.tar.gz.000"
    for stray in (policy.with_name("sp_seed1_update9.ocv2policy"), pack.with_name("pack.json")):
        stray.write_bytes(b"not committed")
        done = subprocess.run(["bash", "bench/gpu_slim.sh"], cwd=root, capture_output=True, text=True)
        assert done.returncode == 1 and "commit them first" in done.stderr  # and nothing was removed:
        assert policy.is_file() and pack.is_file()
        stray.unlink()
    done = subprocess.run(["bash", "bench/gpu_slim.sh"], cwd=root, capture_output=True, text=True, check=True)
    assert not policy.exists() and "1 published policies (1 MiB)" in done.stdout
    assert not pack.exists() and "1 study_state/ pack files (2 MiB)" in done.stdout
    assert (root / "study_state" / "README.md").is_file()  # only the packs leave
    # Out of git's index too (a staged deletion): what travels is the same whether sized from the tree or the index.
    tracked = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, check=True).stdout.split()
    assert sorted(tracked) == ["bench/gpu_slim.sh", "study_state/README.md"]
    again = subprocess.run(["bash", "bench/gpu_slim.sh"], cwd=root, capture_output=True, text=True)
    assert again.returncode == 1 and "slimmed already" in again.stderr  # slimmed twice: refused, saying so
    # bench/gpu_report.py refuses to file a window while the tree is slimmed (it reads earlier windows' policies).
    with pytest.raises(SystemExit, match="bash bench/gpu_slim.sh --restore"):
        gpu_report.refuse_slimmed(root)
    subprocess.run(["bash", "bench/gpu_slim.sh", "--restore"], cwd=root, check=True, capture_output=True)
    assert policy.read_bytes() == b"p" * (1 << 20) and pack.read_bytes() == b"s" * (2 << 20)
    status = subprocess.run(["git", "status", "--porcelain"], cwd=root, capture_output=True, text=True, check=True)
    assert status.stdout == ""  # nothing left staged for a later commit to take
    gpu_report.refuse_slimmed(root)


def test_earlier_windows_measurements_stay_in_the_block_until_measured_again(tmp_path):
    first = made_up_bench()
    first["environment"]["date"] = "2026-12-01T10:00:00+00:00"
    first["results"]["rnn_sp_10_xla"] = {
        **first["results"]["cnn_sp_10"], "config": "v2_grounded_coord_simple_sp.yaml", "model": "rnn",
        "kernels": "xla", "gru_backward": "hand", "gru_unroll": 8, "env_steps_per_s": 123_000.0,
    }  # fmt: skip
    second = made_up_bench()  # a continued window: the RNN case was not measured again
    second["environment"]["date"] = "2026-12-02T10:00:00+00:00"
    block = gpu_report.benchmark_block(second, [first])
    assert "Measured in earlier windows and not again in this one" in block
    assert (
        "| rnn_sp_10_xla (v2_grounded_coord_simple_sp.yaml) | 10 | xla, GRU hand, unroll 8 | float32 | 123,000 |"
        in block
    )
    assert "2026-12-01T10:00:00+00:00, gpu: NVIDIA H100 80GB HBM3 |" in block
    assert block.count("cnn_sp_10 (") == 1  # measured again: only this window's row
    # rates this window did not measure again come from the newest earlier window on the same device, marked
    for name in ("matmul_f32", "matmul_tf32", "matmul_bf16", "env_ocv2", "env_jaxmarl"):
        second["results"].pop(name, None)
    block = gpu_report.benchmark_block(second, [first])
    assert "f32 50.0 TFLOP/s*" in block and "| float32 | 400,000 | 5.000 | 10.00 % |" in block
    assert "- ocv2: 90,000,000 env steps/s (batch 16384, 400 steps; measured in the window of 2026-12-01" in block
    # through main: the history file gets each window once, however often the report is written
    for name, bench in (("one", first), ("two", second)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "gpu_run.json").write_text(json.dumps(bench))
    history = tmp_path / "gpu_windows.json"
    for name in ("one", "two", "two"):
        args = [str(tmp_path / name), "--out", str(tmp_path / "BENCH.md"), "--results", "", "--history", str(history)]
        assert gpu_report.main(args) == 0
    assert [w["environment"]["date"] for w in json.loads(history.read_text())] == [
        first["environment"]["date"], second["environment"]["date"],
    ]  # fmt: skip
    assert "123,000" in (tmp_path / "BENCH.md").read_text()


@dataclasses.dataclass(frozen=True)
class _FakeStep:
    """A planned step whose command is a stand-in study run."""

    code: str
    study: str = "fake"

    def command(self, out, smoke):
        return [sys.executable, "-c", self.code]


@pytest.mark.parametrize("steps, finished", [(["done"], True), (["done", "todo"], False)])
def test_a_study_signalled_at_the_deadline_after_it_finished_counts_as_finished(monkeypatch, tmp_path, steps, finished):
    """The deadline's SIGTERM can land between a study's last report line and its exit (a rehearsal on a loaded CPU
    saw rc -15 so, and the window was counted as failed): the study's directory decides."""
    import time

    from cluster.study import runner

    monkeypatch.setattr(gpu_run, "log", lambda message: None)
    monkeypatch.setattr(runner, "study_status", lambda study_dir: [{"status": status} for status in steps])
    record = gpu_run.train(_FakeStep("import time; time.sleep(60)"), tmp_path, deadline=time.time() + 3.0, smoke=True)
    assert record["rc"] == -gpu_run.signal.SIGTERM and record["stopped_at_deadline"]
    assert record["finished"] is finished and gpu_run.finished(record, tmp_path / "study_fake") is finished


@pytest.mark.parametrize(
    "code, signals",
    [
        # started without job control, it ignores SIGINT (what the deadline once sent); SIGTERM stops it
        ("import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); time.sleep(60)", ["SIGTERM"]),
        # a study whose chunk runs on past the grace: a second SIGTERM, then SIGKILL
        (
            "import signal, time; [signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)]; "
            "time.sleep(60)",
            ["SIGTERM", "SIGTERM", "SIGKILL"],
        ),
    ],
)
def test_the_deadline_stops_the_study_even_where_sigint_is_ignored(monkeypatch, tmp_path, code, signals):
    import time

    sent = []
    monkeypatch.setattr(gpu_run, "STOP_GRACE_S", 1.0)
    monkeypatch.setattr(gpu_run, "KILL_GRACE_S", 1.0)
    monkeypatch.setattr(gpu_run, "log", lambda message: sent.append(message))
    started = time.time()
    # 3 s: time enough for the child to set its handlers on a busy machine before the first signal
    record = gpu_run.train(_FakeStep(code), tmp_path, deadline=time.time() + 3.0, smoke=True)
    assert record["stopped_at_deadline"] and record["rc"] == -getattr(gpu_run.signal, signals[-1])
    assert time.time() - started < 20  # not the child's 60 s
    signalled = [m for m in sent if not m.startswith("running") and "cannot read its status" not in m]
    assert len(signalled) == len(signals)
    assert record["finished"] is False  # a stand-in with no study directory: nothing says it finished


def test_one_study_that_cannot_be_packed_does_not_cost_the_window_its_results(tmp_path, monkeypatch):
    out, returned = tmp_path / "run", tmp_path / "returned"
    (out / "study_broken").mkdir(parents=True)  # no study.json: its status cannot be read
    (out / "gpu_run.json").write_text("{}")
    returned.mkdir()
    monkeypatch.setattr(gpu_run, "log", lambda message: None)
    packed = gpu_run.pack(out, returned)
    assert "StudyError" in packed["study_broken"]["error"]
    with tarfile.open(returned / "results_broken.tar.gz") as tar:
        assert "results/gpu_run.json" in tar.getnames()


def test_trainer_rates_are_measured_at_the_precision_the_studies_train_at_and_at_tf32_beside():
    names = [name for name, _ in gpu_run.measurements(smoke=False)]
    assert names.index("cnn_sp_10") < names.index("matmul_tf32") < names.index("cnn_sp_10_tf32")
    assert "rnn_sp_10_xla_hand_unroll8_tf32" in names
    assert gpu_run.precision_sets("float32") == [] and gpu_run.precision_sets("tf32") == ["run.precision=tf32"]
    # with Table 2 next, every float32 RNN variant of the plan's seed count comes before the TF32 one
    rnn = [n for n, _ in gpu_run.measurements(smoke=False, rnn_first=True) if n.startswith("rnn_sp_10_")]
    assert rnn[-1] == "rnn_sp_10_xla_hand_unroll8_tf32"


def _window(method, devices, results, versions=None):
    environment = {"devices": devices, "nvidia_smi": "H100, 580", "versions": versions or {"jax": "0.11.2"}}
    return {"method": method, "environment": environment, "results": results}


def test_a_window_does_not_measure_again_what_an_earlier_window_measured_the_same_way(monkeypatch):
    gpu = ["gpu: NVIDIA H100 80GB HBM3"]
    rate = {"env_steps_per_s": 1.0, "model_tflops": 1.0}
    history = [
        # the first windows: their trainer rates are stale, their matmul and environment rates are not
        _window(None, gpu, {"cnn_sp_10": rate, "rnn_sp_10_xla": rate, "matmul_f32": {"tflops": 50.0}}),
        _window(gpu_run.METHOD, ["gpu: NVIDIA H200"], {"cnn_sp_1": rate}),  # another device
        _window(
            gpu_run.METHOD,
            gpu,
            {"env_ocv2": {"env_steps_per_s": 5.0}, "matmul_tf32": {"tflops": 9.0}, "cnn_sp_4": {"error": "boom"}},
        ),  # fmt: skip
        _window(gpu_run.METHOD, gpu, {"env_ocv2": {"env_steps_per_s": 6.0}}),  # the newest wins
        _window(gpu_run.METHOD, gpu, {"cnn_sp_4": rate}, versions={"jax": "0.12.0"}),  # other versions: stale
    ]
    known = gpu_run.measured_before(history, _window(None, gpu, {})["environment"])
    assert known == {
        "env_ocv2": {"env_steps_per_s": 6.0},
        "matmul_tf32": {"tflops": 9.0},
        "matmul_f32": {"tflops": 50.0},
    }
    ran = []
    monkeypatch.setattr(gpu_run, "log", lambda message: None)
    monkeypatch.setattr(
        gpu_run, "measurements", lambda smoke, rnn_first: [(n, lambda n=n: ran.append(n) or {"ok": 1}) for n in
                                                            ("cnn_sp_10", "env_ocv2", "matmul_tf32", "cnn_sp_1")]
    )  # fmt: skip
    import time

    results = gpu_run.measure(time.time() + 60, smoke=False, known=frozenset(known))
    assert ran == ["cnn_sp_10", "cnn_sp_1"] and set(results) == {"cnn_sp_10", "cnn_sp_1"}
    assert gpu_run.read_history(Path("/nonexistent/gpu_windows.json")) == []


def test_a_continued_table1_study_that_finishes_hands_the_rest_of_the_window_to_table2(tmp_path, monkeypatch):
    from cluster.study import runner

    state = tmp_path / "state"
    state.mkdir()
    (state / "pack.json").write_text(json.dumps({"study": "gpu_coord_ring_sp"}))
    trained, packed = [], []

    def fake_train(step, out, deadline, smoke):
        trained.append(step)
        return {"step": dataclasses.asdict(step), "rc": 0 if step.study == "gpu_coord_ring_sp" else 130,
                "stopped_at_deadline": step.study != "gpu_coord_ring_sp"}  # fmt: skip

    def fake_pack(out, returned, only=None):
        packed.append((only.name if only else None, [s.study for s in trained]))
        return {}

    done = [{"step": "train sp", "status": "done"}, {"step": "xp sp", "status": "done"}]
    monkeypatch.setattr(runner, "study_status", lambda study_dir: done)
    monkeypatch.setattr(gpu_run, "log", lambda message: None)
    monkeypatch.setattr(gpu_run, "environment", lambda: {"devices": ["gpu: X"], "nvidia_smi": None})
    monkeypatch.setattr(gpu_run, "read_history", lambda: [])
    monkeypatch.setattr(gpu_run, "measure", lambda *a, **k: {})  # a continued window's 30 s: no RNN rate
    monkeypatch.setattr(gpu_run, "continued_step", lambda s, out: gpu_run.Step("gpu_coord_ring_sp", 1.0, 10, 0.0, True))
    monkeypatch.setattr(gpu_run, "train", fake_train)
    monkeypatch.setattr(gpu_run, "pack", fake_pack)
    monkeypatch.setattr(gpu_run, "finished_here", lambda study, published=None: False)
    args = ["--out", str(tmp_path / "out"), "--deadline-s", "480", "--measure-s", "1", "--continue-from", str(state)]
    assert gpu_run.main(args) == 0
    assert [s.study for s in trained] == ["gpu_coord_ring_sp", "gpu_grounded_coord_simple_sp"]
    # no float32 RNN rate known: the best known variant, not the plainest
    assert trained[1].sets == ("model.kernels=xla", "model.gru_backward=hand", "model.gru_unroll=8")
    # Table 1's results were packed before Table 2 started; the rest after it
    assert packed == [("study_gpu_coord_ring_sp", ["gpu_coord_ring_sp"]), (None, [s.study for s in trained])]
    record = json.loads((tmp_path / "out" / "gpu_run.json").read_text())
    assert [p["study"] for p in record["plan"]] == ["gpu_coord_ring_sp", "gpu_grounded_coord_simple_sp"]
    assert record["method"] == gpu_run.METHOD

    def only_table1(arguments) -> list[str]:
        trained.clear()
        packed.clear()
        assert gpu_run.main(arguments) == 0
        return [s.study for s in trained]

    # stopped at its deadline, with too little time left, or a study whose status is not all done: nothing else
    monkeypatch.setattr(gpu_run, "train", lambda *a: trained.append(a[0]) or {"rc": 130, "stopped_at_deadline": True})
    assert only_table1(args) == ["gpu_coord_ring_sp"]
    monkeypatch.setattr(gpu_run, "train", fake_train)
    assert only_table1([*args[:3], "100", *args[4:]]) == ["gpu_coord_ring_sp"]
    monkeypatch.setattr(runner, "study_status", lambda study_dir: [{"step": "xp sp", "status": "partial"}])
    assert only_table1(args) == ["gpu_coord_ring_sp"]
    # a gpu_state/ whose study is already filed as finished is never trained again: the window plans afresh
    monkeypatch.setattr(gpu_run, "finished_here", lambda study, published=None: study == "gpu_coord_ring_sp")
    monkeypatch.setattr(gpu_run, "continued_step", lambda s, out: pytest.fail("continued a finished study"))
    assert only_table1(args) == ["gpu_grounded_coord_simple_sp"]


def test_the_state_of_an_unfinished_study_is_packed_before_any_results(tmp_path, monkeypatch):
    out, returned = tmp_path / "run", tmp_path / "returned"
    for name in ("study_a", "study_b"):
        (out / name).mkdir(parents=True)
    (out / "gpu_run.json").write_text("{}")
    returned.mkdir()
    order = []
    monkeypatch.setattr(gpu_run, "log", lambda message: None)
    from cluster.study import runner

    monkeypatch.setattr(runner, "study_status", lambda study_dir: [{"step": "train", "status": "partial"}])
    monkeypatch.setattr(gpu_run, "_pack_state", lambda d, status, r, n: order.append(("state", d.name, n)) or {})
    monkeypatch.setattr(gpu_run, "_stage_results", lambda d, status, staging: order.append(("results", d.name)))
    packed = gpu_run.pack(out, returned, only=out / "study_a")
    assert order == [("state", "study_a", 2), ("results", "study_a")] and "results_a.tar.gz" in packed
    order.clear()
    packed = gpu_run.pack(out, returned)  # what was packed already is not packed again
    assert order == [("state", "study_b", 2), ("results", "study_b")] and set(packed) == {"results_b.tar.gz"}
    assert sorted(p.name for p in returned.iterdir()) == ["results_a.tar.gz", "results_b.tar.gz"]  # no .partial


def test_a_cut_off_archive_is_reported_and_not_filed(tmp_path):
    files = tmp_path / "files"
    files.mkdir()
    (files / "gpu_run.json").write_text(json.dumps(made_up_bench()))
    (files / "results_gpu_coord_ring_sp.tar.gz").write_bytes(b"\x1f\x8b\x08\x00 cut off")
    assert "unreadable" in gpu_report.study_rates(files)[0]
    assert gpu_report.unpack_results(files, tmp_path / "docs") == []
    assert not (tmp_path / "docs").exists()


def test_after_a_window_the_report_says_what_to_do_with_gpu_state(tmp_path):
    root, files, results = tmp_path / "repo", tmp_path / "files", tmp_path / "results"
    (root / "gpu_state").mkdir(parents=True)
    (root / "gpu_state" / "pack.json").write_text(json.dumps({"study": "gpu_coord_ring_sp"}))
    files.mkdir()
    (results / "gpu_coord_ring_sp").mkdir(parents=True)
    status = results / "gpu_coord_ring_sp" / "study_status.json"
    status.write_text(json.dumps([{"step": "xp sp", "status": "partial"}]))
    assert gpu_report.state_advice(files, results, root) == "next: nothing to do with gpu_state/"
    status.write_text(json.dumps([{"step": "xp sp", "status": "done"}]))
    assert "git rm -r -q gpu_state" in gpu_report.state_advice(files, results, root)
    (files / "state").mkdir()
    assert "cp -r" in gpu_report.state_advice(files, results, root)


def test_each_study_comes_back_in_its_own_archive_and_the_block_says_how_fast_it_trained(tmp_path):
    files = tmp_path / "files"
    files.mkdir()
    (files / "gpu_run.json").write_text(json.dumps(made_up_bench()))
    for study, rates in (
        ("gpu_coord_ring_sp", ["150000", "150000", "140000"]),
        ("gpu_grounded_coord_simple_sp", ["9e4"]),
    ):
        staging = tmp_path / study / "results"
        (staging / f"study_{study}_report").mkdir(parents=True)
        (staging / f"study_{study}_report" / "report.md").write_text("# Study\n")
        (staging / f"study_{study}_report" / "sp_metrics.csv").write_text("seed,update,steps_per_s\n0,1,1\n")
        rows = [f"{seed},{update + 1},{rate}" for update, rate in enumerate(rates) for seed in (0, 1)]
        (staging / f"study_{study}_sp_metrics.csv").write_text("seed,update,steps_per_s\n" + "\n".join(rows) + "\n")
        (staging / f"study_{study}_sp_config.yaml").write_text("run:\n  precision: float32\n  deterministic: true\n")
        (staging / f"study_{study}_status.json").write_text(json.dumps([{"step": "train sp", "status": "partial"}]))
        with tarfile.open(files / f"results_{study}.tar.gz", "w:gz") as tar:
            tar.add(staging, arcname="results")
    lines = gpu_report.study_rates(files)
    assert lines == [
        "- gpu_coord_ring_sp, run sp: 150,000 env steps/s (median over 3 updates, 2 seeds; precision float32, "
        "deterministic true)",
        "- gpu_grounded_coord_simple_sp, run sp: 90,000 env steps/s (median over 1 updates, 2 seeds; precision "
        "float32, deterministic true)",
    ]
    assert "Training in this window's studies" in gpu_report.benchmark_block(made_up_bench(), studies=lines)
    written = gpu_report.unpack_results(files, tmp_path / "docs")
    assert [d.name for d in written] == ["gpu_coord_ring_sp", "gpu_grounded_coord_simple_sp"]


@pytest.mark.skipif(not (ROOT / "gpu_state" / "pack.json").is_file(), reason="no GPU window left a study unfinished")
def test_the_committed_gpu_state_resumes_under_this_code(tmp_path):
    """What the next window continues: every run's config still has the fingerprint its checkpoints were saved
    with, and every seed's latest checkpoint loads into this code's training state."""
    from cluster.runtime.runstate import restore
    from cluster.study.pack import unpack_study
    from cluster.study.runner import StudyOptions, plan_study
    from cluster.study.spec import load_study
    from population import ppo
    from population.config.parse import load_run_config

    record = unpack_study(ROOT / "gpu_state", tmp_path / "study")
    # ocv2 study run accepts the folder as it is: the same options, every run's config the one it trained with
    study = load_study(ROOT / "configs" / "studies" / f"{record['study']}.yaml")
    plan_study(study, tmp_path / "study", StudyOptions(backend="local"))
    runs = [d for d in sorted((tmp_path / "study" / "runs").iterdir()) if (d / "config.yaml").is_file()]
    assert runs
    for run_dir in runs:
        config = load_run_config(run_dir)
        trainer = ppo.make_trainer(config)
        restored = restore(trainer, run_dir, config, list(range(config.population.num_seeds)), 0)
        assert restored is not None and restored[1] > 0, run_dir


def test_a_later_window_keeps_the_snapshot_policies_of_earlier_ones(tmp_path):
    """A window returns its own latest policies; the earlier windows' snapshots (run.num_checkpoints' updates)
    stay published beside them, and deadline stops between snapshots give way."""
    config = ROOT / "docs" / "results" / "gpu_coord_ring_sp" / "sp_config.yaml"  # 610 updates, snapshots every 122

    def policies_folder(folder: Path, updates: list[int]) -> None:
        folder.mkdir(parents=True)
        listing = []
        for update in updates:
            name = f"sp_seed0_update{update}.ocv2policy"
            (folder / name).write_bytes(f"policy {update}".encode())
            digest = hashlib.sha256(f"policy {update}".encode()).hexdigest()
            listing.append({"file": name, "seed": 0, "update": update, "sha256": digest})
        (folder / "SHA256SUMS.json").write_text(json.dumps(listing))

    dest = tmp_path / "docs" / "gpu_coord_ring_sp"
    policies_folder(dest / "policies", [122, 290])  # the first window: a snapshot and its deadline stop
    shutil.copy(config, dest / "sp_config.yaml")
    (dest / "study_status.json").write_text(json.dumps([{"step": "train sp", "status": "partial"}]))
    files, staging = tmp_path / "files", tmp_path / "results"
    files.mkdir()
    (staging / "study_gpu_coord_ring_sp_report").mkdir(parents=True)
    (staging / "study_gpu_coord_ring_sp_report" / "report.md").write_text("# Study\n")
    policies_folder(staging / "study_gpu_coord_ring_sp_policies", [244, 410])
    (staging / "study_gpu_coord_ring_sp_status.json").write_text(
        json.dumps([{"step": "train sp", "status": "partial"}])
    )
    with tarfile.open(files / "results_gpu_coord_ring_sp.tar.gz", "w:gz") as tar:
        tar.add(staging, arcname="results")
    (written,) = gpu_report.unpack_results(files, tmp_path / "docs")
    listing = json.loads((written / "policies" / "SHA256SUMS.json").read_text())
    assert [entry["update"] for entry in listing] == [122, 244, 410]
    assert not (written / "policies" / "sp_seed0_update290.ocv2policy").exists()
    from population import published

    published.checked_listing(written / "policies")  # every file matches its sum
    # an earlier policy that no longer matches its sum stops it before anything is written
    (written / "policies" / "sp_seed0_update122.ocv2policy").write_bytes(b"changed")
    with pytest.raises(SystemExit, match="nothing was written"):
        gpu_report.unpack_results(files, tmp_path / "docs")
    assert (written / "policies" / "sp_seed0_update410.ocv2policy").is_file()


def test_the_rnn_rates_are_measured_with_the_program_table2_then_trains_with(monkeypatch):
    """The measured program is the Table 2 study's own (the same sections, the chunk limit of its schedule), so the
    window's compilation cache hands the study the program it measured instead of compiling it again."""
    from cluster.runtime.runstate import Schedule
    from cluster.study.spec import load_study, run_config

    spec = load_study(ROOT / "configs" / "studies" / "gpu_grounded_coord_simple_sp.yaml")
    config = run_config(spec, spec.runs[0], ROOT / "unused", budget=1.0, seeds=10)
    calls = []
    monkeypatch.setattr(gpu_run, "trainer_rate", lambda *args: calls.append(args))
    dict(gpu_run.measurements(smoke=False))["rnn_sp_10_xla_hand_unroll8"]()
    ((path, seeds, updates, sets, chunk),) = calls
    assert chunk == Schedule.of(config).longest_chunk == 5 and updates <= chunk
    measured = gpu_run.load_config(path, [*sets, f"population.num_seeds={seeds}"])
    # (the model section differs by the --set of the variant, which the plan gives the study too)
    assert (config.env, config.ppo, config.population) == (measured.env, measured.ppo, measured.population)


def test_a_trainer_rate_is_traced_under_the_precision_of_its_config(monkeypatch):
    """What makes a measured rate the rate the study trains at: the program is traced (compiled) under the
    config's ``run.precision``, as a run's shard traces it."""
    import jax

    from population import ppo

    seen = []
    real = ppo.make_advance_chunks

    def spy(trainer, updates, *rest):
        advance = real(trainer, updates, *rest)

        def call(*args):
            seen.append(jax.config.jax_default_matmul_precision)
            return advance(*args)

        return call

    monkeypatch.setattr(ppo, "make_advance_chunks", spy)
    sets = [*gpu_run.SMOKE_SETS, *gpu_run.precision_sets("tf32")]
    result = gpu_run.trainer_rate(gpu_run.CR_SP, 1, 1, sets)
    assert result["precision"] == "tf32" and seen == ["tensorfloat32", "tensorfloat32"]
    assert jax.config.jax_default_matmul_precision is None  # the process default is left as it was
