"""``ocv2 study``: many population runs and their comparisons as one resumable command.

    ocv2 study run STUDY.yaml [--budget F [--budget-mode truncate|compress]] [--seeds N] [--set K=V ...] [--backend ray|local] [--address A] [--out DIR] [--retrain RUN ...] [--extend]
    ocv2 study status DIR
    ocv2 study report DIR [--out FOLDER]
    ocv2 study publish DIR --out FOLDER [--which snapshots|final|all]

``run`` trains every run of the study that has not finished (resuming an interrupted one), runs the
cross-play steps and writes DIR/report.md; the same command after any interruption continues where it
stopped. ``status`` lists every step with its progress and an ETA from the throughput the study measured.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path

from cluster.api import require_backend
from cluster.archive import ArchiveError
from cluster.cli.args import add_set_option, bounded, check_new_folder, positive_int, resolved
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from cluster.runtime import ray_backend
from cluster.runtime.loggers import MissingExtraError
from cluster.runtime.progress import duration
from cluster.runtime.ray_backend import RayBackendError
from cluster.runtime.rundir import RunDirError
from cluster.study.pack import pack_study, unpack_study
from cluster.study.publish import publish_study
from cluster.study.report import damaged, write_report
from cluster.study.runner import (
    StudyOptions,
    continue_hint,
    kept_study,
    plan_study,
    read_state,
    run_study,
    study_status,
)
from cluster.study.spec import BUDGET_MODES, StudyError, default_out, load_study, run_config
from ocv2.atomic import staged_folder
from population.checkpoints import CheckpointError
from population.config import ClusterConfig, ConfigError
from population.numerics import enable_deterministic_ops
from population.policy import PolicyError
from population.published import WHICH, read_listing

#: A study's run is continued by the study command, with its budget and overrides, not by `ocv2 train CONFIG`.
STUDY_RESUME_HINT = "continue with the same `ocv2 study run` command"
BUDGET = bounded(float, 0, 100, "a fraction of the env steps in (0, 100], such as 0.25", low_open=True)


log = logging.getLogger(__name__)


def add_parser(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 study`` and its subcommands (run, status, report, publish, pack, unpack) on ``sub``
    (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "study",
        help="run many population jobs and their comparisons as one resumable study",
        description="Studies: a YAML file lists runs (config + overrides, with the paper's "
        "numbers) and comparisons; `run` trains, cross-plays and reports, and "
        "continues where it stopped after any interruption.",
    )
    commands = parser.add_subparsers(dest="study_command", metavar="{run,status,report,publish,pack,unpack}")
    commands.required = True
    run = commands.add_parser("run", help="train every unfinished run, cross-play, write DIR/report.md")
    run.add_argument("study", help="study file (see configs/studies/)")
    run.add_argument(
        "--budget",
        type=BUDGET,
        default=None,
        help="fraction of every run's env steps; default 1 = the configs as written",
    )
    run.add_argument(
        "--budget-mode",
        choices=BUDGET_MODES,
        default=None,
        help="truncate (default for a new study): each config's schedule as written (LR warm-up and decay, "
        "reward shaping, SA iterations), stopped after the budget's share of its steps; compress: the whole "
        "schedule squeezed into the shorter run (how studies ran before truncation; kept by such directories)",
    )
    run.add_argument("--seeds", type=positive_int, default=None, help="seeds per run (default: each config's own)")
    add_set_option(
        run,
        "override a config value in every run, after the study file's own (repeatable; kept by the "
        "study directory), e.g. --set eval.episodes=8 for a quick pilot of the whole study",
    )
    run.add_argument(
        "--backend",
        choices=["ray", "local"],
        default="ray",
        help="ray (default; a Ray started here unless --address) or local (one process, no Ray)",
    )
    run.add_argument("--address", help="Ray cluster to join: auto or HOST:PORT")
    run.add_argument("--out", help="study directory (default studies/<study name>)")
    run.add_argument(
        "--retrain",
        action="append",
        default=[],
        metavar="RUN",
        help="train RUN again although it was trained with another config than the study now asks for "
        "(repeatable); the trained run and its cross-play move to DIR/replaced/. Without it such a run is refused",
    )
    run.add_argument(
        "--extend",
        action="store_true",
        help="with a --budget larger than a truncating DIR has: train its runs on along the same schedules "
        "(the same numbers as training to that budget at once); the report and cross-play made at the old "
        "budget move to DIR/extended/",
    )
    run.add_argument("--quiet", action="store_true", help="no progress output")
    status = commands.add_parser("status", help="what is done, running and left, with an ETA")
    status.add_argument("dir", help="study directory")
    report = commands.add_parser("report", help="write DIR/report.md again from what is finished")
    report.add_argument("dir", help="study directory")
    report.add_argument(
        "--out",
        help="write the report, summary, pictures and cross-play matrices into this new or empty folder "
        "outside DIR instead (a compact record to keep: no checkpoints, no archives)",
    )
    publish = commands.add_parser(
        "publish", help="export the runs' policies into a folder with SHA256SUMS.json (population.published)"
    )
    publish.add_argument("dir", help="study directory")
    publish.add_argument("--out", required=True, help="the policies folder, e.g. docs/results/<study>/policies")
    publish.add_argument(
        "--which",
        choices=WHICH,
        default="snapshots",
        help="the kept snapshots (default), each seed's final checkpoint only, or every checkpoint on disk",
    )
    pack = commands.add_parser("pack", help="DIR's resumable state as parts of at most 15 MiB (cluster.study.pack)")
    pack.add_argument("dir", help="study directory")
    pack.add_argument("--out", required=True, help="new or empty folder for pack.json and the parts")
    pack.add_argument(
        "--latest-only",
        action="store_true",
        help="per run, only the newest update every seed has a checkpoint of (what resuming starts from; publish "
        "the snapshots before with `ocv2 study publish`)",
    )
    unpack = commands.add_parser("unpack", help="a packed study back into a directory that `run` continues")
    unpack.add_argument("source", help="folder holding pack.json and its parts")
    unpack.add_argument("--out", required=True, help="the study directory to create (must not exist)")
    return parser


def run(args) -> int:
    """Run the ``ocv2 study`` subcommand ``args.study_command`` names. Returns ``EXIT_OK``; raises
    ``CLIError`` with one line for what the user can fix (exit 2), or naming the steps that could not run
    (exit 1)."""
    if args.study_command in ("pack", "unpack"):
        return _pack(args)
    if args.study_command == "status":
        return _status(args.dir)
    if args.study_command == "report":
        return _report(args.dir, args.out)
    if args.study_command == "publish":
        return _publish(args)
    return _run(args)


def _run(args) -> int:
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if args.address and args.backend != "ray":
        raise CLIError("--address needs --backend ray")
    try:
        require_backend(args.backend)
        hint = continue_hint(args.study)  # a study directory given for the study file
        if hint is not None:
            raise CLIError(hint)
        study = load_study(args.study)
    except (StudyError, MissingExtraError) as error:
        raise CLIError(str(error)) from None
    out = Path(args.out) if args.out else default_out(study)
    say = (lambda message: None) if args.quiet else (lambda message: print(message, flush=True))
    options = StudyOptions(
        budget=args.budget,
        seeds=args.seeds,
        backend=args.backend,
        address=args.address,
        show_progress=not args.quiet,
        budget_mode=args.budget_mode,
        overrides=tuple(args.overrides),
        retrain=tuple(args.retrain),
        extend=args.extend,
    )
    # Every check before Ray starts and before the directory is written: a bad --set, a budget too small for
    # a config, a run this machine cannot hold, a trained run whose config changed (docs/studies.md).
    try:
        plan = plan_study(study, out, options)
    except (StudyError, RunDirError) as error:
        raise CLIError(str(error)) from None
    args.os_error_advice = (  # a full disk or a read-only folder: one line from cluster.cli.main
        f"{out} keeps every finished step and checkpoint; fix the cause (e.g. free disk space) and run the "
        "same command again to continue"
    )
    # The local backend trains in this process: XLA's deterministic GPU ops (run.deterministic) must be in
    # XLA_FLAGS before anything runs JAX here, as `ocv2 train` does; a run that turns them off does so alone.
    if any(config.run.deterministic for config in plan.configs.values()):
        applied, message = enable_deterministic_ops()
        log.log(logging.DEBUG if applied else logging.INFO, message)

    # One Ray for every run and comparison, started before the driver runs JAX (ray_backend.session); none when
    # every step is done and a rerun only writes the report again: run_study decides that under the directory's lock.
    def session(needed: bool):
        return ray_backend.session(args.backend if needed else "local", ClusterConfig(address=args.address))

    try:
        state = run_study(study, out, options, say=say, session=session)
    except RayBackendError as error:
        raise CLIError(error.with_hint(STUDY_RESUME_HINT)) from None
    except (StudyError, RunDirError, CheckpointError, ArchiveError, MissingExtraError) as error:
        raise CLIError(str(error)) from None
    blocked = {name: step for name, step in state.steps.items() if not step.done}
    print(f"report: {state.report['report']}")
    if blocked:
        for name, step in blocked.items():
            print(f"not done: {name}: {step.reason or step.status}")
        raise CLIError(
            f"{len(blocked)} step(s) could not run (above); fix them and run the same command again", EXIT_FAILURE
        )
    return EXIT_OK


def _pack(args) -> int:
    try:
        if args.study_command == "pack":
            record = pack_study(Path(args.dir), Path(args.out), latest_only=args.latest_only)
            print(f"packed {record['files']} files of study {record['study']!r} into {len(record['parts'])} part(s), "
                  f"{record['bytes']:,} bytes: {args.out}")  # fmt: skip
        else:
            record = unpack_study(Path(args.source), Path(args.out))
            print(f"unpacked study {record['study']!r} ({record['files']} files) into {args.out}")
    except StudyError as error:
        raise CLIError(str(error)) from None
    return EXIT_OK


def _publish(args) -> int:
    try:
        name, added = publish_study(args.dir, args.out, args.which)
        listed = {entry.file for entry in read_listing(args.out)} if Path(args.out).is_dir() else set()
    except (StudyError, RunDirError, CheckpointError, PolicyError, ConfigError) as error:
        raise CLIError(str(error)) from None
    if not any(added.values()):
        if not any(file.startswith(f"{run_name}_seed") for file in listed for run_name in added):
            hint = "; `--which final` publishes each seed's newest" if args.which == "snapshots" else ""
            raise CLIError(
                f"nothing to publish: no checkpoint of {name}'s runs ({', '.join(added)}) on disk is selected by "
                f"--which {args.which} (a kept snapshot is one of the updates run.num_checkpoints spreads over the "
                f"run{hint})"
            )
        print(f"{name}: nothing new; every checkpoint --which {args.which} selects is already listed in {args.out}")
    for run_name, entries in added.items():
        print(f"{name}/{run_name}: {len(entries)} policies exported into {args.out}")
    return EXIT_OK


def _status(directory: str) -> int:
    try:
        entries = study_status(directory)
    except (StudyError, RunDirError) as error:
        raise CLIError(str(error)) from None
    width = max(len(e["step"]) for e in entries)
    eta_total, unknown = 0.0, False
    for entry in entries:
        detail = "; ".join(filter(None, (entry.get("progress"), entry.get("detail"))))
        eta = entry.get("eta_s")
        if entry["status"] != "done" and entry["step"].startswith("train "):
            if eta is None:
                unknown = True
            else:
                eta_total += eta
        eta_text = "" if entry["status"] == "done" or eta is None else f"  ETA {duration(eta)}"
        print(
            f"{entry['step']:<{width}}  {entry['status']:<11}  {detail}{eta_text}  (wall {duration(entry['wall_s'])})"
        )
    counts = {s: sum(e["status"] == s for e in entries) for s in dict.fromkeys(e["status"] for e in entries)}
    if unknown and not eta_total:
        left = "unknown until this study has timed a chunk of training"
    else:
        left = duration(eta_total) + (" + runs of a model kind not timed yet" if unknown else "")
    print(", ".join(f"{n} {s}" for s, n in counts.items()) + f"; training left: {left} (cross-play not included)")
    return EXIT_OK


def _report(directory: str, dest: str | None) -> int:
    out = resolved(directory)
    try:
        state = read_state(out)
        if state is None:
            raise StudyError(f"{out}: not a study directory (no study.json)")
        if dest is not None:
            check_new_folder("--out", dest)
            inside = resolved(dest, "--out")
            if inside == out or out in inside.parents:  # it would write over the study's own results
                raise CLIError(f"--out {dest}: lies inside the study directory {out}; give a folder outside it")
        study = kept_study(state, out)
        configs = {r.name: run_config(study, r, out, state.budget, state.seeds, state.budget_mode) for r in study.runs}
        if dest is None:
            paths = write_report(study, out, state, configs)
        else:
            paths = _report_elsewhere(study, out, state, configs, Path(dest))
    except (StudyError, RunDirError) as error:
        raise CLIError(str(error)) from None
    for problem in damaged(json.loads(Path(paths["summary"]).read_text())):
        log.warning("%s; its cells say n/a, and `ocv2 study run` redoes the step", problem)
    print(f"wrote {paths['report']}")
    return EXIT_OK


def _report_elsewhere(study, out: Path, state, configs: dict, dest: Path) -> dict:
    """The report written into a staging folder beside ``dest`` (new or empty, checked) and moved there whole:
    a failure part-way leaves ``dest`` as it was, not half a report or a folder this command made."""
    # dest is new or empty (checked); an OSError is main's one line. The files that say "done" move in last.
    with staged_folder(dest, ".report", markers=["summary.json", "report.md"]) as staging:
        write_report(study, out, state, configs, staging)
    return {"report": str(dest / "report.md"), "summary": str(dest / "summary.json")}
