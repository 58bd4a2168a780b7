"""PPO learns: a small CNN on Cramped Room earns several times what uniformly random play earns, in under a
minute on 2 cores.

The return is the team's training return per 50-step episode: the sparse delivery reward plus the shaped
reward (onion into pot, plate and soup picked up; averaged over the two cooks), the quantity the metrics
report as ``sparse_return + shaped_return``. The shaping weight stays 1 (no annealing) so that this is
the quantity being maximised throughout. Random play is measured here with the same episode length and
the same sum, over more episodes than the learner plays per update.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from population import ppo
from population.config import parse_config

EPISODE = 50
# 16 environments x 50 steps each: 32,000 environment steps. The learner passes the bar below by update
# ~20 and ends at ~7.7 (random: ~0.2); fewer updates only make the test stricter about learning speed.
UPDATES = 40
CONFIG = {
    "env": {"layout": "cramped_room", "max_steps": EPISODE},
    "model": {"kind": "cnn", "conv_features": [16, 16], "conv_kernels": [3, 3], "fc_dim": 32},
    "ppo": {
        "num_envs": 16,
        "num_steps": EPISODE,
        "num_minibatches": 4,
        "update_epochs": 4,
        "lr": 1e-3,
        "anneal_lr": False,
        "ent_coef": 0.01,
        "max_grad_norm": 0.5,
        "total_timesteps": 16 * EPISODE * UPDATES,
        "rew_shaping_horizon": 2**30,
    },
}


def random_return(env, key: jax.Array, episodes: int = 256) -> float:
    """Mean team return (sparse + agent-mean shaped) of uniformly random joint actions over whole episodes."""

    def episode(key):
        k_reset, k_steps = jax.random.split(key)

        def step(carry, key):
            state, total = carry
            k_act, k_env = jax.random.split(key)
            out = env.step_arrays(k_env, state, jax.random.randint(k_act, (env.num_agents,), 0, env.num_actions))
            return (out.state, total + out.reward[0] + out.shaped_reward.mean()), None

        (_, total), _ = jax.lax.scan(
            step, (env.reset_state(k_reset), jnp.float32(0)), jax.random.split(k_steps, env.max_steps)
        )
        return total

    return float(jax.jit(jax.vmap(episode))(jax.random.split(key, episodes)).mean())


def test_ppo_beats_random_play_by_a_wide_margin():
    config = parse_config(CONFIG)
    trainer = ppo.make_trainer(config)
    random = random_return(ppo.eval_env(config), jax.random.PRNGKey(1))
    states = ppo.init_population(trainer, [0])
    _, metrics = ppo.make_advance_population(trainer, UPDATES)(states, None, None)
    metrics = ppo.take_seed(metrics, 0)
    learned = np.asarray(metrics.sparse_return + metrics.shaped_return)
    assert np.all(np.isfinite(learned))  # every update ends its 16 episodes (num_steps == max_steps)
    first, last = learned[:3].mean(), learned[-5:].mean()
    # the untrained network plays about as random does; the trained one far better than either
    assert abs(first - random) < 2.0, (first, random)
    assert last > 3 * random + 4.0, (last, random, learned.round(1).tolist())
