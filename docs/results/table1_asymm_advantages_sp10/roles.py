"""Who does what in each Asymm. Advantages seed's self-play, and which pot: the conventions its cross-play needs.

    python docs/results/table1_asymm_advantages_sp10/roles.py --update 183 [--episodes 32]
    python docs/results/table1_asymm_advantages_sp10/roles.py --update 183 --pairs 1,2 2,1   # cross-play pairs too

Asymm. Advantages is two rooms with a wall between them, x = 0 to 8: the two pots (4, 2) and (4, 3) sit in that wall,
and each cook reaches both from its own room; nothing else joins the rooms. Seat 0 starts in the left room (2, 3),
whose onion pile (0, 1) is far from both pots and whose serving window (3, 1) is beside the top one; seat 1 starts in
the right room (5, 3), whose onion pile (5, 1) is beside the top pot and whose serving window (8, 1) is far. Each
room's plates, (3, 4) and (5, 4), are beside the bottom pot. A cook serves only at its own room's window, so its
deliveries say where a soup went out.

Reads the published policies (``<policies>/<method>_seed<i>_update<U>.ocv2policy``, by default this folder's
``policies/``, checked against the folder's SHA256SUMS.json) and plays each seed with itself for N episodes (sampled
actions, a fixed key), keeping every state; ``population.behaviour`` reads the events. Per seed, one table row; with
``--pairs``, one more per ordered pair ``i,j`` (seat 0 from seed i, seat 1 from seed j):

- seat 0's share of each job: onions put into a pot, dishes picked up, soups plated, soups delivered (of the pair's
  total, the count beside it);
- each seat's share of its onions that went into the top pot (4, 2) rather than the bottom one (4, 3);
- each seat's share of the soups it plated that came from the top pot;
- the share of the steps in which a cooked soup waits in the top pot, and in the bottom pot, to be plated;
- the mean return.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cluster.cli.roles_table import JOB_HEADERS, job_cells, print_roles_table, table_row
from ocv2.items import COOKED
from population.behaviour import ROLES, pot_use, role_counts, transitions

HERE = Path(__file__).resolve().parent
TOP_POT = (4, 2)
BOTTOM_POT = (4, 3)


def plated_from_top(states) -> np.ndarray:
    """float[seat]: the share of each seat's plated soups taken from the top pot (NaN: it plated none)."""
    t = transitions(states)
    plated = t.soup_plated
    top = plated & (t.faced_x == TOP_POT[0]) & (t.faced_y == TOP_POT[1])
    with np.errstate(invalid="ignore"):
        return top.sum(axis=(0, 1)) / plated.sum(axis=(0, 1))


def soup_waiting(states) -> list[float]:
    """The share of the recorded states in which a cooked soup sits in the top pot, and in the bottom pot, waiting to be
    plated (the pot holds a cooked soup and its timer has run out)."""
    grid = np.asarray(states.grid)  # [E, T+1, H, W, layer]: layer 1 the pot's contents, layer 2 its cooking timer
    waiting = []
    for x, y in (TOP_POT, BOTTOM_POT):
        contents, timer = grid[:, :, y, x, 1], grid[:, :, y, x, 2]
        waiting.append(float((((contents & COOKED) != 0) & (timer == 0)).mean()))
    return waiting


def table_header() -> str:
    return (
        f"| seed | {JOB_HEADERS} | onions into the top pot (seat 0, seat 1) | soups plated from the top pot (seat 0, seat 1) "
        "| steps a cooked soup waits (top pot, bottom pot) | return |\n|---:|"
        + "---:|" * len(ROLES)
        + "---|---|---|---:|"
    )


def shares(values) -> str:
    return ", ".join("none" if np.isnan(v) else f"{v:.2f}" for v in values)


def seed_row(label, states, returns) -> str:
    """One table row for a recorded play (states [E, T+1, ...], returns [E]) of a seed or a pair (``label``)."""
    use = pot_use(states)
    top = [tuple(cell) for cell in use.cells.tolist()].index(TOP_POT)
    cells = [
        *job_cells(role_counts(states)),
        shares(use.shares()[top]),
        shares(plated_from_top(states)),
        ", ".join(f"{v:.2f}" for v in soup_waiting(states)),
        f"{float(np.mean(returns)):.1f}",
    ]
    return table_row(label, cells)


def main() -> None:
    print_roles_table(__doc__.split("\n\n")[0], HERE / "policies", "asymm_advantages", table_header(), seed_row)


if __name__ == "__main__":
    main()
