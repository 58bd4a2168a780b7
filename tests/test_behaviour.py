"""population.behaviour reads who did what off recorded states: checked against a scripted Forced Coord. play."""

import jax
import numpy as np
import pytest

import ocv2
from ocv2.items import COOKED, PLATE, Action, ingredient_unit
from population import behaviour

S, I, L, R, U, D = Action.STAY, Action.INTERACT, Action.LEFT, Action.RIGHT, Action.UP, Action.DOWN
# Forced Coord.: seat 0 starts at (3, 1) beside the pots and the window, seat 1 at (1, 2) beside the onions and
# plates; the wall between them (x = 2) is where they hand things over. Seat 1 puts an onion on (2, 2), seat 0
# takes it and fills the first pot (3, 0); seat 1 puts a plate on (2, 3), seat 0 takes it.
HANDOVER = [
    (S, L), (S, I), (S, R), (S, I),  # seat 1: face the onions, take one, face the wall, put it down
    (D, S), (L, S), (I, S), (U, S), (U, S), (I, S),  # seat 0: to (3, 2), take it, back up, into the top pot
    (S, D), (S, L), (S, I), (S, R), (S, I),  # seat 1: to (1, 3), take a plate, put it on (2, 3)
    (D, S), (D, S), (L, S), (I, S),  # seat 0: to (3, 3), take the plate
]  # fmt: skip


def scripted_play(layout: str, joint_actions):
    """A scripted play of ``layout`` from its fixed start, every state kept: [E=1, T+1, ...], as play_recorded
    returns it."""
    env = ocv2.make(layout)
    _, state = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(lambda key, s, a: env.step_env(key, s, {"agent_0": a[0], "agent_1": a[1]})[1])
    states = [state]
    for t, joint in enumerate(joint_actions):
        states.append(step(jax.random.PRNGKey(t), states[-1], np.array(joint, np.int32)))
    return jax.tree.map(lambda *x: np.stack(x)[None], *states)


@pytest.fixture(scope="module")
def handover_states():
    both = scripted_play("forced_coord", HANDOVER)
    assert np.asarray(both.agents.inventory[0, -1]).tolist() == [PLATE, 0]  # the script did what it says
    return jax.tree.map(lambda x: np.concatenate([x, x]), both)  # two identical episodes: counts double


def test_role_counts_per_seat(handover_states):
    counts = behaviour.role_counts(handover_states)
    assert counts.shape == (len(behaviour.ROLES), 2)
    assert counts.tolist() == [[2, 0], [2, 2], [0, 0], [0, 0]]  # onions in: seat 0; plates taken: both


def test_pot_use_names_each_pot_in_reading_order(handover_states):
    use = behaviour.pot_use(handover_states)
    assert use.cells.tolist() == [[3, 0], [4, 1]]
    assert use.counts.tolist() == [[2, 0], [0, 0]]
    shares = use.shares()
    assert shares[:, 0].tolist() == [1.0, 0.0] and np.isnan(shares[:, 1]).all()  # seat 1 filled no pot


def test_counter_use_finds_the_handover_cells_items_and_seats(handover_states):
    use = behaviour.counter_use(handover_states)
    assert use.cells.tolist() == [[2, 2], [2, 3]]  # only the counters used, in reading order
    ingredient, plate, dish = range(len(behaviour.ITEM_KINDS))
    put, taken = np.zeros((2, 3, 2), int), np.zeros((2, 3, 2), int)
    put[0, ingredient, 1] = taken[0, ingredient, 0] = 2
    put[1, plate, 1] = taken[1, plate, 0] = 2
    assert use.put.tolist() == put.tolist() and use.taken.tolist() == taken.tolist()


def test_item_kind_tells_ingredients_plates_and_dishes_apart():
    onion = int(ingredient_unit(0))
    soup = PLATE | COOKED | 3 * onion
    kinds = behaviour.item_kind(np.array([0, onion, 2 * onion, PLATE, soup, PLATE | onion]))
    assert kinds.tolist() == [-1, 0, 0, 1, 2, 2]


def _forced_coord_roles():
    return _results_script("docs/results/table1_forced_coord_sp10/roles.py")


def test_forced_coord_roles_row_reads_the_handover(handover_states):
    """The Forced Coord. study's roles.py: onions crossed on (2, 2), plates on (2, 3), each taken up again, no soup
    yet, the top pot only."""
    roles, _ = _forced_coord_roles()
    row = roles.seed_row(4, handover_states, np.array([0.0, 0.0]))
    assert row == "| 4 | 0.00/1.00/0.00 (of 2; 0) | 1.00 | 0.00/0.00/1.00 (of 2; 0) | 1.00 | no soup | 1.00 | 0.0 |"
    assert [line.count("|") for line in roles.table_header().splitlines()] == [row.count("|")] * 2  # its columns


@pytest.mark.parametrize(
    "study, layout, other, other_layout",
    [
        ("table1_forced_coord_sp10", "forced_coord", "table1_coord_ring_sp10", "coord_ring"),
        ("table1_counter_circuit_sp10", "counter_circuit", "table1_forced_coord_sp10", "forced_coord"),
        ("table1_coord_ring_sp10", "coord_ring", "table1_forced_coord_sp10", "forced_coord"),
        ("table1_asymm_advantages_sp10", "asymm_advantages", "table1_cramped_room_sp10", "cramped_room"),
    ],
)
def test_roles_scripts_refuse_another_layouts_policies(study, layout, other, other_layout):
    import subprocess
    import sys

    _, script = _results_script(f"docs/results/{study}/roles.py")
    run = subprocess.run(
        [
            sys.executable,
            str(script),
            "--update",
            "183",
            "--seeds",
            "1",
            "--policies",
            str(script.parents[1] / other / "policies"),
        ],
        capture_output=True,
        text=True,
    )
    assert run.returncode != 0 and "Traceback" not in run.stderr
    assert f"plays layout '{other_layout}'; this reads {layout} only" in run.stderr


def test_forced_coord_roles_names_a_bad_pair_before_playing():
    import subprocess
    import sys

    _, script = _forced_coord_roles()
    for pairs, said in ((["3"], "'3': expected two seeds as i,j"), (["3,10"], "--pairs 3,10: seeds are 0 to 9")):
        run = subprocess.run(
            [sys.executable, str(script), "--update", "183", "--pairs", *pairs], capture_output=True, text=True
        )
        assert run.returncode == 2 and said in run.stderr and "Traceback" not in run.stderr, run.stderr


# Counter Circuit: seat 0 starts at (6, 3) below the island, beside the onions; seat 1 at (2, 1) above it, beside the
# pots. Seat 0 walks left to (3, 3), takes an onion from (3, 4) and puts it on the island (3, 2); seat 1 steps right
# to (3, 1), takes it up and puts it into the left pot (3, 0). Both walk clockwise as the layout is drawn.
ISLAND_PASS = [
    (L, S), (L, S), (L, S), (D, S), (I, S), (U, S), (I, S),  # seat 0: to (3, 3), take an onion, onto the island
    (S, R), (S, D), (S, I), (S, U), (S, I),  # seat 1: to (3, 1), take it up, into the left pot
]  # fmt: skip


def _results_script(relative: str):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / relative
    spec = importlib.util.spec_from_file_location(path.stem + "_" + path.parent.name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module, path


def test_counter_circuit_roles_row_reads_the_island_pass():
    """The Counter Circuit study's roles.py: one onion over the island, put down by seat 0, potted by seat 1 into
    the left pot; both seats moved clockwise; no soup."""
    played = scripted_play("counter_circuit", ISLAND_PASS)
    assert np.asarray(played.agents.x[0, [0, -1]]).tolist() == [[6, 2], [3, 3]]  # the script did what it says
    roles, _ = _results_script("docs/results/table1_counter_circuit_sp10/roles.py")
    row = roles.seed_row(5, played, np.array([0.0]))
    assert row == "| 5 | 0.00 of 1 | none | none | none | 1.00, 1.00 | 1.00 (1.00) | no soup | none in, 1.00 | 0.0 |"
    assert [line.count("|") for line in roles.table_header().splitlines()] == [row.count("|")] * 2


# Asymm. Advantages: seat 1 starts at (5, 3) in the right room, below its onion pile (5, 1) and right of the pots (4, 2)
# and (4, 3); seat 0 at (2, 3) in the left room, beside its plates (3, 4) and window (3, 1). Seat 1 fills the top pot
# with three onions; seat 0 takes a plate, waits by the top pot while the soup cooks, plates it and serves it.
TOP_POT_SOUP = [
    (S, U), *[(S, I), (S, L), (S, I), (S, U)] * 2, (S, I), (S, L), (S, I),  # seat 1: three onions, top pot
    (R, S), (D, S), (I, S), (U, S), (R, S),  # seat 0: to (3, 3), a plate, up to (3, 2), face the top pot
    *[(S, S)] * 20, (I, S), (U, S), (I, S),  # it cooks; seat 0 plates it, faces the window, serves
]  # fmt: skip


# The same soup through the bottom pot (4, 3): seat 1 carries each onion down to (5, 3) beside it; seat 0 takes a plate,
# faces the bottom pot from (3, 3), plates the soup, walks up to (3, 2) and serves.
BOTTOM_POT_SOUP = [
    *[(S, U), (S, U), (S, I), (S, D), (S, L), (S, I)] * 3,  # seat 1: up, take an onion, down, face the pot, put it in
    (R, S), (D, S), (I, S), (R, S),  # seat 0: to (3, 3), a plate, face the bottom pot
    *[(S, S)] * 20, (I, S), (U, S), (U, S), (I, S),  # it cooks; seat 0 plates it, up to (3, 2), faces the window, serves
]  # fmt: skip


@pytest.mark.parametrize(
    "script, expected",
    [
        # the cooked soup waited in the top pot for 7 of the 41 states (0.17)
        (
            TOP_POT_SOUP,
            "| 2 | 0.00 of 3 | 1.00 of 1 | 1.00 of 1 | 1.00 of 1 | none, 1.00 | 1.00, none | 0.17, 0.00 | 20.0 |",
        ),
        # and in the bottom pot for 6 of the 47 (0.13)
        (
            BOTTOM_POT_SOUP,
            "| 2 | 0.00 of 3 | 1.00 of 1 | 1.00 of 1 | 1.00 of 1 | none, 0.00 | 0.00, none | 0.00, 0.13 | 20.0 |",
        ),
    ],
    ids=["top pot", "bottom pot"],
)
def test_asymm_advantages_roles_row_reads_who_fills_and_who_serves_which_pot(script, expected):
    """The Asymm. Advantages study's roles.py: seat 1 put all three onions into one pot, seat 0 took the plate, plated
    that pot's soup and delivered it; the row names the pot and how long its cooked soup waited."""
    played = scripted_play("asymm_advantages", script)
    assert np.asarray(played.agents.inventory[0, -1]).tolist() == [0, 0]  # the script did what it says
    roles, _ = _results_script("docs/results/table1_asymm_advantages_sp10/roles.py")
    row = roles.seed_row(2, played, np.array([20.0]))
    assert row == expected
    assert [line.count("|") for line in roles.table_header().splitlines()] == [row.count("|")] * 2


def test_clockwise_moves_counts_turns_round_a_centre_per_seat():
    """Seat 0 walks clockwise on screen round (1, 1) (right along the top, down the right side), seat 1 the other
    way and then stands still: standing is no move, and each step counts by the way it turns."""
    x = np.array([[0, 2], [1, 2], [2, 2], [2, 2]])  # [T+1, seat]
    y = np.array([[0, 2], [0, 1], [0, 0], [1, 0]])
    clockwise, moves = behaviour.clockwise_moves(x, y, (1, 1))
    assert clockwise.tolist() == [3, 0] and moves.tolist() == [3, 2]
