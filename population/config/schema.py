"""The config's schema: one frozen, typed dataclass per section, and the ``Config`` that holds them.

Sections: ``env`` (the ``ocv2.make`` parameters), ``model``, ``ppo`` (the paper's hyperparameter names in
lower case), ``population`` (method and per-method settings), ``eval``, ``run``, ``archive`` (what goes
into the MCAP trajectory archive) and ``cluster`` (Ray resources; ignored by the local backend).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Mapping, Sequence
from typing import Any

#: Sections that do not change training numbers: left out of ``Config.fingerprint`` by default.
_UNHASHED = ("eval", "run", "archive", "cluster")

#: JAX's default PRNG keys are built from 32-bit seeds: a larger seed would silently wrap around.
MAX_SEED = 2**32 - 1


def is_update_number(text) -> bool:
    """Whether ``text`` spells an update number (a checkpoint) in ASCII digits: ``str.isdigit`` alone also
    takes "²", which ``int`` refuses."""
    text = str(text)
    return text.isascii() and text.isdigit()


#: The SP stage of an FCP run without partners trains with ``population.seed + FCP_STAGE_SEED_OFFSET``.
FCP_STAGE_SEED_OFFSET = 7919


@dataclasses.dataclass(frozen=True)
class Method:
    """What the code needs to know about a training method, as traits rather than its name: the runtime asks
    "does one seat learn?", not "is it FCP?", so a method that is SP in another env (as OP is) is one entry of
    ``METHOD_TABLE``."""

    name: str  # population.method
    long_name: str  # in reports and tables
    one_learner_seat: bool = False  # one seat per env learns; the other is played by a partner from a pool (FCP)
    partner_pool: bool = False  # needs a pool of partner policies before its workers start (FCP)
    permuted_train_env: bool = False  # trains in an env with per-agent ingredient permutations (OP)
    resets_from_buffer: bool = False  # restarts episodes from a shared state buffer at iteration starts (SA)


#: Every method, in the order reports list them.
METHOD_TABLE = (
    Method("sp", "Self-Play"),
    Method("sa", "State-Augmented", resets_from_buffer=True),
    Method("op", "Other-Play", permuted_train_env=True),
    Method("fcp", "Fictitious Co-Play", one_learner_seat=True, partner_pool=True),
)
METHODS = tuple(method.name for method in METHOD_TABLE)
_METHODS_BY_NAME = {method.name: method for method in METHOD_TABLE}
ACTIVATIONS = ("relu", "tanh")
KERNELS = ("auto", "cpu", "xla")  # model.kernels
GRU_BACKWARDS = ("auto", "hand", "autodiff")  # model.gru_backward
MAX_GRU_UNROLL = 64  # model.gru_unroll: beyond this the compile grows and nothing is measured to gain
PRECISIONS = ("float32", "tf32", "bf16")  # run.precision (population.numerics)
SECTIONS = ("env", "model", "ppo", "population", "eval", "run", "archive", "cluster")


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
    # the GRU's backward pass: "hand" (hand-written, one kernel-gradient matmul after the loop), "autodiff"
    # (of the step scan), "auto" the kernel family's (hand on "cpu", autodiff on "xla"); and how many time
    # steps run per loop iteration (a GPU pays a launch latency per iteration). Same function every way.
    gru_backward: str = "auto"
    gru_unroll: int = 1

    @property
    def recurrent(self) -> bool:
        return self.kind == "rnn"


MODEL_DEFAULTS = {
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
    total_timesteps: int = 30_000_000  # env steps this run trains
    # Env steps the learning-rate schedule (warm-up, cosine decay) and SA's iterations are laid over; None: the
    # same as total_timesteps. Larger than total_timesteps trains the first part of a longer run, unchanged
    # ("truncation": `ocv2 study run --budget F` keeps the paper's schedule and stops after F of its steps).
    # The reward-shaping horizon is counted in env steps already, so it needs no counterpart.
    schedule_timesteps: int | None = None
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
        """Updates this run trains."""
        return self.total_timesteps // self.steps_per_update

    @property
    def schedule_updates(self) -> int:
        """Updates of the schedule the run follows (``num_updates`` unless truncated)."""
        steps = self.total_timesteps if self.schedule_timesteps is None else self.schedule_timesteps
        return steps // self.steps_per_update

    @property
    def truncated(self) -> bool:
        return self.schedule_updates > self.num_updates


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
    for this layout and model kind (``configs/paper``); keys given replace single values of that. Its
    ``activation`` is the learner's ``ppo.activation`` unless given (and must equal it): the learner's
    network plays the partners.
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


@dataclasses.dataclass(frozen=True)
class PopulationConfig:
    method: str = "sp"
    num_seeds: int = 10
    seed: int = 0
    sa: SAConfig = SAConfig()
    op: OPConfig = OPConfig()
    fcp: FCPConfig = FCPConfig()

    @property
    def traits(self) -> Method:
        """The ``Method`` named by ``method`` (validated at parse time)."""
        return _METHODS_BY_NAME[self.method]

    @property
    def trains_partners(self) -> bool:
        """Whether the run trains its own FCP partners first (a partner stage of SP seeds): an FCP
        population given no ``fcp.partners`` (a finished SP run to take them from)."""
        return self.method == "fcp" and self.fcp.partners is None


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Cross-play evaluation: E episodes per ordered pair, stochastic actions, team sparse return."""

    episodes: int = 500
    gifs: int = 2  # episode GIFs of the first seeds' self-play written after training


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """How a run is driven: chunking, checkpoints, and how its numbers are computed.

    ``precision``: float32 matmul/convolution precision, ``float32`` (default), ``tf32`` or ``bf16``
    (``population.numerics``; a GPU's own default would be TF32; on a CPU all three compute float32). Part
    of the fingerprint although the rest of ``run`` is not. ``deterministic``: XLA's deterministic GPU ops
    (``--xla_gpu_deterministic_ops``), so the same config and seed give the same numbers on a GPU too
    (slower scatters and reductions; nothing changes on a CPU).
    """

    checkpoint_every: int = 50  # updates between atomic TrainState checkpoints (also the chunk size)
    num_checkpoints: int = 3  # kept snapshots spread over training (0, mid, final), as the paper
    precision: str = "float32"
    deterministic: bool = True


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
    ``num_gpus``: "auto" (default) shares the GPUs Ray reports evenly among the actors, at most one each
    (1 GPU, 2 actors: 0.5 each; 4 GPUs, 2 actors: 1 each), and 0 only when Ray reports none; a number
    is taken as it is (above 1 only when asked for explicitly).
    ``gpu_memory_fraction``: 0 grows GPU memory on demand (several actors can share a GPU); otherwise
    each actor preallocates that fraction. ``max_restarts``: Ray restarts of a dead worker actor.
    ``local_cpus``: logical CPUs of a Ray started on this machine (0: Ray detects them).
    """

    address: str | None = None
    workers: int = 0
    seeds_per_actor: int = 1
    num_cpus: float = 0.5
    num_gpus: float | str = "auto"
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

    def flat(self) -> dict:
        """``to_dict`` with dotted keys ("ppo.lr", "population.fcp.partners"): what a comparison of two configs
        reads key by key."""
        out: dict = {}

        def walk(prefix: str, value) -> None:
            if isinstance(value, Mapping):
                for key, item in value.items():
                    walk(f"{prefix}.{key}" if prefix else str(key), item)
            else:
                out[prefix] = value

        walk("", self.to_dict())
        return out

    def fingerprinted(self) -> dict:
        """The ``flat`` keys that ``fingerprint`` hashes by default (so a mismatch can name them)."""
        hashed_anyway = {f"{name}.{key}" for name, key in _HASHED_ANYWAY}
        return {k: v for k, v in self.flat().items() if k.split(".", 1)[0] not in _UNHASHED or k in hashed_anyway}

    def fingerprint(self, exclude: Sequence[str] = _UNHASHED) -> str:
        """A hash of everything that changes training numbers (checkpoints from another config are refused):
        the sections not in ``exclude`` and ``run.precision`` (``_HASHED_ANYWAY``).

        Keys added after a release are left out at their default value (``_LATER_KEYS``), so runs made
        before the key existed keep their fingerprint and still resume.
        """
        full = self.to_dict()
        data = {k: v for k, v in full.items() if k not in exclude}
        added = {name for name, _ in _HASHED_ANYWAY if name not in data}
        for name, key in _HASHED_ANYWAY:
            data.setdefault(name, {})[key] = full[name][key]
        for *path, key in _LATER_KEYS:
            section = data
            for name in path:
                section = section.get(name) or {}  # a section set to None (e.g. no partner_ppo) has no keys
            if key in section and section[key] == _LATER_KEYS[(*path, key)]:
                del section[key]
        data = {k: v for k, v in data.items() if v or k not in added}
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


#: Keys added after 0.1.0 and their defaults, left out of the fingerprint at those defaults.
_LATER_KEYS = {
    ("population", "fcp", "pool"): "shared",
    ("population", "fcp", "partner_ppo"): None,
    ("model", "kernels"): "auto",
    ("model", "gru_backward"): "auto",
    ("model", "gru_unroll"): 1,
    ("ppo", "schedule_timesteps"): None,
    ("population", "fcp", "partner_ppo", "schedule_timesteps"): None,
    ("run", "precision"): "float32",
    ("run", "deterministic"): True,
}
#: Keys of sections the fingerprint leaves out that change training numbers all the same: hashed anyway
#: (left out at their defaults by _LATER_KEYS, so runs made before they existed keep their fingerprint).
_HASHED_ANYWAY = (("run", "precision"),)


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value
