"""Who does what in a recorded play: per-seat events read off the states, for studying a population's conventions.

Cross-play fails where two seeds settled on different conventions, and a convention is visible in what each
cook does: which pot it fills, where it puts things down for its partner, who plates and who delivers. This
module reads those events from ``population.record.play_recorded``'s states ([E, T+1, ...]) with NumPy, after
the play. Nothing here changes a number the game reports; the tests check the events against scripted plays.

An event is read from the held item before and after a transition and the cell the cook faces:

- an ingredient goes into a pot: a raw ingredient leaves the hand while facing a pot;
- a dish is taken: an empty hand takes a plate (from the pile or a counter);
- a soup is plated: a plate becomes a cooked dish while facing a pot;
- a delivery: a cooked dish leaves the hand while facing the serving window;
- a put-down / take-up on a counter: an item leaves / enters the hand while facing a counter (``Static.WALL``).

Which way round a loop of floor a cook walks (Coordination Ring's ring, Counter Circuit's circuit) is read from its
positions: ``clockwise_moves``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ocv2.items import COOKED, DIRECTION_VECTORS, EMPTY, PLATE, Static, is_raw_ingredient

__all__ = [
    "ITEM_KINDS",
    "ROLES",
    "CounterUse",
    "PotUse",
    "Transitions",
    "counter_use",
    "item_kind",
    "pot_use",
    "role_counts",
    "transitions",
]

ROLES = ("onions to pot", "dishes taken", "soups plated", "deliveries")
ITEM_KINDS = ("ingredient", "plate", "dish")  # what can be handed over on a counter


class Transitions(NamedTuple):
    """Per transition of a recorded play ([E, T, seat]): the item held before and after, the cell faced."""

    held: np.ndarray
    later: np.ndarray
    faced_x: np.ndarray
    faced_y: np.ndarray
    faced: np.ndarray  # the static tile there (Static.*)

    @property
    def onion_into_pot(self) -> np.ndarray:
        """A raw ingredient leaves the hand while facing a pot (not onto a counter)."""
        return np.asarray(is_raw_ingredient(self.held)) & (self.later == EMPTY) & (self.faced == Static.POT)

    @property
    def soup_plated(self) -> np.ndarray:
        """An empty plate becomes a cooked dish while facing a pot."""
        return (self.held == PLATE) & ((self.later & COOKED) != 0) & (self.faced == Static.POT)


class PotUse(NamedTuple):
    """Which pot each seat's ingredients go into."""

    cells: np.ndarray  # int[K, 2] (x, y) of every pot, in reading order (row by row)
    counts: np.ndarray  # int[K, seat] ingredients put into each pot

    def shares(self) -> np.ndarray:
        """float[K, seat]: each pot's share of the seat's ingredients (NaN for a seat that put none in)."""
        with np.errstate(invalid="ignore"):
            return self.counts / self.counts.sum(axis=0, keepdims=True)


class CounterUse(NamedTuple):
    """Items put down on and taken up from each counter, by kind and seat: where the cooks hand things over."""

    cells: np.ndarray  # int[K, 2] (x, y) of every counter used at least once, in reading order
    put: np.ndarray  # int[K, len(ITEM_KINDS), seat]
    taken: np.ndarray  # int[K, len(ITEM_KINDS), seat]


def static_layer(states) -> np.ndarray:
    """The static tiles [E, H, W] (layer 0 of the grid never changes within an episode)."""
    return np.asarray(states.grid[:, 0, :, :, 0])


def transitions(states) -> Transitions:
    """Read a recorded play (states [E, T+1, ...]) transition by transition."""
    agents = states.agents
    held, later = np.asarray(agents.inventory[:, :-1]), np.asarray(agents.inventory[:, 1:])
    x, y, facing = (np.asarray(a[:, :-1]) for a in (agents.x, agents.y, agents.dir))
    static = static_layer(states)
    fx, fy = x + DIRECTION_VECTORS[facing, 0], y + DIRECTION_VECTORS[facing, 1]
    episode = np.arange(static.shape[0])[:, None, None]
    faced = static[episode, np.clip(fy, 0, static.shape[1] - 1), np.clip(fx, 0, static.shape[2] - 1)]
    return Transitions(held, later, fx, fy, faced)


def item_kind(item: np.ndarray) -> np.ndarray:
    """int array: the index in ITEM_KINDS of each item (-1: the empty hand)."""
    item = np.asarray(item)
    kind = np.full(item.shape, -1, np.int32)
    kind[np.asarray(is_raw_ingredient(item))] = 0
    kind[item == PLATE] = 1
    kind[((item & PLATE) != 0) & (item != PLATE)] = 2
    return kind


def role_counts(states) -> np.ndarray:
    """int[len(ROLES), seat] counts over every episode and step of a recorded play (states [E, T+1, ...])."""
    t = transitions(states)
    counts = [
        t.onion_into_pot,
        (t.held == EMPTY) & (t.later == PLATE),
        t.soup_plated,
        ((t.held & COOKED) != 0) & (t.later == EMPTY) & (t.faced == Static.GOAL),
    ]
    return np.stack([c.sum(axis=(0, 1)) for c in counts])


def _per_cell(event: np.ndarray, t: Transitions, cells: np.ndarray) -> np.ndarray:
    """int[K, seat]: the events whose faced cell is each of ``cells``."""
    return np.stack([(event & (t.faced_x == x) & (t.faced_y == y)).sum(axis=(0, 1)) for x, y in cells])


def pot_use(states) -> PotUse:
    """Per pot and seat, the ingredients put in. The layout is the same in every episode."""
    t = transitions(states)
    cells = np.argwhere(static_layer(states)[0] == Static.POT)[:, ::-1]  # argwhere is row-major; store (x, y)
    return PotUse(cells, _per_cell(t.onion_into_pot, t, cells))


def counter_use(states) -> CounterUse:
    """Per counter, item kind and seat, the items put down and taken up; only counters used at least once."""
    t = transitions(states)
    on_counter = t.faced == Static.WALL
    put_kind, taken_kind = item_kind(t.held), item_kind(t.later)
    put_down = on_counter & (t.later == EMPTY) & (put_kind >= 0)
    taken_up = on_counter & (t.held == EMPTY) & (taken_kind >= 0)
    every = np.argwhere(static_layer(states)[0] == Static.WALL)[:, ::-1]
    put = np.stack([_per_cell(put_down & (put_kind == k), t, every) for k in range(len(ITEM_KINDS))], axis=1)
    taken = np.stack([_per_cell(taken_up & (taken_kind == k), t, every) for k in range(len(ITEM_KINDS))], axis=1)
    used = (put.sum(axis=(1, 2)) + taken.sum(axis=(1, 2))) > 0
    return CounterUse(every[used], put[used], taken[used])


def clockwise_moves(x, y, centre: tuple[float, float], time_axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """How many moves went clockwise round ``centre`` (x, y) and how many moves round it were made, summed over every
    axis but the last (the seat). Clockwise as the layout is drawn: y grows downward, so a rise of
    atan2(y - centre_y, x - centre_x) is clockwise on screen. A move is a step that changes that angle."""
    angle = np.arctan2(np.asarray(y, float) - centre[1], np.asarray(x, float) - centre[0])
    turn = (np.diff(angle, axis=time_axis) + np.pi) % (2 * np.pi) - np.pi
    moved = np.abs(turn) > 1e-9
    axes = tuple(range(turn.ndim - 1))
    return (moved & (turn > 0)).sum(axes), moved.sum(axes)
