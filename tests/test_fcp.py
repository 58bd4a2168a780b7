"""FCP as the paper did it: a partner pool per learner (``population.fcp.pool: per_seed``) and partner
stages trained with the self-play hyperparameters of the layout (``population.fcp.partner_ppo``).

Runs are configs/smoke.yaml with 2 learners x 4 updates and one partner seed per learner (the partner
stage is then 2 SP seeds, the same programs as the smoke SP run).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cluster.runtime import coordinator, runstate
from cluster.runtime.extend import extend_run, repoint_partners
from cluster.runtime.local import LocalWorkers
from cluster.runtime.rundir import RunDir, RunDirError
from cluster.runtime.shard import SeedShard
from population import checkpoints as ckpt
from population import ppo
from population.config import ConfigError, load_config, paper, parse_config
from population.networks import init_params

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "smoke.yaml"
PAPER = ROOT / "configs" / "paper"
V2 = (
    "grounded_coord_simple",
    "grounded_coord_ring",
    "test_time_simple",
    "test_time_wide",
    "demo_cook_simple",
    "demo_cook_wide",
)
PER_SEED = ["population.method=fcp", "population.fcp.pool=per_seed", "population.fcp.partner_seeds=1"]
NUM_SEEDS, NUM_UPDATES = 2, 4


def smoke(*overrides):
    return load_config(SMOKE, [*PER_SEED, *overrides])


# ---------------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", V2)
def test_paper_fcp_partners_default_to_the_self_play_hyperparameters(layout):
    fcp_config = load_config(PAPER / f"v2_{layout}_fcp.yaml")
    sp_config = load_config(PAPER / f"v2_{layout}_sp.yaml")
    fcp = fcp_config.population.fcp
    assert fcp.partners is None and fcp.pool == "per_seed" and fcp.partner_seeds == 8
    assert fcp.partner_ppo == sp_config.ppo  # not the FCP column (LR 7e-4, GAE 0.9, entropy 0.04)
    assert fcp_config.ppo != sp_config.ppo
    stage = coordinator.partner_stage(fcp_config)
    assert stage.ppo == sp_config.ppo and stage.env == sp_config.env and stage.model == sp_config.model
    assert stage.population.method == "sp" and stage.population.num_seeds == 80  # 10 learners x 8


def test_partner_ppo_keys_replace_single_self_play_values():
    path = PAPER / "v2_grounded_coord_simple_fcp.yaml"
    sp = load_config(PAPER / "v2_grounded_coord_simple_sp.yaml").ppo
    config = load_config(path, ["population.fcp.partner_ppo.total_timesteps=196608"])
    partner = config.population.fcp.partner_ppo
    assert partner.total_timesteps == 196608 and partner.num_updates == 3
    assert (partner.lr, partner.ent_coef, partner.gae_lambda) == (sp.lr, sp.ent_coef, sp.gae_lambda)
    # the resolved section is written into the run's config.yaml and reads back the same
    assert parse_config(config.to_dict()) == config


def test_partner_ppo_is_not_used_with_a_partner_run():
    config = load_config(PAPER / "v2_grounded_coord_simple_fcp.yaml", ["population.fcp.partners=runs/sp"])
    assert config.population.fcp.partner_ppo is None


BAD = [
    (["population.fcp.pool=each"], "population.fcp.pool"),
    (["population.fcp.partner_ppo=3"], "population.fcp.partner_ppo"),
    (["population.fcp.partner_ppo.learning_rate=0.1"], "population.fcp.partner_ppo.learning_rate"),
    (["population.fcp.partner_ppo.num_minibatches=3"], "population.fcp.partner_ppo.num_minibatches"),
    (["population.fcp.partner_ppo.total_timesteps=10"], "population.fcp.partner_ppo.total_timesteps"),
    (["population.fcp.partner_ppo.gamma=2"], "population.fcp.partner_ppo.gamma"),
    # no paper self-play config for this layout and model kind: the key must be set
    (["population.fcp.partner_ppo=null", "env.layout=cramped_room_v2", "model.kind=cnn"], "population.fcp.partner_ppo"),
]


@pytest.mark.parametrize("overrides,key", BAD)
def test_fcp_config_errors_are_one_line_naming_the_key(overrides, key):
    with pytest.raises(ConfigError) as error:
        load_config(SMOKE, [*PER_SEED, *overrides])
    message = str(error.value)
    # every problem here comes from an override: it names --set, not the file
    assert f"{key}:" in message and "\n" not in message and message.startswith("--set population.")
    assert "smoke.yaml" not in message


@pytest.mark.parametrize(
    "overrides, said",
    [  # the partner stage keeps updates 0, 2 and 4 (with 2 snapshots: 0 and 4)
        (["population.fcp.checkpoints=[mid, '3']"], r"no snapshot at update 3; snapshots are \[0, 2, 4\]"),
        (["population.fcp.checkpoints=[mid, '9']"], r"no snapshot at update 9; .* of its 4 updates"),
        (["population.fcp.checkpoints=[final, final]"], r"'final' and 'final' are both update 4"),
        (["run.num_checkpoints=2"], r"'mid' and 'final' are both update 4 \(snapshots \[0, 4\]\)"),
    ],
)
def test_a_pool_the_partner_stage_cannot_give_is_refused_before_anything_trains(overrides, said, tmp_path):
    """Update 3 would fail only after every partner seed had trained; with two snapshots "mid" is "final", and the
    pool [mid, final] would hold each partner twice. Refused by train (before the run directory is made) and by
    validate; the config itself still parses, so a run directory written with it by an earlier version loads."""
    config = smoke(*overrides)
    assert parse_config(config.to_dict()) == config
    with pytest.raises(RunDirError, match=rf"population.fcp.checkpoints: {said}"):
        coordinator.check_partners(config)
    with pytest.raises(RunDirError, match="population.fcp.checkpoints"):
        coordinator.train(config, tmp_path / "run", LocalWorkers, show_progress=False, evaluate=False)
    assert not (tmp_path / "run").exists()
    coordinator.check_partners(smoke("run.num_checkpoints=2", "population.fcp.checkpoints=[init, final]"))


#: configs/smoke.yaml with method sp (its partner_ppo unused) as runs written before 2026-11-29 recorded it
SMOKE_SP_FINGERPRINT = "85dc74ec6df231e4"


def test_partner_ppo_of_a_run_without_a_partner_stage_is_checked_and_kept():
    """Unused there, but in such runs' config.yaml and fingerprint since they were first written (a partner
    stage's own config holds it): kept as given, and a bad value refused like a used one."""
    sp = load_config(SMOKE, ["population.method=sp"])
    assert sp.population.fcp.partner_ppo.lr == 1.0e-3 and sp.fingerprint() == SMOKE_SP_FINGERPRINT
    with pytest.raises(ConfigError, match=r"population.fcp.partner_ppo.lr: must be > 0"):
        load_config(SMOKE, ["population.method=sp", "population.fcp.partner_ppo.lr=-1"])


def test_missing_paper_configs_are_an_error_not_default_hyperparameters(tmp_path, monkeypatch):
    monkeypatch.setattr(paper, "PAPER_CONFIGS", tmp_path / "not_installed")
    paper.paper_sp_ppo.cache_clear()
    try:
        with pytest.raises(ConfigError, match="paper configs that ship with ocv2 are missing"):
            load_config(PAPER / "v2_grounded_coord_simple_fcp.yaml")
    finally:
        paper.paper_sp_ppo.cache_clear()


def test_paper_configs_are_read_as_package_data():
    # configs/ in a checkout links to the package's copy: one copy, shipped in the wheel
    assert PAPER.resolve() == Path(str(paper.PAPER_CONFIGS)).resolve()
    names = [f.name for f in paper.paper_config_files()]
    assert "classic_cramped_room_sp.yaml" in names and len(names) == len(list(PAPER.glob("*.yaml")))


# ---------------------------------------------------------------------------------------------------
# per-seed pools
# ---------------------------------------------------------------------------------------------------


def _random_pool(init, key, members: int = 2):
    """``members`` partners freshly initialised by ``init(key)``, stacked [members, ...] (each pool differs
    by its key)."""
    keys = jax.random.split(key, members)
    params = [init(k) for k in keys]
    # Scaled up: freshly initialised policies are near uniform (tiny logits), so any two would sample
    # the same actions from the same key; these act near deterministically, each in its own way.
    return jax.tree.map(lambda *xs: 30.0 * jnp.stack(xs), *params)


def test_per_seed_advance_gives_each_learner_its_own_pool_only():
    """Replacing learner j's pool changes learner j and leaves learner i exactly as it was.

    Shapes are those of the runs below (2 learners, 2 updates a chunk, 2 pool members), so they reuse
    this compiled program through the compilation cache.
    """
    config = smoke()
    trainer = ppo.make_trainer(config)
    # Jitted: one compile for all six members, where flax's init run op by op compiles each of its ops.
    init = jax.jit(lambda key: init_params(trainer.network, key, trainer.env.obs_shape))
    a, b, c = (_random_pool(init, jax.random.PRNGKey(k)) for k in (1, 2, 3))
    advance = ppo.make_advance_population(trainer, 2, pool_per_seed=True)

    def learners(pool0, pool1):
        pools = jax.tree.map(lambda *xs: jnp.stack(xs), pool0, pool1)
        states, metrics = advance(ppo.init_population(trainer, [0, 1], None, 2), None, pools)
        return [jax.tree.leaves((ppo.take_seed(states, s), ppo.take_seed(metrics, s))) for s in (0, 1)]

    def same(x, y) -> bool:  # the whole TrainState (env states, partner carries, ...) and the metrics
        return all(
            np.allclose(np.asarray(u), np.asarray(v), rtol=1e-6, atol=1e-7, equal_nan=True)
            for u, v in zip(x, y, strict=True)
        )

    ab, ac, cb = learners(a, b), learners(a, c), learners(c, b)
    assert same(ab[0], ac[0]) and not same(ab[1], ac[1])
    assert same(ab[1], cb[1]) and not same(ab[0], cb[0])


class Recorder:
    """Wraps ``ppo.make_advance_chunks`` (what shards train with) to keep every pool a shard hands to the
    trainer."""

    def __init__(self, monkeypatch):
        self.calls = []  # (pool_per_seed, numpy pool)
        original = ppo.make_advance_chunks

        def make(trainer, max_updates, pool_per_seed=False):
            compiled = original(trainer, max_updates, pool_per_seed)

            def run(states, buffer, pool, count):
                if trainer.fcp:
                    self.calls.append((pool_per_seed, jax.tree.map(np.asarray, pool)))
                return compiled(states, buffer, pool, count)

            return run

        monkeypatch.setattr(ppo, "make_advance_chunks", make)


def _partner_params(run, seed, update, trainer):
    stage = RunDir(run / "partners").load_config()
    return runstate.load_params(
        ckpt.checkpoint_path(run / "partners", seed, update), stage.fingerprint(), runstate.params_template(trainer)
    )


def _assert_pool_is(pool_row, members):
    for index, member in enumerate(members):
        for x, y in zip(jax.tree.leaves(pool_row), jax.tree.leaves(member), strict=True):
            np.testing.assert_array_equal(x[index], np.asarray(y))


@pytest.fixture(scope="module")
def per_seed_run(tmp_path_factory):
    """A per_seed FCP run on the local backend (partner stage included), and the pools its trainer saw."""
    monkeypatch = pytest.MonkeyPatch()
    recorder = Recorder(monkeypatch)
    run = tmp_path_factory.mktemp("fcp") / "per_seed"
    try:
        coordinator.train(smoke(), run, LocalWorkers, show_progress=False, evaluate=False)
    finally:
        monkeypatch.undo()
    return run, recorder.calls


def test_per_seed_pools_hold_only_each_learners_own_partners(per_seed_run):
    run, calls = per_seed_run
    config = smoke()
    trainer = ppo.make_trainer(config)
    stage = RunDir(run / "partners").load_config()
    assert stage.population.method == "sp" and stage.population.num_seeds == NUM_SEEDS  # 2 learners x 1
    assert stage.ppo == config.population.fcp.partner_ppo
    info = RunDir(run).read_manifest()
    assert info["status"] == "finished" and info["pool"] == [["seed0@2", "seed0@4"], ["seed1@2", "seed1@4"]]
    assert calls and all(per_seed for per_seed, _ in calls)
    for _, pool in calls:  # every chunk: pool [2 learners, 2 members]; row i = partner seed i only
        assert jax.tree.leaves(pool)[0].shape[:2] == (NUM_SEEDS, 2)
        for learner in range(NUM_SEEDS):
            _assert_pool_is(
                jax.tree.map(lambda x: x[learner], pool), [_partner_params(run, learner, u, trainer) for u in (2, 4)]
            )
    first = jax.tree.leaves(calls[0][1])[0]
    assert not np.array_equal(first[0], first[1])


def test_per_seed_run_resumes_where_it_stopped(per_seed_run, tmp_path, monkeypatch):
    """A driver that dies after the first chunk: the resumed run rebuilds the same per-seed pools and
    ends where the uninterrupted one did."""
    reference, reference_calls = per_seed_run
    config = smoke(f"population.fcp.partners={reference / 'partners'}")  # the reference's partner stage
    recorder = Recorder(monkeypatch)
    run = tmp_path / "resumed"

    class Stop(Exception):
        pass

    def die(update, workers, _rows):
        if update == 2:
            raise Stop

    with pytest.raises(Stop):
        coordinator.train(config, run, LocalWorkers, show_progress=False, evaluate=False, on_chunk=die)
    coordinator.train(config, run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    assert RunDir(run).read_manifest()["status"] == "finished"
    assert len(recorder.calls) == 2  # one chunk before the stop, one after
    for (per_seed, pool), (_, expected) in zip(recorder.calls, reference_calls, strict=True):
        assert per_seed
        for x, y in zip(jax.tree.leaves(pool), jax.tree.leaves(expected), strict=True):
            np.testing.assert_array_equal(x, y)
    template = runstate.params_template(ppo.make_trainer(config))
    for seed in range(NUM_SEEDS):
        ours = runstate.load_params(ckpt.checkpoint_path(run, seed, NUM_UPDATES), config.fingerprint(), template)
        theirs = runstate.load_params(
            ckpt.checkpoint_path(reference, seed, NUM_UPDATES), smoke().fingerprint(), template
        )
        for x, y in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_run_whose_partners_moved_with_it_resumes_once_repointed(per_seed_run, tmp_path):
    """A study directory carried elsewhere (``ocv2 study unpack``) holds the FCP run and its partner run; the
    partners' place is in the fingerprint, so resuming refused "holds a run of a different config"."""
    reference, _ = per_seed_run
    shutil.copytree(reference / "partners", tmp_path / "here" / "partners")
    stopped = tmp_path / "here" / "fcp"

    def die(update, workers, _rows):
        if update == 2:
            raise KeyboardInterrupt

    config = smoke(f"population.fcp.partners={tmp_path / 'here' / 'partners'}")
    with pytest.raises(KeyboardInterrupt):
        coordinator.train(config, stopped, LocalWorkers, show_progress=False, evaluate=False, on_chunk=die)
    shutil.copytree(tmp_path / "here", tmp_path / "there")
    moved = smoke(f"population.fcp.partners={tmp_path / 'there' / 'partners'}")
    run = tmp_path / "there" / "fcp"
    with pytest.raises(RunDirError, match="holds a run of a different config"):
        coordinator.train(moved, run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    assert not repoint_partners(
        run, smoke("population.fcp.partners=" + str(tmp_path / "there" / "partners"), "ppo.lr=0.1")
    )
    assert repoint_partners(run, moved) and not repoint_partners(run, moved)
    assert RunDir(run).load_config().population.fcp.partners == str(tmp_path / "there" / "partners")
    coordinator.train(moved, run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    template = runstate.params_template(ppo.make_trainer(moved))
    for seed in range(NUM_SEEDS):  # where the uninterrupted run ended
        ours = runstate.load_params(ckpt.checkpoint_path(run, seed, NUM_UPDATES), moved.fingerprint(), template)
        theirs = runstate.load_params(
            ckpt.checkpoint_path(reference, seed, NUM_UPDATES), smoke().fingerprint(), template
        )
        for x, y in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def _stopped_after_the_first_chunk(config, run) -> None:
    def die(update, workers, _rows):
        if update == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        coordinator.train(config, run, LocalWorkers, show_progress=False, evaluate=False, on_chunk=die)


def _run_files(run) -> dict:
    """What a refused resume must leave as it was."""
    kept = [run / "metrics.csv", run / "manifest.json", *(run / "checkpoints").rglob("*")]
    return {path: path.read_bytes() for path in kept if path.is_file()}


def _give_seed_0_the_parameters_of_seed_1(partners) -> None:
    """Seed 1's final parameters in seed 0's final checkpoint, which still says it is seed 0's (a file moved as it
    is is refused by its recorded seed): the same run and fingerprint, so it loads, with other parameters."""
    meta, state = ckpt.read(ckpt.checkpoint_path(partners, 1, NUM_UPDATES))
    extra = {k: v for k, v in meta.items() if k not in ("version", "fingerprint", "seed")}
    ckpt.save(ckpt.checkpoint_path(partners, 0, NUM_UPDATES), state, meta["fingerprint"], seed=0, **extra)


def test_a_resume_refuses_partners_whose_parameters_changed_and_records_a_pool_older_runs_lack(per_seed_run, tmp_path):
    """The pool came from the partner run's files as they were at each start: a half-trained FCP run resumed
    against other partners without a word."""
    reference, _ = per_seed_run
    partners, run = tmp_path / "partners", tmp_path / "fcp"
    shutil.copytree(reference / "partners", partners)
    config = smoke(f"population.fcp.partners={partners}")
    _stopped_after_the_first_chunk(config, run)
    recorded = RunDir(run).read_manifest()
    assert recorded["pool"] == [["seed0@2", "seed0@4"], ["seed1@2", "seed1@4"]]
    assert sorted(recorded["pool_sha256"]) == ["seed0@2", "seed0@4", "seed1@2", "seed1@4"]
    final = ckpt.checkpoint_path(partners, 0, NUM_UPDATES)
    _give_seed_0_the_parameters_of_seed_1(partners)
    before = _run_files(run)
    with pytest.raises(RunDirError, match=r"population\.fcp\.partners: .*the parameters of partners seed0@4 \(sha256"):
        coordinator.train(config, run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    assert _run_files(run) == before
    shutil.copy(ckpt.checkpoint_path(reference / "partners", 0, NUM_UPDATES), final)  # put back
    RunDir(run).write_manifest({k: v for k, v in recorded.items() if k != "pool_sha256"})  # as older versions wrote
    coordinator.train(config, run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    finished = RunDir(run).read_manifest()
    assert finished["status"] == "finished" and finished["pool_sha256"] == recorded["pool_sha256"]


@pytest.mark.parametrize("status", ["finished", "training"])
def test_a_run_trained_to_the_end_is_evaluated_again_whatever_its_partners_became(
    per_seed_run, tmp_path, caplog, status
):
    """A finished run resumed to evaluate it again (a study whose cross-play result went stale) uses its pool no
    more: a changed partner run is said, not refused, and the record of the pool it trained with stays. Also when
    a kill left "training" at the last update (that evaluation sets it first)."""
    reference, _ = per_seed_run
    run = tmp_path / "finished"
    shutil.copytree(reference, run)
    recorded = RunDir(run).read_manifest()
    RunDir(run).write_manifest({**recorded, "status": status})
    _give_seed_0_the_parameters_of_seed_1(run / "partners")
    with caplog.at_level("WARNING", logger="cluster.runtime.coordinator"):
        coordinator.train(smoke(), run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    assert "the parameters of partners seed0@4" in caplog.text and "training is complete" in caplog.text
    after = RunDir(run).read_manifest()
    assert after["status"] == "finished" and after["pool_sha256"] == recorded["pool_sha256"]


def test_a_resume_refuses_a_pool_that_an_extension_of_the_partner_run_moved(tmp_path):
    """``ocv2 train --resume --extend`` on the partner run adds snapshots and re-stamps its files: its "mid" and
    "final" became other updates, which the half-trained FCP run then trained against."""
    schedule, partners, run = "ppo.schedule_timesteps=1024", tmp_path / "partners", tmp_path / "fcp"
    first = load_config(SMOKE, [schedule, "ppo.total_timesteps=512"])
    coordinator.train(first, partners, LocalWorkers, show_progress=False, evaluate=False)
    config = smoke(f"population.fcp.partners={partners}")
    _stopped_after_the_first_chunk(config, run)
    later = load_config(SMOKE, [schedule, "ppo.total_timesteps=768"])
    extend_run(partners, later)
    coordinator.train(later, partners, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    before = _run_files(run)
    with pytest.raises(
        RunDirError,
        match=r"population\.fcp\.partners: .*its pool has changed: seed0@2, seed1@2 then, seed0@6, seed1@6 now",
    ):
        coordinator.train(config, run, LocalWorkers, resume=True, show_progress=False, evaluate=False)
    assert _run_files(run) == before


def test_a_shard_keeps_only_its_seeds_pools(per_seed_run, tmp_path):
    """The Ray backend hands every actor the run's per-seed pools; a shard of seed 1 keeps row 1 only."""
    reference, reference_calls = per_seed_run
    config = smoke(f"population.fcp.partners={reference / 'partners'}")
    pools = reference_calls[0][1]
    RunDir(tmp_path / "run").create(config)
    shard = SeedShard(config, tmp_path / "run", [1], pools)
    assert shard.pool_per_seed
    for x, y in zip(jax.tree.leaves(shard.pool), jax.tree.leaves(pools), strict=True):
        np.testing.assert_array_equal(np.asarray(x), y[1:2])
    with pytest.raises(ValueError, match="per_seed pool has 1 learner pools for 2 seeds"):
        SeedShard(config, tmp_path / "run", [1], jax.tree.map(lambda x: x[:1], pools))


def test_per_seed_partner_run_needs_a_pool_of_seeds_per_learner(per_seed_run, tmp_path):
    run, _ = per_seed_run
    config = smoke("population.fcp.partner_seeds=2", f"population.fcp.partners={run / 'partners'}")
    with pytest.raises(RunDirError, match=r"population.fcp.partner_seeds: 4 partner seeds needed .*has 2 seeds"):
        coordinator.load_pool(config, ppo.make_trainer(config), run / "partners")
    shared = smoke(
        "population.fcp.pool=shared", "population.fcp.partner_seeds=2", f"population.fcp.partners={run / 'partners'}"
    )
    pool, labels = coordinator.load_pool(shared, ppo.make_trainer(shared), run / "partners")
    assert labels == ["seed0@2", "seed0@4", "seed1@2", "seed1@4"]
    assert jax.tree.leaves(pool)[0].shape[0] == 4


def test_a_pool_checkpoint_the_partner_run_did_not_keep_is_refused_by_key(per_seed_run):
    run, _ = per_seed_run  # its partner run keeps updates 0, 2 and 4
    config = smoke(f"population.fcp.partners={run / 'partners'}", "population.fcp.checkpoints=[init, '3']")
    with pytest.raises(
        RunDirError, match=r"population.fcp.checkpoints: .*no snapshot at update 3; snapshots are \[0, 2, 4\]"
    ):
        coordinator.check_partners(config)


def test_partners_of_the_same_population_seed_are_the_learners_twins_and_it_is_said(per_seed_run, caplog):
    """Learner i's initial parameters come from (population.seed, i) alone: with the partner run's seed
    they equal partner seed i's, which load_pool warns about, naming a seed that avoids it."""
    run, _ = per_seed_run
    stage_seed = RunDir(run / "partners").load_config().population.seed
    assert stage_seed == smoke().population.seed + coordinator.PARTNER_SEED_OFFSET  # the built-in stage differs
    twin = smoke(f"population.seed={stage_seed}", f"population.fcp.partners={run / 'partners'}")
    trainer = ppo.make_trainer(twin)
    learner = ppo.init_train_state(trainer, ppo.seed_key(twin, 0), pool_size=2).params
    for x, y in zip(jax.tree.leaves(learner), jax.tree.leaves(_partner_params(run, 0, 0, trainer)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with caplog.at_level("WARNING", logger="cluster.runtime.coordinator"):
        coordinator.load_pool(twin, trainer, run / "partners")
    (record,) = caplog.records
    assert "same population.seed" in record.message
    assert f"--set population.seed={stage_seed + coordinator.PARTNER_SEED_OFFSET}" in record.message
    caplog.clear()
    # the kernel choice computes the same network: partners trained with other kernels are accepted
    other = smoke(f"population.fcp.partners={run / 'partners'}", "model.kernels=xla")
    with caplog.at_level("WARNING", logger="cluster.runtime.coordinator"):
        coordinator.load_pool(other, ppo.make_trainer(other), run / "partners")
    assert caplog.records == []


@pytest.mark.parametrize(
    "path, before",
    [
        ("configs/quickstart.yaml", "c6bf8ae599d8439c"),
        ("configs/paper/v2_grounded_coord_simple_sa.yaml", "f172112564c9ffd6"),
        ("configs/paper/classic_cramped_room_sp.yaml", "e25c665575963c70"),
    ],
)
def test_runs_made_before_the_pool_keys_keep_their_fingerprint(path, before):
    # Values recorded with the code before population.fcp.pool / partner_ppo existed: such runs must resume.
    config = load_config(path)
    assert config.fingerprint() == before
    assert load_config(path, ["population.fcp.pool=per_seed"]).fingerprint() != before
