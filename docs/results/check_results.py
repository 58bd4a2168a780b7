"""Recompute the numbers of docs/RESULTS.md from the files under docs/results/ and compare them with the page.

    python docs/results/check_results.py [--doc docs/RESULTS.md] [--quiet]

Design. A number on the page is checked when it stands inside a tagged span,

    <!-- check:NAME -->SP 219.9, XP 209.4, gap 10.6 (95 % interval over 4 seeds: 1.4 to 29.0)<!-- /check -->

and this script has a function registered as NAME (``@check("NAME")``, in the package checks/ beside it) that
recomputes, from the committed files, the numbers that the span writes, in the order it writes them. A span may be a few words
inside a sentence or a table cell, or a whole table (tag lines around it): in a table's lines the header row,
the separator row and the first cell of every row are labels and are not read. Every other number in the span
is read: digits with optional sign, thousands commas and decimals ("-3.1", "4,997,120", "5.0M" reads 5.0,
"29.8x" reads 29.8); a hyphen after a digit is a range ("0.68-0.72" reads 0.68 and 0.72); "95 %" (the interval
level), recipe names such as 0+0+0 and digits inside identifiers (seed_0) are not numbers. A function returns
one value per number read; ``None`` marks a label that the span must contain but that is not compared.

A number matches at the precision it is written: written with d decimals, it must lie within half a unit of
its last digit of the recomputed value (so 9.648 may be written 9.6 or 9.65 but not 9.7; a tie such as 9.5
may be written 9 or 10). Durations written "X h Y min" are compared as hours and whole minutes of the rounded
total. The script prints one line per number (``--quiet``: only the mismatches) and exits 1 on any mismatch,
on a span whose count of numbers differs from its function's, on a tag without a function and on a function
without a tag (so a check cannot silently drop out of the page). tests/test_results_doc.py runs it.

What it reads: the two studies' summary.json, the cross-play matrices (xp_*.csv), the GCS runs' metrics.csv and
per-episode cross-play returns, the interim cross-plays (xp12_update61/, xp_sp_sa_update152/ and 244/), the
tables of ring_direction.md and button_use.md (written by the scripts beside them from the lost run
directories), the Coordination Ring layout in ocv2/layouts.py (parsed as text), and the 10-seed SP and SA studies'
folders (summary.json, xp_*.csv, roles.md, the policies' SHA256SUMS.json), and the GPU study's folders
(gpu_coord_ring_sp/ and its update-410 cross-play, gpu_coord_ring_sp_update410/). JAX is imported for the checks
that take an interval the way the reports do: study_delta and gpu410_vs_3m (population.xp.bootstrap_difference)
and the gpu410 checks (population.xp.block_summary). The checks live in checks/ beside this script, one module per
part of the page on top of the modules that read the page and the data (checks/__init__.py lists them).

What it cannot check, and why (the page says so where they stand): the Coordination Ring training-return
tables and every Coordination Ring speed (no metrics.csv of those runs was committed; their run directories
were lost with the machine), the 1.5M pilot of the Coordination Ring SP run, the first GCS start's speed, the
per-snapshot cross-play durations, the 8 more seeds' loss at update 70, and the session times of day; no file
under docs/results/ records them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # the repository, for population.xp (study_delta) outside an install
sys.path.insert(0, str(HERE))  # this folder, for checks/ where the script is loaded from its path rather than run
# Import the checks without writing checks/__pycache__: tests/test_published_policies.py fails on any file under
# docs/results/ that git ignores.
dont_write_bytecode, sys.dont_write_bytecode = sys.dont_write_bytecode, True
from checks import (  # noqa: E402  (after the paths above)
    asymm_advantages,
    coord_ring_4_seeds,
    coord_ring_10_seeds,
    counter_circuit,
    cramped_room,
    forced_coord,
    gpu_coord_ring,
    grounded_coord_simple,
    opening_sections,
    ten_seed_rows,
)
from checks.comparison import compare  # noqa: E402
from checks.data import cr_sa, cr_sp, gcs_sp, hm, pairs  # noqa: E402
from checks.four_seed_bootstrap import gap_at_most_zero, resamples  # noqa: E402
from checks.page import matches, read_numbers  # noqa: E402
from checks.registry import CHECKS  # noqa: E402

sys.dont_write_bytecode = dont_write_bytecode

DOC = HERE.parent / "RESULTS.md"
# The modules of checks, by part of the page: importing one registers its checks in CHECKS.
CHECK_MODULES = (
    opening_sections,
    coord_ring_4_seeds,
    coord_ring_10_seeds,
    gpu_coord_ring,
    forced_coord,
    counter_circuit,
    cramped_room,
    asymm_advantages,
    grounded_coord_simple,
    ten_seed_rows,
)
# What tests/test_results_doc.py reads from this script besides compare: the reading rules and the 4-seed bootstrap.
__all__ = [
    "CHECKS",
    "compare",
    "cr_sa",
    "cr_sp",
    "gap_at_most_zero",
    "gcs_sp",
    "hm",
    "main",
    "matches",
    "pairs",
    "read_numbers",
    "resamples",
]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--doc", type=Path, default=DOC, help="the page to check (default docs/RESULTS.md)")
    parser.add_argument("--quiet", action="store_true", help="print only mismatches and errors")
    args = parser.parse_args(argv)
    rows, errors = compare(args.doc.read_text())
    print("| check | # | written | recomputed | |\n|---|---:|---:|---:|---|")
    for name, k, token, value, ok in rows:
        if ok and args.quiet:
            continue
        shown = "label" if value is None else f"{value:.4f}".rstrip("0").rstrip(".")
        print(f"| {name} | {k} | {token} | {shown} | {'ok' if ok else 'MISMATCH'} |")
    bad = [r for r in rows if not r[4]]
    for error in errors:
        print(f"ERROR {error}")
    checked = sum(1 for r in rows if r[3] is not None)
    print(
        f"{checked} numbers in {len({r[0] for r in rows})} spans compared with the files under docs/results/: "
        f"{len(bad)} mismatches, {len(errors)} errors"
    )
    return 1 if bad or errors else 0


if __name__ == "__main__":
    sys.exit(main())
