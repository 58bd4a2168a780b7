"""``ocv2 xp``: cross-play of one run, or across runs and policy files.

    ocv2 xp RUN_DIR [--episodes N] [--wait]
    ocv2 xp --rows SRC [SRC ...] [--cols SRC ...] [--checkpoint final|mid|init|latest|N] [--greedy]
            [--seats both|0] [--pool] [--episodes N] [--seed S] [--out DIR] [--backend ray|local]
            [--address A] [--workers N] [--precision float32|tf32|bf16]

A source SRC is a run directory (all its seeds), a seed directory RUN_DIR/checkpoints/seed_<i>, a
checkpoint file, a file written by ``ocv2 export`` (``cluster/cli/export.py``), or ``human-proxy:LAYOUT``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import logging
import os
import time
from pathlib import Path

from cluster.archive import ArchiveError
from cluster.cli.args import check_new_folder, checkpoint_choice, positive_int, resolved, seed
from cluster.cli.errors import EXIT_OK, CLIError
from cluster.runtime import crossplay, ray_backend, xp_journal
from cluster.runtime.environment import describe_devices
from cluster.runtime.evaluate import evaluate_run
from cluster.runtime.progress import Bar
from cluster.runtime.ray_backend import RayBackendError
from cluster.runtime.rundir import RunDir, RunDirError
from cluster.runtime.xp_journal import JournalMismatch, XPJournal
from ocv2.atomic import staged_folder
from population.checkpoints import CheckpointError
from population.config import PRECISIONS, ClusterConfig, ConfigError
from population.memory import check_crossplay_fits
from population.policy import CHECKPOINT_CHOICES

log = logging.getLogger(__name__)


def add_xp(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 xp`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "xp",
        help="cross-play matrix of a trained population, or across runs and policy files",
        description="With RUN_DIR: evaluate every ordered pair of the run's final policies (diagonal = self-play) "
        "and write RUN_DIR/xp/matrix.csv, episodes.csv, summary.json, heatmap.png (the run's lock is "
        "taken: a run that trains or is evaluated elsewhere is refused unless --wait). With "
        "--rows/--cols: every row policy with every column policy across runs (SP vs SA vs OP vs FCP), "
        "exported files or human-proxy:LAYOUT, in both seat orders (--seats 0: rows in seat 0 only), "
        "written to --out (matrix.csv, episodes.csv, blocks.csv, summary.json, heatmap.png, blocks.png; "
        "with both orders also *_cols_seat0 and *_mean files). Each finished job is kept in OUT.unfinished until "
        "the files are written: after a stop, the same command continues from there. Confidence intervals: "
        "bootstrap over seeds.",
    )
    parser.add_argument("run_dir", nargs="?", help="a run directory: its own cross-play (in-run form)")
    parser.add_argument(
        "--rows",
        nargs="+",
        metavar="SRC",
        help="row policy sources: run dir (all seeds), seed dir, checkpoint, exported file or human-proxy:LAYOUT",
    )
    parser.add_argument("--cols", nargs="+", metavar="SRC", help="column policy sources (default: the --rows)")
    parser.add_argument(
        "--checkpoint",
        help="which checkpoint of run/seed-dir sources: final (default), mid, init, latest or an update number",
    )
    parser.add_argument("--greedy", action="store_true", help="argmax actions instead of sampled ones")
    parser.add_argument(
        "--seats",
        choices=crossplay.SEATS,
        help="with --rows: both (default) plays every pair in both seat orders and reports each "
        "order and their mean; 0 plays the row policies in seat 0 only",
    )
    parser.add_argument(
        "--wait",
        action="store_true",
        help="with RUN_DIR: wait for the process that holds the run (training, another xp) instead of refusing",
    )
    parser.add_argument(
        "--episodes",
        type=positive_int,
        help="episodes per ordered pair (default: the config's eval.episodes; 500 with --rows)",
    )
    parser.add_argument(
        "--seed",
        type=seed,
        help="episode key stream (default: the first row run's population.seed, "
        "so a run against itself reproduces its in-run matrix; else 0)",
    )
    parser.add_argument(
        "--pool",
        action="store_true",
        help="with --rows only: also report every row source's policies as one population (SP = diagonal, "
        "XP = all other cells, bootstrap over all of them), e.g. two runs of one config with different "
        "population.seed; the sources must be runs of one method",
    )
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        help="with --rows: matmul precision the episodes are played at (default: the run.precision the sources "
        "trained with, as their in-run cross-play; a choice is required when they trained at different ones)",
    )
    parser.add_argument("--out", help="output directory for --rows (default runs/xp_<time>)")
    parser.add_argument(
        "--backend",
        choices=["ray", "local"],
        help="with --rows: ray (default) spreads the jobs over Ray workers; local plays them here",
    )
    parser.add_argument("--address", help="Ray cluster to join: auto or HOST:PORT (default: start Ray here)")
    parser.add_argument(
        "--workers", type=positive_int, help="Ray workers (default: one per available CPU, at most one per job)"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    return parser


def run_xp(args) -> int:
    """Cross-play one run (``RUN_DIR``) or rows against columns of sources (``--rows``/``--cols``).
    Returns ``EXIT_OK``; raises ``CLIError`` for a bad option, source or run directory."""
    if args.rows is None:
        if args.run_dir is None:
            raise CLIError("give RUN_DIR (its own cross-play) or --rows SRC ... [--cols SRC ...]")
        if args.cols:
            raise CLIError("--cols needs --rows")
        given = [
            flag
            for flag, value in (
                ("--checkpoint", args.checkpoint),
                ("--greedy", args.greedy or None),
                ("--seed", args.seed),
                ("--out", args.out),
                ("--backend", args.backend),
                ("--address", args.address),
                ("--workers", args.workers),
                ("--seats", args.seats),
                ("--pool", args.pool or None),
                ("--precision", args.precision),
            )
            if value is not None
        ]
        if given:
            raise CLIError(
                f"{', '.join(given)}: only with --rows (the in-run form evaluates RUN_DIR's final "
                "policies here and writes RUN_DIR/xp/; its matrix holds both seat orders)"
            )
        return _in_run(args)
    if args.run_dir is not None:
        raise CLIError(f"give either RUN_DIR ({args.run_dir}) or --rows, not both")
    if args.wait:
        raise CLIError("--wait: only with RUN_DIR (--rows reads checkpoints and takes no run's lock)")
    for flag, sources in (("--rows", args.rows), ("--cols", args.cols or [])):
        _refuse_repeats(flag, sources)
    return _cross_run(args)


def _refuse_repeats(flag: str, sources: list[str]) -> None:
    """A source given twice in one list would be its own partner under two labels: its self-play cell counted as
    cross-play (and the pooled matrix's diagonal blocks all NaN)."""
    seen: dict = {}
    for text in sources:
        key = text if ":" in text and not Path(text).exists() else resolved(text, flag)  # human-proxy:LAYOUT
        if key in seen:
            raise CLIError(f"{flag}: {text} is given twice (also as {seen[key]}); give each source once")
        seen[key] = text


def _in_run(args) -> int:
    try:
        run = RunDir.existing(args.run_dir)
        if args.episodes is not None:
            seeds = run.load_config().population.num_seeds
            check_crossplay_fits(seeds, seeds, args.episodes, "--episodes")
        # the lock keeps out the trainer and a second evaluation, which write the same files
        run.lock(wait=args.wait, advice="wait for it to finish or pass --wait")
        try:
            evaluate_run(args.run_dir, episodes=args.episodes)
        finally:
            run.close()
    except (RunDirError, CheckpointError, ArchiveError, ConfigError) as error:  # ArchiveError: archive.xp without mcap
        raise CLIError(str(error)) from None
    print(f"wrote {os.path.join(args.run_dir, 'xp')}/matrix.csv, episodes.csv, summary.json, heatmap.png")
    return EXIT_OK


def _cross_run(args) -> int:
    # Ray workers and the driver share the machine's accelerator: never let the driver take most of it.
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    backend = args.backend or "ray"
    if backend == "local" and (args.address or args.workers):
        raise CLIError("--address and --workers need --backend ray")
    checkpoint = checkpoint_choice(args.checkpoint or "final", CHECKPOINT_CHOICES)
    sources = [*args.rows, *(args.cols or [])]
    directories = [s for s in sources if not s.startswith(crossplay.HUMAN_PROXY) and Path(s).is_dir()]
    # A file is one fixed policy: --checkpoint would be ignored. A source that does not exist is left to
    # resolve_source, which names it (a mistyped run directory is not a reason to blame --checkpoint).
    everything_there = all(s.startswith(crossplay.HUMAN_PROXY) or Path(s).exists() for s in sources)
    if args.checkpoint is not None and not directories and everything_there:
        raise CLIError(
            f"--checkpoint {args.checkpoint}: picks the checkpoint of a run or seed directory, and no source is "
            f"one ({', '.join(dict.fromkeys(sources))}: each one fixed policy); leave it out"
        )
    out = args.out or os.path.join("runs", f"xp_{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}")
    check_new_folder("--out", out)
    try:
        # Ray first: loading the policies starts JAX, and Ray must fork before that (ray_backend.session)
        with ray_backend.session(backend, ClusterConfig(address=args.address)):
            try:
                rows = [crossplay.resolve_source(s, checkpoint) for s in args.rows]
                cols = rows if not args.cols else [crossplay.resolve_source(s, checkpoint) for s in args.cols]
                env_kwargs = crossplay.check_same_env([*rows, *cols])
            except crossplay.CrossPlayError as error:
                raise CLIError(str(error)) from None
            for flag, groups in (("--rows", rows), ("--cols", cols if args.cols else [])):
                try:  # by content: _refuse_repeats sees one policy under two paths as two sources
                    crossplay.refuse_repeated_policies(groups)
                except crossplay.CrossPlayError as error:
                    raise CLIError(f"{flag}: {error}") from None
            try:
                precision = crossplay.played_precision([*rows, *cols], args.precision)
            except crossplay.CrossPlayError as error:
                raise CLIError(f"{error}; choose one with --precision") from None
            if args.pool:
                _check_poolable(args, rows)
            episodes = args.episodes or 500
            seats = args.seats or "both"
            num_rows, num_cols = sum(len(g.names) for g in rows), sum(len(g.names) for g in cols)
            seatings = 2 if args.cols and seats == "both" else 1  # rows against themselves: one matrix holds both
            try:
                check_crossplay_fits(num_rows, num_cols, episodes, "--episodes", seats=seatings)
            except ConfigError as error:
                raise CLIError(str(error)) from None
            seed = args.seed if args.seed is not None else next((g.seed for g in rows if g.seed is not None), 0)
            jobs = num_rows * len(cols)
            settings = {"episodes": episodes, "seed": seed, "greedy": bool(args.greedy), "seats": seats,
                        "precision": precision, "env": env_kwargs}  # fmt: skip
            total = crossplay.seat_fair_job_count(rows, cols, seats)
            journal = _open_journal(out, xp_journal.request_of(rows, cols, settings, _device(backend)), total)
            continued = journal.count() if journal is not None else 0
            started = time.perf_counter()
            label = f"cross-play {sum(len(g.names) for g in rows)}x{sum(len(g.names) for g in cols)}"
            with (
                _kept_on_failure(journal, out, total),
                crossplay.players(backend, jobs, args.address, args.workers, precision) as workers,
                Bar(label, enabled=not args.quiet) as bar,
            ):
                result = crossplay.play_seat_fair(
                    rows, cols, workers, crossplay.xp_key(seed), episodes, args.greedy, bar, seats, journal
                )
    except RayBackendError as error:
        raise CLIError(str(error)) from None
    except JournalMismatch as error:  # a kept job that does not read: said before anything is played over it
        raise CLIError(f"--out {out}: {error}") from None
    with _kept_on_failure(journal, out, total):  # a failure from here on (a full disk) keeps what was played too
        summary = crossplay.summarize_seat_fair(result)
        if args.pool:
            crossplay.add_pooled(summary, result)
        summary.update(
            {
                "rows": list(args.rows),
                "cols": list(args.cols or args.rows),
                "checkpoint": str(checkpoint) if directories else None,  # it picks nothing from a file
                "updates": {g.label: list(g.updates) for g in [*rows, *cols] if any(u is not None for u in g.updates)},
                "files": _file_records([*rows, *cols]),
                "greedy": bool(args.greedy),
                "seed": seed,
                "precision": precision,
                "env": env_kwargs,
                "backend": backend,
                "wall_s": round(time.perf_counter() - started, 2),  # of this command: after a stop, the rest only
                "jobs_continued": continued,  # of the jobs, played before a stop (kept in OUT.unfinished)
            }
        )
        # Whole or not at all: a rerun after a failure finds no half folder; summary.json, read as the result, moves
        # last.
        with staged_folder(out, ".xp", markers=["summary.json"]) as staging:
            crossplay.write_seat_fair_outputs(result, staging, summary, crossplay.policy_env(env_kwargs))
    if journal is not None:
        journal.remove()  # the results are in: nothing left to continue
    if not args.quiet:
        _print_blocks(summary)
    print(f"wrote {out}/: {', '.join(sorted(p.name for p in Path(out).iterdir()))}")
    return EXIT_OK


def _file_records(groups) -> dict:
    """Per policy-file source: the sha256 of the bytes played, the SHA256SUMS.json beside it (None where its folder
    has none) and whether that lists it (then with these bytes: checked), so a result can be traced to its files."""
    return {
        g.label: {
            "sha256": g.file.sha256,
            "listing": None if g.file.listing is None else str(g.file.listing),
            "listed": g.file.listed,
        }
        for g in dict.fromkeys(groups)  # the rows are the columns when --cols is left out
        if g.file is not None
    }


def _device(backend: str) -> str:
    """What plays the jobs: Ray's workers play on CPUs (``crossplay.players``), the local backend on what JAX found."""
    return "cpu" if backend == "ray" else describe_devices()


def _open_journal(out: str, request: dict, total: int) -> XPJournal | None:
    """The jobs kept for this cross-play (``cluster.runtime.xp_journal``) of ``total``: new, or those of a stopped
    run of the same ``request``, which are then not played again (said). None, with a warning, where --out is an
    empty folder this process may write into but no folder may be made beside it (an empty mount point): the command
    still runs, but a stop loses what it played. Any other failure to write (a full disk, a read-only file system) is
    the command's error now, not after the whole matrix was played only to fail at its own write."""
    try:
        journal = XPJournal.open(out, request)
    except JournalMismatch as error:
        raise CLIError(f"--out {out}: {error}") from None
    except PermissionError as error:
        if not (os.path.isdir(out) and os.access(out, os.W_OK)):
            raise
        log.warning("cannot keep the jobs beside --out (%s): a stop will lose those played", error)
        return None
    if kept := journal.count():
        log.warning(
            "continuing a stopped cross-play: %d of its %d jobs were played before (%s)", kept, total, journal.folder
        )
    return journal


@contextlib.contextmanager
def _kept_on_failure(journal: XPJournal | None, out: str, total: int):
    """On any failure or stop in the block: say where the jobs played so far are kept and how to continue, or leave
    nothing behind if none were."""
    try:
        yield
    except JournalMismatch:
        raise  # the kept jobs are what is wrong, and its message says what to do with them
    except BaseException:
        if journal is not None:
            if kept := journal.count():
                log.warning(
                    "%d of the %d jobs are played and kept in %s: the same command with --out %s continues from there",
                    kept, total, journal.folder, out,
                )  # fmt: skip
            else:
                journal.remove()
        raise


def _check_poolable(args, rows) -> None:
    """--pool: one population means the rows are the columns and every source is a run of one method."""
    if args.cols:
        raise CLIError("--pool: pools the --rows sources against themselves; leave out --cols")
    methods = {g.label: g.method for g in rows}
    unknown = [label for label, method in methods.items() if method is None]
    if unknown:
        raise CLIError(f"--pool: {', '.join(unknown)}: not a run or seed directory (no method to pool by)")
    if len(set(methods.values())) > 1:
        listed = ", ".join(f"{label} ({method})" for label, method in methods.items())
        raise CLIError(f"--pool: the sources are runs of different methods: {listed}; pool runs of one method")


def _print_blocks(summary: dict) -> None:
    both = summary["seats"] == "both"
    for index, block in enumerate(summary["blocks"]):
        if block["xp_mean"] != block["xp_mean"]:  # a policy with itself only: self-play, no cross-play to report
            print(f"{block['rows']} x {block['cols']}: SP {block['sp_mean']:.1f} (self-play only)")
            continue
        low, high = block["xp_ci95_interval"]
        line = f"{block['rows']} x {block['cols']}: XP {block['xp_mean']:.1f} [{low:.1f}, {high:.1f}]"
        if both:
            first, second = (summary["orders"][order][index]["xp_mean"] for order in ("rows_seat0", "cols_seat0"))
            line += f" (mean of rows in seat 0: {first:.1f}, cols in seat 0: {second:.1f})"
        if block["sp_mean"] == block["sp_mean"]:
            line += f", SP {block['sp_mean']:.1f}, gap {block['gap']:.1f} +- {block['gap_std']:.1f}"
        print(line)
    if "pooled" in summary:
        block = summary["pooled"]
        sp, xp, gap = (block[f"{k}_ci95_interval"] for k in ("sp", "xp", "gap"))
        print(
            f"pooled ({block['num_rows']} policies of {len(block['sources'])} sources): "
            f"SP {block['sp_mean']:.1f} [{sp[0]:.1f}, {sp[1]:.1f}], XP {block['xp_mean']:.1f} "
            f"[{xp[0]:.1f}, {xp[1]:.1f}], gap {block['gap']:.1f} [{gap[0]:.1f}, {gap[1]:.1f}]"
        )
