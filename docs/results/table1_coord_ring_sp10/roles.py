"""Who does what, per seat, in each Coordination Ring seed's self-play: the role split beside the ring direction.

    python docs/results/table1_coord_ring_sp10/roles.py --update 61 [--episodes 32]
    python docs/results/table1_coord_ring_sp10/roles.py --update 183 --method sa --policies DIR   # another population

Reads the published policies (``<policies>/<method>_seed<i>_update<U>.ocv2policy``, by default this folder's
``policies/sp_seed...``, checked against the folder's SHA256SUMS.json) and
plays each seed with itself for N episodes (sampled actions, a fixed key), keeping every state. Per seat, from the
held item before and after each transition and the cell the cook faces (read by ``population.behaviour``):

- onions put into a pot (a raw ingredient leaves the hand while facing a pot),
- dishes picked up (an empty hand takes a plate, from the pile or a counter),
- soups plated (a plate becomes a cooked dish while facing a pot),
- deliveries (a cooked dish leaves the hand while facing the serving window);

each as a share of the pair's total, the clockwise share of the seat's ring moves (as ring_direction.py in
table1_coord_ring/ measures it), and which pot the onions go into: Coordination Ring has two, and the share of each
seat's onions that go into the first in reading order (row 0, column 3; the other is row 1, column 4). Two seeds whose agents split the work the same way per seat, and walk the same
way, have the same convention; a seed on another one is where low cross-play pairs are to be expected.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

from cluster.cli.args import add_published_population, published_files
from population.behaviour import ROLES, clockwise_moves, pot_use, role_counts
from population.policy import PolicyError, policy_env
from population.published import load_population
from population.record import jitted_play_recorded

HERE = Path(__file__).resolve().parent
RING_CENTRE = (2, 2)  # (x, y) of Coordination Ring's centre counter, as ring_direction.py in table1_coord_ring/


def first_pot_share(states) -> np.ndarray:
    """Per seat, the share of the onions it puts into a pot that go into the layout's first pot in reading order
    (NaN: none)."""
    return pot_use(states).shares()[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_published_population(parser, HERE / "policies")
    args = parser.parse_args()
    files = published_files(args)
    try:  # checked sums, one game, one network, coord_ring (the cells read are its own)
        policies = load_population(args.policies, files, layout="coord_ring")
    except PolicyError as error:
        sys.exit(str(error))
    header = " | ".join(f"{role} (seat 0 share)" for role in ROLES)
    print(
        f"| seed | clockwise share (seat 0, seat 1) | {header} | onions into the first pot (seat 0, seat 1) | return |"
    )
    print("|---:|---|" + "---:|" * len(ROLES) + "---|---:|")
    first = policies[0]  # one compiled self-play rollout for every seed (same network, same env)
    play = jitted_play_recorded(first.apply, first.hidden_size, policy_env(first.env), args.episodes)
    for seed, policy in enumerate(policies):
        played = play((policy.params, policy.params), jax.random.PRNGKey(7))
        clockwise, moves = clockwise_moves(played.states.agents.x, played.states.agents.y, RING_CENTRE, time_axis=1)
        share = clockwise / np.maximum(moves, 1)
        counts = role_counts(played.states)
        cells = [f"{c[0] / max(c.sum(), 1):.2f} of {int(c.sum())}" for c in counts]
        pot = first_pot_share(played.states)
        print(
            f"| {seed} | {share[0]:.2f}, {share[1]:.2f} | " + " | ".join(cells)
            + f" | {pot[0]:.2f}, {pot[1]:.2f} | {float(np.mean(played.returns)):.1f} |",
            flush=True,
        )  # fmt: skip


if __name__ == "__main__":
    main()
