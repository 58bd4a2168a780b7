"""Experiment configuration: YAML parsed once into frozen, typed, validated dataclasses.

Sections: ``env`` (the ``ocv2.make`` parameters), ``model``, ``ppo`` (the paper's hyperparameter names in
lower case), ``population`` (method and per-method settings), ``eval``, ``run``, ``archive`` (what goes
into the MCAP trajectory archive) and ``cluster`` (Ray resources; ignored by the local backend). Every error names
the offending key (``ppo.num_minibatches``) and, when loaded from a file, the file.

    config = load_config("configs/quickstart.yaml", overrides=["ppo.total_timesteps=1e5"])
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import types
import typing
from typing import Any, Mapping, Sequence

import yaml

from ocv2.atomic import atomic_write
from ocv2.config import build_config

#: JAX's default PRNG keys are built from 32-bit seeds: a larger seed would silently wrap around.
MAX_SEED = 2**32 - 1
#: The SP stage of an FCP run without partners trains with ``population.seed + FCP_STAGE_SEED_OFFSET``.
FCP_STAGE_SEED_OFFSET = 7919
#: YAML nodes a config may expand to (aliases included): a config is a few hundred; this stops alias bombs.
MAX_YAML_NODES = 100_000


class ConfigError(ValueError):
    """Configuration problems; the message names the key (and file) at fault.

    ``problems`` lists every problem found (``ocv2 validate`` prints them all); the message is the first
    one, followed by how many more there are.
    """

    def __init__(self, message: str | Sequence[str], partial: Any = None):
        self.problems = [message] if isinstance(message, str) else list(message)
        self.partial = partial  # what could be parsed (bad keys at their defaults), to check the rest against
        first = self.problems[0]
        more = len(self.problems) - 1
        super().__init__(first if not more else f"{first} (and {more} more problem{'s' * (more > 1)}; "
                                                 "ocv2 validate lists them all)")

    def prefixed(self, prefix: str) -> "ConfigError":
        """The same problems with ``prefix`` (e.g. the file) in front of each."""
        return ConfigError([f"{prefix}: {problem}" for problem in self.problems])


# ---------------------------------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Network. ``cnn``: the classic-layout CNN; ``rnn``: 1x1-conv mixer + CNN + GRU (paper appendix B)."""

    kind: str = "rnn"
    # cnn: conv features / kernel sizes / dense width (Conv 5x5/32, 3x3/32, 3x3/32 -> Dense 64)
    # rnn: 1x1 mixer (128,128,8) -> 3x3 convs (16,32,32) -> Dense 128 -> GRU 128
    conv_features: tuple[int, ...] | None = None
    conv_kernels: tuple[int, ...] | None = None
    mixer_features: tuple[int, ...] = (128, 128, 8)
    fc_dim: int | None = None
    gru_dim: int = 128
    # how convolutions and the GRU are computed (same function and parameters either way): "cpu" the
    # matmul forms and hand-written GRU backward tuned for XLA:CPU, "xla" XLA's own convolution op and
    # autodiff (cuDNN on GPU), "auto" the first on a CPU backend, the second elsewhere
    kernels: str = "auto"

    @property
    def recurrent(self) -> bool:
        return self.kind == "rnn"


_MODEL_DEFAULTS = {
    "cnn": {"conv_features": (32, 32, 32), "conv_kernels": (5, 3, 3), "fc_dim": 64},
    "rnn": {"conv_features": (16, 32, 32), "conv_kernels": (3, 3, 3), "fc_dim": 128},
}


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters (paper appendix D names). Defaults: the paper's RNN self-play column."""

    lr: float = 2.5e-4
    anneal_lr: bool = True
    lr_warmup: float = 0.05  # fraction of all optimizer steps spent warming up from 0 to lr
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    gamma: float = 0.99
    gae_lambda: float = 0.95
    max_grad_norm: float = 0.25
    num_envs: int = 256
    num_steps: int = 256
    num_minibatches: int = 64
    update_epochs: int = 4
    total_timesteps: int = 30_000_000
    rew_shaping_horizon: int = 15_000_000
    activation: str = "relu"
    # Reproduce the paper code's recurrent bug (post-step done used as the replay's reset flag).
    paper_done_bug: bool = False

    @property
    def steps_per_update(self) -> int:
        """Environment steps (transitions of whole kitchens) per PPO update."""
        return self.num_envs * self.num_steps

    @property
    def num_updates(self) -> int:
        return self.total_timesteps // self.steps_per_update


@dataclasses.dataclass(frozen=True)
class SAConfig:
    """State augmentation (paper Algorithm 1)."""

    iterations: int = 10
    rollouts_per_pair: int = 10
    keep_every: int = 10
    # MCAP archives (e.g. last month's cross-play, human play) whose every keep_every-th state joins
    # each iteration's buffer; paths are relative to where ocv2 train runs.
    archives: tuple[str, ...] = ()


@dataclasses.dataclass(frozen=True)
class OPConfig:
    """Other-play: ingredient indices each agent's view is permuted over, per episode."""

    ingredients: tuple[int, ...] = (0, 1)


@dataclasses.dataclass(frozen=True)
class FCPConfig:
    """Fictitious co-play: a learner per seed against a frozen pool of SP checkpoints.

    ``partners``: an SP run directory to take the pools from; None trains an SP stage first (same
    env/model sections, ``partner_ppo`` hyperparameters). ``partner_seeds``: SP seeds per pool.
    ``checkpoints``: which snapshots of each partner seed join the pool ("init", "mid", "final" or an
    update number). ``pool``: "shared" (every learner plays partner seeds [0, k)) or "per_seed" (the
    paper: learner i plays its own partner seeds [i*k, (i+1)*k), so the SP stage trains num_seeds x k
    seeds). ``partner_ppo``: the SP stage's ppo section; unset, the paper's self-play hyperparameters
    for this layout and model kind (``configs/paper``); keys given replace single values of that.
    """

    partners: str | None = None
    partner_seeds: int = 8
    checkpoints: tuple[str, ...] = ("mid", "final")
    pool: str = "shared"
    partner_ppo: PPOConfig | None = None

    @property
    def per_seed(self) -> bool:
        return self.pool == "per_seed"

    def pool_seeds(self, learner: int) -> range:
        """The partner-run seeds whose checkpoints make up learner ``learner``'s pool."""
        k = self.partner_seeds
        return range(learner * k, (learner + 1) * k) if self.per_seed else range(k)

    def stage_seeds(self, num_learners: int) -> int:
        """SP seeds the partner run needs for ``num_learners`` learners."""
        return self.partner_seeds * (num_learners if self.per_seed else 1)


FCP_POOLS = ("shared", "per_seed")
# The paper's configs; the partner stage's default ppo section is the self-play config's of the same
# layout and model kind (the paper trained FCP partners as ordinary self-play runs).
PAPER_CONFIGS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "configs", "paper")


@dataclasses.dataclass(frozen=True)
class PopulationConfig:
    method: str = "sp"
    num_seeds: int = 10
    seed: int = 0
    sa: SAConfig = SAConfig()
    op: OPConfig = OPConfig()
    fcp: FCPConfig = FCPConfig()


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Cross-play evaluation: E episodes per ordered pair, stochastic actions, team sparse return."""

    episodes: int = 500
    gifs: int = 2  # episode GIFs of the first seeds' self-play written after training


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """How a run is driven: chunking, checkpoints."""

    checkpoint_every: int = 50  # updates between atomic TrainState checkpoints (also the chunk size)
    num_checkpoints: int = 3  # kept snapshots spread over training (0, mid, final), as the paper


@dataclasses.dataclass(frozen=True)
class ArchiveConfig:
    """The MCAP trajectory archive under RUN_DIR/archive/ (both backends; see docs/archive.md).

    ``xp``: every scored cross-play episode -> ``archive/xp/seat0_seed_<i>.mcap``. ``sa_collection``: every SA collection
    episode (all states, not only the kept ones) -> ``archive/sa/iteration_<k>.mcap``. ``train_every``:
    every N updates each seed's current policy plays one self-play episode -> ``archive/train/`` (0: off).
    ``foxglove``: add a rendered-frame channel for Foxglove Studio (~10x larger files).
    """

    xp: bool = True
    sa_collection: bool = True
    train_every: int = 0
    foxglove: bool = False


@dataclasses.dataclass(frozen=True)
class ClusterConfig:
    """The Ray backend (``ocv2 train`` default). Not part of the config fingerprint: a run may resume
    with other resources or another split of seeds (which moves parameters only at float-rounding level,
    ~1e-7, because XLA picks different kernels for different batch sizes; docs/cluster.md).

    ``address``: None starts Ray on this machine; "auto" or "HOST:PORT" joins a running cluster.
    ``seeds_per_actor`` seeds are vmapped in one actor (a GPU wants several); ``workers`` (0: one actor
    per ``seeds_per_actor`` seeds) sets the number of actors instead, spreading seeds evenly. ``num_cpus``/``num_gpus`` are
    per actor (fractional on a laptop: Ray's default of 1 CPU would leave actors pending on 2 cores).
    ``gpu_memory_fraction``: 0 grows GPU memory on demand (several actors can share a GPU); otherwise
    each actor preallocates that fraction. ``max_restarts``: Ray restarts of a dead worker actor.
    ``local_cpus``: logical CPUs of a Ray started on this machine (0: Ray detects them).
    """

    address: str | None = None
    workers: int = 0
    seeds_per_actor: int = 1
    num_cpus: float = 0.5
    num_gpus: float = 0.0
    gpu_memory_fraction: float = 0.0
    max_restarts: int = 3
    local_cpus: int = 0


@dataclasses.dataclass(frozen=True)
class Config:
    env: tuple[tuple[str, Any], ...] = (("layout", "cramped_room"),)
    model: ModelConfig = ModelConfig()
    ppo: PPOConfig = PPOConfig()
    population: PopulationConfig = PopulationConfig()
    eval: EvalConfig = EvalConfig()
    run: RunConfig = RunConfig()
    archive: ArchiveConfig = ArchiveConfig()
    cluster: ClusterConfig = ClusterConfig()

    @property
    def env_kwargs(self) -> dict:
        """Keyword arguments for ``ocv2.make``."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.env}

    def to_dict(self) -> dict:
        """Plain YAML/JSON-able form (round-trips through ``parse_config``)."""
        out = {"env": self.env_kwargs}
        for name in SECTIONS[1:]:
            out[name] = _plain(dataclasses.asdict(getattr(self, name)))
        return out

    def fingerprint(self, exclude: Sequence[str] = ("eval", "run", "archive", "cluster")) -> str:
        """A hash of everything that changes training numbers (checkpoints from another config are refused).

        Keys added after a release are left out at their default value (``_LATER_KEYS``), so runs made
        before the key existed keep their fingerprint and still resume.
        """
        data = {k: v for k, v in self.to_dict().items() if k not in exclude}
        for *path, key in _LATER_KEYS:
            section = data
            for name in path:
                section = section.get(name, {})
            if key in section and section[key] == _LATER_KEYS[(*path, key)]:
                del section[key]
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


#: Keys added after 0.1.0 and their defaults, left out of the fingerprint at those defaults.
_LATER_KEYS = {("population", "fcp", "pool"): "shared", ("population", "fcp", "partner_ppo"): None,
               ("model", "kernels"): "auto"}


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


# ---------------------------------------------------------------------------------------------------
# parsing
# ---------------------------------------------------------------------------------------------------

METHODS = ("sp", "sa", "op", "fcp")
ACTIVATIONS = ("relu", "tanh")
KERNELS = ("auto", "cpu", "xla")  # model.kernels
SECTIONS = ("env", "model", "ppo", "population", "eval", "run", "archive", "cluster")


def load_config(path: str | os.PathLike, overrides: Sequence[str] = ()) -> Config:
    """Read a YAML file, apply ``section.key=value`` overrides, validate. Errors name file and key."""
    path = os.fspath(path)
    raw = read_yaml(path)
    try:
        return parse_config(raw if raw is not None else {}, overrides)
    except ConfigError as error:
        raise error.prefixed(path) from None


def read_yaml(path: str) -> Any:
    """The plain data (mappings, lists, strings, numbers, booleans, null) of a YAML file, or a ConfigError."""
    if os.path.isdir(path):
        raise ConfigError(f"{path}: is a directory, not a config file")
    try:
        with open(path, encoding="utf-8") as handle:
            raw = yaml.safe_load(handle)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (not valid UTF-8)") from None
    except OSError as error:
        raise ConfigError(f"{path}: cannot read: {error.strerror or error}") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {yaml_problem(error)}") from None
    try:
        check_plain_data(raw)
    except ConfigError as error:
        raise error.prefixed(path) from None
    return raw


def yaml_problem(error: yaml.YAMLError) -> str:
    """A YAML error as one line: what went wrong and where (PyYAML's own message spans several lines)."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}"


def check_plain_data(value, where: str = "") -> None:
    """Refuse what YAML can express but a config cannot hold: dates, binary, sets, self-referencing
    anchors, and alias chains that expand to more than ``MAX_YAML_NODES`` nodes."""
    budget = [MAX_YAML_NODES]

    def walk(node, key: str, parents: tuple[int, ...]) -> None:
        budget[0] -= 1
        if budget[0] < 0:
            raise ConfigError(f"the YAML expands to more than {MAX_YAML_NODES} values (anchors and aliases "
                              "repeated too often)")
        name = key or "the config"
        if isinstance(node, (dict, list)):
            if id(node) in parents:
                raise ConfigError(f"{name}: refers to itself through a YAML anchor")
            inner = (*parents, id(node))
            items = node.items() if isinstance(node, dict) else enumerate(node)
            for child_key, child in items:
                if isinstance(node, dict) and not isinstance(child_key, str):
                    raise ConfigError(f"{name}: key {child_key!r} is not a string")
                child_name = f"{key}.{child_key}" if isinstance(node, dict) and key else (
                    str(child_key) if isinstance(node, dict) else f"{name}[{child_key}]")
                walk(child, child_name, inner)
            return
        if node is None or isinstance(node, (bool, int, float, str)):
            return
        kind = {"date": "a date", "datetime": "a date and time", "bytes": "binary data (!!binary)",
                "set": "a set (!!set)"}.get(type(node).__name__, f"a {type(node).__name__}")
        hint = "; quote it to make it a string" if type(node).__name__ in ("date", "datetime") else ""
        raise ConfigError(f"{name}: {kind} is not a config value, got {node!r}{hint}")

    walk(value, where, ())


def apply_overrides(raw: Mapping, overrides: Sequence[str]) -> dict:
    """``["ppo.lr=1e-3", "env.layout=coord_ring"]`` -> a new nested dict; values are parsed as YAML."""
    data = json.loads(json.dumps(raw))  # deep copy of plain data
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r}: expected section.key=value")
        dotted, text = item.split("=", 1)
        parts = dotted.strip().split(".")
        if len(parts) < 2 or not all(parts):
            raise ConfigError(f"override {item!r}: expected section.key=value")
        node = data
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: {part} is not a section")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError as error:
            raise ConfigError(f"override {item!r}: the value is not valid YAML: {yaml_problem(error)}") from None
        check_plain_data(value, dotted.strip())
        node[parts[-1]] = value
    return data


def parse_config(raw: Mapping, overrides: Sequence[str] = ()) -> Config:
    """Validate a nested mapping (e.g. from YAML) into a ``Config``; a ConfigError lists every problem."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"the config must be a mapping of sections {SECTIONS}, got {type(raw).__name__}")
    check_plain_data(raw)
    if is_ray_launcher_config(raw):
        raise ConfigError("a Ray cluster launcher config (for 'ray up'), not an ocv2 experiment config")
    raw = apply_overrides(raw, overrides)
    problems = [f"unknown section {name!r}; sections are {', '.join(SECTIONS)}"
                for name in sorted(set(raw) - set(SECTIONS), key=str)]

    def parsed(parse, *args, default):
        try:
            return parse(*args)
        except ConfigError as error:
            problems.extend(error.problems)
            return default if error.partial is None else error.partial

    env = parsed(_parse_env, raw.get("env") or {}, default=Config().env)
    model = _resolve_model(parsed(_parse_section, "model", ModelConfig, raw.get("model"), default=ModelConfig()),
                           problems)
    ppo = parsed(_parse_section, "ppo", PPOConfig, raw.get("ppo"), default=PPOConfig())
    pop_raw = raw.get("population") or {}
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
    subs = {name: parsed(_parse_section, f"population.{name}", cls, pop_raw.pop(name, None), default=cls())
            for name, cls in (("sa", SAConfig), ("op", OPConfig))}
    subs["fcp"] = parsed(_parse_section, "population.fcp", FCPConfig, fcp_raw, default=FCPConfig())
    population = dataclasses.replace(
        parsed(_parse_section, "population", PopulationConfig, pop_raw, default=PopulationConfig()), **subs)
    partner_ppo = parsed(_partner_ppo, partner_raw, env, model, population, default=None)
    population = dataclasses.replace(population, fcp=dataclasses.replace(population.fcp, partner_ppo=partner_ppo))
    config = Config(env=env, model=model, ppo=ppo, population=population,
                    eval=parsed(_parse_eval, raw.get("eval"), default=EvalConfig()),
                    run=parsed(_parse_section, "run", RunConfig, raw.get("run"), default=RunConfig()),
                    archive=parsed(_parse_section, "archive", ArchiveConfig, raw.get("archive"),
                                   default=ArchiveConfig()),
                    cluster=parsed(_parse_cluster, raw.get("cluster"), default=ClusterConfig()))
    # Values are checked with every key that did not parse at its default; a key already reported is
    # not reported again.
    reported = {problem.split(":", 1)[0] for problem in problems}
    problems += [p for p in _validate(config) if p.split(":", 1)[0] not in reported]
    if problems:
        raise ConfigError(problems)
    return config


#: Keys every Ray cluster launcher YAML has (``ray up``); configs/cluster/ holds one beside ocv2 configs.
RAY_LAUNCHER_KEYS = frozenset({"cluster_name", "provider"})


def is_ray_launcher_config(raw) -> bool:
    return isinstance(raw, Mapping) and RAY_LAUNCHER_KEYS <= set(raw) and not set(raw) & set(SECTIONS[:-1])


def _parse_section(name: str, cls, raw) -> Any:
    if raw is None:
        return cls()
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{name}: expected a mapping of keys, got {type(raw).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    values, problems = {}, []
    for key, value in raw.items():
        if key not in fields:
            problems.append(f"{name}.{key}: unknown key; valid keys are {', '.join(fields)}")
            continue
        try:
            values[key] = _coerce(f"{name}.{key}", value, hints[key])
        except ConfigError as error:
            problems.extend(error.problems)
    if problems:
        raise ConfigError(problems, partial=cls(**values))
    return cls(**values)


def _coerce(key: str, value, hint):
    """Check ``value`` against a field's type; ints given as 1e7 floats are accepted when integral."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(key, value, inner[0])
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return tuple(_coerce(f"{key}[{i}]", v, args[0]) for i, v in enumerate(value))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                as_float = float(value)
            except ValueError:
                as_float = math.nan
            if as_float.is_integer():
                return int(as_float)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, str):
            try:
                value = float(value)  # YAML reads "1e-4" (no dot) as a string
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        if not math.isfinite(value):  # a NaN learning rate would "train" to NaN parameters without a word
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        return float(value)
    if hint is str:
        if isinstance(value, bool) or not isinstance(value, (str, int)):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return str(value)
    return value


def _parse_env(raw) -> tuple[tuple[str, Any], ...]:
    if not isinstance(raw, Mapping):
        raise ConfigError(f"env: expected a mapping of ocv2.make parameters, got {type(raw).__name__}")
    if "initial_state_buffer" in raw:
        raise ConfigError("env.initial_state_buffer: state buffers come from population.method=sa, not the config")
    # Integral floats (YAML reads 1e3 as a float) count as integers, as in the other sections.
    params = {k: int(v) if isinstance(v, float) and v.is_integer() else v for k, v in raw.items()}
    params.setdefault("layout", "cramped_room")
    try:
        build_config(**params)
    except TypeError as error:
        raise ConfigError(f"env: {error}") from None
    except ValueError as error:
        raise ConfigError(f"env: {error}") from None
    frozen = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in params.items()))
    return frozen


def _parse_eval(raw) -> EvalConfig:
    if isinstance(raw, Mapping) and "archive_episodes" in raw:
        raise ConfigError("eval.archive_episodes: replaced by archive.xp (default true), which archives every "
                          "scored cross-play episode to archive/xp/")
    return _parse_section("eval", EvalConfig, raw)


def _parse_cluster(raw) -> ClusterConfig:
    if isinstance(raw, Mapping) and "checkpoint_every" in raw:
        raise ConfigError("cluster.checkpoint_every: checkpoints are set by run.checkpoint_every, which both "
                          "backends use (it is also the chunk between coordinator steps)")
    return _parse_section("cluster", ClusterConfig, raw)


def _resolve_model(model: ModelConfig, problems: list[str]) -> ModelConfig:
    if model.kind not in _MODEL_DEFAULTS:
        problems.append(f"model.kind: expected one of {', '.join(_MODEL_DEFAULTS)}, got {model.kind!r}")
        model = dataclasses.replace(model, kind=ModelConfig.kind)
    fill = {k: v for k, v in _MODEL_DEFAULTS[model.kind].items() if getattr(model, k) is None}
    return dataclasses.replace(model, **fill)


def _partner_ppo(raw, env, model: ModelConfig, population: PopulationConfig) -> PPOConfig | None:
    """The FCP partner stage's ppo section: ``raw`` keys over the paper's self-play section for this layout."""
    key = "population.fcp.partner_ppo"
    if raw is not None and not isinstance(raw, Mapping):
        raise ConfigError(f"{key}: expected a mapping of ppo keys, got {type(raw).__name__}")
    trains_partners = population.method == "fcp" and population.fcp.partners is None
    if not trains_partners:
        # Not used (another method, or partners from a finished SP run): only checked, never looked up.
        return None if raw is None else _parse_section(key, PPOConfig, raw)
    layout = dict(env)["layout"]
    base = paper_sp_ppo(layout, model.kind)
    if base is None and raw is None:
        raise ConfigError(f"{key}: no paper self-play config for layout {layout!r} with model.kind={model.kind} "
                          "to take the partner stage's hyperparameters from; set it (a ppo mapping)")
    values = dataclasses.asdict(base) if base is not None else {}
    values.update(raw or {})
    return _parse_section(key, PPOConfig, values)


@functools.lru_cache(maxsize=None)
def paper_sp_ppo(layout: str, model_kind: str) -> PPOConfig | None:
    """The ppo section of the paper's self-play config for ``layout`` and ``model_kind`` (None: there is none)."""
    found = {}
    if os.path.isdir(PAPER_CONFIGS):
        for name in sorted(os.listdir(PAPER_CONFIGS)):
            if not name.endswith(".yaml"):
                continue
            with open(os.path.join(PAPER_CONFIGS, name)) as handle:
                raw = yaml.safe_load(handle) or {}
            pop, env, model = raw.get("population") or {}, raw.get("env") or {}, raw.get("model") or {}
            if pop.get("method") == "sp" and env.get("layout") == layout and model.get("kind") == model_kind:
                found[name] = _parse_section(f"{name}: ppo", PPOConfig, raw.get("ppo"))
    if len(set(found.values())) > 1:
        raise ConfigError(f"population.fcp.partner_ppo: paper self-play configs {', '.join(found)} disagree "
                          f"for layout {layout!r}; set population.fcp.partner_ppo")
    return next(iter(found.values()), None)


def _positive(key: str, value, allow_zero: bool = False) -> list[str]:
    if value < 0 or (value == 0 and not allow_zero):
        return [f"{key}: must be {'>= 0' if allow_zero else '> 0'}, got {value}"]
    return []


def _validate_ppo(prefix: str, ppo: PPOConfig) -> list[str]:
    """Range checks of a ppo section (``prefix``: where it sits, e.g. ppo or population.fcp.partner_ppo)."""
    problems: list[str] = []
    if ppo.activation not in ACTIVATIONS:
        problems.append(f"{prefix}.activation: expected one of {', '.join(ACTIVATIONS)}, got {ppo.activation!r}")
    for key in ("lr", "clip_eps", "max_grad_norm", "num_envs", "num_steps", "num_minibatches",
                "update_epochs", "total_timesteps"):
        problems += _positive(f"{prefix}.{key}", getattr(ppo, key))
    for key in ("ent_coef", "vf_coef", "rew_shaping_horizon"):
        problems += _positive(f"{prefix}.{key}", getattr(ppo, key), allow_zero=True)
    for key in ("gamma", "gae_lambda", "lr_warmup"):
        if not 0.0 <= getattr(ppo, key) <= 1.0:
            problems.append(f"{prefix}.{key}: must lie in [0, 1], got {getattr(ppo, key)}")
    if ppo.num_envs > 0 and ppo.num_steps > 0 and ppo.num_updates < 1:
        problems.append(f"{prefix}.total_timesteps: {ppo.total_timesteps} is less than one update "
                        f"(num_envs x num_steps = {ppo.steps_per_update})")
    return problems


def _validate_fcp(fcp: FCPConfig, num_agents: int) -> list[str]:
    problems = _positive("population.fcp.partner_seeds", fcp.partner_seeds)
    if fcp.pool not in FCP_POOLS:
        problems.append(f"population.fcp.pool: expected one of {', '.join(FCP_POOLS)}, got {fcp.pool!r}")
    if not fcp.checkpoints:
        problems.append("population.fcp.checkpoints: needs at least one checkpoint")
    for c in fcp.checkpoints:
        if c not in ("init", "mid", "final") and not str(c).isdigit():
            problems.append(f"population.fcp.checkpoints: {c!r} is not init, mid, final or an update number")
    if num_agents != 2:
        problems.append("population.method: fcp needs a two-agent layout")
    partner = fcp.partner_ppo
    if partner is None:
        return problems
    key = "population.fcp.partner_ppo"
    partner_problems = _validate_ppo(key, partner)
    problems += partner_problems
    if partner_problems:  # the checks below divide by these sizes
        return problems
    if (partner.num_envs * num_agents) % partner.num_minibatches:
        problems.append(f"{key}.num_minibatches: {partner.num_minibatches} does not divide the "
                        f"{partner.num_envs * num_agents} self-play sequences per update of the partner stage "
                        f"(num_envs x {num_agents} agents)")
    late = [c for c in fcp.checkpoints if str(c).isdigit() and int(c) > partner.num_updates]
    if late:
        problems.append(f"population.fcp.checkpoints: update {late[0]} is past the partner stage's "
                        f"{partner.num_updates} updates ({key}.total_timesteps)")
    return problems


def _validate(config: Config) -> list[str]:
    """Every problem of values checked against each other (each value has the right type already)."""
    model, ppo, pop = config.model, config.ppo, config.population
    problems: list[str] = []
    if len(model.conv_features) != len(model.conv_kernels):
        problems.append("model.conv_kernels: needs one kernel size per entry of model.conv_features")
    if model.kernels not in KERNELS:
        problems.append(f"model.kernels: expected one of {', '.join(KERNELS)}, got {model.kernels!r}")
    for key in ("fc_dim", "gru_dim"):
        problems += _positive(f"model.{key}", getattr(model, key))
    for key, values in (("conv_features", model.conv_features), ("conv_kernels", model.conv_kernels),
                        ("mixer_features", model.mixer_features)):
        for v in values:
            problems += _positive(f"model.{key}", v)
    problems += _validate_ppo("ppo", ppo)
    sizes_ok = ppo.num_envs > 0 and ppo.num_steps > 0 and ppo.num_minibatches > 0
    env = build_config(**config.env_kwargs)
    learner_actors = ppo.num_envs if pop.method == "fcp" else ppo.num_envs * env.num_agents
    if sizes_ok and learner_actors % ppo.num_minibatches:
        seats = "1 learner seat" if pop.method == "fcp" else f"{env.num_agents} agents"
        problems.append(f"ppo.num_minibatches: {ppo.num_minibatches} does not divide the {learner_actors} "
                        f"learner sequences per update (num_envs x {seats})")
    if pop.method not in METHODS:
        problems.append(f"population.method: expected one of {', '.join(METHODS)}, got {pop.method!r}")
    problems += _positive("population.num_seeds", pop.num_seeds)
    problems += _seed_problems(pop)
    for key in ("iterations", "rollouts_per_pair", "keep_every"):
        problems += _positive(f"population.sa.{key}", getattr(pop.sa, key))
    if pop.method == "sa":
        if sizes_ok and pop.sa.iterations > ppo.num_updates:
            problems.append(f"population.sa.iterations: {pop.sa.iterations} iterations need at least as many "
                            f"updates, the config has {ppo.num_updates}")
        if pop.sa.keep_every > env.max_steps:
            problems.append(f"population.sa.keep_every: {pop.sa.keep_every} exceeds env.max_steps={env.max_steps}")
    if pop.method == "op":
        n = env.num_ingredients
        if len(pop.op.ingredients) < 2 or len(set(pop.op.ingredients)) != len(pop.op.ingredients):
            problems.append("population.op.ingredients: needs at least two distinct ingredient indices")
        if any(not 0 <= i < n for i in pop.op.ingredients):
            problems.append(f"population.op.ingredients: indices must lie in [0, {n}) for layout "
                            f"{env.layout.name!r}, got {list(pop.op.ingredients)}")
        if env.op_enabled:
            problems.append("env.op_ingredient_permutations: set population.op.ingredients instead "
                            "(evaluation must run without permutations)")
    if pop.method == "fcp":
        problems += _validate_fcp(pop.fcp, env.num_agents)
    problems += _positive("eval.episodes", config.eval.episodes)
    problems += _positive("eval.gifs", config.eval.gifs, allow_zero=True)
    problems += _positive("run.checkpoint_every", config.run.checkpoint_every)
    problems += _positive("archive.train_every", config.archive.train_every, allow_zero=True)
    problems += _cluster_problems(config.cluster, pop.num_seeds)
    if config.run.num_checkpoints < 2:
        problems.append(f"run.num_checkpoints: must be >= 2 (initial and final), got {config.run.num_checkpoints}")
    return problems


def _seed_problems(pop: PopulationConfig) -> list[str]:
    """Every seed a run derives must fit a 32-bit PRNG seed (larger ones would wrap onto small ones)."""
    if pop.seed < 0:
        return [f"population.seed: must be >= 0, got {pop.seed}"]
    largest = MAX_SEED - (FCP_STAGE_SEED_OFFSET if pop.method == "fcp" and pop.fcp.partners is None else 0)
    if pop.seed > largest:
        why = " (the FCP partner stage trains with seed + 7919)" if largest < MAX_SEED else ""
        return [f"population.seed: must be <= {largest}{why}, got {pop.seed}"]
    return []


def _cluster_problems(cluster: ClusterConfig, num_seeds: int) -> list[str]:
    problems: list[str] = []
    if cluster.address is not None:
        address = cluster.address.strip()
        host, _, port = address.rpartition(":")
        if address != "auto" and not (host and port.isdigit()) and not address.startswith("ray://"):
            problems.append(f"cluster.address: expected auto, HOST:PORT or ray://HOST:PORT, got {cluster.address!r}")
    problems += _positive("cluster.workers", cluster.workers, allow_zero=True)
    problems += _positive("cluster.seeds_per_actor", cluster.seeds_per_actor)
    if cluster.workers and cluster.seeds_per_actor != 1:
        problems.append("cluster.workers: set either workers or seeds_per_actor, not both")
    if cluster.workers > num_seeds:
        problems.append(f"cluster.workers: {cluster.workers} actors for {num_seeds} seeds (at most one per seed)")
    problems += _positive("cluster.num_cpus", cluster.num_cpus)
    problems += _positive("cluster.num_gpus", cluster.num_gpus, allow_zero=True)
    if not 0.0 <= cluster.gpu_memory_fraction < 1.0:
        problems.append(f"cluster.gpu_memory_fraction: must lie in [0, 1), got {cluster.gpu_memory_fraction}")
    problems += _positive("cluster.max_restarts", cluster.max_restarts, allow_zero=True)
    problems += _positive("cluster.local_cpus", cluster.local_cpus, allow_zero=True)
    return problems


def shards(config: Config) -> list[list[int]]:
    """The seeds each Ray worker actor trains: consecutive blocks, as even as possible."""
    seeds, cluster = list(range(config.population.num_seeds)), config.cluster
    count = cluster.workers or math.ceil(len(seeds) / cluster.seeds_per_actor)
    size, extra = divmod(len(seeds), count)
    blocks, start = [], 0
    for index in range(count):
        end = start + size + (index < extra)
        blocks.append(seeds[start:end])
        start = end
    return blocks


def dump_config(config: Config, path: str | os.PathLike) -> None:
    """Write the resolved config as YAML (atomically)."""
    atomic_write(path, yaml.safe_dump(config.to_dict(), sort_keys=False))
