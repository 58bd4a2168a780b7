"""Bridges to the behavioural reference, ``jaxmarl==0.2.0`` (a test-only dependency).

Converts states both ways and builds the reference env with the same parameters as ours, so tests
can feed identical keys and actions to both and compare every output.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

# jaxmarl is a declared test dependency: without it the conformance tests must fail, not pass by skipping.
MISSING_REFERENCE = "the conformance tests need jaxmarl==0.2.0 (a test dependency): pip install -e '.[test]'"
try:
    from jaxmarl.environments.overcooked_v2 import common as ref_common
    from jaxmarl.environments.overcooked_v2 import overcooked as jaxmarl_ov2
    from jaxmarl.environments.overcooked_v2.layouts import Layout as RefLayout
except ImportError as error:
    raise ImportError(f"{MISSING_REFERENCE} ({error})") from error

import ocv2  # noqa: E402
from ocv2.state import Agents, State  # noqa: E402

REF_PARAMS = (
    "max_steps",
    "observation_type",
    "agent_view_size",
    "random_reset",
    "random_agent_positions",
    "start_cooking_interaction",
    "negative_rewards",
    "sample_recipe_on_delivery",
    "indicate_successful_delivery",
    "op_ingredient_permutations",
    "force_path_planning",
)


def ref_layout(layout: ocv2.Layout) -> RefLayout:
    return RefLayout(
        agent_positions=list(layout.agent_positions),
        static_objects=np.asarray(layout.static_objects).astype(int),
        num_ingredients=layout.num_ingredients,
        possible_recipes=[list(r) for r in layout.possible_recipes],
    )


def make_pair(layout="cramped_room", ref_buffer=None, **params):
    """Our env and the reference env with the same layout and reference parameters."""
    ours = ocv2.make(layout, **params)
    ref_kwargs = {k: v for k, v in params.items() if k in REF_PARAMS}
    if isinstance(ref_kwargs.get("observation_type"), tuple):
        ref_kwargs["observation_type"] = list(ref_kwargs["observation_type"])
    if ref_kwargs.get("op_ingredient_permutations") is not None:
        ref_kwargs["op_ingredient_permutations"] = list(ref_kwargs["op_ingredient_permutations"])
    ref = jaxmarl_ov2.OvercookedV2(layout=ref_layout(ours.layout), initial_state_buffer=ref_buffer, **ref_kwargs)
    return ours, ref


def to_ours(ref_state, num_agents: int, num_ingredients: int) -> State:
    """A reference state as an ocv2 ``State`` (identity permutations where the reference has None)."""
    perms = ref_state.ingredient_permutations
    batch = ref_state.step.shape
    if perms is None:
        perms = jnp.broadcast_to(jnp.arange(num_ingredients, dtype=jnp.int32), batch + (num_agents, num_ingredients))
    return State(
        agents=Agents(
            x=jnp.asarray(ref_state.agents.pos.x, jnp.int32),
            y=jnp.asarray(ref_state.agents.pos.y, jnp.int32),
            dir=jnp.asarray(ref_state.agents.dir, jnp.int32),
            inventory=jnp.asarray(ref_state.agents.inventory, jnp.int32),
        ),
        grid=jnp.asarray(ref_state.grid, jnp.int32),
        recipe=jnp.asarray(ref_state.recipe, jnp.int32),
        step=jnp.asarray(ref_state.step, jnp.int32),
        done=jnp.asarray(ref_state.done, bool),
        new_correct_delivery=jnp.asarray(ref_state.new_correct_delivery, bool),
        ingredient_permutations=jnp.asarray(perms, jnp.int32),
    )


def to_ref(state: State, with_permutations: bool):
    """An ocv2 state as a reference ``State`` (permutations dropped unless the reference env uses OP)."""
    agents = ref_common.Agent(
        pos=ref_common.Position(x=state.agents.x, y=state.agents.y),
        dir=state.agents.dir,
        inventory=state.agents.inventory,
    )
    return jaxmarl_ov2.State(
        agents=agents,
        grid=state.grid,
        step=state.step,
        done=state.done,
        recipe=state.recipe,
        new_correct_delivery=state.new_correct_delivery,
        ingredient_permutations=state.ingredient_permutations if with_permutations else None,
    )


def state_diff(ours: State, ref_state, num_ingredients: int) -> list[str]:
    """Names of the fields where two states differ (empty list = equal)."""
    theirs = to_ours(ref_state, ours.agents.x.shape[-1], num_ingredients)
    out = []
    for name, a, b in zip(
        ("x", "y", "dir", "inventory"),
        (ours.agents.x, ours.agents.y, ours.agents.dir, ours.agents.inventory),
        (theirs.agents.x, theirs.agents.y, theirs.agents.dir, theirs.agents.inventory),
    ):
        if not np.array_equal(np.asarray(a), np.asarray(b)):
            out.append(f"agents.{name}")
    for name in ("grid", "recipe", "step", "done", "new_correct_delivery"):
        if not np.array_equal(np.asarray(getattr(ours, name)), np.asarray(getattr(theirs, name))):
            out.append(name)
    if ref_state.ingredient_permutations is not None and not np.array_equal(
        np.asarray(ours.ingredient_permutations), np.asarray(ref_state.ingredient_permutations)
    ):
        out.append("ingredient_permutations")
    return out


def actions_dict(actions, agents):
    return {a: actions[..., i] for i, a in enumerate(agents)}
