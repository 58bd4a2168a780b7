"""Where each Forced Coord. seed hands things over, in its self-play: the convention its cross-play depends on.

    python docs/results/table1_forced_coord_sp10/roles.py --update 183 [--episodes 32]
    python docs/results/table1_forced_coord_sp10/roles.py --update 183 --method sa --policies DIR   # another population

Forced Coord. splits the kitchen with a wall: seat 1 starts on the left, beside the onions and the plates, and seat 0
on the right, beside both pots and the serving window. Neither can cook alone, so every onion and every plate crosses
one of the three counters in the middle (x = 2, rows 1 to 3). Which counters a seed uses, whether it passes plates
before the soup is done, and which pot it fills are its convention; a pair from two seeds whose conventions differ
is where cross-play fails.

Reads the published policies (``<policies>/<method>_seed<i>_update<U>.ocv2policy``, by default this folder's
``policies/``, checked against the folder's SHA256SUMS.json) and plays each seed with itself for N episodes (sampled
actions, a fixed key), keeping every state; ``population.behaviour`` reads the events. Per seed, one table row:

- onions and plates put down on each middle counter (by either seat, as a share of that item's put-downs; the
  count beside it), and how many were put down anywhere else;
- plates handed over per soup delivered (1.0: one plate crosses for each soup; more: plates wait on the counter);
- the share of the right seat's onions that go into the top pot (3, 0) rather than the right one (4, 1);
- the mean return.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

from cluster.cli.args import positive_int
from population.behaviour import ITEM_KINDS, counter_use, pot_use, role_counts
from population.policy import PolicyError, load, policy_env
from population.published import verify
from population.record import play_recorded

HERE = Path(__file__).resolve().parent
MIDDLE = ((2, 1), (2, 2), (2, 3))  # (x, y) of the counters between the two rooms
HANDED = ("ingredient", "plate")
RIGHT_SEAT = 0  # starts beside the pots: seat order is the layout's reading order


def handover_shares(states) -> dict[str, tuple[np.ndarray, int, int]]:
    """Per handed item kind: (share put down on each MIDDLE counter [3], total put down there, put down elsewhere)."""
    use = counter_use(states)
    cells = [tuple(c) for c in use.cells.tolist()]
    out = {}
    for kind in HANDED:
        put = use.put[:, ITEM_KINDS.index(kind), :].sum(axis=1)  # both seats
        middle = np.array([put[cells.index(c)] if c in cells else 0 for c in MIDDLE])
        elsewhere = int(put.sum() - middle.sum())
        out[kind] = (middle / max(int(middle.sum()), 1), int(middle.sum()), elsewhere)
    return out


def table_header() -> str:
    counters = "/".join(f"({x},{y})" for x, y in MIDDLE)
    return (
        f"| seed | onions on {counters} (of n; elsewhere) | plates on {counters} (of n; elsewhere) "
        "| plates handed per soup | right seat's onions into the top pot | return |\n|---:|---|---|---:|---:|---:|"
    )


def seed_row(seed: int, states, returns) -> str:
    """One table row for a seed's recorded self-play (states [E, T+1, ...], returns [E])."""
    shares = handover_shares(states)
    cells = []
    for kind in HANDED:
        share, total, elsewhere = shares[kind]
        cells.append("/".join(f"{s:.2f}" for s in share) + f" (of {total}; {elsewhere})")
    delivered = int(role_counts(states)[3].sum())
    per_soup = f"{shares['plate'][1] / delivered:.2f}" if delivered else "no soup"
    top = pot_use(states).shares()[0, RIGHT_SEAT]
    top_cell = "none in" if np.isnan(top) else f"{top:.2f}"
    return f"| {seed} | {cells[0]} | {cells[1]} | {per_soup} | {top_cell} | {float(np.mean(returns)):.1f} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--update", type=int, required=True, help="the snapshot (<method>_seed<i>_update<U>)")
    parser.add_argument("--episodes", type=positive_int, default=32)
    parser.add_argument("--seeds", type=positive_int, default=10)
    parser.add_argument("--method", default="sp", help="the file names' method prefix (sp, sa, ...)")
    parser.add_argument("--policies", type=Path, default=HERE / "policies", help="a published policies folder")
    args = parser.parse_args()
    files = [args.policies / f"{args.method}_seed{seed}_update{args.update}.ocv2policy" for seed in range(args.seeds)]
    try:
        verify(args.policies, files)
        policies = [load(path) for path in files]
    except PolicyError as error:
        sys.exit(str(error))
    for path, policy in zip(files, policies, strict=True):
        if policy.env.get("layout") != "forced_coord":  # the counters and seats are Forced Coord.'s cells
            sys.exit(f"{path}: plays layout {policy.env.get('layout')!r}; this script reads forced_coord only")
    print(table_header())
    play = None
    for seed, policy in enumerate(policies):
        if play is None:  # one compiled self-play rollout for every seed (same network, same env)
            env = policy_env(policy.env)
            play = jax.jit(
                lambda params, key: play_recorded(
                    policy.apply, policy.hidden_size, env, (params, params), key, args.episodes
                )
            )
        played = play(policy.params, jax.random.PRNGKey(7))
        print(seed_row(seed, played.states, played.returns), flush=True)


if __name__ == "__main__":
    main()
