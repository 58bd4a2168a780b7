"""One trained policy as a value: load it from a run, a checkpoint or an exported file, act with it.

    policy = load("runs/my_run")                       # seed 0, final checkpoint
    policy = load("runs/my_run", seed=3, checkpoint="mid")
    policy = load("runs/my_run/checkpoints/seed_3")    # that seed's final checkpoint
    policy = load("runs/my_run/checkpoints/seed_3/update_0000004.msgpack")
    policy = load("cook.ocv2policy")                   # written by export()

    hidden = policy.initial_hidden(batch)
    actions, hidden = policy.act(key, obs, hidden, reset)   # obs [B, H, W, C], reset bool[B]

An exported file is one sealed msgpack file (``population.sealed``: every byte under one SHA-256)
holding a JSON header -- format name and version, the network (``ModelConfig`` + activation + number
of actions), the ``ocv2.make`` keyword arguments of the environment it plays, free ``meta`` -- and the
network parameters, which must be finite floating-point arrays. Nothing of the training run (optimizer
state, PPO settings, metrics) is in it, so it can be shared on its own. Version-1 files (the same
header and parameters, no checksum) still load, with a ``PolicyFormatWarning``.

``Policy.apply`` follows the network calling convention of ``population.networks``, which is what
``population.evaluation`` pairs seat by seat: policies of different runs, CNN with RNN, or
hand-written ones play together through the same rollout.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import operator
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

import ocv2
from ocv2 import boundedjson
from ocv2.atomic import atomic_write
from ocv2.config import build_config
from population import checkpoints as ckpt
from population.config import (
    PRECISIONS,
    Config,
    ConfigError,
    ModelConfig,
    is_update_number,
    load_run_config,
    parse_config,
)
from population.networks import init_params, make_network, same_function
from population.sealed import SealError, is_sealed, seal, unseal

FORMAT_NAME = "ocv2-policy"
FORMAT_VERSION = 2
#: Exports before the checksum: read, with a warning.
UNSEALED_VERSION = 1
SUFFIX = ".ocv2policy"
CHECKPOINT_CHOICES = ("init", "mid", "final", "latest")


class PolicyError(ValueError):
    """A policy source that cannot be loaded or exported (the message names the file)."""


class PolicyFormatWarning(UserWarning):
    """A policy file in an older format that still loads, without the checks of the current one."""


@dataclasses.dataclass(frozen=True, eq=False)
class Policy:
    """A network with its parameters and the environment it plays (``env``: ``ocv2.make`` kwargs)."""

    name: str
    apply: Any  # (params, hidden [B, H], obs [T, B, ...], reset bool[T, B]) -> (hidden, logits, value)
    params: Any
    hidden_size: int
    model: ModelConfig
    env: dict
    activation: str = "relu"
    source: str = ""
    meta: dict = dataclasses.field(default_factory=dict)

    def initial_hidden(self, batch: int) -> jax.Array:
        """float32[batch, hidden_size] zeros (the CNN's is [batch, 0])."""
        return jnp.zeros((batch, self.hidden_size), jnp.float32)

    def act(self, key: jax.Array, obs: jax.Array, hidden: jax.Array, reset: jax.Array, greedy: bool = False):
        """One step for B agents: (int32[B] actions, new hidden). ``reset[b]``: agent b's episode starts
        at this observation (its recurrent state is zeroed first). Sampled unless ``greedy`` (argmax).
        Jittable; the same key gives the same actions as ``population.evaluation.play_step``."""
        return act(self.apply, self.params, key, obs, hidden, reset, greedy)

    def make_env(self) -> ocv2.OvercookedV2:
        """The environment this policy was trained/evaluated in (one shared object per settings)."""
        return policy_env(self.env)

    @property
    def seat(self) -> tuple:
        """(apply, params, hidden_size): what ``population.evaluation`` takes per seat."""
        return self.apply, self.params, self.hidden_size


@functools.partial(jax.jit, static_argnames=("apply", "greedy"))
def act(apply, params, key: jax.Array, obs: jax.Array, hidden: jax.Array, reset: jax.Array, greedy: bool = False):
    """``Policy.act`` as a function of (apply, params): one network step for a batch of agents."""
    hidden, logits, _ = apply(params, hidden, obs[None], jnp.asarray(reset, bool)[None])
    logits = logits[0]
    actions = jnp.argmax(logits, axis=-1) if greedy else jax.random.categorical(key, logits)
    return actions.astype(jnp.int32), hidden


# ---------------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------------


def export(path, *, params, model: ModelConfig, env, meta: dict | None = None, activation: str = "relu") -> Path:
    """Write ``params`` of a network ``model`` playing ``env`` to one file, atomically.

    ``env``: ``ocv2.make`` keyword arguments (a mapping, e.g. ``Config.env_kwargs``) or a run ``Config``.
    ``meta``: JSON-able extras (origin, layout notes, ...), returned as ``Policy.meta``. The parameters
    are checked against the network before anything is written.
    """
    path = Path(path)
    env_kwargs = _env_kwargs(env)
    header = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "model": _plain(dataclasses.asdict(model)),
        "activation": activation,
        "env": _plain(env_kwargs),
        "meta": meta or {},
    }
    try:
        header_text = json.dumps(header, sort_keys=True)
    except TypeError as error:
        raise PolicyError(f"{path}: meta must be JSON-able ({error})") from None
    params = jax.tree.map(np.asarray, params)
    config = _validated(header, str(path))
    _restore_params(str(path), _template(config), serialization.to_state_dict(params))
    content = {"header": header_text, "params": serialization.to_state_dict(params)}
    return atomic_write(path, seal(FORMAT_NAME, FORMAT_VERSION, content))


def export_checkpoint(
    source, out, *, seed: int | None = None, checkpoint: str | int = "final", meta: dict | None = None
) -> Path:
    """Export the policy ``load(source, seed=..., checkpoint=...)`` finds (a run, seed dir or checkpoint)."""
    policy = load(source, seed=seed, checkpoint=checkpoint)
    return export(
        out,
        params=policy.params,
        model=policy.model,
        env=policy.env,
        activation=policy.activation,
        meta={"exported_from": policy.source, "name": policy.name, **policy.meta, **(meta or {})},
    )


# ---------------------------------------------------------------------------------------------------
# load
# ---------------------------------------------------------------------------------------------------


def load(source, *, seed: int | None = None, checkpoint: str | int = "final") -> Policy:
    """A ``Policy`` from an exported file, a checkpoint file, a seed directory or a run directory.

    ``seed`` (run directory only; default 0) and ``checkpoint`` ("final", "mid", "init", "latest" or an
    update number; run or seed directory) pick the checkpoint. Bad input raises ``PolicyError``.
    """
    if not isinstance(source, str | os.PathLike):
        raise PolicyError(f"source must be a path (a str or os.PathLike), got {type(source).__name__}")
    path = Path(source)
    seed = _checked_seed(path, seed)
    if path.is_file():
        if seed is not None or str(checkpoint) != "final":
            raise PolicyError(f"{path}: is one policy; seed and checkpoint choices apply to a run or seed directory")
        return _load_file(path)
    if path.is_dir():
        if (path / "config.yaml").is_file():
            return _load_from_run(path, 0 if seed is None else seed, checkpoint)
        folder_seed = ckpt.seed_of_folder(path.name)
        if (
            folder_seed is not None
            and path.parent.name == "checkpoints"
            and (path.parent.parent / "config.yaml").is_file()
        ):
            if seed is not None and seed != folder_seed:
                raise PolicyError(f"{path}: is seed {folder_seed}'s directory, but seed={seed} was asked")
            return _load_from_run(path.parent.parent, folder_seed, checkpoint)
        raise PolicyError(f"{path}: not a run directory (no config.yaml) nor a run's checkpoints/seed_<i> directory")
    raise PolicyError(f"{path}: no such file or directory")


def _checked_seed(path: Path, seed) -> int | None:
    """``seed`` as an int (None stays None); ``PolicyError`` for a bool, a float or a string, which would otherwise
    look for checkpoints/seed_True or seed_1.5, or fail comparing a string with the run's seed count."""
    if seed is None:
        return None
    try:
        if isinstance(seed, bool):
            raise TypeError
        return operator.index(seed)
    except TypeError:
        raise PolicyError(f"{path}: seed {seed!r} must be an int, not a {type(seed).__name__}") from None


def _load_file(path: Path) -> Policy:
    try:
        payload = serialization.msgpack_restore(path.read_bytes())
    except OSError as error:
        raise PolicyError(f"{path}: cannot read ({error.strerror or error})") from None
    except Exception as error:  # msgpack raises several types on truncated or foreign data
        raise PolicyError(
            f"{path}: not an ocv2 policy or checkpoint file, or a damaged or cut one (msgpack: {error})"
        ) from None
    if is_sealed(payload) and payload.get("format") == ckpt.FORMAT_NAME:
        return _load_checkpoint_file(path)
    if is_sealed(payload):
        try:
            content = unseal(payload, FORMAT_NAME, FORMAT_VERSION)
        except SealError as error:
            raise PolicyError(f"{path}: {error}") from None
        if "header" not in content or "params" not in content:
            raise PolicyError(f"{path}: not an {FORMAT_NAME} file (no header/params)")
        return _load_exported(path, content, FORMAT_VERSION)
    if isinstance(payload, dict) and "header" in payload and "params" in payload:
        return _load_exported(path, payload, UNSEALED_VERSION)
    if isinstance(payload, dict) and "meta" in payload and "state" in payload:
        return _load_checkpoint_file(path)
    raise PolicyError(f"{path}: not an ocv2 policy or checkpoint file")


def _load_exported(path: Path, payload: dict, version: int) -> Policy:
    try:
        header = boundedjson.loads(payload["header"])
    except boundedjson.JSONDepthError as error:
        raise PolicyError(f"{path}: corrupt policy header ({error})") from None
    except (TypeError, ValueError):
        raise PolicyError(f"{path}: corrupt policy header") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise PolicyError(f"{path}: not an {FORMAT_NAME} file")
    if header.get("version") != version:
        raise PolicyError(
            f"{path}: {FORMAT_NAME} version {header.get('version')!r}; this ocv2 reads version "
            f"{FORMAT_VERSION} (and {UNSEALED_VERSION} without a checksum)"
        )
    if version == UNSEALED_VERSION:
        warnings.warn(
            f"{path}: an {FORMAT_NAME} version-{UNSEALED_VERSION} file has no checksum, so damage to it "
            f"cannot be detected; export it again to get version {FORMAT_VERSION}",
            PolicyFormatWarning,
            stacklevel=4,
        )
    config = _validated(header, str(path))
    params = _restore_params(str(path), _template(config), payload["params"])
    meta = header.get("meta") or {}
    return _policy(config, params, name=str(meta.get("name") or path.stem), source=str(path), meta=meta)


def _load_checkpoint_file(path: Path) -> Policy:
    seed_dir = path.parent
    seed = ckpt.seed_of_folder(seed_dir.name)
    run_dir = seed_dir.parent.parent
    if seed is None or seed_dir.parent.name != "checkpoints" or not (run_dir / "config.yaml").is_file():
        raise PolicyError(
            f"{path}: a checkpoint must lie in RUN_DIR/checkpoints/seed_<i>/ next to its run's "
            "config.yaml (or export it with 'ocv2 export')"
        )
    config = _run_config(run_dir)
    return _from_checkpoint(config, path, run_dir, seed)


def _load_from_run(run_dir: Path, seed: int, checkpoint) -> Policy:
    config = _run_config(run_dir)
    if not 0 <= seed < config.population.num_seeds:
        raise PolicyError(f"{run_dir}: has seeds 0..{config.population.num_seeds - 1}, not seed {seed}")
    update = _pick_update(run_dir, config, seed, checkpoint)
    return _from_checkpoint(config, ckpt.checkpoint_path(run_dir, seed, update), run_dir, seed)


def _pick_update(run_dir: Path, config: Config, seed: int, checkpoint) -> int:
    available = ckpt.list_updates(run_dir, seed)
    if not available:
        raise PolicyError(f"{ckpt.seed_dir(run_dir, seed)}: no checkpoints")
    choice = str(checkpoint)
    if choice == "latest":
        return available[-1]
    if choice in ("init", "mid", "final"):
        try:  # a damaged manifest.json, or snapshots that do not hold the choice
            snapshots = ckpt.run_snapshots(run_dir, config.ppo.num_updates, config.run.num_checkpoints)
            update = ckpt.resolve_snapshot(choice, snapshots)
        except ckpt.CheckpointError as error:
            raise PolicyError(str(error)) from None
    elif is_update_number(choice):
        update = int(choice)
    else:
        raise PolicyError(
            f"checkpoint {checkpoint!r}: expected one of {', '.join(CHECKPOINT_CHOICES)} or an update number"
        )
    if update not in available:
        raise PolicyError(
            f"{ckpt.seed_dir(run_dir, seed)}: no checkpoint at update {update} ({choice}); it has updates {available}"
        )
    return update


def _run_config(run_dir: Path) -> Config:
    try:
        return load_run_config(run_dir)
    except ConfigError as error:
        raise PolicyError(str(error)) from None


def _from_checkpoint(config: Config, path: Path, run_dir: Path, seed: int) -> Policy:
    try:
        meta, raw = ckpt.read(path, config.fingerprint())
    except ckpt.CheckpointError as error:
        raise PolicyError(str(error)) from None
    if not isinstance(raw, dict) or "params" not in raw:
        raise PolicyError(f"{path}: checkpoint holds no network parameters")
    params = _restore_params(str(path), _template(config), raw["params"])
    update = int(meta.get("update", -1))
    return _policy(
        config,
        params,
        name=f"{run_dir.name}/seed_{seed}@{update}",
        source=str(path),
        meta={
            "run_dir": str(run_dir),
            "seed": seed,
            "update": update,
            "method": config.population.method,
            "precision": config.run.precision,  # the matmul precision its run trained and cross-played at
            # the run's config fingerprint, so that an exported file names the training config it came from
            # (a study's report.md lists it per run; ``load_run_config(run).fingerprint()`` computes it)
            "fingerprint": config.fingerprint(),
        },
    )


# ---------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------


def trained_precision(policy: Policy) -> str | None:
    """The ``run.precision`` ``policy`` trained at: a checkpoint's run's, or the meta of a file exported from one;
    None where nothing says. ``PolicyError`` for a name that is not one of ``PRECISIONS`` (the caller names the
    source): cross-play, render and play trace a policy at it."""
    precision = policy.meta.get("precision")
    if precision is not None and precision not in PRECISIONS:
        raise PolicyError(f"meta precision {precision!r} is not one of {', '.join(PRECISIONS)}")
    return precision


def env_settings(env: Mapping) -> dict:
    """Every setting of the environment ``env`` (``ocv2.make`` kwargs) asks for, defaults written out: a run
    config that leaves ``max_steps`` out and one that writes 400 ask for the same game, and compare equal here.
    Settings ``ocv2.make`` would refuse are returned as given (they then differ from any valid ones)."""
    try:
        config = build_config(**dict(env))
    except (TypeError, ValueError):
        return dict(env)
    settings = {"layout": config.layout.name}
    for field in dataclasses.fields(config):
        if field.name != "layout":
            value = getattr(config, field.name)
            settings[field.name] = list(value) if isinstance(value, tuple) else value
    return settings


def network_settings(config: Config) -> dict:
    """The network a run trains, as plain data: two runs with equal settings train the same function (their
    kernel choice aside, ``population.networks.same_function``), so their numbers compare."""
    return {**dataclasses.asdict(same_function(config.model)), "activation": config.ppo.activation}


def comparable_key(config: Config) -> str:
    """What makes two runs' numbers comparable, as one string: the game each asks for, defaults written out
    (``env_settings``), and the network it trains (``network_settings``). Reports compare a method with the
    self-play run of the same key."""
    settings = {"env": env_settings(config.env_kwargs), "network": network_settings(config)}
    return json.dumps(settings, sort_keys=True, default=list)


def same_env(env: Mapping, reference: Mapping) -> bool:
    """Whether two environment settings (``Policy.env``, ``Config.env_kwargs``) make the same game."""
    return env_settings(env) == env_settings(reference)


def env_difference(env: Mapping, reference: Mapping) -> str:
    """How two policies' environment settings (``Policy.env``) differ, for an error message: "differs in KEYS:
    <env's value> vs <reference's value>" of the first differing key, defaults written out; "" when they make the
    same game."""
    env, reference = env_settings(env), env_settings(reference)
    keys = sorted(k for k in set(env) | set(reference) if env.get(k) != reference.get(k))
    return f"differs in {', '.join(keys)}: {env.get(keys[0])!r} vs {reference.get(keys[0])!r}" if keys else ""


def policy_env(env_kwargs: Mapping) -> ocv2.OvercookedV2:
    """``ocv2.make(**env_kwargs)``, one object per distinct settings: jitted rollouts are cached per env
    object, so policies (or worker calls) with equal settings share compiled programs."""
    return _env_from_items(_freeze(env_kwargs))


@functools.lru_cache(maxsize=32)
def _env_from_items(items: tuple) -> ocv2.OvercookedV2:
    return ocv2.make(**{k: list(v) if isinstance(v, tuple) else v for k, v in items})


@functools.lru_cache(maxsize=32)
def network(model: ModelConfig, activation: str, num_actions: int):
    """The network of ``model``, one object per distinct settings (so equal networks share ``apply``
    and with it jit caches)."""
    return make_network(model, num_actions, activation)


def hidden_size_of(model: ModelConfig) -> int:
    return model.gru_dim if model.recurrent else 0


def _policy(config: Config, params, *, name: str, source: str, meta: dict) -> Policy:
    return Policy(
        name=name,
        apply=_network(config).apply,
        params=params,
        hidden_size=hidden_size_of(config.model),
        model=config.model,
        env=config.env_kwargs,
        activation=config.ppo.activation,
        source=source,
        meta=meta,
    )


def _network(config: Config):
    return network(config.model, config.ppo.activation, policy_env(config.env_kwargs).num_actions)


def _freeze(env_kwargs: Mapping) -> tuple:
    return tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in env_kwargs.items()))


@functools.lru_cache(maxsize=32)
def _template(config: Config):
    """Shapes and dtypes of the network's parameters (nothing is computed)."""
    env = policy_env(config.env_kwargs)
    if not isinstance(env.obs_shape, tuple):
        raise PolicyError(
            f"layout {config.env_kwargs['layout']!r}: agents with different observation shapes cannot share one network"
        )
    network = _network(config)
    return jax.eval_shape(lambda k: init_params(network, k, env.obs_shape), jax.random.PRNGKey(0))


def _restore_params(where: str, template, raw):
    try:
        params = serialization.from_state_dict(template, raw)
    except (KeyError, ValueError, TypeError) as error:
        raise PolicyError(f"{where}: parameters do not fit the network ({error})") from None
    ckpt.check_shapes(where, template, params, PolicyError, what="parameter array")
    _check_values(where, params)
    return jax.tree.map(lambda t, x: jnp.asarray(x, t.dtype), template, params)


def _check_values(where: str, params) -> None:
    """Refuse parameters that the cast to the network's float32 would silently change or that would make
    every action NaN: non-float arrays (complex ones lose their imaginary part) and NaN or infinity."""
    for keys, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        name = "/".join(str(getattr(k, "key", k)) for k in keys)
        value = np.asarray(leaf)
        if not jnp.issubdtype(value.dtype, jnp.floating):
            raise PolicyError(f"{where}: parameter {name} has dtype {value.dtype}, not a floating-point one")
        if not np.isfinite(value).all():
            raise PolicyError(f"{where}: parameter {name} holds NaN or infinite values")


def _validated(header: dict, where: str) -> Config:
    """The header's network and environment as a (default-trained) ``Config``: validated like a run's."""
    model, env = header.get("model"), header.get("env")
    if not isinstance(model, dict) or not isinstance(env, dict):
        raise PolicyError(f"{where}: header needs 'model' and 'env' mappings")
    try:
        return parse_config({"env": env, "model": model, "ppo": {"activation": header.get("activation", "relu")}})
    except ConfigError as error:
        raise PolicyError(f"{where}: {error}") from None


def _env_kwargs(env) -> dict:
    if isinstance(env, Config):
        return env.env_kwargs
    if isinstance(env, Mapping):
        return dict(env)
    if isinstance(env, ocv2.OvercookedV2):
        env = env.config
    if isinstance(env, ocv2.EnvConfig):
        return _env_config_kwargs(env)
    raise PolicyError(
        f"env must be ocv2.make keyword arguments (a mapping), an ocv2 env or EnvConfig, or a run "
        f"Config; got {type(env).__name__}"
    )


def _env_config_kwargs(config: ocv2.EnvConfig) -> dict:
    """The ``ocv2.make`` kwargs of an env's config: its built-in layout's name and every non-default setting."""
    name = config.layout.name
    if ocv2.LAYOUTS.get(name) is not config.layout:
        raise PolicyError(f"env: layout {name!r} is not a built-in layout; only built-in layouts can be exported")
    kwargs = {"layout": name}
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if field.name != "layout" and value != field.default:
            kwargs[field.name] = list(value) if isinstance(value, tuple) else value
    return kwargs


def _plain(value):
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "Policy",
    "PolicyError",
    "SUFFIX",
    "act",
    "export",
    "export_checkpoint",
    "hidden_size_of",
    "load",
    "network",
    "policy_env",
]
