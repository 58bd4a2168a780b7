"""The 2019 human trials: conversion, the dynamics reproduction check, archives, the BC proxy.

The fixture ``tests/data/human_slice.json.gz`` holds the first 150 (train) / 90 (test) ticks of the
first cramped_room game of each split of overcooked-ai 1.1.0's ``clean_*_trials.pickle`` (two soups
delivered in the train slice, one in the test slice), so no test needs the sdist or the network.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import pickle
import tarfile
from pathlib import Path

import jax
import numpy as np
import pytest

import ocv2
from cluster.archive import ArchiveReader, states_as_buffer
from cluster.cli.human import write_trials
from cluster.cli.main import main
from cluster.runtime import crossplay
from cluster.runtime.coordinator import archived_states
from population import bc, human, policy
from population.config import load_config
from population.networks import make_network

FIXTURE = Path(__file__).parent / "data" / "human_slice.json.gz"
CONFIGS = Path(__file__).parent.parent / "configs"


@pytest.fixture(scope="module")
def rows():
    with gzip.open(FIXTURE, "rt") as handle:
        return json.load(handle)["splits"]


@pytest.fixture(scope="module")
def trials(rows):
    return {split: human.trials_from_rows(rows[split], split) for split in human.SPLITS}


def test_slice_converts_to_ocv2_states(trials):
    (trial,) = trials["train"]
    assert (trial.layout, trial.source_layout, trial.split) == ("cramped_room", "cramped_room", "train")
    assert trial.actions.shape == (150, 2) and trial.states.step.shape == (151,)
    assert set(np.unique(trial.actions)) <= set(range(6))
    # the kitchen is ocv2's cramped_room, and onions / dishes / soups appear as ocv2 items
    assert (trial.states.grid[..., 0] == ocv2.LAYOUTS["cramped_room"].static_objects).all()
    assert (trial.states.agents.inventory == human.ONION).any()
    assert (trial.states.agents.inventory == human.ONION_SOUP_DISH).any()
    assert trial.states.done[-1] and not trial.states.done[:-1].any()
    events = human.rule_events([trial])  # what this slice exercises: two whole soups, start to serving
    assert events["pot starts cooking (3rd onion)"] == events["soup finishes cooking"] == 2
    assert events["deliver at serving window"] == events["transitions with a delivery reward"] == 2
    assert events["move blocked by the other agent"] > 0


def test_import_of_slice_reproduces_recorded_rewards(trials):
    for split in human.SPLITS:
        result = human.reproduce(trials[split])
        assert result.transitions == len(trials[split][0].actions)
        assert result.exact == result.transitions, result.by_class
        assert trials[split][0].rewards.sum() >= 20  # at least one soup, at ocv2's 20 per soup
        assert result.by_field["reward"] == 0


def test_reproduction_check_catches_a_wrong_reward_and_a_wrong_action(trials):
    (trial,) = trials["train"]
    delivery = int(np.nonzero(trial.rewards)[0][0])
    wrong_reward = trial._replace(rewards=np.roll(trial.rewards, 1))
    result = human.reproduce([wrong_reward])
    assert result.by_field["reward"] == 2 * int((trial.rewards > 0).sum())
    assert "reward" in result.by_class and result.exact == result.transitions - result.by_class["reward"]
    actions = trial.actions.copy()
    actions[delivery] = [4, 4]  # nobody delivers: held items and the reward both differ
    result = human.reproduce([trial._replace(actions=actions)])
    assert result.exact == result.transitions - 1
    assert result.by_class == {"held+reward": 1}


def test_bad_rows_name_the_problem(rows):
    bad = [dict(r) for r in rows["test"][:5]]
    bad[3]["joint_action"] = "[[0, 0], 'DANCE']"
    with pytest.raises(human.HumanDataError, match=r"row 3: unknown action 'DANCE'"):
        human.trials_from_rows(bad, "test")
    moved = [dict(r, layout="['XXPXX', 'O  2O', 'X1  X', 'XSXDX']") for r in rows["test"][:5]]  # pile/window swapped
    with pytest.raises(human.HumanDataError, match=r"recorded map .* is not ocv2's 'cramped_room' kitchen \["):
        human.trials_from_rows(moved, "test")
    with pytest.raises(human.HumanDataError, match="has no human data"):
        human.trials_from_rows(rows["test"], "test", layouts=["two_rooms"])
    with pytest.raises(human.HumanDataError, match="no such file"):
        human.read_frame("/nonexistent/overcooked_ai-1.1.0.tar.gz", "train")
    for layout in ("garbage", "[1, 2", "42"):  # a map that is not a list of rows: once a SyntaxError traceback
        with pytest.raises(human.HumanDataError, match="layout 'cramped_room': the recorded map"):
            human.trials_from_rows([dict(r, layout=layout) for r in rows["test"][:5]], "test")
    no_players = [dict(r) for r in rows["test"][:5]]
    no_players[2]["state"] = "{'objects': []}"
    with pytest.raises(human.HumanDataError, match="row 2: the state has no key 'players'"):
        human.trials_from_rows(no_players, "test")


def test_a_table_without_a_needed_column_is_named(rows):
    import pandas as pd

    frame = pd.DataFrame(rows["test"][:5]).drop(columns=["reward"])
    with pytest.raises(human.HumanDataError, match=r"clean_test_trials.pickle lacks column\(s\) \['reward'\]"):
        human.rows_from_frame(frame, "clean_test_trials.pickle")
    without_next = pd.DataFrame(rows["test"][:5]).drop(columns=["next_state"], errors="ignore")
    assert len(human.trials_from_rows(human.rows_from_frame(without_next), "test")) == 1  # next_state is optional


class _Payload:
    """What a hostile pickle carries: unpickling calls ``os.system(command)``."""

    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def _crafted_pickles(marker: Path) -> dict[str, bytes]:
    touch = f"touch {marker}"
    return {
        "a __reduce__ calling os.system": pickle.dumps(_Payload(touch)),
        "os.system inside a list of rows": pickle.dumps([{"state": "{}"}, _Payload(touch)]),
        "builtins.eval": b"cbuiltins\neval\n(V__import__('os').system(" + repr(touch).encode() + b")\ntR.",
        "a class from another module": pickle.dumps(human.Trial),
    }


def _sdist_with(tmp_path: Path, pickle_bytes: bytes) -> Path:
    """A rebuilt overcooked_ai-1.1.0.tar.gz whose train pickle is ``pickle_bytes``."""
    tarball = tmp_path / "rebuilt" / human.SDIST_NAME
    tarball.parent.mkdir(parents=True)
    with tarfile.open(tarball, "w:gz") as tar:
        info = tarfile.TarInfo("overcooked_ai-1.1.0/src/overcooked_ai_py/data/human_data/clean_train_trials.pickle")
        info.size = len(pickle_bytes)
        tar.addfile(info, io.BytesIO(pickle_bytes))
    return tarball


def test_a_crafted_pickle_cannot_run_code(tmp_path, capsys):
    pytest.importorskip("pandas")
    marker = tmp_path / "code_ran"
    for what, data in _crafted_pickles(marker).items():
        lone = tmp_path / human.PICKLE_NAMES["train"]
        lone.write_bytes(data)
        for source in (lone, _sdist_with(tmp_path / what.replace(" ", "_"), data)):
            (tmp_path / "out").mkdir(exist_ok=True)
            with pytest.warns(human.HumanDataWarning, match="sha256"):  # not the known file: said so ...
                with pytest.raises(human.HumanDataError, match="refused to load") as error:  # ... and refused
                    human.read_frame(source, "train")
            assert str(source) in str(error.value) and "\n" not in str(error.value), what
            assert main(["human", "import", str(source), "--splits", "train", "--out", str(tmp_path / "out")]) == 1
            err = capsys.readouterr().err
            assert "warning:" in err and "sha256" in err and "refused to load" in err and "Traceback" not in err
            assert [line for line in err.splitlines() if not line.startswith("warning:")] == [
                line for line in err.splitlines() if "error:" in line
            ] and err.count("error:") == 1, err
            assert not marker.exists(), f"{what}: the pickle ran code"
            assert not list((tmp_path / "out").iterdir())


@pytest.mark.parametrize("value", [[1, 2, 3], None, {"state": []}])
def test_a_pickle_that_is_not_a_data_frame_is_a_one_line_error(tmp_path, capsys, value):
    pytest.importorskip("pandas")
    path = tmp_path / human.PICKLE_NAMES["test"]
    path.write_bytes(pickle.dumps(value))
    with pytest.warns(human.HumanDataWarning):
        with pytest.raises(human.HumanDataError, match=f"holds a {type(value).__name__}, not the pandas DataFrame"):
            human.read_frame(path, "test")
    assert main(["human", "import", str(path), "--splits", "test", "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert f"ocv2 human: error: {path}: holds a {type(value).__name__}" in err and "Traceback" not in err


def test_a_device_or_pipe_as_source_is_refused_before_it_is_read(tmp_path, capsys):
    """``/dev/zero`` was read whole (the machine's memory, then an OOM kill); a FIFO blocked forever."""
    fifo_folder = tmp_path / "data"
    fifo_folder.mkdir()
    os.mkfifo(fifo_folder / human.PICKLE_NAMES["train"])
    for source in ("/dev/zero", str(fifo_folder)):
        assert main(["human", "import", source, "--splits", "train", "--out", str(tmp_path / "out")]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "not a regular file (a device, pipe or socket)" in err, err
        assert main(["human", "proxy", "cramped_room", "--source", source, "--out", str(tmp_path / "p")]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "not a regular file" in err, err
    assert not (tmp_path / "p").exists()


def test_reads_are_capped_per_file_and_per_archive_entry(tmp_path, monkeypatch, capsys):
    """A 2 MB .tar.gz of a 2 GB zero pickle reached 2.3 GB before failing. The caps are made small here
    (a few kB of zeros stand for the gigabytes); the message names the cap."""
    monkeypatch.setattr(human, "MAX_PICKLE_BYTES", 4096)
    monkeypatch.setattr(human, "_CHUNK", 1000)  # several chunks below the cap
    zeros = bytes(5000)
    lone = tmp_path / human.PICKLE_NAMES["train"]
    lone.write_bytes(zeros)
    bomb = _sdist_with(tmp_path / "bomb", zeros)
    other = tmp_path / "other" / human.SDIST_NAME  # a large entry that is not the pickle is refused as well
    other.parent.mkdir()
    with tarfile.open(other, "w:gz") as tar:
        info = tarfile.TarInfo("overcooked_ai-1.1.0/padding.bin")
        info.size = len(zeros)
        tar.addfile(info, io.BytesIO(zeros))
    for source, what in ((lone, "the file is larger than 4,096 bytes"), (bomb, "an entry of 5,000 bytes is larger "
                         "than 4,096 bytes"), (other, "padding.bin: an entry of 5,000 bytes")):  # fmt: skip
        with pytest.raises(human.HumanDataError, match="more than ocv2 reads from the human data") as error:
            human.read_frame(source, "train", warn=lambda _: None)
        assert what in str(error.value) and "\n" not in str(error.value), str(error.value)
    # an entry's header is checked before its data is decompressed; the read itself stops at the cap as well
    monkeypatch.setattr(human, "MAX_PICKLE_BYTES", 4999)
    with pytest.raises(human.HumanDataError, match="an entry of 5,000 bytes"):
        human.read_frame(bomb, "train", warn=lambda _: None)
    with io.BytesIO(zeros) as stream, pytest.raises(human.HumanDataError, match="the entry is larger than 4,999"):
        human._read_capped(stream, "x", human.MAX_PICKLE_BYTES, "the entry")
    many = tmp_path / "many" / human.SDIST_NAME
    many.parent.mkdir()
    with tarfile.open(many, "w:gz") as tar:
        for index in range(5):
            tar.addfile(tarfile.TarInfo(f"overcooked_ai-1.1.0/f{index}"), io.BytesIO(b""))
    monkeypatch.setattr(human, "MAX_ARCHIVE_MEMBERS", 3)
    with pytest.raises(human.HumanDataError, match="holds more than 3 entries"):
        human.read_frame(many, "train", warn=lambda _: None)
    assert main(["human", "import", str(bomb), "--splits", "train", "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "Traceback" not in err and "larger than 4,999 bytes" in err


def test_imported_archive_is_a_state_augmentation_source(trials, tmp_path):
    path = tmp_path / "human_train_cramped_room.mcap"
    write_trials(str(path), trials["train"])
    with ArchiveReader(path) as reader:
        episode = reader.episode(0)
    assert episode.meta["human_seats"] == [0, 1] and episode.meta["worker"] == trials["train"][0].worker
    np.testing.assert_array_equal(episode.actions, trials["train"][0].actions)
    assert episode.meta["return"] == float(trials["train"][0].rewards.sum())
    # population.sa.archives takes this file: a training run's SA buffer gets its states
    config = load_config(CONFIGS / "smoke.yaml", ["population.method=sa", f"population.sa.archives=['{path}']"])
    extra = archived_states(config)
    assert extra.step.shape == (15,)  # t = 0, 10, ..., 140 of 150 transitions
    buffer = states_as_buffer([path], keep_every=10)
    env = ocv2.make("cramped_room", initial_state_buffer=buffer)
    state = env.reset_state(jax.random.PRNGKey(3))
    matches = (np.asarray(buffer.agents.x) == np.asarray(state.agents.x)).all(-1) & (
        np.asarray(buffer.grid) == np.asarray(state.grid)
    ).all((-1, -2, -3))
    assert matches.any() and int(state.step) == 0


def test_bc_beats_uniform_on_held_out_actions_and_round_trips(trials, tmp_path, monkeypatch):
    config = bc.BCConfig(steps=60, batch_size=64, eval_every=60, learning_rate=3e-3, selfplay_episodes=1, max_steps=20)
    result = bc.train(config, trials["train"], trials["test"])
    scores = result.scores
    assert scores["test_samples"] == 180 and scores["train_samples"] == 300
    assert scores["test_accuracy"] > scores["uniform_accuracy"] + 0.2
    path = bc.save_proxy(tmp_path / "proxy.ocv2policy", result, config)
    proxy = policy.load(path)  # an ordinary exported policy: cross-play loads it like any other
    assert proxy.meta["layout"] == "cramped_room" and proxy.meta["scores"] == scores
    assert bc.load_proxy(path).meta["kind"] == "human-proxy" and proxy.hidden_size == 0
    data = bc.dataset(trials["test"], bc.proxy_env("cramped_room"))
    assert bc.accuracy(make_network(proxy.model), proxy.params, data) == scores["test_accuracy"]
    # saved at proxy_path, it is what `ocv2 xp --cols human-proxy:LAYOUT` plays with
    monkeypatch.setenv("OCV2_CACHE", str(tmp_path / "cache"))
    bc.save_proxy(human.proxy_path("cramped_room"), result, config)
    group = crossplay.resolve_source("human-proxy:cramped_room")
    assert group.names == ("human-proxy:cramped_room",) and group.env["layout"] == "cramped_room"
    policy.export(tmp_path / "other.ocv2policy", params=proxy.params, model=proxy.model, env=proxy.env)
    with pytest.raises(ValueError, match="other.ocv2policy: an ocv2 policy, but not a human proxy"):
        bc.load_proxy(tmp_path / "other.ocv2policy")


def test_proxy_path_is_in_the_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("OCV2_CACHE", str(tmp_path))
    assert human.proxy_path("coord_ring") == tmp_path / "human_proxy" / "coord_ring.ocv2policy"
    with pytest.raises(ValueError, match="'two_rooms' has no human data"):
        human.proxy_path("two_rooms")


def test_cli_import_writes_archives_and_report(rows, tmp_path, capsys):
    import pandas as pd  # in the test extra (ocv2[human]): a missing pandas fails here, never skips

    source = tmp_path / "data"
    source.mkdir()
    for split in human.SPLITS:
        frame = pd.DataFrame(rows[split])
        frame["next_state"] = frame["state"].shift(-1).fillna(rows[split][-1]["next_state"])
        frame.to_pickle(source / human.PICKLE_NAMES[split])
    out = tmp_path / "out"
    assert main(["human", "import", str(source), "--out", str(out)]) == 0
    report = json.loads((out / "reproduction.json").read_text())
    assert report["splits"]["test"]["cramped_room"]["exact"] == 90
    assert len(ArchiveReader(out / "human_train_cramped_room.mcap")) == 1
    assert main(["human", "import", str(source), "--out", str(out)]) == 2  # no silent overwrite
    assert "exists; pass --overwrite" in capsys.readouterr().err
    (out / "human_test_cramped_room.mcap").rename(out / "human_test_cramped_room.mcap.partial")  # interrupted
    assert main(["human", "import", str(source), "--out", str(out), "--splits", "test"]) == 2
    assert ".partial exists (an unfinished import); pass --overwrite" in capsys.readouterr().err
    assert main(["human", "import", str(tmp_path / "missing"), "--out", str(out)]) == 1
    assert "no such file or folder" in capsys.readouterr().err
    assert main(["human", "import", str(tmp_path / "missing"), "--out", str(tmp_path / "new")]) == 1
    assert not (tmp_path / "new").exists()  # a bad source makes no --out folder
    # The proxy's --out is checked before the training, not after it: an existing file needs --force.
    taken = tmp_path / "taken.ocv2policy"
    taken.write_text("another policy")
    assert main(["human", "proxy", "cramped_room", "--source", str(source), "--out", str(taken)]) == 2
    assert "exists; pass --force to replace it" in capsys.readouterr().err and taken.read_text() == "another policy"
