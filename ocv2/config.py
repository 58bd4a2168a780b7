"""Frozen, validated settings of one environment instance (everything that fixes shapes or rules)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from ocv2.layouts import Layout, get_layout

OBSERVATION_TYPES = ("default", "featurized")


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Constructor parameters of ``ocv2.make``; names and defaults are the reference's.

    Reference-bug fixes are opt-in (``fix_*``); ``paper_obs_truncation`` reproduces the older
    environment the paper's agents were trained on. See ``docs/environment.md``.
    """

    layout: Layout
    max_steps: int = 400
    observation_type: str | tuple[str, ...] = "default"
    agent_view_size: int | None = None
    random_reset: bool = False
    random_agent_positions: bool = False
    start_cooking_interaction: bool = False
    negative_rewards: bool = False
    sample_recipe_on_delivery: bool = False
    indicate_successful_delivery: bool = False
    op_ingredient_permutations: tuple[int, ...] | None = None
    force_path_planning: bool = False
    # --- fixes of reference bugs (default: reproduce the reference) ---
    fix_negative_placement_reward: bool = False
    fix_offmap_interaction: bool = False
    fix_zero_view_size: bool = False
    fix_button_repress: bool = False
    # --- reproduce the paper's training environment ---
    paper_obs_truncation: bool = False
    # --- representation ---
    obs_dtype: str = "uint8"

    @property
    def num_agents(self) -> int:
        return self.layout.num_agents

    @property
    def num_ingredients(self) -> int:
        return self.layout.num_ingredients

    @property
    def observation_types(self) -> tuple[str, ...]:
        """One observation type per agent."""
        if isinstance(self.observation_type, tuple):
            return self.observation_type
        return (self.observation_type,) * self.num_agents

    @property
    def view_radius(self) -> int | None:
        """The effective view radius: None = whole map (the reference also treats 0 as None)."""
        if self.agent_view_size is None:
            return None
        if self.agent_view_size == 0 and not self.fix_zero_view_size:
            return None
        return self.agent_view_size

    @property
    def op_enabled(self) -> bool:
        return bool(self.op_ingredient_permutations)


_BOOL_FIELDS = (
    "random_reset",
    "random_agent_positions",
    "start_cooking_interaction",
    "negative_rewards",
    "sample_recipe_on_delivery",
    "indicate_successful_delivery",
    "force_path_planning",
    "fix_negative_placement_reward",
    "fix_offmap_interaction",
    "fix_zero_view_size",
    "fix_button_repress",
    "paper_obs_truncation",
)


def build_config(layout="cramped_room", **params) -> EnvConfig:
    """Validate user parameters into an ``EnvConfig``; every error names the parameter."""
    known = {f.name for f in dataclasses.fields(EnvConfig)} - {"layout"}
    unknown = sorted(set(params) - known)
    if unknown:
        raise TypeError(f"unknown environment parameter(s) {unknown}; valid parameters: {sorted(known)}")
    layout = get_layout(layout)
    for name in _BOOL_FIELDS:
        if name in params and not isinstance(params[name], bool):
            raise TypeError(f"{name} must be True or False, got {params[name]!r}")

    max_steps = params.get("max_steps", 400)
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or not 1 <= max_steps < 2**31:
        # the step counter in the state is int32
        raise ValueError(f"max_steps must be an integer in [1, 2**31), got {max_steps!r}")

    obs_type = params.get("observation_type", "default")
    obs_type = _validate_observation_type(obs_type, layout)
    params["observation_type"] = obs_type

    view = params.get("agent_view_size")
    if view is not None:
        if isinstance(view, bool) or not isinstance(view, int):
            raise TypeError(f"agent_view_size must be None or a non-negative int, got {view!r}")
        if not 0 <= view < 2**31:
            # the radius is compared with int32 positions inside jit
            raise ValueError(f"agent_view_size must be None or an integer in [0, 2**31), got {view}")
    types = obs_type if isinstance(obs_type, tuple) else (obs_type,)
    if "featurized" in types:
        if layout.num_ingredients != 1:
            raise ValueError(
                f"observation_type 'featurized' supports only single-ingredient layouts; layout {layout.name!r} "
                f"has {layout.num_ingredients} ingredients (use 'default')"
            )
        if view is not None:
            raise ValueError("observation_type 'featurized' cannot be combined with agent_view_size (it is not a grid)")

    perms = params.get("op_ingredient_permutations")
    if perms is not None:
        if isinstance(perms, (str, bytes)) or not isinstance(perms, Sequence):
            raise TypeError(f"op_ingredient_permutations must be a list of ingredient indices, got {perms!r}")
        perms = tuple(perms)
        for i in perms:
            if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < layout.num_ingredients:
                raise ValueError(
                    f"op_ingredient_permutations: {i!r} is not an ingredient index of layout {layout.name!r} "
                    f"(0..{layout.num_ingredients - 1})"
                )
        if len(set(perms)) != len(perms):
            raise ValueError(f"op_ingredient_permutations has repeated ingredients: {list(perms)}")
        params["op_ingredient_permutations"] = perms or None

    dtype = params.get("obs_dtype", "uint8")
    if dtype not in ("uint8", "int32"):
        raise ValueError(f"obs_dtype must be 'uint8' or 'int32', got {dtype!r}")
    return EnvConfig(layout=layout, **params)


def _validate_observation_type(obs_type, layout: Layout):
    if isinstance(obs_type, str):
        if obs_type not in OBSERVATION_TYPES:
            raise ValueError(f"unknown observation_type {obs_type!r}; choose one of {OBSERVATION_TYPES}")
        return obs_type
    if isinstance(obs_type, (list, tuple)):
        if len(obs_type) != layout.num_agents:
            raise ValueError(
                f"observation_type lists {len(obs_type)} types but layout {layout.name!r} has {layout.num_agents} agents"
            )
        for t in obs_type:
            if t not in OBSERVATION_TYPES:
                raise ValueError(f"unknown observation_type {t!r} in {list(obs_type)}; choose from {OBSERVATION_TYPES}")
        return tuple(obs_type)
    raise TypeError(f"observation_type must be a string or a list of strings, got {obs_type!r}")
