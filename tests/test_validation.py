"""Bad input fails at construction with an error that names the problem and where it is."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ocv2
from ocv2.layouts import default_recipes

GOOD = "WWPWW\n0A AX\nW   R\nWBWWW"


def test_a_map_with_windows_line_endings_reads_as_the_same_map():
    crlf, lf = ocv2.Layout.from_string(GOOD.replace("\n", "\r\n")), ocv2.Layout.from_string(GOOD)
    np.testing.assert_array_equal(crlf.static_objects, lf.static_objects)
    assert (crlf.agent_positions, crlf.num_ingredients, crlf.possible_recipes) == (
        lf.agent_positions,
        lf.num_ingredients,
        lf.possible_recipes,
    )


@pytest.mark.parametrize(
    "grid,kwargs,match",
    [
        ("WWPWW\n0A?AX\nW   R\nWBWWW", {}, r"unknown character '\?' at row 1, column 2 \(counted from 0\)"),
        ("WWPWW\r0A AX\nW   R\nWBWWW", {}, r"unknown character '\\r' \(a carriage return: end the map's lines with"),
        ("WWPWW\n0   X\nW   R\nWBWWW", {}, r"no agent"),
        ("WWPWW\n0A AX\n    R\nWBWWW", {}, r"map edge at row 2, column 0: the border is open"),
        ("WWPWW\n0A AX\nW   R\nWBW", {}, r"row 3 has 3 characters, the map is 5 wide.*open"),  # padded with floor
        ("WWPWW\nWA AX\nW   R\nWBWWW", {}, r"no ingredient pile"),
        ("WWPWW\n0A AX\nW   W\nWBWWW", {}, r"recipe indicator 'R'"),
        (GOOD, {"possible_recipes": []}, r"possible_recipes is empty"),
        (GOOD, {"possible_recipes": [[0, 0]]}, r"recipe 0 .* exactly 3"),
        (GOOD, {"possible_recipes": [[0, 0, 1]]}, r"ingredient 1, which has no pile"),
        (GOOD, {"possible_recipes": "000"}, r"list of 3-ingredient lists"),
        ("", {}, r"empty"),
        # piles 0 and 2: the default recipes (of ingredients 0..2) would need a pile 1 that is not on the map
        ("WWPWWW\n0A A2W\nW    R\nWBWXWW", {}, r"ingredient piles 0, 2 but no 1; number the piles 0 to 1"),
    ],
)
def test_bad_layouts(grid, kwargs, match):
    with pytest.raises(ValueError, match=match):
        ocv2.Layout.from_string(grid, **kwargs)


@pytest.mark.parametrize(
    "grid, where, size",
    [
        ("\n    WWPWW\n    0A AX\n    W   R\n    WBWWW\n", "row 0, column 0", "4 x 9"),  # an indented map
        ("WWPWW  \n0A AX\nW   R\nWBWWW", "row 0, column 5", "4 x 7"),  # trailing spaces
    ],
)
def test_floor_no_cook_reaches_on_the_map_edge_warns_with_the_cell_and_the_size(grid, where, size):
    """An indented map built 4 extra columns of floor, and observations 4 columns wider, without a word."""
    with pytest.warns(ocv2.layouts.LayoutEdgeWarning, match=rf"{where}, counted from 0\).* map is {size},"):
        ocv2.Layout.from_string(grid)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ocv2.Layout.from_string(GOOD)  # a closed map says nothing


def test_a_layout_built_without_piles_says_so():
    grid = ocv2.Layout.from_string(GOOD).static_objects.copy()
    grid[grid >= ocv2.layouts.Static.INGREDIENT_PILE] = ocv2.layouts.Static.WALL
    with pytest.raises(ValueError, match="no ingredient pile on the map"):
        ocv2.Layout(grid, ((1, 1), (3, 1)), num_ingredients=1)


def test_piles_with_a_gap_build_with_recipes_of_the_piles_on_the_map():
    layout = ocv2.Layout.from_string("WWPWWW\n0A A2W\nW    R\nWBWXWW", possible_recipes=[[0, 0, 2], [2, 2, 2]])
    assert layout.num_ingredients == 3 and layout.possible_recipes == ((0, 0, 2), (2, 2, 2))


def test_non_integer_recipe_is_type_error():
    with pytest.raises(TypeError, match="non-integer ingredient"):
        ocv2.Layout.from_string(GOOD, possible_recipes=[[0, 0, "a"]])


def test_good_layout_and_roundtrip():
    layout = ocv2.Layout.from_string(GOOD)
    assert layout.num_agents == 2 and layout.num_ingredients == 1
    assert ocv2.Layout.from_string(layout.to_string()).agent_positions == layout.agent_positions
    for name, built_in in ocv2.LAYOUTS.items():
        again = ocv2.Layout.from_string(
            built_in.to_string(), possible_recipes=[list(r) for r in built_in.possible_recipes]
        )
        assert (again.static_objects == built_in.static_objects).all(), name


def test_a_kitchen_where_no_soup_can_be_delivered_builds_with_a_warning_naming_why():
    """The reference builds such maps without a word; ocv2 builds them too (a test kitchen may lack parts on
    purpose) but says why nothing will ever be delivered, down to the cell no cook can reach."""
    from ocv2.layouts import LAYOUTS, LayoutWarning, kitchen_problems

    assert not [name for name, layout in LAYOUTS.items() if kitchen_problems(layout)]  # every shipped kitchen works
    with pytest.warns(LayoutWarning, match="layout 'nopot': no soup can be delivered: no pot$"):
        ocv2.Layout.from_string("WWWWW\nWA AW\nW0 BW\nWWXWW", possible_recipes=[[0, 0, 0]], name="nopot")
    with pytest.warns(LayoutWarning) as caught:
        ocv2.Layout.from_string("WWWWW\nWA AW\nWWWWW\nW0PBX\nWWWWW", possible_recipes=[[0, 0, 0]], name="walled")
    message = str(caught[0].message)
    assert "no cook can reach a pot (the first at row 3, column 2)" in message
    assert "no cook can reach an ingredient pile (the first at row 3, column 1)" in message


def test_default_recipe_order_matches_reference_table():
    assert default_recipes(2) == ((0, 0, 0), (0, 0, 1), (1, 1, 1), (0, 1, 1))
    assert default_recipes(3)[:3] == ((2, 2, 2), (0, 0, 0), (1, 1, 2))
    assert len(default_recipes(4)) == 20


def test_all_layouts_present():
    assert len(ocv2.REFERENCE_LAYOUT_NAMES) == 23
    assert set(ocv2.LAYOUTS) == set(ocv2.REFERENCE_LAYOUT_NAMES) | {"overcookedv2_demo"}


@pytest.mark.parametrize(
    "kwargs,error,match",
    [
        ({"layout": "no_such_room"}, ValueError, r"unknown layout 'no_such_room'; choose one of: cramped_room"),
        ({"layout": 3}, TypeError, r"layout must be"),
        ({"agent_view_size": -1}, ValueError, r"agent_view_size must be None or an integer in \[0, 2\*\*31\), got -1"),
        ({"agent_view_size": 99999999999}, ValueError, r"agent_view_size .* got 99999999999"),
        ({"agent_view_size": 1.5}, TypeError, r"agent_view_size"),
        ({"observation_type": "pixels"}, ValueError, r"unknown observation_type 'pixels'"),
        ({"observation_type": ["default"]}, ValueError, r"lists 1 types but layout .* has 2 agents"),
        ({"layout": "cramped_room_v2", "observation_type": "featurized"}, ValueError, r"single-ingredient"),
        ({"observation_type": "featurized", "agent_view_size": 2}, ValueError, r"cannot be combined"),
        ({"max_steps": 0}, ValueError, r"max_steps"),
        ({"random_reset": 1}, TypeError, r"random_reset must be True or False"),
        ({"op_ingredient_permutations": [0, 5]}, ValueError, r"op_ingredient_permutations: 5"),
        ({"op_ingredient_permutations": [0, 0]}, ValueError, r"repeated"),
        ({"obs_dtype": "float16"}, ValueError, r"obs_dtype"),
        ({"not_a_param": 1}, TypeError, r"unknown environment parameter\(s\) \['not_a_param'\]"),
    ],
)
def test_bad_parameters(kwargs, error, match):
    with pytest.raises(error, match=match):
        ocv2.make(**kwargs)


def test_bad_state_buffer():
    env = ocv2.make("cramped_room")
    good = ocv2.stack_states([env.reset_state(jax.random.PRNGKey(k)) for k in range(3)])
    ocv2.make("cramped_room", initial_state_buffer=good)
    with pytest.raises(
        ValueError, match=r"initial_state_buffer.grid has shape \(3, 5, 9, 3\), expected \(3, 4, 5, 3\)"
    ):
        other = ocv2.make("asymm_advantages")
        ocv2.make(
            "cramped_room",
            initial_state_buffer=ocv2.stack_states([other.reset_state(jax.random.PRNGKey(k)) for k in range(3)]),
        )
    with pytest.raises(ValueError, match="leading batch axis"):
        ocv2.make("cramped_room", initial_state_buffer=env.reset_state(jax.random.PRNGKey(0)))
    with pytest.raises(ValueError, match="different kitchen"):
        ocv2.make("cramped_room", initial_state_buffer=good.replace(grid=good.grid.at[1, 0, 0, 0].set(0)))
    with pytest.raises(TypeError, match="ocv2.State"):
        ocv2.make("cramped_room", initial_state_buffer={"grid": jnp.zeros(3)})


def test_missing_action_names_agent():
    env = ocv2.make("cramped_room")
    _, state = env.reset(jax.random.PRNGKey(0))
    with pytest.raises(KeyError, match="agent_1"):
        env.step(jax.random.PRNGKey(1), state, {"agent_0": 0})


def _cramped(**changes):
    """cramped_room's fields as Layout keyword arguments, with ``changes`` applied."""
    base = ocv2.LAYOUTS["cramped_room"]
    fields = {
        "static_objects": base.static_objects.copy(),
        "agent_positions": base.agent_positions,
        "num_ingredients": 1,
        "possible_recipes": ((0, 0, 0),),
    }
    return {**fields, **changes}


def _with_cell(value, row=2, column=2):
    grid = ocv2.LAYOUTS["cramped_room"].static_objects.copy()
    grid[row, column] = value
    return grid


@pytest.mark.parametrize(
    "changes,error,match",
    [
        ({"static_objects": _with_cell(8)}, ValueError, r"unknown cell id 8 at row 2, column 2"),
        ({"static_objects": _with_cell(-3, 0, 0)}, ValueError, r"unknown cell id -3 at row 0, column 0"),
        # a pile of ingredient 20 would overflow the int32 item encoding
        ({"static_objects": _with_cell(10 + 20, 0, 0)}, ValueError, r"unknown cell id 30 at row 0, column 0"),
        ({"static_objects": _with_cell(1).astype(float)}, ValueError, r"integer cell ids, got dtype float64"),
        ({"num_ingredients": 25}, ValueError, r"num_ingredients is 25, must be in \[1, 10\]"),
        (
            {"static_objects": _with_cell(11, 0, 0)},
            ValueError,
            r"num_ingredients is 1, must be in \[2, 10\] \(the map has a pile of ingredient 1 at row 0, column 0\)",
        ),
        ({"num_ingredients": "2"}, TypeError, r"num_ingredients must be an integer, got '2'"),
        ({"num_ingredients": 2.9}, TypeError, r"num_ingredients must be an integer, got 2.9"),
        ({"agent_positions": ((1.5, 1), (3, 1))}, TypeError, r"agent_positions\[0\] = \(1.5, 1\) must hold integer"),
        ({"agent_positions": ((1, 1), (3,))}, ValueError, r"agent_positions\[1\] must be an \(x, y\) pair"),
    ],
)
def test_a_layout_built_directly_is_checked_cell_by_cell(changes, error, match):
    with pytest.raises(error, match=match):
        ocv2.Layout(**_cramped(**changes))


def test_a_layout_built_from_jax_integers_is_accepted_as_before():
    """The checks refuse floats and strings, not array scalars and arrays of an integer dtype."""
    import jax.numpy as jnp

    layout = ocv2.Layout(**_cramped(agent_positions=jnp.array([[1, 1], [3, 1]]), num_ingredients=jnp.int32(1)))
    assert layout.agent_positions == ((1, 1), (3, 1)) and layout.num_ingredients == 1
    with pytest.raises(TypeError, match=r"num_ingredients must be an integer"):
        ocv2.Layout(**_cramped(num_ingredients=jnp.float32(1)))


def test_an_archived_layout_spec_is_checked_like_a_built_one():
    from cluster.archive.format import layout_from_spec, layout_spec

    spec = {**layout_spec(ocv2.LAYOUTS["cramped_room"]), "name": "stored", "num_ingredients": 25}
    with pytest.raises(ValueError, match=r"layout 'stored': num_ingredients is 25"):
        layout_from_spec(spec)
    spec = {**layout_spec(ocv2.LAYOUTS["cramped_room"]), "name": "stored", "agent_positions": [[1.0, 1], [3, 1]]}
    with pytest.raises(TypeError, match=r"agent_positions\[0\]"):
        layout_from_spec(spec)


def test_a_short_row_that_opens_the_border_is_named_by_its_length():
    """The padded column is nowhere in the text, so the error names the short row instead."""
    with pytest.raises(ValueError, match=r"row 1 has 4 characters, the map is 5 wide.*the border is open"):
        ocv2.Layout.from_string("WWWWW\nW0A \nWPXBW\nWRWWW")
    # a short row the cooks cannot reach leaves a floor hole in the border, which the reference accepts too
    with pytest.warns(ocv2.layouts.LayoutEdgeWarning, match=r"row 3, column 4, counted from 0"):
        layout = ocv2.Layout.from_string("WWPWW\n0A AX\nW   R\nWBWW")
    assert layout.static_objects[3, 4] == ocv2.layouts.Static.FLOOR


@pytest.mark.parametrize(
    "grid,recipes,match",
    [
        # pile 1 walled in: the only recipe needs it
        (
            "WWWWWWW\n0A  PW1\nW A XWW\nWBWWRWW",
            [[1, 1, 1]],
            r"no soup can be delivered: recipe \[1, 1, 1\] can never be served: no cook can bring ingredient 1 "
            r"\(pile at row 1, column 6\)",
        ),
        # the same with the default recipes: three of four need ingredient 1
        (
            "WWWWWWW\n0A  PW1\nW A XWW\nWBWWRWW",
            None,
            r"some orders can never be delivered: recipes \[0, 0, 1\], \[1, 1, 1\], \[0, 1, 1\] can never be served",
        ),
        # pot in one room, pile, plates and window in the other, no counter between them
        (
            "WWWWWWWWW\nW  PWW 0W\nW A WW AX\nW   WWB W\nWWWWWWWWW",
            [[0, 0, 0]],
            r"no soup can be delivered: no pot where a cook who can fetch a plate and reach a serving window",
        ),
    ],
)
def test_a_kitchen_whose_rooms_cannot_complete_a_soup_warns(grid, recipes, match):
    from ocv2.layouts import LayoutWarning

    with pytest.warns(LayoutWarning, match=match):
        ocv2.Layout.from_string(grid, recipes)


@pytest.mark.parametrize(
    "grid",
    [
        "WWWWWWWWW\nW  PW  0W\nW A W AXW\nW   WWB W\nWWWWWWWWW",  # a counter both rooms touch passes the soup
        "WWWWWWWWW\n0   WWBXW\nW A P A W\nW   WW  W\nWWWWWWWWW",  # ... and so does a pot both rooms touch
    ],
)
def test_rooms_linked_by_a_shared_counter_or_pot_make_a_working_kitchen(grid):
    from ocv2.layouts import kitchen_problems

    assert kitchen_problems(ocv2.Layout.from_string(grid, [[0, 0, 0]])) == []


def _buffer(layout, count=3):
    env = ocv2.make(layout)
    return ocv2.stack_states([env.reset_state(jax.random.PRNGKey(k)) for k in range(count)])


def _agents(state, **fields):
    return state.replace(agents=state.agents.replace(**fields))


def test_a_buffer_passed_per_call_is_checked_like_the_constructors():
    env, key = ocv2.make("coord_ring"), jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match=r"state_buffer state 0 has a different kitchen than layout 'coord_ring'"):
        env.reset(key, state_buffer=_buffer("forced_coord"))  # same size, other kitchen
    with pytest.raises(ValueError, match=r"state_buffer.grid has shape \(3, 4, 5, 3\), expected \(3, 5, 5, 3\)"):
        env.reset(key, state_buffer=_buffer("cramped_room"))
    # the shape check is static, so it holds under jit too
    with pytest.raises(ValueError, match=r"state_buffer.grid has shape"):
        jax.jit(lambda buffer: env.reset_arrays(key, buffer))(_buffer("cramped_room"))
    with pytest.raises(ValueError, match=r"state_buffer.grid has shape"):
        env.step_arrays(key, env.reset_state(key), jnp.zeros(2, jnp.int32), state_buffer=_buffer("cramped_room"))
    obs, _ = jax.jit(lambda buffer: env.reset_arrays(key, buffer))(_buffer("coord_ring"))
    assert obs.shape[1:] == env.obs_shape


def test_a_state_passed_per_call_is_checked():
    env, key = ocv2.make("cramped_room"), jax.random.PRNGKey(0)
    state = env.reset_state(key)
    other = ocv2.make("forced_coord").reset_state(key)
    with pytest.raises(ValueError, match=r"state.grid has shape \(5, 5, 3\), expected \(4, 5, 3\)"):
        env.reset_from_state(key, other)
    with pytest.raises(ValueError, match=r"state: agents.dir\[1\] is 7"):
        env.reset_from_state(key, _agents(state, dir=state.agents.dir.at[1].set(7)))
    with pytest.raises(ValueError, match=r"reset_state: recipe is 999"):
        env.step_arrays(key, state, jnp.zeros(2, jnp.int32), reset_state=state.replace(recipe=jnp.int32(999)))
    with pytest.raises(ValueError, match=r"state.grid has shape \(5, 5, 3\)"):
        env.step(key, other, {"agent_0": 0, "agent_1": 0})
    with pytest.raises(ValueError, match=r"state.done has dtype int32, expected bool"):
        jax.jit(env.step_arrays)(key, state.replace(done=jnp.int32(0)), jnp.zeros(2, jnp.int32))


@pytest.mark.parametrize(
    "change,match",
    [
        (lambda b: b.replace(grid=b.grid.astype(jnp.float32)), r"grid has dtype float32, expected int32"),
        (lambda b: _agents(b, x=b.agents.x.astype(jnp.float32)), r"agents.x has dtype float32, expected int32"),
        (
            lambda b: _agents(b, x=b.agents.x.at[1].set(0), y=b.agents.y.at[1].set(0)),
            r"state 1: agents.x/agents.y put agent 0 on a non-floor cell \(row 0, column 0\)",
        ),
        (
            lambda b: _agents(
                b, x=b.agents.x.at[2, 1].set(b.agents.x[2, 0]), y=b.agents.y.at[2, 1].set(b.agents.y[2, 0])
            ),
            r"state 2: agents.x/agents.y put agents 0 and 1 on the same cell",
        ),
        (lambda b: _agents(b, x=b.agents.x.at[0, 1].set(9)), r"state 0: .* agent 1 at \(x=9, y=1\), outside the 4x5"),
        (lambda b: _agents(b, dir=b.agents.dir.at[1, 0].set(7)), r"state 1: agents.dir\[0\] is 7, expected 0..3"),
        (lambda b: _agents(b, dir=b.agents.dir.at[2, 1].set(-1)), r"state 2: agents.dir\[1\] is -1"),
        (lambda b: b.replace(recipe=b.recipe.at[0].set(999)), r"state 0: recipe is 999, not the encoding .* \(12 = "),
    ],
)
def test_a_buffer_state_that_no_episode_could_reach_is_refused(change, match):
    with pytest.raises(ValueError, match=r"initial_state_buffer.*" + match):
        ocv2.make("cramped_room", initial_state_buffer=change(_buffer("cramped_room")))


@pytest.mark.parametrize(
    "actions,error,match",
    [
        (jnp.array([0]), ValueError, r"actions has shape \(1,\), expected \(2,\)"),  # would broadcast
        (jnp.array([0, 1, 2]), ValueError, r"actions has shape \(3,\), expected \(2,\)"),
        (jnp.array([0, 6]), ValueError, r"actions\[1\] is 6, not an action; actions are 0..5"),
        (jnp.array([0.0, 2.7]), ValueError, r"actions must be integers 0..5, got dtype float32"),
        ({"agent_0": 9, "agent_1": 4}, ValueError, r"actions\['agent_0'\] is 9, not an action"),
        ({"agent_0": 0, "agent_1": -3}, ValueError, r"actions\['agent_1'\] is -3, not an action"),
        ({"agent_0": 2.7, "agent_1": 0}, ValueError, r"actions\['agent_0'\] must be integers 0..5, got dtype float"),
        ({"agent_0": 0, "agent_1": 0, "agent_7": 3}, KeyError, r"unknown agent\(s\) \['agent_7'\]"),
    ],
)
def test_bad_actions_are_refused_not_reinterpreted(actions, error, match):
    env, key = ocv2.make("cramped_room"), jax.random.PRNGKey(0)
    state = env.reset_state(key)
    with pytest.raises(error, match=match):
        if isinstance(actions, dict):
            env.step(key, state, actions)
        else:
            env.step_arrays(key, state, actions)


def test_traced_actions_get_the_static_checks():
    env, key = ocv2.make("cramped_room"), jax.random.PRNGKey(0)
    state = env.reset_state(key)
    with pytest.raises(ValueError, match=r"actions has shape \(3,\)"):
        jax.jit(env.step_arrays)(key, state, jnp.zeros(3, jnp.int32))
    with pytest.raises(ValueError, match=r"got dtype float32"):
        jax.jit(lambda a: env.step(key, state, {"agent_0": a, "agent_1": 0}))(jnp.float32(1))
    # any integer dtype is an action (the reference's action space samples uint32)
    jax.jit(env.step_arrays)(key, state, jnp.array([0, 5], jnp.uint32))


def test_an_unknown_agent_name_is_refused_by_both_spaces():
    env = ocv2.make("cramped_room")
    for space in (env.observation_space, env.action_space):
        with pytest.raises(ValueError, match=r"unknown agent 'agent_9'; this env's agents are agent_0, agent_1"):
            space("agent_9")
    assert env.action_space().n == env.action_space("agent_1").n == 6
