"""A game of ``ocv2 play``: seats, the fixed tick, answering browser messages, and recording.

Plain classes, no HTTP: ``cluster/play/server.py`` calls ``GameSession.handle`` from its request
threads and ``GameSession.run`` (the clock) from one thread; tests call ``handle`` and ``tick``
directly. One lock guards the session; JAX runs only in the constructor and in ``tick``, so on one
thread at a time. Messages arrive validated (``cluster/play/protocol.py``; documented in ``docs/play.md``).

Life of a session: humans ``join`` (one seat each) and press start (``ready``); when every human
seat is ready an episode starts. Each tick takes every human's latest action (``stay`` if none
arrived since the last tick), lets the partner act, steps the env and publishes the new views. An
episode ends at ``max_steps`` (recorded as complete), or cut short when a human leaves or stops
polling for ``disconnect_s`` seconds, or when the server stops: what was played is recorded with
``cut_short: true`` and the ``end_reason``. Every recorded episode is flushed to the archive when it
ends, so a killed server loses at most the episode in progress.
"""

from __future__ import annotations

import base64
import io
import logging
import secrets
import threading
import time
from collections.abc import Callable

import jax
import numpy as np
from PIL import Image

from cluster.archive import RESERVED_KEYS, ArchiveError, ArchiveWriter, env_meta
from cluster.play.game import Game, GameCarry, host, ingredient_colour, recipe_ingredients
from cluster.play.protocol import Message, ProtocolError
from ocv2 import items as it
from ocv2.state import State, stack_states

log = logging.getLogger(__name__)

SEAT_COLOURS = ("red", "blue", "green", "purple", "yellow", "orange")  # ocv2.render.AGENT_COLORS' order
POLL_TIMEOUT_S = 1.0  # a poll with nothing new answers after this long: it doubles as the heartbeat
WAITING, PLAYING, OVER = "waiting", "playing", "over"
#: Episode metadata keys a session writes itself (``docs/play.md`` explains each); extra ``meta`` may not use them.
PLAY_META_KEYS = (
    "env_params",
    "method",
    "kind",
    "human_seats",
    "partner",
    "policies",
    "checkpoints",
    "partner_run",
    "config_fingerprint",
    "seed",
    "tick_hz",
    "session",
    "play_episode",
    "cut_short",
    "end_reason",
    "started_at",
    "wall_s",
)


class Player:
    """A joined browser tab."""

    def __init__(self, token: str, seat: int, now: float):
        self.token, self.seat, self.last_seen = token, seat, now
        self.ready = False
        self.pending = int(it.Action.STAY)  # the action for the next tick


class EpisodeLog:
    """The episode in progress, on the host, until it is written to the archive."""

    def __init__(self, first: State):
        self.states = [first]
        self.actions, self.rewards, self.shaped, self.dones = [], [], [], []
        self.started = time.time()

    @property
    def steps(self) -> int:
        return len(self.actions)

    def add(self, record, reached: State):
        self.states.append(reached)
        self.actions.append(record.actions)
        self.rewards.append(record.reward)
        self.shaped.append(record.shaped_reward)
        self.dones.append(record.done)

    def write(self, writer: ArchiveWriter, meta: dict, layout) -> int | None:
        """Write the episode (None when no transition was played: an archive episode needs one)."""
        if not self.actions:
            return None
        return writer.write_episode(
            meta,
            stack_states(self.states),
            np.stack(self.actions),
            np.stack(self.rewards),
            np.stack(self.shaped),
            np.stack(self.dones),
            layout=layout,
        )


class GameSession:
    """Seats, ticks and recording of one ``ocv2 play`` server.

    Args:
        game: the compiled game (``cluster.play.game.make_game``); its human seats are the seats browsers take.
        writer: an open ``ArchiveWriter`` every finished or cut-short episode is written to.
        seed: root PRNG seed; episode e uses ``fold_in(PRNGKey(seed), e)`` (reset: fold_in 0, step t: fold_in t + 1).
        fps: ticks (environment steps) per second.
        first_seat: the seat a tab that asks for none gets first (``--seat``).
        disconnect_s: a player silent this long (no poll, no message) has left.
        max_episodes: after this many recorded episodes ``finished`` is set (None: never).
        meta: extra metadata for every episode (e.g. a participant id).
        clock: monotonic seconds (tests pass a fake one).
    """

    def __init__(
        self,
        game: Game,
        writer: ArchiveWriter,
        *,
        seed: int,
        fps: float,
        first_seat: int | None = None,
        disconnect_s: float = 10.0,
        max_episodes: int | None = None,
        meta: dict | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.game, self.writer = game, writer
        self.seed, self.fps = int(seed), float(fps)
        self.disconnect_s, self.max_episodes, self.clock = float(disconnect_s), max_episodes, clock
        self.first_seat = game.human_seats[0] if first_seat is None else int(first_seat)
        self.env = game.env
        self.root_key = jax.random.PRNGKey(self.seed)
        taken = sorted(set(meta or {}) & set(PLAY_META_KEYS + RESERVED_KEYS))
        if taken:
            raise ValueError(f"metadata key(s) {taken} are written by the session itself; choose other names")
        self.base_meta = {**_session_meta(game, self.seed, self.fps), **(meta or {})}
        self.players: dict[str, Player] = {}
        self.phase = WAITING
        self.episodes_recorded = 0
        self.last_episode: dict | None = None
        self.last_error: str | None = None  # shown on the page (e.g. an episode that could not be recorded)
        self.failure: str | None = None  # why the clock stopped, if it did
        self.finished = threading.Event()
        self._changed = threading.Condition(threading.Lock())
        self._version = 0
        self._frame_version = 0
        self._closed = False
        self._number = -1  # episodes started or prepared (their keys' index)
        with self._changed:
            self._prepare_next()

    # ---------------------------------------------------------------------------------------------
    # the game (called by the clock thread)
    # ---------------------------------------------------------------------------------------------

    def tick(self) -> None:
        """One tick: drop silent players; start an episode when everyone is ready, or play one step."""
        with self._changed:
            if self._closed:
                return
            now = self.clock()
            for player in [p for p in self.players.values() if now - p.last_seen > self.disconnect_s]:
                self._remove(player, "disconnected")
            if self.phase != PLAYING:
                if self._everyone_ready() and not self.finished.is_set():
                    self._start()
                return
            actions = np.full((self.env.num_agents,), int(it.Action.STAY), np.int32)
            for player in self.players.values():
                actions[player.seat] = player.pending
                player.pending = int(it.Action.STAY)
            key = jax.random.fold_in(self._episode_key, self._log.steps + 1)
            self._carry, record = self.game.step(self.game.partner.params, self._carry, actions, key)
            record = host(record)
            reached = host(self._carry.state)
            self._log.add(record, reached)
            self.score += float(record.reward)
            self._publish(reached)
            if bool(record.done):
                self._end("completed")

    def run(self, stop: threading.Event) -> None:
        """Tick at ``fps`` until ``stop`` is set (or a tick fails: ``failure`` says why, ``finished`` is set).

        A late tick is not made up for: no burst of steps after a stall.
        """
        period = 1.0 / self.fps
        due = time.monotonic()
        while not stop.is_set():
            try:
                self.tick()
            except Exception as error:  # the game cannot go on: say why and let the command stop
                self.failure = self.last_error = f"the game loop failed: {type(error).__name__}: {error}"
                self.finished.set()
                return
            due += period
            delay = due - time.monotonic()
            if delay < 0:
                due = time.monotonic()
            stop.wait(max(delay, 0.0))

    def close(self, reason: str = "server stopped") -> None:
        """End the episode in progress (recorded, cut short) and wake every waiting poll. Idempotent."""
        with self._changed:
            if self._closed:
                return
            if self.phase == PLAYING:
                self._end(reason)
            self._closed = True
            self._bump()

    # ---------------------------------------------------------------------------------------------
    # messages (called by request threads)
    # ---------------------------------------------------------------------------------------------

    def handle(self, message: Message, poll_timeout: float = POLL_TIMEOUT_S) -> dict:
        """Answer one validated message; raises ``ProtocolError`` for a request that cannot be served."""
        with self._changed:
            if self._closed:
                raise ProtocolError("the game server is shutting down", 503)
            if message.type == "join":
                return self._join(message.seat)
            player = self.players.get(message.token)
            if player is None:
                raise ProtocolError("unknown token: join first (or rejoin: this tab was dropped)", 403)
            player.last_seen = self.clock()
            if message.type == "ready":
                player.ready = True
                self._bump()
                return {"ok": True}
            if message.type == "action":
                if self.phase == PLAYING:  # the latest action before the tick wins
                    player.pending = message.action
                return {"ok": True, "applied": self.phase == PLAYING}
            if message.type == "leave":
                self._remove(player, "left")
                return {"ok": True}
            # poll: answer at once if something changed since the client's version, else wait a little
            self._changed.wait_for(lambda: self._version > message.since or self._closed, poll_timeout)
            if message.token in self.players:
                player.last_seen = self.clock()
            return self._snapshot(player, message.since)

    def _join(self, seat: int | None) -> dict:
        taken = {p.seat for p in self.players.values()}
        humans = self.game.human_seats
        if seat is not None and seat not in humans:
            raise ProtocolError(f"seat {seat} is not a human seat here (human seats: {list(humans)})", 409)
        if seat is not None and seat in taken:
            raise ProtocolError(f"seat {seat} is taken", 409)
        if seat is None:
            free = [s for s in sorted(humans, key=lambda s: s != self.first_seat) if s not in taken]
            if not free:
                raise ProtocolError(f"every human seat ({list(humans)}) is taken", 409)
            seat = free[0]
        token = secrets.token_urlsafe(18)
        self.players[token] = Player(token, seat, self.clock())
        self._bump()
        return {"ok": True, "token": token, "seat": seat, "colour": SEAT_COLOURS[seat % len(SEAT_COLOURS)]}

    # ---------------------------------------------------------------------------------------------
    # internals (the lock is held)
    # ---------------------------------------------------------------------------------------------

    def _everyone_ready(self) -> bool:
        return len(self.players) == len(self.game.human_seats) and all(p.ready for p in self.players.values())

    def _prepare_next(self) -> None:
        """Reset the next episode now, so that waiting players see the kitchen they will play."""
        self._number += 1
        self._episode_key = jax.random.fold_in(self.root_key, self._number)
        self._carry: GameCarry = self.game.reset(jax.random.fold_in(self._episode_key, 0))
        self.score = 0.0
        self._first = host(self._carry.state)
        self._publish(self._first)

    def _start(self) -> None:
        self.phase = PLAYING
        self._log = EpisodeLog(self._first)
        self._bump()

    def _end(self, reason: str) -> None:
        log, cut_short = self._log, reason != "completed"
        meta = {
            **self.base_meta,
            "play_episode": self._number,
            "cut_short": cut_short,
            "end_reason": reason,
            "started_at": round(log.started, 3),
            "wall_s": round(time.time() - log.started, 3),
        }
        index = None
        try:
            index = log.write(self.writer, meta, self.env.layout)
        except (OSError, ArchiveError, ValueError) as error:  # keep serving; say so on the console and the page
            self.last_error = f"could not record episode {self._number}: {error}"
            log.warning("ocv2 play: %s", self.last_error)
        if index is not None:
            self.episodes_recorded += 1
        self.last_episode = {
            "score": self.score,
            "steps": log.steps,
            "cut_short": cut_short,
            "end_reason": reason,
            "archive_index": index,
        }
        self.phase = OVER if reason == "completed" else WAITING
        for player in self.players.values():
            player.ready = False
            player.pending = int(it.Action.STAY)
        if self.max_episodes is not None and self.episodes_recorded >= self.max_episodes:
            self.finished.set()
        self._prepare_next()

    def _remove(self, player: Player, reason: str) -> None:
        del self.players[player.token]
        if self.phase == PLAYING:
            self._end(reason)
        self._bump()

    def _publish(self, state: State) -> None:
        views = host(self.game.views(state))
        self._frames = {seat: _png_data_url(frame) for seat, frame in zip(self.game.human_seats, views.frames)}
        self._recipe_visible = dict(zip(self.game.human_seats, views.recipe_visible.tolist()))
        self._state = state
        self._bump()
        self._frame_version = self._version

    def _bump(self) -> None:
        self._version += 1
        self._changed.notify_all()

    def _snapshot(self, player: Player, since: int) -> dict:
        step = int(self._state.step)
        max_steps = self.env.max_steps
        recipe = None
        if self._recipe_visible[player.seat]:
            ingredients = recipe_ingredients(int(self._state.recipe), self.env.layout.num_ingredients)
            recipe = {"ingredients": ingredients, "colours": [ingredient_colour(i) for i in ingredients]}
        reply = {
            "ok": True,
            "version": self._version,
            "phase": self.phase,
            "closed": self._closed,
            "seat": player.seat,
            "colour": SEAT_COLOURS[player.seat % len(SEAT_COLOURS)],
            "layout": self.env.layout.name,
            "partner": self.game.partner.label,
            "fps": self.fps,
            "view_radius": self.env.config.view_radius,
            "step": step,
            "max_steps": max_steps,
            "steps_left": max_steps - step,
            "seconds_left": round((max_steps - step) / self.fps, 1),
            "score": self.score,
            "recipe": recipe,
            "episodes_recorded": self.episodes_recorded,
            "last_episode": self.last_episode,
            "joined": sorted(p.seat for p in self.players.values()),
            "ready": sorted(p.seat for p in self.players.values() if p.ready),
            "human_seats": list(self.game.human_seats),
            "you_ready": player.ready,
            "error": self.last_error,
            "dropped": player.token not in self.players,
        }
        if since < self._frame_version:
            reply["frame"] = self._frames[player.seat]
        return reply


def _session_meta(game: Game, seed: int, fps: float) -> dict:
    """Episode metadata shared by every episode of a session (docs/play.md lists the keys)."""
    partner, humans = game.partner, game.human_seats
    seats = range(game.env.num_agents)
    return {
        **env_meta(game.env),
        "method": "play",
        "kind": "human-play",
        "human_seats": list(humans),
        "partner": partner.kind,
        "policies": ["human" if s in humans else partner.label for s in seats],
        "checkpoints": [None if s in humans else partner.checkpoint for s in seats],
        "partner_run": partner.run_dir,
        "config_fingerprint": partner.config_fingerprint,
        "seed": seed,
        "tick_hz": fps,
        "session": secrets.token_hex(6),
    }


def _png_data_url(frame: np.ndarray) -> str:
    buffer = io.BytesIO()
    Image.fromarray(np.asarray(frame, np.uint8)).save(buffer, format="PNG", compress_level=1)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")
