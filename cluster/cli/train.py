"""``ocv2 train``: train a population (``ocv2 xp`` lives in ``cluster.cli.xp``).

ocv2 train CONFIG [--set section.key=value ...] [--out RUN_DIR] [--backend ray|local] [--address A] [--resume]
          [--extend] [--logger NAME]   (NAME: one of cluster.runtime.loggers.LOGGERS; repeatable)
"""

from __future__ import annotations

import argparse
import datetime as _dt
import logging
import os
import shlex
from pathlib import Path

from cluster.api import require_backend, train_population
from cluster.archive import ArchiveError
from cluster.cli.args import add_set_option
from cluster.cli.errors import EXIT_OK, CLIError
from cluster.runtime import ray_backend
from cluster.runtime.extend import extend_run
from cluster.runtime.loggers import LOGGERS, MissingExtraError, check_loggers, logger_help
from cluster.runtime.ray_backend import RayBackendError
from cluster.runtime.rundir import RunDirError
from population.checkpoints import CheckpointError
from population.config import ConfigError, load_config
from population.memory import check_fits
from population.numerics import enable_deterministic_ops

log = logging.getLogger(__name__)


def add_train(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 train`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "train",
        help="train a population from a YAML config",
        description="Train a population (SP, SA, OP or FCP) from a YAML config, then "
        "evaluate cross-play and write plots and GIFs into the run directory.",
    )
    parser.add_argument("config", help="YAML config (see configs/)")
    add_set_option(
        parser,
        "override a config value (repeatable), e.g. --set ppo.total_timesteps=1e6",
    )
    parser.add_argument("--out", help="run directory (default runs/<layout>_<method>_<time>)")
    parser.add_argument(
        "--backend",
        choices=["ray", "local"],
        default="ray",
        help="ray (default): one Ray actor per shard of seeds (cluster: section); "
        "local: one process, seeds vmapped in one jitted program, no Ray",
    )
    parser.add_argument(
        "--address",
        help="Ray cluster to join: auto or HOST:PORT (default: cluster.address, else start Ray on this machine)",
    )
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoints")
    parser.add_argument(
        "--extend",
        action="store_true",
        help="with --resume: train a truncated run on to this config's later ppo.total_timesteps (the same "
        "schedule, so the same numbers as training there at once; docs/studies.md, Extending a study)",
    )
    parser.add_argument(
        "--logger",
        dest="loggers",
        action="append",
        default=[],
        choices=LOGGERS,
        help=logger_help(),
    )
    parser.add_argument("--no-eval", action="store_true", help="skip cross-play, plots and GIFs after training")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    return parser


def resume_advice(args, out: str) -> str:
    """What to do after a full disk or read-only folder stopped ``ocv2 train``: continue the run it had started, with
    the overrides, backend and loggers it was started with, or, if it had not started, run it again."""
    command = ["ocv2", "train", args.config, "--out", out]
    command += [part for override in args.overrides for part in ("--set", override)]
    command += ["--backend", args.backend] if args.backend != "ray" else []  # ray: the default
    command += ["--address", args.address] if args.address else []
    command += [part for logger in args.loggers for part in ("--logger", logger)]
    if not (Path(out) / "manifest.json").is_file():
        return f"nothing was trained; fix the cause (e.g. a read-only folder) and run `{shlex.join(command)}` again"
    return (
        f"{out} keeps its last complete checkpoint and metrics; fix the cause (e.g. free disk space) and "
        f"continue with `{shlex.join([*command, '--resume'])}`"
    )


def run_train(args) -> int:
    """Train (or resume) the population ``args.config`` describes into its run directory. Returns
    ``EXIT_OK``; raises ``CLIError`` for a bad config, run directory, backend or logger."""
    # The driver runs JAX too (SA buffer merge, GIFs): on a GPU machine it must not take 75 % of the
    # memory the seed actors need. Set before JAX initialises; an explicit user setting wins.
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    try:
        config = load_config(args.config, args.overrides)
    except ConfigError as error:
        raise CLIError(str(error)) from None
    if args.address:
        if args.backend != "ray":
            raise CLIError("--address needs --backend ray")
        try:
            config = load_config(args.config, [*args.overrides, f"cluster.address={args.address}"])
        except ConfigError as error:
            message = str(error).replace(f"--set cluster.address={args.address}: ", "")  # given as --address
            raise CLIError(message.replace("cluster.address", "--address")) from None
    try:  # before the run directory exists: a run that cannot fit this machine leaves nothing behind
        place = "local" if args.backend == "local" else "ray" if config.cluster.address is None else "cluster"
        check_fits(config, place)
    except ConfigError as error:
        raise CLIError(str(error)) from None
    out = args.out or _default_run_dir(config)
    if args.resume and not args.out:
        raise CLIError("--resume needs --out RUN_DIR (the run to continue)")
    if args.extend and not args.resume:
        raise CLIError("--extend needs --resume --out RUN_DIR (the truncated run to train on)")
    try:  # missing extras are reported before the run directory is touched
        require_backend(args.backend)
        check_loggers(args.loggers)
    except MissingExtraError as error:
        raise CLIError(str(error)) from None
    # A full disk or a read-only folder while training: one line from cluster.cli.main (every write is atomic),
    # whose advice depends on whether the run had started when it happened.
    args.os_error_advice = lambda: resume_advice(args, out)
    if config.run.deterministic:  # XLA reads XLA_FLAGS once, when JAX starts: before anything runs JAX here
        applied, message = enable_deterministic_ops()
        log.log(logging.DEBUG if applied else logging.INFO, message)
    try:
        if args.extend and (record := extend_run(out, config)) is not None:
            log.info("%s: extended from update %d to %d", out, record["from_updates"], record["to_updates"])
        with ray_backend.session(args.backend, config.cluster):  # Ray before JAX starts here (its docstring)
            summary = train_population(
                config,
                out,
                backend=args.backend,
                resume=args.resume,
                show_progress=not args.quiet,
                evaluate=not args.no_eval,
                loggers=args.loggers,
            )
    except (RunDirError, CheckpointError, ArchiveError, RayBackendError, MissingExtraError) as error:
        raise CLIError(str(error)) from None
    print(f"run directory: {summary['run_dir']}")
    return EXIT_OK


def _default_run_dir(config) -> str:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return os.path.join("runs", f"{config.env_kwargs['layout']}_{config.population.method}_{stamp}")
