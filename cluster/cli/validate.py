"""``ocv2 validate``: check configs before a run, running nothing.

    ocv2 validate CONFIG [CONFIG ...] [--set section.key=value ...]

Parses every config as ``ocv2 train`` would (same overrides): one OK line per file with what it would
train and the memory it needs here, or the file and key at fault; every file is checked, and any bad
one makes the exit code 1. A study file (``configs/studies/``) is checked as ``ocv2 study run`` reads it at
``--budget 1``: every run's config with the study's overrides, and every comparison; one OK line per run.
"""

from __future__ import annotations

import argparse
import sys

from cluster.archive import ArchiveError
from cluster.cli.args import add_set_option
from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from cluster.runtime.coordinator import check_inputs
from cluster.runtime.rundir import RunDirError
from cluster.study.runner import check_comparisons, check_partners_from
from cluster.study.spec import StudyError, default_out, load_study, run_config, with_overrides
from population.config import ConfigError, is_ray_launcher_config, is_study_data, parse_config, read_config_file
from population.config.parse import blame_overrides
from population.memory import check_fits, estimate


def add_validate(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 validate`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "validate",
        help="check YAML configs without running anything",
        description="Parse and validate each config exactly as 'ocv2 train' would (with the "
        "same --set overrides) and print what it would train. Exit 1 if any "
        "config is invalid (every file is checked).",
    )
    parser.add_argument(
        "configs",
        nargs="+",
        metavar="CONFIG",
        help="YAML config(s), e.g. configs/paper/*.yaml, or study files (configs/studies/*.yaml)",
    )
    add_set_option(
        parser,
        "override a config value in every file (repeatable)",
    )
    return parser


def describe_config(config) -> str:
    """One line: method, layout, seeds, updates and env steps per seed (plus SA / FCP specifics)."""
    ppo, pop = config.ppo, config.population
    steps = ppo.num_updates * ppo.steps_per_update
    view = config.env_kwargs.get("agent_view_size")
    text = (
        f"{pop.method} on {config.env_kwargs['layout']} ({'full view' if view is None else f'view {view}'}, "
        f"{config.model.kind}), {pop.num_seeds} seeds x {ppo.num_updates} updates x {ppo.steps_per_update:,} "
        f"= {steps:,} env steps per seed"
    )
    if pop.method == "sa":
        text += f"; {pop.sa.iterations} SA iterations"
    if pop.method == "fcp":
        fcp = pop.fcp
        pool = (
            f"{fcp.partner_seeds} partner seeds x {list(fcp.checkpoints)} {'per learner' if fcp.per_seed else 'shared'}"
        )
        text += (
            f"; pool {pool} from {fcp.partners}"
            if fcp.partners
            else f"; first an SP partner stage of {fcp.stage_seeds(pop.num_seeds)} seeds x "
            f"{fcp.partner_ppo.num_updates} updates, pool {pool}"
        )
    return text


def check_study_file(path: str, overrides) -> tuple[str, object]:
    """("ok", {run name: Config}) for a study file as ``ocv2 study run`` reads it at budget 1 (each run's config
    with the study's and ``overrides``' settings, each fitting this machine, every comparison playable), or
    ("fail", [the problem])."""
    try:
        study = with_overrides(load_study(path), list(overrides))
        out = default_out(study)  # where FCP partners would be: only their path enters a config
        configs = {run.name: run_config(study, run, out, 1.0, None) for run in study.runs}
        for name, config in configs.items():
            try:
                check_fits(config, "cluster")
            except ConfigError as error:
                raise StudyError(f"{study.origin}: run {name!r}: {error}") from None
        check_comparisons(study, configs)
        check_partners_from(study, configs, out)
    except StudyError as error:
        return "fail", [str(error)]
    return "ok", configs


def check_config_file(path: str, overrides) -> tuple[str, object]:
    """("ok", Config), ("study", {run: Config}) for a study file, ("skip", reason) for a Ray launcher YAML, or
    ("fail", [every problem])."""
    try:
        raw = read_config_file(path)
        if is_ray_launcher_config(raw):
            return "skip", "a Ray cluster launcher config (for 'ray up'), not an ocv2 experiment config"
        if is_study_data(raw):  # with one of study:/runs: misspelled still a study, its error naming the key
            status, result = check_study_file(path, overrides)
            return ("study" if status == "ok" else status), result
        config = parse_config(raw, overrides)
        # What a run needs on this machine at the least (training on a cluster, this machine the
        # driver) must fit; what it needs when it trains here is shown.
        check_fits(config, "cluster")
    except ConfigError as error:
        problems = (
            error.problems if all(p.startswith(f"{path}:") for p in error.problems) else error.prefixed(path).problems
        )
        return "fail", problems
    try:  # what the run reads besides its config: what train checks before it makes a run directory
        check_inputs(config)
    except (RunDirError, ArchiveError) as error:  # named after the --set that gave the key, or else the file
        (problem,) = blame_overrides([str(error)], overrides)
        return "fail", [problem if problem != str(error) else f"{path}: {error}"]
    return "ok", config


def run_validate(args) -> int:
    """Check every config of ``args.configs`` with ``args.overrides``, printing one line per file (OK with
    what it trains, SKIP for a Ray launcher config, FAIL with each problem). Returns ``EXIT_OK``; raises
    ``CLIError`` (exit 1) naming the invalid files when any is."""
    bad = []
    for path in args.configs:
        status, result = check_config_file(path, args.overrides)
        if status == "skip":
            print(f"SKIP {path}: {result}")
        elif status == "study":
            for name, config in result.items():
                print(f"OK   {path}: run {name!r}: {describe_config(config)} (at --budget 1)")
        elif status == "fail":
            for problem in result:
                print(f"FAIL {problem}", file=sys.stderr)
            bad.append(path)
        else:
            print(f"OK   {path}: {describe_config(result)}; memory here {estimate(result, 'local').describe()}")
    if bad:
        raise CLIError(f"{len(bad)} of {len(args.configs)} config(s) invalid: {', '.join(bad)}", EXIT_FAILURE)
    return EXIT_OK
