#!/usr/bin/env bash
# The prepared GPU run (bench/gpu_run.py says what it does): one command on a lent GPU machine, no network.
#
#   bash bench/gpu_wheels.sh                       # here, with network: the wheels it installs, into .whl/
#   device run, carry [".whl"], timeout_s 600:  bash bench/gpu_run.sh
#   GPU_RUN_SMOKE=1 bash bench/gpu_run.sh          # the rehearsal: the same steps, tiny, on a CPU (~2 minutes)
#
# What comes back, in $OUT (the device tool's folder; ./out/gpu_run elsewhere), at most 8 files: gpu_run.log,
# gpu_run.json (environment, measurements, plan, what trained), results_<study>.tar.gz (its report, exported policies
# with sha256 sums, metrics) and, when a study is left unfinished at the deadline, state/ (its resumable state:
# pack.json and parts of at most 15 MiB). bench/gpu_report.py files them into the repository; commit state/ as
# gpu_state/ and the next window continues that study instead of planning a new one.
# GPU_RUN_DEADLINE_S (default 480; 300 smoke, where a loaded CPU compiles the unrolled RNN variant measured first
# for minutes) is when training is told to stop, counted from the start of this command (the wheels' install and
# the flag check below included); the export and packing after it take about a minute, inside a 600 s command.
started=$(date +%s.%N)
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-$PWD/out/gpu_run}
mkdir -p "$out"
python=${PYTHON:-python3}
work=$(mktemp -d /tmp/ocv2-gpu-run.XXXXXX)
export PYTHONUNBUFFERED=1
# Memory on demand: the measuring process stays alive while the study trains in a child process, and JAX's
# default (75 % of the GPU taken at start) in both would leave the child a quarter.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
# The carried wheels, without network or build isolation, into a folder of their own (the machine's own
# packages stay as they are); only what the interpreter does not have already. Training needs neither mcap nor
# jaxmarl (studies write no trajectory archive), only the JaxMARL env measurement does, so a window that carried
# no .whl/ (a continued Table 2 window, short of the 64 MiB) still runs, and says what it goes without.
if ! "$python" -c "import mcap" 2>/dev/null || ! "$python" -c "import jaxmarl" 2>/dev/null; then
    if ! ls .whl/*.whl >/dev/null 2>&1; then
        echo "gpu_run: mcap or jaxmarl is missing and no .whl/ came along (bench/gpu_wheels.sh, carry .whl): going on" \
            "without them (no JaxMARL measurement, no trajectory archive)" >&2
    elif "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$work/site" \
        .whl/*.whl; then
        export PYTHONPATH="$PYTHONPATH:$work/site"  # before site-packages too; no carried wheel is one the machine has
    else
        echo "gpu_run: installing .whl/ failed: going on without its wheels" >&2
    fi
fi
# XLA's deterministic GPU ops, as the run's own process sets them (run.deterministic, on by default), so that
# what is measured is what trains; bench/gpu_run.py measures the plan's case once without them too.
export XLA_FLAGS="$("$python" -c 'import os; from population.xla_flags import extend_xla_flags as e
print(e(os.environ.get("XLA_FLAGS", ""), ["--xla_gpu_deterministic_ops=true"]))')"
# One compilation cache for this process and its children (the studies' programs compile once per window).
export JAX_COMPILATION_CACHE_DIR="$work/jax-cache"
smoke=${GPU_RUN_SMOKE:-0}
deadline=${GPU_RUN_DEADLINE_S:-$([ "$smoke" = 1 ] && echo 300 || echo 480)}
measure=$([ "$smoke" = 1 ] && echo 20 || echo 120)
continue_from=()
# The rehearsal leaves a committed gpu_state/ alone: it is a full-size study (tests/test_gpu_run.py checks that it
# resumes under this code), and the rehearsal rehearses the plan of a fresh window.
if [ "$smoke" != 1 ] && [ -f gpu_state/pack.json ]; then
    continue_from=(--continue-from gpu_state)  # an earlier window's unfinished study: go on with it
    # 75 s: the 10-seed CNN at float32 and TF32 (about 33 and 22 s, compile and a first run included) and the
    # determinism cost; a case runs whole if it starts before the measuring time ends, so these three take about
    # 100 s and the rest of Coordination Ring SP (about 220 s) with its cross-play still fits the 480 s deadline.
    measure=75
fi
"$python" bench/gpu_run.py --out "$work/run" --returned "$out" --deadline-s "$deadline" --measure-s "$measure" \
    --started-at "$started" "${continue_from[@]}" 2>&1 | tee "$out/gpu_run.log"
rc=${PIPESTATUS[0]}
ls -lR "$out" | tee -a "$out/gpu_run.log"
rm -rf "$work"
exit "$rc"
