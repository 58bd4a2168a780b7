"""The renderer (pure JAX images of states), episode roll-outs and GIF writing."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image, ImageSequence

import ocv2
from ocv2 import items as it
from ocv2.items import Action, Direction, Static
from ocv2.render import AGENT_COLORS, INGREDIENT_COLORS, make_renderer, render, render_frames, rollout_states, write_gif

TILE = 16
GREY = (100, 100, 100)


@pytest.fixture(scope="module")
def cramped():
    """cramped_room at its layout start (agents facing up, empty kitchen)."""
    env = ocv2.make("cramped_room")
    return env, env.reset_state(jax.random.PRNGKey(0))


def draw(state, **kw):
    kw.setdefault("tile_size", TILE)
    return np.asarray(render(state, **kw))


def pixel(img, row, col, fx=0.5, fy=0.5, tile=TILE):
    """RGB at fraction (fx, fy) of cell (row, col)."""
    return tuple(int(v) for v in img[int(row * tile + fy * tile), int(col * tile + fx * tile)])


def tile_of(img, row, col, tile=TILE):
    return img[row * tile : (row + 1) * tile, col * tile : (col + 1) * tile]


def changed_cells(a, b, tile=TILE):
    diff = (a != b).any(-1)
    h, w = diff.shape[0] // tile, diff.shape[1] // tile
    per_cell = diff.reshape(h, tile, w, tile).any(axis=(1, 3))
    return {tuple(int(v) for v in rc) for rc in np.argwhere(per_cell)}


def cells(layout, static):
    return [tuple(int(v) for v in rc) for rc in np.argwhere(layout.static_objects == static)]


# --------------------------------------------------------------------------------------- shapes


@pytest.mark.parametrize(
    "name,tile", [("cramped_room", 8), ("grounded_coord_ring", 12), ("long_room", 32), ("demo_cook_wide", 5)]
)
def test_shape_and_dtype(name, tile):
    env = ocv2.make(name)
    state = env.reset_state(jax.random.PRNGKey(1))
    img = render(state, tile_size=tile)
    assert img.shape == (env.height * tile, env.width * tile, 3)
    assert img.dtype == jnp.uint8


def test_bad_options_and_mismatched_layout(cramped):
    _, state = cramped
    with pytest.raises(ValueError, match="tile_size"):
        render(state, tile_size=0)
    with pytest.raises(ValueError, match="agent_view_size"):
        render(state, agent_view_size=-1)
    with pytest.raises(ValueError, match=r"agent_view_size must be None or an integer in \[0, 2\*\*31\)"):
        render(state, agent_view_size=2**31)  # would overflow the int32 comparison on the device
    with pytest.raises(ValueError, match="long_room"):
        render(state, "long_room")
    with pytest.raises(ValueError, match="jax.vmap"):
        render(jax.tree.map(lambda x: jnp.stack([x, x]), state))


def test_a_grid_of_another_kitchen_of_the_same_size_is_refused(cramped):
    """cramped_room_v2 has cramped_room's size: only the static layer tells them apart."""
    _, state = cramped
    frames = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    match = r"is not of layout 'cramped_room_v2': its static cell at row 1, column 4 is 10, the layout's is 11"
    with pytest.raises(ValueError, match=r"state grid " + match):
        render(state, "cramped_room_v2")
    with pytest.raises(ValueError, match=r"state grid frame 0 " + match):
        render_frames(frames, "cramped_room_v2", tile_size=8)
    with pytest.raises(ValueError, match=r"state grid frame 0 " + match):
        make_renderer(ocv2.make("cramped_room_v2"), tile_size=8)(frames)


@pytest.mark.parametrize("batch_size", [0, -1, 2.5, True])
def test_render_frames_needs_a_positive_integer_batch_size(cramped, batch_size):
    _, state = cramped
    frames = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    with pytest.raises(ValueError, match=r"batch_size must be a positive integer"):
        render_frames(frames, tile_size=8, batch_size=batch_size)


# --------------------------------------------------------------------------------------- look


def test_fixed_state_pixels(cramped):
    """Colours of the layout start; breaks if a wall, floor, goal, pot, pile or agent colour changes."""
    env, state = cramped
    img = draw(state)
    layout = env.layout
    wall = cells(layout, Static.WALL)[0]
    assert pixel(img, *wall) == GREY
    floor = next(
        rc
        for rc in cells(layout, Static.FLOOR)
        if rc not in set(zip(np.asarray(state.agents.y).tolist(), np.asarray(state.agents.x).tolist()))
    )
    assert pixel(img, *floor) == (0, 0, 0)
    assert pixel(img, *floor, fx=0.0, fy=0.0) == GREY  # grid line
    goal = cells(layout, Static.GOAL)[0]
    assert pixel(img, *goal) == (0, 255, 0)
    assert pixel(img, *goal, fx=0.02, fy=0.5) == GREY
    pot = cells(layout, Static.POT)[0]
    assert pixel(img, *pot, fy=0.6) == (25, 25, 25)
    pile = cells(layout, Static.INGREDIENT_PILE)[0]
    assert pixel(img, *pile, fx=0.5, fy=0.15) == tuple(INGREDIENT_COLORS[0].astype(int))  # yellow onions
    plates = cells(layout, Static.PLATE_PILE)[0]
    assert pixel(img, *plates, fx=0.3, fy=0.3) == (255, 255, 255)
    for index in range(env.num_agents):
        row, col = int(state.agents.y[index]), int(state.agents.x[index])
        assert pixel(img, row, col) == tuple(AGENT_COLORS[index].astype(int))
        # facing up: the tip is at the top centre, the bottom corners are floor
        assert pixel(img, row, col, fx=0.5, fy=0.3) == tuple(AGENT_COLORS[index].astype(int))
        assert pixel(img, row, col, fx=0.5, fy=0.95) == (0, 0, 0)
    assert AGENT_COLORS[:2].astype(int).tolist() == [[255, 0, 0], [0, 0, 255]]


def test_deterministic_and_entry_points_agree(cramped):
    env, state = cramped
    a, b = draw(state), draw(state)
    assert np.array_equal(a, b)
    jitted = jax.jit(render, static_argnames=("agent_view_size", "tile_size"))
    assert np.array_equal(np.asarray(jitted(state, tile_size=TILE)), a)
    assert np.array_equal(draw(state, layout_or_none="cramped_room"), a)
    assert np.array_equal(np.asarray(make_renderer(env, tile_size=TILE)(state)), a)


def test_agent_direction_and_held_item(cramped):
    _, state = cramped
    row, col = int(state.agents.y[0]), int(state.agents.x[0])
    red = tuple(AGENT_COLORS[0].astype(int))
    # two points near the triangle's base corners, per facing direction
    base = {
        Direction.UP: [(0.3, 0.8), (0.7, 0.8)],
        Direction.DOWN: [(0.3, 0.2), (0.7, 0.2)],
        Direction.RIGHT: [(0.2, 0.3), (0.2, 0.7)],
        Direction.LEFT: [(0.8, 0.3), (0.8, 0.7)],
    }
    for direction in base:
        turned = state.replace(agents=state.agents.replace(dir=state.agents.dir.at[0].set(int(direction))))
        img = draw(turned)
        for other, other_points in base.items():
            for fx, fy in other_points:
                assert (pixel(img, row, col, fx, fy) == red) == (other == direction), (direction, other)
    holding = state.replace(agents=state.agents.replace(inventory=state.agents.inventory.at[0].set(it.PLATE)))
    img = draw(holding)
    assert pixel(img, row, col, 0.75, 0.75) == (255, 255, 255)
    assert changed_cells(img, draw(state)) == {(row, col)}


def test_agent_move_changes_only_its_cells(cramped):
    env, state = cramped
    actions = jnp.array([Action.STAY] * env.num_agents).at[0].set(Action.DOWN)
    moved = jax.jit(env.step_arrays)(jax.random.PRNGKey(0), state, actions).state
    before, after = (int(state.agents.y[0]), int(state.agents.x[0])), (int(moved.agents.y[0]), int(moved.agents.x[0]))
    assert before != after
    assert changed_cells(draw(state), draw(moved)) == {before, after}


def test_items_pots_buttons_and_delivery_are_visible():
    env = ocv2.make("overcookedv2_demo")  # WWPWW / 0A A1 / L   R / WBWXW
    state = env.reset_state(jax.random.PRNGKey(0))
    base = draw(state)
    grid = state.grid

    # a raw ingredient (tomato = ingredient 1, dark green) on the top-left counter
    on_counter = draw(state.replace(grid=grid.at[0, 0, 1].set(it.ingredient_unit(1))))
    assert changed_cells(base, on_counter) == {(0, 0)}
    assert pixel(on_counter, 0, 0) == tuple(INGREDIENT_COLORS[1].astype(int))

    # pot: filling opens the lid, cooking draws a timer bar, progress moves the bar
    pot = (0, 2)
    two = it.ingredient_unit(0) + it.ingredient_unit(1)
    idle = draw(state.replace(grid=grid.at[pot + (1,)].set(two)))
    cooking = draw(state.replace(grid=grid.at[pot + (1,)].set(two).at[pot + (2,)].set(15)))
    later = draw(state.replace(grid=grid.at[pot + (1,)].set(two).at[pot + (2,)].set(5)))
    for img in (idle, cooking, later):
        assert changed_cells(base, img) == {pot}
    assert not np.array_equal(tile_of(idle, *pot), tile_of(cooking, *pot))
    bar = (cooking != later).any(-1)
    assert bar.any() and np.argwhere(bar)[:, 0].min() >= int(0.8 * TILE)  # only the bar moved
    r, g, b = pixel(later, *pot, fx=0.5, fy=0.855)
    assert g > 150 and r < 50 and b < 50  # green bar (anti-aliased: under one pixel high at 16 px)
    assert pixel(idle, *pot, fx=0.5, fy=0.855) == (25, 25, 25)

    # button: red when idle; while active it shows the order and a bar instead
    button = (2, 0)
    assert pixel(base, *button) == (255, 0, 0)
    active = draw(state.replace(grid=grid.at[button + (2,)].set(4)))
    assert changed_cells(base, active) == {button}
    assert pixel(active, *button) != (255, 0, 0)

    # a correct delivery highlights the delivery cell(s) only
    delivered = draw(state.replace(new_correct_delivery=jnp.array(True)))
    assert changed_cells(base, delivered) == set(cells(env.layout, Static.GOAL))

    # the recipe indicator shows the current order
    other_recipe = state.replace(recipe=jnp.int32(it.recipe_encoding_np([1, 1, 1])))
    assert changed_cells(base, draw(other_recipe)) == {(2, 4)}  # the R cell


def test_view_window_highlight(cramped):
    env, state = cramped
    plain = draw(state)
    seen = draw(state, agent_view_size=1)
    brighter = seen.astype(int) - plain.astype(int)
    assert (brighter >= 0).all() and brighter.any()
    # radius 1 around both agents covers every cell of the 4x5 kitchen except the outer columns' far rows
    ys, xs = np.asarray(state.agents.y), np.asarray(state.agents.x)
    for row in range(env.height):
        for col in range(env.width):
            inside = any(abs(row - y) <= 1 and abs(col - x) <= 1 for y, x in zip(ys, xs))
            differs = not np.array_equal(tile_of(plain, row, col), tile_of(seen, row, col))
            assert differs == inside, (row, col)
    floor = (int(ys[0]) + 1, int(xs[0]))
    assert env.layout.static_objects[floor] == Static.FLOOR
    assert 70 <= pixel(seen, *floor)[0] <= 80  # black blended 30 % toward white
    # make_renderer takes the env's view radius
    viewing = ocv2.make("cramped_room", agent_view_size=1)
    assert np.array_equal(np.asarray(make_renderer(viewing, tile_size=TILE)(state)), seen)


# --------------------------------------------------------------------------------------- episodes


def test_rollout_and_vmap_over_time():
    env = ocv2.make("cramped_room_v2")
    states = rollout_states(env, jax.random.PRNGKey(2), 6)
    assert states.grid.shape[0] == 7 and states.agents.x.shape == (7, env.num_agents)
    assert np.asarray(states.step).tolist() == list(range(7))
    frames = jax.vmap(lambda s: render(s, tile_size=8))(states)
    assert frames.shape == (7, env.height * 8, env.width * 8, 3) and frames.dtype == jnp.uint8
    one_by_one = np.stack([np.asarray(render(jax.tree.map(lambda x: x[t], states), tile_size=8)) for t in (0, 6)])
    assert np.array_equal(np.asarray(frames)[[0, 6]], one_by_one)
    assert np.array_equal(render_frames(states, tile_size=8, batch_size=4), np.asarray(frames))
    assert np.array_equal(np.asarray(make_renderer(env, tile_size=8)(states)), np.asarray(frames))
    # a batch x time stack renders too
    batched = jax.tree.map(lambda x: jnp.stack([x, x]), states)
    assert make_renderer(env, tile_size=8)(batched).shape == (2,) + frames.shape


def test_rollout_with_policy():
    env = ocv2.make("cramped_room")
    states = rollout_states(
        env, jax.random.PRNGKey(0), 4, policy=lambda key, state: jnp.full((env.num_agents,), Action.STAY)
    )
    assert (np.asarray(states.agents.x) == np.asarray(states.agents.x)[0]).all()
    with pytest.raises(ValueError, match="steps"):
        rollout_states(env, jax.random.PRNGKey(0), -1)


# --------------------------------------------------------------------------------------- GIF


def _frames(count=4, size=(12, 20), seed=0):
    rng = np.random.default_rng(seed)
    palette = rng.integers(0, 256, (6, 3), dtype=np.uint8)
    return palette[rng.integers(0, 6, (count,) + size)]


def read_gif(path) -> np.ndarray:
    """Every frame of a GIF as RGB uint8[T, h, w, 3]."""
    with Image.open(path) as im:
        return np.stack([np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(im)])


def _durations(path):
    with Image.open(path) as im:
        out = []
        for index in range(im.n_frames):
            im.seek(index)
            out.append(im.info["duration"])
        return im.n_frames, out


@pytest.mark.parametrize("fps", [5, 4, 10])
def test_gif_duration_loop_and_frames(tmp_path, fps):
    frames = _frames()
    path = tmp_path / "ep.gif"
    assert write_gif(frames, path, fps=fps) == str(path)
    back = read_gif(path)
    assert back.shape[:3] == frames.shape[:3]
    assert np.array_equal(back[..., :3], frames)
    with Image.open(path) as im:
        assert im.info["loop"] == 0
    count, durations = _durations(path)
    assert count == 4 and durations == [1000 / fps] * 4
    assert os.listdir(tmp_path) == ["ep.gif"]  # no temporary left behind


def test_gif_keeps_repeated_and_many_colour_frames(tmp_path):
    frames = _frames(3)
    frames = np.stack([frames[0], frames[0], frames[0], frames[1], frames[1]])  # Pillow would merge these
    write_gif(frames, tmp_path / "rep.gif", fps=5)
    assert _durations(tmp_path / "rep.gif") == (5, [200] * 5)
    noise = np.random.default_rng(1).integers(0, 256, (3, 16, 16, 3), dtype=np.uint8)
    noise[1] = noise[0]
    write_gif(noise, tmp_path / "noise.gif", fps=5)
    assert read_gif(tmp_path / "noise.gif").shape[0] == 3


def test_gif_play_once_and_overwrite(tmp_path):
    path = tmp_path / "once.gif"
    path.write_bytes(b"old")
    write_gif(_frames(2), path, fps=2, loop=False)
    with Image.open(path) as im:
        assert im.n_frames == 2 and "loop" not in im.info


@pytest.mark.parametrize("fps", [0, -1, float("nan"), 101, "5", True])
def test_gif_bad_fps(tmp_path, fps):
    with pytest.raises(ValueError, match="fps"):
        write_gif(_frames(), tmp_path / "x.gif", fps=fps)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("shape", [(4, 12, 20), (4, 12, 20, 4), (0, 12, 20, 3)])
def test_gif_bad_frames(tmp_path, shape):
    with pytest.raises(ValueError, match="frames"):
        write_gif(np.zeros(shape, np.uint8), tmp_path / "x.gif")
    assert os.listdir(tmp_path) == []


def test_gif_failed_write_leaves_nothing(tmp_path, monkeypatch):
    def broken(image, path, *args, **kwargs):
        with open(path, "wb") as f:
            f.write(b"GIF89a partial")
        raise OSError("disk full")

    monkeypatch.setattr(Image.Image, "save", broken)
    (tmp_path / "keep.gif").write_bytes(b"previous")
    with pytest.raises(OSError, match="disk full"):
        write_gif(_frames(), tmp_path / "keep.gif")
    assert os.listdir(tmp_path) == ["keep.gif"]
    assert (tmp_path / "keep.gif").read_bytes() == b"previous"
