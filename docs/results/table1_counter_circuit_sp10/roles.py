"""Who does what, and which way round, in each Counter Circuit seed's self-play: the conventions its cross-play needs.

    python docs/results/table1_counter_circuit_sp10/roles.py --update 183 [--episodes 32]
    python docs/results/table1_counter_circuit_sp10/roles.py --update 183 --method sa --policies DIR   # another population
    python docs/results/table1_counter_circuit_sp10/roles.py --update 183 --pairs 3,7 7,3   # cross-play pairs too

Counter Circuit is a loop of floor round a counter island (x = 2 to 5, y = 2): both pots at the top (3, 0) and (4, 0),
both onion piles at the bottom (3, 4) and (4, 4), the plates on the left (0, 2) and the serving window on the right
(7, 2). Seat 0 starts at the bottom right (6, 3), beside the onions, and seat 1 at the top left (2, 1), beside the
pots. A cook can carry each onion round the loop, or the one below can put it on the island for the one above to
take up: a short cut. Which way the cooks circle, whether they pass over the island and which pot they fill are the
conventions a seed settles on; a pair from two seeds whose conventions differ is where cross-play fails.

Reads the published policies (``<policies>/<method>_seed<i>_update<U>.ocv2policy``, by default this folder's
``policies/``, checked against the folder's SHA256SUMS.json) and plays each seed with itself for N episodes (sampled
actions, a fixed key), keeping every state; ``population.behaviour`` reads the events. Per seed, one table row; with
``--pairs``, one more per ordered pair ``i,j`` (seat 0 from seed i, seat 1 from seed j):

- seat 0's share of each job: onions put into a pot, dishes picked up, soups plated, soups delivered (of the pair's
  total, the count beside it);
- the clockwise share of each seat's moves round the island as the layout is drawn (y grows downward, so a rise of
  atan2(y - 2, x - 3.5) about the island's centre is clockwise on screen);
- onions put down on the island per onion that went into a pot (1.0: every onion crossed the island), and seat
  0's share of those put-downs;
- plates put down on the island per soup delivered, and seat 0's share of those put-downs;
- each seat's share of its onions that went into the left pot (3, 0) rather than the right one (4, 0);
- the mean return.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cluster.cli.roles_table import JOB_HEADERS, job_cells, print_roles_table, table_row
from population.behaviour import ITEM_KINDS, ROLES, clockwise_moves, counter_use, pot_use, role_counts

HERE = Path(__file__).resolve().parent
ISLAND = tuple((x, 2) for x in range(2, 6))  # (x, y) of the counters inside the loop
CENTRE = (3.5, 2.0)  # the island's centre, (x, y)


def island_put_downs(states, kind: str) -> np.ndarray:
    """int[seat]: the items of ``kind`` (ITEM_KINDS) each seat put down on the island."""
    use = counter_use(states)
    rows = [k for k, cell in enumerate(use.cells.tolist()) if tuple(cell) in ISLAND]
    return use.put[rows, ITEM_KINDS.index(kind), :].sum(axis=0)


def clockwise_share(x, y) -> np.ndarray:
    """Per seat, the share of its moves round the island that go clockwise on screen (NaN: it never moved).
    ``x``, ``y``: positions [E, T+1, seat]."""
    clockwise, moves = clockwise_moves(x, y, CENTRE, time_axis=1)
    with np.errstate(invalid="ignore"):
        return clockwise / moves


def table_header() -> str:
    return (
        f"| seed | {JOB_HEADERS} | clockwise share (seat 0, seat 1) | onions over the island per onion potted (seat 0 share) "
        "| plates over the island per soup (seat 0 share) | onions into the left pot (seat 0, seat 1) | return |\n"
        "|---:|" + "---:|" * len(ROLES) + "---|---|---:|---|---:|"
    )


def seed_row(label, states, returns) -> str:
    """One table row for a recorded play (states [E, T+1, ...], returns [E]) of a seed or a pair (``label``)."""
    counts = role_counts(states)
    jobs = job_cells(counts)
    turn = clockwise_share(states.agents.x, states.agents.y)
    onions, plates = island_put_downs(states, "ingredient"), island_put_downs(states, "plate")
    potted, delivered = int(counts[0].sum()), int(counts[3].sum())
    over = f"{onions.sum() / potted:.2f}" if potted else "none potted"
    over += f" ({onions[0] / onions.sum():.2f})" if onions.sum() else ""
    per_soup = f"{plates.sum() / delivered:.2f}" if delivered else "no soup"
    per_soup += f" ({plates[0] / plates.sum():.2f})" if plates.sum() else ""
    left = pot_use(states).shares()[0]
    cells = [
        *jobs,
        ", ".join("-" if np.isnan(v) else f"{v:.2f}" for v in turn),
        over,
        per_soup,
        ", ".join("none in" if np.isnan(v) else f"{v:.2f}" for v in left),
        f"{float(np.mean(returns)):.1f}",
    ]
    return table_row(label, cells)


def main() -> None:
    print_roles_table(__doc__.split("\n\n")[0], HERE / "policies", "counter_circuit", table_header(), seed_row)


if __name__ == "__main__":
    main()
