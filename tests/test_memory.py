"""population.memory: the memory a run needs, refused before anything runs when this machine cannot hold it."""

from __future__ import annotations

import pytest

from population.config import ConfigError, parse_config
from population.memory import MEASURED, XP_BYTES_PER_EPISODE, check_crossplay_fits, check_fits, crossplay_mib, estimate

SMALL_PPO = {"num_envs": 4, "num_steps": 16, "num_minibatches": 2, "total_timesteps": 640}


def test_memory_estimate_is_linear_in_seeds_and_rollout_size():
    cnn = {
        "env": {"layout": "cramped_room"},
        "model": {"kind": "cnn"},
        "ppo": {"num_envs": 64, "num_steps": 256, "num_minibatches": 16},
    }
    one, ten = (parse_config(cnn, [f"population.num_seeds={n}"]) for n in (1, 10))
    measured = MEASURED["cnn"]  # measured at exactly these sizes
    assert estimate(one).total_mib == pytest.approx(measured.base_mib + measured.per_seed_mib)
    assert estimate(ten).total_mib == pytest.approx(measured.base_mib + 10 * measured.per_seed_mib)
    half = parse_config(cnn, ["population.num_seeds=10", "ppo.num_envs=32"])
    assert estimate(half).total_mib == pytest.approx(measured.base_mib + 5 * measured.per_seed_mib)
    # Ray started here: a process per actor, the driver and Ray's own processes on top
    assert estimate(ten, "ray").total_mib > estimate(ten).total_mib
    # joining a cluster: only the driver stays here, with every seed's parameters
    assert estimate(ten, "cluster").total_mib < estimate(ten).total_mib


def test_an_fcp_partner_stage_counts_its_seeds():
    fcp = parse_config(
        {
            "ppo": SMALL_PPO,
            "population": {
                "method": "fcp",
                "num_seeds": 2,
                "fcp": {"pool": "per_seed", "partner_seeds": 4, "partner_ppo": SMALL_PPO},
            },
        }
    )
    assert "8 seeds" in estimate(fcp).where  # 2 learners x 4 partner seeds train first


def test_a_run_that_cannot_fit_is_refused_naming_both_sizes():
    huge = parse_config({"ppo": SMALL_PPO}, ["population.num_seeds=1000000000"])
    with pytest.raises(ConfigError) as info:
        check_fits(huge, "cluster", available_mib=24 * 1024)
    message = str(info.value)
    assert message.startswith("population.num_seeds: the run needs about") and "TiB" in message
    assert "it has 24.0 GiB" in message
    small = parse_config({"ppo": SMALL_PPO})
    assert check_fits(small, "ray", available_mib=24 * 1024).total_mib < 24 * 1024


def test_a_network_too_big_for_one_seed_is_blamed_not_the_seed_count():
    """model.fc_dim=10000000 was refused with "lower population.num_seeds", which no seed count could fix."""
    wide = parse_config({"ppo": SMALL_PPO}, ["model.fc_dim=10000000"])
    with pytest.raises(ConfigError) as info:
        check_fits(wide, "cluster", available_mib=24 * 1024)
    message = str(info.value)
    assert message.startswith("model: one seed alone needs about") and "population.num_seeds" not in message
    assert "(the driver of 1 seed;" in message


def test_a_cross_play_too_big_to_hold_is_refused_before_anything_plays():
    """eval.episodes (or ``ocv2 xp --episodes``) had no upper bound: 10 x 10 seeds x 2**31 - 1 episodes ended in a
    MemoryError where the per-episode arrays were made, after training, when nothing could be changed."""
    assert crossplay_mib(10, 10, 500) == 10 * 10 * 500 * XP_BYTES_PER_EPISODE / 2**20
    assert crossplay_mib(10, 10, 500, seats=2) == 2 * crossplay_mib(10, 10, 500)
    greedy = parse_config({"ppo": SMALL_PPO}, ["population.num_seeds=10", f"eval.episodes={2**31 - 1}"])
    with pytest.raises(ConfigError) as info:
        check_fits(greedy, "local", available_mib=24 * 1024)
    message = str(info.value)
    assert message.startswith("eval.episodes: a 10 x 10 cross-play of 2,147,483,647 episodes per pair keeps 300 bytes")
    assert "about 58.6 TiB, but this machine has 24.0 GiB" in message and message.endswith("fewer episodes per pair")
    with pytest.raises(ConfigError, match=r"^--episodes: a 3 x 4 cross-play .* in 2 seatings"):
        check_crossplay_fits(3, 4, 10**9, "--episodes", seats=2, available_mib=1024)
    assert check_crossplay_fits(10, 10, 500, "eval.episodes", available_mib=1024) < 15  # the paper's: 14.3 MiB


def test_a_view_too_wide_is_named_and_partner_seeds_are_not_blamed_on_one_seed():
    """agent_view_size 3000 was refused as "a smaller network", and 10**8 FCP partner seeds as "one seed alone
    (the driver of 100,000,000 seeds)"; the view is named, and the partner stage is counted as seeds."""
    wide = parse_config({"ppo": SMALL_PPO, "env": {"layout": "cramped_room", "agent_view_size": 3000}})
    with pytest.raises(ConfigError, match=r"or a smaller env.agent_view_size \(observations of 6001 cells a side\)"):
        check_fits(wide, "local", available_mib=24 * 1024)
    many = parse_config({"ppo": SMALL_PPO, "population": {"method": "fcp", "fcp": {"partner_seeds": 100_000_000}}})
    with pytest.raises(ConfigError) as info:
        check_fits(many, "cluster", available_mib=24 * 1024)
    assert str(info.value).startswith("population.num_seeds: the run needs about"), str(info.value)
