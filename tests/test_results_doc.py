"""docs/RESULTS.md matches the files under docs/results/: docs/results/check_results.py recomputes
every tagged number of the page and fails on any that differs at the precision written. No training, no JAX."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "results" / "check_results.py"
DOC = ROOT / "docs" / "RESULTS.md"


@pytest.fixture(scope="module")
def checker():
    spec = importlib.util.spec_from_file_location("check_results", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_results_page_matches_its_data():
    result = run("--quiet")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "0 mismatches, 0 errors" in result.stdout


def test_the_checker_covers_the_headline_numbers(checker):
    """The page's headline blocks are tagged (a check cannot drop out unnoticed: the script fails on a
    registered check without a span), and the page has well over a thousand checked numbers."""
    rows, errors = checker.compare(DOC.read_text())
    assert not errors
    names = {row[0] for row in rows}
    for name in (
        "top_cr_sp",
        "top_cr_sa",
        "top_gcs_sp",
        "top_gcs_fcp",
        "cr_sp_over_training",
        "cr_sa_over_training",
        "gcs_sp_training",
        "gcs_fcp_speed",
        "xp12_wall",
        "four_seed_gap_zero",
        "cr_geometry",
    ):
        assert name in names
    assert sum(value is not None for _, _, _, value, _ in rows) > 1000


def altered(tmp_path, old, new):
    text = DOC.read_text()
    assert text.count(old) == 1, old
    path = tmp_path / "RESULTS.md"
    path.write_text(text.replace(old, new))
    return path


def test_an_altered_number_is_caught(tmp_path):
    # the GCS SP training table had 9.7 for seed 1 at update 40, where sp_metrics.csv has 9.648
    path = altered(tmp_path, "| 40 | 2,621,440 | 0.0, 9.6,", "| 40 | 2,621,440 | 0.0, 9.7,")
    result = run("--doc", str(path), "--quiet")
    assert result.returncode == 1
    assert "| gcs_sp_training | 41 | 9.7 | 9.6484 | MISMATCH |" in result.stdout


def test_an_altered_headline_and_a_lost_or_extra_number_are_caught(tmp_path):
    path = altered(
        tmp_path,
        "gap 10.6 (95 % interval over 4 seeds: 1.4\n  to 29.0)",
        "gap 10.7 (95 % interval over 4 seeds: 1.4\n  to 29.0)",
    )
    result = run("--doc", str(path), "--quiet")
    assert result.returncode == 1 and "| top_cr_sp | 2 | 10.7 |" in result.stdout
    path = altered(tmp_path, "(<!-- check:xp12_wall -->83.4 s<!-- /check -->", "(83.4 s")
    result = run("--doc", str(path), "--quiet")
    assert result.returncode == 1 and "xp12_wall: no <!-- check:xp12_wall --> span on the page" in result.stdout
    path = altered(tmp_path, "<!-- check:top_bc -->107.0,", "<!-- check:top_bc -->107.0, 99.9,")
    result = run("--doc", str(path), "--quiet")
    assert result.returncode == 1 and "top_bc (line" in result.stdout and "recomputes 2" in result.stdout


def test_reading_numbers(checker):
    read = checker.read_numbers
    assert read("SP 5.2, XP -3.1, gap 8.3 (95 % interval over 4 seeds: 0.5 to 18.7)") == [
        "5.2",
        "-3.1",
        "8.3",
        "4",
        "0.5",
        "18.7",
    ]
    assert read("clockwise share 0.42-0.45, 2,723-3,057 env steps, 9-46 with -45.0") == [
        "0.42",
        "0.45",
        "2,723",
        "3,057",
        "9",
        "46",
        "-45.0",
    ]
    assert read("recipe 0+0+0 in seat 1 with seed_2 of sp10, 4 x 5.0M, 29.8x") == ["4", "5.0", "29.8"]
    assert read("its seat-0 partner, [the table](#intervals-at-4-seeds)") == []
    table = "| update | seeds 0-3 |\n|---:|---|\n| 10 | -0.5, 0.1 |\n| 20 | 0.0, **7.6** ± 1.1 |"
    assert read(table) == ["-0.5", "0.1", "0.0", "7.6", "1.1"]


def test_numbers_match_at_the_precision_written(checker):
    assert checker.matches("9.6", 9.648) and not checker.matches("9.7", 9.648)
    assert checker.matches("-0.1", -0.147) and not checker.matches("-0.2", -0.147)
    assert checker.matches("45", 45.467) and not checker.matches("46", 45.467)
    assert checker.matches("9", 9.5) and checker.matches("10", 9.5)  # a tie may go either way
    assert checker.matches("2,723", 2723.2) and not checker.matches("2,850", 2853.2 + 1)
    assert checker.hm(53930.1) == [14, 59]


def test_the_4_seed_bootstrap_facts(checker):
    """What the page says about 4-seed intervals: 252 resamples with a cross-play cell, the XP interval
    ends are the lowest and the highest pair, and 4 of 252 resamples have a gap <= 0 in the final blocks."""
    import numpy as np

    for m in (checker.cr_sp(), checker.cr_sa(), checker.gcs_sp()):
        r = checker.resamples(m)
        assert len(r) == 252
        low, high = np.percentile(r[:, 1], [2.5, 97.5])
        pairs = checker.pairs(m)
        assert np.isclose(low, min(pairs)) and np.isclose(high, max(pairs))
        assert checker.gap_at_most_zero(m) == [4, 252]


def test_the_checker_imports_no_jax():
    code = f"import runpy, sys; runpy.run_path({str(SCRIPT)!r}, run_name='not_main'); print('jax' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert result.stdout.strip() == "False", result.stdout + result.stderr
