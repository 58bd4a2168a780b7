"""How training computes (population/numerics.py): run.precision's matmul precision, XLA's deterministic GPU
ops set before JAX starts, and what the local backend records about the device it trains on."""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cluster.cli import main
from cluster.runtime.environment import cpu_record
from cluster.study.state import StudyState
from population import numerics
from population.config import PRECISIONS

ROOT = Path(__file__).resolve().parents[1]
SMOKE = str(ROOT / "configs" / "smoke.yaml")
FLAG = numerics.DETERMINISTIC_FLAG


def test_each_precision_is_a_jax_matmul_precision_and_a_cpu_computes_float32_under_all():
    assert [numerics.jax_precision(p) for p in PRECISIONS] == ["float32", "tensorfloat32", "bfloat16"]
    with pytest.raises(ValueError, match="run.precision"):
        numerics.jax_precision("fp16")
    x = jax.random.normal(jax.random.PRNGKey(0), (16, 64))
    w = jax.random.normal(jax.random.PRNGKey(1), (64, 8))
    results = {}
    for precision in PRECISIONS:
        with numerics.matmul_precision(precision):
            assert jax.config.jax_default_matmul_precision == numerics.jax_precision(precision)
            results[precision] = np.asarray(jax.jit(jnp.dot)(x, w))  # traced and compiled per precision
    assert jax.config.jax_default_matmul_precision is None  # the context ends with the block
    if jax.default_backend() == "cpu":
        for precision in PRECISIONS:
            np.testing.assert_array_equal(results[precision], results["float32"])


def test_the_flag_is_found_in_xla_flags_the_last_setting_winning():
    assert numerics.deterministic_ops_in(f"--xla_backend_optimization_level=0 {FLAG}")
    assert not numerics.deterministic_ops_in("--xla_backend_optimization_level=0")
    assert not numerics.deterministic_ops_in(f"{FLAG} --xla_gpu_deterministic_ops=false")
    assert numerics.deterministic_flag_known()  # jaxlib 0.10.2 knows it, CPU build included


def test_the_flag_is_added_before_jax_starts_and_never_after(monkeypatch):
    monkeypatch.setattr(numerics, "jax_backend_started", lambda: False)
    environ = {"XLA_FLAGS": "--xla_backend_optimization_level=0"}
    assert numerics.enable_deterministic_ops(environ)[0]
    assert environ["XLA_FLAGS"] == f"--xla_backend_optimization_level=0 {FLAG}"
    assert numerics.enable_deterministic_ops(environ)[0] and environ["XLA_FLAGS"].count("deterministic") == 1
    off = {"XLA_FLAGS": "--xla_gpu_deterministic_ops=false"}  # an explicit setting wins
    applied, message = numerics.enable_deterministic_ops(off)
    assert not applied and "off explicitly" in message and off == {"XLA_FLAGS": "--xla_gpu_deterministic_ops=false"}
    monkeypatch.setattr(numerics, "jax_backend_started", lambda: True)
    late = {}
    applied, message = numerics.enable_deterministic_ops(late)
    assert not applied and late == {}  # a later subprocess must not inherit a flag this process lacks
    assert "JAX was already running" in message


def test_the_train_command_says_when_jax_started_too_early_for_the_flag(tmp_path, monkeypatch, capsys):
    """``ocv2 train`` sets the flag for itself before anything runs JAX; run from a process where JAX already
    runs (this one), it leaves XLA_FLAGS alone and says so in a log line."""
    import cluster.cli.train as train_cli

    jnp.zeros(1).block_until_ready()  # JAX's backend is running here
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    monkeypatch.setattr(train_cli, "train_population", lambda *a, **k: {"run_dir": str(tmp_path)})
    assert main(["train", SMOKE, "--out", str(tmp_path / "run"), "--backend", "local"]) == 0
    err = capsys.readouterr().err
    assert "run.deterministic: JAX was already running in this process" in err
    assert numerics.DETERMINISTIC_FLAG not in os.environ["XLA_FLAGS"]
    assert (
        main(["train", SMOKE, "--out", str(tmp_path / "run"), "--backend", "local", "--set", "run.deterministic=false"])
        == 0
    )
    assert "run.deterministic" not in capsys.readouterr().err


def test_the_local_backend_records_its_device_precision_and_flags(tmp_path, capsys):
    """environment.json's driver record names the worker (this process), the device it trains on, the
    precision and flags in force; the run's header says the same."""
    run = tmp_path / "run"
    overrides = ["--set", "run.precision=tf32", "--set", "ppo.total_timesteps=256"]
    assert main(["train", SMOKE, "--out", str(run), "--backend", "local", "--no-eval", *overrides]) == 0
    record = json.loads((run / "environment.json").read_text())["drivers"][-1]
    assert record["run"] == {"precision": "tf32", "deterministic": True}
    (worker,) = record["workers"]
    assert worker["worker"] == "this process" and worker["seeds"] == [0, 1] and worker["num_gpus"] is None
    assert worker["cpu"]["cores"] == os.cpu_count() and worker["cpu"]["model"]  # a rate is read beside its CPU
    assert worker["device"] == numerics_device() and worker["matmul_precision"] == "tensorfloat32"
    assert worker["computes"] == ("float32" if jax.default_backend() == "cpu" else "tf32")
    err = capsys.readouterr().err
    assert "run.precision tf32 (matmuls compute" in err
    assert f"seeds 0-1 train on {numerics_device()} (this process)" in err
    # the deterministic GPU flag is set in this process, but on a CPU nothing it governs runs: the header says so
    on_cpu = numerics_device() == "cpu"
    assert ("(CPU only, deterministic as it is)" in err) == on_cpu
    assert ("(XLA's deterministic GPU ops on)" in err) != on_cpu


def numerics_device() -> str:
    device = jax.devices()[0]
    return "cpu" if device.platform == "cpu" else f"{device.platform}: {device.device_kind}"


def test_the_study_command_sets_the_flag_like_the_train_command(tmp_path, monkeypatch, capsys):
    """``ocv2 study run`` trains in its own process with the local backend: it sets the flag the same way
    (here JAX already runs, so it says so), and not when every run turns run.deterministic off."""
    import yaml

    import cluster.cli.study as study_cli

    jnp.zeros(1).block_until_ready()
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    done = StudyState(study="s", spec={}, report={"report": "r.md"})
    monkeypatch.setattr(study_cli, "run_study", lambda *a, **k: done)
    study = tmp_path / "s.yaml"
    study.write_text(yaml.safe_dump({"study": "s", "runs": [{"name": "a", "config": str(SMOKE)}]}))
    assert main(["study", "run", str(study), "--backend", "local", "--out", str(tmp_path / "out")]) == 0
    assert "run.deterministic: JAX was already running in this process" in capsys.readouterr().err
    off = ["--set", "run.deterministic=false"]
    assert main(["study", "run", str(study), "--backend", "local", "--out", str(tmp_path / "o2"), *off]) == 0
    assert "run.deterministic" not in capsys.readouterr().err


def test_the_cpu_record_names_the_model_cores_and_vector_units(tmp_path):
    """Two 2-core machines trained the same run three times apart: environment.json says which CPU each was."""
    x86 = tmp_path / "x86"
    x86.write_text(
        "processor\t: 0\nmodel name\t: AMD EPYC 9654\nflags\t\t: fpu sse4_2 avx avx2 fma avx512f\n\n"
        "processor\t: 1\nmodel name\t: other\nflags\t\t: fpu\n"
    )
    record = cpu_record(x86)
    assert record["model"] == "AMD EPYC 9654" and record["vector_flags"] == ["sse4_2", "avx", "avx2", "fma", "avx512f"]
    assert record["cores"] == os.cpu_count() and 1 <= record["usable_cores"] <= os.cpu_count()
    arm = tmp_path / "arm"
    arm.write_text("processor\t: 0\nFeatures\t: fp asimd sve\n")
    assert cpu_record(arm)["vector_flags"] == ["asimd", "sve"] and cpu_record(arm)["model"]
    assert cpu_record(tmp_path / "absent")["vector_flags"] is None
