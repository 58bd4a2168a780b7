"""ocv2: OvercookedV2 in pure JAX, transition-for-transition equal to ``jaxmarl==0.2.0``.

The environment alone: nothing in this package imports the learning code (``population``) or the runtime
(``cluster``); tests/test_layers.py checks it. Trained policies are ``population.policy``.
"""

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
    # `ocv2.policy` was an alias of population.policy until the environment stopped importing upward: say
    # where it went instead of a bare AttributeError.
    if name == "policy":
        raise AttributeError("module 'ocv2' has no attribute 'policy': use `from population import policy`")
    raise AttributeError(f"module 'ocv2' has no attribute {name!r}")
