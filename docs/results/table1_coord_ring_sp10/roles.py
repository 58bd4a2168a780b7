"""Who does what, per seat, in each Coordination Ring seed's self-play: the role split beside the ring direction.

    python docs/results/table1_coord_ring_sp10/roles.py --update 61 [--episodes 32]
    python docs/results/table1_coord_ring_sp10/roles.py --update 183 --method sa --policies DIR   # another population
    python docs/results/table1_coord_ring_sp10/roles.py --update 183 --pairs 1,3 3,1   # cross-play pairs too

Reads the published policies (``<policies>/<method>_seed<i>_update<U>.ocv2policy``, by default this folder's
``policies/sp_seed...``, checked against the folder's SHA256SUMS.json) and
plays each seed with itself for N episodes (sampled actions, a fixed key), keeping every state; with ``--pairs i,j``
also each ordered pair (seat 0 from seed i, seat 1 from seed j), one more row each. Per seat, from the
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

from pathlib import Path

import numpy as np

from cluster.cli.roles_table import JOB_HEADERS, print_roles_table
from population.behaviour import ROLES, clockwise_moves, pot_use, role_counts

HERE = Path(__file__).resolve().parent
RING_CENTRE = (2, 2)  # (x, y) of Coordination Ring's centre counter, as ring_direction.py in table1_coord_ring/


def first_pot_share(states) -> np.ndarray:
    """Per seat, the share of the onions it puts into a pot that go into the layout's first pot in reading order
    (NaN: none)."""
    return pot_use(states).shares()[0]


def table_header() -> str:
    return (
        f"| seed | clockwise share (seat 0, seat 1) | {JOB_HEADERS} | onions into the first pot (seat 0, seat 1) | return |\n"
        "|---:|---|" + "---:|" * len(ROLES) + "---|---:|"
    )


def seed_row(label, states, returns) -> str:
    """One table row for a recorded play (states [E, T+1, ...], returns [E]) of a seed or a pair (``label``)."""
    clockwise, moves = clockwise_moves(states.agents.x, states.agents.y, RING_CENTRE, time_axis=1)
    share = clockwise / np.maximum(moves, 1)
    cells = [f"{c[0] / max(c.sum(), 1):.2f} of {int(c.sum())}" for c in role_counts(states)]
    pot = first_pot_share(states)
    return (
        f"| {label} | {share[0]:.2f}, {share[1]:.2f} | " + " | ".join(cells)
        + f" | {pot[0]:.2f}, {pot[1]:.2f} | {float(np.mean(returns)):.1f} |"
    )  # fmt: skip


def main() -> None:
    print_roles_table(__doc__.split("\n\n")[0], HERE / "policies", "coord_ring", table_header(), seed_row)


if __name__ == "__main__":
    main()
