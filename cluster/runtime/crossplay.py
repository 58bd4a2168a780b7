"""Cross-run cross-play: policies of several runs (or single checkpoints, exported files) in a rows x cols matrix.

A *source* is anything ``population.policy.load`` reads, plus ``human-proxy:LAYOUT``: a run directory
contributes every seed (at the chosen checkpoint), a seed directory / checkpoint / exported file one
policy. Each source is a ``PolicyGroup``: its policies share one network, so a job -- one seat-0
policy against every policy of one column group, or of neighbouring column groups of one network
(``column_batches``) -- is one vmapped, jitted program (``population.xp.cross_play``). Jobs go to
workers in blocks, wave by wave (``in_waves``); the workers
are in-process (``LocalPlayers``) or Ray actors (``RayPlayers``, which reuse the Ray backend's
retrying ``call``). Every cell uses the same episode keys whatever worker plays it, and a row group
playing against itself goes through exactly the in-run cross-play code, so ``--rows RUN --cols RUN``
reproduces ``ocv2 xp RUN``.

On OvercookedV2 layouts the two seats are different roles, so ``play_seat_fair`` plays both orders
(row policies in seat 0, then column policies in seat 0, with the same episode keys) and reports each
order and their mean (``summarize_seat_fair``); ``play_matrix`` is one order.

Cross-play traces at the matmul precision the runs trained with (``run.precision``, as their in-run cross-play
does; ``played_precision``): on a GPU, JAX's own default would be TF32 for runs trained at float32.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cluster.runtime.jobs import InProcessWorkers, in_waves
from cluster.runtime.ray_backend import RayWorkers, actor_env, ray, session
from cluster.runtime.rundir import write_csv, write_json, write_matrix_csv
from population.config import ClusterConfig, Config, ConfigError, ModelConfig, load_run_config
from population.evaluation import stack_params
from population.human import proxy_path
from population.keys import derive_key
from population.networks import same_function
from population.numerics import DEFAULT_PRECISION, matmul_precision
from population.plots import xp_heatmap
from population.policy import (
    PolicyError,
    env_difference,
    hidden_size_of,
    load,
    network,
    policy_env,
    same_env,
    trained_precision,
)
from population.published import FileCheck, check_file
from population.xp import Side, block_summary, cross_play, recipe_names

log = logging.getLogger(__name__)

HUMAN_PROXY = "human-proxy:"
HUMAN_PROXY_METHOD = "human-proxy"  # the method named for a human-proxy source
SEATS = ("both", "0")  # both seat orders, or the row policies in seat 0 only
ORDERS = ("rows_seat0", "cols_seat0")


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
    precision: str | None = None  # the run's run.precision, when known
    updates: tuple = ()  # the checkpoint update of each policy, None where unknown (empty: none known)
    file: FileCheck | None = None  # a policy file's sha256 and the SHA256SUMS.json beside it, if any (not a run)

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
        layout = text[len(HUMAN_PROXY) :]
        path = _human_proxy_path(layout)
        if not path.exists():
            raise CrossPlayError(
                f"{text}: no human proxy for {layout} on this machine ({path} does not exist); make it with "
                f"'ocv2 human proxy {layout} --source overcooked_ai-1.1.0.tar.gz' (docs/human.md)"
            )
        group = _single(text, path, "final")
        return dataclasses.replace(group, method=HUMAN_PROXY_METHOD)
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
        config = load_run_config(path)
    except ConfigError as error:
        raise CrossPlayError(str(error)) from None
    policies = [_load(text, path, checkpoint, seed) for seed in range(config.population.num_seeds)]
    first = policies[0]
    return PolicyGroup(
        text,
        tuple(f"{path.name}/seed_{i}" for i in range(len(policies))),
        tuple(policy_id(p) for p in policies),
        first.model,
        first.activation,
        first.env,
        stack_params([jax.tree.map(np.asarray, p.params) for p in policies]),
        config.population.method,
        config.population.seed,
        config.run.precision,
        tuple(_update(p) for p in policies),
    )


def _single(text: str, path: Path, checkpoint) -> PolicyGroup:
    file = _checked_file(text, path) if path.is_file() else None  # before loading: a changed file is named as such
    policy = _load(text, path, checkpoint)
    meta = policy.meta
    try:
        precision = trained_precision(policy)
    except PolicyError as error:
        raise CrossPlayError(f"{text}: {error}") from None
    return PolicyGroup(
        text,
        (policy.name,),
        (policy_id(policy),),
        policy.model,
        policy.activation,
        policy.env,
        stack_params([jax.tree.map(np.asarray, policy.params)]),
        meta.get("method"),
        precision=precision,
        updates=(_update(policy),),
        file=file,
    )


def _checked_file(text: str, path: Path) -> FileCheck:
    """``published.check_file``: a file its folder's SHA256SUMS.json lists with other bytes is refused; one that a
    listing beside it does not name is played, with a warning (a published folder lists every file it holds)."""
    try:
        check = check_file(path)
    except PolicyError as error:
        raise _source_error(text, path, error) from None
    if check.listing is not None and not check.listed:
        log.warning("%s: not listed in %s beside it, so not a published file; playing it as it is", text, check.listing)
    return check


def _update(policy) -> int | None:
    """The checkpoint update a policy was saved at: a checkpoint's, or a file exported from one (its meta)."""
    update = policy.meta.get("update")
    return update if isinstance(update, int) and not isinstance(update, bool) and update >= 0 else None


def policy_id(policy) -> str:
    """A content hash: an exported copy of a run's checkpoint is the same policy as the checkpoint."""
    digest = hashlib.sha256(repr((same_function(policy.model), policy.activation)).encode())
    for leaf in jax.tree.leaves(policy.params):
        digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
    return digest.hexdigest()[:16]


def _load(text, path, checkpoint, seed=None):
    try:
        return load(path, seed=seed, checkpoint=checkpoint)
    except PolicyError as error:
        raise _source_error(text, path, error) from None


def _source_error(text: str, path: Path, error: PolicyError) -> CrossPlayError:
    """``error`` about source ``text``, which names it once: prefixed with it unless it already names ``path``."""
    message = str(error)
    return CrossPlayError(message if str(path) in message else f"{text}: {message}")


def refuse_repeated_policies(groups) -> None:
    """``CrossPlayError`` naming both sources when one policy (same network and parameters) is among ``groups``
    twice: a copy of an exported file, or a run and its own checkpoint file, would be its own partner under two
    names, its self-play cells counted as cross-play and the policy counted as two seeds."""
    seen: dict[str, str] = {}
    for group in groups:
        for name, policy in zip(group.names, group.ids):
            if policy in seen:
                raise CrossPlayError(
                    f"{group.label} ({name}) is the same policy as {seen[policy]}; give each policy once"
                )
            seen[policy] = f"{group.label} ({name})"


def check_same_env(groups) -> dict:
    """All policies must play the same environment; returns its ``ocv2.make`` kwargs."""
    first = groups[0]
    for group in groups[1:]:
        if not same_env(group.env, first.env):
            raise CrossPlayError(
                f"{group.label} plays another environment than {first.label} ({env_difference(group.env, first.env)})"
            )
    return first.env


def played_precision(groups, chosen: str | None = None) -> str:
    """The ``run.precision`` cross-play of ``groups`` traces at: ``chosen`` if given, else the one every group
    that knows it trained with (the default, float32, when none does). ``CrossPlayError`` when they differ and
    nothing was chosen (the caller says how to choose): which one the numbers come from must be a decision, not an
    accident of order."""
    if chosen is not None:
        return chosen
    known = {g.label: g.precision for g in groups if g.precision is not None}
    if len(set(known.values())) > 1:
        trained = ", ".join(f"{label}: {precision}" for label, precision in known.items())
        raise CrossPlayError(f"the sources trained at different run.precision ({trained})")
    return next(iter(known.values()), DEFAULT_PRECISION)


# ---------------------------------------------------------------------------------------------------
# workers
# ---------------------------------------------------------------------------------------------------


class RowsResult(NamedTuple):
    job: tuple  # (row group, batch of column groups, row)
    returns: np.ndarray  # [len(rows), C, E]
    start_recipe: np.ndarray


class CrossPlayPlayer:
    """Plays jobs: seat-0 ``rows`` of one group against every policy of another group, traced at ``precision``
    (a ``run.precision`` name)."""

    def __init__(self, precision: str = DEFAULT_PRECISION):
        self.precision = precision

    def play(
        self, row_spec, row_params, col_spec, col_params, rows, key, episodes: int, greedy: bool, job
    ) -> RowsResult:
        with matmul_precision(self.precision):
            return self._play(row_spec, row_params, col_spec, col_params, rows, key, episodes, greedy, job)

    def _play(self, row_spec, row_params, col_spec, col_params, rows, key, episodes, greedy, job) -> RowsResult:
        env = policy_env(row_spec[2])
        row_side = _side(row_spec, row_params, env)
        # No column group: the row group against itself, through the in-run code path (numbers included).
        partners = None if col_spec is None else _side(col_spec, col_params, env)
        result = cross_play(
            row_side.apply,
            row_side.hidden_size,
            env,
            row_side.params,
            jnp.asarray(key),
            episodes,
            rows=rows,
            partners=partners,
            greedy=greedy,
        )
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

    def __init__(self, precision: str = DEFAULT_PRECISION):
        super().__init__([[0]], CrossPlayPlayer(precision))


class RayPlayers(RayWorkers):
    """``num_workers`` Ray actors, each a ``CrossPlayPlayer``; ``call``/``share`` are the Ray backend's."""

    def __init__(self, num_workers: int, cluster: ClusterConfig, precision: str = DEFAULT_PRECISION):
        self.config = Config(cluster=cluster)  # RayWorkers.call reads cluster.max_restarts
        self.shards = [[i] for i in range(num_workers)]
        self._pool = None
        options = dict(
            num_cpus=cluster.num_cpus or 1,
            max_restarts=cluster.max_restarts,
            max_task_retries=0,
            scheduling_strategy="SPREAD",
            runtime_env={"env_vars": actor_env(cluster)},
        )
        actor = ray.remote(CrossPlayPlayer)
        self.actors = [actor.options(**options).remote(precision) for _ in range(num_workers)]
        self.events = []


def ray_worker_count(requested: int | None, jobs: int, cpus_per_worker: float) -> int:
    available = int(ray.cluster_resources().get("CPU", 1) // max(cpus_per_worker, 1))
    return max(1, min(requested or available, jobs))


@contextmanager
def players(
    backend: str,
    jobs: int,
    address: str | None = None,
    workers: int | None = None,
    precision: str = DEFAULT_PRECISION,
):
    """``LocalPlayers``, or ``RayPlayers`` on the Ray cluster at ``address`` (default: started here and
    shut down afterwards); one worker per CPU unless ``workers``, never more than ``jobs``; every player traces
    at ``precision``. Raises ``RayBackendError`` when Ray cannot be reached."""
    if backend == "local":
        yield LocalPlayers(precision)
        return
    cluster = ClusterConfig(address=address)
    with session("ray", cluster):
        ray_players = RayPlayers(ray_worker_count(workers, jobs, 1), cluster, precision)
        try:
            yield ray_players
        finally:
            ray_players.close()


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


#: Most policies one job plays against when it joins column groups (``column_batches``): a bound on one call's batch.
MAX_BATCH_POLICIES = 16


def _same(row_group: PolicyGroup, col_group: PolicyGroup) -> bool:
    """A group against itself: played through the in-run code path (no partners), as a run's own cross-play."""
    return row_group.ids == col_group.ids and row_group.spec == col_group.spec


def column_batches(row_group: PolicyGroup, col_groups, jobs: int = 1) -> list[tuple[int, ...]]:
    """The column groups each job of ``row_group``'s policies plays against, in column order: neighbours of one
    network spec join (up to ``MAX_BATCH_POLICIES`` policies), so that ten exported one-policy files are one job
    per seat-0 policy instead of ten. Every pair gets the same episode keys either way (a block's key is shared by
    all pairs), so the returns do not change: equal on a CPU, tested (a GPU may choose kernels by batch shape).
    On 2 idle CPU cores a Cramped Room row of ten files took 96 % of the time of ten calls once compiled, within
    the rows' spread, and its first row 21 s instead of 28 s (bench/xp_files.py): fewer, larger jobs, not speed.

    A column group of several policies that is ``row_group`` itself stays alone: it keeps the in-run path against
    itself, so ``ocv2 xp --rows RUN`` is the run's own cross-play. A one-policy file joins its neighbours, also in
    its own row: its self-play cell then takes the partners' path, whose returns equal the in-run path's on a CPU
    (tested with an exported seed against its run), and one batch size per matrix means one compiled program.
    Batches are split again while the row group would have fewer than ``jobs`` jobs, its share of the Ray
    workers, so that joining does not leave most of them idle."""

    def alone(group) -> bool:
        return len(group.names) > 1 and _same(row_group, group)

    batches: list[list[int]] = []
    for c, group in enumerate(col_groups):
        last = batches[-1] if batches else None
        joins = (
            last is not None
            and not alone(group)
            and not alone(col_groups[last[0]])
            and col_groups[last[0]].spec == group.spec
            and sum(len(col_groups[k].names) for k in last) + len(group.names) <= MAX_BATCH_POLICIES
        )
        if joins:
            last.append(c)
        else:
            batches.append([c])
    while len(row_group.names) * len(batches) < jobs and max(map(len, batches), default=1) > 1:
        widest = max(range(len(batches)), key=lambda b: len(batches[b]))
        half = len(batches[widest]) // 2
        batches[widest : widest + 1] = [batches[widest][:half], batches[widest][half:]]
    return [tuple(batch) for batch in batches]


def play_matrix(
    row_groups, col_groups, workers, key, episodes: int, greedy: bool = False, progress=None, journal=None
) -> Matrix:
    """Every row policy against every column policy, ``episodes`` each, spread over ``workers``.

    A job plays one seat-0 policy against the policies of one batch of column groups (``column_batches``). Jobs
    are handed out in waves of one per worker, so the progress bar moves as jobs finish; results are stored, and
    counted by ``progress(done, total)``, per (group, row) and column group, so a job that ran twice after a worker
    restart changes nothing. ``journal`` (an ``xp_journal.OrderJournal``) supplies the (row, column group) pieces
    played before a stop, which are not played again, and saves each new one as it finishes.
    """
    check_same_env([*row_groups, *col_groups])
    row_offsets, col_offsets = _offsets(row_groups), _offsets(col_groups)
    num_rows, num_cols = row_offsets[-1], col_offsets[-1]
    returns = np.full((num_rows, num_cols, episodes), np.nan, np.float32)
    recipes = np.zeros((num_rows, num_cols, episodes), np.int32)
    row_params = [workers.share(g.params) for g in row_groups]
    shared = {}  # column batch -> its policies' params, stacked and shared once

    def params_of(batch: tuple[int, ...]):
        if batch not in shared:
            parts = [col_groups[c].params for c in batch]
            stacked = parts[0] if len(parts) == 1 else jax.tree.map(lambda *xs: np.concatenate(xs), *parts)
            shared[batch] = workers.share(stacked)
        return shared[batch]

    def job(r: int, batch: tuple[int, ...], i: int) -> tuple:
        same = len(batch) == 1 and _same(row_groups[r], col_groups[batch[0]])
        return (
            row_groups[r].spec,
            row_params[r],
            None if same else col_groups[batch[0]].spec,
            None if same else params_of(batch),
            [i],
            np.asarray(key),
            episodes,
            greedy,
            (r, batch, i),
        )

    pieces = [
        (r, c, i) for r, group in enumerate(row_groups) for c in range(len(col_groups)) for i in range(len(group.names))
    ]
    shapes = {(r, c, i): (col_offsets[c + 1] - col_offsets[c], episodes) for r, c, i in pieces}
    played = journal.played(shapes) if journal is not None else {}
    for (r, c, i), (saved_returns, saved_recipes) in played.items():
        cols = slice(col_offsets[c], col_offsets[c + 1])
        returns[row_offsets[r] + i, cols], recipes[row_offsets[r] + i, cols] = saved_returns, saved_recipes
    items = []
    jobs_per_group = -(-len(workers.shards) // len(row_groups))  # enough jobs for every worker, where they can be
    for r, group in enumerate(row_groups):
        for batch in column_batches(group, col_groups, jobs_per_group):
            for i in range(len(group.names)):
                left = tuple(c for c in batch if (r, c, i) not in played)
                # a batch half played before a stop (by one job per group, as before batches): the rest one by one
                items += [(r, left, i)] if left == batch else [(r, (c,), i) for c in left]
    if progress is not None:
        progress(0, len(pieces) - len(played))
    for wave in in_waves(workers, items):  # at most one job per worker, then the bar moves
        for part in workers.call("play", [(shard, job(*item)) for shard, item in wave]):
            r, batch, i = part.job
            row, first = row_offsets[r] + i, col_offsets[batch[0]]  # the batch's columns are consecutive
            for c in batch:
                cols, within = (
                    slice(col_offsets[c], col_offsets[c + 1]),
                    slice(col_offsets[c] - first, col_offsets[c + 1] - first),
                )
                returns[row, cols], recipes[row, cols] = part.returns[0][within], part.start_recipe[0][within]
                if journal is not None:
                    journal.record((r, c, i), returns[row, cols], recipes[row, cols])
        if progress is not None:
            progress(sum(len(batch) for _, (_, batch, _) in wave), len(pieces) - len(played))
    if np.isnan(returns).any():
        raise RuntimeError("cross-play: some pairs were not evaluated")
    return Matrix(returns, recipes, tuple(row_groups), tuple(col_groups))


@dataclasses.dataclass(frozen=True)
class SeatFairMatrix:
    """Cross-play in both seat orders. ``rows_seat0``: the row policies in seat 0 (rows x cols);
    ``cols_seat0``: the column policies in seat 0 (its rows are the column groups), None when only the
    first order was played. When the columns are the row groups themselves, one matrix holds both
    orders and ``cols_seat0`` is ``rows_seat0``."""

    rows_seat0: Matrix
    cols_seat0: Matrix | None = None

    @property
    def orders(self) -> tuple[str, ...]:
        return ORDERS if self.cols_seat0 is not None else ORDERS[:1]

    def oriented(self, order: str) -> Matrix:
        """One order as a rows x cols ``Matrix``: cell (r, c) pairs row policy r with column policy c,
        r in seat 0 for ``rows_seat0``, in seat 1 for ``cols_seat0``."""
        if order == "rows_seat0":
            return self.rows_seat0
        if order != "cols_seat0" or self.cols_seat0 is None:
            raise ValueError(f"no {order!r} order in this result (orders: {', '.join(self.orders)})")
        m = self.cols_seat0
        return Matrix(m.returns.transpose(1, 0, 2), m.start_recipe.transpose(1, 0, 2), m.col_groups, m.row_groups)

    @property
    def mean(self) -> Matrix:
        """rows x cols, each episode's return averaged over the two orders (the same episode keys, so
        the same start states); the first order alone when only that was played."""
        if self.cols_seat0 is None:
            return self.rows_seat0
        first, second = self.rows_seat0, self.oriented("cols_seat0")
        return Matrix((first.returns + second.returns) / 2, first.start_recipe, first.row_groups, first.col_groups)


def same_groups(row_groups, col_groups) -> bool:
    """Whether the column groups are the row groups (same policies, same networks, same order)."""
    return len(row_groups) == len(col_groups) and all(
        r.ids == c.ids and r.spec == c.spec for r, c in zip(row_groups, col_groups)
    )


def play_seat_fair(
    row_groups,
    col_groups,
    workers,
    key,
    episodes: int,
    greedy: bool = False,
    progress=None,
    seats: str = "both",
    journal=None,
) -> SeatFairMatrix:
    """``play_matrix`` in both seat orders (``seats="both"``) or with the rows in seat 0 only ("0").

    Both orders use the same episode keys. When the columns are the row groups, the one matrix already
    holds both orders (cell (i, j) and (j, i)) and is played once. ``progress(done, total)`` counts the
    jobs of both orders together (those ``journal``, an ``xp_journal.XPJournal``, holds from before a stop
    left out).
    """
    if seats not in SEATS:
        raise ValueError(f"seats: expected one of {', '.join(SEATS)}, got {seats!r}")
    one_matrix = _one_matrix(row_groups, col_groups, seats)
    journals = {order: None if journal is None else journal.order(order) for order in ORDERS}
    total = seat_fair_job_count(row_groups, col_groups, seats) - (0 if journal is None else journal.count())
    bar = None if progress is None else (lambda done, _: progress(done, total))
    first = play_matrix(row_groups, col_groups, workers, key, episodes, greedy, bar, journals[ORDERS[0]])
    if seats == "0":
        return SeatFairMatrix(first)
    second = (
        first
        if one_matrix
        else play_matrix(col_groups, row_groups, workers, key, episodes, greedy, bar, journals[ORDERS[1]])
    )
    return SeatFairMatrix(first, second)


def seat_fair_job_count(row_groups, col_groups, seats: str = "both") -> int:
    """How many jobs ``play_seat_fair`` plays: one per seat-0 policy and column group, in each order it plays."""
    second = 0 if _one_matrix(row_groups, col_groups, seats) else _job_count(col_groups, row_groups)
    return _job_count(row_groups, col_groups) + second


def _one_matrix(row_groups, col_groups, seats: str) -> bool:
    """Whether one matrix is played: the rows in seat 0 only, or columns that are the rows (both orders in it)."""
    return seats == "0" or same_groups(row_groups, col_groups)


def _job_count(row_groups, col_groups) -> int:
    return sum(len(g.names) for g in row_groups) * len(col_groups)


def _offsets(groups) -> list[int]:
    offsets = [0]
    for group in groups:
        offsets.append(offsets[-1] + len(group.names))
    return offsets


def summarize_matrix(result: Matrix) -> dict:
    """One entry per (row source, column source) block: SP/XP means, std across cells, the gap with its
    std, seed-bootstrap CIs."""
    matrix = result.matrix
    return {
        "num_rows": int(matrix.shape[0]),
        "num_cols": int(matrix.shape[1]),
        "episodes_per_pair": int(result.returns.shape[-1]),
        "ci_method": "95% percentile bootstrap over seeds (rows and columns resampled by policy)",
        "blocks": _blocks(result),
    }


def _blocks(result: Matrix) -> list[dict]:
    row_offsets, col_offsets = _offsets(result.row_groups), _offsets(result.col_groups)
    matrix = result.matrix
    blocks = []
    for r, rg in enumerate(result.row_groups):
        for c, cg in enumerate(result.col_groups):
            cells = matrix[row_offsets[r] : row_offsets[r + 1], col_offsets[c] : col_offsets[c + 1]]
            blocks.append(_block_entry(cells, list(rg.ids), list(cg.ids), (rg.label, cg.label), (rg.method, cg.method)))
    return blocks


def _block_entry(cells, row_ids: list, col_ids: list, labels: tuple, methods: tuple) -> dict:
    """``block_summary`` of one block under its (rows, cols) source labels and methods; its policy counts
    are ``num_rows``/``num_cols``."""
    entry = {"rows": labels[0], "cols": labels[1], "row_method": methods[0], "col_method": methods[1]}
    entry.update(block_summary(cells, row_ids, col_ids))
    entry["rows"], entry["cols"] = labels  # block_summary's "rows"/"cols" are counts
    entry["num_rows"], entry["num_cols"] = len(row_ids), len(col_ids)
    return entry


POOLED = "pooled"  # the rows/cols label of pooled_block


def pooled_block(result: Matrix) -> dict:
    """Every source of a square cross-play as one population (``ocv2 xp --pool``): SP is the diagonal,
    XP every other cell, seed-bootstrap intervals over all the policies; e.g. two runs of one config with
    different ``population.seed`` read as one population of their seeds together."""
    row_ids = [i for g in result.row_groups for i in g.ids]
    col_ids = [i for g in result.col_groups for i in g.ids]
    method = "+".join(sorted({g.method or "" for g in result.row_groups}))
    entry = _block_entry(result.matrix, row_ids, col_ids, (POOLED, POOLED), (method, method))
    entry["sources"] = [g.label for g in result.row_groups]
    return entry


def add_pooled(summary: dict, result: SeatFairMatrix) -> dict:
    """``summary`` with ``pooled``: ``pooled_block`` of the seat-averaged matrix, and ``pooled_orders``:
    of each seat order."""
    summary["pooled"] = pooled_block(result.mean)
    summary["pooled_orders"] = {order: pooled_block(result.oriented(order)) for order in result.orders}
    return summary


def summarize_seat_fair(result: SeatFairMatrix) -> dict:
    """``summarize_matrix`` of the seat-averaged matrix (``blocks``), plus ``orders``: the blocks of
    each seat order, (row source, column source) keyed as in ``blocks`` (``cols_seat0``: the column
    source in seat 0), and ``seats``: "both" or "0"."""
    summary = summarize_matrix(result.mean)
    summary["seats"] = "both" if result.cols_seat0 is not None else "0"
    summary["orders"] = {order: _blocks(result.oriented(order)) for order in result.orders}
    return summary


def seat_pairs(summary: dict) -> list[dict]:
    """Each pair of sources of a square cross-play, read from its ``summarize_seat_fair`` summary.

    Takes the summary of a ``SeatFairMatrix`` whose columns are its rows, with both orders played
    (``orders`` holds ``rows_seat0`` and ``cols_seat0``). Returns, for each pair of sources (A, B) with A
    before B: ``a_seat0`` (A in seat 0, B in seat 1: block (A, B) of ``rows_seat0``), ``a_seat1`` (A in
    seat 1: block (A, B) of ``cols_seat0``), the std across the cells of each, and ``mean`` with
    ``mean_ci95_interval``: the XP of block (A, B) averaged over both orders, with its seed-bootstrap
    interval. Raises ``KeyError``, ``IndexError`` or ``TypeError`` on a summary of another shape."""
    first, second, mean = summary["orders"]["rows_seat0"], summary["orders"]["cols_seat0"], summary["blocks"]
    count = math.isqrt(len(mean))
    if count * count != len(mean) or len(first) != len(mean) or len(second) != len(mean):
        raise IndexError("not a square cross-play with both seat orders")
    pairs = []
    for a in range(count):
        for b in range(a + 1, count):
            k = a * count + b
            pairs.append(
                {
                    "a": mean[k]["rows"],
                    "b": mean[k]["cols"],
                    "a_method": mean[k]["row_method"],
                    "b_method": mean[k]["col_method"],
                    "a_seat0": first[k]["xp_mean"],
                    "a_seat0_std": first[k]["xp_std"],
                    "a_seat1": second[k]["xp_mean"],
                    "a_seat1_std": second[k]["xp_std"],
                    "mean": mean[k]["xp_mean"],
                    "mean_ci95_interval": mean[k]["xp_ci95_interval"],
                }
            )
    return pairs


_BLOCK_FIELDS = [
    "rows",
    "cols",
    "row_method",
    "col_method",
    "num_rows",
    "num_cols",
    "sp_mean",
    "sp_std",
    "xp_mean",
    "xp_std",
    "gap",
    "gap_std",
    "xp_ci95_low",
    "xp_ci95_high",
    "sp_ci95_low",
    "sp_ci95_high",
    "gap_ci95_low",
    "gap_ci95_high",
]


def _block_row(order: str, b: dict) -> list:
    return [
        order,
        b["rows"],
        b["cols"],
        b["row_method"] or "",
        b["col_method"] or "",
        b["num_rows"],
        b["num_cols"],
        *(_round(b[k]) for k in ("sp_mean", "sp_std", "xp_mean", "xp_std", "gap", "gap_std")),
        *(_round(v) for v in b["xp_ci95_interval"]),
        *(_round(v) for v in b["sp_ci95_interval"]),
        *(_round(v) for v in b["gap_ci95_interval"]),
    ]


def write_outputs(result: Matrix, out, summary: dict, env) -> dict:
    """matrix.csv, episodes.csv, blocks.csv, summary.json, heatmap.png (+ blocks.png) under ``out``: one order."""
    out = Path(out)
    _write_order(result, out, env, "", policy_labels([*result.row_groups, *result.col_groups]))
    lines = [_block_row("rows_seat0", b) for b in summary["blocks"]]
    if "pooled" in summary:
        lines.append(_block_row("rows_seat0", summary["pooled"]))
    write_csv(out / "blocks.csv", ["order", *_BLOCK_FIELDS], lines)
    write_json(out / "summary.json", summary)
    _write_blocks_png(result, out, summary["blocks"], "mean cross-play return by source (rows in seat 0)")
    return {"matrix": str(out / "matrix.csv"), "summary": str(out / "summary.json")}


def write_seat_fair_outputs(result: SeatFairMatrix, out, summary: dict, env) -> dict:
    """``summarize_seat_fair``'s result and the matrices under ``out``: matrix.csv, episodes.csv and
    heatmap.png of the rows-in-seat-0 order; with both orders also matrix_cols_seat0.csv,
    episodes_cols_seat0.csv, heatmap_cols_seat0.png (the column policies in seat 0, when they are
    other policies than the rows) and matrix_mean.csv + heatmap_mean.png (rows x cols, averaged over
    the orders); blocks.csv (one line per order and block, plus the "mean" lines), summary.json and
    blocks.png (mean XP per block)."""
    if result.cols_seat0 is None:
        return write_outputs(result.rows_seat0, out, summary, env)
    out = Path(out)
    labels = policy_labels([*result.rows_seat0.row_groups, *result.rows_seat0.col_groups])
    _write_order(result.rows_seat0, out, env, "", labels)
    if result.cols_seat0 is not result.rows_seat0:
        _write_order(result.cols_seat0, out, env, "_cols_seat0", labels)
    mean = result.mean
    rows, cols = _names(mean.row_groups, labels), _names(mean.col_groups, labels)
    write_matrix_csv(out / "matrix_mean.csv", mean.matrix, rows, cols, corner="row\\col (mean of both seat orders)")
    xp_heatmap(
        mean.matrix,
        out / "heatmap_mean.png",
        labels=rows,
        col_labels=cols,
        row_title="row policy",
        col_title="column policy",
        title=f"cross-play, mean of both seat orders, {mean.returns.shape[-1]} episodes/pair/order",
    )
    lines = [_block_row(order, b) for order in result.orders for b in summary["orders"][order]]
    lines += [_block_row("mean", b) for b in summary["blocks"]]
    if "pooled" in summary:
        lines += [_block_row(order, summary["pooled_orders"][order]) for order in result.orders]
        lines.append(_block_row("mean", summary["pooled"]))
    write_csv(out / "blocks.csv", ["order", *_BLOCK_FIELDS], lines)
    write_json(out / "summary.json", summary)
    _write_blocks_png(mean, out, summary["blocks"], "mean cross-play return by source (both seat orders)")
    paths = {
        "matrix": str(out / "matrix.csv"),
        "matrix_mean": str(out / "matrix_mean.csv"),
        "summary": str(out / "summary.json"),
    }
    if result.cols_seat0 is not result.rows_seat0:
        paths["matrix_cols_seat0"] = str(out / "matrix_cols_seat0.csv")
    return paths


def policy_labels(groups) -> dict:
    """The labels of every group's policies in matrix.csv, episodes.csv and the heatmaps, keyed by group: its
    ``names``, except where different policies share a name (exported files of two runs both named ``sp``, two
    runs named ``sp`` in different folders), which then get the part of their source's path that tells the
    sources apart as a prefix: ``gpu_coord_ring_sp/sp/seed_0@122``. One policy of two sources (a copy) keeps its
    name."""
    entries = [(name, group.label, policy) for group in groups for name, policy in zip(group.names, group.ids)]
    renamed = iter(_tell_apart(entries))
    return {_key(group): tuple(next(renamed) for _ in group.names) for group in groups}


def _key(group: PolicyGroup) -> tuple:
    return group.label, group.ids


def _tell_apart(entries: list[tuple]) -> list[str]:
    """``(name, source, identity)`` -> one label each: the name, or ``TAG/name`` when the name stands for more
    than one identity, TAG the part of the source's path that differs between the sources sharing that name (the
    whole source where that part does not tell them apart)."""
    identities: dict[str, set] = {}
    for name, _, identity in entries:
        identities.setdefault(name, set()).add(identity)
    tags: dict[tuple[str, str], str] = {}
    for name, seen in identities.items():
        if len(seen) > 1:
            sources = sorted({source for other, source, _ in entries if other == name})
            tags.update({(name, source): tag for source, tag in zip(sources, _source_tags(sources))})
    return [f"{tags[name, source]}/{name}" if (name, source) in tags else name for name, source, _ in entries]


def _source_tags(sources: list[str]) -> list[str]:
    """The first part of each source's path where the sources differ (``table1_coord_ring_sp10`` and
    ``gpu_coord_ring_sp`` for ``docs/results/<that>/policies/sp_seed0_update122.ocv2policy``); the sources
    themselves when those parts are not all different."""
    parts = [
        (source,) if source.startswith(HUMAN_PROXY) else Path(os.path.abspath(source.rstrip("/") or "/")).parts
        for source in sources
    ]
    common = 0
    while all(len(p) > common for p in parts) and len({p[common] for p in parts}) == 1:
        common += 1
    tags = [p[common] if len(p) > common else source for p, source in zip(parts, sources)]
    return tags if len(set(tags)) == len(tags) else list(sources)


def _names(groups, labels: dict) -> list[str]:
    return [n for g in groups for n in labels[_key(g)]]


def _write_order(result: Matrix, out: Path, env, suffix: str, labels: dict) -> None:
    """matrix, episodes and heatmap of one order: rows in seat 0, columns in seat 1 (``labels``:
    ``policy_labels`` of all the groups)."""
    rows, cols = _names(result.row_groups, labels), _names(result.col_groups, labels)
    matrix = result.matrix
    names = recipe_names(env)
    write_matrix_csv(out / f"matrix{suffix}.csv", matrix, rows, cols)
    write_csv(
        out / f"episodes{suffix}.csv",
        ["seat0", "seat1", "episode", "return", "start_recipe"],
        [
            [rows[i], cols[j], e, float(result.returns[i, j, e]), names.get(int(result.start_recipe[i, j, e]), "")]
            for i in range(len(rows))
            for j in range(len(cols))
            for e in range(result.returns.shape[-1])
        ],
    )
    xp_heatmap(
        matrix,
        out / f"heatmap{suffix}.png",
        labels=rows,
        col_labels=cols,
        title=f"cross-play (rows in seat 0), {result.returns.shape[-1]} episodes/pair",
    )


def _write_blocks_png(result: Matrix, out: Path, blocks: list[dict], title: str) -> None:
    if len(result.row_groups) > 1 or len(result.col_groups) > 1:
        groups = [*result.row_groups, *result.col_groups]
        shorts = _tell_apart([(_short(g), g.label, g.label) for g in groups])
        block_means = np.asarray([b["xp_mean"] for b in blocks], np.float64)  # row-source major
        block_means = block_means.reshape(len(result.row_groups), len(result.col_groups))
        xp_heatmap(
            block_means,
            out / "blocks.png",
            labels=shorts[: len(result.row_groups)],
            col_labels=shorts[len(result.row_groups) :],
            title=title,
            row_title="row source",
            col_title="column source",
        )


def _short(group: PolicyGroup) -> str:
    name = Path(group.label.rstrip("/")).name or group.label
    return f"{name} ({group.method})" if group.method else name


def _round(value) -> float | str:
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else round(float(value), 4)
