#!/usr/bin/env python
"""The prepared GPU run: measure, plan from what was measured, train until a deadline, pack what came out.

A lent GPU machine is ours for minutes (one command of at most 10 minutes, no network, no Ray): this
script makes one such command count. ``bench/gpu_run.sh`` calls it after installing the carried wheels;
it can also run by itself (``python bench/gpu_run.py --out DIR``).

1. **environment**: device, driver (nvidia-smi), Python and package versions, XLA flags.
2. **measure** (``--measure-s``, about 2 minutes): the same GPU's float32 and bf16 matmul rates; trainer env
   steps/s of Coordination Ring SP (PPO-CNN) at 10, 4 and 1 seeds and of Grounded Coord. Simple SP (PPO-RNN) at
   1, 10 and 20 seeds in both kernel families (``model.kernels`` cpu/xla) and in the ways to run the GRU's time
   loop (``model.gru_backward`` hand/autodiff, ``model.gru_unroll``); the environment alone (ours, and JaxMARL's
   if it imports). Most important first (the 10-seed RNN variants first when Table 2 is next); what the time
   leaves out is recorded as skipped, never guessed.
3. **plan** (``--plan auto``): until docs/results/gpu_coord_ring_sp/ holds that study finished, the largest run
   that ends before the deadline at the measured 10-seed CNN rate: Table 1 Coordination Ring SP
   (configs/studies/gpu_coord_ring_sp.yaml), 10 seeds, the paper's 10M schedule -- truncated (stopped early,
   ``--budget-mode truncate``), never compressed, when it does not fit; SA in the time left when SP fits with
   time to spare (gpu_coord_ring_sa.yaml). Then Table 2 Grounded Coord. Simple SP
   (gpu_grounded_coord_simple_sp.yaml), 10 seeds, the paper's whole 30M schedule with the fastest measured RNN
   variant, trained window after window.
4. **train**: ``ocv2 study run --backend local`` in a child process; at the deadline it gets SIGTERM, which
   stops training after the chunk in flight (saved), so what it has is packed and a later window resumes it.
5. **pack**: first the resumable state of a study left unfinished at the deadline -> state/ (``ocv2 study
   pack``: pack.json and parts of at most 15 MiB), then each study's report folder (``ocv2 study report --out``),
   every seed's exported policy (its latest checkpoint, then kept snapshots while 12 MiB allow) with sha256
   sums, metrics.csv and gpu_run.json -> results_<study>.tar.gz. Commit state/ as gpu_state/ and the next window's
   ``bench/gpu_run.sh`` continues that study (``--continue-from``) instead of planning a new one.

Everything it learns goes into gpu_run.json, rewritten after every phase: the environment (device, driver,
versions, XLA flags), the measurements, the plan, what trained and what was packed.

``GPU_RUN_SMOKE=1`` (or ``--smoke``) shrinks every size (2 seeds, a few updates of a few envs, 4 episodes per
pair): the same steps end to end in about 2 minutes on a CPU, which is how the script is rehearsed.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from cluster.runtime.environment import package_versions  # noqa: E402
from population import ppo  # noqa: E402
from population.config import load_config  # noqa: E402

STUDIES = ROOT / "configs" / "studies"  # gpu_coord_ring_sp.yaml, gpu_coord_ring_sa.yaml: one run each
CR_SP = ROOT / "configs" / "paper" / "classic_coord_ring_sp.yaml"
GCS_SP = ROOT / "configs" / "paper" / "v2_grounded_coord_simple_sp.yaml"
# What the smoke rehearsal shrinks every config to: the same programs, tiny.
SMOKE_SETS = ["ppo.num_envs=4", "ppo.num_steps=8", "ppo.num_minibatches=2", "ppo.update_epochs=1"]
EXTRA_PACKAGES = ("jax-cuda13-plugin", "jax-cuda12-plugin", "mcap")  # beside the run record's own list


def log(message: str) -> None:
    print(f"[gpu_run {time.strftime('%H:%M:%S')}] {message}", flush=True)


# ---------------------------------------------------------------------------------------------------
# 1. environment
# ---------------------------------------------------------------------------------------------------


def environment() -> dict:
    """What ran where: device, driver, versions, flags."""
    devices = jax.devices()
    smi = None
    try:
        smi = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total,clocks.max.sm", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        ).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        pass
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "backend": jax.default_backend(),
        "devices": [f"{d.platform}: {d.device_kind}" for d in devices],
        "nvidia_smi": smi,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "versions": package_versions(EXTRA_PACKAGES),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "JAX_DEFAULT_MATMUL_PRECISION": os.environ.get("JAX_DEFAULT_MATMUL_PRECISION"),
    }


# ---------------------------------------------------------------------------------------------------
# 2. measure
# ---------------------------------------------------------------------------------------------------


def matmul_rate(size: int, dtype, precision: str, repeats: int = 10) -> dict:
    """TFLOP/s of a jitted size^3 matmul (median of ``repeats``, after a warm-up), random operands."""
    k_a, k_b = jax.random.split(jax.random.PRNGKey(0))
    a, b = (jax.random.normal(k, (size, size), jnp.float32).astype(dtype) for k in (k_a, k_b))
    with jax.default_matmul_precision(precision):
        fn = jax.jit(jnp.dot)
        jax.block_until_ready(fn(a, b))
        times = []
        for _ in range(repeats):
            started = time.perf_counter()
            jax.block_until_ready(fn(a, b))
            times.append(time.perf_counter() - started)
    return {
        "size": size,
        "dtype": jnp.dtype(dtype).name,
        "precision": precision,
        "tflops": 2 * size**3 / statistics.median(times) / 1e12,
    }


def trainer_rate(config_path: Path, seeds: int, updates: int, sets: list[str], chunk: int | None = None) -> dict:
    """Env steps/s of ``seeds`` seeds trained together (one vmapped program, as the local backend does):
    ``updates`` updates timed once after a compile-and-run call of the same program, traced under the config's
    ``run.precision`` as a run's shard traces it. (The first window measured without it, at JAX's default: TF32
    on an H100, 2.8x the rate its float32 study then trained at.) ``chunk``: the program's longest chunk
    (default ``updates``); the study's own (``study_chunk``) makes it the program the study then compiles, which
    the window's compilation cache hands over instead of compiling it again (tens of seconds of the window)."""
    from train_throughput import flops_per_env_step

    from population.numerics import matmul_precision

    config = load_config(config_path, [*sets, f"population.num_seeds={seeds}"])
    with matmul_precision(config.run.precision):
        trainer = ppo.make_trainer(config)
        states = ppo.init_population(trainer, list(range(seeds)))
        advance = ppo.make_advance_chunks(trainer, chunk or updates)  # the program a run's shard trains with
        count = jnp.int32(updates)
        started = time.perf_counter()
        states, _ = jax.block_until_ready(advance(states, None, None, count))
        compile_s = time.perf_counter() - started
        started = time.perf_counter()
        states, metrics = jax.block_until_ready(advance(states, None, None, count))
        seconds = time.perf_counter() - started
    steps = seeds * updates * config.ppo.steps_per_update
    flops = flops_per_env_step(trainer, ppo.take_seed(states.params, 0)) * steps
    return {
        "config": config_path.name,
        "model": config.model.kind,
        "kernels": config.model.kernels,
        "gru_backward": config.model.gru_backward,
        "gru_unroll": config.model.gru_unroll,
        "precision": config.run.precision,
        "seeds": seeds,
        "updates": updates,
        "chunk": chunk or updates,
        "steps_per_update": config.ppo.steps_per_update,
        "compile_plus_first_s": round(compile_s, 2),
        "timed_s": round(seconds, 3),
        "env_steps_per_s": steps / seconds,
        "model_tflops": flops / seconds / 1e12,
        "finite": bool(jnp.isfinite(metrics.loss.total).all()) if hasattr(metrics.loss, "total") else None,
    }


def study_chunk(study: str) -> int:
    """The longest chunk of the one run of ``configs/studies/<study>.yaml`` at its whole budget with 10 seeds: the
    limit of the training program that study compiles (``ppo.make_advance_chunks``)."""
    from cluster.runtime.runstate import Schedule
    from cluster.study.spec import load_study, run_config

    spec = load_study(STUDIES / f"{study}.yaml")
    (run,) = spec.runs
    return Schedule.of(run_config(spec, run, ROOT / "unused", budget=1.0, seeds=10)).longest_chunk


def env_rate(impl: str, batch: int, steps: int) -> dict:
    """Env steps/s of random-action rollouts alone (bench/env_throughput.py's case), Coordination Ring."""
    from env_throughput import Case

    case = Case(impl, "coord_ring", None, batch, steps)
    case.time(3)
    result = case.result()
    return {k: result[k] for k in ("impl", "layout", "batch", "steps", "env_steps_per_s", "compile_plus_first_run_s")}


def measurements(smoke: bool, rnn_first: bool = False) -> list[tuple[str, object]]:
    """(name, thunk) in order of importance, since the measuring time may run out (each trainer case is a
    compile of tens of seconds on a GPU): the plan's case first, then one of each other kind, then the rest.
    ``rnn_first``: the 10-seed RNN variants first (the Table 2 plan trains with the fastest of them)."""
    sets = SMOKE_SETS if smoke else []
    cnn_updates, rnn_updates = (2, 2) if smoke else (10, 3)  # 10: the GPU study's chunk, so its compile is reused
    # Table 2's program has room for its chunk of 5 updates; 3 of them are timed (a GPU RNN update takes seconds).
    rnn_chunk = None if smoke else study_chunk(TABLE2)
    size = 512 if smoke else 8192
    plan_seeds, many = (2, 2) if smoke else (10, 10)

    def cnn(seeds: int, precision: str = "float32", kernels: str = "auto"):
        sets_p = [*sets, *precision_sets(precision), *([] if kernels == "auto" else [f"model.kernels={kernels}"])]
        name = f"cnn_sp_{seeds}{'' if kernels == 'auto' else '_' + kernels}{precision_suffix(precision)}"
        return name, lambda: trainer_rate(CR_SP, seeds, cnn_updates, sets_p)

    def rnn(seeds: int, kernels: str, backward: str = "auto", unroll: int = 1, precision: str = "float32"):
        variant = kernels + ("" if backward == "auto" else f"_{backward}") + ("" if unroll == 1 else f"_unroll{unroll}")
        sets_k = [*sets, *rnn_sets(kernels, backward, unroll), *precision_sets(precision)]
        name = f"rnn_sp_{seeds}_{variant}{precision_suffix(precision)}"
        return name, lambda: trainer_rate(GCS_SP, seeds, rnn_updates, sets_k, rnn_chunk)

    batch, steps = (64, 16) if smoke else (16384, 400)
    plan_case = f"cnn_sp_{plan_seeds}"
    ordered = [
        ("matmul_f32", lambda: matmul_rate(size, jnp.float32, "float32")),
        cnn(plan_seeds),
        ("env_ocv2", lambda: env_rate("ocv2", batch, steps)),
        ("env_jaxmarl", lambda: env_rate("jaxmarl", batch, steps)),
        ("matmul_bf16", lambda: matmul_rate(size, jnp.bfloat16, "bfloat16")),
        # What float32 fidelity (run.precision, the default) costs: the plan's case at TF32, what JAX computes on
        # an H100 unless told otherwise, beside the same GPU's TF32 matmul rate.
        ("matmul_tf32", lambda: matmul_rate(size, jnp.float32, "tensorfloat32")),
        cnn(plan_seeds, "tf32"),
        # What XLA's deterministic GPU ops (run.deterministic, on in every other measurement: gpu_run.sh sets the
        # flag as the run's own process does) cost: the plan's case again in a process without the flag. Here,
        # before the RNN, so that a continued window's short measuring phase reaches it (the docs owe its cost).
        (f"{plan_case}_nondeterministic", lambda: without_determinism(plan_case, smoke)),
        # The CNN's matmul-only form (model.kernels=cpu: banded rows, written for XLA:CPU) on the GPU: float32
        # matmuls are not convolutions to cuDNN, and the study's float32 rate (150k) is far below its FLOP share.
        cnn(plan_seeds, kernels="cpu"),
        # An RNN update is 2 x 256 sequential GRU steps per minibatch: latency-bound on a GPU. Unrolling the
        # time loop and the hand-written backward pass (a shorter step) are the candidates; the Table 2 plan
        # trains with whichever 10-seed float32 variant measured fastest (best_rnn_sets), for the whole schedule.
        # The first window's fastest first (163k against 111k env steps/s for the plain form, at TF32): if the
        # measuring time holds one variant only, the study still trains the best known way.
        rnn(many, "xla", "hand", 8),
        rnn(many, "xla"),
        rnn(many, "cpu"),
        rnn(many, "xla", "autodiff", 8),
        rnn(many, "xla", "hand"),
        rnn(many, "xla", "hand", 32),
        rnn(many, "xla", "hand", 8, "tf32"),  # what TF32 would buy Table 2
        cnn(1),
        rnn(1, "xla"),
        rnn(1, "cpu"),
        *([] if smoke else [cnn(4), rnn(20, "xla"), rnn(20, "xla", "hand", 8)]),  # growth with seeds in one program
    ]
    if rnn_first:  # a stable sort: the float32 matmul rate (a second; the RNN rates' FLOP share is of it), the RNN
        # cases of the plan's seed count, in their order, then the rest in theirs
        ordered.sort(
            key=lambda case: 0 if case[0] == "matmul_f32" else 1 if case[0].startswith(f"rnn_sp_{many}_") else 2
        )
    return ordered


def precision_sets(precision: str) -> list[str]:
    """The ``--set`` of a measurement at ``precision`` (none at the configs' own float32)."""
    return [] if precision == "float32" else [f"run.precision={precision}"]


def precision_suffix(precision: str) -> str:
    return "" if precision == "float32" else f"_{precision}"


def rnn_sets(kernels: str, backward: str = "auto", unroll: int = 1) -> list[str]:
    """The ``--set`` overrides of one way to compute the RNN (the same function every way: docs/training.md)."""
    return [f"model.kernels={kernels}", f"model.gru_backward={backward}", f"model.gru_unroll={unroll}"]


def fastest_rnn_name(measured: dict, seeds: int) -> str | None:
    """The name of the fastest ``seeds``-seed RNN variant measured at float32, the precision the study trains at,
    or None."""
    rates = [
        name for name, result in measured.items()
        if name.startswith(f"rnn_sp_{seeds}_") and result.get("env_steps_per_s") and result.get("precision") == "float32"
    ]  # fmt: skip
    return max(rates, key=lambda name: measured[name]["env_steps_per_s"], default=None)


def fastest_rnn(measured: dict, seeds: int) -> dict | None:
    """The measurement ``fastest_rnn_name`` names, or None."""
    name = fastest_rnn_name(measured, seeds)
    return None if name is None else measured[name]


def best_rnn_sets(measured: dict, seeds: int) -> list[str]:
    """The overrides of the fastest ``seeds``-seed RNN variant measured at float32; when none was, the hand-written
    backward unrolled 8 steps, the fastest of the first window's (163k env steps/s against 111k for autodiff, at
    TF32): a study keeps its ``--set`` for the whole schedule, so the fallback is the best known, not the plainest."""
    best = fastest_rnn(measured, seeds)
    if best is None:
        return rnn_sets("xla", "hand", 8)
    return rnn_sets(best["kernels"], best["gru_backward"], best["gru_unroll"])


def without_determinism(name: str, smoke: bool) -> dict:
    """Measurement ``name`` in a child process whose XLA_FLAGS lack ``--xla_gpu_deterministic_ops``."""
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if "xla_gpu_deterministic_ops" not in f)
    command = [sys.executable, __file__, "--measure-one", name, "--out", "-"] + (["--smoke"] if smoke else [])
    done = subprocess.run(command, env={**os.environ, "XLA_FLAGS": flags}, capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        raise RuntimeError(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"rc {done.returncode}")
    return {**json.loads(done.stdout.strip().splitlines()[-1]), "XLA_FLAGS": flags}


def measure(deadline: float, smoke: bool, rnn_first: bool = False, known: frozenset = frozenset()) -> dict:
    """Every measurement that starts before ``deadline`` (each is one compile and a few seconds), but those in
    ``known`` (made in an earlier window the way they are made now: ``measured_before``)."""
    results = {}
    for name, thunk in measurements(smoke, rnn_first):
        if name in known:
            continue
        if time.time() > deadline:
            results[name] = {"skipped": "the measuring time was spent"}
            continue
        started = time.perf_counter()
        try:
            results[name] = thunk()
        except Exception as error:  # a failed measurement is a result too (e.g. jaxmarl not carried)
            results[name] = {"error": f"{type(error).__name__}: {error}"[:500]}
        results[name]["wall_s"] = round(time.perf_counter() - started, 1)
        log(f"measured {name}: {json.dumps(results[name])[:300]}")
    return results


# Bumped whenever a change to the measuring makes earlier windows' numbers stale (2: trainer rates traced under
# run.precision; the first windows measured them at JAX's default precision, TF32 on an H100).
METHOD = 2
HISTORY = ROOT / "docs" / "results" / "gpu_windows.json"  # every window's gpu_run.json (bench/gpu_report.py)


SAME_MACHINE = ("devices", "nvidia_smi", "versions")  # what an earlier window must share for its rates to stand


def measured_before(history: list[dict], environment: dict) -> dict:
    """The newest success of each measurement in earlier windows on the same machine (devices, driver and
    package versions as in ``environment``) measured by this ``METHOD``: a window need not spend its minutes on
    them again (bench/gpu_report.py lists them with their window), and the plan uses them where this window did
    not measure."""
    known = {}
    for window in history:
        if any(window.get("environment", {}).get(key) != environment.get(key) for key in SAME_MACHINE):
            continue
        for name, result in window.get("results", {}).items():
            # the matmul and environment-alone cases have been measured the same way by every METHOD so far
            same_way = window.get("method") == METHOD or name.startswith(("matmul_", "env_"))
            if same_way and ("tflops" in result or "env_steps_per_s" in result):
                known[name] = result
    return known


def read_history(path: Path = HISTORY) -> list[dict]:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):  # none yet, or unreadable: measure everything
        return []


# ---------------------------------------------------------------------------------------------------
# 3. plan
# ---------------------------------------------------------------------------------------------------


TABLE1 = "gpu_coord_ring_sp"  # Table 1 Coordination Ring SP: the first thing a GPU window trains
TABLE1_SA = "gpu_coord_ring_sa"
TABLE2 = "gpu_grounded_coord_simple_sp"  # Table 2 Grounded Coord. Simple SP: once TABLE1 has finished
PUBLISHED = ROOT / "docs" / "results"  # where bench/gpu_report.py files each study (docs/results/<study>/)


@dataclasses.dataclass(frozen=True)
class Step:
    """One study to run: configs/studies/``study``.yaml at ``budget`` (truncated) with ``seeds``."""

    study: str
    budget: float
    seeds: int
    train_s: float  # the planned training time at the measured rate
    resume: bool = False  # an earlier window's study, unpacked: its directory keeps budget, seeds and --set
    sets: tuple[str, ...] = ()  # --set overrides beyond the smoke sizes (e.g. the fastest RNN variant)
    rate_case: str = ""  # the measurement (gpu_run.json "results") whose rate planned it; "" when none did (resumed)

    def command(self, out: Path, smoke: bool) -> list[str]:
        study = [sys.executable, "-m", "cluster.cli", "study", "run", str(STUDIES / f"{self.study}.yaml")]
        if self.resume:
            return [*study, "--backend", "local", "--out", str(out / f"study_{self.study}")]
        overrides = [*(SMOKE_SETS + ["eval.episodes=4"] if smoke else []), *self.sets]
        return [
            *study, "--backend", "local", "--budget", f"{self.budget:.6g}", "--budget-mode", "truncate",
            "--seeds", str(self.seeds), "--out", str(out / f"study_{self.study}"),
            *(x for s in overrides for x in ("--set", s)),
        ]  # fmt: skip


def finished_here(study: str, published: Path = PUBLISHED) -> bool:
    """Whether ``study`` is published under ``published`` as finished (every step done, by the study_status.json
    bench/gpu_report.py files beside its report)."""
    from gpu_report import unfinished  # the same file read the same way as when it is filed

    return (published / study / "study_status.json").is_file() and not unfinished(published / study)


def plan(measured: dict, seconds_left: float, smoke: bool, table1_done: bool = False) -> list[Step]:
    """Table 1 until it has finished (``plan_table1``), then Table 2 (``plan_table2``)."""
    if table1_done:
        return plan_table2(measured, smoke)
    return plan_table1(measured, seconds_left, smoke)


def plan_table1(measured: dict, seconds_left: float, smoke: bool) -> list[Step]:
    """SP at the largest truncation that ends in time (at least 1 %), then SA in what SP leaves, if it is
    worth it. Reserve: a compile, the cross-play (500 episodes per ordered pair, both orders), the export."""
    seeds = 2 if smoke else 10
    rate = measured.get(f"cnn_sp_{seeds}", {}).get("env_steps_per_s")
    config = load_config(CR_SP, SMOKE_SETS if smoke else [])
    full_steps = seeds * config.ppo.total_timesteps
    case = f"cnn_sp_{seeds}" if rate else ""
    if smoke:  # 20 tiny updates: two chunks, a snapshot between them, then the cross-play
        budget = 20 * config.ppo.steps_per_update / config.ppo.total_timesteps
        return [Step(TABLE1, budget, seeds, float("nan"), rate_case=case)]
    if not rate:
        log("no 10-seed CNN rate measured: training SP at 10 % and letting the deadline stop it")
        return [Step(TABLE1, 0.1, seeds, float("nan"))]
    reserve = 90.0  # compile (~30 s) + 10x10 cross-play in both orders + export, from the CPU's proportions
    budget = max(0.01, min(1.0, (seconds_left - reserve) * rate / full_steps))
    steps = [Step(TABLE1, round(budget, 3), seeds, budget * full_steps / rate, rate_case=case)]
    left = seconds_left - reserve - steps[0].train_s
    if budget == 1.0 and left > reserve + 60:
        # SA trains as fast as SP between its iterations, plus 10 collections of 100 pairs x 10 rollouts.
        sa_budget = min(1.0, (left - reserve) * rate / full_steps / 1.3)
        if sa_budget >= 0.1:
            train_s = sa_budget * full_steps / rate * 1.3
            steps.append(Step(TABLE1_SA, round(sa_budget, 3), seeds, train_s, rate_case=case))
    return steps


def plan_table2(measured: dict, smoke: bool) -> list[Step]:
    """Grounded Coord. Simple SP, 10 seeds, the paper's whole 30M schedule (no window holds it: each trains until
    its deadline and packs the state that the next one continues), computed the fastest measured way."""
    seeds = 2 if smoke else 10
    config = load_config(GCS_SP, SMOKE_SETS if smoke else [])
    budget = 12 * config.ppo.steps_per_update / config.ppo.total_timesteps if smoke else 1.0
    case = fastest_rnn_name(measured, seeds)
    rate = measured[case]["env_steps_per_s"] if case else None
    train_s = budget * seeds * config.ppo.total_timesteps / rate if rate else float("nan")
    return [Step(TABLE2, budget, seeds, train_s, sets=tuple(best_rnn_sets(measured, seeds)), rate_case=case or "")]


# ---------------------------------------------------------------------------------------------------
# 4. train
# ---------------------------------------------------------------------------------------------------


STOP_GRACE_S = 40.0  # a chunk in flight at the deadline gets this long to finish and be saved; with the kill
# below and about a minute of export and packing, a 480 s deadline still ends inside the 600 s command
KILL_GRACE_S = 10.0  # then a second SIGTERM (exit at once), and this long before SIGKILL


def train(step: Step, out: Path, deadline: float, smoke: bool) -> dict:
    """Run one planned study until ``deadline``: then SIGTERM (it stops after the chunk in flight, saved; not SIGINT,
    which a process started without job control ignores), a second SIGTERM ``STOP_GRACE_S`` later (it stops at
    once, keeping its last checkpoint), SIGKILL ``KILL_GRACE_S`` after that: the packing after it must fit."""
    command = step.command(out, smoke)
    log("running " + " ".join(command))
    started = time.time()
    child = subprocess.Popen(command, cwd=ROOT, start_new_session=True)
    interrupted = False
    stops = [
        (deadline, signal.SIGTERM, "deadline: asking the study to stop after its chunk in flight"),
        (deadline + STOP_GRACE_S, signal.SIGTERM, "its chunk runs on past the grace: stopping it now"),
        (deadline + STOP_GRACE_S + KILL_GRACE_S, signal.SIGKILL, "still running: killed"),
    ]
    while child.poll() is None:
        if stops and time.time() > stops[0][0]:
            _, signum, message = stops.pop(0)
            log(message)
            child.send_signal(signum)
            interrupted = True
        time.sleep(0.2)
    record = {"step": dataclasses.asdict(step), "rc": child.returncode, "wall_s": round(time.time() - started, 1),
              "stopped_at_deadline": interrupted}  # fmt: skip
    if interrupted and child.returncode not in (0, 1, 130):
        # The signal can land after the study has finished (its report written, the process not gone yet): a
        # rehearsal on a loaded CPU saw rc -15 so. Its directory says whether anything was lost.
        record["finished"] = _done_here(out / f"study_{step.study}")
    return record


def _done_here(study_dir: Path) -> bool:
    """Whether ``study_dir`` says every step of its study is done (False if it cannot be read)."""
    from cluster.study.runner import study_status

    try:
        return study_done(study_status(study_dir))
    except Exception as error:  # an unreadable study is not finished
        log(f"{study_dir}: cannot read its status ({type(error).__name__}: {error})")
        return False


# ---------------------------------------------------------------------------------------------------
# 5. export and pack
# ---------------------------------------------------------------------------------------------------

RETURNED_FILES = 8  # what the device tool brings back from $OUT
POLICY_BYTES = 12 << 20  # exported policies per run, inside its results_<study>.tar.gz's 16 MiB (0.4 MB per CNN policy)


def export_policies(run_dir: Path, dest: Path) -> list:
    """Every seed's latest checkpoint, then kept snapshots from the newest back while ``POLICY_BYTES`` allows,
    as ``ocv2 export`` files listed in ``dest``/SHA256SUMS.json (``population.published``)."""
    from population import checkpoints as ckpt
    from population.published import publish_checkpoint, read_listing, write_listing

    config = load_config(run_dir / "config.yaml")
    seeds = range(config.population.num_seeds)
    updates = {seed: ckpt.list_updates(run_dir, seed) for seed in seeds}
    order = [(seed, updates[seed][-1]) for seed in seeds if updates[seed]]
    depth = max((len(u) for u in updates.values()), default=0)
    order += [(s, updates[s][-1 - k]) for k in range(1, depth) for s in seeds if k < len(updates[s])]
    exported, total = [], 0
    for seed, update in order:
        entry = publish_checkpoint(run_dir, dest, seed, update)
        size = (dest / entry.file).stat().st_size
        if total + size > POLICY_BYTES and exported:
            (dest / entry.file).unlink()
            break
        total += size
        exported.append(entry)
    # The study's other runs share dest: their entries stay in the listing.
    write_listing(dest, [*read_listing(dest), *exported])
    return exported


def study_done(status: list[dict]) -> bool:
    """Whether a study's ``study_status`` says every step is done."""
    return all(entry["status"] == "done" for entry in status)


def _pack_state(study_dir: Path, status: list[dict], returned: Path, studies: int) -> dict:
    """An unfinished study's resumable state into ``returned/state/`` (what the next window needs most: packed
    before any report or export), of ``studies`` this window returns; {} for a finished one (``status``)."""
    from cluster.study.pack import pack_study

    if study_done(status):
        return {}
    state = returned / "state"
    if state.exists():
        return {study_dir.name: "not packed: another unfinished study took state/ (one per window)"}
    # Only the newest update every seed has (and the snapshots a later step of the study reads; the GPU studies have no
    # such step): the others travel as exported policies, and all of them would not fit (6 snapshots of 10 CNN seeds
    # are about 80 MB; 10 RNN seeds 42 MB each).
    record = pack_study(study_dir, state, latest_only=True)
    packed = {study_dir.name: {"state": record["bytes"], "parts": len(record["parts"])}}
    # + pack.json, gpu_run.log, gpu_run.json and one results tarball per study
    if len(record["parts"]) + 3 + studies > RETURNED_FILES:
        packed[study_dir.name]["error"] = f"{len(record['parts'])} parts: more than {RETURNED_FILES} return"
    return packed


def _stage_results(study_dir: Path, status: list[dict], staging: Path) -> None:
    """A study's ``status``, report folder, exported policies, metrics and configs into ``staging``."""
    import shutil

    (staging / f"{study_dir.name}_status.json").write_text(json.dumps(status, indent=1))
    report = staging / f"{study_dir.name}_report"
    subprocess.run(
        [sys.executable, "-m", "cluster.cli", "study", "report", str(study_dir), "--out", str(report)],
        cwd=ROOT,
        check=False,
    )
    for run_dir in sorted((study_dir / "runs").iterdir()):
        if not (run_dir / "config.yaml").exists():
            continue
        policies = staging / f"{study_dir.name}_policies"
        policies.mkdir(exist_ok=True)
        export_policies(run_dir, policies)
        for name in ("metrics.csv", "config.yaml"):
            if (run_dir / name).exists():
                shutil.copy(run_dir / name, staging / f"{study_dir.name}_{run_dir.name}_{name}")


def results_name(study_dir: Path) -> str:
    return f"results_{study_dir.name.removeprefix('study_')}.tar.gz"


def pack(out: Path, returned: Path, only: Path | None = None) -> dict:
    """Every study of this window not packed yet (or ``only`` that one): first each unfinished study's resumable
    state as ``returned/state/`` (``ocv2 study pack``: pack.json and parts of at most 15 MiB), then one
    ``results_<study>.tar.gz`` per study (report, policies, metrics, gpu_run.json; each under the 16 MiB a returned
    file may have), written under a temporary name and renamed whole, so that a command cut off while packing
    returns no half archive."""
    import shutil
    import tarfile

    from cluster.study.runner import study_status

    packed, statuses = {}, {}
    every = sorted(out.glob("study_*"))
    study_dirs = [only] if only else [d for d in every if not (returned / results_name(d)).exists()]
    for study_dir in study_dirs:
        try:
            statuses[study_dir] = study_status(study_dir)
            packed.update(_pack_state(study_dir, statuses[study_dir], returned, len(every)))
        except Exception as error:  # its report and policies below still come back
            log(f"packing the state of {study_dir.name} failed: {type(error).__name__}: {error}")
            packed[study_dir.name] = {"error": f"{type(error).__name__}: {error}"}
    for study_dir in study_dirs:
        staging = out / "results" / study_dir.name
        staging.mkdir(parents=True, exist_ok=True)
        try:
            if study_dir in statuses:  # a study whose status cannot be read has its error recorded above
                _stage_results(study_dir, statuses[study_dir], staging)
        except Exception as error:  # one study's problem must not cost the window its results
            log(f"packing {study_dir.name} failed: {type(error).__name__}: {error}")
            packed[study_dir.name] = {"error": f"{type(error).__name__}: {error}"}
        shutil.copy(out / "gpu_run.json", staging / "gpu_run.json")
        name = results_name(study_dir)
        partial = returned / f".{name}.partial"  # a dot name: bench/gpu_report.py reads results*.tar.gz only
        with tarfile.open(partial, "w:gz") as tar:
            tar.add(staging, arcname="results")
        partial.rename(returned / name)
        packed[name] = (returned / name).stat().st_size
    return packed


def continued_step(state: Path, out: Path) -> Step:
    """The study a carried ``state`` (an earlier window's ``state/``) holds, unpacked into ``out``: go on with it."""
    from cluster.study.pack import unpack_study
    from cluster.study.runner import read_state

    record = unpack_study(state, out / "study_unpacking")
    study = str(record["study"])
    target = out / f"study_{study}"
    (out / "study_unpacking").rename(target)
    kept = read_state(target)
    return Step(study, kept.budget, kept.seeds, float("nan"), resume=True)


GO_ON_MIN_S = 150.0  # a new study after a finished one: an RNN compile (~35 s) and a few chunks at least


def finished(trained: dict, study_dir: Path) -> bool:
    """Whether a ``train`` record's study ran to its end (not stopped at the deadline, not failed) and its
    directory says every step is done."""
    if trained.get("finished"):  # signalled at the deadline after it had finished (``train``)
        return True
    if trained.get("rc") != 0 or trained.get("stopped_at_deadline"):
        return False
    return _done_here(study_dir)


def train_in_turn(steps: list[Step], out: Path, deadline: float, smoke: bool, record: dict, save) -> None:
    """``steps`` one after another until ``deadline``, each one's ``train`` record appended to record["trained"]."""
    save()
    log(f"plan: {[dataclasses.asdict(s) for s in steps]}")
    for step in steps:
        if time.time() > deadline - (5 if smoke else 30):  # a compile and a chunk at least
            record["trained"].append({"step": dataclasses.asdict(step), "skipped": "no time left"})
            continue
        record["trained"].append(train(step, out, deadline, smoke))
        save()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="folder for everything this run writes")
    parser.add_argument("--returned", help="folder for the files that come back (default: --out)")
    parser.add_argument("--deadline-s", type=float, default=480.0, help="seconds from start to stop training")
    parser.add_argument("--measure-s", type=float, default=120.0, help="seconds for measuring")
    parser.add_argument("--continue-from", type=Path, help="an earlier window's state/ folder: go on with it")
    parser.add_argument(
        "--started-at",
        type=float,
        help="when the command began, in epoch seconds (gpu_run.sh: before it installs the wheels): the deadline counts "
        "from it (default: this script's start; the measuring time always counts from this script's start)",
    )
    parser.add_argument(
        "--plan",
        choices=("auto", "table1", "table2"),
        default="auto",
        help="what to train without --continue-from: auto = Table 1 until docs/results holds it finished, then Table 2",
    )
    parser.add_argument("--smoke", action="store_true", default=os.environ.get("GPU_RUN_SMOKE") == "1")
    parser.add_argument("--measure-one", help=argparse.SUPPRESS)  # one measurement, as JSON on stdout
    args = parser.parse_args(argv)
    if args.measure_one:
        print(json.dumps(dict(measurements(args.smoke))[args.measure_one]()))
        return 0
    start = time.time()  # the measuring time counts from here, the deadline from the command's start
    out = Path(args.out)
    returned = Path(args.returned or out)
    for folder in (out, returned):
        folder.mkdir(parents=True, exist_ok=True)
    record = {"environment": environment(), "method": METHOD}

    def save() -> None:  # after every phase: a window cut short still returns what it reached
        (out / "gpu_run.json").write_text(json.dumps(record, indent=1))
        if returned.resolve() != out.resolve():
            shutil.copy(out / "gpu_run.json", returned / "gpu_run.json")

    save()
    log(f"devices {record['environment']['devices']}; {record['environment']['nvidia_smi']}; smoke={args.smoke}")
    table1_done = args.plan == "table2" or (args.plan == "auto" and finished_here(TABLE1))
    continue_from, held = args.continue_from, None
    if continue_from:
        held = json.loads((continue_from / "pack.json").read_text()).get("study")
        if finished_here(held):  # a window finished it and gpu_state/ was left behind: never train it again
            log(f"{continue_from} holds {held}, which docs/results holds finished: planning afresh (remove it)")
            continue_from = None
    # the RNN variants matter to a continued Table 2 run (measured for the record)
    rnn_first = held == TABLE2 if continue_from else table1_done
    known = {} if args.smoke else measured_before(read_history(), record["environment"])
    if known:
        log(f"measured in earlier windows, not again: {', '.join(known)}")
    record["results"] = measure(start + args.measure_s, args.smoke, rnn_first, frozenset(known))
    save()
    deadline = (args.started_at or start) + args.deadline_s
    if continue_from:
        steps = [continued_step(continue_from, out)]
    else:
        steps = plan({**known, **record["results"]}, deadline - time.time(), args.smoke, table1_done)
    record["plan"] = [dataclasses.asdict(s) for s in steps]
    record["trained"] = []
    train_in_turn(steps, out, deadline, args.smoke, record, save)
    # A continued Table 1 study that finished leaves the rest of the window: its results are packed at once (the
    # packing after the deadline must stay as short as with one study), then Table 2 starts in what is left, and
    # its state is what comes back for the next window (one study's state per window: Table 1's has finished).
    table1_dir = out / f"study_{TABLE1}"
    record["packed"] = {}
    if continue_from and steps[0].study == TABLE1 and finished(record["trained"][-1], table1_dir):
        record["packed"] = pack(out, returned, only=table1_dir)
        save()
        if deadline - time.time() > (20 if args.smoke else GO_ON_MIN_S):
            more = plan_table2({**known, **record["results"]}, args.smoke)
            record["plan"] += [dataclasses.asdict(s) for s in more]
            train_in_turn(more, out, deadline, args.smoke, record, save)
    record["packed"].update(pack(out, returned))
    save()
    log(f"trained: {json.dumps(record['trained'])}; packed: {record['packed']}; wall {time.time() - start:.0f} s")
    # A study's rc 1 (a step blocked) or 130 (stopped at the deadline) leaves a resumable directory.
    return 0 if all(d.get("rc", 0) in (0, 1, 130) or d.get("finished") for d in record["trained"]) else 1


if __name__ == "__main__":
    sys.exit(main())
