#!/usr/bin/env bash
# The prepared GPU run (bench/gpu_run.py says what it does): one command on a lent GPU machine, no network.
#
#   bash bench/gpu_wheels.sh                       # here, with network: the wheels it installs, into .whl/
#   device run, carry [".whl"], timeout_s 600:  bash bench/gpu_run.sh
#   GPU_RUN_SMOKE=1 bash bench/gpu_run.sh          # the rehearsal: the same steps, tiny, on a CPU (~2 minutes)
#
# Everything comes back as at most 8 files in $OUT (the device tool's folder; ./out/gpu_run elsewhere):
# gpu_run.log, environment.json, bench.json, plan.json, trained.json, results.tar.gz (study reports, exported
# policies with sha256 sums, metrics) and checkpoints.tar.gz (the latest checkpoint of every seed, to resume).
# GPU_RUN_DEADLINE_S (default 480; 140 smoke) is when training is told to stop, counted from the start of
# bench/gpu_run.py; the export and packing after it take about a minute, inside a 600 s command.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-$PWD/out/gpu_run}
mkdir -p "$out"
python=${PYTHON:-python3}
work=$(mktemp -d /tmp/ocv2-gpu-run.XXXXXX)
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
# The carried wheels, without network or build isolation, into a folder of their own (the machine's own
# packages stay as they are); only what the interpreter does not have already.
if ! "$python" -c "import mcap" 2>/dev/null || ! "$python" -c "import jaxmarl" 2>/dev/null; then
    if ! ls .whl/*.whl >/dev/null 2>&1; then
        echo "gpu_run: mcap or jaxmarl is missing and there is no .whl/ to install them from: run bench/gpu_wheels.sh" \
            "here and carry .whl" | tee "$out/gpu_run.log" >&2
        exit 2
    fi
    "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$work/site" .whl/*.whl \
        || { echo "gpu_run: installing .whl/ failed" >&2; exit 2; }
    export PYTHONPATH="$PYTHONPATH:$work/site"  # after the checkout and the machine's own site-packages
fi
# XLA's deterministic GPU ops, as the run's own process sets them (run.deterministic, on by default), so that
# what is measured is what trains; bench/gpu_run.py measures the plan's case once without them too.
export XLA_FLAGS="$("$python" -c 'import os; from population.xla_flags import extend_xla_flags as e
print(e(os.environ.get("XLA_FLAGS", ""), ["--xla_gpu_deterministic_ops=true"]))')"
# One compilation cache for this process and its children (the studies' programs compile once per window).
export JAX_COMPILATION_CACHE_DIR="$work/jax-cache"
smoke=${GPU_RUN_SMOKE:-0}
deadline=${GPU_RUN_DEADLINE_S:-$([ "$smoke" = 1 ] && echo 140 || echo 480)}
measure=$([ "$smoke" = 1 ] && echo 20 || echo 120)
"$python" bench/gpu_run.py --out "$work/run" --deadline-s "$deadline" --measure-s "$measure" 2>&1 | tee "$out/gpu_run.log"
rc=${PIPESTATUS[0]}
for name in environment.json bench.json plan.json trained.json results.tar.gz checkpoints.tar.gz; do
    if [ -f "$work/run/$name" ]; then cp "$work/run/$name" "$out/"; else echo "gpu_run: no $name" | tee -a "$out/gpu_run.log"; fi
done
ls -l "$out" | tee -a "$out/gpu_run.log"
rm -rf "$work"
exit "$rc"
