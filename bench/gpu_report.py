#!/usr/bin/env python
"""What a GPU window brought back, into the repository: docs/BENCHMARKS.md's GPU block and docs/results/.

    python bench/gpu_report.py FILES_DIR                 # the folder the device tool returned ($OUT's files)
    python bench/gpu_report.py FILES_DIR --results ''    # the benchmark block only

From ``gpu_run.json`` (bench/gpu_run.py's record: environment and measurements) it writes the block between ``<!-- gpu_run:start -->``
and ``<!-- gpu_run:end -->``: the device and versions, every measured trainer rate with its FLOP rate as a share
of the same GPU's matmul rate (float32 and bf16, measured in the same command), and the environment alone
against JaxMARL's. From ``results.tar.gz`` it unpacks each study's report folder, exported policies (with
their sha256 sums, checked here) and metrics into ``docs/results/gpu_coord_ring_<run>/``, beside gpu_run.json.
A ``state/`` folder that came back is the next window's starting point: move it to ``gpu_state/`` and commit it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import tarfile
import tempfile
from pathlib import Path

from sections import publish  # bench/ is sys.path[0] when a script runs

START, END = "<!-- gpu_run:start -->", "<!-- gpu_run:end -->"
ROOT = Path(__file__).resolve().parent.parent


def _rate(value) -> str:
    return "-" if value is None else f"{value:,.0f}"


def benchmark_block(bench: dict) -> str:
    env, results = bench["environment"], bench["results"]
    peaks = {k: results.get(k, {}).get("tflops") for k in ("matmul_f32", "matmul_bf16")}
    lines = [
        START,
        "## On a GPU (bench/gpu_run.sh)",
        "",
        f"- device: {', '.join(env['devices'])}; nvidia-smi: {env.get('nvidia_smi') or '-'}",
        f"- Python {env['python']}; "
        + ", ".join(f"{k} {v}" for k, v in env["versions"].items() if v and k != "python")
        + f"; XLA_FLAGS=`{env.get('XLA_FLAGS') or '(unset)'}`",
        "- matmul (jitted, random operands, median of 10): "
        + ", ".join(f"{k[7:]} {results[k]['size']}^3 {v:,.1f} TFLOP/s" for k, v in peaks.items() if v),
        "",
        "| measurement | seeds | kernels | env steps/s | model TFLOP/s | % of f32 matmul | % of bf16 matmul | compile+first (s) |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for name, r in results.items():
        if name.startswith("matmul") or name.startswith("env_"):
            continue
        if "env_steps_per_s" not in r:
            lines.append(f"| {name} | | | {r.get('skipped') or r.get('error')} | | | | |")
            continue
        shares = [f"{100 * r['model_tflops'] / p:.2f} %" if p else "-" for p in peaks.values()]
        lines.append(
            f"| {name} ({r['config']}) | {r['seeds']} | {r['kernels']} | {_rate(r['env_steps_per_s'])} | "
            f"{r['model_tflops']:.3f} | {shares[0]} | {shares[1]} | {r['compile_plus_first_s']} |"
        )
    ours, theirs = results.get("env_ocv2", {}), results.get("env_jaxmarl", {})
    lines += ["", "Environment alone (Coordination Ring, random actions, one jitted scan):", ""]
    for r, name in ((ours, "ocv2"), (theirs, "JaxMARL overcooked_v2")):
        if "env_steps_per_s" in r:
            lines.append(
                f"- {name}: {_rate(r['env_steps_per_s'])} env steps/s (batch {r['batch']}, {r['steps']} steps)"
            )
        else:
            lines.append(f"- {name}: {r.get('skipped') or r.get('error') or 'not measured'}")
    if "env_steps_per_s" in ours and "env_steps_per_s" in theirs:
        lines.append(f"- ratio: **{ours['env_steps_per_s'] / theirs['env_steps_per_s']:.2f}x** (target: at least 3x)")
    lines += ["", END]
    return "\n".join(lines)


def unpack_results(files: Path, dest_root: Path) -> list[Path]:
    """Each study of results.tar.gz into dest_root/gpu_<study>/, policies checked against their sums."""
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(files / "results.tar.gz") as tar:
            tar.extractall(tmp, filter="data")
        results = Path(tmp) / "results"
        studies = sorted({p.name.split("_report")[0] for p in results.glob("study_*_report")})
        for study in studies:  # every check before anything is written
            dest = dest_root / f"gpu_coord_ring_{study.removeprefix('study_')}"
            if dest.exists():
                raise SystemExit(f"{dest} exists: move it away first (nothing was written)")
            policies = results / f"{study}_policies"
            if policies.is_dir():
                for entry in json.loads((policies / "SHA256SUMS.json").read_text()):
                    digest = hashlib.sha256((policies / entry["file"]).read_bytes()).hexdigest()
                    if digest != entry["sha256"]:
                        raise SystemExit(
                            f"{policies.name}/{entry['file']}: sha256 {digest} is not {entry['sha256']} "
                            "(nothing was written)"
                        )
        for study in studies:
            dest = dest_root / f"gpu_coord_ring_{study.removeprefix('study_')}"
            shutil.copytree(results / f"{study}_report", dest)
            policies = results / f"{study}_policies"
            if policies.is_dir():
                shutil.copytree(policies, dest / "policies")
            for extra in results.glob(f"{study}_*_*"):
                if extra.is_file():
                    shutil.copy(extra, dest / extra.name.removeprefix(f"{study}_"))
            if (files / "gpu_run.json").exists():
                shutil.copy(files / "gpu_run.json", dest / "gpu_run.json")
            written.append(dest)
    return written


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", type=Path, help="the folder holding what bench/gpu_run.sh left in $OUT")
    parser.add_argument("--out", default=str(ROOT / "docs" / "BENCHMARKS.md"), help="'' prints only")
    parser.add_argument("--results", default=str(ROOT / "docs" / "results"), help="'' skips the unpacking")
    args = parser.parse_args(argv)
    publish(benchmark_block(json.loads((args.files / "gpu_run.json").read_text())), args.out, START, END)
    if args.results and (args.files / "results.tar.gz").exists():
        for dest in unpack_results(args.files, Path(args.results)):
            print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
