"""The OvercookedV2 environment: JaxMARL-compatible dict API over array-first pure functions.

``reset``/``step`` take and return per-agent dicts (``agent_0``...) like the reference; the array
entry points (``reset_arrays``/``step_arrays``) keep a leading agent axis for learning code. Nothing
is jitted here: wrap the methods in ``jax.jit`` (the env object is immutable, so that is safe).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.config import EnvConfig, build_config
from ocv2.dynamics import transition
from ocv2.featurized import make_featurizer
from ocv2.observations import default_observations, grid_obs_shape
from ocv2.reset import buffer_reset_state, default_reset_state, state_from, validate_buffer, validate_state
from ocv2.spaces import Box, Discrete
from ocv2.state import State


class StepArrays(NamedTuple):
    """Array form of one auto-resetting step; the agent axis leads."""

    obs: jax.Array  # [N, ...] (default observations) -- or a tuple per agent for mixed types
    state: State  # the next state (already reset if the episode ended)
    reward: jax.Array  # float32[N] team reward, the same for every agent
    shaped_reward: jax.Array  # float32[N]
    done: jax.Array  # bool[] the transition ended the episode
    terminal_state: State  # the state the transition reached, before any auto-reset


def make(layout="cramped_room", **params) -> OvercookedV2:
    """Create an environment; parameters as the reference ``OvercookedV2`` constructor (plus fix flags)."""
    return OvercookedV2(layout, **params)


class OvercookedV2:
    """OvercookedV2 on one layout. Behaves transition for transition like ``jaxmarl==0.2.0``.

    Args:
        layout: a name from ``ocv2.LAYOUTS`` or a ``Layout``.
        max_steps, observation_type, agent_view_size, random_reset, random_agent_positions,
        start_cooking_interaction, negative_rewards, sample_recipe_on_delivery,
        indicate_successful_delivery, op_ingredient_permutations, force_path_planning: as the reference.
        initial_state_buffer: a batched ``State`` to draw every reset from (state augmentation).
        fix_negative_placement_reward, fix_offmap_interaction, fix_zero_view_size, fix_button_repress:
            opt-in fixes of reference bugs. paper_obs_truncation: the paper's older observation.
        obs_dtype: 'uint8' (default, same values as the reference) or 'int32'.

    Raises:
        ValueError / TypeError naming the bad parameter or layout cell.
    """

    name = "Overcooked V2"

    def __init__(self, layout="cramped_room", initial_state_buffer: State | None = None, **params):
        self.config: EnvConfig = build_config(layout, **params)
        if initial_state_buffer is not None:
            validate_buffer(self.config, initial_state_buffer)
        self.initial_state_buffer = initial_state_buffer
        config = self.config
        self.layout = config.layout
        self.num_agents = config.num_agents
        self.agents = [f"agent_{i}" for i in range(self.num_agents)]
        self.height, self.width = self.layout.height, self.layout.width
        self.max_steps = config.max_steps
        self.agent_view_size = config.agent_view_size
        self.possible_recipes = jnp.asarray(self.layout.possible_recipes, dtype=jnp.int32)
        self.enclosed_spaces = jnp.asarray(self.layout.room_labels)
        self.action_set = jnp.arange(it.NUM_ACTIONS, dtype=jnp.int32)
        self._featurizer = None
        if "featurized" in config.observation_types or config.force_path_planning:
            self._featurizer = make_featurizer(self.layout)
        shapes = [self._obs_shape_for(t) for t in config.observation_types]
        self.obs_shape = shapes[0] if len(set(shapes)) == 1 else shapes

    # ------------------------------------------------------------------ spaces
    @property
    def num_actions(self) -> int:
        return it.NUM_ACTIONS

    def action_space(self, agent_id: str = "") -> Discrete:
        """The actions of ``agent_id`` (every agent has the same six; an unknown name is still an error)."""
        self._agent_index(agent_id)
        return Discrete(it.NUM_ACTIONS)

    def observation_space(self, agent_id: str = "") -> Box:
        """The true observation space of ``agent_id`` (default: agent 0): dtype and value bounds."""
        index = self._agent_index(agent_id)
        kind = self.config.observation_types[index]
        shape = self._obs_shape_for(kind)
        if kind == "featurized":
            return Box(
                low=-float(max(self.height, self.width)),
                high=float(max(self.height, self.width, it.POT_COOK_TIME)),
                shape=shape,
                dtype=jnp.float32,
            )
        # Largest value: the pot timer (20) or summed layers of N agents (counts <= 3).
        high = max(it.POT_COOK_TIME, 3 * self.num_agents)
        return Box(low=0, high=high, shape=shape, dtype=jnp.dtype(self.config.obs_dtype))

    def _obs_shape_for(self, kind: str):
        if kind == "featurized":
            return (self._featurizer.size,)
        return grid_obs_shape(self.config)

    # ------------------------------------------------------------------ observations
    def get_obs_arrays(self, state: State):
        """Observations with the agent axis leading: an array [N, ...], or a tuple for mixed types."""
        kinds = self.config.observation_types
        if all(k == "default" for k in kinds):
            return default_observations(self.config, state)
        if all(k == "featurized" for k in kinds):
            return self._featurizer(state)
        grid = default_observations(self.config, state) if "default" in kinds else None
        feats = self._featurizer(state)
        return tuple(grid[i] if k == "default" else feats[i] for i, k in enumerate(kinds))

    def get_obs(self, state: State) -> dict:
        obs = self.get_obs_arrays(state)
        return {name: obs[i] for i, name in enumerate(self.agents)}

    # ------------------------------------------------------------------ reset
    def reset_state(self, key: jax.Array, state_buffer: State | None = None) -> State:
        """A fresh episode's state (no observation). ``state_buffer`` overrides the constructor's buffer.

        A buffer passed here is checked like the constructor's: shapes and dtypes always, contents when
        it is concrete (not traced).
        """
        if state_buffer is not None and state_buffer is not self.initial_state_buffer:
            validate_buffer(self.config, state_buffer, "state_buffer")
        buffer = self.initial_state_buffer if state_buffer is None else state_buffer
        if buffer is not None:
            return buffer_reset_state(self.config, key, buffer)
        return default_reset_state(self.config, key)

    def reset(self, key: jax.Array, state_buffer: State | None = None):
        """Start an episode. Returns ``(obs_dict, state)``; the key is consumed."""
        state = self.reset_state(key, state_buffer)
        return self.get_obs(state), state

    def reset_from_state(self, key: jax.Array, state: State):
        """Start an episode from ``state`` (kitchen, agents, recipe kept; step/done/flags cleared)."""
        validate_state(self.config, state, "state")
        state = state_from(self.config, key, state)
        return self.get_obs(state), state

    # ------------------------------------------------------------------ step
    def step_env(self, key: jax.Array, state: State, actions: dict):
        """One transition without auto-reset: ``(obs, state, rewards, dones, infos)``."""
        validate_state(self.config, state, "state", contents=False)
        result = transition(self.config, key, state, self._action_array(actions))
        obs = self.get_obs(result.state)
        return (obs, result.state) + self._dicts(result.reward, result.shaped_reward, result.state.done)

    def step(
        self,
        key: jax.Array,
        state: State,
        actions: dict,
        reset_state: State | None = None,
        state_buffer: State | None = None,
    ):
        """One auto-resetting transition: ``(obs, state, rewards, dones, infos)`` in JaxMARL's dict form.

        When the episode ends the returned state/obs are the next episode's first (drawn from
        ``reset_state`` if given, else the buffer, else a fresh reset); rewards and dones are the
        transition's.
        """
        out = self.step_arrays(key, state, self._action_array(actions), reset_state, state_buffer)
        obs = {name: out.obs[i] for i, name in enumerate(self.agents)}
        return (obs, out.state) + self._dicts(out.reward[0], out.shaped_reward, out.done)

    def step_arrays(
        self,
        key: jax.Array,
        state: State,
        actions: jax.Array,
        reset_state: State | None = None,
        state_buffer: State | None = None,
    ) -> StepArrays:
        """Array form of ``step``: actions int32[N] in, ``StepArrays`` out.

        ``state`` gets the static checks only (shapes, dtypes: free under ``jit``), as this is the training
        hot path; a ``reset_state`` or ``state_buffer`` also gets its contents checked when concrete.
        """
        validate_state(self.config, state, "state", contents=False)
        _check_actions(actions, (self.num_agents,), "actions")
        if reset_state is not None:
            validate_state(self.config, reset_state, "reset_state")
        k_step, k_reset = jax.random.split(key)
        result = transition(self.config, k_step, state, actions)
        if reset_state is None:
            reset_state = self.reset_state(k_reset, state_buffer)
        done = result.state.done
        next_state = jax.tree.map(lambda r, s: jax.lax.select(done, r, s), reset_state, result.state)
        # Observations are built once, from the state actually returned (the reference builds both).
        obs = self.get_obs_arrays(next_state)
        reward = jnp.broadcast_to(result.reward, (self.num_agents,))
        return StepArrays(obs, next_state, reward, result.shaped_reward, done, result.state)

    def reset_arrays(self, key: jax.Array, state_buffer: State | None = None):
        state = self.reset_state(key, state_buffer)
        return self.get_obs_arrays(state), state

    # ------------------------------------------------------------------ helpers
    def _agent_index(self, agent_id: str) -> int:
        """Index of agent ``agent_id``; "" (the reference's default) means agent 0."""
        if agent_id == "":
            return 0
        if agent_id not in self.agents:
            raise ValueError(f"unknown agent {agent_id!r}; this env's agents are {', '.join(self.agents)}")
        return self.agents.index(agent_id)

    def _action_array(self, actions) -> jax.Array:
        """Dict or array actions as int32[N], checked by ``_check_actions``."""
        if isinstance(actions, dict):
            missing = [a for a in self.agents if a not in actions]
            if missing:
                raise KeyError(f"actions are missing agent(s) {missing}; expected keys {self.agents}")
            unknown = [a for a in actions if a not in self.agents]
            if unknown:
                raise KeyError(f"actions name unknown agent(s) {unknown}; expected keys {self.agents}")
            for name in self.agents:
                _check_actions(actions[name], (), f"actions[{name!r}]")
            return jnp.stack([jnp.asarray(actions[a], dtype=jnp.int32) for a in self.agents])
        _check_actions(actions, (self.num_agents,), "actions")
        return jnp.asarray(actions, dtype=jnp.int32)

    def _dicts(self, reward, shaped, done):
        reward = reward.astype(jnp.float32)
        rewards = {a: reward for a in self.agents}
        dones = {a: done for a in self.agents}
        dones["__all__"] = done
        infos = {"shaped_reward": {a: shaped[i] for i, a in enumerate(self.agents)}}
        return rewards, dones, infos

    def __repr__(self) -> str:
        changed = {
            f.name: getattr(self.config, f.name)
            for f in dataclasses.fields(self.config)
            if f.name != "layout" and getattr(self.config, f.name) != f.default
        }
        return f"OvercookedV2(layout={self.layout.name!r}, {changed})"


def _check_actions(actions, shape: tuple, what: str) -> None:
    """Actions must have ``shape`` and an integer dtype (static checks), and, when concrete, lie in 0..5.

    Traced actions are not range-checked: that would cost every step. Out of range they act as STAY here,
    while the reference wraps -6..-1 to 0..5 and moves any other out-of-range action RIGHT.
    """
    got = tuple(np.shape(actions))
    if got != shape:
        raise ValueError(f"{what} has shape {got}, expected {shape} (one action per agent)")
    dtype = actions.dtype if hasattr(actions, "dtype") else np.asarray(actions).dtype
    if not jnp.issubdtype(dtype, jnp.integer):
        raise ValueError(f"{what} must be integers 0..{it.NUM_ACTIONS - 1}, got dtype {dtype}")
    if isinstance(actions, jax.core.Tracer):
        return
    values = np.asarray(actions)
    bad = np.argwhere((values < 0) | (values >= it.NUM_ACTIONS))
    if len(bad):
        index = tuple(int(i) for i in bad[0])
        where = f"{what}[{index[0]}]" if index else what
        raise ValueError(
            f"{where} is {values[index]}, not an action; actions are 0..{it.NUM_ACTIONS - 1} "
            f"({', '.join(f'{a.value} {a.name}' for a in it.Action)})"
        )
