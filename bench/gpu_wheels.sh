#!/usr/bin/env bash
# Wheels bench/gpu_run.sh installs on a machine without network (a lent GPU machine has Python 3.12 with jax,
# flax, optax, numpy, pyyaml, rich, pillow, matplotlib, seaborn, chex, jaxtyping, safetensors, cloudpickle, but no
# mcap and no jaxmarl): mcap and its compressors (run archives), and jaxmarl with what its package import needs
# (the environment-alone comparison). Downloaded here, with network, into the git-ignored .whl/ (about 7.5 MB),
# for Python 3.12 on x86-64 Linux; the device tool carries it (carry: [".whl"]).
#   bash bench/gpu_wheels.sh [PYTHON_VERSION]      # default 3.12
set -euo pipefail
cd "$(dirname "$0")/.."
version=${1:-3.12}
tag=${version/./}
mkdir -p .whl
# Versions: constraints.txt's (the set the suite passed with).
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$version" --implementation cp \
    --abi "cp$tag" --abi abi3 --abi none --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform any -d .whl \
    mcap==1.6.0 lz4==4.4.5 zstandard==0.25.0 jaxmarl==0.2.0 gymnax==1.0.1 gymnasium==1.3.0 \
    farama-notifications==0.0.6
ls -1 .whl
