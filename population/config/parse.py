"""YAML -> ``Config``: the sections parsed and checked, every problem collected, each naming its key and
where it came from (the file, or the ``--set`` override).

    config = load_config("configs/quickstart.yaml", overrides=["ppo.total_timesteps=1e5"])
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Collection, Mapping, Sequence
from typing import Any

from ocv2.config import EnvConfig, build_config
from population.config.errors import SET_PREFIX, ConfigError
from population.config.fields import bounded_int, finite_float32, integral, nearest, parse_section
from population.config.paper import paper_sp_ppo
from population.config.schema import (
    MODEL_DEFAULTS,
    SECTIONS,
    ArchiveConfig,
    ClusterConfig,
    Config,
    EvalConfig,
    FCPConfig,
    ModelConfig,
    OPConfig,
    PopulationConfig,
    PPOConfig,
    RunConfig,
    SAConfig,
)
from population.config.validate import ppo_problems, validate
from population.config.yaml_io import apply_overrides, check_plain_data, read_yaml


def load_config(path: str | os.PathLike, overrides: Sequence[str] = ()) -> Config:
    """Read a YAML file, apply ``section.key=value`` overrides, validate. Errors name file and key."""
    path = os.fspath(path)
    raw = read_config_file(path)
    try:
        return parse_config(raw, overrides)
    except ConfigError as error:
        raise error.prefixed(path) from None


def read_config_file(path: str | os.PathLike):
    """A config file's YAML, refused by name when it is empty or only comments: a truncated or mistaken file, not
    a wish for the all-defaults run (about 300M env steps), which ``{}`` asks for."""
    raw = read_yaml(path)
    if raw is None:
        raise ConfigError(
            f"{os.fspath(path)}: empty (only comments or nothing); write {{}} for a config of every default"
        )
    return raw


def load_run_config(run_dir: str | os.PathLike) -> Config:
    """A run directory's ``config.yaml``. ocv2 writes every key there, so an empty file is damage, not the
    all-defaults config an empty YAML file means elsewhere: refused by name rather than read as another run."""
    path = os.path.join(os.fspath(run_dir), "config.yaml")
    raw = read_yaml(path)
    if raw is None:
        raise ConfigError(f"{path}: empty (damaged): a run's config.yaml holds every key of the run's config")
    try:
        return parse_config(raw)
    except ConfigError as error:
        raise error.prefixed(path) from None


def parse_config(raw: Mapping, overrides: Sequence[str] = ()) -> Config:
    """Validate a nested mapping (e.g. from YAML) into a ``Config``; a ConfigError lists every problem."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"the config must be a mapping of sections {SECTIONS}, got {type(raw).__name__}")
    check_plain_data(raw)
    if is_ray_launcher_config(raw):
        raise ConfigError("a Ray cluster launcher config (for 'ray up'), not an ocv2 experiment config")
    mixed = mixed_file_problem(raw)
    if mixed is not None:
        raise ConfigError(mixed)
    if is_study_data(raw):
        raise ConfigError(
            "a study file (it names a study or lists runs), not an experiment config: run it with `ocv2 study run "
            "FILE`; `ocv2 validate FILE` checks it"
        )
    original, raw = raw, apply_overrides(raw, overrides)
    problems = [
        f"{name}: unknown section{nearest(name, SECTIONS)} (sections: {', '.join(SECTIONS)})"
        for name in sorted(set(raw) - set(SECTIONS), key=str)
    ]

    def parsed(parse, *args, default):
        try:
            return parse(*args)
        except ConfigError as error:
            problems.extend(error.problems)
            return default if error.partial is None else error.partial

    # A section left empty (``env:``) is its defaults; any other non-mapping (``env: false``) is refused by name.
    env_raw = raw.get("env")
    env = parsed(_parse_env, {} if env_raw is None else env_raw, default=Config().env)
    model = _resolve_model(
        parsed(parse_section, "model", ModelConfig, raw.get("model"), default=ModelConfig()), problems
    )
    ppo = parsed(parse_section, "ppo", PPOConfig, raw.get("ppo"), default=PPOConfig())
    pop_raw = {} if raw.get("population") is None else raw["population"]
    if not isinstance(pop_raw, Mapping):
        problems.append(f"population: expected a mapping of keys, got {type(pop_raw).__name__}")
        pop_raw = {}
    pop_raw = dict(pop_raw)
    fcp_raw = pop_raw.pop("fcp", None)
    if fcp_raw is not None and not isinstance(fcp_raw, Mapping):
        problems.append(f"population.fcp: expected a mapping of keys, got {type(fcp_raw).__name__}")
        fcp_raw = None
    fcp_raw = dict(fcp_raw or {})
    partner_raw = fcp_raw.pop("partner_ppo", None)
    subs = {
        name: parsed(parse_section, f"population.{name}", cls, pop_raw.pop(name, None), default=cls())
        for name, cls in (("sa", SAConfig), ("op", OPConfig))
    }
    subs["fcp"] = parsed(parse_section, "population.fcp", FCPConfig, fcp_raw, default=FCPConfig())
    population = dataclasses.replace(
        parsed(parse_section, "population", PopulationConfig, pop_raw, default=PopulationConfig()), **subs
    )
    partner_ppo = parsed(_partner_ppo, partner_raw, env, model, population, ppo, default=None)
    population = dataclasses.replace(population, fcp=dataclasses.replace(population.fcp, partner_ppo=partner_ppo))
    config = Config(
        env=env,
        model=model,
        ppo=ppo,
        population=population,
        eval=parsed(_parse_eval, raw.get("eval"), default=EvalConfig()),
        run=parsed(parse_section, "run", RunConfig, raw.get("run"), default=RunConfig()),
        archive=parsed(parse_section, "archive", ArchiveConfig, raw.get("archive"), default=ArchiveConfig()),
        cluster=parsed(_parse_cluster, raw.get("cluster"), default=ClusterConfig()),
    )
    # Values are checked with every key that did not parse at its default; a key already reported is
    # not reported again, nor is a check across keys that names one of them (its numbers came from the
    # default: "num_envs: four" would add "total_timesteps ... (num_envs x num_steps = 65536)").
    reported = {problem.split(":", 1)[0] for problem in problems}
    problems += [p for p in validate(config) if not _about_reported(p, reported)]
    if problems:
        raise ConfigError(blame_overrides(problems, overrides, _own_problems(original) if overrides else None))
    return config


def _own_problems(raw: Mapping) -> set[str]:
    """The problems of the config without its overrides: those the file has itself (an override did not cause)."""
    try:
        parse_config(raw)
    except ConfigError as error:
        return set(error.problems)
    return set()


def _about_reported(problem: str, reported: set[str]) -> bool:
    """Whether ``problem`` is about a key in ``reported``: the same key, or one of its section's checks that
    names the key's last part ("num_envs" for ppo.num_envs) as a word."""
    key = problem.split(":", 1)[0]
    if key in reported:
        return True
    section = key.split(".", 1)[0]
    return any(
        name.split(".", 1)[0] == section and re.search(rf"\b{re.escape(name.rsplit('.', 1)[-1])}\b", problem)
        for name in reported
        if "." in name
    )


def blame_overrides(problems: Sequence[str], overrides: Sequence[str], own: Collection[str] | None = None) -> list[str]:
    """Each problem at, inside or just above a key an override set, named after that override (``--set
    ppo.lr=1e308: ppo.lr: ...``): the file did not cause it. Given ``own``, the problems of the file alone, so is a
    problem not among them that a check across keys of the override's section raised, naming it (``num_envs x
    num_steps``)."""
    dotted = [(item.split("=", 1)[0].strip(), item) for item in overrides]
    blamed = []
    for problem in problems:
        key = problem.split(":", 1)[0]
        hits = [
            item
            for name, item in dotted
            if name == key
            or key.startswith((f"{name}.", f"{name}["))
            or name.startswith(f"{key}.")
            or (own is not None and problem not in own and _about_reported(problem, {name}))
        ]
        blamed.append(f"{SET_PREFIX}{hits[-1]}: {problem}" if hits else problem)
    return blamed


#: Keys every Ray cluster launcher YAML has (``ray up``); configs/cluster/ holds one beside ocv2 configs.
RAY_LAUNCHER_KEYS = frozenset({"cluster_name", "provider"})


def is_ray_launcher_config(raw) -> bool:
    return isinstance(raw, Mapping) and RAY_LAUNCHER_KEYS <= set(raw) and not set(raw) & set(SECTIONS[:-1])


#: Sections of an experiment config whose presence marks a file as one (the sections ``SECTIONS`` lists, but ``run``,
#: which a study file's typo of ``runs`` could be).
CONFIG_MARKS = ("env", "ppo", "model", "population")


def mixed_file_problem(raw) -> str | None:
    """What is wrong with a file that has both a study file's keys (``study``, a list of ``runs``) and an experiment
    config's sections: ``ocv2 train`` called it a study file and ``ocv2 study run`` a config, each sending the user to
    the other. None for any other file."""
    if not is_study_data(raw):
        return None
    marks = [key for key in CONFIG_MARKS if key in raw]
    if not marks:
        return None
    study_keys = [key for key in ("study", "runs") if key in raw]
    return (
        f"holds a study file's {' and '.join(study_keys)} and an experiment config's {', '.join(marks)}: a file is one "
        "or the other; put the sections in a config that a study run names (runs[i].config), or its overrides in "
        "the study's set"
    )


def is_study_data(raw) -> bool:
    """A study file's data (``ocv2 study run``), not an experiment config: it names its study or lists its runs (a
    config's misspelled ``runs:`` for ``run:`` is a mapping, and stays a config's unknown section)."""
    return isinstance(raw, Mapping) and ("study" in raw or isinstance(raw.get("runs"), list))


def _parse_env(raw) -> tuple[tuple[str, Any], ...]:
    if not isinstance(raw, Mapping):
        raise ConfigError(f"env: expected a mapping of ocv2.make parameters, got {type(raw).__name__}")
    if "initial_state_buffer" in raw:
        raise ConfigError("env.initial_state_buffer: state buffers come from population.method=sa, not the config")
    names = [f.name for f in dataclasses.fields(EnvConfig)]
    problems = [
        f"env.{key}: unknown parameter{nearest(key, names, 'env')} (valid parameters: {', '.join(names)})"
        for key in raw
        if key not in names
    ]
    # Integral numbers count as integers where the parameter is one, as in the other sections: 1000.0, and
    # 1e3, which YAML reads as a string (it needs a dot to read a float).
    params = {k: _env_integer(v) if k in ENV_INTEGERS else v for k, v in raw.items() if k in names}
    params.setdefault("layout", "cramped_room")
    problems += [problem for key, value in params.items() for problem in _number_problems(f"env.{key}", value)]
    if problems:
        raise ConfigError(problems)
    try:
        build_config(**params)
    except (TypeError, ValueError) as error:
        # build_config's messages name the parameter first ("max_steps must be ...", "unknown layout ..."): name
        # the key as every other section does
        found = [(m.start(), n) for n in names for m in [re.search(rf"\b{n}\b", str(error))] if m]
        named = min(found)[1] if found else None
        raise ConfigError(f"env.{named}: {error}" if named else f"env: {error}") from None
    frozen = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in params.items()))
    return frozen


#: env parameters that are integers (or lists of them), to take in any integral form
ENV_INTEGERS = ("max_steps", "agent_view_size", "op_ingredient_permutations")


def _env_integer(value):
    """``value`` as an int when it is integral in any YAML form (``fields.integral``), elementwise in a list;
    anything else unchanged, for build_config to judge."""
    if isinstance(value, list):
        return [_env_integer(v) for v in value]
    number = integral(value)
    return value if number is None else number


def _number_problems(key: str, value) -> list[str]:
    """Integers must fit int32 and floats float32 (every env parameter ends up in a JAX array)."""
    if isinstance(value, (list, tuple)):
        return [p for i, v in enumerate(value) for p in _number_problems(f"{key}[{i}]", v)]
    try:
        if isinstance(value, int) and not isinstance(value, bool):
            bounded_int(key, value)
        elif isinstance(value, float):
            finite_float32(key, value)
    except ConfigError as error:
        return error.problems
    return []


def _parse_eval(raw) -> EvalConfig:
    if isinstance(raw, Mapping) and "archive_episodes" in raw:
        raise ConfigError(
            "eval.archive_episodes: replaced by archive.xp (default true), which archives every "
            "scored cross-play episode to archive/xp/"
        )
    return parse_section("eval", EvalConfig, raw)


def _parse_cluster(raw) -> ClusterConfig:
    if isinstance(raw, Mapping) and "checkpoint_every" in raw:
        raise ConfigError(
            "cluster.checkpoint_every: checkpoints are set by run.checkpoint_every, which both "
            "backends use (it is also the chunk between coordinator steps)"
        )
    return parse_section("cluster", ClusterConfig, raw)


def _resolve_model(model: ModelConfig, problems: list[str]) -> ModelConfig:
    if model.kind not in MODEL_DEFAULTS:
        problems.append(f"model.kind: expected one of {', '.join(MODEL_DEFAULTS)}, got {model.kind!r}")
        model = dataclasses.replace(model, kind=ModelConfig.kind)
    fill = {k: v for k, v in MODEL_DEFAULTS[model.kind].items() if getattr(model, k) is None}
    return dataclasses.replace(model, **fill)


def _partner_ppo(raw, env, model: ModelConfig, population: PopulationConfig, ppo: PPOConfig) -> PPOConfig | None:
    """The FCP partner stage's ppo section: ``raw`` keys over the paper's self-play section for this layout, with
    the learner's ``activation`` unless ``raw`` names one: the learner plays the partners with its own network,
    activation included, so partners trained with another would be played as a function they never were."""
    key = "population.fcp.partner_ppo"
    if raw is not None and not isinstance(raw, Mapping):
        raise ConfigError(f"{key}: expected a mapping of ppo keys, got {type(raw).__name__}")
    if not population.trains_partners:
        # Not used (another method, or partners from a finished SP run), but kept as given: it has always been in
        # such runs' config.yaml and fingerprint (a partner stage's own config holds it), so dropping it now would
        # orphan their checkpoints. Checked like a used one, so that a bad value is not carried along unseen.
        if raw is None:
            return None
        partner = parse_section(key, PPOConfig, raw)
        problems = ppo_problems(key, partner)
        if problems:
            raise ConfigError(problems)
        return partner
    layout = dict(env)["layout"]
    base = paper_sp_ppo(layout, model.kind)
    if base is None and raw is None:
        raise ConfigError(
            f"{key}: no paper self-play config for layout {layout!r} with model.kind={model.kind} "
            "to take the partner stage's hyperparameters from; set it (a ppo mapping)"
        )
    values = dataclasses.asdict(base) if base is not None else {}
    values["activation"] = ppo.activation
    values.update(raw or {})
    return parse_section(key, PPOConfig, values)
