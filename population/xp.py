"""Cross-play: every ordered pair of K policies (diagonal included), E episodes each, team sparse return.

``cross_play`` returns the per-episode returns [K, K, E] (row = seat 0, column = seat 1), optionally
handing every transition to a callback (the trajectory archive); with ``partners`` the columns are
another group of policies (another run, another network), giving a rectangular [K, C, E] block.
``summarize`` turns a population's matrix into the paper's numbers: SP = mean of the diagonal cells,
XP = mean of the off-diagonal cells, each +- the std across cells, the gap SP - XP, 95 % confidence
intervals and a per-recipe breakdown. Every pair uses the same episode keys (common random numbers),
so differences between cells come from the policies, not from luck of the draw.

Confidence intervals come from a bootstrap over seeds (``bootstrap_block``; ``bootstrap_difference`` for
one population's numbers minus another's, ``paired_difference`` for the same seeds at two points of their
training, and ``summary_difference`` for the reports' Δ rows built on the first):
the training seeds are the independent samples, while the cells of one matrix share policies and are not
independent, so resampling cells (or a normal interval over cells) claims too much certainty.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import jax
import numpy as np

from ocv2.items import recipe_encoding_np
from population.evaluation import PolicyApply, play_row
from population.record import jitted_play_recorded_row

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0  # fixed: the same matrix always gives the same interval


@dataclasses.dataclass(frozen=True)
class CrossPlay:
    returns: np.ndarray  # float32[K, K, E]
    start_recipe: np.ndarray  # int32[K, K, E] recipe encoding at each episode's start

    @property
    def matrix(self) -> np.ndarray:
        return self.returns.mean(axis=-1)


class Side(NamedTuple):
    """K policies that share one network: ``apply``, its hidden size, params stacked on a leading [K] axis."""

    apply: Any
    hidden_size: int
    params: Any


EPISODE_BLOCK = 64  # episodes per pair per jitted call: bounds memory when every transition is kept


def episode_blocks(episodes: int, block: int = EPISODE_BLOCK) -> tuple[int, int]:
    """(number of blocks, episodes per block): as few equal blocks of at most ``block`` as cover ``episodes``."""
    count = math.ceil(episodes / block)
    return count, math.ceil(episodes / count)


def cross_play(
    apply: PolicyApply,
    hidden_size: int,
    env,
    params,
    key: jax.Array,
    episodes: int,
    rows=None,
    on_block=None,
    partners: Side | None = None,
    greedy: bool = False,
    on_progress=None,
) -> CrossPlay:
    """Evaluate all ordered pairs of the K stacked ``params`` (or only the given seat-0 ``rows``).

    One jitted call per row and block of episodes (C pairs x at most 64 episodes) bounds memory; block
    b uses ``fold_in(key, b)`` for every pair. ``on_block(row, first_episode, recorded)``: if given,
    every transition is kept (``population.record``, the same episodes) and handed over per block,
    ``recorded`` trimmed to the episodes that count -- how the trajectory archive gets every scored
    episode. Returns are the same with or without it.

    ``partners``: the seat-1 policies (default: the same K); the result is then [K, C, E]. With
    ``greedy`` both seats take their most likely action instead of sampling one.
    ``on_progress(done, total)``: called with 0 first, then after each block (``done`` blocks more).
    """
    num = jax.tree.leaves(params)[0].shape[0]
    rows = range(num) if rows is None else rows
    if partners is None:
        cols, seat_apply, seat_hidden = params, apply, hidden_size
    else:
        cols, seat_apply, seat_hidden = partners.params, (apply, partners.apply), (hidden_size, partners.hidden_size)
    num_cols = jax.tree.leaves(cols)[0].shape[0]
    count, size = episode_blocks(episodes)
    if on_block is None:
        play = _jitted_play(seat_apply, seat_hidden, env, size, greedy)
    elif greedy:
        raise ValueError("cross_play: recording (on_block) plays sampled actions only")
    else:
        play = jitted_play_recorded_row(seat_apply, seat_hidden, env, size)
    returns = np.full((num, num_cols, episodes), np.nan, np.float32)
    recipes = np.zeros((num, num_cols, episodes), np.int32)
    if on_progress is not None:
        on_progress(0, len(rows) * count)
    for i in rows:
        seat0 = jax.tree.map(lambda x: x[i], params)  # shared by the row's pairs, not copied per pair
        for block in range(count):
            first, n = block * size, min(size, episodes - block * size)
            block_key = jax.random.fold_in(key, block)  # common random numbers: one key for every pair
            result = jax.device_get(play(seat0, cols, block_key))
            if on_block is None:
                block_returns, block_recipes = result.returns, result.start_recipe
            else:
                result = jax.tree.map(lambda x: x[:, :n], result)
                block_returns, block_recipes = result.returns, result.states.recipe[:, :, 0]
                on_block(i, first, result)
            returns[i, :, first : first + n] = np.asarray(block_returns)[:, :n]
            recipes[i, :, first : first + n] = np.asarray(block_recipes)[:, :n]
            if on_progress is not None:
                on_progress(1, len(rows) * count)
    return CrossPlay(returns, recipes)


@functools.lru_cache(maxsize=16)
def _jitted_play(apply, hidden_size, env, episodes, greedy=False):
    return jax.jit(lambda a, b, k: play_row(apply, hidden_size, env, a, b, k, episodes, greedy=greedy))


def _mean_std(values: np.ndarray) -> tuple[float, float]:
    values = np.asarray(values, np.float64)
    if values.size == 0:
        return math.nan, math.nan
    return float(values.mean()), float(values.std(ddof=1)) if values.size > 1 else 0.0


def _interval(samples: np.ndarray) -> tuple[float, float]:
    """The central 95 % of bootstrap ``samples`` (NaN where a resample had nothing to average)."""
    samples = samples[~np.isnan(samples)]
    if samples.size == 0:
        return math.nan, math.nan
    low, high = np.percentile(samples, [2.5, 97.5])
    return float(low), float(high)


def _resample_chunks(cells: int, resamples: int):
    """Resample counts per chunk so that a chunk's gathered [B, R, C] stays near 2M numbers."""
    per = max(1, 2_000_000 // max(cells, 1))
    return [min(per, resamples - start) for start in range(0, resamples, per)]


def bootstrap_samples(
    matrix: np.ndarray, row_ids=None, col_ids=None, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED
) -> tuple[np.ndarray, np.ndarray]:
    """The SP and XP means of ``resamples`` bootstrap resamples of the seeds of a [R, C] matrix (NaN where a
    resample has no cell of that kind), as two [resamples] arrays.

    ``row_ids``/``col_ids`` name the policy of each row/column (default: rows and columns are the same
    K policies, as in one population's matrix). A cell is self-play when its two policies are the same
    policy, cross-play otherwise. When rows and columns are the same policies, one resample of the
    seeds serves both sides (a seed drawn twice does not cross-play with itself); otherwise rows and
    columns are resampled independently.
    """
    matrix = np.asarray(matrix, np.float64)
    rows, cols = matrix.shape
    row_ids = list(range(rows)) if row_ids is None else list(row_ids)
    col_ids = list(range(cols)) if col_ids is None else list(col_ids)
    shared = row_ids == col_ids
    codes = {name: index for index, name in enumerate(dict.fromkeys(row_ids + col_ids))}
    row_code, col_code = np.asarray([codes[r] for r in row_ids]), np.asarray([codes[c] for c in col_ids])
    rng = np.random.default_rng(seed)
    sp, xp = [], []
    for size in _resample_chunks(rows * cols, resamples):
        ri = rng.integers(0, rows, size=(size, rows))
        ci = ri if shared else rng.integers(0, cols, size=(size, cols))
        cells = matrix[ri[:, :, None], ci[:, None, :]]
        same = row_code[ri][:, :, None] == col_code[ci][:, None, :]
        for mask, out in ((same, sp), (~same, xp)):
            count = mask.sum(axis=(1, 2))
            total = np.where(mask, cells, 0.0).sum(axis=(1, 2))
            out.append(np.where(count > 0, total / np.maximum(count, 1), np.nan))
    return np.concatenate(sp), np.concatenate(xp)


def bootstrap_block(
    matrix: np.ndarray, row_ids=None, col_ids=None, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED
) -> dict:
    """95 % percentile intervals of the SP and XP means of a [R, C] matrix by bootstrap over seeds
    (``bootstrap_samples`` says how a resample is drawn). Returns {"sp": (low, high), "xp": (low, high),
    "gap": (low, high)}."""
    sp, xp = bootstrap_samples(matrix, row_ids, col_ids, resamples, seed)
    return {"sp": _interval(sp), "xp": _interval(xp), "gap": _interval(sp - xp)}


def bootstrap_difference(
    base: np.ndarray,
    other: np.ndarray,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    names: tuple[str, str] = ("base", "other"),
) -> dict:
    """95 % intervals of ``other``'s SP, XP and gap minus ``base``'s, for two populations' own square
    matrices (say SP's and SA's, each of its own independently seeded policies).

    The two populations share no seed, so each is resampled on its own (``base`` with ``seed``, ``other``
    with ``seed + 1``) and the k-th resamples are subtracted: the interval of Table 1's "Gap (delta)" that
    the two per-population intervals cannot give (their overlap says little about the difference).
    Returns {"sp": (low, high), "xp": (low, high), "gap": (low, high)}. ``ValueError`` for a matrix that is
    not square (rows lost from a file) or holds a cell that is not a number: either would give an interval
    of other resamples than it says, without a word (``names`` name the two in the message).
    """
    for name, matrix in zip(names, (base, other), strict=True):
        _check_population(name, matrix)
    base_sp, base_xp = bootstrap_samples(base, resamples=resamples, seed=seed)
    other_sp, other_xp = bootstrap_samples(other, resamples=resamples, seed=seed + 1)
    return _difference_intervals(base_sp, base_xp, other_sp, other_xp)


def paired_difference(
    before: np.ndarray,
    after: np.ndarray,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    names: tuple[str, str] = ("before", "after"),
) -> dict:
    """95 % intervals of ``after``'s SP, XP and gap minus ``before``'s, for two K x K matrices of the *same*
    seeds (say one population at 3M and, trained on, at 6M: row k of both is seed k).

    Each resample draws one set of seed indices and uses it in both matrices, so what a seed contributes
    cancels where it stayed the same; ``bootstrap_difference`` (for populations that share no seed) would
    add both populations' spread. Returns {"sp": (low, high), "xp": (low, high), "gap": (low, high)}.
    ``ValueError`` for a matrix that is not square or not all numbers, or two of different sizes (they
    cannot be the same seeds)."""
    for name, matrix in zip(names, (before, after), strict=True):
        _check_population(name, matrix)
    if np.shape(before) != np.shape(after):
        raise ValueError(
            f"{names[0]} has {np.shape(before)[0]} seeds and {names[1]} {np.shape(after)[0]}: not the same seeds"
        )
    before_sp, before_xp = bootstrap_samples(before, resamples=resamples, seed=seed)
    after_sp, after_xp = bootstrap_samples(after, resamples=resamples, seed=seed)  # the same draws
    return _difference_intervals(before_sp, before_xp, after_sp, after_xp)


def _check_population(name: str, matrix) -> None:
    """``ValueError`` naming ``name`` unless ``matrix`` is one population's K x K (K >= 2) matrix of numbers: a
    cut or holed matrix would give an interval over other resamples than it says, without a word."""
    matrix = np.asarray(matrix, np.float64)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or matrix.shape[0] < 2:
        raise ValueError(f"{name}: a {' x '.join(map(str, matrix.shape))} matrix, not one population's K x K (K >= 2)")
    if not np.isfinite(matrix).all():
        raise ValueError(f"{name}: {int((~np.isfinite(matrix)).sum())} cell(s) are not numbers")


def _difference_intervals(base_sp, base_xp, other_sp, other_xp) -> dict:
    return {
        "sp": _interval(other_sp - base_sp),
        "xp": _interval(other_xp - base_xp),
        "gap": _interval((other_sp - other_xp) - (base_sp - base_xp)),
    }


class Difference(NamedTuple):
    """One population's summary numbers minus a baseline population's (say SA's minus SP's)."""

    sp: float
    xp: float
    gap: float
    gap_interval: tuple[float, float]  # 95 %, both populations' seeds resampled; NaNs where there is none
    problem: str  # why there is no interval; "" when there is one


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):  # None or "" (nothing measured): no number
        return math.nan


def summary_difference(
    base: dict, other: dict, base_matrix, other_matrix, names: tuple[str, str] = ("base", "other")
) -> Difference:
    """``other``'s SP, XP and gap minus ``base``'s, from two ``summarize`` results (``sp_mean``, ``xp_mean``,
    ``gap``), and the gap's interval from the two matrices by ``bootstrap_difference``. A matrix that is
    None, not square or not all numbers gives NaNs and the reason in ``problem`` (``names`` name the two in
    it), never an interval over other resamples than it says."""
    sp, xp, gap = (_number(other.get(key)) - _number(base.get(key)) for key in ("sp_mean", "xp_mean", "gap"))
    missing = [name for name, matrix in zip(names, (base_matrix, other_matrix), strict=True) if matrix is None]
    if missing:
        return Difference(sp, xp, gap, (math.nan, math.nan), "no " + " and no ".join(missing))
    try:
        interval = bootstrap_difference(np.asarray(base_matrix), np.asarray(other_matrix), names=names)["gap"]
    except ValueError as error:
        return Difference(sp, xp, gap, (math.nan, math.nan), str(error))
    return Difference(sp, xp, gap, interval, "")


def block_summary(matrix: np.ndarray, row_ids, col_ids) -> dict:
    """SP/XP means, std across cells and seed-bootstrap 95 % intervals of one [R, C] block; the gap
    SP - XP with ``gap_std``, the std across row policies of each one's own gap (its SP cell minus the
    mean of its XP cells)."""
    matrix = np.asarray(matrix, np.float64)
    same = np.asarray(row_ids)[:, None] == np.asarray(col_ids)[None, :]
    sp_mean, sp_std = _mean_std(matrix[same])
    xp_mean, xp_std = _mean_std(matrix[~same])
    ci = bootstrap_block(matrix, row_ids, col_ids)
    own_gaps = [
        matrix[i][same[i]].mean() - matrix[i][~same[i]].mean()
        for i in range(matrix.shape[0])
        if same[i].any() and (~same[i]).any()
    ]
    return {
        "sp_mean": sp_mean,
        "sp_std": sp_std,
        "xp_mean": xp_mean,
        "xp_std": xp_std,
        "gap": sp_mean - xp_mean if same.any() and (~same).any() else math.nan,
        "gap_std": _mean_std(own_gaps)[1],
        "sp_ci95_interval": list(ci["sp"]),
        "xp_ci95_interval": list(ci["xp"]),
        "gap_ci95_interval": list(ci["gap"]),
        "rows": len(row_ids),
        "cols": len(col_ids),
    }


def _half_width(interval) -> float:
    return (interval[1] - interval[0]) / 2


def summarize(result: CrossPlay, recipe_names: dict[int, str] | None = None) -> dict:
    """Paper-style summary. Keys: sp_mean, sp_std, xp_mean, xp_std, gap, gap_std, sp_ci95, xp_ci95,
    sp_ci95_interval, xp_ci95_interval, gap_ci95_interval, ci_method, num_policies, episodes_per_pair,
    per_recipe {name: {sp_mean, xp_mean, episodes}}.

    Std is across cells (policies for SP, ordered pairs for XP), as the paper's tables. The 95 %
    intervals are a percentile bootstrap over seeds (``bootstrap_block``); ``sp_ci95``/``xp_ci95`` are
    their half-widths.
    """
    matrix = result.matrix
    num = matrix.shape[0]
    ids = list(range(num))
    block = block_summary(matrix, ids, ids)
    per_recipe = {}
    for code in np.unique(result.start_recipe):
        name = (recipe_names or {}).get(int(code), str(int(code)))
        mask = result.start_recipe == code
        sp_cells = [result.returns[i, i][mask[i, i]].mean() for i in range(num) if mask[i, i].any()]
        xp_cells = [
            result.returns[i, j][mask[i, j]].mean()
            for i in range(num)
            for j in range(num)
            if i != j and mask[i, j].any()
        ]
        per_recipe[name] = {
            "sp_mean": _mean_std(sp_cells)[0],
            "xp_mean": _mean_std(xp_cells)[0],
            "episodes": int(mask.sum()),
        }
    return {
        "sp_mean": block["sp_mean"],
        "sp_std": block["sp_std"],
        "xp_mean": block["xp_mean"],
        "xp_std": block["xp_std"],
        "gap": block["gap"] if num > 1 else math.nan,
        "gap_std": block["gap_std"],
        "sp_ci95": _half_width(block["sp_ci95_interval"]),
        "xp_ci95": _half_width(block["xp_ci95_interval"]),
        "sp_ci95_interval": block["sp_ci95_interval"],
        "xp_ci95_interval": block["xp_ci95_interval"],
        "gap_ci95_interval": block["gap_ci95_interval"],
        "ci_method": f"95% percentile bootstrap over seeds ({BOOTSTRAP_RESAMPLES} resamples)",
        "num_policies": num,
        "episodes_per_pair": int(result.returns.shape[-1]),
        "per_recipe": per_recipe,
    }


def recipe_names(env) -> dict[int, str]:
    """Recipe encoding -> readable name ("0+0+1") for a layout's possible recipes."""
    return {recipe_encoding_np(r): "+".join(str(i) for i in r) for r in env.layout.possible_recipes}
