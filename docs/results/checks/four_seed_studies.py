"""What several sections of the page read the same way from the two 4-seed studies (table1_coord_ring/ and
reduced_gcs/): a Coordination Ring snapshot's env steps and its seeds' ring direction, the counter-clockwise SA
seed's pairs, Grounded Coord. Simple's SP seed 2 and the GCS runs' training time."""

from __future__ import annotations

from .data import SP_SP_SA_BC, both_seats, button_rows, chunks, cr_sa, gcs_sp, matrix, point, ring, sp_xp


def cr_millions(name, update):
    """Env steps per seed, in millions, of the 4-seed Coordination Ring run ``name`` ("sp" or "sa") at ``update``."""
    return point(name, update)["env_steps_per_seed"] / 1e6


def clockwise_shares(table, update):
    """Clockwise share of seat 0 per seed at ``update`` of a ring_direction.md snapshot table."""
    return [cell[0] for cell in ring()[table][update]]


CLOCKWISE, EVEN = 0.58, 0.45  # a share above 0.58: clockwise; 0.45-0.58: about even; below 0.45: counter-clockwise


def sa_ccw_seed_pairs():
    """SA seed 1 (the counter-clockwise seed): [self-play, sorted pairs with the other SA seeds], [pairs
    with the 4 SP seeds] (means of both seat orders)."""
    sa = both_seats(cr_sa())
    big = both_seats(matrix(SP_SP_SA_BC))
    return [sa[1, 1], *sorted(sa[1, j] for j in (0, 2, 3))], [big[5, j] for j in range(4)]


def gcs_seed2_wrong():
    """Return per 1+1+1 episode of SP seed 2 cooking for SP seeds 0 and 1 in seat 0 (button_use.md)."""
    return [button_rows(s, "sp/2", "1+1+1")[0]["return"] for s in ("sp/0", "sp/1")]


def gcs_without_seed2():
    """SP, XP and gap of the Grounded Coord. Simple SP seeds 0, 1 and 3."""
    return list(sp_xp(gcs_sp(), [0, 1, 3]))


def gcs_training_s(name):
    """Seconds a Grounded Coord. Simple run (``name``: "sp" or "fcp") trained: its chunks' wall times summed."""
    return sum(w for w, _, _ in chunks(name))


RESUMED_AT = 10  # FCP's resume point (the run's manifest: resumed_from 10)
