"""Kitchen layouts: the ``Layout`` record, the ASCII builder with validation, and every built-in map.

Layout characters (the reference's): ``W`` counter, ``X`` delivery, ``B`` plate pile, ``P`` pot,
``R`` recipe indicator, ``L`` button recipe indicator, ``0``-``9`` ingredient piles (``O`` = ``0``),
``A`` agent start (a floor cell), space = floor. Unlike the reference, any other character is an
error, and so is a map an agent could walk off (its room touches the map's edge).
"""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import types
import warnings
from collections import deque
from collections.abc import Mapping, Sequence

import numpy as np

from ocv2.items import MAX_INGREDIENT_KINDS, Static

CHAR_TO_STATIC = {
    " ": Static.FLOOR,
    "A": Static.FLOOR,
    "W": Static.WALL,
    "X": Static.GOAL,
    "B": Static.PLATE_PILE,
    "P": Static.POT,
    "R": Static.RECIPE_INDICATOR,
    "L": Static.BUTTON,
    "O": Static.INGREDIENT_PILE,  # deprecated alias of '0'
    **{str(i): Static.INGREDIENT_PILE + i for i in range(MAX_INGREDIENT_KINDS)},
}
STATIC_TO_CHAR = {int(v): k for k, v in CHAR_TO_STATIC.items() if k not in ("A", "O")}


def default_recipes(num_ingredients: int) -> tuple[tuple[int, int, int], ...]:
    """Every multiset of 3 ingredients, in the reference's order.

    The reference collects the recipes in a Python ``set`` of sorted tuples and samples them by
    index, so matching its random stream needs the same (CPython set iteration) order; we rebuild
    the set from the same insertions to get it. The order is deterministic for tuples of ints.
    """
    pool = list(range(num_ingredients)) * 3
    unique = set(tuple(sorted(combo)) for combo in itertools.combinations(pool, 3))
    return tuple(tuple(int(i) for i in recipe) for recipe in unique)


def _room_labels(walkable: np.ndarray) -> np.ndarray:
    """Label 4-connected floor regions; id = largest row-major index in the region, -1 elsewhere.

    Only equality of ids matters; the id choice mirrors the reference for easy cross-checking.
    """
    height, width = walkable.shape
    labels = np.full((height, width), -1, dtype=np.int32)
    for start in zip(*np.nonzero(walkable)):
        if labels[start] != -1:
            continue
        cells, queue = [start], deque([start])
        labels[start] = 0
        while queue:
            y, x = queue.popleft()
            for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                ny, nx = y + dy, x + dx
                if 0 <= ny < height and 0 <= nx < width and walkable[ny, nx] and labels[ny, nx] == -1:
                    labels[ny, nx] = 0
                    cells.append((ny, nx))
                    queue.append((ny, nx))
        room_id = max(y * width + x for y, x in cells)
        for cell in cells:
            labels[cell] = room_id
    return labels


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
    """A kitchen: static cells, agent starts and the recipes that can be ordered.

    Attributes:
        static_objects: int32 (H, W) array of ``Static`` ids (rows x columns).
        agent_positions: (x, y) start cell of each agent, in agent index order.
        num_ingredients: n, the number of ingredient kinds (1 + the highest pile index).
        possible_recipes: the recipes (3 ingredient indices each) drawn at reset.
        name: a label for listings and archives.
    """

    static_objects: np.ndarray
    agent_positions: tuple[tuple[int, int], ...]
    num_ingredients: int
    possible_recipes: tuple[tuple[int, int, int], ...] | None = None
    name: str = "custom"

    def __post_init__(self):
        grid = np.array(self.static_objects, dtype=np.int32)
        if grid.ndim != 2 or grid.size == 0:
            raise ValueError(
                f"layout {self.name!r}: static_objects must be a non-empty 2-D array, got shape {grid.shape}"
            )
        grid.setflags(write=False)
        object.__setattr__(self, "static_objects", grid)
        positions = tuple((int(x), int(y)) for x, y in self.agent_positions)
        object.__setattr__(self, "agent_positions", positions)
        if int(self.num_ingredients) < 1:
            raise ValueError(f"layout {self.name!r}: needs at least one ingredient pile (characters 0-9)")
        object.__setattr__(self, "num_ingredients", int(self.num_ingredients))
        recipes = self.possible_recipes
        if recipes is None:
            present = sorted({int(v) - Static.INGREDIENT_PILE for v in grid.ravel() if v >= Static.INGREDIENT_PILE})
            absent = [i for i in range(self.num_ingredients) if i not in present]
            if not present:
                raise ValueError(f"layout {self.name!r}: no ingredient pile on the map (characters 0-9)")
            if absent:  # the default is every recipe of ingredients 0..n-1, some of which no pile gives
                raise ValueError(
                    f"layout {self.name!r}: ingredient piles {', '.join(map(str, present))} but no "
                    f"{', '.join(map(str, absent))}; number the piles 0 to {len(present) - 1} without gaps, or "
                    "give possible_recipes that use only the piles on the map"
                )
            recipes = default_recipes(self.num_ingredients)
        object.__setattr__(self, "possible_recipes", _validate_recipes(recipes, grid, self.num_ingredients, self.name))
        self._validate_agents(grid, positions)

    def _validate_agents(self, grid: np.ndarray, positions):
        height, width = grid.shape
        if not positions:
            raise ValueError(f"layout {self.name!r}: no agent; mark at least one start cell with 'A'")
        if len(set(positions)) != len(positions):
            raise ValueError(f"layout {self.name!r}: two agents start on the same cell: {positions}")
        rooms = _room_labels(grid == Static.FLOOR)
        for index, (x, y) in enumerate(positions):
            if not (0 <= x < width and 0 <= y < height):
                raise ValueError(
                    f"layout {self.name!r}: agent {index} at (x={x}, y={y}) is outside the {height}x{width} map"
                )
            if grid[y, x] != Static.FLOOR:
                raise ValueError(
                    f"layout {self.name!r}: agent {index} starts on a non-floor cell (row {y}, column {x})"
                )
            room = rooms == rooms[y, x]
            edge = np.zeros_like(room)
            edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
            leaks = np.argwhere(room & edge)
            if len(leaks):
                ry, rx = (int(v) for v in leaks[0])
                raise ValueError(
                    f"layout {self.name!r}: agent {index} (row {y}, column {x}) can walk to the map edge at "
                    f"row {ry}, column {rx}: the border is open; close it with counters ('W') or other non-floor cells"
                )

    @property
    def height(self) -> int:
        return self.static_objects.shape[0]

    @property
    def width(self) -> int:
        return self.static_objects.shape[1]

    @property
    def num_agents(self) -> int:
        return len(self.agent_positions)

    @property
    def room_labels(self) -> np.ndarray:
        """Room id of every floor cell (4-connected components), -1 on non-floor cells."""
        return _room_labels(self.static_objects == Static.FLOOR)

    def to_string(self) -> str:
        """The ASCII map (agents as 'A'); ``from_string(to_string())`` gives the same layout."""
        rows = [[STATIC_TO_CHAR[int(v)] for v in row] for row in self.static_objects]
        for x, y in self.agent_positions:
            rows[y][x] = "A"
        return "\n".join("".join(row) for row in rows)

    @staticmethod
    def from_string(grid: str, possible_recipes=None, swap_agents: bool = False, name: str = "custom") -> Layout:
        """Build a layout from an ASCII map (one line per row; leading/trailing empty line dropped).

        Short rows are padded on the right with floor, as in the reference. Agents are numbered in
        reading order (``swap_agents`` reverses it). Without ``possible_recipes`` the map must hold
        a recipe indicator ``R`` and every 3-ingredient recipe is possible.

        Raises:
            ValueError: unknown character (with row/column), no agent, an open border, recipes of the
                wrong form or naming an ingredient without a pile, no ``R`` and no recipes.
        """
        if not isinstance(grid, str):
            raise TypeError(f"layout {name!r}: from_string expects a str, got {type(grid).__name__}")
        rows = grid.split("\n")
        if rows and rows[0] == "":
            rows = rows[1:]
        if rows and rows[-1] == "":
            rows = rows[:-1]
        if not rows or max(len(r) for r in rows) == 0:
            raise ValueError(f"layout {name!r}: the map is empty")
        static = np.zeros((len(rows), max(len(r) for r in rows)), dtype=np.int32)
        agents = []
        for y, row in enumerate(rows):
            for x, char in enumerate(row):
                if char not in CHAR_TO_STATIC:
                    raise ValueError(
                        f"layout {name!r}: unknown character {char!r} at row {y}, column {x}; "
                        f"valid characters are {''.join(sorted(CHAR_TO_STATIC))!r} and space"
                    )
                static[y, x] = CHAR_TO_STATIC[char]
                if char == "A":
                    agents.append((x, y))
        if swap_agents:
            agents = agents[::-1]
        piles = static[static >= Static.INGREDIENT_PILE]
        num_ingredients = int(piles.max() - Static.INGREDIENT_PILE + 1) if piles.size else 0
        if num_ingredients < 1:
            raise ValueError(f"layout {name!r}: no ingredient pile; add at least one of the characters 0-9")
        if possible_recipes is None and not (static == Static.RECIPE_INDICATOR).any():
            raise ValueError(
                f"layout {name!r}: without a recipe indicator 'R' the possible recipes must be given "
                "(possible_recipes=[[i, j, k], ...])"
            )
        layout = Layout(static, tuple(agents), num_ingredients, possible_recipes, name=name)
        problems = kitchen_problems(layout)
        if problems:  # a legal map (the reference builds it too), but one where no soup is ever delivered
            warnings.warn(f"layout {name!r}: no soup can be delivered: {'; '.join(problems)}", LayoutWarning, 2)
        return layout


class LayoutWarning(UserWarning):
    """A map that builds, but where the cooks cannot earn a delivery reward."""


def kitchen_problems(layout: Layout) -> list[str]:
    """Why no soup can be delivered in ``layout`` (empty: none found): no pot, serving window, plate pile or
    ingredient pile, or none of them that a cook can reach (no floor cell beside it in a room a cook starts in)."""
    static = np.asarray(layout.static_objects)
    walkable = static == Static.FLOOR
    labels = _room_labels(walkable)
    rooms = [labels[y, x] for x, y in layout.agent_positions if walkable[y, x]]
    reachable = np.pad(np.isin(labels, rooms) & walkable, 1)
    beside = reachable[:-2, 1:-1] | reachable[2:, 1:-1] | reachable[1:-1, :-2] | reachable[1:-1, 2:]
    problems = []
    for what, cells in (
        ("pot", static == Static.POT),
        ("serving window", static == Static.GOAL),
        ("plate pile", static == Static.PLATE_PILE),
        ("ingredient pile", static >= Static.INGREDIENT_PILE),
    ):
        if not cells.any():
            problems.append(f"no {what}")
        elif not (cells & beside).any():
            y, x = np.argwhere(cells)[0]
            article = "an" if what[0] in "aeiou" else "a"
            problems.append(f"no cook can reach {article} {what} (the first at row {y}, column {x})")
    return problems


def _validate_recipes(recipes, grid: np.ndarray, num_ingredients: int, name: str):
    if isinstance(recipes, (str, bytes)) or not isinstance(recipes, Sequence):
        raise ValueError(f"layout {name!r}: possible_recipes must be a list of 3-ingredient lists, got {recipes!r}")
    if len(recipes) == 0:
        raise ValueError(f"layout {name!r}: possible_recipes is empty; give at least one recipe")
    piles = {int(v) - Static.INGREDIENT_PILE for v in np.unique(grid) if v >= Static.INGREDIENT_PILE}
    out = []
    for r, recipe in enumerate(recipes):
        if isinstance(recipe, (str, bytes)) or not isinstance(recipe, Sequence) or len(recipe) != 3:
            raise ValueError(f"layout {name!r}: recipe {r} ({recipe!r}) must list exactly 3 ingredient indices")
        for ingredient in recipe:
            if isinstance(ingredient, bool) or not isinstance(ingredient, (int, np.integer)):
                raise TypeError(f"layout {name!r}: recipe {r} ({recipe!r}) has a non-integer ingredient {ingredient!r}")
            if not 0 <= ingredient < num_ingredients or int(ingredient) not in piles:
                raise ValueError(
                    f"layout {name!r}: recipe {r} ({list(recipe)}) names ingredient {ingredient}, which has no pile "
                    f"on the map (piles: {sorted(piles)})"
                )
        out.append(tuple(int(i) for i in recipe))
    return tuple(out)


_MAPS = {
    "cramped_room": ("WWPWW\nOA AO\nW   W\nWBWXW", [[0, 0, 0]], True),
    "asymm_advantages": ("WWWWWWWWW\nO WXWOW X\nW   P   W\nW A PA  W\nWWWBWBWWW", [[0, 0, 0]], False),
    "coord_ring": ("WWWPW\nW A P\nBAW W\nO   W\nWOXWW", [[0, 0, 0]], False),
    "forced_coord": ("WWWPW\nO WAP\nOAW W\nB W W\nWWWXW", [[0, 0, 0]], False),
    "counter_circuit": ("WWWPPWWW\nW A    W\nB WWWW X\nW     AW\nWWWOOWWW", [[0, 0, 0]], True),
    "cramped_room_v2": ("WWPWW\n0A A1\nW   R\nWBWXW", None, False),
    "asymm_advantages_recipes_center": ("WWWWWWWWW\n0 WXR01 X\n1   P   W\nW A PA  W\nWWWBWBWWW", None, False),
    "asymm_advantages_recipes_right": ("WWWWWWWWW\n0 WXW01 X\n1   P   R\nW A PA  W\nWWWBWBWWW", None, False),
    "asymm_advantages_recipes_left": ("WWWWWWWWW\n0 WXW01 X\n1   P   R\nR A PA  W\nWWWBWBWWW", None, False),
    "two_rooms": ("WWWWWB10W\nW   W   R\nP A W A W\nW   W   X\nWWWWWWWWW", None, False),
    "two_rooms_both": ("W01BWB10W\nW   W   R\nP A W A W\nW   W   X\nWWWWWWWWW", None, False),
    "long_room": ("WWWWWWWWWWWWWWW\nB            AP\n0             X\nWWWWWWWWWWWWWWW", [[0, 0, 0]], False),
    "fun_coordination": ("WWWWWWWWW\n0   X   2\nRA  P  AW\n1   B   3\nWWWWWWWWW", [[0, 0, 2], [1, 1, 3]], False),
    "more_fun_coordination": (
        "WWWWWWWWW\nW   X   W\nRA  P  A1\n0   P   2\nW   B   W\nWWWWWWWWW",
        [[0, 1, 1], [0, 2, 2]],
        False,
    ),
    "fun_symmetries": ("WWWWBWW\n2  W  0\nR APA X\n2  W  1\nWWWWBWW", [[0, 0, 0], [1, 1, 1]], False),
    "fun_symmetries_plates": ("WWWWWWW\nB  W  0\nR APA X\nB  W  1\nWWWWWWW", [[0, 0, 0], [1, 1, 1]], False),
    "fun_symmetries1": ("WWWWWBWW\n2  WW  0\nR AWPA X\n2  WW  1\nWWWWWBWW", [[0, 0, 0], [1, 1, 1]], False),
    "grounded_coord_simple": ("WW2WWWWW\nW  WB  0\nR ALPA X\nW  WB  1\nWW2WWWWW", [[0, 0, 0], [1, 1, 1]], False),
    "grounded_coord_ring": (
        "WWW2R2WWW\nW       W\nW WWLWW W\n2 0   B 2\nRAXAP X R\n2 1   B 2\nW WWLWW W\nW       W\nWWW2R2WWW",
        [[0, 0, 0], [1, 1, 1]],
        False,
    ),
    "test_time_simple": ("WW2WWWWW\nW  WB  0\nR AWPA X\nW  WB  1\nWW2WWWWW", [[0, 0, 0], [1, 1, 1]], False),
    "test_time_wide": ("WWXBWW\n0 A  0\n1    1\nWPWPWW\n3 A  3\nW    W\nWWRWWW", [[0, 0, 0], [1, 1, 1]], False),
    "demo_cook_simple": (
        "WWWWWR2W0WW\n0      W  B\nW     APA X\n1      W  B\nWWWWWR2W1WW",
        [[0, 0, 0], [1, 1, 1]],
        False,
    ),
    "demo_cook_wide": (
        "WWWWBXBWWWW\nWWW0 A 1WWW\nWWWWWPWWWWW\nW    A    W\n0  W3R3W  0\nW1WWWWWWW1W",
        [[0, 0, 0], [1, 1, 1]],
        False,
    ),
    # The paper's Figure 1 map; not registered in the reference, paired there with these recipes.
    "overcookedv2_demo": ("WWPWW\n0A A1\nL   R\nWBWXW", [[0, 0, 1], [0, 1, 1]], False),
}

#: Every built-in layout by its reference name (plus ``overcookedv2_demo``), read-only.
LAYOUTS: Mapping[str, Layout] = types.MappingProxyType(
    {
        name: Layout.from_string(grid, recipes, swap_agents=swap, name=name)
        for name, (grid, recipes, swap) in _MAPS.items()
    }
)

#: The names the reference registers (all but ``overcookedv2_demo``).
REFERENCE_LAYOUT_NAMES = tuple(name for name in _MAPS if name != "overcookedv2_demo")


def get_layout(layout) -> Layout:
    """Resolve a layout name or pass a ``Layout`` through; a clear error for anything else."""
    if isinstance(layout, Layout):
        return layout
    if isinstance(layout, str):
        if layout not in LAYOUTS:
            close = difflib.get_close_matches(layout, list(LAYOUTS), n=3)
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise ValueError(f"unknown layout {layout!r}; choose one of: {', '.join(LAYOUTS)}{hint}")
        return LAYOUTS[layout]
    raise TypeError(f"layout must be a layout name or an ocv2.Layout, got {type(layout).__name__}")
