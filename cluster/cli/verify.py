"""``ocv2 verify``: check published policies folders against their SHA256SUMS.json before trusting a number.

    ocv2 verify docs/results/table1_cramped_room_sa10/policies [MORE_FOLDERS ...]

Every listed file must be there with the listed bytes, and every policy file there must be listed (publishing
never leaves one unlisted). Prints one line per folder that is whole; names every problem of the others and exits
with 1. ``ocv2 xp`` checks each policy file it is given against the listing beside it too, and records the sha256
of the files it played in its summary.json.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from cluster.cli.errors import EXIT_FAILURE, EXIT_OK, CLIError
from population.policy import PolicyError
from population.published import SUMS, folder_problems

log = logging.getLogger(__name__)


def add_verify(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 verify`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "verify",
        help=f"check published policies folders against their {SUMS}",
        description=f"Check that every file a published policies folder's {SUMS} lists is there with the listed "
        "sha256, and that every policy file there is listed.",
    )
    parser.add_argument("folders", nargs="+", type=Path, metavar="FOLDER", help="published policies folders")
    return parser


def run_verify(args) -> int:
    """Check every folder; ``CLIError`` (exit 1) after all are checked if any has a problem, each problem logged."""
    failed = []
    for folder in args.folders:
        try:
            listing, problems = folder_problems(folder)
        except PolicyError as error:
            log.error("%s", error)
            failed.append(str(folder))
            continue
        for problem in problems:
            log.error("%s", problem)
        if problems:
            failed.append(str(folder))
        else:
            print(f"{folder}: all {len(listing)} files match {SUMS}")
    if failed:
        raise CLIError(f"{len(failed)} of {len(args.folders)} folders failed: {', '.join(failed)}", EXIT_FAILURE)
    return EXIT_OK
