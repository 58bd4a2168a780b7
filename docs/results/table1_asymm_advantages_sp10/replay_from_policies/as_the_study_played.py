"""Seed 0's row of the final cross-play played from the published files the way the study's own cross-play plays it:
the ten update-183 policies stacked in one program (``population.xp.cross_play``, seed 0 in seat 0 against all ten
at once, 500 episodes, the study's episode key), once as they are and once recording every transition as the
study's trajectory archive does (``on_block``). Writes ``as_the_study_played.csv`` beside it (row = how it was
played, a column per seat-1 seed), to be set beside ``matrix.csv`` (``ocv2 xp``, one file against one) and the
study's ``xp_sp.csv``: the replay's one cell that differs from the study's (seed 6's) tells whether the batching or
the recording makes the difference.

    python docs/results/table1_asymm_advantages_sp10/replay_from_policies/as_the_study_played.py

About 6 minutes per way on 2 cores.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from population import policy
from population.evaluation import stack_params
from population.keys import derive_key
from population.xp import cross_play

HERE = Path(__file__).resolve().parent
POLICIES = HERE.parent / "policies"
SEEDS, EPISODES, KEY = range(10), 500, derive_key(0, "xp")  # the study's seeds, episodes per pair and key


def main() -> None:
    policies = [policy.load(POLICIES / f"sp_seed{seed}_update183.ocv2policy") for seed in SEEDS]
    first = policies[0]
    stacked = stack_params([p.params for p in policies])
    rows = {}
    for way, on_block in (("batched", None), ("batched, recorded", lambda *_: None)):
        returns = cross_play(
            first.apply, first.hidden_size, first.make_env(), stacked, KEY, EPISODES, rows=[0], on_block=on_block
        ).returns[0]
        rows[way] = [round(float(x), 2) for x in np.asarray(returns).mean(axis=-1)]
        print(way, rows[way])
    with (HERE / "as_the_study_played.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["played\\seat1", *(f"seed_{seed}" for seed in SEEDS)])
        writer.writerows([way, *cells] for way, cells in rows.items())


if __name__ == "__main__":
    main()
