"""Pictures of kitchens: a pure-JAX renderer, episode roll-outs and looping GIFs.

``render(state)`` draws one state as an RGB image, one ``tile_size`` square per grid cell, in the
look of the reference visualiser (JaxMARL 0.2.0): black floor with grey grid
lines, grey counters with their item, a green delivery square, pots with their contents, lid and
cooking bar, plate and ingredient piles, recipe / button indicators and the agents as triangles in
their colour (red, blue, green, purple, yellow, orange) holding a small item.

How it works: every shape a tile can contain is rasterised once, in numpy, at ``subdivs`` times the
tile resolution and box-averaged down to a coverage mask in [0, 1] (anti-aliasing by supersampling,
paid once per tile size rather than per frame). A frame is then a fixed sequence of alpha blends
``img += coverage * cell_condition * (colour - img)`` over an ``[H, W, tile, tile, 3]`` array, where
the conditions and colours are per-cell arrays computed from the state. That is all elementwise
array work and gathers, so it jits, vmaps over time and batch axes, and costs the same for every
state.

Differences from the reference, on purpose: a correct delivery (``state.new_correct_delivery``) is
shown by gold borders on the delivery cells, and ``write_gif`` writes real frame durations and loops
forever (the reference wrote 0 ms frames that played once).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

from ocv2 import items as it
from ocv2.atomic import atomic_path
from ocv2.items import Static
from ocv2.layouts import Layout, get_layout
from ocv2.state import State

__all__ = [
    "render",
    "make_renderer",
    "render_frames",
    "rollout_states",
    "write_gif",
    "check_frame_size",
    "INGREDIENT_COLORS",
    "AGENT_COLORS",
]

# --- colours (RGB) ---
BLACK = (0, 0, 0)
GREY = (100, 100, 100)
WHITE = (255, 255, 255)
POT_BLACK = (25, 25, 25)
GREEN = (0, 255, 0)
RED = (255, 0, 0)
BROWN = (139, 69, 19)
GOLD = (255, 200, 0)
DELIVERED_GREEN = (170, 255, 170)

#: Ingredient colour by ingredient index: yellow, dark green, purple, cyan, red, orange, purple, blue,
#: pink, brown (the reference's table, duplicate purple included).
INGREDIENT_COLORS = np.array(
    [
        (255, 255, 0),
        (0, 150, 0),
        (160, 32, 240),
        (0, 255, 255),
        (255, 0, 0),
        (230, 180, 0),
        (160, 32, 240),
        (0, 0, 255),
        (255, 105, 180),
        (139, 69, 19),
    ],
    dtype=np.float32,
)
#: Agent colour by agent index: red, blue, green, purple, yellow, orange (later agents reuse orange).
AGENT_COLORS = np.array(
    [(255, 0, 0), (0, 0, 255), (0, 255, 0), (160, 32, 240), (255, 255, 0), (230, 180, 0)], dtype=np.float32
)

HIGHLIGHT = 0.3  # view-window cells are blended this far toward white
DEFAULT_SUBDIVS = 3

#: Pixels of one frame at most: a 4K screen (3840 x 2160), so every picture can be shown whole. Drawing
#: works on float32 ``[H, W, tile, tile, 3]`` arrays and their blends: ``ocv2 play`` at this bound
#: (cramped_room, tile size 643) peaked at 1 GB and took 1.3 s a tick on 2 busy CPU cores; at tile
#: size 1500, 3.4 GB and 4-8 s, and 6000 was killed for memory.
MAX_FRAME_PIXELS = 3840 * 2160
#: Bytes of the RGB frames one call holds together (a GIF's): beyond this, refuse rather than swap.
MAX_FRAMES_BYTES = 2 << 30


# ---------------------------------------------------------------------------------------------------
# Constant coverage masks (numpy, once per tile size)
# ---------------------------------------------------------------------------------------------------


def _rect(x0, x1, y0, y1):
    return lambda x, y: (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)


def _circle(cx, cy, r):
    return lambda x, y: (x - cx) ** 2 + (y - cy) ** 2 <= r * r


def _union(*shapes):
    return lambda x, y: functools.reduce(np.logical_or, (s(x, y) for s in shapes))


def _triangle(a, b, c):
    """Points on the inner side of all three edges (either winding)."""

    def inside(x, y):
        def side(p, q):
            return (q[0] - p[0]) * (y - p[1]) - (q[1] - p[1]) * (x - p[0])

        s1, s2, s3 = side(a, b), side(b, c), side(c, a)
        return ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))

    return inside


def _rotated(shape, cx, cy, theta):
    """``shape`` rotated by ``theta`` radians about (cx, cy) in image coordinates (y down).

    Positive ``theta`` turns clockwise on screen (x axis toward the y axis).
    """
    cos, sin = math.cos(theta), math.sin(theta)

    def inside(x, y):
        dx, dy = x - cx, y - cy  # undo the rotation: rotate the sample point by -theta
        return shape(cx + cos * dx + sin * dy, cy - sin * dx + cos * dy)

    return inside


# Facing angle per Direction (UP, DOWN, RIGHT, LEFT) for a triangle drawn pointing right.
_DIRECTION_ANGLE = {
    it.Direction.UP: -math.pi / 2,
    it.Direction.DOWN: math.pi / 2,
    it.Direction.RIGHT: 0.0,
    it.Direction.LEFT: math.pi,
}


@functools.lru_cache(maxsize=16)
def _masks(tile_size: int, subdivs: int) -> dict[str, np.ndarray]:
    """Coverage in [0, 1] of every shape, float32 [tile, tile] (or [k, tile, tile] for tables)."""
    fine = tile_size * subdivs
    coords = (np.arange(fine, dtype=np.float64) + 0.5) / fine
    x, y = np.meshgrid(coords, coords)  # x: column position, y: row position

    def cover(shape) -> np.ndarray:
        hit = np.asarray(shape(x, y), dtype=np.float32)
        return hit.reshape(tile_size, subdivs, tile_size, subdivs).mean(axis=(1, 3))

    def bar(k: int, per_step: float):
        return (
            cover(_rect(0.1, 0.9 - per_step * k, 0.83, 0.88))
            if 0.9 - per_step * k > 0.1
            else np.zeros((tile_size, tile_size), np.float32)
        )

    line = max(0.031, 1.0 / tile_size)  # grid lines: 3.1 % of the tile, at least one pixel
    lid = _union(_rect(0.1, 0.9, 0.21, 0.25), _rect(0.4, 0.6, 0.16, 0.21))
    right_triangle = _triangle((0.12, 0.19), (0.87, 0.50), (0.12, 0.81))
    inner = _rect(0.1, 0.9, 0.1, 0.9)
    masks = {
        "grid_lines": cover(_union(_rect(0.0, line, 0.0, 1.0), _rect(0.0, 1.0, 0.0, line))),
        "full": np.ones((tile_size, tile_size), np.float32),
        "inner": cover(inner),
        "frame": cover(lambda px, py: ~inner(px, py)),
        "button": cover(_circle(0.5, 0.5, 0.2)),
        "button_bar": np.stack([bar(k, 0.8 / it.BUTTON_ACTIVE_TIME) for k in range(it.BUTTON_ACTIVE_TIME + 1)]),
        "pot_bar": np.stack([bar(k, 0.8 / it.POT_COOK_TIME) for k in range(it.POT_COOK_TIME + 1)]),
        "plate_pile": cover(_union(*(_circle(cx, cy, 0.2) for cx, cy in [(0.3, 0.3), (0.75, 0.42), (0.4, 0.75)]))),
        "ingredient_pile": cover(
            _union(
                *(_circle(cx, cy, 0.15) for cx, cy in [(0.5, 0.15), (0.3, 0.4), (0.8, 0.35), (0.4, 0.8), (0.75, 0.75)])
            )
        ),
        "pot_slots": np.stack([cover(_circle(cx, 0.33, 0.13)) for cx in (0.23, 0.77, 0.50)]),
        "pot_body": cover(_rect(0.1, 0.9, 0.33, 0.9)),
        "lid_closed": cover(lid),
        "lid_open": cover(_rotated(lid, 0.1, 0.25, -0.1 * math.pi)),
        # an item lying on a counter / the recipe shown on an indicator
        "item_plate": cover(_circle(0.5, 0.5, 0.3)),
        "item_single": cover(_circle(0.5, 0.5, 0.15)),
        "item_dots": np.stack([cover(_circle(cx, cy, 0.1)) for cx, cy in [(0.5, 0.4), (0.4, 0.6), (0.6, 0.6)]]),
        # an item held by an agent (small, lower right)
        "held_plate": cover(_circle(0.75, 0.75, 0.2)),
        "held_single": cover(_circle(0.75, 0.75, 0.15)),
        "held_dots": np.stack([cover(_circle(cx, cy, 0.075)) for cx, cy in [(0.65, 0.65), (0.85, 0.65), (0.75, 0.85)]]),
        "agent": np.stack([cover(_rotated(right_triangle, 0.5, 0.5, _DIRECTION_ANGLE[d])) for d in it.Direction]),
    }
    for value in masks.values():
        value.setflags(write=False)
    return masks


# ---------------------------------------------------------------------------------------------------
# Drawing
# ---------------------------------------------------------------------------------------------------


def _paint(img, coverage, where, colour):
    """Blend ``colour`` into ``img`` [H, W, t, t, 3] with ``coverage`` ([t, t] or [H, W, t, t]) on cells ``where``.

    ``colour`` is an RGB triple or per-cell [H, W, 3].
    """
    alpha = jnp.asarray(coverage) * where[:, :, None, None].astype(jnp.float32)
    colour = jnp.asarray(colour, dtype=jnp.float32)
    if colour.ndim == 3:
        colour = colour[:, :, None, None, :]
    return img + alpha[..., None] * (colour - img)


def _ingredient_slots(item):
    """Up to three ingredient indices of an item, smallest first: (int32[..., 3], valid bool[..., 3], total)."""
    shifts = 2 + 2 * jnp.arange(it.MAX_INGREDIENT_KINDS, dtype=jnp.int32)
    counts = (item[..., None] >> shifts) & 3
    cumulative = jnp.cumsum(counts, axis=-1)
    total = cumulative[..., -1]
    ks = jnp.arange(3, dtype=jnp.int32)
    # Slot k holds the first ingredient whose running count exceeds k.
    slots = jnp.sum(cumulative[..., None, :] <= ks[:, None], axis=-1)
    slots = jnp.clip(slots, 0, it.MAX_INGREDIENT_KINDS - 1)
    return slots, ks < total[..., None], total


def _paint_item(img, item, where, plate_mask, single_mask, dot_masks):
    """Draw ``item`` (a plate, a raw ingredient or a dish) on the cells ``where``."""
    colours = jnp.asarray(INGREDIENT_COLORS)
    slots, valid, total = _ingredient_slots(item)
    plated = (item & it.PLATE) != 0
    img = _paint(img, plate_mask, where & plated, WHITE)
    img = _paint(img, single_mask, where & ~plated & (total == 1), colours[slots[..., 0]])
    as_dots = where & (plated | (total > 1))
    for k in range(3):
        img = _paint(img, dot_masks[k], as_dots & valid[..., k], colours[slots[..., k]])
    return img


def _render_tiles(state: State, static, agent_view_size, tile_size: int, subdivs: int):
    masks = _masks(tile_size, subdivs)
    grid = state.grid
    height, width = grid.shape[0], grid.shape[1]
    static = grid[:, :, 0] if static is None else static
    item, timer = grid[:, :, 1], grid[:, :, 2]
    ing_colours = jnp.asarray(INGREDIENT_COLORS)

    img = jnp.zeros((height, width, tile_size, tile_size, 3), jnp.float32)
    everywhere = jnp.ones((height, width), bool)
    img = _paint(img, masks["grid_lines"], everywhere, GREY)
    img = _paint(img, masks["full"], static != Static.FLOOR, GREY)

    # delivery: green square; gold frame + lighter square right after a correct delivery
    goal = static == Static.GOAL
    delivered = jnp.asarray(state.new_correct_delivery, bool)
    img = _paint(
        img,
        masks["inner"],
        goal,
        jnp.where(delivered, jnp.asarray(DELIVERED_GREEN, jnp.float32), jnp.asarray(GREEN, jnp.float32)),
    )
    img = _paint(img, masks["frame"], goal & delivered, GOLD)

    # counters' items, recipe indicators (always the order) and active buttons (the order + a timer bar)
    indicator = static == Static.RECIPE_INDICATOR
    button = static == Static.BUTTON
    active = button & (timer > 0)
    img = _paint(img, masks["inner"], indicator | button, BROWN)
    img = _paint(img, masks["button"], button & ~active, RED)
    img = _paint(img, jnp.asarray(masks["button_bar"])[jnp.clip(timer, 0, it.BUTTON_ACTIVE_TIME)], active, GREEN)
    dish = jnp.asarray(state.recipe, jnp.int32) | it.PLATE | it.COOKED
    shown = jnp.where(static == Static.WALL, item, jnp.where(indicator | active, dish, 0))
    img = _paint_item(img, shown, shown != 0, masks["item_plate"], masks["item_single"], masks["item_dots"])

    # piles
    img = _paint(img, masks["plate_pile"], static == Static.PLATE_PILE, WHITE)
    pile = static >= Static.INGREDIENT_PILE
    pile_colour = ing_colours[jnp.clip(static - Static.INGREDIENT_PILE, 0, it.MAX_INGREDIENT_KINDS - 1)]
    img = _paint(img, masks["ingredient_pile"], pile, pile_colour)

    # pots: contents (partly behind the body), body, lid (tilted open while idle and non-empty), timer bar
    pot = static == Static.POT
    slots, valid, total = _ingredient_slots(item)
    for k in range(3):
        img = _paint(img, masks["pot_slots"][k], pot & valid[..., k], ing_colours[slots[..., k]])
    cooking = timer > 0
    idle = ~cooking & ((item & it.COOKED) == 0)
    lid_open = pot & idle & (total > 0)
    img = _paint(img, masks["pot_body"], pot, POT_BLACK)
    img = _paint(img, masks["lid_closed"], pot & ~lid_open, POT_BLACK)
    img = _paint(img, masks["lid_open"], lid_open, POT_BLACK)
    img = _paint(img, jnp.asarray(masks["pot_bar"])[jnp.clip(timer, 0, it.POT_COOK_TIME)], pot & cooking, GREEN)

    # agents: a triangle facing their direction, the held item small at the lower right
    agents = state.agents
    rows = jnp.arange(height, dtype=jnp.int32)[None, :, None]
    cols = jnp.arange(width, dtype=jnp.int32)[None, None, :]
    on_cell = (agents.y[:, None, None] == rows) & (agents.x[:, None, None] == cols)  # [N, H, W]
    present = on_cell.any(axis=0)
    index = jnp.argmax(on_cell, axis=0)  # lowest agent index on the cell
    agent_colour = jnp.asarray(AGENT_COLORS)[jnp.minimum(index, len(AGENT_COLORS) - 1)]
    facing = jnp.clip(agents.dir[index], 0, 3)
    img = _paint(img, jnp.asarray(masks["agent"])[facing], present, agent_colour)
    held = jnp.where(present, agents.inventory[index], 0)
    img = _paint_item(img, held, held != 0, masks["held_plate"], masks["held_single"], masks["held_dots"])

    if agent_view_size is not None:
        near = (jnp.abs(agents.y[:, None, None] - rows) <= agent_view_size) & (
            jnp.abs(agents.x[:, None, None] - cols) <= agent_view_size
        )
        seen = near.any(axis=0)
        img = jnp.where(seen[:, :, None, None, None], img + HIGHLIGHT * (255.0 - img), img)

    img = jnp.clip(jnp.round(img), 0, 255).astype(jnp.uint8)
    return img.transpose(0, 2, 1, 3, 4).reshape(height * tile_size, width * tile_size, 3)


@functools.partial(jax.jit, static_argnames=("layout", "agent_view_size", "tile_size", "subdivs"))
def _render_jit(state, layout, agent_view_size, tile_size, subdivs):
    static = None if layout is None else jnp.asarray(layout.static_objects, dtype=jnp.int32)
    return _render_tiles(state, static, agent_view_size, tile_size, subdivs)


def check_frame_size(layout: Layout, tile_size: int, frames: int = 1) -> None:
    """Refuse, before anything is drawn, frames of ``layout`` too big for memory or for any screen.

    ``ocv2 render`` (a GIF of ``frames`` frames) and ``ocv2 play`` (a frame per tick) check their
    ``--tile-size`` here; the caller adds the flag names to the message.

    Raises:
        ValueError: one line with the size asked for and the bound: a frame over ``MAX_FRAME_PIXELS``
            (naming the largest tile size for this layout), or frames over ``MAX_FRAMES_BYTES``.
    """
    cells = layout.height * layout.width
    width, height = layout.width * tile_size, layout.height * tile_size
    if width * height > MAX_FRAME_PIXELS:
        largest = math.isqrt(MAX_FRAME_PIXELS // cells)
        raise ValueError(
            f"{layout.name} would be {width}x{height} pixels, over the {MAX_FRAME_PIXELS:,} of a 4K screen "
            f"(3840x2160): the tile size for {layout.name} is at most {largest}"
        )
    needed = frames * width * height * 3
    if needed > MAX_FRAMES_BYTES:
        raise ValueError(
            f"{frames} frames of {width}x{height} pixels need {needed / 2**30:.1f} GiB, over "
            f"{MAX_FRAMES_BYTES / 2**30:.0f} GiB: use fewer frames or a smaller tile size"
        )


def _check_grid_fits(grid, layout: Layout | None) -> None:
    """The grid (any leading axes) must be of ``layout``: its shape always, its static layer when concrete.

    Otherwise the layout's map would be drawn over another kitchen's items and agents.
    """
    if layout is None:
        return
    if tuple(grid.shape[-3:-1]) != (layout.height, layout.width):
        raise ValueError(
            f"state grid is {tuple(grid.shape[-3:-1])} (HxW) but layout {layout.name!r} is "
            f"{layout.height}x{layout.width}"
        )
    if isinstance(grid, jax.core.Tracer):
        return
    static = np.asarray(grid)[..., 0]
    where = layout.first_difference(static)
    if where is not None:
        frame = f"frame {', '.join(map(str, where[:-2]))} " if len(where) > 2 else ""
        row, column = where[-2:]
        raise ValueError(
            f"state grid {frame}is not of layout {layout.name!r}: its static cell at row {row}, column {column} "
            f"is {static[where]}, the layout's is {layout.static_objects[row, column]}"
        )


def _whole(value, low: int) -> bool:
    """A Python or numpy integer (not a bool) of at least ``low``."""
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= low


def _check_options(agent_view_size, tile_size, subdivs):
    if not _whole(tile_size, 1):
        raise ValueError(f"tile_size must be a positive integer (pixels per cell), got {tile_size!r}")
    if not _whole(subdivs, 1):
        raise ValueError(f"subdivs must be a positive integer (supersampling factor), got {subdivs!r}")
    if agent_view_size is not None and not (_whole(agent_view_size, 0) and agent_view_size < 2**31):
        # compared with int32 positions on the device
        raise ValueError(f"agent_view_size must be None or an integer in [0, 2**31), got {agent_view_size!r}")


def render(
    state: State,
    layout_or_none: Layout | str | None = None,
    *,
    agent_view_size: int | None = None,
    tile_size: int = 32,
    subdivs: int = DEFAULT_SUBDIVS,
) -> jax.Array:
    """Draw one state: uint8[H * tile_size, W * tile_size, 3].

    Pure JAX: call it eagerly (it is jitted inside, compiled once per layout / options), under
    ``jax.jit`` with the keyword options static, or under ``jax.vmap`` for stacked states
    (``jax.vmap(render)(states)`` renders a time or batch axis).

    Args:
        state: one ``State`` (no leading axes; vmap for those).
        layout_or_none: optionally the state's layout (or its name). Its static map is then drawn as
            a constant instead of being read from ``state.grid`` (the two agree for every state of the
            layout); the grid's shape is checked against it, and so is its static layer when the grid
            is concrete (not traced).
        agent_view_size: view radius v; every cell within v (Chebyshev) of an agent is blended 30 %
            toward white. None draws no view window. Note 0 highlights the agents' own cells; the
            env's ``config.view_radius`` already maps the reference's "0 means whole map" to None.
        tile_size: pixels per cell side.
        subdivs: supersampling factor of the (precomputed) shape masks.

    Raises:
        ValueError: bad options, or a grid that does not match ``layout_or_none``.
    """
    _check_options(agent_view_size, tile_size, subdivs)
    layout = None if layout_or_none is None else get_layout(layout_or_none)
    _check_grid_fits(state.grid, layout)
    if state.grid.ndim != 3:
        raise ValueError(
            f"render draws one state (grid of rank 3), got grid shape {tuple(state.grid.shape)}; "
            "use jax.vmap(render) or render_frames for stacked states"
        )
    view = None if agent_view_size is None else int(agent_view_size)
    return _render_jit(state, layout, view, int(tile_size), int(subdivs))


def render_frames(
    states: State,
    layout_or_none: Layout | str | None = None,
    *,
    agent_view_size: int | None = None,
    tile_size: int = 32,
    batch_size: int = 32,
) -> np.ndarray:
    """Render stacked states (one leading axis) to a numpy uint8[T, H*tile, W*tile, 3] array.

    Frames are drawn ``batch_size`` at a time (``lax.map``) to bound memory on long episodes.
    """
    if states.grid.ndim != 4:
        raise ValueError(
            f"render_frames expects states with one leading (time) axis, got grid shape {tuple(states.grid.shape)}"
        )
    _check_options(agent_view_size, tile_size, DEFAULT_SUBDIVS)
    if not _whole(batch_size, 1):
        raise ValueError(f"batch_size must be a positive integer (frames drawn at once), got {batch_size!r}")
    layout = None if layout_or_none is None else get_layout(layout_or_none)
    _check_grid_fits(states.grid, layout)
    return np.asarray(_render_many(states, layout, agent_view_size, int(tile_size), int(batch_size)))


@functools.partial(jax.jit, static_argnames=("layout", "agent_view_size", "tile_size", "batch_size"))
def _render_many(states, layout, agent_view_size, tile_size, batch_size):
    draw = functools.partial(render, layout_or_none=layout, agent_view_size=agent_view_size, tile_size=tile_size)
    return jax.lax.map(draw, states, batch_size=batch_size)


def make_renderer(
    env, tile_size: int = 32, *, agent_view_size: int | None | str = "env"
) -> Callable[[State], jax.Array]:
    """A ``state -> image`` for ``env`` (an ``ocv2.make`` environment), jitted inside.

    The view window is the env's ``config.view_radius`` unless ``agent_view_size`` is given (None
    switches it off). States with leading batch/time axes are rendered frame by frame (vmapped),
    giving ``[..., H*tile, W*tile, 3]``.
    """
    view = env.config.view_radius if agent_view_size == "env" else agent_view_size
    _check_options(view, tile_size, DEFAULT_SUBDIVS)
    layout = env.layout
    draw = functools.partial(render, layout_or_none=layout, agent_view_size=view, tile_size=int(tile_size))

    @jax.jit
    def draw_all(state: State) -> jax.Array:
        fn = draw
        for _ in range(state.grid.ndim - 3):
            fn = jax.vmap(fn)
        return fn(state)

    def renderer(state: State) -> jax.Array:
        _check_grid_fits(state.grid, layout)  # before jit, where a concrete grid can still be compared
        return draw_all(state)

    return renderer


# ---------------------------------------------------------------------------------------------------
# Episodes
# ---------------------------------------------------------------------------------------------------


def rollout_states(env, key: jax.Array, steps: int, policy: Callable | None = None) -> State:
    """Play ``steps`` transitions from a reset and return the ``steps + 1`` states visited.

    The result is a ``State`` with a leading time axis: index 0 the reset state, index t the state
    after t transitions (auto-reset: after an episode ends the next one's first state follows).

    Args:
        env: an ``ocv2.make`` environment.
        key: a PRNG key (consumed).
        steps: number of transitions (>= 0).
        policy: ``policy(key, state) -> int32[N]`` actions; default uniformly random actions.
    """
    if not _whole(steps, 0):
        raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
    num_agents = env.num_agents

    def random_policy(k, _state):
        return jax.random.randint(k, (num_agents,), 0, it.NUM_ACTIONS, dtype=jnp.int32)

    act = random_policy if policy is None else policy

    @jax.jit
    def run(key):
        k_reset, k_run = jax.random.split(key)
        first = env.reset_state(k_reset)

        def body(state, k):
            k_act, k_step = jax.random.split(k)
            actions = jnp.asarray(act(k_act, state), dtype=jnp.int32)
            nxt = env.step_arrays(k_step, state, actions).state
            return nxt, nxt

        _, later = jax.lax.scan(body, first, jax.random.split(k_run, int(steps)))
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b], axis=0), first, later)

    return run(key)


# ---------------------------------------------------------------------------------------------------
# GIF
# ---------------------------------------------------------------------------------------------------

_GIF_MAX_COLOURS = 255  # one palette entry kept free for the duplicate-frame marker


def _limit_colours(frames: np.ndarray) -> np.ndarray:
    """Map all frames onto one shared palette of at most 255 colours (no dithering) when they use more.

    With <= 256 colours per frame Pillow's GIF writer keeps pixels exact, so the duplicate marker
    below survives, and a shared palette avoids colour flicker between frames.
    """
    packed = (frames[..., 0].astype(np.uint32) << 16) | (frames[..., 1].astype(np.uint32) << 8) | frames[..., 2]
    if np.unique(packed).size <= _GIF_MAX_COLOURS:
        return frames
    count, height, width, _ = frames.shape
    sheet = Image.fromarray(frames.reshape(count * height, width, 3))
    quantised = sheet.quantize(colors=_GIF_MAX_COLOURS, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    return np.asarray(quantised.convert("RGB")).reshape(frames.shape)


def _mark_repeats(frames: np.ndarray) -> np.ndarray:
    """Keep consecutive identical frames apart by flipping the lowest red bit of the top-left pixel.

    Pillow merges identical consecutive GIF frames (summing their durations), which would break
    "one GIF frame per state, each 1000/fps ms". The change is invisible.
    """
    out = frames
    copied = False
    for t in range(1, len(frames)):
        if np.array_equal(out[t], out[t - 1]):
            if not copied:
                out, copied = frames.copy(), True
            out[t, 0, 0, 0] ^= 1
    return out


def write_gif(frames, path, fps: float = 5, loop: bool = True) -> str:
    """Write RGB frames uint8[T, h, w, 3] to an animated GIF at ``path``; returns the path written.

    Each frame lasts 1000/fps ms (GIF stores delays in 10 ms units, so it is rounded down to one),
    and the animation loops forever (``loop=0``) unless ``loop=False`` (then it plays once). Every
    input frame becomes one GIF frame. The file is written to a temporary file in the same folder
    and moved into place, so a failed write leaves no partial file.

    Raises:
        ValueError: fps not a number in (0, 100] (a GIF cannot show frames shorter than 10 ms), or
            frames not a non-empty uint8-compatible [T, h, w, 3] array.
    """
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)) or not math.isfinite(fps):
        raise ValueError(f"fps must be a number of frames per second, got {fps!r}")
    if not 0 < fps <= 100:
        raise ValueError(f"fps must be > 0 and <= 100 (GIF frame delays have 10 ms resolution), got {fps}")
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or 0 in frames.shape:
        raise ValueError(
            f"frames must be a non-empty uint8 array of shape [T, height, width, 3], got shape {frames.shape}"
        )
    if frames.dtype != np.uint8:
        if not np.issubdtype(frames.dtype, np.integer) or frames.min() < 0 or frames.max() > 255:
            raise ValueError(f"frames must be uint8 RGB (integers 0..255), got dtype {frames.dtype}")
        frames = frames.astype(np.uint8)

    frames = _mark_repeats(_limit_colours(frames))
    path = os.fspath(path)
    options = {"duration": 1000.0 / float(fps)}
    if loop:
        options["loop"] = 0
    first, *rest = [Image.fromarray(frame) for frame in frames]
    if rest:
        options.update(save_all=True, append_images=rest)
    with atomic_path(path) as tmp:
        first.save(tmp, format="GIF", **options)
    return path
