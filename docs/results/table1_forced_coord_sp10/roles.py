"""Where each Forced Coord. seed hands things over, in its self-play: the convention its cross-play depends on.

    python docs/results/table1_forced_coord_sp10/roles.py --update 183 [--episodes 32]
    python docs/results/table1_forced_coord_sp10/roles.py --update 183 --method sa --policies DIR   # another population
    python docs/results/table1_forced_coord_sp10/roles.py --update 183 --pairs 3,7 7,3   # cross-play pairs too

Forced Coord. splits the kitchen with a wall: seat 1 starts on the left, beside the onions and the plates, and seat 0
on the right, beside both pots and the serving window. Neither can cook alone, so every onion and every plate crosses
one of the three counters in the middle (x = 2, rows 1 to 3). Which counters a seed uses, whether it passes plates
before the soup is done, and which pot it fills are its convention; a pair from two seeds whose conventions differ
is where cross-play fails.

Reads the published policies (``<policies>/<method>_seed<i>_update<U>.ocv2policy``, by default this folder's
``policies/``, checked against the folder's SHA256SUMS.json) and plays each seed with itself for N episodes (sampled
actions, a fixed key), keeping every state; ``population.behaviour`` reads the events. Per seed, one table row;
with ``--pairs``, one more per ordered pair ``i,j`` (seat 0, the right cook, from seed i; seat 1 from seed j):

- onions and plates put down on each middle counter (by either seat, as a share of that item's put-downs; the
  count beside it), and how many were put down anywhere else;
- the share of those put down on the middle counters that the right cook (seat 0) took up (a pair whose right cook
  does not collect what the left one hands over leaves it lying there);
- plates handed over per soup delivered (1.0: one plate crosses for each soup; more: plates wait on the counter);
- the share of the right seat's onions that go into the top pot (3, 0) rather than the right one (4, 1);
- the mean return.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from cluster.cli.roles_table import print_roles_table
from population.behaviour import ITEM_KINDS, counter_use, pot_use, role_counts

HERE = Path(__file__).resolve().parent
MIDDLE = ((2, 1), (2, 2), (2, 3))  # (x, y) of the counters between the two rooms
HANDED = ("ingredient", "plate")
RIGHT_SEAT = 0  # starts beside the pots: seat order is the layout's reading order


class Handover(NamedTuple):
    """One item kind's trips across the middle counters (both seats together)."""

    shares: np.ndarray  # float[3]: each MIDDLE counter's share of the put-downs there
    put: int  # put down on the middle counters
    taken: int  # taken up from them by the right cook
    elsewhere: int  # put down on any other counter


def handovers(states) -> dict[str, Handover]:
    """Per handed item kind (HANDED), its trips across the middle counters in a recorded play."""
    use = counter_use(states)
    cells = [tuple(c) for c in use.cells.tolist()]

    def middle(counts: np.ndarray) -> np.ndarray:
        return np.array([counts[cells.index(c)] if c in cells else 0 for c in MIDDLE])

    out = {}
    for kind in HANDED:
        put = use.put[:, ITEM_KINDS.index(kind), :].sum(axis=1)
        taken = use.taken[:, ITEM_KINDS.index(kind), RIGHT_SEAT]
        on_middle = middle(put)
        total = int(on_middle.sum())
        out[kind] = Handover(on_middle / max(total, 1), total, int(middle(taken).sum()), int(put.sum()) - total)
    return out


def table_header() -> str:
    counters = "/".join(f"({x},{y})" for x, y in MIDDLE)
    return (
        f"| seed | onions on {counters} (of n; elsewhere) | onions the right cook took | plates on {counters} (of n; elsewhere) "
        "| plates the right cook took | plates handed per soup | right seat's onions into the top pot | return |\n"
        "|---:|---|---:|---|---:|---:|---:|---:|"
    )


def seed_row(label, states, returns) -> str:
    """One table row for a recorded play (states [E, T+1, ...], returns [E]) of a seed or a pair (``label``)."""
    trips = handovers(states)
    cells = []
    for kind in HANDED:
        trip = trips[kind]
        cells.append("/".join(f"{s:.2f}" for s in trip.shares) + f" (of {trip.put}; {trip.elsewhere})")
        cells.append(f"{trip.taken / trip.put:.2f}" if trip.put else "none put")
    delivered = int(role_counts(states)[3].sum())
    per_soup = f"{trips['plate'].put / delivered:.2f}" if delivered else "no soup"
    top = pot_use(states).shares()[0, RIGHT_SEAT]
    top_cell = "none in" if np.isnan(top) else f"{top:.2f}"
    return f"| {label} | " + " | ".join(cells) + f" | {per_soup} | {top_cell} | {float(np.mean(returns)):.1f} |"


def main() -> None:
    print_roles_table(__doc__.split("\n\n")[0], HERE / "policies", "forced_coord", table_header(), seed_row)


if __name__ == "__main__":
    main()
