"""Behaviour cloning: a human proxy policy from the 2019 human trials (Carroll et al. 2019).

Every recorded (state, action) of both seats becomes one sample: the seat's ocv2 default observation
of the recorded state and the action the human took. A feed-forward network of
``population.networks`` (the classic-layout CNN by default) is fitted by cross-entropy with optax's
Adam on minibatches drawn with an explicit key; training is one jitted ``lax.scan`` per evaluation
chunk, so the same config and seed give the same parameters.

The proxy is scored by its action accuracy on the held-out test trials (against a uniform
policy, 1/6, and the majority action of the training data) and the team return of the proxy playing
with itself (sampled actions, ``population.evaluation.play_episodes``).

A proxy is saved as an exported policy (``population.policy.export``; ``save_proxy``) whose metadata
holds its scores, so anything that loads policies plays with it; ``proxy_path(layout)``
(``population.human``) is where ``ocv2 human proxy`` caches it by default.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

import ocv2
from ocv2 import items as it
from ocv2.items import Action
from population import policy
from population.config import MODEL_DEFAULTS, ModelConfig
from population.evaluation import play_episodes
from population.human import Trial
from population.networks import ActorCritic, init_params, make_network

PROXY_KIND = "human-proxy"


@dataclasses.dataclass(frozen=True)
class BCConfig:
    """Behaviour-cloning hyperparameters (defaults: the run reported in docs/human.md)."""

    kind: str = "cnn"  # population ModelConfig kind; only feed-forward 'cnn' (samples are single steps)
    steps: int = 1500
    batch_size: int = 256
    learning_rate: float = 1e-3
    eval_every: int = 500
    seed: int = 0
    selfplay_episodes: int = 16
    max_steps: int = 400  # episode length of the self-play score (ocv2's default)

    def __post_init__(self):
        if self.kind != "cnn":
            raise ValueError(f"BCConfig.kind: only 'cnn' (feed-forward) is supported, got {self.kind!r}")
        for name in ("steps", "batch_size", "eval_every", "selfplay_episodes", "max_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"BCConfig.{name} must be a positive integer, got {value!r}")
        if not self.learning_rate > 0:
            raise ValueError(f"BCConfig.learning_rate must be > 0, got {self.learning_rate!r}")

    @property
    def model(self) -> ModelConfig:
        return ModelConfig(kind=self.kind, **MODEL_DEFAULTS[self.kind])


class BCData(NamedTuple):
    obs: np.ndarray  # [S, H, W, C] a seat's default observation of a recorded state
    actions: np.ndarray  # int32[S] the action that seat's human took


class BCResult(NamedTuple):
    params: dict
    model: ModelConfig
    layout: str
    history: list  # [{"step", "loss", "test_accuracy"}] at every eval_every steps
    scores: dict  # test_accuracy, uniform_accuracy, majority_accuracy, train_accuracy, selfplay_return...


def proxy_env(layout: str, max_steps: int = 400) -> ocv2.OvercookedV2:
    """The environment a proxy observes and plays: the layout's default observations, 2019 rules."""
    return ocv2.make(layout, max_steps=max_steps)


def dataset(trials: Sequence[Trial], env: ocv2.OvercookedV2) -> BCData:
    """Both seats' (observation, action) samples of every transition of ``trials`` (one layout)."""
    if not trials:
        raise ValueError("no trials to build a dataset from")
    layouts = sorted({t.layout for t in trials})
    if layouts != [env.layout.name]:
        raise ValueError(f"trials are on {layouts}, the env on {env.layout.name!r}: one layout per dataset")
    observe = jax.jit(jax.vmap(env.get_obs_arrays))
    obs, actions = [], []
    for trial in trials:
        states = jax.tree.map(lambda x: x[:-1], trial.states)
        per_seat = np.asarray(observe(states))  # [T, N, H, W, C]
        obs.append(per_seat.reshape((-1,) + per_seat.shape[2:]))
        actions.append(trial.actions.reshape(-1))
    return BCData(np.concatenate(obs), np.concatenate(actions).astype(np.int32))


def _logits(network: ActorCritic, params, obs: jax.Array) -> jax.Array:
    hidden = network.initial_hidden(obs.shape[0])
    _, logits, _ = network.apply(params, hidden, obs[None], jnp.zeros((1, obs.shape[0]), bool))
    return logits[0]


def _loss(network: ActorCritic, params, obs, actions):
    logits = _logits(network, params, obs)
    return optax.softmax_cross_entropy_with_integer_labels(logits, actions).mean()


def make_train_chunk(network: ActorCritic, optimizer: optax.GradientTransformation, batch_size: int, length: int):
    """A jitted function running ``length`` minibatch steps: (params, opt_state, key, obs, actions) ->
    (params, opt_state, key, mean loss)."""

    def step(carry, _):
        params, opt_state, key, obs, actions = carry
        key, sub = jax.random.split(key)
        index = jax.random.randint(sub, (batch_size,), 0, actions.shape[0])
        loss, grads = jax.value_and_grad(lambda p: _loss(network, p, obs[index], actions[index]))(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state, key, obs, actions), loss

    @jax.jit
    def chunk(params, opt_state, key, obs, actions):
        (params, opt_state, key, _, _), losses = jax.lax.scan(
            step, (params, opt_state, key, obs, actions), None, length=length
        )
        return params, opt_state, key, losses.mean()

    return chunk


def accuracy(network: ActorCritic, params, data: BCData, chunk: int = 4096, exclude_stay: bool = False) -> float:
    """Share of samples whose most likely action is the human's (``exclude_stay``: most likely among
    the five non-stay actions)."""
    mask = jnp.where(jnp.arange(it.NUM_ACTIONS) == int(Action.STAY), -jnp.inf, 0.0) if exclude_stay else 0.0
    predict = jax.jit(lambda p, o: jnp.argmax(_logits(network, p, o) + mask, axis=-1))
    hits = 0
    for start in range(0, len(data.actions), chunk):
        predicted = np.asarray(predict(params, jnp.asarray(data.obs[start : start + chunk])))
        hits += int((predicted == data.actions[start : start + chunk]).sum())
    return hits / max(len(data.actions), 1)


def _active(data: BCData) -> BCData:
    keep = data.actions != int(Action.STAY)
    return BCData(data.obs[keep], data.actions[keep])


def baselines(train: BCData, test: BCData) -> dict:
    """Held-out accuracy of a uniform policy (1/6) and of always playing the training majority action."""
    counts = np.bincount(train.actions, minlength=it.NUM_ACTIONS)
    majority = int(counts.argmax())
    active = test.actions[test.actions != int(Action.STAY)]
    counts[int(Action.STAY)] = -1
    return {
        "uniform_accuracy": 1.0 / it.NUM_ACTIONS,
        "majority_action": majority,
        "majority_accuracy": float((test.actions == majority).mean()),
        "active_share": float((test.actions != int(Action.STAY)).mean()),
        # among non-stay samples: uniform over the five, and the training split's commonest non-stay action
        "active_uniform_accuracy": 1.0 / (it.NUM_ACTIONS - 1),
        "active_majority_accuracy": float((active == int(counts.argmax())).mean()) if len(active) else 0.0,
    }


def selfplay_return(network: ActorCritic, params, env: ocv2.OvercookedV2, key: jax.Array, episodes: int) -> float:
    """Mean team return (20 per soup) of the proxy in both seats, sampled actions, from the layout start."""
    returns = jax.jit(lambda k: play_episodes(network.apply, 0, env, (params, params), k, episodes).returns)(key)
    return float(np.mean(np.asarray(returns)))


def train(config: BCConfig, train_trials: Sequence[Trial], test_trials: Sequence[Trial], log=None) -> BCResult:
    """Fit the proxy on ``train_trials`` and score it on ``test_trials`` (all on one layout)."""
    layout = train_trials[0].layout if train_trials else "?"
    env = proxy_env(layout, config.max_steps)
    train_data, test_data = dataset(train_trials, env), dataset(test_trials, env)
    model = config.model
    network = make_network(model, it.NUM_ACTIONS)
    key = jax.random.PRNGKey(config.seed)
    key, init_key, play_key = jax.random.split(key, 3)
    params = init_params(network, init_key, train_data.obs.shape[1:])
    optimizer = optax.adam(config.learning_rate)
    opt_state = optimizer.init(params)
    obs, actions = jnp.asarray(train_data.obs), jnp.asarray(train_data.actions)
    history, done = [], 0
    chunks = {}
    while done < config.steps:
        length = min(config.eval_every, config.steps - done)
        if length not in chunks:
            chunks[length] = make_train_chunk(network, optimizer, config.batch_size, length)
        params, opt_state, key, loss = chunks[length](params, opt_state, key, obs, actions)
        done += length
        entry = {"step": done, "loss": float(loss), "test_accuracy": accuracy(network, params, test_data)}
        history.append(entry)
        if log is not None:
            log(entry)
    scores = {
        "train_samples": int(len(train_data.actions)),
        "test_samples": int(len(test_data.actions)),
        "train_accuracy": accuracy(network, params, train_data),
        "test_accuracy": history[-1]["test_accuracy"],
        # STAY dominates the recordings (the game ticks faster than people press keys), and whether a
        # person presses a key on this tick is mostly not in the state; so also: given the person
        # acted, does the proxy's most likely non-stay action match?
        "test_accuracy_active": accuracy(network, params, _active(test_data), exclude_stay=True),
        **baselines(train_data, test_data),
        "selfplay_return": selfplay_return(network, params, env, play_key, config.selfplay_episodes),
        "selfplay_episodes": config.selfplay_episodes,
        "selfplay_max_steps": config.max_steps,
    }
    return BCResult(params, model, layout, history, scores)


# ---------------------------------------------------------------------------------------------------
# Saving and loading a proxy: an ordinary exported policy (population.policy) marked as a human proxy
# ---------------------------------------------------------------------------------------------------


def save_proxy(path, result: BCResult, config: BCConfig, meta: dict | None = None) -> Path:
    """Export the proxy with ``population.policy.export``: ``policy.load`` (and so ``ocv2 xp``) reads it;
    its ``meta`` holds ``kind: human-proxy``, the layout, the BC settings, scores and history."""
    info = {
        "name": f"human-proxy:{result.layout}",
        "kind": PROXY_KIND,
        "layout": result.layout,
        "bc": dataclasses.asdict(config),
        "scores": result.scores,
        "history": result.history,
        **(meta or {}),
    }
    return policy.export(
        path,
        params=result.params,
        model=result.model,
        env={"layout": result.layout, "max_steps": config.max_steps},
        meta=info,
    )


def load_proxy(path) -> policy.Policy:
    """A proxy file as a ``population.policy.Policy``; ``PolicyError`` (a ValueError) naming the file if
    it is not a policy, or a policy that is not a human proxy."""
    loaded = policy.load(path)
    if loaded.meta.get("kind") != PROXY_KIND:
        raise policy.PolicyError(f"{path}: an ocv2 policy, but not a human proxy (made by `ocv2 human proxy`)")
    return loaded
