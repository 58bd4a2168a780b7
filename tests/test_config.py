"""The experiment config (population/config/): parsing, round trips, fingerprints, errors naming the key."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import pytest
import yaml

from population.config import (
    PRECISIONS,
    Config,
    ConfigError,
    ModelConfig,
    PPOConfig,
    RunConfig,
    apply_overrides,
    dump_config,
    load_config,
    load_yaml_text,
    parse_config,
    yaml_io,
)

ROOT = Path(__file__).resolve().parents[1]
SMALL_PPO = {"num_envs": 4, "num_steps": 16, "num_minibatches": 2, "total_timesteps": 640}


def _error(raw, overrides=()) -> str:
    with pytest.raises(ConfigError) as info:
        parse_config(raw, overrides)
    return str(info.value)


# ---------------------------------------------------------------------------------------------------
# defaults, round trips, fingerprints
# ---------------------------------------------------------------------------------------------------


def test_defaults_parse_to_the_paper_settings():
    config = parse_config({})
    assert isinstance(config, Config)
    assert config.env_kwargs == {"layout": "cramped_room"}
    assert config.model.kind == "rnn"
    # the rnn kind's sizes are filled in
    assert config.model.conv_features == (16, 32, 32) and config.model.conv_kernels == (3, 3, 3)
    assert config.model.fc_dim == 128 and config.model.gru_dim == 128
    assert config.model.mixer_features == (128, 128, 8)
    assert config.ppo == PPOConfig()
    assert config.ppo.num_updates == 30_000_000 // (256 * 256)
    assert config.population.method == "sp"
    cnn = parse_config({"model": {"kind": "cnn"}}).model
    assert (cnn.conv_features, cnn.conv_kernels, cnn.fc_dim) == ((32, 32, 32), (5, 3, 3), 64)
    # an explicit size wins over the kind's default
    assert parse_config({"model": {"kind": "cnn", "fc_dim": 16}}).model.fc_dim == 16


@pytest.mark.parametrize(
    "raw",
    [
        {},
        {"model": {"kind": "cnn"}},
        {
            "env": {"layout": "grounded_coord_simple", "max_steps": 50, "agent_view_size": 2},
            "model": {"conv_features": [4, 4], "conv_kernels": [3, 3], "fc_dim": 8, "gru_dim": 8},
            "ppo": dict(SMALL_PPO, lr=1e-3, paper_done_bug=True),
            "population": {"method": "op", "num_seeds": 3, "op": {"ingredients": [0, 2]}},
        },
        {
            "ppo": SMALL_PPO,
            "population": {"method": "fcp", "fcp": {"partners": "runs/sp", "checkpoints": ["init", "120"]}},
            "eval": {"episodes": 7},
            "run": {"checkpoint_every": 3},
        },
    ],
)
def test_round_trip_through_to_dict(raw):
    config = parse_config(raw)
    again = parse_config(config.to_dict())
    assert again == config
    assert again.fingerprint() == config.fingerprint()
    # the plain form survives YAML too (as dump_config writes it)
    assert parse_config(yaml.safe_load(yaml.safe_dump(config.to_dict()))) == config


def test_dump_then_load(tmp_path):
    config = parse_config({"ppo": SMALL_PPO, "env": {"max_steps": 30}})
    path = tmp_path / "config.yaml"
    dump_config(config, path)
    assert load_config(path) == config


def test_fingerprint_tracks_training_settings_only():
    base = parse_config({"ppo": SMALL_PPO})
    assert base.fingerprint() == parse_config({"ppo": SMALL_PPO}).fingerprint()
    assert base.fingerprint() != parse_config({"ppo": dict(SMALL_PPO, lr=1e-3)}).fingerprint()
    assert base.fingerprint() != parse_config({"ppo": dict(SMALL_PPO, paper_done_bug=True)}).fingerprint()
    assert base.fingerprint() != parse_config({"ppo": SMALL_PPO, "env": {"max_steps": 30}}).fingerprint()
    assert base.fingerprint() != parse_config({"ppo": SMALL_PPO, "model": {"gru_dim": 64}}).fingerprint()
    assert base.fingerprint() == parse_config({"ppo": SMALL_PPO, "eval": {"episodes": 3}}).fingerprint()
    assert base.fingerprint() == parse_config({"ppo": SMALL_PPO, "run": {"checkpoint_every": 1}}).fingerprint()


def test_run_precision_is_in_the_fingerprint_and_the_rest_of_run_is_not(monkeypatch):
    """Another matmul precision trains other numbers (on a GPU), so its checkpoints are another run's; float32,
    the default, leaves the fingerprint of runs made before the key existed as it was."""
    base = parse_config({"ppo": SMALL_PPO})
    assert (base.run.precision, base.run.deterministic) == ("float32", True)
    fingerprints = {p: parse_config({"ppo": SMALL_PPO, "run": {"precision": p}}).fingerprint() for p in PRECISIONS}
    assert fingerprints["float32"] == base.fingerprint() and len(set(fingerprints.values())) == 3
    # determinism is not part of it: resuming with it off (or on) continues the same run
    assert parse_config({"ppo": SMALL_PPO, "run": {"deterministic": False}}).fingerprint() == base.fingerprint()
    hashed = []  # what fingerprint hashes: no trace of run at its defaults, only run.precision otherwise
    real_sha256 = hashlib.sha256
    monkeypatch.setattr(hashlib, "sha256", lambda data=b"": hashed.append(json.loads(data)) or real_sha256(data))
    parse_config({"ppo": SMALL_PPO, "run": {"checkpoint_every": 2, "deterministic": False}}).fingerprint()
    assert "run" not in hashed[-1]
    parse_config({"ppo": SMALL_PPO, "run": {"checkpoint_every": 2, "precision": "tf32"}}).fingerprint()
    assert hashed[-1]["run"] == {"precision": "tf32"}


def test_run_precision_and_deterministic_are_checked_naming_the_key():
    assert "run.precision: expected one of float32, tf32, bf16, got 'fp16'" in _error({"run": {"precision": "fp16"}})
    assert "run.deterministic: expected true or false" in _error({"run": {"deterministic": "yes"}})
    assert parse_config({}, ["run.precision=bf16", "run.deterministic=false"]).run == RunConfig(
        precision="bf16", deterministic=False
    )


def test_cluster_num_gpus_is_auto_unless_a_number_is_given(tmp_path):
    assert parse_config({}).cluster.num_gpus == "auto"
    assert parse_config({"cluster": {"num_gpus": 1}}).cluster.num_gpus == 1.0
    assert parse_config({}, ["cluster.num_gpus=0.5"]).cluster.num_gpus == 0.5
    assert parse_config({}, ["cluster.num_gpus=0"]).cluster.num_gpus == 0.0
    assert "cluster.num_gpus: expected auto or a number >= 0, got 'many'" in _error({"cluster": {"num_gpus": "many"}})
    assert "cluster.num_gpus: must be >= 0" in _error({"cluster": {"num_gpus": -1}})
    assert "cluster.num_gpus: expected a number, got True" in _error({"cluster": {"num_gpus": True}})
    assert parse_config({"cluster": {"address": "head:6379"}}).cluster.address == "head:6379"
    for address in ("head:99999999", "head:\u0666\u0663\u0667\u0669", "head:"):  # past 65535; Arabic-Indic digits
        assert "cluster.address: expected auto, HOST:PORT or ray://HOST:PORT" in _error(
            {"cluster": {"address": address}}
        )
    path = tmp_path / "config.yaml"
    dump_config(parse_config({}), path)
    assert load_config(path).cluster.num_gpus == "auto"


# ---------------------------------------------------------------------------------------------------
# errors name the key
# ---------------------------------------------------------------------------------------------------


def test_unknown_section():
    message = _error({"ppoo": {"lr": 1e-3}})
    assert "ppoo" in message and "section" in message


def test_unknown_key():
    message = _error({"ppo": {"lrr": 1e-3}})
    assert "ppo.lrr" in message
    assert "lr" in message.split("ppo.lrr", 1)[1]  # lists the valid keys
    assert "population.sa.iters" in _error({"population": {"sa": {"iters": 3}}})
    assert "model.gru" in _error({"model": {"gru": 3}})


@pytest.mark.parametrize(
    "raw, key",
    [
        ({"ppo": {"num_envs": "abc"}}, "ppo.num_envs"),
        ({"ppo": {"num_envs": 2.5}}, "ppo.num_envs"),
        ({"ppo": {"num_envs": True}}, "ppo.num_envs"),
        ({"ppo": {"lr": "fast"}}, "ppo.lr"),
        ({"ppo": {"anneal_lr": "yes"}}, "ppo.anneal_lr"),
        ({"model": {"conv_features": 4}}, "model.conv_features"),
        ({"model": {"conv_features": [4, "x"]}}, "model.conv_features[1]"),
        ({"population": {"method": ["sp"]}}, "population.method"),
        ({"ppo": [1, 2]}, "ppo"),
        ({"population": "x"}, "population"),  # was a ValueError from dict("x") before the mapping check
        ({"population": 5}, "population"),  # was a TypeError
        ({"population": ["ab"]}, "population"),
        ({"population": {"fcp": "x"}}, "population.fcp"),
        # A falsy non-mapping section was read as an empty one: the defaults, without a word.
        ({"env": False}, "env"),
        ({"env": []}, "env"),
        ({"env": 0}, "env"),
        ({"population": []}, "population"),
        ({"population": False}, "population"),
        ({"population": ""}, "population"),
    ],
)
def test_wrong_type(raw, key):
    assert _error(raw).startswith(key)


def test_impossible_values_name_the_key():
    message = _error({"ppo": {"num_envs": 4, "num_minibatches": 3, "num_steps": 16, "total_timesteps": 640}})
    assert "ppo.num_minibatches" in message and "8" in message  # 4 envs x 2 agents
    # FCP trains one learner seat per environment: 8 minibatches of 4 sequences is impossible there only
    fine_for_sp = {"ppo": dict(SMALL_PPO, num_minibatches=8)}
    parse_config(fine_for_sp)
    assert "ppo.num_minibatches" in _error(dict(fine_for_sp, population={"method": "fcp"}))
    assert "ppo.total_timesteps" in _error({"ppo": dict(SMALL_PPO, total_timesteps=63)})
    parse_config({"ppo": dict(SMALL_PPO, total_timesteps=64)})  # exactly one update is fine
    assert "ppo.gamma" in _error({"ppo": {"gamma": 1.5}})
    assert "ppo.lr" in _error({"ppo": {"lr": 0}})
    assert "ppo.activation" in _error({"ppo": {"activation": "gelu"}})
    assert "model.kind" in _error({"model": {"kind": "transformer"}})
    assert "model.conv_kernels" in _error({"model": {"conv_features": [4, 4], "conv_kernels": [3]}})
    assert "model.gru_dim" in _error({"model": {"gru_dim": 0}})
    assert "run.num_checkpoints" in _error({"run": {"num_checkpoints": 1}})
    assert "population.fcp.checkpoints" in _error({"population": {"method": "fcp", "fcp": {"checkpoints": ["later"]}}})
    assert "population.fcp.checkpoints: '\u00b2' is not" in _error(
        {"population": {"method": "fcp", "fcp": {"checkpoints": ["\u00b2"]}}}
    )
    assert "population.sa.iterations" in _error(
        {"ppo": SMALL_PPO, "population": {"method": "sa", "sa": {"iterations": 11}}}
    )


def test_an_fcp_partner_stage_trains_with_the_learners_activation():
    """The learner's network plays the partners' parameters, so the stage takes ``ppo.activation`` unless told
    otherwise, and another one given outright is refused (it used to train relu partners, played as tanh)."""
    fcp = {"method": "fcp"}
    config = parse_config({"env": {"layout": "cramped_room"}, "ppo": {"activation": "tanh"}, "population": fcp})
    assert (config.ppo.activation, config.population.fcp.partner_ppo.activation) == ("tanh", "tanh")
    assert (
        parse_config({"env": {"layout": "cramped_room"}, "population": fcp}).population.fcp.partner_ppo.activation
        == "relu"
    )
    message = _error(
        {
            "env": {"layout": "cramped_room"},
            "ppo": {"activation": "tanh"},
            "population": {**fcp, "fcp": {"partner_ppo": {"activation": "relu"}}},
        }
    )
    assert "population.fcp.partner_ppo.activation: 'relu', but ppo.activation is 'tanh'" in message
    # Partners from a finished run: their own config says how they were trained (checked when the run starts).
    given = {**fcp, "fcp": {"partners": "runs/sp", "partner_ppo": {"activation": "relu"}}}
    assert parse_config(
        {"env": {"layout": "cramped_room"}, "ppo": {"activation": "tanh"}, "population": given}
    ).population


def test_values_that_crashed_or_failed_late_are_refused_naming_the_key():
    """Each was a traceback (a zero divided by), or a run directory written before training failed."""
    for key in ("num_envs", "num_steps"):  # ZeroDivisionError in schedule_updates
        assert _error({"ppo": {key: 0}}).startswith(f"ppo.{key}: must be > 0, got 0")
        partner = {"method": "fcp", "fcp": {"partner_ppo": {key: 0}}}
        assert f"population.fcp.partner_ppo.{key}: must be > 0" in _error({"population": partner})
    # An empty partners path: the partner stage was skipped, then the run failed reading RUN/partners.
    message = _error({"population": {"method": "fcp", "fcp": {"partners": ""}}})
    assert message.startswith("population.fcp.partners: empty; give an SP run directory")
    # Featurized observations passed, then the network's init failed on a vector after the run directory existed.
    for kind in ("featurized", ["default", "featurized"]):
        assert _error({"env": {"observation_type": kind}}).startswith("env.observation_type: ocv2's networks train")


def test_a_study_file_given_as_a_config_says_so():
    """`ocv2 train STUDY.yaml` said "runs: unknown section; did you mean run?"."""
    study = {"study": "s", "runs": [{"name": "sp", "config": "configs/smoke.yaml"}]}
    for raw in (study, {"runs": study["runs"]}, {"study": "s"}):
        assert "a study file (it names a study or lists runs), not an experiment config" in _error(raw)
    assert "runs: unknown section; did you mean run?" in _error({"runs": {"checkpoint_every": 3}})  # a config's typo


def test_a_problem_an_override_caused_across_keys_is_blamed_on_it():
    """A check across keys (num_envs x num_steps) was blamed on the file, which the override had changed."""
    raw = {"ppo": dict(SMALL_PPO, num_minibatches=4)}
    assert _error(raw, ["ppo.num_envs=3"]).startswith("--set ppo.num_envs=3: ppo.num_minibatches: ")
    assert _error(raw, ["ppo.num_steps=256"]).startswith("--set ppo.num_steps=256: ppo.total_timesteps: ")
    assert _error({"ppo": dict(SMALL_PPO, total_timesteps=63)}).startswith("ppo.total_timesteps")  # the file's own
    # A problem the file has too, at the key the override sets, is still the override's; one the file has elsewhere
    # is the file's, though it names the override's key as a word ("did you mean ppo.lr?").
    assert _error({"ppo": {"lr": 0}}, ["ppo.lr=0"]).startswith("--set ppo.lr=0: ppo.lr: must be > 0")
    assert _error({"ppo": {"lrr": 1}}, ["ppo.lr=0.1"]).startswith("ppo.lrr: unknown key; did you mean ppo.lr?")


def test_bad_method():
    message = _error({"population": {"method": "selfplay"}})
    assert "population.method" in message and "selfplay" in message


def test_bad_env_parameters():
    message = _error({"env": {"layout": "no_such_kitchen"}})
    assert message.startswith("env") and "no_such_kitchen" in message
    assert "env" in _error({"env": {"bogus": 1}}) and "bogus" in _error({"env": {"bogus": 1}})
    assert "max_steps" in _error({"env": {"max_steps": -3}})
    assert "env.initial_state_buffer" in _error({"env": {"initial_state_buffer": None}})
    assert _error({"env": [1]}).startswith("env")


def test_op_ingredients():
    layout = {"layout": "grounded_coord_simple"}  # three ingredients
    parse_config({"env": layout, "population": {"method": "op", "op": {"ingredients": [0, 2]}}})
    for ingredients in ([0, 3], [-1, 0], [1], [1, 1]):
        message = _error({"env": layout, "population": {"method": "op", "op": {"ingredients": ingredients}}})
        assert "population.op.ingredients" in message, ingredients
    # cramped_room has a single ingredient: the default [0, 1] is out of range there
    assert "population.op.ingredients" in _error({"population": {"method": "op"}})
    # the per-agent permutations belong to the method, not the env section
    message = _error({"env": dict(layout, op_ingredient_permutations=[0, 1]), "population": {"method": "op"}})
    assert "env.op_ingredient_permutations" in message


def test_integral_floats_are_accepted_for_ints():
    config = parse_config({"ppo": {"total_timesteps": 1e7, "num_envs": 256.0}})
    assert config.ppo.total_timesteps == 10_000_000 and isinstance(config.ppo.total_timesteps, int)
    assert isinstance(config.ppo.num_envs, int)
    # YAML reads 1e7 (no dot) as a string; it is accepted too
    raw = yaml.safe_load("ppo:\n  total_timesteps: 1e7\n  lr: 3e-4\n")
    assert raw["ppo"]["total_timesteps"] == "1e7"
    config = parse_config(raw)
    assert config.ppo.total_timesteps == 10_000_000 and config.ppo.lr == pytest.approx(3e-4)
    assert isinstance(config.ppo.lr, float)
    assert isinstance(parse_config({"ppo": {"lr": 1}}).ppo.lr, float)


# ---------------------------------------------------------------------------------------------------
# overrides
# ---------------------------------------------------------------------------------------------------


def test_overrides():
    raw = {"ppo": {"lr": 2e-4}}
    data = apply_overrides(raw, ["ppo.lr=1e-3", "env.layout=coord_ring", "population.fcp.partner_seeds=4"])
    assert data["ppo"]["lr"] == "1e-3"  # parsed as YAML; the config coerces
    assert data["env"] == {"layout": "coord_ring"}
    assert data["population"] == {"fcp": {"partner_seeds": 4}}
    assert raw == {"ppo": {"lr": 2e-4}}  # the input is not modified
    config = parse_config(
        raw,
        [
            "ppo.lr=1e-3",
            "ppo.total_timesteps=1e7",
            "model.conv_features=[4, 8]",
            "model.conv_kernels=[3, 3]",
            "env.max_steps=30",
            "ppo.anneal_lr=false",
        ],
    )
    assert config.ppo.lr == pytest.approx(1e-3)
    assert config.ppo.total_timesteps == 10_000_000
    assert config.model.conv_features == (4, 8)
    assert config.env_kwargs["max_steps"] == 30
    assert config.ppo.anneal_lr is False
    # overrides are validated like the file
    assert "ppo.lrr" in _error({}, ["ppo.lrr=1"])
    assert "ppo.num_envs" in _error({}, ["ppo.num_envs=many"])


@pytest.mark.parametrize("item", ["ppo.lr", "lr=1e-3", "ppo..lr=1", ".lr=1", "=3", "ppo.lr.x=1"])
def test_malformed_overrides(item):
    with pytest.raises(ConfigError):
        parse_config({}, [item])


def test_override_through_a_non_section():
    with pytest.raises(ConfigError) as info:
        apply_overrides({"ppo": {"lr": 1e-3}}, ["ppo.lr.x=1"])
    assert "lr" in str(info.value)


# ---------------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------------


def test_load_config_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError) as info:
        load_config(missing)
    assert str(missing) in str(info.value)

    broken = tmp_path / "broken.yaml"
    broken.write_text("ppo: [unclosed\n  lr: 1\n")
    with pytest.raises(ConfigError) as info:
        load_config(broken)
    assert str(broken) in str(info.value) and "YAML" in str(info.value)

    bad_key = tmp_path / "bad_key.yaml"
    bad_key.write_text("ppo:\n  lrr: 0.001\n")
    with pytest.raises(ConfigError) as info:
        load_config(bad_key)
    assert str(bad_key) in str(info.value) and "ppo.lrr" in str(info.value)

    not_mapping = tmp_path / "list.yaml"
    not_mapping.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError) as info:
        load_config(not_mapping)
    assert str(not_mapping) in str(info.value)


def test_load_config_with_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("ppo:\n  num_envs: 4\n  num_steps: 16\n  num_minibatches: 2\n  total_timesteps: 640\n")
    empty = tmp_path / "empty.yaml"
    for text in ("", "# only a comment\n"):  # refused by name, not trained as every default
        empty.write_text(text)
        with pytest.raises(ConfigError, match=rf"{empty}: empty .*write {{}} for a config of every default"):
            load_config(empty)
    empty.write_text("{}\n")
    assert load_config(empty) == parse_config({})
    config = load_config(path, ["ppo.lr=5e-4", "eval.episodes=3"])
    assert config.ppo.num_envs == 4 and config.ppo.lr == pytest.approx(5e-4) and config.eval.episodes == 3
    with pytest.raises(ConfigError) as info:
        load_config(path, ["ppo.num_minibatches=3"])
    # the override caused it: the message names --set, not the file
    assert str(info.value).startswith("--set ppo.num_minibatches=3: ppo.num_minibatches: 3 does not divide")
    assert str(path) not in str(info.value)


def test_configs_are_frozen():
    config = parse_config({})
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.ppo.lr = 1.0  # type: ignore[misc]
    assert isinstance(config.model, ModelConfig)
    assert hash(config) == hash(parse_config({}))


# ---------------------------------------------------------------------------------------------------
# bad input: one line naming the file and key, never a traceback, never a silent "run"
# ---------------------------------------------------------------------------------------------------


def _file_error(tmp_path, text: str, overrides=(), start=None) -> str:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path, overrides)
    message = str(info.value)
    assert message.startswith(start or str(path)) and "\n" not in message
    return message


def test_override_with_broken_yaml_is_one_line(tmp_path):
    message = _file_error(tmp_path, "{}", ["ppo.lr=[1,"], start="--set ppo.lr=[1,: ")
    assert "not valid YAML" in message and "line 1" in message


@pytest.mark.parametrize(
    "item, start, hint",
    [
        ("ppo.lrr=1e-3", "--set ppo.lrr=1e-3: ppo.lrr: unknown key", "did you mean ppo.lr?"),
        (
            "population.num_seed=3",
            "--set population.num_seed=3: population.num_seed: unknown key",
            "did you mean population.num_seeds?",
        ),
        ("ppoo.lr=1e-3", "--set ppoo.lr=1e-3: ppoo: unknown section", "did you mean ppo?"),
        ("ppo.lr=fast", "--set ppo.lr=fast: ppo.lr: expected a number", ""),
        ("ppo.lr", "--set ppo.lr: expected section.key=value", ""),
    ],
)
def test_override_errors_name_set_and_the_nearest_key(tmp_path, item, start, hint):
    message = _file_error(tmp_path, "ppo: {num_envs: 4, num_steps: 16, num_minibatches: 2}\n", [item], start=start)
    assert hint in message and str(tmp_path) not in message


def test_file_errors_suggest_the_nearest_key_and_keep_the_file(tmp_path):
    message = _file_error(tmp_path, "ppo: {lrr: 1.0e-3}\n", ["ppo.lr=1e-3"])
    assert "ppo.lrr: unknown key; did you mean ppo.lr?" in message and "--set" not in message


def test_broken_yaml_file_is_one_line(tmp_path):
    assert "line 2, column 11" in _file_error(tmp_path, "ppo:\n  lr: [1, }\n")


def test_config_path_that_is_a_directory(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        load_config(tmp_path)


def test_config_file_that_is_not_text(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(ConfigError, match="not a text file"):
        load_config(path)


@pytest.mark.parametrize(
    "text, key, what",
    [
        ("run: {checkpoint_every: 2020-01-01}\n", "run.checkpoint_every", "a date"),
        ("population: {fcp: {partners: 2024-05-01 10:00:00}}\n", "population.fcp.partners", "a date and time"),
        ("env: {layout: !!binary aGVsbG8=}\n", "env.layout", "binary data"),
        ("population: {sa: {archives: !!set {a.mcap}}}\n", "population.sa.archives", "a set"),
        ("env: &a {layout: cramped_room, again: *a}\n", "env.again", "refers to itself"),
    ],
)
def test_yaml_values_a_config_cannot_hold(tmp_path, text, key, what):
    message = _file_error(tmp_path, text)
    assert key in message and what in message


def test_libyaml_reads_every_shipped_config_as_the_pure_python_parser_does(monkeypatch):
    """Configs are read by libyaml's parser (several times faster); what it reads must be what PyYAML's own parser
    reads, the checks of ``StrictLoader`` included."""
    assert yaml_io.FastStrictLoader is not None, "PyYAML without libyaml: PyPI's wheels have it"
    paths = sorted(ROOT.joinpath("population", "config", "files").rglob("*.yaml"))
    assert len(paths) > 50
    for path in paths:
        text = path.read_text(encoding="utf-8")
        assert yaml_io._load(text, yaml_io.FastStrictLoader) == yaml_io._load(text, yaml_io.StrictLoader), path
    used, real = [], yaml_io._load
    monkeypatch.setattr(yaml_io, "_load", lambda text, loader: used.append(loader) or real(text, loader))
    load_config(str(paths[0]))
    assert used and set(used) == {yaml_io.FastStrictLoader}  # a valid config never takes the slow path


def test_yaml_alias_bomb_is_refused(tmp_path):
    lines = ["a: &l0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]" for i in range(1, 8)]
    assert "expands to more than" in _file_error(tmp_path, "\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "text, what",
    [
        ("ppo: " + "[" * 5000 + "\n", "nested deeper than 64 levels"),
        # libyaml's composer recurses in C: a segmentation fault of the whole process, were it reached (the mapping
        # is level 1, so the 64th bracket is one too deep)
        ("ppo: " + "[" * 200_000 + "\n", "nested deeper than 64 levels at line 1, column 69"),
        # a scalar counts as a level, as it always did: 63 lists in the mapping hold no number
        ("ppo: " + "[" * 63 + "1" + "]" * 63 + "\n", "nested deeper than 64 levels at line 1, column 69"),
        # libyaml takes the tab as a space; PyYAML's own parser, and so ocv2 with or without libyaml, refuses it
        ("ppo:\n  lr:\t0.1\n", "found character '\\t' that cannot start any token at line 2, column 6"),
        ("ppo: {lr: " + "1" * 4301 + "}\n", "an integer of 4301 digits (at most 100)"),
        ("ppo: {num_envs: " + "9" * 400 + "}\n", "an integer of 400 digits"),
        (
            "env: {layout: cramped_room}\nppo: {lr: 0.1}\nenv: {layout: coord_ring}\n",
            "duplicate key 'env' (first at line 1)",
        ),
        ("ppo:\n  lr: 0.1\n  num_envs: 4\n  lr: 0.2\n", "duplicate key 'lr' (first at line 2) at line 4"),
    ],
    ids=[
        "5000-nested",
        "200000-nested",
        "scalar-too-deep",
        "tab",
        "4301-digits",
        "400-digits",
        "env-twice",
        "key-twice",
    ],
)
def test_hostile_or_ambiguous_yaml_is_a_one_line_error(tmp_path, text, what):
    """Deep nesting (RecursionError inside PyYAML), huge integers (ValueError past 4,300 digits) and a key
    given twice (PyYAML keeps the last silently) are refused with the file and line."""
    message = _file_error(tmp_path, text)
    assert "not valid YAML" in message and what in message, message


@pytest.mark.parametrize(
    "item, what",
    [
        ("ppo.lr=" + "[" * 5000, "nested deeper than 64 levels"),
        ("ppo.lr=" + "1" * 5000, "an integer of 5000 digits"),
        ("env.x={a: 1, a: 2}", "duplicate key 'a'"),
        ("ppo." + ".".join(["a"] * 5000) + "=1", "nested deeper than 64 levels"),
        # a byte that is not UTF-8 on the command line (a lone surrogate in Python): libyaml cannot even encode it
        ("ppo.lr=\udcff", "the value is not valid YAML: unacceptable character #xdcff"),
    ],
    ids=["5000-nested", "5000-digits", "key-twice", "5000-key-parts", "not-utf8"],
)
def test_hostile_set_values_are_one_line_errors_naming_the_override(tmp_path, item, what):
    message = _file_error(tmp_path, "{}", [item], start=f"--set {item[:20]}")
    assert what in message, message[:300]


def test_merge_keys_may_still_override_an_anchor(tmp_path):
    path = tmp_path / "c.yaml"
    text = "ppo:\n  <<: {num_envs: 4, num_steps: 16, num_minibatches: 2, total_timesteps: 640}\n  num_envs: 8\n"
    path.write_text(text)
    assert load_config(path).ppo.num_envs == 8


def test_plain_anchors_still_work(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("model: {kind: cnn, conv_features: &sizes [8, 8], conv_kernels: [3, 3], mixer_features: *sizes}\n")
    assert load_config(path).model.mixer_features == (8, 8)


@pytest.mark.parametrize(
    "item, key",
    [
        ("ppo.lr=.nan", "ppo.lr"),
        ("ppo.lr=nan", "ppo.lr"),
        ("ppo.ent_coef=.inf", "ppo.ent_coef"),
        ("ppo.gamma=-.inf", "ppo.gamma"),
        ("cluster.num_cpus=inf", "cluster.num_cpus"),
    ],
)
def test_non_finite_floats_are_refused(item, key):
    message = _error({}, [item])
    assert message.startswith(f"--set {item}: {key}:") and "finite" in message


@pytest.mark.parametrize(
    "item, key, what",
    [
        ("ppo.lr=1e308", "ppo.lr", "outside float32's range"),  # finite in float64, inf in float32
        ("ppo.ent_coef=-1e39", "ppo.ent_coef", "outside float32's range"),
        ("ppo.lr=1e-50", "ppo.lr", "rounds to 0 in float32"),
        ("cluster.gpu_memory_fraction=1e-46", "cluster.gpu_memory_fraction", "rounds to 0"),
        ("ppo.clip_eps=" + "9" * 100, "ppo.clip_eps", "outside float32's range"),  # the longest integer YAML admits
    ],
    ids=["1e308", "-1e39", "1e-50", "1e-46", "100-digits"],
)
def test_floats_must_fit_float32(item, key, what):
    message = _error({"ppo": SMALL_PPO}, [item])
    assert message.startswith(f"--set {item}: {key}:") and what in message


def test_integers_longer_than_any_config_value_are_refused_as_yaml():
    """400 digits overflow float(); past 4,300 Python refuses to parse them at all."""
    item = "ppo.clip_eps=" + "9" * 400
    message = _error({"ppo": SMALL_PPO}, [item])
    assert message.startswith(f"--set {item}: the value is not valid YAML: an integer of 400 digits (at most 100)")


@pytest.mark.parametrize(
    "item, key, what",
    [
        ("ppo.total_timesteps=1e30", "ppo.total_timesteps", "int32"),
        ("ppo.num_envs=1e10", "ppo.num_envs", "int32"),
        ("population.num_seeds=-1e12", "population.num_seeds", "int32"),
        ("model.conv_features=[8, 1e12]", "model.conv_features[1]", "int32"),
        ("env.max_steps=1.0e+30", "env.max_steps", "int32"),
        ("population.seed=1e30", "population.seed", "int64"),  # held by Python, then checked against 32 bits
        ("ppo.rew_shaping_horizon=1e19", "ppo.rew_shaping_horizon", "int64"),
    ],
)
def test_integers_must_fit_what_holds_them(item, key, what):
    message = _error({"ppo": SMALL_PPO}, [item])
    assert message.startswith(f"--set {item}: {key}:") and f"the {what}" in message
    assert parse_config({"ppo": SMALL_PPO}, ["ppo.rew_shaping_horizon=3e9"]).ppo.rew_shaping_horizon == 3 * 10**9


def test_step_counters_must_fit_int32():
    # 2**31 env steps in one update, or more optimiser steps than the int32 counter holds, would wrap
    def problems(ppo):
        with pytest.raises(ConfigError) as info:
            parse_config({"ppo": dict(SMALL_PPO, num_minibatches=1, **ppo)})
        return " | ".join(info.value.problems)

    assert "exceed the int32 step counter" in problems({"num_envs": 2**16, "num_steps": 2**15})
    assert "optimiser steps exceed" in problems({"num_steps": 1, "update_epochs": 2**20, "total_timesteps": 2**30})


def test_seeds_must_fit_32_bits():
    assert parse_config({"population": {"seed": 2**32 - 1}}).population.seed == 2**32 - 1
    assert _error({"population": {"seed": 2**32}}).startswith("population.seed")
    # an FCP run without partners trains its SP stage with seed + 7919
    fcp = {"ppo": SMALL_PPO, "population": {"method": "fcp", "seed": 2**32 - 100}}
    assert "7919" in _error(fcp)


def test_max_steps_must_fit_the_int32_step_counter():
    assert parse_config({"env": {"max_steps": 2**31 - 1}}).env_kwargs["max_steps"] == 2**31 - 1
    assert "max_steps" in _error({"env": {"max_steps": 2**31}})


def test_every_problem_is_listed():
    with pytest.raises(ConfigError) as info:
        parse_config({"ppo": {"lr": -1, "lrr": 3, "num_envs": "many"}, "eval": {"episodes": 0}})
    problems = info.value.problems
    # keys that do not parse first, then values (checked with the bad keys at their defaults)
    assert [p.split(":")[0] for p in problems] == ["ppo.lrr", "ppo.num_envs", "ppo.lr", "eval.episodes"]
    assert "and 3 more problems" in str(info.value)
    with pytest.raises(ConfigError) as info:
        parse_config({"ppo": dict(SMALL_PPO, lr=-1), "eval": {"episodes": 0}, "run": {"num_checkpoints": 1}})
    assert [p.split(":")[0] for p in info.value.problems] == ["ppo.lr", "eval.episodes", "run.num_checkpoints"]


def test_a_problem_is_reported_once():
    with pytest.raises(ConfigError) as info:
        parse_config({"model": {"kind": "mlp"}, "ppo": {"lr": "fast"}, "bogus": {}})
    problems = info.value.problems
    assert problems[0].startswith("bogus: unknown section")
    assert [p.split(":")[0] for p in problems[1:]] == ["model.kind", "ppo.lr"]


def test_file_prefix_on_every_problem(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("ppo: {lrr: 1, clip: 2}\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert all(p.startswith(f"{path}: ppo.") for p in info.value.problems) and len(info.value.problems) == 2


def test_seed_shards_and_job_blocks_are_one_split():
    from cluster.runtime import jobs
    from population.config import shards, spread

    assert jobs.spread is spread  # the coordinator's job blocks and the seed shards split alike
    config = parse_config({"population": {"num_seeds": 10}, "cluster": {"seeds_per_actor": 3}})
    assert shards(config) == [[0, 1, 2], [3, 4, 5], [6, 7], [8, 9]] == spread(range(10), 4)
    assert shards(parse_config({"population": {"num_seeds": 5}, "cluster": {"workers": 2}})) == [[0, 1, 2], [3, 4]]
    assert spread([1, 2], 3) == [[1], [2], []]


def test_every_method_is_one_table_entry_whose_traits_the_code_reads():
    """What the runtime asks of a method (one learner seat, a partner pool, a permuted env, a state buffer) is a
    trait of its METHOD_TABLE entry; the names, their order and the long names come from the same table."""
    from cluster.cli.report import METHOD_NAMES as CLI_NAMES
    from cluster.study.report import METHOD_NAMES as STUDY_NAMES
    from population import ppo
    from population.config import METHOD_TABLE, METHODS, parse_config

    assert METHODS == ("sp", "sa", "op", "fcp") == tuple(m.name for m in METHOD_TABLE)
    assert CLI_NAMES == STUDY_NAMES == {m.name: m.long_name for m in METHOD_TABLE}
    layout = {"layout": "grounded_coord_simple"}  # two ingredients: OP's default permutation applies
    traits = {m: parse_config({"env": layout, "population": {"method": m}}).population.traits for m in METHODS}
    assert [t.name for t in traits.values() if t.one_learner_seat] == ["fcp"]
    assert [t.name for t in traits.values() if t.partner_pool] == ["fcp"]
    assert [t.name for t in traits.values() if t.permuted_train_env] == ["op"]
    assert [t.name for t in traits.values() if t.resets_from_buffer] == ["sa"]
    op = parse_config({"env": layout, "population": {"method": "op"}})  # the trait at work (more: test_methods.py)
    assert ppo.train_env(op).config.op_enabled and not ppo.eval_env(op).config.op_enabled
    assert ppo.make_trainer(parse_config({"env": layout, "population": {"method": "fcp"}})).fcp


def test_a_key_that_did_not_parse_is_not_blamed_again_through_its_default():
    """num_envs: four once added "total_timesteps: 640 is less than one update (num_envs x num_steps = 65536)",
    computed from num_envs' default; a check that names another key still reports."""
    with pytest.raises(ConfigError) as info:
        parse_config({"ppo": {"num_envs": "four", "total_timesteps": 640}})
    assert info.value.problems == ["ppo.num_envs: expected an integer, got 'four'"]
    with pytest.raises(ConfigError) as info:
        parse_config({"ppo": {"num_envs": 4, "num_steps": 16, "total_timesteps": 32, "lr": "x"}})
    keys = [p.split(":")[0] for p in info.value.problems]
    assert keys[0] == "ppo.lr" and "ppo.total_timesteps" in keys  # it names num_envs and num_steps, not lr


def test_an_override_into_an_empty_section_fills_it(tmp_path):
    """ "env:" with nothing under it is an empty section (YAML null), which --set fills like an absent one; a
    key that holds a value is still no section."""
    path = tmp_path / "c.yaml"
    path.write_text("env:\nppo:\n")
    assert load_config(path, ["env.layout=coord_ring"]).env_kwargs["layout"] == "coord_ring"
    with pytest.raises(ConfigError, match=r"--set eval.episodes.x=1: episodes is not a section"):
        load_config(path, ["eval.episodes=3", "eval.episodes.x=1"])


def test_env_problems_name_their_key_and_their_source(tmp_path):
    """The env section as every other: env.<key> in each problem, the nearest name for a typo, and a problem of
    the file not blamed on an override of another env key."""
    message = _file_error(tmp_path, "env: {layuot: coord_ring}")
    assert "env.layuot: unknown parameter; did you mean env.layout?" in message
    message = _file_error(tmp_path, "env: {max_steps: 0}", ["env.layout=coord_ring"])
    assert message.startswith(f"{tmp_path / 'c.yaml'}: env.max_steps: max_steps must be an integer"), message
    _file_error(tmp_path, "{}", ["env.max_steps=0"], start="--set env.max_steps=0: env.max_steps:")


def test_env_integers_may_be_written_as_1e3_as_elsewhere(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("env: {layout: coord_ring, max_steps: 1e3, agent_view_size: 2.0}\nppo: {total_timesteps: 1e5}\n")
    env = dict(load_config(path).env_kwargs)
    assert env["max_steps"] == 1000 and env["agent_view_size"] == 2
    assert type(env["max_steps"]) is int and type(env["agent_view_size"]) is int
    _file_error(tmp_path, "env: {max_steps: 1.5}")


def test_numbers_in_other_scripts_or_base_60_are_refused_not_read():
    """float() reads "٤٠" as 40 and YAML 1.1 reads 1:00 as 60: a config with either trained on a number nobody
    wrote; fcp.checkpoints already refused such digits."""
    assert "env.max_steps" in _error({"env": {"max_steps": "\u0664\u0660"}})
    assert "ppo.lr: expected a number, got" in _error({"ppo": {"lr": "\u0660.\u0660\u0660\u0661"}})
    for text in ("ppo:\n  update_epochs: 1:00\n", "ppo:\n  lr: 1:30.5\n"):
        with pytest.raises(yaml.YAMLError, match=r"(?s)reads as a base-60 number in YAML 1.1.*line 2"):
            load_yaml_text(text)
    assert load_yaml_text("cluster:\n  address: '10.0.0.1:6379'\n") == {"cluster": {"address": "10.0.0.1:6379"}}
