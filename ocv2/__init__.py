"""ocv2: OvercookedV2 in pure JAX, transition-for-transition equal to ``jaxmarl==0.2.0``.

``ocv2.policy`` (load, export, Policy) is ``population.policy``, looked up only when first used: the
environment package itself never imports the learning code (see docs/evaluation.md).
"""

import importlib

from ocv2.config import EnvConfig
from ocv2.env import OvercookedV2, StepArrays, make
from ocv2.items import Action, Direction, Static
from ocv2.layouts import LAYOUTS, REFERENCE_LAYOUT_NAMES, Layout
from ocv2.state import Agents, State, stack_states

__all__ = [
    "Action",
    "Agents",
    "Direction",
    "EnvConfig",
    "LAYOUTS",
    "Layout",
    "OvercookedV2",
    "REFERENCE_LAYOUT_NAMES",
    "State",
    "Static",
    "StepArrays",
    "make",
    "stack_states",
]


def __getattr__(name: str):
    # Lazy: `import ocv2` loads neither the learning code (population/) nor optax. It does load flax,
    # whose struct dataclasses are the State pytrees (and what flax.serialization checkpoints know).
    if name == "policy":
        return importlib.import_module("population.policy")
    raise AttributeError(f"module 'ocv2' has no attribute {name!r}")
