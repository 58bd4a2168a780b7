"""Publishing into a folder that already lists a file of the same name (run directory name, seed, update) checks
that the listed file is that checkpoint: a run trained again, or another study's run of the same name, is refused
rather than taken as published already."""

from __future__ import annotations

import pytest
from policy_runs import shared_run, train

from population.policy import PolicyError
from population.published import publish_run, read_listing


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return shared_run(tmp_path_factory)


def test_a_listed_name_from_another_training_is_refused_and_the_same_one_adds_nothing(run, tmp_path):
    folder = tmp_path / "policies"
    first = publish_run(run, folder, which="final")
    assert [e.file for e in first] == [
        "policy_demo_run_seed0_update4.ocv2policy",
        "policy_demo_run_seed1_update4.ocv2policy",
    ]
    assert publish_run(run, folder, which="final") == []  # the same checkpoints: already published, nothing added
    other = tmp_path / "elsewhere" / run.name  # another training under the same directory name
    assert train(other, "population.seed=7") == 0
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    with pytest.raises(
        PolicyError, match=r"policy_demo_run_seed0_update4\.ocv2policy: published from another training"
    ):
        publish_run(other, folder, which="final")
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before  # nothing written
    assert len(read_listing(folder)) == 2
