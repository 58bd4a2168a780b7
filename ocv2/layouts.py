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


def _edge_cells(shape: tuple[int, int]) -> np.ndarray:
    """A bool (H, W) mask of the map's outermost rows and columns."""
    edge = np.zeros(shape, dtype=bool)
    edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
    return edge


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
        grid = _checked_grid(self.static_objects, self.name)
        grid.setflags(write=False)
        object.__setattr__(self, "static_objects", grid)
        positions = _checked_positions(self.agent_positions, self.name)
        object.__setattr__(self, "agent_positions", positions)
        object.__setattr__(self, "num_ingredients", _checked_num_ingredients(self.num_ingredients, grid, self.name))
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

    def first_difference(self, static_layers) -> tuple[int, ...] | None:
        """Where concrete static layers ([..., H, W], any leading axes) first differ from this kitchen's map: the
        index (leading indices, then row and column), or None when every layer is this kitchen's. Used to refuse a
        state of another kitchen (reset's state buffers, the renderer) with the cell that tells them apart."""
        differs = np.asarray(static_layers) != self.static_objects
        if not differs.any():
            return None
        return tuple(int(i) for i in np.argwhere(differs)[0])

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
            leaks = np.argwhere(room & _edge_cells(grid.shape))
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
        rows = grid.replace("\r\n", "\n").split("\n")  # a map saved with Windows line endings reads the same
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
                    hint = " (a carriage return: end the map's lines with \\n)" if char == "\r" else ""
                    raise ValueError(
                        f"layout {name!r}: unknown character {char!r}{hint} at row {y}, column {x} (counted from 0); "
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
        _check_padding_closed(static, agents, [len(row) for row in rows], name)
        layout = Layout(static, tuple(agents), num_ingredients, possible_recipes, name=name)
        _warn_unreached_edge_floor(layout)
        problems, some_served = _kitchen_report(layout)
        if problems:  # a legal map (the reference builds it too), but one where some or all orders never pay
            what = "some orders can never be delivered" if some_served else "no soup can be delivered"
            warnings.warn(f"layout {name!r}: {what}: {'; '.join(problems)}", LayoutWarning, 2)
        return layout


def _check_padding_closed(static: np.ndarray, agents, row_lengths: list[int], name: str) -> None:
    """Refuse a short row whose floor padding a cook can walk on: padding runs to the right edge, so that
    cook could walk off the map. Said by row length, since the padded column is nowhere in the text."""
    width = static.shape[1]
    padding = np.arange(width)[None, :] >= np.asarray(row_lengths)[:, None]
    rooms = _room_labels(static == Static.FLOOR)
    for index, (x, y) in enumerate(agents):
        reached = np.argwhere((rooms == rooms[y, x]) & padding)
        if len(reached):
            row = int(reached[0][0])
            raise ValueError(
                f"layout {name!r}: row {row} has {row_lengths[row]} characters, the map is {width} wide; short rows "
                f"are padded with floor, and agent {index} (row {y}, column {x}) can walk through that padding off "
                f"the map: the border is open; write the row out to its full width, ending in a counter ('W')"
            )


class LayoutWarning(UserWarning):
    """A map that builds, but where the cooks can never earn the delivery reward of some or all orders."""


class LayoutEdgeWarning(UserWarning):
    """A map with floor on its edge that no cook can reach: most often an indented map or trailing spaces, which
    widen the map, and with it every observation, by columns of floor nobody uses (the reference builds it too)."""


def _warn_unreached_edge_floor(layout: Layout) -> None:
    grid = layout.static_objects
    rooms = _room_labels(grid == Static.FLOOR)
    used = [rooms[y, x] for x, y in layout.agent_positions]
    unreached = np.argwhere(_edge_cells(grid.shape) & (grid == Static.FLOOR) & ~np.isin(rooms, used))
    if len(unreached):
        row, column = (int(v) for v in unreached[0])
        warnings.warn(
            f"layout {layout.name!r}: floor that no cook can reach on the map's edge (the first at row {row}, column "
            f"{column}, counted from 0): an indented map, trailing spaces or a short row? The map is {layout.height} x "
            f"{layout.width}, and every observation that size; remove them, or put counters ('W') there",
            LayoutEdgeWarning,
            3,
        )


def kitchen_problems(layout: Layout) -> list[str]:
    """Why some or all orders of ``layout`` can never be delivered (empty: none found).

    A soup needs every ingredient of its recipe carried from a pile to one pot, a plate carried to that
    pot, and the dish carried to a serving window. Cooks stay in the room they start in; items cross
    between rooms on a counter both rooms touch, and a pot both touch passes its soup (filled from one
    side, plated from the other). Reported: a missing pot, window, plate pile or ingredient pile, one no
    cook can reach, no pot whose soup can be plated and served, and each recipe some of whose
    ingredients cannot reach such a pot.
    """
    return _kitchen_report(layout)[0]


def _kitchen_report(layout: Layout) -> tuple[list[str], bool]:
    """(problems, whether any recipe can be delivered at all)."""
    static = np.asarray(layout.static_objects)
    problems = _unreachable_parts(layout)
    if problems:
        return problems, False
    teams = _teams_beside(layout)

    def teams_at(cells: np.ndarray) -> set[int]:
        return set().union(*(teams[y][x] for y, x in np.argwhere(cells)))

    serving = teams_at(static == Static.PLATE_PILE) & teams_at(static == Static.GOAL)
    servable_pots = [teams[y][x] for y, x in np.argwhere(static == Static.POT) if teams[y][x] & serving]
    if not servable_pots:
        return [
            "no pot where a cook who can fetch a plate and reach a serving window can take the soup out "
            "(no counter links the rooms that hold them)"
        ], False
    suppliers = {i: teams_at(static == Static.INGREDIENT_PILE + i) for i in range(layout.num_ingredients)}
    blocked = {}  # missing ingredients -> the recipes they block
    for recipe in dict.fromkeys(layout.possible_recipes):
        needed = sorted(set(recipe))
        missing = min(([i for i in needed if not pot & suppliers[i]] for pot in servable_pots), key=len)
        if missing:
            blocked.setdefault(tuple(missing), []).append(list(recipe))
    problems = [
        f"recipe{'s' if len(recipes) > 1 else ''} {', '.join(map(str, recipes))} can never be served: no cook can "
        f"bring ingredient{'s' if len(missing) > 1 else ''} {', '.join(_pile_place(static, i) for i in missing)} to a pot whose soup can be plated "
        "and served"
        for missing, recipes in blocked.items()
    ]
    unservable = sum(len(recipes) for recipes in blocked.values())
    return problems, unservable < len(set(layout.possible_recipes))


def _pile_place(static: np.ndarray, ingredient: int) -> str:
    y, x = np.argwhere(static == Static.INGREDIENT_PILE + ingredient)[0]
    return f"{ingredient} (pile at row {y}, column {x})"


def _unreachable_parts(layout: Layout) -> list[str]:
    """A missing pot, serving window, plate pile or ingredient pile, or one beside no room a cook starts in."""
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


def _teams_beside(layout: Layout) -> list[list[frozenset[int]]]:
    """For every cell, the teams whose cooks can use it from a neighbouring floor cell.

    A team is the cooks of rooms linked by counters: a counter beside two rooms lets their cooks pass
    any item. A team's id is the id of one of its rooms."""
    static = np.asarray(layout.static_objects)
    labels = _room_labels(static == Static.FLOOR)
    cook_rooms = {int(labels[y, x]) for x, y in layout.agent_positions}
    height, width = static.shape

    def rooms_beside(y: int, x: int) -> set[int]:
        around = ((y + dy, x + dx) for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)))
        return {int(labels[ny, nx]) for ny, nx in around if 0 <= ny < height and 0 <= nx < width} & cook_rooms

    team = {room: room for room in cook_rooms}

    def root(room: int) -> int:
        while team[room] != room:
            room = team[room]
        return room

    for y, x in np.argwhere(static == Static.WALL):
        linked = sorted(root(r) for r in rooms_beside(y, x))
        for other in linked[1:]:
            team[other] = linked[0]
    return [[frozenset(root(r) for r in rooms_beside(y, x)) for x in range(width)] for y in range(height)]


def _is_integer(value) -> bool:
    """A Python or numpy integer, or a 0-d array of an integer dtype (a JAX scalar): not a bool, a float or a
    numeric string, which ``int()`` would coerce."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (int, np.integer)):
        return True
    return hasattr(value, "__array__") and np.ndim(value) == 0 and np.issubdtype(np.asarray(value).dtype, np.integer)


def _is_sequence(value) -> bool:
    """A list, tuple or array (numpy's or JAX's) of at least one dimension; not a string."""
    if isinstance(value, (str, bytes)):
        return False
    return isinstance(value, (Sequence, np.ndarray)) or (hasattr(value, "__array__") and np.ndim(value) >= 1)


def _valid_cell_ids() -> str:
    named = ", ".join(f"{v} ({STATIC_TO_CHAR[v]!r})" for v in sorted(STATIC_TO_CHAR) if v < Static.INGREDIENT_PILE)
    last = Static.INGREDIENT_PILE + MAX_INGREDIENT_KINDS - 1
    return f"{named}, {int(Static.INGREDIENT_PILE)}-{last} (piles '0'-'{MAX_INGREDIENT_KINDS - 1}')"


def _checked_grid(static_objects, name: str) -> np.ndarray:
    """``static_objects`` as an int32 grid of known cell ids; the first unknown id is named by row and column."""
    raw = np.asarray(static_objects)
    if raw.ndim != 2 or raw.size == 0:
        raise ValueError(f"layout {name!r}: static_objects must be a non-empty 2-D array, got shape {raw.shape}")
    if raw.dtype.kind not in "iu":  # a float or bool grid would be cast, and 2.9 silently read as 2
        raise ValueError(f"layout {name!r}: static_objects must hold integer cell ids, got dtype {raw.dtype}")
    unknown = ~np.isin(raw, list(STATIC_TO_CHAR))
    if unknown.any():
        y, x = (int(v) for v in np.argwhere(unknown)[0])
        raise ValueError(
            f"layout {name!r}: static_objects has unknown cell id {raw[y, x]} at row {y}, column {x}; "
            f"valid ids (with their map characters) are {_valid_cell_ids()}"
        )
    return raw.astype(np.int32)


def _checked_positions(agent_positions, name: str) -> tuple[tuple[int, int], ...]:
    """Agent starts as (x, y) integer pairs; a float or string coordinate is refused, not truncated."""
    if not _is_sequence(agent_positions):
        raise ValueError(f"layout {name!r}: agent_positions must be a list of (x, y) pairs, got {agent_positions!r}")
    positions = []
    for index, position in enumerate(agent_positions):
        if not _is_sequence(position) or np.ndim(position) != 1 or len(position) != 2:
            raise ValueError(f"layout {name!r}: agent_positions[{index}] must be an (x, y) pair, got {position!r}")
        if not all(_is_integer(v) for v in position):
            raise TypeError(
                f"layout {name!r}: agent_positions[{index}] = {tuple(position)!r} must hold integer cell coordinates"
            )
        positions.append((int(position[0]), int(position[1])))
    return tuple(positions)


def _checked_num_ingredients(num_ingredients, grid: np.ndarray, name: str) -> int:
    """n must cover every pile on the map (else a pile's ingredient is invisible in observations) and fit
    the item encoding (at most ``MAX_INGREDIENT_KINDS`` kinds)."""
    if not _is_integer(num_ingredients):
        raise TypeError(f"layout {name!r}: num_ingredients must be an integer, got {num_ingredients!r}")
    piles = np.argwhere(grid >= Static.INGREDIENT_PILE)
    highest = max((int(grid[y, x]) - Static.INGREDIENT_PILE for y, x in piles), default=-1)
    low = max(1, highest + 1)
    if not low <= num_ingredients <= MAX_INGREDIENT_KINDS:
        where = ""
        if num_ingredients < low and highest >= 0:
            y, x = (int(v) for v in piles[np.argmax(grid[tuple(piles.T)])])
            where = f" (the map has a pile of ingredient {highest} at row {y}, column {x})"
        raise ValueError(
            f"layout {name!r}: num_ingredients is {num_ingredients}, must be in [{low}, {MAX_INGREDIENT_KINDS}]{where}"
        )
    return int(num_ingredients)


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
