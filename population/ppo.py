"""Independent PPO with parameters shared across seats, as pure functions over a ``TrainState`` pytree.

One PPO serves every method; the methods are switches, not copies:

- SP: every seat of every environment is a learner actor (B = num_envs x num_agents sequences).
- SA: SP whose environments reset from a state buffer passed to ``advance`` (traced, so a new buffer
  does not recompile).
- OP: SP on an environment built with per-agent ingredient permutations (``population.op``).
- FCP: one learner seat per environment (B = num_envs); the other seat is played by a frozen pool
  member, redrawn at every episode end, with environments grouped by partner (``population.fcp``).

Shapes: T = ppo.num_steps, E = ppo.num_envs, N = agents, B = learner sequences. ``advance(trainer,
state, n)`` runs n updates in one ``lax.scan``; ``advance_upto`` runs a traced number of them (one program
for every chunk length of a run); a population is ``jax.vmap`` of either over seeds.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

import ocv2
from ocv2.items import recipe_encoding_np
from ocv2.state import State
from population.config import Config
from population.keys import derive_key
from population.networks import ActorCritic, init_params, make_network

# ---------------------------------------------------------------------------------------------------
# containers
# ---------------------------------------------------------------------------------------------------


class Transition(NamedTuple):
    """One rollout step of the learner sequences; every field is [T, B, ...] once stacked."""

    obs: jax.Array  # uint8[..., H, W, C]
    action: jax.Array  # int32
    log_prob: jax.Array  # float32, of the action under the rollout policy
    value: jax.Array  # float32, critic estimate at obs
    reward: jax.Array  # float32, sparse + annealed shaped reward
    reset: jax.Array  # bool, an episode starts at this step (pre-step done): the RNN reset flag
    terminal: jax.Array  # bool, this step ended the episode (post-step done): GAE cut


@struct.dataclass
class EpisodeStats:
    """Per-environment episode bookkeeping for the metrics (no effect on learning)."""

    sparse: jax.Array  # float32[E] running team sparse return of the current episode
    shaped: jax.Array  # float32[E] running shaped return (mean over learner seats)
    recipe: jax.Array  # int32[E] index of the recipe the current episode started with
    last_sparse: jax.Array  # float32[E] return of the last finished episode (NaN before the first)
    last_shaped: jax.Array  # float32[E]
    last_recipe: jax.Array  # int32[E]
    finished: jax.Array  # int32[] episodes finished during the current update


@struct.dataclass
class PartnerState:
    """FCP: which pool member plays the other seat of each environment, and its GRU carry."""

    slot: jax.Array  # int32[E] distinct slots in [0, K*G); partner = slot // G
    learner_seat: jax.Array  # int32[E] the learner's agent index in this episode
    hidden: jax.Array  # float32[E, H] partner carry


@struct.dataclass
class TrainState:
    """Everything needed to continue training one seed bit for bit."""

    params: dict
    opt_state: optax.OptState
    env_state: State  # batched [E]
    obs: jax.Array  # uint8[E, N, H, W, C]
    start: jax.Array  # bool[E] the next step is an episode's first (pre-step done)
    hidden: jax.Array  # float32[B, H] learner carry
    key: jax.Array
    update: jax.Array  # int32[] updates done so far
    stats: EpisodeStats
    partner: PartnerState | None = None


class LossInfo(NamedTuple):
    total: jax.Array
    actor: jax.Array
    value: jax.Array
    entropy: jax.Array
    approx_kl: jax.Array
    clip_frac: jax.Array


class UpdateMetrics(NamedTuple):
    """Scalars per update (arrays [n] from ``advance``; [S, n] for a population)."""

    update: jax.Array
    env_steps: jax.Array  # environment steps done after this update
    sparse_return: jax.Array  # mean over environments of the last finished episode's team return
    shaped_return: jax.Array
    episodes: jax.Array  # episodes finished during this update
    recipe_returns: jax.Array  # [R] mean last return by the episode's starting recipe (NaN: none yet)
    lr: jax.Array
    shaping_coef: jax.Array
    loss: LossInfo


# ---------------------------------------------------------------------------------------------------
# the static part: env, network, optimizer, schedules
# ---------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Trainer:
    """Static context of a run (hashed by identity, so jit caches per Trainer)."""

    config: Config
    env: ocv2.OvercookedV2
    network: ActorCritic
    optimizer: optax.GradientTransformation
    lr_schedule: optax.Schedule
    recipe_codes: jax.Array  # int32[R] encodings of the layout's possible recipes

    @property
    def fcp(self) -> bool:
        """One learner seat per env, the other played by partners from a pool (FCP)."""
        return self.config.population.traits.one_learner_seat

    @property
    def num_sequences(self) -> int:
        ppo = self.config.ppo
        return ppo.num_envs if self.fcp else ppo.num_envs * self.env.num_agents


# Cached: env objects compare by identity, and the jitted rollouts of population.sa/xp/record are
# cached per env, so a fresh env per call would recompile them at every SA iteration or XP row block.
@functools.lru_cache(maxsize=32)
def train_env(config: Config) -> ocv2.OvercookedV2:
    """The environment learners train in (OP adds per-agent permutations)."""
    kwargs = config.env_kwargs
    if config.population.traits.permuted_train_env:
        kwargs["op_ingredient_permutations"] = list(config.population.op.ingredients)
    return ocv2.make(**kwargs)


@functools.lru_cache(maxsize=32)
def eval_env(config: Config) -> ocv2.OvercookedV2:
    """The environment populations are evaluated and SA states collected in (never permuted)."""
    return ocv2.make(**config.env_kwargs)


def lr_schedule(config: Config) -> optax.Schedule:
    """Linear warm-up from 0 to lr over ``lr_warmup`` of all optimizer steps, then cosine to 0 (over the
    schedule's steps: a truncated run follows the first part of the longer run's schedule)."""
    ppo = config.ppo
    total = ppo.schedule_updates * ppo.update_epochs * ppo.num_minibatches
    if not ppo.anneal_lr:
        return optax.constant_schedule(ppo.lr)
    warmup = int(ppo.lr_warmup * total)
    return optax.warmup_cosine_decay_schedule(
        0.0, ppo.lr, warmup_steps=warmup, decay_steps=max(total, warmup + 1), end_value=0.0
    )


def shaping_coef(config: Config, env_steps) -> jax.Array:
    """Weight of the shaped reward: 1 -> 0 linearly over ``rew_shaping_horizon`` environment steps."""
    horizon = config.ppo.rew_shaping_horizon
    if horizon == 0:
        return jnp.float32(0.0)
    return jnp.clip(1.0 - jnp.asarray(env_steps, jnp.float32) / horizon, 0.0, 1.0)


# Cached, and so are the run drivers' programs built from a Trainer below (init, SA's restart, the training
# chunk; each keyed by the Trainer's identity): a process that trains a config again (a study's retrain, a
# test that trains twice to compare) reuses the traced and compiled programs instead of tracing, lowering
# and compiling them anew. JAX's persistent cache skips only the last of the three; tracing and lowering
# a PPO chunk take seconds on a CPU. Few entries: each holds compiled programs, and a process rarely
# trains more than a couple of configs in turn. (Cross-play and SA's collection were cached already, per
# env and network.)
_PROGRAMS_KEPT = 8


@functools.lru_cache(maxsize=_PROGRAMS_KEPT)
def make_trainer(config: Config) -> Trainer:
    """The static context of a run of ``config`` (the same object for an equal config while it is cached)."""
    env = train_env(config)
    schedule = lr_schedule(config)
    optimizer = optax.chain(optax.clip_by_global_norm(config.ppo.max_grad_norm), optax.adam(schedule, eps=1e-5))
    codes = jnp.asarray([recipe_encoding_np(r) for r in env.layout.possible_recipes], jnp.int32)
    return Trainer(
        config, env, make_network(config.model, env.num_actions, config.ppo.activation), optimizer, schedule, codes
    )


def seed_key(config: Config, index: int) -> jax.Array:
    """Seed ``index`` of a population: independent of how many seeds train beside it."""
    return derive_key(config.population.seed, "seed", index)


# ---------------------------------------------------------------------------------------------------
# initialisation
# ---------------------------------------------------------------------------------------------------


def _recipe_index(trainer: Trainer, recipe: jax.Array) -> jax.Array:
    return jnp.argmax(recipe[..., None] == trainer.recipe_codes, axis=-1).astype(jnp.int32)


def reset_envs(trainer: Trainer, key: jax.Array, buffer: State | None = None):
    """Fresh environments: (env_state [E], obs [E, N, ...]); the key is consumed."""
    keys = jax.random.split(key, trainer.config.ppo.num_envs)
    states = jax.vmap(trainer.env.reset_state, in_axes=(0, None))(keys, buffer)
    return states, jax.vmap(trainer.env.get_obs_arrays)(states)


def _draw_partners(trainer: Trainer, key: jax.Array, pool_size: int):
    """A random assignment of environments to distinct pool slots (uniform partner per env) and seats."""
    num_envs = trainer.config.ppo.num_envs
    group = -(-num_envs // pool_size)
    k_slot, k_seat = jax.random.split(key)
    slot = jax.random.permutation(k_slot, pool_size * group)[:num_envs].astype(jnp.int32)
    seat = jax.random.randint(k_seat, (num_envs,), 0, trainer.env.num_agents, jnp.int32)
    return slot, seat


def init_train_state(trainer: Trainer, key: jax.Array, buffer: State | None = None, pool_size: int = 0) -> TrainState:
    """A new seed: fresh network, optimizer and environments. The key is consumed."""
    k_params, k_env, k_partner, key = jax.random.split(key, 4)
    params = init_params(trainer.network, k_params, trainer.env.obs_shape)
    env_state, obs = reset_envs(trainer, k_env, buffer)
    num_envs = trainer.config.ppo.num_envs
    partner = None
    if trainer.fcp:
        if pool_size < 1:
            raise ValueError("FCP needs a partner pool: pass pool_size >= 1")
        slot, seat = _draw_partners(trainer, k_partner, pool_size)
        partner = PartnerState(slot, seat, trainer.network.initial_hidden(num_envs))
    nan = jnp.full((num_envs,), jnp.nan, jnp.float32)
    zeros = jnp.zeros((num_envs,), jnp.float32)
    recipe = _recipe_index(trainer, env_state.recipe)
    stats = EpisodeStats(zeros, zeros, recipe, nan, nan, recipe, jnp.int32(0))
    return TrainState(
        params,
        trainer.optimizer.init(params),
        env_state,
        obs,
        jnp.ones((num_envs,), bool),
        trainer.network.initial_hidden(trainer.num_sequences),
        key,
        jnp.int32(0),
        stats,
        partner,
    )


def restart_episodes(trainer: Trainer, state: TrainState, key: jax.Array, buffer: State | None = None) -> TrainState:
    """Start new episodes everywhere (SA does this after each new buffer); learning state is kept."""
    env_state, obs = reset_envs(trainer, key, buffer)
    stats = state.stats.replace(
        sparse=jnp.zeros_like(state.stats.sparse),
        shaped=jnp.zeros_like(state.stats.shaped),
        recipe=_recipe_index(trainer, env_state.recipe),
    )
    partner = state.partner
    if partner is not None:
        partner = partner.replace(hidden=jnp.zeros_like(partner.hidden))
    return state.replace(
        env_state=env_state,
        obs=obs,
        start=jnp.ones_like(state.start),
        hidden=jnp.zeros_like(state.hidden),
        stats=stats,
        partner=partner,
    )


# ---------------------------------------------------------------------------------------------------
# acting
# ---------------------------------------------------------------------------------------------------


def sample_actions(key: jax.Array, logits: jax.Array):
    """Categorical sample and its log-probability. logits [..., A] -> (int32[...], float32[...])."""
    action = jax.random.categorical(key, logits).astype(jnp.int32)
    log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], axis=-1)[..., 0]
    return action, log_prob


def learner_view(trainer: Trainer, state: TrainState):
    """The learner sequences' observations [B, ...] and reset flags [B] for the next step."""
    if trainer.fcp:
        rows = jnp.arange(state.obs.shape[0])
        return state.obs[rows, state.partner.learner_seat], state.start
    num_agents = trainer.env.num_agents
    return state.obs.reshape((-1,) + state.obs.shape[2:]), jnp.repeat(state.start, num_agents)


def partner_actions(
    network: ActorCritic, pool_params, partner: PartnerState, obs: jax.Array, start: jax.Array, key: jax.Array
):
    """Actions of the frozen partners, computed per pool member on its group of environments.

    Environments are scattered into [K, G] slots (K pool members, G = ceil(E/K) slots each), so each
    member runs once on a batch of G: parameter memory is O(K), never one copy per environment.
    Returns (actions int32[E], new hidden [E, H]).
    """
    pool_size = jax.tree.leaves(pool_params)[0].shape[0]
    num_envs = obs.shape[0]
    group = -(-num_envs // pool_size)
    slots = pool_size * group
    rows = jnp.arange(num_envs)
    partner_obs = obs[rows, 1 - partner.learner_seat]

    def scatter(x, fill=0):
        out = jnp.full((slots,) + x.shape[1:], fill, x.dtype).at[partner.slot].set(x)
        return out.reshape((pool_size, group) + x.shape[1:])

    hidden, logits, _ = jax.vmap(network.apply)(
        pool_params, scatter(partner.hidden), scatter(partner_obs)[:, None], scatter(start, True)[:, None]
    )
    actions = jax.random.categorical(key, logits[:, 0]).astype(jnp.int32)  # independent noise per slot
    actions = actions.reshape(slots)[partner.slot]
    hidden = hidden.reshape((slots,) + hidden.shape[2:])[partner.slot]
    return actions, hidden


class StepCarry(NamedTuple):
    state: TrainState
    shaping: jax.Array  # float32[] shaped-reward weight of this update


def rollout_step(trainer: Trainer, pool_params, buffer, carry: StepCarry, _unused):
    """One environment step of every learner sequence; returns the new carry and a ``Transition``."""
    state = carry.state
    key, k_act, k_env, k_partner, k_draw = jax.random.split(state.key, 5)
    obs, reset = learner_view(trainer, state)
    hidden, logits, value = trainer.network.apply(state.params, state.hidden, obs[None], reset[None])
    action, log_prob = sample_actions(k_act, logits[0])
    num_envs, num_agents = state.obs.shape[:2]
    partner = state.partner
    if trainer.fcp:
        other, partner_hidden = partner_actions(
            trainer.network, pool_params, partner, state.obs, state.start, k_partner
        )
        seat = partner.learner_seat
        joint = jnp.where(seat[:, None] == jnp.arange(num_agents), action[:, None], other[:, None])
    else:
        joint = action.reshape(num_envs, num_agents)
    keys = jax.random.split(k_env, num_envs)
    out = jax.vmap(trainer.env.step_arrays, in_axes=(0, 0, 0, None, None))(keys, state.env_state, joint, None, buffer)
    sparse = out.reward[:, 0]
    if trainer.fcp:
        shaped = out.shaped_reward[jnp.arange(num_envs), partner.learner_seat]
        reward = sparse + carry.shaping * shaped
        terminal = out.done
    else:
        shaped = out.shaped_reward.mean(axis=1)
        reward = (sparse[:, None] + carry.shaping * out.shaped_reward).reshape(-1)
        terminal = jnp.repeat(out.done, num_agents)
    transition = Transition(obs, action, log_prob, value[0], reward, reset, terminal)
    stats = _track_episodes(trainer, state.stats, sparse, shaped, out.done, out.state)
    if trainer.fcp:
        # Episodes are time-limited and start together, so every environment ends on the same step:
        # the whole assignment is redrawn at once and slots stay distinct.
        pool_size = jax.tree.leaves(pool_params)[0].shape[0]
        slot, seat = _draw_partners(trainer, k_draw, pool_size)
        redraw = out.done.all()
        partner = PartnerState(
            jnp.where(redraw, slot, partner.slot), jnp.where(redraw, seat, partner.learner_seat), partner_hidden
        )
    state = state.replace(
        env_state=out.state, obs=out.obs, start=out.done, hidden=hidden, key=key, stats=stats, partner=partner
    )
    return StepCarry(state, carry.shaping), transition


def _track_episodes(trainer: Trainer, stats: EpisodeStats, sparse, shaped, done, next_state) -> EpisodeStats:
    ep_sparse = stats.sparse + sparse
    ep_shaped = stats.shaped + shaped
    return EpisodeStats(
        sparse=jnp.where(done, 0.0, ep_sparse),
        shaped=jnp.where(done, 0.0, ep_shaped),
        recipe=jnp.where(done, _recipe_index(trainer, next_state.recipe), stats.recipe),
        last_sparse=jnp.where(done, ep_sparse, stats.last_sparse),
        last_shaped=jnp.where(done, ep_shaped, stats.last_shaped),
        last_recipe=jnp.where(done, stats.recipe, stats.last_recipe),
        finished=stats.finished + done.sum(dtype=jnp.int32),
    )


# ---------------------------------------------------------------------------------------------------
# learning
# ---------------------------------------------------------------------------------------------------


def compute_gae(rewards, values, terminals, last_value, gamma: float, gae_lambda: float):
    """Generalised advantage estimation over [T, B]; no bootstrap across a terminal step.

    Returns (advantages [T, B], value targets [T, B]).
    """

    def backward(carry, step):
        gae, next_value = carry
        reward, value, terminal = step
        not_done = 1.0 - terminal.astype(jnp.float32)
        delta = reward + gamma * next_value * not_done - value
        gae = delta + gamma * gae_lambda * not_done * gae
        return (gae, value), gae

    init = (jnp.zeros_like(last_value), last_value)
    _, advantages = jax.lax.scan(backward, init, (rewards, values, terminals), reverse=True)
    return advantages, advantages + values


def replay_reset(config: Config, batch: Transition) -> jax.Array:
    """The RNN reset flags used when replaying a stored sequence in the update.

    Correct: the pre-step done the rollout used. ``ppo.paper_done_bug`` reproduces the paper code,
    which replayed with the post-step done (resetting one step early at every episode boundary).
    """
    return batch.terminal if config.ppo.paper_done_bug else batch.reset


def ppo_loss(trainer: Trainer, params, hidden, batch: Transition, advantages, targets):
    """Clipped-surrogate PPO loss on whole sequences [T, b] starting from ``hidden`` [b, H]."""
    ppo = trainer.config.ppo
    _, logits, value = trainer.network.apply(params, hidden, batch.obs, replay_reset(trainer.config, batch))
    log_probs = jax.nn.log_softmax(logits)
    log_prob = jnp.take_along_axis(log_probs, batch.action[..., None], axis=-1)[..., 0]
    log_ratio = log_prob - batch.log_prob
    ratio = jnp.exp(log_ratio)
    adv = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    actor = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - ppo.clip_eps, 1 + ppo.clip_eps) * adv).mean()
    value_clipped = batch.value + jnp.clip(value - batch.value, -ppo.clip_eps, ppo.clip_eps)
    value_loss = 0.5 * jnp.maximum(jnp.square(value - targets), jnp.square(value_clipped - targets)).mean()
    entropy = -(jnp.exp(log_probs) * log_probs).sum(-1).mean()
    total = actor + ppo.vf_coef * value_loss - ppo.ent_coef * entropy
    info = LossInfo(
        total, actor, value_loss, entropy, ((ratio - 1) - log_ratio).mean(), (jnp.abs(ratio - 1) > ppo.clip_eps).mean()
    )
    return total, info


class Batch(NamedTuple):
    """One update's training data over B sequences."""

    hidden: jax.Array  # [B, H] learner carry at the rollout's first step
    transitions: Transition  # [T, B, ...]
    advantages: jax.Array  # [T, B]
    targets: jax.Array  # [T, B]


def split_minibatches(batch: Batch, permutation: jax.Array, num_minibatches: int) -> Batch:
    """Shuffle the B sequences and cut them into [M, ...] minibatches of whole sequences."""

    def along_time(x):  # [T, B, ...] -> [M, T, B/M, ...]
        x = jnp.take(x, permutation, axis=1)
        x = x.reshape((x.shape[0], num_minibatches, -1) + x.shape[2:])
        return jnp.swapaxes(x, 0, 1)

    hidden = jnp.take(batch.hidden, permutation, axis=0)
    hidden = hidden.reshape((num_minibatches, hidden.shape[0] // num_minibatches) + hidden.shape[1:])
    return Batch(
        hidden, jax.tree.map(along_time, batch.transitions), along_time(batch.advantages), along_time(batch.targets)
    )


class OptCarry(NamedTuple):
    params: dict
    opt_state: optax.OptState


def minibatch_step(trainer: Trainer, carry: OptCarry, minibatch: Batch):
    grad_fn = jax.value_and_grad(ppo_loss, argnums=1, has_aux=True)
    (_, info), grads = grad_fn(
        trainer, carry.params, minibatch.hidden, minibatch.transitions, minibatch.advantages, minibatch.targets
    )
    updates, opt_state = trainer.optimizer.update(grads, carry.opt_state, carry.params)
    return OptCarry(optax.apply_updates(carry.params, updates), opt_state), info


def update_epoch(trainer: Trainer, batch: Batch, carry: tuple, _unused):
    opt, key = carry
    key, k_perm = jax.random.split(key)
    permutation = jax.random.permutation(k_perm, batch.hidden.shape[0])
    minibatches = split_minibatches(batch, permutation, trainer.config.ppo.num_minibatches)
    opt, infos = jax.lax.scan(lambda c, mb: minibatch_step(trainer, c, mb), opt, minibatches)
    return (opt, key), infos


def update_step(trainer: Trainer, pool_params, buffer, state: TrainState, _unused):
    """Collect T steps, compute GAE, run the PPO epochs. Returns (state, UpdateMetrics)."""
    ppo = trainer.config.ppo
    env_steps_before = state.update * ppo.steps_per_update
    coef = shaping_coef(trainer.config, env_steps_before)
    initial_hidden = state.hidden
    state = state.replace(stats=state.stats.replace(finished=jnp.int32(0)))
    step = lambda c, x: rollout_step(trainer, pool_params, buffer, c, x)
    carry, transitions = jax.lax.scan(step, StepCarry(state, coef), None, length=ppo.num_steps)
    state = carry.state
    obs, reset = learner_view(trainer, state)
    _, _, last_value = trainer.network.apply(state.params, state.hidden, obs[None], reset[None])
    advantages, targets = compute_gae(
        transitions.reward, transitions.value, transitions.terminal, last_value[0], ppo.gamma, ppo.gae_lambda
    )
    batch = Batch(initial_hidden, transitions, advantages, targets)
    key, k_epochs = jax.random.split(state.key)
    epoch = lambda c, x: update_epoch(trainer, batch, c, x)
    (opt, _), infos = jax.lax.scan(
        epoch, (OptCarry(state.params, state.opt_state), k_epochs), None, length=ppo.update_epochs
    )
    lr = trainer.lr_schedule(state.update * ppo.update_epochs * ppo.num_minibatches)
    state = state.replace(params=opt.params, opt_state=opt.opt_state, key=key, update=state.update + 1)
    metrics = UpdateMetrics(
        update=state.update,
        env_steps=state.update * ppo.steps_per_update,
        sparse_return=_nanmean(state.stats.last_sparse),
        shaped_return=_nanmean(state.stats.last_shaped),
        episodes=state.stats.finished,
        recipe_returns=_returns_by_recipe(trainer, state.stats),
        lr=jnp.asarray(lr, jnp.float32),
        shaping_coef=coef,
        loss=jax.tree.map(jnp.mean, infos),
    )
    return state, metrics


def _nanmean(x):
    valid = ~jnp.isnan(x)
    return jnp.where(valid.any(), jnp.where(valid, x, 0.0).sum() / jnp.maximum(valid.sum(), 1), jnp.nan)


def _returns_by_recipe(trainer: Trainer, stats: EpisodeStats):
    match = stats.last_recipe[:, None] == jnp.arange(trainer.recipe_codes.shape[0])
    valid = match & ~jnp.isnan(stats.last_sparse)[:, None]
    total = jnp.where(valid, stats.last_sparse[:, None], 0.0).sum(0)
    count = valid.sum(0)
    return jnp.where(count > 0, total / jnp.maximum(count, 1), jnp.nan)


def advance(trainer: Trainer, state: TrainState, num_updates: int, buffer: State | None = None, pool_params=None):
    """Run ``num_updates`` PPO updates (one ``lax.scan``). Returns (state, UpdateMetrics with leading [n])."""
    step = lambda s, x: update_step(trainer, pool_params, buffer, s, x)
    return jax.lax.scan(step, state, None, length=num_updates)


def advance_upto(
    trainer: Trainer,
    state: TrainState,
    count: jax.Array,
    max_updates: int,
    buffer: State | None = None,
    pool_params=None,
):
    """Run ``count`` PPO updates, ``count`` traced (0 <= count <= ``max_updates``, static).

    The same updates as ``advance(trainer, state, count)`` -- each ``update_step`` draws its keys from
    the state it is given, so the key flow does not depend on the loop -- in a ``lax.fori_loop`` whose
    trip count is an argument: every count up to ``max_updates`` runs one compiled program. Returns
    (state, UpdateMetrics with leading [max_updates]): row i holds update i of this call for i < count;
    the rows after ``count`` are zeros, to be dropped by the caller. A count above ``max_updates``
    cannot be reported from inside the program (its extra rows would overwrite the last one): callers
    check it on the host.
    """
    template = jax.eval_shape(lambda s: update_step(trainer, pool_params, buffer, s, None)[1], state)
    rows = jax.tree.map(lambda x: jnp.zeros((max_updates,) + x.shape, x.dtype), template)

    def body(i, carry):
        state, rows = carry
        state, metrics = update_step(trainer, pool_params, buffer, state, None)
        rows = jax.tree.map(lambda buf, x: jax.lax.dynamic_update_index_in_dim(buf, x, i, 0), rows, metrics)
        return state, rows

    return jax.lax.fori_loop(0, count, body, (state, rows))


# ---------------------------------------------------------------------------------------------------
# populations: seeds on a leading vmap axis
# ---------------------------------------------------------------------------------------------------


def init_population(trainer: Trainer, seeds, buffer: State | None = None, pool_size: int = 0) -> TrainState:
    """TrainStates of the given seed indices stacked on a leading axis (S)."""
    # One jitted init per seed, then stacked: XLA:CPU (jax 0.10.2) deadlocks running a vmapped flax
    # init of these networks, and per-seed init makes "alone == in a batch" hold by construction.
    init = _init_program(trainer, pool_size)
    states = [init(seed_key(trainer.config, int(i)), buffer) for i in seeds]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)


@functools.lru_cache(maxsize=_PROGRAMS_KEPT)
def _init_program(trainer: Trainer, pool_size: int):
    return jax.jit(lambda k, b: init_train_state(trainer, k, b, pool_size))


@functools.lru_cache(maxsize=_PROGRAMS_KEPT)
def make_restart_population(trainer: Trainer):
    """A jitted ``(states [S], keys [S], buffer) -> states``: ``restart_episodes`` of every seed."""
    return jax.jit(jax.vmap(lambda s, k, b: restart_episodes(trainer, s, k, b), in_axes=(0, 0, None)))


def make_advance_population(trainer: Trainer, num_updates: int, pool_per_seed: bool = False):
    """A jitted ``(states [S], buffer, pool) -> (states, metrics [S, n])`` for a whole population.

    The buffer is shared by all seeds; the pool is shared unless ``pool_per_seed`` (one pool per
    FCP learner, leading axis S).
    """

    def run(states, buffer, pool_params):
        return advance(trainer, states, num_updates, buffer, pool_params)

    return jax.jit(jax.vmap(run, in_axes=(0, None, 0 if pool_per_seed else None)), donate_argnums=(0,))


def make_advance_chunks(trainer: Trainer, max_updates: int, pool_per_seed: bool = False):
    """A jitted ``(states [S], buffer, pool, count) -> (states, metrics [S, max_updates])``: ``count``
    updates of every seed (``advance_upto``), one compiled program for every ``count <= max_updates``.

    What the run drivers train with (``cluster.runtime.shard``): a run stops at checkpoints, snapshots
    and SA iteration starts, so its chunks have many lengths (1 to 50 in a Coordination Ring SA run),
    and ``make_advance_population`` would compile a program per length (seconds each on a CPU, tens
    of seconds on a GPU). ``count`` is an int32 scalar shared by all seeds; metrics rows ``[:, count:]``
    are padding. Buffer and pool as ``make_advance_population``.
    """
    if max_updates < 1:
        raise ValueError(f"max_updates must be at least 1, got {max_updates}")
    return _advance_chunks_program(trainer, int(max_updates), bool(pool_per_seed))  # one key however it is called


@functools.lru_cache(maxsize=_PROGRAMS_KEPT)
def _advance_chunks_program(trainer: Trainer, max_updates: int, pool_per_seed: bool):
    def run(states, buffer, pool_params, count):
        return advance_upto(trainer, states, count, max_updates, buffer, pool_params)

    return jax.jit(jax.vmap(run, in_axes=(0, None, 0 if pool_per_seed else None, None)), donate_argnums=(0,))


def clear_program_caches() -> None:
    """Forget the cached trainers and the programs built from them, so the next use traces afresh (what a
    test that counts traces, or swaps a function the programs call, needs)."""
    for cached in _CACHED:
        cached.cache_clear()


# The cached functions themselves, not looked up by name when cleared: a test may have swapped a name.
_CACHED = (make_trainer, _init_program, make_restart_population, _advance_chunks_program)


def take_seed(tree, index: int):
    """One seed's slice of a population pytree."""
    return jax.tree.map(lambda x: x[index], tree)


__all__ = [
    "Batch",
    "EpisodeStats",
    "LossInfo",
    "PartnerState",
    "Trainer",
    "TrainState",
    "Transition",
    "UpdateMetrics",
    "advance",
    "advance_upto",
    "clear_program_caches",
    "compute_gae",
    "eval_env",
    "init_population",
    "init_train_state",
    "learner_view",
    "lr_schedule",
    "make_advance_chunks",
    "make_advance_population",
    "make_restart_population",
    "make_trainer",
    "partner_actions",
    "ppo_loss",
    "replay_reset",
    "reset_envs",
    "restart_episodes",
    "rollout_step",
    "sample_actions",
    "seed_key",
    "shaping_coef",
    "split_minibatches",
    "take_seed",
    "train_env",
    "update_step",
]
