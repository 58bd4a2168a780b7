"""Cross-play: every ordered pair of K policies (diagonal included), E episodes each, team sparse return.

``cross_play`` returns the per-episode returns [K, K, E] (row = seat 0, column = seat 1), optionally
handing every transition to a callback (the trajectory archive);
``summarize`` turns them into the paper's numbers: SP = mean of the diagonal cells, XP = mean of the
off-diagonal cells, each +- the std across cells, the gap SP - XP, 95 % confidence intervals and a
per-recipe breakdown. Every pair uses the same episode keys (common random numbers), so differences
between cells come from the policies, not from luck of the draw.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from population.evaluation import PolicyApply, gather_params, play_pairs


@dataclasses.dataclass(frozen=True)
class CrossPlay:
    returns: np.ndarray  # float32[K, K, E]
    start_recipe: np.ndarray  # int32[K, K, E] recipe encoding at each episode's start

    @property
    def matrix(self) -> np.ndarray:
        return self.returns.mean(axis=-1)


EPISODE_BLOCK = 64  # episodes per pair per jitted call: bounds memory when every transition is kept


def episode_blocks(episodes: int, block: int = EPISODE_BLOCK) -> tuple[int, int]:
    """(number of blocks, episodes per block): as few equal blocks of at most ``block`` as cover ``episodes``."""
    count = math.ceil(episodes / block)
    return count, math.ceil(episodes / count)


def cross_play(apply: PolicyApply, hidden_size: int, env, params, key: jax.Array, episodes: int,
               rows=None, on_block=None) -> CrossPlay:
    """Evaluate all ordered pairs of the K stacked ``params`` (or only the given seat-0 ``rows``).

    One jitted call per row and block of episodes (K pairs x at most 64 episodes) bounds memory; block
    b uses ``fold_in(key, b)`` for every pair. ``on_block(row, first_episode, recorded)``: if given,
    every transition is kept (``population.record``, the same episodes) and handed over per block,
    ``recorded`` trimmed to the episodes that count -- how the trajectory archive gets every scored
    episode. Returns are the same with or without it.
    """
    num = jax.tree.leaves(params)[0].shape[0]
    rows = range(num) if rows is None else rows
    count, size = episode_blocks(episodes)
    if on_block is None:
        play = _jitted_play(apply, hidden_size, env, size)
    else:
        from population.record import jitted_play_recorded_pairs

        play = jitted_play_recorded_pairs(apply, hidden_size, env, size)
    returns = np.full((num, num, episodes), np.nan, np.float32)
    recipes = np.zeros((num, num, episodes), np.int32)
    for i in rows:
        seat0 = gather_params(params, [i] * num)
        for block in range(count):
            first, n = block * size, min(size, episodes - block * size)
            keys = jnp.stack([jax.random.fold_in(key, block)] * num)  # common random numbers across pairs
            result = jax.device_get(play(seat0, params, keys))
            if on_block is None:
                block_returns, block_recipes = result.returns, result.start_recipe
            else:
                result = jax.tree.map(lambda x: x[:, :n], result)
                block_returns, block_recipes = result.returns, result.states.recipe[:, :, 0]
                on_block(i, first, result)
            returns[i, :, first:first + n] = np.asarray(block_returns)[:, :n]
            recipes[i, :, first:first + n] = np.asarray(block_recipes)[:, :n]
    return CrossPlay(returns, recipes)


@functools.lru_cache(maxsize=16)
def _jitted_play(apply, hidden_size, env, episodes):
    return jax.jit(lambda a, b, k: play_pairs(apply, hidden_size, env, a, b, k, episodes))


def _mean_std_ci(values: np.ndarray):
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return math.nan, math.nan, math.nan
    std = float(values.std(ddof=1)) if values.size > 1 else 0.0
    return float(values.mean()), std, 1.96 * std / math.sqrt(values.size)


def summarize(result: CrossPlay, recipe_names: dict[int, str] | None = None) -> dict:
    """Paper-style summary. Keys: sp_mean, sp_std, xp_mean, xp_std, gap, sp_ci95, xp_ci95,
    num_policies, episodes_per_pair, per_recipe {name: {sp_mean, xp_mean, episodes}}.

    Std and CI are across cells (policies for SP, ordered pairs for XP), as the paper's tables.
    """
    matrix = result.matrix
    num = matrix.shape[0]
    diagonal = np.eye(num, dtype=bool)
    sp_mean, sp_std, sp_ci = _mean_std_ci(matrix[diagonal])
    xp_mean, xp_std, xp_ci = _mean_std_ci(matrix[~diagonal])
    per_recipe = {}
    for code in np.unique(result.start_recipe):
        name = (recipe_names or {}).get(int(code), str(int(code)))
        mask = result.start_recipe == code
        sp_cells = [result.returns[i, i][mask[i, i]].mean() for i in range(num) if mask[i, i].any()]
        xp_cells = [result.returns[i, j][mask[i, j]].mean() for i in range(num) for j in range(num)
                    if i != j and mask[i, j].any()]
        per_recipe[name] = {"sp_mean": _mean_std_ci(sp_cells)[0], "xp_mean": _mean_std_ci(xp_cells)[0],
                            "episodes": int(mask.sum())}
    return {
        "sp_mean": sp_mean, "sp_std": sp_std, "xp_mean": xp_mean, "xp_std": xp_std,
        "gap": sp_mean - xp_mean if num > 1 else math.nan,
        "sp_ci95": sp_ci, "xp_ci95": xp_ci,
        "num_policies": num, "episodes_per_pair": int(result.returns.shape[-1]),
        "per_recipe": per_recipe,
    }


def recipe_names(env) -> dict[int, str]:
    """Recipe encoding -> readable name ("0+0+1") for a layout's possible recipes."""
    from ocv2.items import recipe_encoding_np

    return {recipe_encoding_np(r): "+".join(str(i) for i in r) for r in env.layout.possible_recipes}
