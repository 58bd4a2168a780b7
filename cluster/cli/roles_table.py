"""The shared ``main`` of the results scripts that read a published population's conventions (``roles.py`` under
``docs/results/<study>/``): play each seed with itself, and any ``--pairs i,j`` in cross-play, then print one
table row per play. The script says what a row holds; this module only parses, loads, plays and prints."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import jax

from cluster.cli.args import add_published_population, published_files, published_pairs
from population.behaviour import ROLES
from population.numerics import DEFAULT_PRECISION, matmul_precision
from population.policy import PolicyError, policy_env
from population.published import load_population
from population.record import jitted_play_recorded

ROLLOUT_KEY = 7  # the same sampled actions in every script and every run


def print_roles_table(
    description: str, default_folder: Path, layout: str, header: str, row: Callable, argv=None
) -> None:
    """Parse --update/--episodes/--seeds/--method/--policies/--pairs (``argv``, default sys.argv), load the policies
    (checked sums, one game, one network, ``layout`` only: the cells a script reads are its layout's), print
    ``header`` and then ``row(label, states [E, T+1, ...], returns [E])`` for each seed's self-play and each pair."""
    parser = argparse.ArgumentParser(description=description)
    add_published_population(parser, default_folder, pairs=True)
    args = parser.parse_args(argv)
    pairs = published_pairs(parser, args)
    try:
        policies = load_population(args.policies, published_files(args), layout=layout)
    except PolicyError as error:
        sys.exit(str(error))
    print(header)
    first = policies[0]  # one compiled rollout for every seed and pair (same network, same env)
    play = jitted_play_recorded(first.apply, first.hidden_size, policy_env(first.env), args.episodes)
    plays = [(str(seed), seed, seed) for seed in range(args.seeds)] + [(f"{i} × {j}", i, j) for i, j in pairs]
    # As the population trained (its run.precision; float32 for files exported before it was recorded): on a GPU the
    # default would be TF32.
    with matmul_precision(first.meta.get("precision") or DEFAULT_PRECISION):
        for label, seat0, seat1 in plays:
            played = play((policies[seat0].params, policies[seat1].params), jax.random.PRNGKey(ROLLOUT_KEY))
            print(row(label, played.states, played.returns), flush=True)


def table_row(label, cells) -> str:
    """One markdown table row: ``label`` (a seed, or a pair "i × j") then ``cells``."""
    return f"| {label} | " + " | ".join(cells) + " |"


#: The header cells of the four jobs (``population.behaviour.ROLES``), each as seat 0's share.
JOB_HEADERS = " | ".join(f"{role} (seat 0 share)" for role in ROLES)


def job_cells(counts) -> list[str]:
    """Seat 0's share of each job (``role_counts``: int[len(ROLES), seat]) and the pair's count ("none" for a job
    nobody did)."""
    return [f"{c[0] / c.sum():.2f} of {int(c.sum())}" if c.sum() else "none" for c in counts]
