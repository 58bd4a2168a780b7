#!/usr/bin/env python
"""What a GPU window brought back, into the repository: docs/BENCHMARKS.md's GPU block and docs/results/.

    python bench/gpu_report.py FILES_DIR                 # the folder the device tool returned ($OUT's files)
    python bench/gpu_report.py FILES_DIR --results ''    # the benchmark block only

From ``gpu_run.json`` (bench/gpu_run.py's record: environment and measurements) it writes the block between ``<!-- gpu_run:start -->``
and ``<!-- gpu_run:end -->``: the device and versions, every measured trainer rate with its FLOP rate as a share
of the same GPU's matmul rate at the trainer's precision (float32, TF32 or bf16, measured in the same command), and the environment alone
against JaxMARL's, and how fast this window's studies trained. From ``results_<study>.tar.gz`` (``results.tar.gz``
before) it unpacks each study's report folder, exported policies (with
their sha256 sums, checked here), metrics and the study's status into ``docs/results/<study>/``, beside
gpu_run.json (replacing an earlier window's unfinished part of the same study). Every window's record is
appended to docs/results/gpu_windows.json, and the block lists below this window's measurements those of earlier
windows it did not make again (a continued window measures for 75 s only). A ``state/`` folder that came back
is the next window's starting point: move it to ``gpu_state/`` and commit it; this script says whether it fits
what travels to the GPU machine (64 MiB with the work tree and .whl/).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from sections import publish  # bench/ is sys.path[0] when a script runs

from population import checkpoints as ckpt
from population import published
from population.config import load_config
from population.policy import PolicyError

START, END = "<!-- gpu_run:start -->", "<!-- gpu_run:end -->"
ROOT = Path(__file__).resolve().parent.parent
HISTORY = ROOT / "docs" / "results" / "gpu_windows.json"  # every window's gpu_run.json, oldest first


def _rate(value) -> str:
    return "-" if value is None else f"{value:,.0f}"


def _computed(result: dict) -> str:
    """How the network was computed: the kernel family, and for the RNN the GRU's backward pass and unrolling."""
    if result.get("model") != "rnn" or "gru_backward" not in result:
        return result["kernels"]
    return f"{result['kernels']}, GRU {result['gru_backward']}, unroll {result['gru_unroll']}"


def _measured(result: dict) -> bool:
    return "env_steps_per_s" in result or "tflops" in result


# The matmul measurement whose rate a trainer row's FLOP rate is a share of: the same precision. A row without a
# precision was measured before trainer rates were traced under run.precision (gpu_run.METHOD 1): at JAX's default,
# which is TF32 on an H100, so its share is of the TF32 matmul rate.
PEAK_OF = {"float32": "matmul_f32", "tf32": "matmul_tf32", "bf16": "matmul_bf16", None: "matmul_tf32"}
DEFAULT_PRECISION = "default (TF32)"
HEADER = (
    "| measurement | seeds | kernels | precision | env steps/s | model TFLOP/s | % of the matmul rate at that precision "
    "| compile+first (s) |"
)
RULE = "|---|---:|---|---|---:|---:|---:|---:|"


def _trainer_row(name: str, r: dict, peaks: dict, window: str | None = None) -> str:
    peak = peaks.get(PEAK_OF.get(r.get("precision"), ""))
    share = f"{100 * r['model_tflops'] / peak:.2f} %" if peak else "-"
    return (
        f"| {name} ({r['config']}) | {r['seeds']} | {_computed(r)} | {r.get('precision') or DEFAULT_PRECISION} | "
        f"{_rate(r['env_steps_per_s'])} | {r['model_tflops']:.3f} | {share} | {r['compile_plus_first_s']} |"
        + ("" if window is None else f" {window} |")
    )


def _peaks(results: dict) -> dict:
    return {k: results.get(k, {}).get("tflops") for k in ("matmul_f32", "matmul_tf32", "matmul_bf16")}


def benchmark_block(bench: dict, earlier: list[dict] = (), studies: list[str] = ()) -> str:
    """The GPU block of this window's record ``bench``; ``earlier``: the records of earlier windows (oldest
    first), whose trainer measurements this window did not make again (a continued window measures for 75 s only)
    are listed below its own, each with its window's date and device and shares of that window's matmul peaks;
    ``studies``: lines saying how fast this window's studies trained (``study_rates``)."""
    env, results = bench["environment"], bench["results"]
    peaks = _peaks(results)
    for window in _here_newest_first(earlier, env):  # a rate not measured again: the newest earlier window's
        peaks = {k: v or _peaks(window["results"])[k] for k, v in peaks.items()}
    lines = [
        START,
        "## On a GPU (bench/gpu_run.sh)",
        "",
        f"- device: {', '.join(env['devices'])}; nvidia-smi: {env.get('nvidia_smi') or '-'}",
        f"- Python {env['python']}; "
        + ", ".join(f"{k} {v}" for k, v in env["versions"].items() if v and k != "python")
        + f"; XLA_FLAGS=`{env.get('XLA_FLAGS') or '(unset)'}`",
        "- matmul (jitted, random operands, median of 10; * an earlier window's): "
        + ", ".join(
            f"{k[7:]} {v:,.1f} TFLOP/s" + ("" if results.get(k, {}).get("tflops") else "*")
            for k, v in peaks.items()
            if v
        ),
        "",
        HEADER,
        RULE,
    ]
    not_measured = {}  # reason -> names: one line each below the table
    for name, r in results.items():
        if name.startswith("matmul") or name.startswith("env_"):
            continue
        if "env_steps_per_s" not in r:
            not_measured.setdefault(r.get("skipped") or r.get("error") or "no result", []).append(name)
            continue
        lines.append(_trainer_row(name, r, peaks))
    if not_measured:
        lines.append("")
        lines += [f"Not measured ({reason}): {', '.join(names)}." for reason, names in not_measured.items()]
    older = {}  # name -> (row): the newest earlier success of each measurement this window did not make
    for window in earlier:
        label = f"{window['environment'].get('date', 'undated')}, {', '.join(window['environment']['devices'])}"
        for name, r in window["results"].items():
            if "env_steps_per_s" in r and "model_tflops" in r and not _measured(results.get(name, {})):
                older[name] = _trainer_row(name, r, _peaks(window["results"]), label)
    if older:
        lines += ["", "Measured in earlier windows and not again in this one:", "", HEADER + " window |", RULE + "---|"]
        lines += older.values()
    if any(r.get("precision") is None for r in results.values() if "model_tflops" in r) or any(
        DEFAULT_PRECISION in row for row in older.values()
    ):
        lines += [
            "",
            f"Precision {DEFAULT_PRECISION}: measured before the trainer rates were traced under `run.precision`, at "
            "JAX's own default, which is TF32 on an H100; the studies train at float32 (`run.precision`'s default) "
            "unless told otherwise.",
        ]
    if studies:
        lines += ["", "Training in this window's studies (`ocv2 study run`, the whole run as it trains):", "", *studies]
    ours, theirs = (_newest(name, results, _here_newest_first(earlier, env)) for name in ("env_ocv2", "env_jaxmarl"))
    lines += ["", "Environment alone (Coordination Ring, random actions, one jitted scan):", ""]
    for r, name in ((ours, "ocv2"), (theirs, "JaxMARL overcooked_v2")):
        if "env_steps_per_s" in r:
            lines.append(
                f"- {name}: {_rate(r['env_steps_per_s'])} env steps/s (batch {r['batch']}, {r['steps']} steps"
                + (f"; measured in the window of {r['window']})" if "window" in r else ")")
            )
        else:
            lines.append(f"- {name}: {r.get('skipped') or r.get('error') or 'not measured'}")
    if "env_steps_per_s" in ours and "env_steps_per_s" in theirs:
        lines.append(f"- ratio: **{ours['env_steps_per_s'] / theirs['env_steps_per_s']:.2f}x** (target: at least 3x)")
    lines += ["", END]
    return "\n".join(lines)


def _here_newest_first(earlier: list[dict], env: dict) -> list[dict]:
    """The earlier windows (oldest first in ``earlier``) on this window's devices, newest first."""
    return [window for window in reversed(earlier) if window["environment"].get("devices") == env.get("devices")]


def _newest(name: str, results: dict, here: list[dict]) -> dict:
    """This window's result ``name``, or else the newest of the earlier windows ``here`` (with its date as
    "window"), or {}."""
    if name in results:
        return results[name]
    for window in here:
        found = window["results"].get(name, {})
        if "env_steps_per_s" in found:
            return {**found, "window": window["environment"].get("date", "undated")}
    return {}


def result_archives(files: Path) -> list[Path]:
    """What a window returned of its studies: one ``results_<study>.tar.gz`` per study (``results.tar.gz`` from
    windows before that)."""
    return sorted(files.glob("results*.tar.gz"))


def study_rates(files: Path) -> list[str]:
    """One line per run trained in the window: its median chunk rate (env steps/s from the run's metrics.csv, each
    chunk's wall time as the run measured it) and the precision of its config."""
    import csv
    import io
    import statistics

    import yaml

    lines = []
    for archive in result_archives(files):
        try:
            tar = tarfile.open(archive)
            members = {m.name: m for m in tar.getmembers() if m.isfile()}
        except (tarfile.TarError, OSError, EOFError) as error:
            lines.append(f"- {archive.name}: unreadable ({type(error).__name__}: {error})")
            continue
        with tar:
            studies = {
                Path(n).parent.name.removesuffix("_report") for n in members if Path(n).parent.name.endswith("_report")
            }
            for name, member in sorted(members.items()):
                if not name.endswith("_metrics.csv") or Path(name).parent.name != "results":  # the run's own copy
                    continue
                rows = list(csv.DictReader(io.TextIOWrapper(tar.extractfile(member), "utf-8")))
                chunks = {(r["update"], r["steps_per_s"]) for r in rows if r.get("seed") == rows[0].get("seed")}
                rates = [float(rate) for _, rate in chunks if rate]
                if not rates:
                    continue
                config = members.get(name.removesuffix("metrics.csv") + "config.yaml")
                run = yaml.safe_load(tar.extractfile(config)).get("run", {}) if config else {}
                seeds = len({r["seed"] for r in rows})
                file = Path(name).name  # study_<study>_<run>_metrics.csv, <study> from its report folder's name
                study = max((x for x in studies if file.startswith(f"{x}_")), key=len, default="")
                label = f"{study.removeprefix('study_')}, run {file[len(study) + 1 :].removesuffix('_metrics.csv')}"
                lines.append(
                    f"- {label}: {_rate(statistics.median(rates))} env steps/s (median over {len(rates)} updates, "
                    f"{seeds} seeds; precision {run.get('precision', 'float32')}, deterministic "
                    f"{str(run.get('deterministic', True)).lower()})"
                )
    return lines


def unfinished(dest: Path) -> bool:
    """Whether ``dest`` holds a study filed before it had finished (its study_status.json has a step not done):
    a later window's results of the same study supersede it."""
    status = dest / "study_status.json"
    return status.is_file() and any(entry["status"] != "done" for entry in json.loads(status.read_text()))


def unpack_results(files: Path, dest_root: Path) -> list[Path]:
    """Each study of the returned archives into dest_root/<study>/, policies checked against their sums. A folder there
    already is replaced only when it holds the same study unfinished (an earlier window's part of it)."""
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        results = Path(tmp) / "results"
        results.mkdir()
        for index, archive in enumerate(result_archives(files)):
            whole = Path(tmp) / f"archive{index}"  # an archive is filed whole or not at all (a command cut short)
            try:
                with tarfile.open(archive) as tar:
                    tar.extractall(whole, filter="data")
            except (tarfile.TarError, OSError, EOFError) as error:
                print(f"{archive}: unreadable, nothing of it is filed ({type(error).__name__}: {error})")
                continue
            for entry in (whole / "results").iterdir():
                if not (results / entry.name).exists():  # gpu_run.json is in every archive
                    entry.rename(results / entry.name)
        studies = sorted({p.name.split("_report")[0] for p in results.glob("study_*_report")})
        kept_by_study = {}
        for study in studies:  # every check before anything is written
            dest = dest_root / study.removeprefix("study_")
            if dest.exists() and not unfinished(dest):
                raise SystemExit(f"{dest} exists and holds a finished study: move it away first (nothing was written)")
            kept_by_study[study] = earlier_snapshots(dest, Path(tmp) / f"{study}_kept")
            policies = results / f"{study}_policies"
            if policies.is_dir():
                try:
                    published.verify(policies, [entry.file for entry in published.read_listing(policies)])
                except PolicyError as error:
                    raise SystemExit(f"{error} (nothing was written)") from None
        for study in studies:
            dest = dest_root / study.removeprefix("study_")
            kept = kept_by_study[study]
            if dest.exists():
                print(f"{dest}: an earlier window's unfinished part of this study, replaced by this window's")
                shutil.rmtree(dest)
            shutil.copytree(results / f"{study}_report", dest)
            policies = results / f"{study}_policies"
            if policies.is_dir():
                shutil.copytree(policies, dest / "policies")
            if kept:
                keep_snapshots(kept, Path(tmp) / f"{study}_kept", dest / "policies")
            for extra in results.glob(f"{study}_*_*"):
                if extra.is_file():
                    shutil.copy(extra, dest / extra.name.removeprefix(f"{study}_"))
            if (results / f"{study}_status.json").is_file():
                shutil.copy(results / f"{study}_status.json", dest / "study_status.json")
            if (files / "gpu_run.json").exists():
                shutil.copy(files / "gpu_run.json", dest / "gpu_run.json")
            written.append(dest)
    return written


def earlier_snapshots(dest: Path, holding: Path) -> list:
    """The snapshot policies (``run.num_checkpoints``' updates, by the run's config beside them) an earlier window
    published in ``dest``, checked against their sums and copied to ``holding``: a window returns only its own
    latest snapshots, and the earlier ones would be lost with the folder it replaces. Deadline stops between
    snapshots are not kept (the next window supersedes them)."""
    folder = dest / "policies"
    if not (folder / published.SUMS).is_file():
        return []
    try:
        entries = published.checked_listing(folder)
    except PolicyError as error:
        raise SystemExit(f"{error} (nothing was written)") from None
    kept = []
    for entry in entries:
        config = dest / f"{entry.file.rsplit('_seed', 1)[0]}_config.yaml"
        if not config.is_file():
            continue
        run = load_config(config)
        if entry.update in ckpt.snapshot_updates(run.ppo.num_updates, run.run.num_checkpoints):
            kept.append(entry)
    holding.mkdir(parents=True, exist_ok=True)
    for entry in kept:
        shutil.copy(folder / entry.file, holding / entry.file)
    return kept


def keep_snapshots(kept: list, holding: Path, folder: Path) -> None:
    """Add the ``kept`` earlier snapshots (in ``holding``) that this window did not return to ``folder``'s files
    and listing."""
    folder.mkdir(exist_ok=True)
    listing = published.read_listing(folder) if (folder / published.SUMS).is_file() else []
    known = {entry.file for entry in listing}
    added = [entry for entry in kept if entry.file not in known]
    for entry in added:
        shutil.copy(holding / entry.file, folder / entry.file)
    published.write_listing(folder, sorted([*listing, *added], key=lambda e: (e.update, e.seed)))
    if added:
        print(f"{folder}: kept {len(added)} snapshot policies of earlier windows")


TRAVEL_BYTES = 64 << 20  # what the device tool copies to the GPU machine: the work tree and the carried paths


def travel_check(state: Path, root: Path = ROOT) -> str:
    """Whether the next window's input fits what travels: the tracked work tree (gpu_state/ replaced by ``state``)
    and the carried .whl/; and if not, whether it fits once bench/gpu_slim.sh has taken what the GPU machine never
    reads out of the work tree: the published policies and the CPU studies packed in study_state/."""
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True).stdout.split(b"\0")
    files = [root / n.decode() for n in tracked if n and not n.startswith(b"gpu_state/")]
    sizes = {path: path.stat().st_size for path in files if path.is_file()}
    tree = sum(sizes.values())
    results, packs = root / "docs" / "results", root / "study_state"  # what bench/gpu_slim.sh takes out
    policies = sum(
        size for path, size in sizes.items() if path.suffix == ".ocv2policy" and path.is_relative_to(results)
    )
    packed = sum(size for path, size in sizes.items() if path.parent != packs and path.is_relative_to(packs))
    wheels = sum(p.stat().st_size for p in (root / ".whl").glob("*")) if (root / ".whl").is_dir() else 0
    carried = sum(p.stat().st_size for p in state.rglob("*") if p.is_file())
    total = tree + wheels + carried
    line = (
        f"next window carries {total / 2**20:.1f} MiB of {TRAVEL_BYTES / 2**20:.0f} MiB: work tree "
        f"{tree / 2**20:.1f} (published policies {policies / 2**20:.1f} and study_state/ packs {packed / 2**20:.1f} "
        f"of it), .whl {wheels / 2**20:.1f}, state {carried / 2**20:.1f}"
    )
    if total - policies - packed - wheels > TRAVEL_BYTES:
        line += " -- TOO MUCH even without the published policies, study packs and .whl: remove large results first"
    elif total - policies - packed > TRAVEL_BYTES:  # the wheels serve the JaxMARL measurement only (gpu_run.sh)
        line += (
            " -- run `bash bench/gpu_slim.sh` before the call (and `bash bench/gpu_slim.sh --restore` after it), and"
            " carry nothing: without .whl it fits (training needs neither mcap nor jaxmarl)"
        )
    elif total > TRAVEL_BYTES:
        line += " -- run `bash bench/gpu_slim.sh` before the call (and `bash bench/gpu_slim.sh --restore` after it)"
    return line


def refuse_slimmed(root: Path = ROOT) -> None:
    """SystemExit while bench/gpu_slim.sh has the published policies or study packs out (deleted from the work tree
    or the index): filing a window reads earlier windows' policies, and a commit then would take the deletions."""
    slimmed = [
        subprocess.run(command, cwd=root, capture_output=True, text=True, check=True).stdout.strip()
        for command in (
            ["git", "ls-files", "--deleted", "--", "docs/results", "study_state"],
            ["git", "diff", "--cached", "--name-only", "--diff-filter=D", "--", "docs/results", "study_state"],
        )
    ]
    if any(slimmed):
        count = len(set("\n".join(slimmed).split()))
        raise SystemExit(
            f"gpu_report: {count} files of docs/results or study_state are out: bash bench/gpu_slim.sh --restore first"
        )


def index_lists(folder: Path) -> bool:
    """Whether the results index (README.md beside ``folder``) names it, as tests/test_docs.py requires."""
    index = folder.parent / "README.md"
    return index.is_file() and f"[{folder.name}/]({folder.name}/" in index.read_text()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", type=Path, help="the folder holding what bench/gpu_run.sh left in $OUT")
    parser.add_argument("--out", default=str(ROOT / "docs" / "BENCHMARKS.md"), help="'' prints only")
    parser.add_argument("--results", default=str(ROOT / "docs" / "results"), help="'' skips the unpacking")
    parser.add_argument("--history", default=str(HISTORY), help="every window's record, appended ('' skips)")
    args = parser.parse_args(argv)
    refuse_slimmed()
    record = args.files / "gpu_run.json"
    if not record.is_file():  # gpu_run.sh stopped before gpu_run.py began (its log says why: no wheels to install)
        log_file = args.files / "gpu_run.log"
        why = log_file.read_text().strip().splitlines()[-1:] if log_file.is_file() else ["no gpu_run.log either"]
        raise SystemExit(f"gpu_report: no gpu_run.json in {args.files}: nothing was measured or trained ({why[0]})")
    bench = json.loads(record.read_text())
    bench.setdefault("results", {})  # a window cut off while measuring: what it reached is still filed
    history = json.loads(Path(args.history).read_text()) if args.history and Path(args.history).is_file() else []
    earlier = [window for window in history if window["environment"] != bench["environment"]]
    publish(benchmark_block(bench, earlier, study_rates(args.files)), args.out, START, END)
    if args.history and len(earlier) == len(history):  # this window is not on record yet
        temporary = Path(args.history).with_suffix(".json.tmp")
        temporary.write_text(json.dumps([*history, bench], indent=1) + "\n")
        temporary.replace(args.history)  # whole or not at all
    if args.results and result_archives(args.files):
        for dest in unpack_results(args.files, Path(args.results)):
            print(f"wrote {dest}")
            if not index_lists(dest):
                print(f"also: add {dest.name}/ to {dest.parent / 'README.md'} (tests/test_docs.py checks every folder)")
    if args.out:
        print(
            "also: the summary table at the top of docs/BENCHMARKS.md has a GPU row written by hand; bring it up to date"
        )
    if (args.files / "state").is_dir():
        print(travel_check(args.files / "state"))
    elif bench.get("plan") and "packed" not in bench:
        print(
            "warning: this window planned training but its record ends before packing (the command was cut off?): "
            "what it trained came back only if a state/ or results_*.tar.gz is here"
        )
    print(state_advice(args.files, Path(args.results) if args.results else None))
    return 0


def state_advice(files: Path, results: Path | None, root: Path = ROOT) -> str:
    """What to do with gpu_state/ after this window: replace it with a returned state/, or remove it once the study
    it holds is filed as finished (else the next window would train that study again)."""
    held = root / "gpu_state" / "pack.json"
    if (files / "state").is_dir():
        return (
            f"next: rm -rf gpu_state && cp -r {files / 'state'} gpu_state && git add -A gpu_state "
            "(the next window continues it)"
        )
    if held.is_file() and results is not None:
        study = json.loads(held.read_text()).get("study")
        status = results / str(study) / "study_status.json"
        if status.is_file() and not unfinished(results / str(study)):
            return f"next: git rm -r -q gpu_state ({study} is filed as finished; nothing to continue)"
    return "next: nothing to do with gpu_state/"


if __name__ == "__main__":
    sys.exit(main())
