"""Cross-run cross-play: policies of several runs (or single checkpoints, exported files) in a rows x cols matrix.

A *source* is anything ``population.policy.load`` reads, plus ``human-proxy:LAYOUT``: a run directory
contributes every seed (at the chosen checkpoint), a seed directory / checkpoint / exported file one
policy. Each source is a ``PolicyGroup``: its policies share one network, so a job -- one seat-0
policy against every policy of one column group -- is one vmapped, jitted program
(``population.xp.cross_play``). Jobs go to workers in blocks (``spread_jobs``); the workers
are in-process (``LocalPlayers``) or Ray actors (``RayPlayers``, which reuse the Ray backend's
retrying ``call``). Every cell uses the same episode keys whatever worker plays it, and a row group
playing against itself goes through exactly the in-run cross-play code, so ``--rows RUN --cols RUN``
reproduces ``ocv2 xp RUN``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cluster.runtime.jobs import InProcessWorkers, spread_jobs
from cluster.runtime.ray_backend import RayWorkers, actor_env, connect, ray
from cluster.runtime.rundir import write_csv, write_json
from population.config import ClusterConfig, Config, ConfigError, ModelConfig, load_config
from population.evaluation import stack_params
from population.human import proxy_path
from population.keys import derive_key
from population.plots import xp_heatmap
from population.policy import PolicyError, hidden_size_of, load, network, policy_env
from population.xp import Side, block_summary, cross_play, recipe_names

HUMAN_PROXY = "human-proxy:"


class CrossPlayError(ValueError):
    """A cross-play request that cannot run (bad source, policies of different environments, ...)."""


@dataclasses.dataclass(frozen=True, eq=False)
class PolicyGroup:
    """Policies of one source sharing one network; ``params`` stacked [K] (numpy)."""

    label: str  # the source as given
    names: tuple[str, ...]  # one per policy, e.g. "sp_run/seed_3"
    ids: tuple[str, ...]  # content hash of each policy (network + params): equal ids = the same policy
    model: ModelConfig
    activation: str
    env: dict
    params: Any
    method: str | None = None  # the run's population method, when known
    seed: int | None = None  # the run's population seed, when known

    @property
    def spec(self) -> tuple:
        """What a worker needs to rebuild the group's network (cheap to ship; params go separately)."""
        return self.model, self.activation, self.env


# ---------------------------------------------------------------------------------------------------
# sources
# ---------------------------------------------------------------------------------------------------

def resolve_source(text: str, checkpoint="final") -> PolicyGroup:
    """A column/row spec -> its policies. Errors name the spec."""
    if text.startswith(HUMAN_PROXY):
        return _single(text, _human_proxy_path(text[len(HUMAN_PROXY):]), "final")
    path = Path(text)
    if path.is_dir() and (path / "config.yaml").is_file():
        return _run_group(text, path, checkpoint)
    return _single(text, path, checkpoint if path.is_dir() else "final")  # a file is one fixed policy


def _human_proxy_path(layout: str) -> Path:
    try:
        return Path(proxy_path(layout))
    except (ValueError, LookupError, OSError) as error:
        raise CrossPlayError(f"{HUMAN_PROXY}{layout}: {error}") from None


def _run_group(text: str, path: Path, checkpoint) -> PolicyGroup:
    try:
        config = load_config(path / "config.yaml")
    except ConfigError as error:
        raise CrossPlayError(str(error)) from None
    policies = [_load(text, path, checkpoint, seed) for seed in range(config.population.num_seeds)]
    first = policies[0]
    return PolicyGroup(text, tuple(f"{path.name}/seed_{i}" for i in range(len(policies))),
                       tuple(policy_id(p) for p in policies), first.model, first.activation,
                       first.env, stack_params([jax.tree.map(np.asarray, p.params) for p in policies]),
                       config.population.method, config.population.seed)


def _single(text: str, path: Path, checkpoint) -> PolicyGroup:
    policy = _load(text, path, checkpoint)
    meta = policy.meta
    return PolicyGroup(text, (policy.name,), (policy_id(policy),), policy.model, policy.activation,
                       policy.env, stack_params([jax.tree.map(np.asarray, policy.params)]), meta.get("method"))


def policy_id(policy) -> str:
    """A content hash: an exported copy of a run's checkpoint is the same policy as the checkpoint."""
    digest = hashlib.sha256(repr((policy.model, policy.activation)).encode())
    for leaf in jax.tree.leaves(policy.params):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return digest.hexdigest()[:16]


def _load(text, path, checkpoint, seed=None):
    try:
        return load(path, seed=seed, checkpoint=checkpoint)
    except PolicyError as error:
        message = str(error)
        raise CrossPlayError(message if str(path) in message else f"{text}: {message}") from None


def check_same_env(groups) -> dict:
    """All policies must play the same environment; returns its ``ocv2.make`` kwargs."""
    first = groups[0]
    for group in groups[1:]:
        if group.env != first.env:
            differ = sorted(k for k in set(first.env) | set(group.env) if first.env.get(k) != group.env.get(k))
            raise CrossPlayError(f"{group.label} plays another environment than {first.label} (differs in "
                                 f"{', '.join(differ)}: {group.env.get(differ[0])!r} vs {first.env.get(differ[0])!r})")
    return first.env


# ---------------------------------------------------------------------------------------------------
# workers
# ---------------------------------------------------------------------------------------------------

class RowsResult(NamedTuple):
    job: tuple  # (row group, col group, rows)
    returns: np.ndarray  # [len(rows), C, E]
    start_recipe: np.ndarray


class CrossPlayPlayer:
    """Plays jobs: seat-0 ``rows`` of one group against every policy of another group."""

    def play(self, row_spec, row_params, col_spec, col_params, rows, key, episodes: int, greedy: bool,
             job) -> RowsResult:
        env = policy_env(row_spec[2])
        row_side = _side(row_spec, row_params, env)
        if col_spec is None:  # the row group against itself: the in-run code path, numbers included
            result = cross_play(row_side.apply, row_side.hidden_size, env, row_side.params, jnp.asarray(key), episodes,
                                rows=rows, greedy=greedy)
        else:
            result = cross_play(row_side.apply, row_side.hidden_size, env, row_side.params, jnp.asarray(key), episodes,
                                rows=rows, partners=_side(col_spec, col_params, env), greedy=greedy)
        rows = list(rows)
        return RowsResult(job, result.returns[rows], result.start_recipe[rows])

    def position(self) -> int:  # what RayWorkers asks a restarted actor
        return 0

    def ping(self) -> int:
        return os.getpid()


def _side(spec, params, env) -> Side:
    model, activation, _ = spec
    net = network(model, activation, env.num_actions)
    return Side(net.apply, hidden_size_of(model), jax.tree.map(jnp.asarray, params))


class LocalPlayers(InProcessWorkers):
    """One in-process player."""

    def __init__(self):
        super().__init__([[0]], CrossPlayPlayer())


class RayPlayers(RayWorkers):
    """``num_workers`` Ray actors, each a ``CrossPlayPlayer``; ``call``/``share`` are the Ray backend's."""

    def __init__(self, num_workers: int, cluster: ClusterConfig):
        self.config = Config(cluster=cluster)  # RayWorkers.call reads cluster.max_restarts
        self.shards = [[i] for i in range(num_workers)]
        self._pool = None
        options = dict(num_cpus=cluster.num_cpus or 1, max_restarts=cluster.max_restarts, max_task_retries=0,
                       scheduling_strategy="SPREAD", runtime_env={"env_vars": actor_env(cluster)})
        actor = ray.remote(CrossPlayPlayer)
        self.actors = [actor.options(**options).remote() for _ in range(num_workers)]
        self.events = []


def ray_worker_count(requested: int | None, jobs: int, cpus_per_worker: float) -> int:
    available = int(ray.cluster_resources().get("CPU", 1) // max(cpus_per_worker, 1))
    return max(1, min(requested or available, jobs))


@contextmanager
def players(backend: str, jobs: int, address: str | None = None, workers: int | None = None):
    """``LocalPlayers``, or ``RayPlayers`` on the Ray cluster at ``address`` (default: started here and
    shut down afterwards); one worker per CPU unless ``workers``, never more than ``jobs``.
    Raises ``RayBackendError`` when Ray cannot be reached."""
    if backend == "local":
        yield LocalPlayers()
        return
    cluster = ClusterConfig(address=address)
    started = connect(cluster)
    try:
        ray_players = RayPlayers(ray_worker_count(workers, jobs, 1), cluster)
        try:
            yield ray_players
        finally:
            ray_players.close()
    finally:
        if started:
            ray.shutdown()


# ---------------------------------------------------------------------------------------------------
# the matrix
# ---------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Matrix:
    returns: np.ndarray  # float32[R, C, E]
    start_recipe: np.ndarray  # int32[R, C, E]
    row_groups: tuple
    col_groups: tuple

    @property
    def matrix(self) -> np.ndarray:
        return self.returns.mean(axis=-1)


def xp_key(seed: int) -> jax.Array:
    """The episode keys of a cross-play: the XP stream of a population with this seed (as ``ocv2 xp RUN``)."""
    return derive_key(seed, "xp")


def play_matrix(row_groups, col_groups, workers, key, episodes: int, greedy: bool = False, progress=None) -> Matrix:
    """Every row policy against every column policy, ``episodes`` each, spread over ``workers``.

    Jobs (one seat-0 policy x one column group) are handed out in waves of one per worker, so the
    progress bar moves as jobs finish; every job's result is stored by its (group, row) position, so
    a job that ran twice after a worker restart changes nothing.
    """
    check_same_env([*row_groups, *col_groups])
    row_offsets, col_offsets = _offsets(row_groups), _offsets(col_groups)
    num_rows, num_cols = row_offsets[-1], col_offsets[-1]
    returns = np.full((num_rows, num_cols, episodes), np.nan, np.float32)
    recipes = np.zeros((num_rows, num_cols, episodes), np.int32)
    row_params = [workers.share(g.params) for g in row_groups]
    col_params = [workers.share(g.params) for g in col_groups]
    items = [(r, c, i) for r, group in enumerate(row_groups) for c in range(len(col_groups))
             for i in range(len(group.names))]
    jobs = []
    for shard, block in spread_jobs(workers, items, lambda block: block):  # consecutive blocks, one per worker
        for r, c, i in block:
            same = row_groups[r].ids == col_groups[c].ids and row_groups[r].spec == col_groups[c].spec
            jobs.append((shard, (row_groups[r].spec, row_params[r], None if same else col_groups[c].spec,
                                 None if same else col_params[c], [i], np.asarray(key), episodes, greedy, (r, c, i))))
    # A wave holds at most one job per worker (consecutive blocks interleaved), then the bar moves.
    by_shard = [[job for job in jobs if job[0] == s] for s in range(len(workers.shards))]
    waves = [[queue[w] for queue in by_shard if w < len(queue)] for w in range(max(map(len, by_shard), default=0))]
    if progress is not None:
        progress(0, len(jobs))
    for wave in waves:
        for part in workers.call("play", wave):
            r, c, i = part.job
            row = row_offsets[r] + i
            cols = slice(col_offsets[c], col_offsets[c + 1])
            returns[row, cols], recipes[row, cols] = part.returns[0], part.start_recipe[0]
        if progress is not None:
            progress(len(wave), len(jobs))
    if np.isnan(returns).any():
        raise RuntimeError("cross-play: some pairs were not evaluated")
    return Matrix(returns, recipes, tuple(row_groups), tuple(col_groups))


def _offsets(groups) -> list[int]:
    offsets = [0]
    for group in groups:
        offsets.append(offsets[-1] + len(group.names))
    return offsets


def summarize_matrix(result: Matrix) -> dict:
    """One entry per (row source, column source) block: SP/XP means, std across cells, seed-bootstrap CIs."""
    row_offsets, col_offsets = _offsets(result.row_groups), _offsets(result.col_groups)
    matrix = result.matrix
    blocks = []
    for r, rg in enumerate(result.row_groups):
        for c, cg in enumerate(result.col_groups):
            cells = matrix[row_offsets[r]:row_offsets[r + 1], col_offsets[c]:col_offsets[c + 1]]
            entry = {"rows": rg.label, "cols": cg.label, "row_method": rg.method, "col_method": cg.method}
            entry.update(block_summary(cells, list(rg.ids), list(cg.ids)))
            entry["rows"], entry["cols"] = rg.label, cg.label
            entry["num_rows"], entry["num_cols"] = len(rg.ids), len(cg.ids)
            blocks.append(entry)
    return {"num_rows": int(matrix.shape[0]), "num_cols": int(matrix.shape[1]),
            "episodes_per_pair": int(result.returns.shape[-1]),
            "ci_method": "95% percentile bootstrap over seeds (rows and columns resampled by policy)",
            "blocks": blocks}


def write_outputs(result: Matrix, out, summary: dict, env) -> dict:
    """matrix.csv, episodes.csv, blocks.csv, summary.json, heatmap.png (+ blocks.png) under ``out``."""
    out = Path(out)
    rows = [n for g in result.row_groups for n in g.names]
    cols = [n for g in result.col_groups for n in g.names]
    matrix = result.matrix
    names = recipe_names(env)
    write_csv(out / "matrix.csv", ["seat0\\seat1"] + cols,
              [[rows[i]] + [round(float(v), 4) for v in matrix[i]] for i in range(len(rows))])
    write_csv(out / "episodes.csv", ["seat0", "seat1", "episode", "return", "start_recipe"],
              [[rows[i], cols[j], e, float(result.returns[i, j, e]), names.get(int(result.start_recipe[i, j, e]), "")]
               for i in range(len(rows)) for j in range(len(cols)) for e in range(result.returns.shape[-1])])
    fields = ["rows", "cols", "row_method", "col_method", "num_rows", "num_cols", "sp_mean", "sp_std", "xp_mean",
              "xp_std", "gap", "xp_ci95_low", "xp_ci95_high", "sp_ci95_low", "sp_ci95_high"]
    write_csv(out / "blocks.csv", fields,
              [[b["rows"], b["cols"], b["row_method"] or "", b["col_method"] or "", b["num_rows"], b["num_cols"],
                *(_round(b[k]) for k in ("sp_mean", "sp_std", "xp_mean", "xp_std", "gap")),
                *(_round(v) for v in b["xp_ci95_interval"]), *(_round(v) for v in b["sp_ci95_interval"])]
               for b in summary["blocks"]])
    write_json(out / "summary.json", summary)
    episodes = result.returns.shape[-1]
    xp_heatmap(matrix, out / "heatmap.png", labels=rows, col_labels=cols,
               title=f"cross-play, {episodes} episodes/pair")
    paths = {"matrix": str(out / "matrix.csv"), "summary": str(out / "summary.json")}
    if len(result.row_groups) > 1 or len(result.col_groups) > 1:
        block_means = np.asarray([b["xp_mean"] for b in summary["blocks"]], np.float64)  # row-source major
        block_means = block_means.reshape(len(result.row_groups), len(result.col_groups))
        xp_heatmap(block_means, out / "blocks.png", labels=[_short(g) for g in result.row_groups],
                   col_labels=[_short(g) for g in result.col_groups], title="mean cross-play return by source")
    return paths


def _short(group: PolicyGroup) -> str:
    name = Path(group.label.rstrip("/")).name or group.label
    return f"{name} ({group.method})" if group.method else name


def _round(value) -> float | str:
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else round(float(value), 4)
