"""Published policies are usable as they are: a committed cross-play cell is played again from the committed
policy files (docs/results/table1_coord_ring_sp10/policies/, the 10-seed Coordination Ring SP population's
0.49M snapshot) and gives the committed numbers; every published policies folder under docs/results/ matches its
SHA256SUMS.json.

Made by ``ocv2 xp --rows P0 P1 --episodes 8 --seed 0 --backend local`` (the matrix in seat order, 8 episodes per
ordered pair, a fixed episode key). Tolerance: 5 points per cell, two deliveries (20 each) in 8 episodes, because
a different XLA build may round a logit differently and flip a sampled action; on the pinned versions the
cells repeat exactly."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import re
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from cluster.cli import main
from cluster.runtime import crossplay
from cluster.runtime.rundir import read_matrix_csv
from population.policy import load, policy_env
from population.record import play_recorded

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "table1_coord_ring_sp10"
POLICIES = RESULTS / "policies"


PUBLISHED = sorted(RESULTS.parent.glob("*/policies/SHA256SUMS.json"))


def test_the_xp_check_snapshot_is_published_for_every_seed():
    listing = json.loads((POLICIES / "SHA256SUMS.json").read_text())
    assert {entry["seed"] for entry in listing if entry["update"] == 30} == set(range(10))


@pytest.mark.parametrize("sums", PUBLISHED, ids=lambda path: path.parent.parent.name)
def test_every_published_policy_matches_its_sha256(sums):
    listing = json.loads(sums.read_text())
    folder = sums.parent
    assert sorted(entry["file"] for entry in listing) == sorted(p.name for p in folder.glob("*.ocv2policy"))
    for entry in listing:
        assert hashlib.sha256((folder / entry["file"]).read_bytes()).hexdigest() == entry["sha256"]


def test_every_finished_study_under_results_published_its_policies():
    """The SP and SA halves of the 10-seed Coordination Ring test, at least: a reader can replay both."""
    assert {path.parent.parent.name for path in PUBLISHED} >= {"table1_coord_ring_sp10", "table1_coord_ring_sa10"}


def test_a_committed_cross_play_cell_is_played_again_from_the_committed_policies(tmp_path):
    files = [str(POLICIES / f"sp_seed{seed}_update30.ocv2policy") for seed in (0, 1)]
    out = tmp_path / "xp"
    assert (
        main(
            [
                "xp",
                "--rows",
                *files,
                "--episodes",
                "8",
                "--seed",
                "0",
                "--backend",
                "local",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    for path in files:  # the bytes played, checked against the listing beside them
        assert summary["files"][path] == {
            "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
            "listing": str(POLICIES / "SHA256SUMS.json"),
            "listed": True,
        }
    again = read_matrix_csv(out / "matrix.csv").values
    committed = read_matrix_csv(RESULTS / "xp_check_update30.csv").values
    np.testing.assert_allclose(again, committed, atol=5.0)


def test_no_published_result_is_hidden_by_gitignore():
    """A result file that git ignores is missing from every clone (the policies above once were)."""
    root = RESULTS.parents[2]
    if not (root / ".git").exists():
        pytest.skip("not a git checkout")
    listed = subprocess.run(
        ["git", "ls-files", "--others", "--ignored", "--exclude-standard", "docs/results", "study_state"],
        cwd=root,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert listed == []


def test_the_role_counts_account_for_every_delivery_in_the_returns():
    """roles.py's per-seat counts read the recorded states the way the environment scores them: on the classic
    Coordination Ring every delivery is worth 20, so the deliveries it finds are the returns / 20."""
    spec = importlib.util.spec_from_file_location("sp10_roles", RESULTS / "roles.py")
    roles = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(roles)
    policy = load(POLICIES / "sp_seed3_update30.ocv2policy")
    env = policy_env(policy.env)
    played = play_recorded(policy.apply, policy.hidden_size, env, (policy.params,) * 2, jax.random.PRNGKey(7), 4)
    counts = roles.role_counts(played.states)
    assert counts.shape == (len(roles.ROLES), 2)
    assert counts[3].sum() * 20 == float(played.returns.sum()) > 0
    assert counts[0].sum() >= 3 * counts[2].sum() >= 3 * counts[3].sum()  # 3 onions a soup, a soup a delivery
    # Which pot: roles.md finds seed 1 (update 183) putting onions into the first pot only and seed 0 into the other.
    for seed, first_only in ((1, True), (0, False)):
        policy = load(POLICIES / f"sp_seed{seed}_update183.ocv2policy")
        played = play_recorded(policy.apply, policy.hidden_size, env, (policy.params,) * 2, jax.random.PRNGKey(7), 4)
        share = roles.first_pot_share(played.states)
        assert ((share >= 0.95) if first_only else (share <= 0.05)).all(), (seed, share)


def test_roles_reads_another_methods_published_folder_and_names_a_wrong_one(tmp_path):
    """roles.py serves any published Coordination Ring population (--method, --policies); a folder that is not a
    published one, or a method whose files are not listed there, stops it with the reason before anything plays."""
    script = str(RESULTS / "roles.py")
    run = [sys.executable, script, "--update", "183"]
    wrong_folder = subprocess.run([*run, "--policies", str(tmp_path)], capture_output=True, text=True)
    assert wrong_folder.returncode != 0
    assert f"{tmp_path}: no SHA256SUMS.json (not a published policies folder)" in wrong_folder.stderr
    wrong_method = subprocess.run([*run, "--method", "sa", "--policies", str(POLICIES)], capture_output=True, text=True)
    assert wrong_method.returncode != 0
    assert "sa_seed0_update183.ocv2policy: not listed in" in wrong_method.stderr
    no_episodes = subprocess.run([*run, "--episodes", "0"], capture_output=True, text=True)
    assert no_episodes.returncode == 2 and "--episodes" in no_episodes.stderr and "Traceback" not in no_episodes.stderr


def test_a_population_is_one_game_and_one_network_or_the_file_that_differs_is_named(tmp_path):
    """load_population (what roles.py reads with) once played every seed in seed 0's environment: a seed exported
    for a 50-step game, or with another network, is refused by name rather than measured in the wrong game."""
    from population import published
    from population.policy import PolicyError, export

    names = ["sp_seed0_update183.ocv2policy", "sp_seed1_update183.ocv2policy"]
    first, second = (load(POLICIES / name) for name in names)
    for what, env, activation, said in (
        ("game", {**second.env, "max_steps": 50}, second.activation, "plays another environment than"),
        ("network", second.env, "tanh", "plays another network than"),
    ):
        folder = tmp_path / what
        export(folder / names[0], params=first.params, model=first.model, env=first.env, activation=first.activation)
        export(folder / names[1], params=second.params, model=second.model, env=env, activation=activation)
        published.write_listing(
            folder,
            [
                published.PublishedPolicy(n, seed, 183, None, published.sha256_of(folder / n))
                for seed, n in enumerate(names)
            ],
        )
        with pytest.raises(PolicyError, match=f"{names[1]}: {said} {names[0]}"):
            published.load_population(folder, names)
    loaded = published.load_population(POLICIES, names)
    assert [p.env for p in loaded] == [first.env, first.env]
    with pytest.raises(PolicyError, match="max_steps: 50 vs 400"):
        published.load_population(tmp_path / "game", names)


def _copy_listed_folder(tmp_path) -> Path:
    """A copy of a small published folder (Asymm. Advantages SA: its snapshots so far, update 30 among them)."""
    source = RESULTS.parent / "table1_asymm_advantages_sa10" / "policies"
    listing = json.loads((source / "SHA256SUMS.json").read_text())
    folder = tmp_path / "policies"
    folder.mkdir()
    for name in ["SHA256SUMS.json", *(entry["file"] for entry in listing)]:
        (folder / name).write_bytes((source / name).read_bytes())
    return folder


def test_ocv2_verify_passes_a_whole_folder_and_names_every_problem_of_a_changed_one(tmp_path, capsys):
    folder = _copy_listed_folder(tmp_path)
    listed = len(json.loads((folder / "SHA256SUMS.json").read_text()))  # grows as the study is published
    assert main(["verify", str(folder)]) == 0
    assert f"{folder}: all {listed} files match SHA256SUMS.json" in capsys.readouterr().out
    # A copy under another seed's name, a listed file gone, a file nobody listed: each named, all of them.
    (folder / "sa_seed8_update30.ocv2policy").write_bytes((folder / "sa_seed0_update30.ocv2policy").read_bytes())
    (folder / "sa_seed9_update30.ocv2policy").unlink()
    (folder / "mine.ocv2policy").write_bytes((folder / "sa_seed1_update30.ocv2policy").read_bytes())
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["verify", str(folder), str(empty)]) == 1
    captured = capsys.readouterr()
    assert "files match" not in captured.out
    for line in (
        f"{folder / 'sa_seed8_update30.ocv2policy'}: not the published file",
        f"{folder / 'sa_seed9_update30.ocv2policy'}: listed in SHA256SUMS.json but missing",
        f"{folder / 'mine.ocv2policy'}: not listed in SHA256SUMS.json",
        f"{empty}: no SHA256SUMS.json (not a published policies folder)",
        f"2 of 2 folders failed: {folder}, {empty}",
    ):
        assert line in captured.err, line


def test_xp_refuses_a_file_its_listing_names_with_other_bytes_and_records_what_it_played(tmp_path, caplog):
    """A renamed copy beside a SHA256SUMS.json once played as the seed it was named after; now it is refused before
    anything plays, an unlisted file beside a listing is played with a warning, and each file's sha256 is kept."""
    folder = _copy_listed_folder(tmp_path)
    renamed = folder / "sa_seed8_update30.ocv2policy"
    renamed.write_bytes((folder / "sa_seed0_update30.ocv2policy").read_bytes())
    with pytest.raises(crossplay.CrossPlayError) as refused:
        crossplay.resolve_source(str(renamed))
    assert str(refused.value).startswith(f"{renamed}: not the published file (its sha256 ")  # named once
    linked = tmp_path / "seed8.ocv2policy"  # a link elsewhere to the renamed copy: checked where it points
    linked.symlink_to(renamed)
    with pytest.raises(crossplay.CrossPlayError, match="not the published file"):
        crossplay.resolve_source(str(linked))
    listed = crossplay.resolve_source(str(folder / "sa_seed1_update30.ocv2policy"))
    expected = hashlib.sha256((folder / "sa_seed1_update30.ocv2policy").read_bytes()).hexdigest()
    assert (listed.file.sha256, listed.file.listing, listed.file.listed) == (expected, folder / "SHA256SUMS.json", True)
    stray = folder / "mine.ocv2policy"
    stray.write_bytes((folder / "sa_seed1_update30.ocv2policy").read_bytes())
    with caplog.at_level(logging.WARNING):
        assert crossplay.resolve_source(str(stray)).file.listed is False
    assert f"{stray}: not listed in {folder / 'SHA256SUMS.json'} beside it" in caplog.text
    alone = tmp_path / "alone.ocv2policy"
    alone.write_bytes(stray.read_bytes())
    assert crossplay.resolve_source(str(alone)).file.listing is None


def test_a_listing_that_names_a_path_an_empty_one_or_a_folder_is_a_problem_named(tmp_path, capsys):
    """A listing entry "../x" or "/etc/x" would compare a file outside the folder; ocv2 verify once passed it."""
    folder = _copy_listed_folder(tmp_path)
    listing = json.loads((folder / "SHA256SUMS.json").read_text())
    outside = tmp_path / "outside.ocv2policy"
    outside.write_bytes((folder / listing[0]["file"]).read_bytes())
    listing[0]["file"] = "../outside.ocv2policy"
    (folder / "SHA256SUMS.json").write_text(json.dumps(listing))
    assert main(["verify", str(folder)]) == 1
    assert "entry file '../outside.ocv2policy' is not a file name in the listing's folder" in capsys.readouterr().err
    # ocv2 xp, given a file beside that listing, says which listing and what to do
    with pytest.raises(crossplay.CrossPlayError, match="not a file name in the listing's folder; repair it, or move"):
        crossplay.resolve_source(str(folder / listing[1]["file"]))
    (folder / "SHA256SUMS.json").write_text("[]")
    for path in folder.glob("*.ocv2policy"):
        path.unlink()
    assert main(["verify", str(folder)]) == 1
    assert f"{folder / 'SHA256SUMS.json'}: lists no policies" in capsys.readouterr().err
    (folder / "SHA256SUMS.json").write_text("[" * 100_000)  # json.loads once ended verify in a RecursionError
    assert main(["verify", str(folder)]) == 1
    assert "SHA256SUMS.json: not JSON (JSON nested deeper than 32 levels)" in capsys.readouterr().err
    (folder / "SHA256SUMS.json").unlink()
    (folder / "SHA256SUMS.json").mkdir()
    assert main(["verify", str(folder)]) == 1
    assert "SHA256SUMS.json: a folder, not the listing file" in capsys.readouterr().err


def test_the_python_snippet_of_the_results_index_runs_as_pasted(capsys, monkeypatch):
    """docs/results/README.md shows how to load two published files and play them; it must keep working."""
    monkeypatch.chdir(RESULTS.parents[2])  # the repository root, where a reader runs it
    text = (RESULTS.parent / "README.md").read_text()
    (snippet,) = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    exec(compile(snippet, "docs/results/README.md", "exec"), {})
    seed, update, mean = capsys.readouterr().out.split()
    assert (seed, update) == ("1", "183") and 0 <= float(mean) <= 400
