"""ocv2: OvercookedV2 in pure JAX, transition-for-transition equal to ``jaxmarl==0.2.0``."""

from ocv2.config import EnvConfig
from ocv2.env import OvercookedV2, StepArrays, make
from ocv2.items import Action, Direction, Static
from ocv2.layouts import LAYOUTS, REFERENCE_LAYOUT_NAMES, Layout
from ocv2.state import Agents, State, stack_states

__all__ = [
    "Action", "Agents", "Direction", "EnvConfig", "LAYOUTS", "Layout", "OvercookedV2",
    "REFERENCE_LAYOUT_NAMES", "State", "Static", "StepArrays", "make", "stack_states",
]
