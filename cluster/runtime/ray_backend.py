"""The Ray backend (``ocv2 train`` default): one actor per shard of seeds, driven by the coordinator.

Actors are thin shells: ``ray.remote(SeedShard)``, the same class the local backend calls in-process.
The driver is the coordinator; it connects to Ray (starting one on this machine when no address is
given), checks that the requested resources exist, creates the actors and calls them through
``RayWorkers.call``, which survives worker deaths:

* an actor that dies (``os._exit``, ``kill -9``, its node removed) is restarted by Ray
  (``cluster.max_restarts``); its constructor restores the shard from its last checkpoint;
* the failed call is resubmitted once the actor answers again. Calls are idempotent (``SeedShard``),
  so a call that ran although Ray reported it failed changes nothing.

Ray is imported here and by ``crossplay`` (its Ray players); both import without it, and the first
Ray call says which extra to install.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import signal
import socket
import threading
import time
import warnings
from pathlib import Path

try:
    import ray
    from ray.exceptions import ActorDiedError, ActorUnavailableError, GetTimeoutError, RayActorError, RayTaskError
except ModuleNotFoundError:  # Ray is the optional ocv2[ray] extra: --backend local must import this room without it
    ray = None

from cluster.runtime import coordinator
from cluster.runtime.environment import process_record
from cluster.runtime.interrupt import ChunkWait
from cluster.runtime.rundir import RunDirError
from cluster.runtime.shard import SeedShard
from population import numerics
from population.checkpoints import CheckpointError
from population.config import ClusterConfig, Config
from population.config import shards as seed_shards
from population.xla_flags import flag_name

RESTART_TIMEOUT_S = 600.0  # how long a restarting actor may take to answer again

log = logging.getLogger(__name__)


#: How a run a dead worker stopped is continued; ``ocv2 study run`` says "the same study command" instead, since
#: a study's runs train with its budget and overrides, which ``ocv2 train CONFIG`` alone would not match.
TRAIN_RESUME_HINT = "continue with `ocv2 train CONFIG --out RUN_DIR --resume`"


class RayBackendError(RuntimeError):
    """Ray cannot run this population as asked (unreachable address, impossible resources, dead worker).

    A run that stopped with its checkpoints saved carries ``resumable=True``: its message ends with how to continue
    it (``TRAIN_RESUME_HINT``), and a caller that continues runs another way says so with ``with_hint``. The flag
    is one of the exception's args, so it survives pickling (Ray sends exceptions between processes)."""

    def __init__(self, message: str, resumable: bool = False):
        super().__init__(message, resumable)
        self.message, self.resumable = message, resumable

    def with_hint(self, hint: str) -> str:
        """The message, ending with ``hint`` in place of ``TRAIN_RESUME_HINT`` when the run can be continued."""
        return f"{self.message}; {hint}" if self.resumable else self.message

    def __str__(self) -> str:
        return self.with_hint(TRAIN_RESUME_HINT)


# ---------------------------------------------------------------------------------------------------
# connecting
# ---------------------------------------------------------------------------------------------------


def connect(cluster: ClusterConfig) -> bool:
    """Join ``cluster.address`` or start Ray here. Returns True if this call started/joined (then shut down)."""
    if ray is None:
        raise RayBackendError("Ray is not installed: pip install 'ocv2[ray]', or use --backend local")
    if ray.is_initialized():  # e.g. a test session or a notebook that already connected
        return False
    with _sigterm_kept():
        return _connect(cluster)


@contextlib.contextmanager
def _sigterm_kept():
    """Keep the process's SIGTERM handler through ``ray.init``, which installs its own (``sys.exit(15)``, with
    a native stack dump): the CLI makes SIGTERM stop a command as Ctrl-C does (``cluster.cli.main``), so that a
    study or training run stopped by a script saves its chunk in flight, on the Ray backend as on the local one.
    A process that left SIGTERM at its default (a library caller) gets Ray's, which shuts Ray down on the way out."""
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGTERM) if main else None
    try:
        yield
    finally:
        if before not in (None, signal.SIG_DFL) and signal.getsignal(signal.SIGTERM) is not before:
            signal.signal(signal.SIGTERM, before)


def _connect(cluster: ClusterConfig) -> bool:
    address = cluster.address
    if address is None:
        start_local(num_cpus=cluster.local_cpus or None)
        return True
    if address not in ("auto",) and not address.startswith("ray://"):
        _check_reachable(address)
    try:
        ray.init(address=address, configure_logging=False)
    except ConnectionError as error:
        raise RayBackendError(
            f"cluster.address {address!r}: no Ray cluster found ({error}). Start one with "
            "`ray start --head` or leave cluster.address unset to run Ray on this machine"
        ) from None
    except Exception as error:  # Ray raises its own types for auth problems; name the usual cause
        if "auth" in str(error).lower():
            raise RayBackendError(
                f"cluster.address {address!r}: authentication failed ({error}). Export the same "
                "RAY_AUTH_MODE (and RAY_AUTH_TOKEN for token mode) as the cluster; see "
                "docs/cluster.md"
            ) from None
        raise
    return True


@contextlib.contextmanager
def session(backend: str, cluster: ClusterConfig):
    """Ray for the whole of a command (nothing for ``backend="local"``): joined or started once, and shut
    down at the end if started here.

    The CLI enters it before anything runs JAX in the driver (loading policies, evaluation). Ray starts
    its processes with ``subprocess.Popen(preexec_fn=...)``, which runs the interpreter's at-fork hooks;
    once JAX is running, its hook warns that forking a multithreaded process may deadlock. Starting Ray
    first means that fork happens before JAX has any threads, and the calls inside (training, cross-play,
    every run of a study) join this instance instead of starting and stopping their own.
    """
    started = backend == "ray" and connect(cluster)
    try:
        yield
    finally:
        if started:
            ray.shutdown()


def start_local(num_cpus: int | None = None, num_gpus: float | None = None) -> None:
    """Start a fresh Ray instance on this machine (never one that RAY_ADDRESS or `ray start` left running).

    ``num_cpus``/``num_gpus``: the logical CPUs and GPUs it declares (None: Ray counts them; the tests declare
    GPUs a CPU machine does not have, to check what actors are given).

    Quietly: Ray's own notices on this path are alarming and not about anything wrong.

    * Token authentication: with ``RAY_AUTH_MODE`` unset, Ray turns it on for a local instance (its
      default since 2.59) and logs a warning about it every time. That warning is dropped and this
      module says the same once, as an INFO record.
    * ``os.fork()``: Ray launches its processes with ``subprocess.Popen(preexec_fn=...)``, and a
      ``preexec_fn`` runs the interpreter's at-fork hooks, where JAX warns that forking a
      multithreaded process may deadlock. The CLI avoids it at the cause: it starts Ray (``session``)
      before JAX runs. Library callers (a notebook, a test session) may already run JAX; for them the
      warning is filtered for exactly these launches, because the child only masks SIGINT and sets its
      parent-death signal before ``exec``: it never runs JAX's threads or locks.
    """
    mode_before = os.environ.get("RAY_AUTH_MODE")
    notices = logging.getLogger("ray._private.authentication.authentication_token_setup")
    notices.addFilter(_token_auth_notice)
    try:
        with ray_process_launches():
            ray.init(
                address="local",
                num_cpus=num_cpus,
                num_gpus=num_gpus,
                include_dashboard=False,
                configure_logging=False,
            )
    finally:
        notices.removeFilter(_token_auth_notice)
    if mode_before is None and os.environ.get("RAY_AUTH_MODE") == "token":  # Ray chose its default
        log.info(
            "started Ray on this machine with token authentication, Ray's default for a local instance "
            "(RAY_AUTH_MODE=disabled turns it off; docs/cluster.md)"
        )


@contextlib.contextmanager
def ray_process_launches():
    """Around code that makes Ray start processes here: JAX's at-fork warning is not shown for them
    (each child execs at once; see ``start_local``). Any other warning still is."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield


def _token_auth_notice(record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in seconds with a clear message instead of Ray's long reconnect loop."""
    host, _, port = address.rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except OSError as error:
        raise RayBackendError(
            f"cluster.address {address!r}: cannot reach the Ray head ({error}); is "
            f"`ray start --head --port={port}` running there and the port open?"
        ) from None


def _node_resources() -> list[dict]:
    return [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]


def gpus_per_actor(cluster: ClusterConfig, num_actors: int) -> float:
    """The GPUs each worker actor asks Ray for: ``cluster.num_gpus``, with ``auto`` resolved.

    ``auto`` shares the GPUs of the cluster's alive nodes evenly among the actors, never more than one per
    actor (a shard is one vmapped program on one device; more than one GPU each only when asked for with a
    number): each whole GPU hosts k actors of 1/k GPU, k the smallest number that places every actor (1 GPU
    and 2 actors: 0.5 each; 2 GPUs and 3 actors: 0.5 each; 4 GPUs and 2 actors: 1 each). 0 only when Ray
    reports no GPU at all.
    """
    if cluster.num_gpus != "auto":
        return float(cluster.num_gpus)
    per_node = [r.get("GPU", 0.0) for r in _node_resources()]
    if not any(per_node) or num_actors < 1:
        return 0.0
    whole = sum(int(gpus) for gpus in per_node)
    if whole == 0:  # only fractions of a GPU declared: the largest node's share
        return max(per_node) / num_actors
    return 1.0 / math.ceil(num_actors / whole)


def check_resources(config: Config, num_actors: int) -> None:
    """Refuse requests the cluster cannot place: all actors must run at once (the coordinator waits for all)."""

    cluster = config.cluster
    per_node = _node_resources()
    total = ray.cluster_resources()
    share = gpus_per_actor(cluster, num_actors)  # what each actor asks Ray for
    if 0 < share < 1 and cluster.gpu_memory_fraction > share + 1e-9:  # actors that share a GPU preallocate
        raise RayBackendError(
            f"cluster.gpu_memory_fraction: each worker actor preallocates {cluster.gpu_memory_fraction:g} of its GPU's "
            f"memory, but the actors share GPUs ({share:g} of one each), so a later one could not start; give "
            f"cluster.gpu_memory_fraction at most {share:g}, or 0 to allocate on demand"
        )
    for name, want in (("GPU", share), ("CPU", cluster.num_cpus)):
        if want <= 0:
            continue
        key = "num_gpus" if name == "GPU" else "num_cpus"
        largest = max((r.get(name, 0.0) for r in per_node), default=0.0)
        if want > largest:
            raise RayBackendError(
                f"cluster.{key}: each worker actor asks for {want:g} {name}s but no node has more "
                f"than {largest:g} (the cluster has {total.get(name, 0.0):g} in all)"
            )
        if want * num_actors > total.get(name, 0.0) + 1e-9:
            raise RayBackendError(
                f"cluster.{key}: {num_actors} worker actors x {want:g} {name}s = {want * num_actors:g}, but the "
                f"cluster has {total.get(name, 0.0):g}; lower cluster.{key} or raise cluster.seeds_per_actor"
            )


def actor_env(cluster: ClusterConfig, num_gpus: float | None = None, deterministic: bool = True) -> dict[str, str]:
    """Environment of a worker process, set before it imports JAX (settings made later are ignored).

    ``num_gpus``: the GPUs the actor asks Ray for (None: ``cluster.num_gpus`` when it is a number; ``auto``
    left unresolved counts as 0, an actor that asks for none). An actor without a GPU gets
    ``JAX_PLATFORMS=cpu`` (Ray hides every GPU from it anyway; this skips the CUDA probe); an actor with
    one never does. ``deterministic`` (``run.deterministic``): an actor with a GPU gets
    ``--xla_gpu_deterministic_ops=true`` appended to the node's own ``XLA_FLAGS`` (Ray expands
    ``${XLA_FLAGS}`` there), if the driver's jaxlib knows the flag and the driver's ``XLA_FLAGS`` does not
    turn it off explicitly. Actors without a GPU are left without it: XLA:CPU is deterministic anyway, and
    the flag would only change their compilation-cache keys.
    """
    if num_gpus is None:
        num_gpus = 0.0 if cluster.num_gpus == "auto" else float(cluster.num_gpus)
    env = (
        {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
        if cluster.gpu_memory_fraction == 0
        else {"XLA_PYTHON_CLIENT_PREALLOCATE": "true", "XLA_CLIENT_MEM_FRACTION": f"{cluster.gpu_memory_fraction:.3f}"}
    )
    if num_gpus == 0:
        env["JAX_PLATFORMS"] = "cpu"
    elif deterministic:
        here = os.environ.get("XLA_FLAGS", "")
        turned_off = flag_name(numerics.DETERMINISTIC_FLAG) in {flag_name(t) for t in here.split()} and not (
            numerics.deterministic_ops_in(here)
        )
        if not turned_off and numerics.deterministic_flag_known():
            env["XLA_FLAGS"] = f"${{XLA_FLAGS}} {numerics.DETERMINISTIC_FLAG}"
    return env


# ---------------------------------------------------------------------------------------------------
# workers
# ---------------------------------------------------------------------------------------------------

# A shard's own errors (a checkpoint that cannot load, a full disk) reach the driver as themselves.
SHARD_ERRORS = (CheckpointError, RunDirError, OSError)


class _ShardActor(SeedShard):
    """The actor: a SeedShard that can also say where it runs.

    An exception in an actor's constructor reaches the driver only as "the actor died" (and Ray does
    not restart it), which read like a worker that had used up its restarts, with advice to resume that could
    not help. A shard that cannot start keeps its error instead and raises it from ``position``, the first call
    the coordinator and every restart check make: its own errors (a checkpoint that cannot load, a full disk)
    as themselves, any other as a ``RayBackendError`` naming the seeds and the error (the traceback is logged
    by the actor; Ray forwards it to the driver's output). A run directory the actor's node cannot see (not on
    storage every node shares) is refused before the shard would make one of its own there.

    The actor's process serves this one shard of one run, so ``run.precision`` is made its default before
    anything is traced: every program it compiles (training, SA collection, cross-play, recorded episodes)
    uses it, as the driver's ``numerics.matmul_precision`` context does for in-process shards.
    """

    def __init__(self, config, run_dir, seeds, pool=None):
        self._load_error = None
        try:
            numerics.set_process_precision(config.run.precision)
            visible_run_dir(run_dir)
            super().__init__(config, run_dir, seeds, pool)
        except SHARD_ERRORS as error:
            self._load_error = error
        except Exception as error:
            log.exception(f"worker for seeds {seeds}: could not start")
            self._load_error = RayBackendError(
                f"the worker for seeds {seeds} could not start: {type(error).__name__}: {error} (its traceback is "
                "above)"
            )

    def position(self) -> int:
        if self._load_error is not None:
            raise self._load_error
        return super().position()

    def node_id(self) -> str:
        return ray.get_runtime_context().get_node_id()

    def describe(self) -> dict:
        """Where this actor trains: ``environment.process_record`` and what Ray gave it."""
        context = ray.get_runtime_context()
        return {
            **process_record(),
            "worker": "Ray actor",
            "node_id": context.get_node_id(),
            "num_gpus": context.get_assigned_resources().get("GPU", 0.0),
            "gpu_ids": [str(i) for i in ray.get_gpu_ids()],
        }


#: How often an actor looks for the run directory's config.yaml before it refuses the directory (``visible_run_dir``).
VISIBLE_TRIES = 5


def visible_run_dir(run_dir) -> None:
    """Refuse a run directory this process cannot see: the driver writes config.yaml before any actor starts, so
    an actor on a node where the path is missing (the directory is not on storage every node shares) would
    otherwise make an empty one on its own disk, train there, and the driver would find no checkpoint at the end.
    Looked for a few times over about two seconds: a network file system may answer from a cache that predates the
    file (an NFS negative lookup), and listing the folder makes it look again."""
    config = Path(run_dir) / "config.yaml"
    for _ in range(VISIBLE_TRIES - 1):
        if config.is_file():
            return
        with contextlib.suppress(OSError):
            os.listdir(run_dir)
        time.sleep(0.5)
    if not config.is_file():
        raise RunDirError(
            f"{run_dir}: the run directory is not visible on the worker's node ({ray.util.get_node_ip_address()}); "
            "put it on storage every node of the cluster shares (docs/cluster.md)"
        )


@functools.lru_cache(maxsize=1)
def _actor_class():
    return ray.remote(_ShardActor)


class RayWorkers:
    """One ``SeedShard`` actor per shard; ``call`` resubmits a job whose actor died and came back."""

    def __init__(self, config: Config, run_dir: Path, pool=None):
        self.config, self.shards = config, seed_shards(config)
        cluster = config.cluster
        check_resources(config, len(self.shards))
        self.num_gpus = gpus_per_actor(cluster, len(self.shards))
        cluster_gpus = ray.cluster_resources().get("GPU", 0.0)
        if self.num_gpus == 0 and cluster_gpus > 0:  # asked for explicitly: say so, never silently
            log.warning(
                f"cluster.num_gpus=0: the worker actors train on the CPU although the cluster has "
                f"{cluster_gpus:g} GPUs (cluster.num_gpus: auto shares them)"
            )
        self._pool = None if pool is None else ray.put(pool)  # held here so the object outlives restarts
        options = dict(
            num_cpus=cluster.num_cpus,
            num_gpus=self.num_gpus,
            max_restarts=cluster.max_restarts,
            max_task_retries=0,
            scheduling_strategy="SPREAD",
            runtime_env={"env_vars": actor_env(cluster, self.num_gpus, config.run.deterministic)},
        )
        self.actors = [
            _actor_class().options(**options).remote(config, str(run_dir), seeds, self._pool) for seeds in self.shards
        ]
        self.events: list[dict] = []  # one per observed worker death: shard, seeds, method, restored_update

    def pids(self) -> list[int]:
        return ray.get([actor.ping.remote() for actor in self.actors])

    def node_ids(self) -> list[str]:
        return ray.get([actor.node_id.remote() for actor in self.actors])

    def describe(self) -> list[dict]:
        """Each actor's ``_ShardActor.describe``, in shard order."""
        return self.call("describe", [(shard, ()) for shard in range(len(self.shards))])

    def share(self, value):
        return ray.put(value)

    def restarts(self) -> int:
        return len(self.events)

    def call(self, method: str, jobs):
        if method != "advance":
            return self._call(method, list(jobs), None)
        # A training chunk: Ctrl-C or SIGTERM lets it finish and be recorded, as on the local backend; the handlers
        # hold for the whole call, restarts included, so a signal between two results is answered the same way.
        jobs = list(jobs)
        wait = _chunk_wait(jobs)
        with wait.answering():
            results = self._call(method, jobs, wait)
        if wait.stop_requested:  # the coordinator records the chunk, then stops
            results = [result._replace(stop_requested=True) for result in results]
        return results

    def _call(self, method: str, jobs: list, wait: ChunkWait | None) -> list:
        results = [None] * len(jobs)
        submit = lambda i: getattr(self.actors[jobs[i][0]], method).remote(*jobs[i][1])
        pending = {submit(i): i for i in range(len(jobs))}
        failures = [0] * len(jobs)
        while pending:
            ref = _next_ready(list(pending), wait)
            index = pending.pop(ref)
            try:
                results[index] = _get(ref)
            except RayActorError as error:
                shard = jobs[index][0]
                if wait is not None and wait.stop_requested:  # asked to stop: the chunk is not trained again
                    raise RayBackendError(
                        f"worker for seeds {self.shards[shard]} died during {method} after the stop was asked for: "
                        f"its chunk is lost, {wait.resume_hint}",
                        resumable=True,
                    ) from None
                failures[index] += 1
                if failures[index] > self.config.cluster.max_restarts + 1:
                    raise RayBackendError(
                        f"worker for seeds {self.shards[shard]} kept dying during {method} "
                        f"({failures[index]} times): {error}"
                    ) from None
                restored = self._wait_until_back(shard, error)
                self.events.append(
                    {
                        "shard": shard,
                        "seeds": self.shards[shard],
                        "method": method,
                        "restored_update": restored,
                        "time": time.time(),
                    }
                )
                pending[submit(index)] = index
        return results

    def _wait_until_back(self, shard: int, cause) -> int:
        """Block until the restarted actor answers; returns the update it restored. Dead for good: error."""

        deadline = time.monotonic() + RESTART_TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                return _get(self.actors[shard].position.remote(), timeout=30)
            except (ActorUnavailableError, GetTimeoutError):
                time.sleep(0.5)
            except RayBackendError as error:  # the restarted actor could not start (out of memory on its new node?)
                raise RayBackendError(
                    f"{error.message}; its checkpoints are in the run directory", resumable=True
                ) from None
            except ActorDiedError as error:
                raise RayBackendError(
                    f"worker for seeds {self.shards[shard]} died and cannot be restarted (cluster.max_restarts="
                    f"{self.config.cluster.max_restarts} used up, or no node can host it): {error}. Its checkpoints "
                    f"are in the run directory",
                    resumable=True,
                ) from None
        raise RayBackendError(
            f"worker for seeds {self.shards[shard]} did not come back within "
            f"{RESTART_TIMEOUT_S:.0f} s after it died ({cause}). Its checkpoints are in the run "
            f"directory",
            resumable=True,
        )

    def close(self) -> None:
        for actor in self.actors:
            ray.kill(actor)
        self.actors = []


def _chunk_wait(jobs) -> ChunkWait:
    """The wait for a chunk of ``advance`` jobs ``(shard, (stop, buffer, update))``: a first Ctrl-C or SIGTERM lets
    the actors finish it so it is saved, a second stops at once (``cluster.runtime.interrupt``)."""
    stop, _, update = jobs[0][1]
    return ChunkWait(f"updates {update + 1}-{stop}", f"resuming continues from update {update}")


def _next_ready(refs: list, wait: ChunkWait | None):
    """The first of ``refs`` to finish; with ``wait``, polled so a signal is answered meanwhile (a driver blocked
    in ``ray.wait`` got a plain KeyboardInterrupt, and the actors were killed with the chunk in flight)."""
    if wait is None:
        return ray.wait(refs, num_returns=1)[0][0]
    while True:
        ready, _ = ray.wait(refs, num_returns=1, timeout=0)
        if ready:
            return ready[0]
        wait.poll()


def _get(ref, timeout: float | None = None):
    """``ray.get``, raising a shard's own error (or a worker's that could not start) as itself (its message names
    the file; Ray's wrapper would add a remote traceback and hide the type from the CLI's error handling)."""
    try:
        return ray.get(ref, timeout=timeout)
    except RayTaskError as error:
        if isinstance(error.cause, (*SHARD_ERRORS, RayBackendError)):
            raise error.cause from None
        raise


def train_population(
    config: Config,
    run_dir,
    *,
    resume: bool = False,
    show_progress: bool = True,
    evaluate: bool = True,
    label: str | None = None,
    on_chunk=None,
) -> dict:
    """Train (or resume) a population on Ray: join/start Ray, check resources, run the coordinator."""

    with session("ray", config.cluster):
        check_resources(config, len(seed_shards(config)))
        return coordinator.train(
            config,
            run_dir,
            RayWorkers,
            resume=resume,
            show_progress=show_progress,
            evaluate=evaluate,
            label=label,
            on_chunk=on_chunk,
        )
