"""The 2019 human-human Overcooked games (Carroll et al. 2019) as ocv2 episodes, and a rules check.

The ``overcooked-ai==1.1.0`` source distribution ships ``clean_train_trials.pickle`` and
``clean_test_trials.pickle``: pandas DataFrames with one row per game tick (``state``,
``joint_action``, ``next_state``, ``reward``, ``layout_name``, ``workerid_num``, ...). States are
the 2019 format: players' position/orientation/held object, objects on counters, soups as
``['onion', n, cook_ticks]``. This module turns each (layout, worker) game into ocv2 ``State``s plus
joint actions and recorded rewards, and steps ocv2's dynamics from every recorded state with the
recorded joint action to count how many transitions ocv2 reproduces exactly (``reproduce``).

Only reading the pickles needs pandas (the ``[human]`` extra); everything else takes plain row dicts
(``rows_from_frame`` / a JSON fixture), so tests run without the sdist.

Every read is bounded: SOURCE must be a regular file (or a folder of them), a pickle is read in chunks and
refused past ``MAX_PICKLE_BYTES``, an archive past ``MAX_ARCHIVE_MEMBERS`` entries or a member past
``MAX_PICKLE_BYTES`` (``/dev/zero`` or a small archive of a huge zero file would otherwise fill memory).

Unpickling runs whatever callables a pickle names, so a pickle from anywhere but the known sdist
could run code. ``read_frame`` therefore never calls ``pickle.load``/``pd.read_pickle``: its
``TableUnpickler`` admits only the pandas/numpy constructors a data table needs (``PICKLE_CLASSES``)
and refuses any other name before it is imported. The known files' SHA-256s are checked as well;
other bytes are read (with the same restrictions) after a warning.
"""

from __future__ import annotations

import ast
import collections
import hashlib
import importlib
import io
import os
import pickle
import stat
import tarfile
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ocv2 import items as it
from ocv2.config import EnvConfig, build_config
from ocv2.dynamics import transition
from ocv2.items import Action, Direction, Static
from ocv2.layouts import Layout, get_layout
from ocv2.state import Agents, State

#: overcooked-ai layout name -> the ocv2 layout with the same kitchen.
LAYOUT_MAP = {
    "cramped_room": "cramped_room",
    "asymmetric_advantages": "asymm_advantages",
    "coordination_ring": "coord_ring",
    "random0": "forced_coord",
    "random3": "counter_circuit",
}
SPLITS = ("train", "test")
PICKLE_NAMES = {"train": "clean_train_trials.pickle", "test": "clean_test_trials.pickle"}
SDIST_NAME = "overcooked_ai-1.1.0.tar.gz"
#: SHA-256 of the PyPI source distribution (the hash pip checks when it downloads it) and of its two pickles.
SDIST_SHA256 = "478bf319274bdb6c5bede8048ee901d088912353111ab85e9fb2bf389c6ccddf"
PICKLE_SHA256 = {
    "train": "28659cfd09ee033d82b56bed905b239f078877e1b09d1f1b916e4bc0480ca4fa",
    "test": "59979552a053f1efe762de976f37dd83e269d70d19b67613c61e856c86705666",
}
CACHE_ENV = "OCV2_CACHE"

#: Bounds on what a SOURCE can make ocv2 read. The 2019 data as PyPI serves it: the sdist is 2,344,591 bytes,
#: 102 entries, its pickles 27,549,202 (test) and 27,723,418 (train) bytes decompressed. A pickle (alone or
#: an archive member) above 9x the larger one, any archive member that large, or more entries than 100x
#: the sdist's is not the human data: refused before it is read, or as soon as the read passes the cap.
MAX_PICKLE_BYTES = 256 << 20
MAX_ARCHIVE_MEMBERS = 10_000
#: An archive's file (the sdist, or the same tar uncompressed, about 60 MB) is hashed in chunks up to this size.
MAX_ARCHIVE_BYTES = 1 << 30
_CHUNK = 1 << 20

#: The 2019 game paid 5 points per soup; ocv2 (like overcooked-ai's MDP) pays DELIVERY_REWARD = 20.
RECORDED_SOUP_REWARD = 5.0
REWARD_SCALE = it.DELIVERY_REWARD / RECORDED_SOUP_REWARD
#: Ticks a full pot cooks in the 2019 game (its cook counter runs on past it; the soup is ready at >= 20).
RECORDED_COOK_TIME = 20

# 2019 layout characters -> ocv2's ('1'/'2' mark player starts on floor).
_CHAR_MAP = {"X": "W", "S": "X", "D": "B", "O": "0", "P": "P", " ": " ", "1": "A", "2": "A"}
_ORIENTATION = {(0, -1): Direction.UP, (0, 1): Direction.DOWN, (1, 0): Direction.RIGHT, (-1, 0): Direction.LEFT}
_MOVE = {(0, -1): Action.UP, (0, 1): Action.DOWN, (1, 0): Action.RIGHT, (-1, 0): Action.LEFT, (0, 0): Action.STAY}
ONION = it.ingredient_unit(0)
ONION_SOUP_DISH = 3 * ONION | it.PLATE | it.COOKED
#: Row keys the converter reads (a fixture keeps only these).
ROW_KEYS = ("layout_name", "layout", "workerid_num", "cur_gameloop", "state", "joint_action", "reward")


class HumanDataError(ValueError):
    """The human data cannot be read or converted; the message names the file / row / field."""


class HumanDataWarning(UserWarning):
    """The human data is not the known overcooked-ai 1.1.0 file (read anyway, with the restricted unpickler)."""


class Trial(NamedTuple):
    """One recorded game: T transitions on one ocv2 layout (arrays are numpy)."""

    layout: str  # ocv2 layout name
    source_layout: str  # overcooked-ai name
    worker: int  # workerid_num: which recorded session (one game per layout)
    split: str  # train | test
    states: State  # [T + 1] s_0 .. s_T (s_T is the last row's next_state)
    actions: np.ndarray  # int32[T, 2] ocv2 action indices
    rewards: np.ndarray  # float32[T] recorded reward x REWARD_SCALE (ocv2's 20 per soup)


# ---------------------------------------------------------------------------------------------------
# Reading the pickles
# ---------------------------------------------------------------------------------------------------

#: (module, name) a human-data pickle may name -> (module, name) actually imported. The first block is
#: what overcooked-ai 1.1.0's pickles name (pandas 1.x / numpy 1.x spellings, mapped to today's places
#: as pandas' own compatibility table does); the second what today's pandas writes for a table of
#: strings and numbers (a re-saved or sliced copy). All build arrays, indexes and frames from data;
#: none calls anything a pickle chooses.
PICKLE_CLASSES = {
    ("numpy", "dtype"): ("numpy", "dtype"),
    ("numpy", "ndarray"): ("numpy", "ndarray"),
    ("numpy.core.multiarray", "_reconstruct"): ("numpy._core.multiarray", "_reconstruct"),
    ("pandas.core.frame", "DataFrame"): ("pandas", "DataFrame"),
    ("pandas.core.indexes.base", "Index"): ("pandas", "Index"),
    ("pandas.core.indexes.base", "_new_Index"): ("pandas.core.indexes.base", "_new_Index"),
    ("pandas.core.indexes.numeric", "Int64Index"): ("pandas", "Index"),
    ("pandas.core.internals.managers", "BlockManager"): ("pandas.core.internals.managers", "BlockManager"),
    ("builtins", "slice"): ("builtins", "slice"),
    ("numpy._core.multiarray", "_reconstruct"): ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.numeric", "_frombuffer"): ("numpy._core.numeric", "_frombuffer"),
    ("pandas", "DataFrame"): ("pandas", "DataFrame"),
    ("pandas", "Index"): ("pandas", "Index"),
    ("pandas", "RangeIndex"): ("pandas", "RangeIndex"),
    ("pandas", "StringDtype"): ("pandas", "StringDtype"),
    ("pandas.arrays", "StringArray"): ("pandas.arrays", "StringArray"),
    ("pandas._libs.arrays", "__pyx_unpickle_NDArrayBacked"): ("pandas._libs.arrays", "__pyx_unpickle_NDArrayBacked"),
    ("pandas._libs.internals", "_unpickle_block"): ("pandas._libs.internals", "_unpickle_block"),
}


class TableUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the names in ``PICKLE_CLASSES``: any other global (``os.system``,
    ``builtins.eval``, a class with a malicious ``__reduce__``) is refused before its module is imported."""

    def find_class(self, module: str, name: str):
        target = PICKLE_CLASSES.get((module, name))
        if target is None:
            raise pickle.UnpicklingError(
                f"refused to load {module}.{name}: the human data holds only pandas/numpy tables"
            )
        return getattr(importlib.import_module(target[0]), target[1])

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("refused a persistent reference: the human data holds only pandas/numpy tables")


def _warn(message: str) -> None:
    warnings.warn(message, HumanDataWarning, stacklevel=3)


def read_frame(source: str | os.PathLike, split: str, warn: Callable[[str], None] | None = None):
    """The DataFrame of one split from ``source``: the sdist ``.tar.gz``, a folder holding the pickle
    (the unpacked sdist or its ``human_data`` folder), or the ``.pickle`` file itself.

    The pickle is read by ``TableUnpickler`` (it cannot run code). Bytes other than the known sdist's
    (``SDIST_SHA256``) or pickle's (``PICKLE_SHA256``) are read after ``warn(message)`` (default: a
    ``HumanDataWarning``).

    Raises:
        HumanDataError: unknown split, missing file, pandas missing, unreadable pickle, a pickle that
            names anything but a data table's classes, or one that holds no DataFrame.
    """
    if split not in SPLITS:
        raise HumanDataError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    warn = warn or _warn
    path = Path(source)
    name = PICKLE_NAMES[split]
    if not path.exists():
        raise HumanDataError(f"{path}: no such file or folder (expected {SDIST_NAME}, a folder with {name}, or {name})")
    try:
        import pandas as pd  # optional dependency: the [human] extra
    except ImportError:
        raise HumanDataError("reading the human data needs pandas: pip install 'ocv2[human]'") from None
    where = path
    try:
        if path.is_dir():
            found = sorted(path.rglob(name))
            if not found:
                raise HumanDataError(f"{path}: no {name} below this folder")
            where = found[0]
            data = _read_file(where, MAX_PICKLE_BYTES, PICKLE_SHA256[split], f"overcooked-ai 1.1.0's {name}", warn)
        elif path.name.endswith((".tar.gz", ".tgz", ".tar")):
            _read_file(path, MAX_ARCHIVE_BYTES, SDIST_SHA256, SDIST_NAME, warn, keep=False)
            where, data = _read_member(path, name)
        else:
            data = _read_file(path, MAX_PICKLE_BYTES, PICKLE_SHA256[split], f"overcooked-ai 1.1.0's {name}", warn)
        frame = TableUnpickler(data).load()
    except HumanDataError:
        raise
    except Exception as error:  # pickle/tar/pandas errors: one line naming the file
        raise HumanDataError(f"{where}: cannot read the {split} trials: {type(error).__name__}: {error}") from None
    if not isinstance(frame, pd.DataFrame):
        raise HumanDataError(f"{where}: holds a {type(frame).__name__}, not the pandas DataFrame of the {split} trials")
    return frame


def _size(count: int) -> str:
    return f"{count / 2**20:,.0f} MiB" if count >= 2**20 else f"{count:,} bytes"


def _too_big(where, cap: int, what: str) -> HumanDataError:
    return HumanDataError(
        f"{where}: {what} is larger than {_size(cap)}, more than ocv2 reads from the human data (the 2019 pickles "
        "are 27.5 and 27.7 MB, the sdist 2.3 MB; docs/human.md); not the overcooked-ai 1.1.0 trials"
    )


def _read_file(
    path: Path, cap: int, expected: str, what: str, warn: Callable[[str], None], keep: bool = True
) -> io.BytesIO | None:
    """A regular file read in chunks (refused past ``cap`` bytes) and checked against its known sha256;
    its bytes (``keep``) as a stream to unpickle from. A device (``/dev/zero``), pipe or socket is refused
    before it is opened."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise HumanDataError(
                f"{path}: not a regular file (a device, pipe or socket); give {SDIST_NAME}, a folder holding the "
                "trials' pickles, or one pickle"
            )
        with open(path, "rb") as handle:
            if os.fstat(handle.fileno()).st_size > cap:  # refused before a byte is read
                raise _too_big(path, cap, "the file")
            digest, data = _read_capped(handle, path, cap, "the file", keep)
    except OSError as error:
        raise HumanDataError(f"{path}: cannot read: {error.strerror or error}") from None
    if digest != expected:
        warn(
            f"{path}: not {what} (sha256 {digest[:16]}..., expected {expected[:16]}...); reading it anyway, "
            "with an unpickler that only builds pandas/numpy tables"
        )
    return data


def _read_capped(handle, where, cap: int, what: str, keep: bool = True) -> tuple[str, io.BytesIO | None]:
    """(sha256, the bytes or None) of ``handle`` read in chunks; a HumanDataError once more than ``cap``."""
    digest, data, total = hashlib.sha256(), io.BytesIO() if keep else None, 0
    while chunk := handle.read(_CHUNK):
        total += len(chunk)
        if total > cap:
            raise _too_big(where, cap, what)
        digest.update(chunk)
        if data is not None:
            data.write(chunk)
    if data is not None:
        data.seek(0)
    return digest.hexdigest(), data


def _read_member(path: Path, name: str) -> tuple[str, io.BytesIO]:
    """(where, bytes) of the archive member ending in ``/name``, read entry by entry: every entry's size is
    checked against ``MAX_PICKLE_BYTES`` from its header before its data is decompressed, and at most
    ``MAX_ARCHIVE_MEMBERS`` entries are read."""
    with tarfile.open(path) as tar:
        for count, member in enumerate(tar, start=1):
            if count > MAX_ARCHIVE_MEMBERS:
                raise HumanDataError(
                    f"{path}: holds more than {MAX_ARCHIVE_MEMBERS:,} entries (the sdist has 102) before {name}; "
                    "not the overcooked-ai 1.1.0 sdist"
                )
            if member.size > MAX_PICKLE_BYTES:
                raise _too_big(f"{path}:{member.name}", MAX_PICKLE_BYTES, f"an entry of {_size(member.size)}")
            if member.isfile() and member.name.endswith("/" + name):
                where = f"{path}:{member.name}"
                return where, _read_capped(tar.extractfile(member), where, MAX_PICKLE_BYTES, "the entry")[1]
    raise HumanDataError(f"{path}: the archive holds no {name}")


def rows_from_frame(frame, where: str = "the human data") -> list[dict]:
    """The DataFrame's rows as dicts of the ``ROW_KEYS`` (what ``trials_from_rows`` takes); ``where`` names the
    table in an error."""
    missing = [k for k in ROW_KEYS if k not in frame.columns]
    if missing:
        raise HumanDataError(f"{where} lacks column(s) {missing}; expected the overcooked-ai 1.1.0 trials")
    extra = ["next_state"] if "next_state" in frame.columns else []  # optional: the last row's state ends a game
    return frame[list(ROW_KEYS) + extra].to_dict("records")


# ---------------------------------------------------------------------------------------------------
# Converting rows
# ---------------------------------------------------------------------------------------------------


def check_layout(source_layout: str, grid_text: str) -> Layout:
    """The ocv2 layout of a 2019 layout name, checked cell by cell against the recorded map."""
    if source_layout not in LAYOUT_MAP:
        raise HumanDataError(f"layout {source_layout!r} has no ocv2 counterpart; known: {', '.join(LAYOUT_MAP)}")
    layout = get_layout(LAYOUT_MAP[source_layout])
    rows = _parse(grid_text, f"layout {source_layout!r}: the recorded map")
    if not isinstance(rows, list | tuple) or not all(isinstance(row, str | list | tuple) for row in rows):
        raise HumanDataError(f"layout {source_layout!r}: the recorded map {grid_text!r} is not a list of rows")
    try:
        mapped = Layout.from_string(
            "\n".join("".join(_CHAR_MAP[c] for c in row) for row in rows),
            possible_recipes=[[0, 0, 0]],
            name=source_layout,
        )
        same = mapped.static_objects.shape == layout.static_objects.shape and bool(
            (mapped.static_objects == layout.static_objects).all()
        )
    except (KeyError, ValueError):
        same = False
    if not same:
        raise HumanDataError(
            f"layout {source_layout!r}: the recorded map {rows} is not ocv2's {layout.name!r} "
            f"kitchen {layout.to_string().splitlines()}"
        )
    return layout


def action_index(action) -> int:
    """An overcooked-ai action ((dx, dy) or 'INTERACT') as an ocv2 ``Action`` index."""
    if isinstance(action, str):
        if action.upper() == "INTERACT":
            return int(Action.INTERACT)
        raise HumanDataError(f"unknown action {action!r}")
    key = tuple(int(v) for v in action)
    if key not in _MOVE:
        raise HumanDataError(f"unknown action {action!r}")
    return int(_MOVE[key])


def _held_item(obj: dict | None, where: str) -> int:
    if not obj:
        return it.EMPTY
    name = obj.get("name")
    if name == "onion":
        return ONION
    if name == "dish":
        return it.PLATE
    if name == "soup":
        kind, count, _ticks = obj["state"]
        if kind != "onion" or count != 3:
            raise HumanDataError(f"{where}: a plated soup {obj['state']} is not a 3-onion soup")
        return ONION_SOUP_DISH
    raise HumanDataError(f"{where}: unknown object {name!r}")


def state_from_record(layout: Layout, record: dict, step: int = 0, delivered: bool = False) -> State:
    """One 2019 state dict as an ocv2 ``State`` (numpy leaves) on ``layout``.

    Pots: ``['onion', n, ticks]`` -> n onions; a full pot cooking for ``ticks`` ticks has
    ``RECORDED_COOK_TIME - ticks`` left (ocv2 counts down), and is cooked from ``ticks >= 20`` on.
    """
    static = np.asarray(layout.static_objects, np.int32)
    items = np.zeros_like(static)
    timers = np.zeros_like(static)
    players = record["players"]
    if len(players) != layout.num_agents:
        raise HumanDataError(f"step {step}: {len(players)} players on {layout.name!r}")
    xs, ys, dirs, inventory = [], [], [], []
    for a, player in enumerate(players):
        x, y = (int(v) for v in player["position"])
        orientation = tuple(int(v) for v in player["orientation"])
        if orientation not in _ORIENTATION:
            raise HumanDataError(f"step {step}: player {a} has orientation {orientation}")
        xs.append(x)
        ys.append(y)
        dirs.append(int(_ORIENTATION[orientation]))
        inventory.append(_held_item(player.get("held_object"), f"step {step}, player {a}"))
    for obj in record["objects"].values():
        x, y = (int(v) for v in obj["position"])
        where = f"step {step}, object at (x={x}, y={y})"
        if static[y, x] == Static.POT:
            if obj["name"] != "soup":
                raise HumanDataError(f"{where}: a {obj['name']!r} in a pot")
            kind, count, ticks = obj["state"]
            if kind != "onion" or not 1 <= count <= it.MAX_INGREDIENTS_IN_POT:
                raise HumanDataError(f"{where}: pot contents {obj['state']} are not 1-3 onions")
            items[y, x] = count * ONION
            if count == it.MAX_INGREDIENTS_IN_POT and ticks >= RECORDED_COOK_TIME:
                items[y, x] |= it.COOKED
            elif count == it.MAX_INGREDIENTS_IN_POT:
                timers[y, x] = RECORDED_COOK_TIME - ticks
        elif static[y, x] == Static.WALL:
            items[y, x] = _held_item(obj, where)
        else:
            raise HumanDataError(f"{where}: an object on a cell that is neither counter nor pot")
    return State(
        agents=Agents(
            x=np.asarray(xs, np.int32),
            y=np.asarray(ys, np.int32),
            dir=np.asarray(dirs, np.int32),
            inventory=np.asarray(inventory, np.int32),
        ),
        grid=np.stack([static, items, timers], axis=-1),
        recipe=np.asarray(it.recipe_encoding_np([0, 0, 0]), np.int32),
        step=np.asarray(step, np.int32),
        done=np.asarray(False),
        new_correct_delivery=np.asarray(bool(delivered)),
        ingredient_permutations=np.zeros((layout.num_agents, layout.num_ingredients), np.int32),
    )


def _parse(text, what: str):
    if not isinstance(text, str):
        return text
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        raise HumanDataError(f"{what}: not a Python literal: {text[:80]!r}") from None


def trials_from_rows(
    rows: Iterable[dict], split: str = "train", layouts: Sequence[str] | None = None, max_trials: int | None = None
) -> list[Trial]:
    """Group rows by (layout, worker) in first-appearance order, sort each game by ``cur_gameloop``
    and convert it. ``layouts`` filters by ocv2 or overcooked-ai layout name; ``max_trials`` keeps the
    first games only (per call, after filtering)."""
    wanted = None
    if layouts is not None:
        reverse = {v: k for k, v in LAYOUT_MAP.items()}
        wanted = set()
        for name in layouts:
            if name not in LAYOUT_MAP and name not in reverse:
                raise HumanDataError(f"layout {name!r} has no human data; choose from {', '.join(LAYOUT_MAP.values())}")
            wanted.add(reverse.get(name, name))
    games: dict = collections.OrderedDict()
    for row in rows:
        if wanted is not None and row["layout_name"] not in wanted:
            continue
        games.setdefault((row["layout_name"], int(row["workerid_num"])), []).append(row)
    trials = []
    for (source_layout, worker), game in games.items():
        if max_trials is not None and len(trials) >= max_trials:
            break
        trials.append(_trial(source_layout, worker, split, sorted(game, key=lambda r: r["cur_gameloop"])))
    return trials


def _trial(source_layout: str, worker: int, split: str, rows: list[dict]) -> Trial:
    where = f"{split} trial {source_layout}/worker {worker}"
    layout = check_layout(source_layout, rows[0]["layout"])
    states, actions, rewards = [], [], []
    delivered = False
    for t, row in enumerate(rows):
        record = _parse(row["state"], f"{where}, row {t} state")
        try:
            states.append(state_from_record(layout, record, t, delivered))
            joint = _parse(row["joint_action"], f"{where}, row {t} joint_action")
            actions.append([action_index(a) for a in joint])
        except KeyError as error:
            raise HumanDataError(f"{where}, row {t}: the state has no key {error}") from None
        except (TypeError, ValueError) as error:  # HumanDataError is a ValueError
            raise HumanDataError(f"{where}, row {t}: {error}") from None
        reward = float(row["reward"]) * REWARD_SCALE
        rewards.append(reward)
        delivered = reward > 0
    last = rows[-1].get("next_state")
    if last is None:  # a fixture may omit it: the last row's state ends the game
        actions, rewards = actions[:-1], rewards[:-1]
    else:
        states.append(state_from_record(layout, _parse(last, f"{where}, last next_state"), len(rows), delivered))
    if not actions:
        raise HumanDataError(f"{where}: needs at least two rows")
    states[-1] = states[-1].replace(done=np.asarray(True))  # the game ended here, as ocv2's max_steps would
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *states)
    return Trial(
        layout.name,
        source_layout,
        worker,
        split,
        stacked,
        np.asarray(actions, np.int32),
        np.asarray(rewards, np.float32),
    )


def proxy_path(layout: str) -> Path:
    """Default file of the BC human proxy for ``layout`` (``ocv2 human proxy`` writes it, ``ocv2 xp
    --cols human-proxy:LAYOUT`` reads it): ``$OCV2_CACHE/human_proxy/LAYOUT.ocv2policy``, where
    ``OCV2_CACHE`` defaults to ``$XDG_CACHE_HOME/ocv2``, else ``~/.cache/ocv2``."""
    name = get_layout(layout).name
    if name not in LAYOUT_MAP.values():
        raise HumanDataError(f"layout {name!r} has no human data; choose one of {', '.join(LAYOUT_MAP.values())}")
    base = os.environ.get(CACHE_ENV)
    if not base:
        base = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(Path.home(), ".cache"), "ocv2")
    return Path(base) / "human_proxy" / f"{name}.ocv2policy"


def human_env_config(layout: str | Layout, max_steps: int) -> EnvConfig:
    """The ocv2 rules the 2019 games ran under: auto-start cooking, no negative rewards, one recipe."""
    return build_config(layout, max_steps=max_steps)


# ---------------------------------------------------------------------------------------------------
# Reproduction check
# ---------------------------------------------------------------------------------------------------

#: Mismatch classes, in the order they are reported (a transition can fall into several).
FIELDS = ("position", "orientation", "held", "counter", "pot", "reward")


class Reproduction(NamedTuple):
    """How many of a set of recorded transitions ocv2's dynamics reproduce exactly."""

    transitions: int
    exact: int
    by_field: dict  # field -> transitions whose next state differs in that field
    by_class: dict  # mismatch class (``mismatch_class``) -> transitions
    examples: dict  # class -> up to 3 (trial, t) locations


def _stepper(layout_name: str):
    config = human_env_config(layout_name, 1_000_000)

    @jax.jit
    def step(states, actions):
        out = jax.vmap(lambda s, a: transition(config, jax.random.PRNGKey(0), s, a))(states, actions)
        return out.state, out.reward, out.shaped_reward

    return step


_STEPPERS: dict = {}


def step_recorded(trial: Trial):
    """ocv2's next states, rewards and shaped rewards [T] from every recorded state with the recorded
    joint action (the recipe key is irrelevant: one recipe, no resampling)."""
    if trial.layout not in _STEPPERS:
        _STEPPERS[trial.layout] = _stepper(trial.layout)
    before = jax.tree.map(lambda x: x[:-1], trial.states)
    states, rewards, shaped = _STEPPERS[trial.layout](before, jnp.asarray(trial.actions))
    return jax.tree.map(np.asarray, states), np.asarray(rewards), np.asarray(shaped)


def field_mismatches(layout: Layout, predicted: State, recorded: State, predicted_reward, recorded_reward) -> dict:
    """bool[T] per field of ``FIELDS``: where ocv2's next state differs from the recorded one."""
    static = np.asarray(layout.static_objects)
    counters = static == Static.WALL
    pots = static == Static.POT
    p, r = predicted, recorded
    grid_diff = p.grid != r.grid
    return {
        "position": ((p.agents.x != r.agents.x) | (p.agents.y != r.agents.y)).any(-1),
        "orientation": (p.agents.dir != r.agents.dir).any(-1),
        "held": (p.agents.inventory != r.agents.inventory).any(-1),
        "counter": (grid_diff[..., 1] & counters).any((-1, -2)),
        "pot": ((grid_diff[..., 1] | grid_diff[..., 2]) & pots).any((-1, -2)),
        "reward": np.asarray(predicted_reward) != np.asarray(recorded_reward),
    }


def mismatch_class(fields: Sequence[str]) -> str:
    """A mismatching transition's class: the fields that differ, in ``FIELDS`` order."""
    return "+".join(f for f in FIELDS if f in fields)


def reproduce(trials: Sequence[Trial], max_examples: int = 3) -> Reproduction:
    """Step ocv2 from every recorded state of ``trials`` and compare with the next recorded state."""
    total = exact = 0
    by_field = collections.Counter()
    by_class = collections.Counter()
    examples: dict = collections.defaultdict(list)
    for trial in trials:
        predicted, rewards, _ = step_recorded(trial)
        recorded = jax.tree.map(lambda x: x[1:], trial.states)
        diff = field_mismatches(get_layout(trial.layout), predicted, recorded, rewards, trial.rewards)
        bad = np.zeros(len(trial.actions), bool)
        for field, mask in diff.items():
            by_field[field] += int(mask.sum())
            bad |= mask
        total += len(bad)
        exact += int((~bad).sum())
        for t in np.nonzero(bad)[0]:
            label = mismatch_class([f for f in FIELDS if diff[f][t]])
            by_class[label] += 1
            if len(examples[label]) < max_examples:
                examples[label].append((f"{trial.split}:{trial.source_layout}/{trial.worker}", int(t)))
    return Reproduction(total, exact, dict(by_field), dict(by_class), dict(examples))


# ---------------------------------------------------------------------------------------------------
# Which rules the recordings exercise
# ---------------------------------------------------------------------------------------------------


def rule_events(trials: Sequence[Trial]) -> dict:
    """Count what happens in the recorded transitions (per agent and step), read off the recorded
    states: which parts of the rules an exact reproduction has actually checked."""
    counts = collections.Counter()
    for trial in trials:
        s = trial.states
        static = np.asarray(get_layout(trial.layout).static_objects)
        x, y, d, inv = (np.asarray(v) for v in (s.agents.x, s.agents.y, s.agents.dir, s.agents.inventory))
        grid = np.asarray(s.grid)
        dx, dy = it.DIRECTION_VECTORS[d, 0], it.DIRECTION_VECTORS[d, 1]
        for t, joint in enumerate(trial.actions):
            for a, action in enumerate(joint):
                if action <= Action.UP:
                    vx, vy = it.DIRECTION_VECTORS[it.ACTION_DIRECTION[action]]
                    moved = (x[t + 1, a], y[t + 1, a]) != (x[t, a], y[t, a])
                    target = static[y[t, a] + vy, x[t, a] + vx]
                    counts[
                        "move"
                        if moved
                        else "move blocked by a counter/object"
                        if target != Static.FLOOR
                        else "move blocked by the other agent"
                    ] += 1
                elif action == Action.INTERACT:
                    fx, fy = x[t + 1, a] + dx[t + 1, a], y[t + 1, a] + dy[t + 1, a]
                    counts[_interaction(static[fy, fx], inv[t, a], inv[t + 1, a])] += 1
            pots = static == Static.POT
            starts = pots & (grid[t, ..., 2] == 0) & (grid[t + 1, ..., 2] > 0)
            finishes = pots & ((grid[t + 1, ..., 1] & ~grid[t, ..., 1] & it.COOKED) != 0)
            counts["pot starts cooking (3rd onion)"] += int(starts.sum())
            counts["soup finishes cooking"] += int(finishes.sum())
            counts["transitions with a delivery reward"] += int(trial.rewards[t] > 0)
    return dict(sorted(counts.items()))


def _interaction(cell: int, before: int, after: int) -> str:
    if before == after:
        return "interact without effect"
    names = {Static.PLATE_PILE: "dish pile", Static.POT: "pot", Static.GOAL: "serving window", Static.WALL: "counter"}
    where = "onion pile" if cell >= Static.INGREDIENT_PILE else names.get(int(cell), "cell")
    if before == it.EMPTY:
        return f"pick up from {where}"
    if after == it.EMPTY:
        return f"put down on {where}" if cell != Static.GOAL else "deliver at serving window"
    return f"exchange at {where}"  # a dish becomes a soup at the pot
