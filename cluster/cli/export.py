"""``ocv2 export``: one trained policy to one file, read without its run directory.

    ocv2 export SRC --out FILE [--force] [--seed I] [--checkpoint final|mid|init|latest|N]

SRC is a run directory (``--seed`` picks the seed, 0 by default), a seed directory
RUN_DIR/checkpoints/seed_<i> or a checkpoint file. The file holds the params, the network and the
environment settings: ``ocv2 xp``, ``population.policy.load`` and ``ocv2 play`` read it. It is never
written inside a run directory, nor over a file without ``--force``.
"""

from __future__ import annotations

import argparse

from cluster.cli.args import check_new_file, checkpoint_choice, non_negative_int, resolved
from cluster.cli.errors import EXIT_OK, CLIError
from cluster.runtime.rundir import enclosing_run
from cluster.study.pack import PACK_NAME
from cluster.study.spec import is_study_directory
from population.policy import CHECKPOINT_CHOICES, PolicyError, export_checkpoint
from population.published import SUMS


def add_export(sub) -> argparse.ArgumentParser:
    """Declare ``ocv2 export`` on ``sub`` (argparse subparsers); returns its parser."""
    parser = sub.add_parser(
        "export",
        help="write one policy (params + network + env settings) to a file",
        description="Export one trained policy to a single file that 'ocv2 xp', "
        "population.policy.load and 'ocv2 play' read without the run directory.",
    )
    parser.add_argument("source", help="run directory, RUN_DIR/checkpoints/seed_<i>, or a checkpoint file")
    parser.add_argument(
        "--out", required=True, help="the file to write (e.g. cook.ocv2policy), never inside a run directory"
    )
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")
    parser.add_argument("--seed", type=non_negative_int, help="which seed of a run directory (default 0)")
    parser.add_argument(
        "--checkpoint",
        default="final",
        help="final (default), mid, init, latest or an update number (run or seed directory)",
    )
    return parser


def run_export(args) -> int:
    """Write the policy ``args.source`` names to ``args.out``; returns ``EXIT_OK``. Raises ``CLIError`` for
    a bad ``--checkpoint``, an ``--out`` that exists (without ``--force``), is a folder or lies inside a run
    directory, and a source that holds no such policy."""
    checkpoint = checkpoint_choice(args.checkpoint, CHECKPOINT_CHOICES)
    check_new_file("--out", args.out, force=args.force)
    run = enclosing_run(resolved(args.out, "--out"))
    if run is not None:  # its config.yaml, checkpoints or results would be replaced by a policy file
        raise CLIError(f"--out {args.out}: lies inside the run directory {run}; write the policy outside it")
    check_outside_kept_folders(args.out)
    try:
        path = export_checkpoint(args.source, args.out, seed=args.seed, checkpoint=checkpoint)
    except PolicyError as error:
        raise CLIError(str(error)) from None
    print(f"wrote {path}")
    return EXIT_OK


def check_outside_kept_folders(out: str) -> None:
    """Refuse an ``--out`` inside a study directory (its study.json is its only state), a published policies folder
    (a file there that SHA256SUMS.json does not list fails ``ocv2 verify``; one it lists would get other bytes) or a
    pack (its parts are checked against pack.json): each is written whole by its own command."""
    parent = resolved(out, "--out").parent
    for folder in (parent, *parent.parents):
        if is_study_directory(folder):
            raise CLIError(f"--out {out}: lies inside the study directory {folder}; write the policy outside it")
    kept = {SUMS: "a published policies folder ('ocv2 study publish' writes it)", PACK_NAME: "a packed study"}
    for name, what in kept.items():
        if (parent / name).is_file():
            raise CLIError(f"--out {out}: {parent} is {what} ({name}); write the policy outside it")
