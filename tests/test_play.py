"""``ocv2 play`` without a browser: message validation, the game loop, recording, HTTP, partners, CLI errors.

Sessions run with a fake clock and explicit ``tick()`` calls (no timing in the tests); the games are
cramped_room with 6-step episodes and 8-pixel tiles, so each compiles in about a second.
"""

from __future__ import annotations

import http.client
import importlib
import json
import logging
import select
import socket
import struct
import threading
import time
from pathlib import Path

import jax
import numpy as np
import pytest

import ocv2
from cluster.archive import ArchiveReader, ArchiveWriter, states_as_buffer
from cluster.cli import main
from cluster.play.game import HIDDEN_RGB, PartnerError, human_partner, load_policy_partner, make_game, scripted_partner
from cluster.play.protocol import Message, ProtocolError, parse_message
from cluster.play.server import PlayServer
from cluster.play.session import GameSession
from cluster.runtime.rundir import RunDir
from population import checkpoints as ckpt
from population import policy as policies
from population import ppo
from population.config import load_config
from population.networks import init_params

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")
STEPS = 6
UP, LEFT, STAY, INTERACT = 3, 2, 4, 5


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture(scope="module")
def solo_game():
    """One human (seat 0) with a view radius of 1, partner 'stay'."""
    env = ocv2.make("cramped_room", max_steps=STEPS, agent_view_size=1)
    return make_game(env, scripted_partner("stay"), [0], tile_size=8)


@pytest.fixture(scope="module")
def duo_game():
    """Two humans, whole map in view."""
    return make_game(ocv2.make("cramped_room", max_steps=STEPS), human_partner(), [0, 1], tile_size=8)


@pytest.fixture
def archive(tmp_path):
    path = tmp_path / "play.mcap"
    writer = ArchiveWriter(path).open()
    yield writer
    writer.close()


def session_of(game, writer, **options):
    clock = FakeClock()
    return GameSession(game, writer, seed=0, fps=5, clock=clock, **options), clock


def send(session, **fields):
    return session.handle(parse_message(json.dumps(fields).encode()), poll_timeout=0)


def join(session, **fields) -> str:
    return send(session, type="join", **fields)["token"]


def episodes(writer) -> list:
    writer.close()
    return list(ArchiveReader(writer.path).iter_episodes())


# ---------------------------------------------------------------------------------------------------
# messages
# ---------------------------------------------------------------------------------------------------


def test_valid_messages_parse():
    assert parse_message(b'{"type": "join"}') == Message("join")
    assert parse_message(b'{"type": "join", "seat": 1}').seat == 1
    assert parse_message(b'{"type": "action", "token": "t", "action": "up"}').action == UP
    assert parse_message(b'{"type": "action", "token": "t", "action": 5}').action == INTERACT
    assert parse_message(b'{"type": "poll", "token": "t", "since": 7}').since == 7


@pytest.mark.parametrize(
    "body, status, words",
    [
        (b"\xff\xfe", 400, "not UTF-8 JSON"),
        (b"{nope", 400, "not UTF-8 JSON"),
        (b"[1, 2]", 400, "JSON object"),
        (b'{"type": "dance"}', 400, "unknown message type 'dance'"),
        (b'{"action": "up"}', 400, "unknown message type None"),
        (b'{"type": "action", "token": "t"}', 400, "missing ['action']"),
        (b'{"type": "poll", "token": "t", "evil": 1}', 400, "unexpected ['evil']"),
        (b'{"type": "action", "token": "t", "action": "jump"}', 400, "action must be one of"),
        (b'{"type": "action", "token": "t", "action": 6}', 400, "action must be one of"),
        (b'{"type": "action", "token": "t", "action": true}', 400, "action must be one of"),
        (b'{"type": "poll", "token": "t", "since": -1}', 400, "since must be"),
        (b'{"type": "poll", "token": 12}', 400, "token must be"),
        (b'{"type": "join", "seat": "0"}', 400, "seat must be"),
        (b" " * 5000, 413, "limit"),
        (b"[" * 2040 + b"]" * 2040, 400, "nests deeper than 2 levels"),  # 4 KB that json.loads cannot parse
        (b'{"type": "join", "seat": ' + b"[" * 2000 + b"]" * 2000 + b"}", 400, "nests deeper than 2 levels"),
        (b'{"type": "join", "seat": [[1]]}', 400, "nests deeper than 2 levels"),
    ],
)
def test_malformed_messages_are_rejected(body, status, words):
    with pytest.raises(ProtocolError, match=words.replace("[", r"\[").replace("]", r"\]")) as info:
        parse_message(body)
    assert info.value.status == status


# ---------------------------------------------------------------------------------------------------
# the game loop
# ---------------------------------------------------------------------------------------------------


def test_an_episode_plays_tick_by_tick_and_is_archived_whole(solo_game, archive):
    session, _ = session_of(solo_game, archive, meta={"participant": "P01"})
    token = join(session)
    first = send(session, type="poll", token=token, since=0)
    assert first["phase"] == "waiting" and first["frame"].startswith("data:image/png;base64,")
    assert first["seat"] == 0 and first["colour"] == "red" and first["step"] == 0 and first["max_steps"] == STEPS
    assert "frame" not in send(session, type="poll", token=token, since=first["version"])  # nothing new: no frame
    session.tick()
    assert session.phase == "waiting"  # nobody pressed start
    assert send(session, type="action", token=token, action="up") == {"ok": True, "applied": False}
    send(session, type="ready", token=token)
    session.tick()
    assert session.phase == "playing"
    send(session, type="action", token=token, action="up")
    send(session, type="action", token=token, action="left")  # the latest action before a tick wins
    session.tick()
    state = send(session, type="poll", token=token, since=0)
    assert state["step"] == 1 and state["steps_left"] == STEPS - 1 and state["phase"] == "playing"
    for action in ("interact", None, "up", None, "interact"):
        if action:
            send(session, type="action", token=token, action=action)
        session.tick()
    over = send(session, type="poll", token=token, since=0)
    assert over["phase"] == "over" and over["step"] == 0  # the next episode's kitchen is already shown
    assert over["last_episode"]["steps"] == STEPS and not over["last_episode"]["cut_short"]
    assert session.episodes_recorded == 1

    (episode,) = episodes(archive)
    np.testing.assert_array_equal(episode.actions[:, 0], [LEFT, INTERACT, STAY, UP, STAY, INTERACT])
    np.testing.assert_array_equal(episode.actions[:, 1], [STAY] * STEPS)
    meta = episode.meta
    assert meta["steps"] == STEPS and meta["human_seats"] == [0] and meta["policies"] == ["human", "stay"]
    assert meta["cut_short"] is False and meta["end_reason"] == "completed" and meta["participant"] == "P01"
    assert meta["env_params"]["agent_view_size"] == 1 and meta["method"] == "play" and meta["seed"] == 0
    assert episode.dones.tolist() == [False] * (STEPS - 1) + [True]
    # The archive holds what was played: replaying the actions from each state gives the next one.
    env = solo_game.env
    step = jax.jit(lambda s, a: env.step_arrays(jax.random.PRNGKey(0), s, a).terminal_state)
    for t in range(STEPS):
        reached = step(jax.tree.map(lambda x: x[t], episode.states), episode.actions[t])
        for got, want in zip(
            jax.tree.leaves(reached), jax.tree.leaves(jax.tree.map(lambda x: x[t + 1], episode.states))
        ):
            np.testing.assert_array_equal(np.asarray(got), want)
    assert int(states_as_buffer(archive.path, keep_every=2).step.shape[0]) == 3


def test_the_human_sees_only_their_view_window(solo_game):
    carry = solo_game.reset(jax.random.PRNGKey(0))
    views = solo_game.views(carry.state)
    frame = np.asarray(views.frames[0])
    x, y = int(carry.state.agents.x[0]), int(carry.state.agents.y[0])
    tile = 8
    cell = lambda cx, cy: frame[cy * tile : (cy + 1) * tile, cx * tile : (cx + 1) * tile]
    assert not (cell(x, y) == HIDDEN_RGB).all()  # the own cell is drawn
    far = [(cx, cy) for cy in range(4) for cx in range(5) if max(abs(cx - x), abs(cy - y)) > 1]
    assert far and all((cell(cx, cy) == HIDDEN_RGB).all() for cx, cy in far)


def test_a_silent_tab_is_dropped_and_its_episode_recorded_cut_short(solo_game, archive):
    session, clock = session_of(solo_game, archive, disconnect_s=10)
    token = join(session)
    send(session, type="ready", token=token)
    session.tick()
    send(session, type="action", token=token, action="up")
    session.tick()
    session.tick()
    clock.now += 10.5  # no poll, no message: the tab crashed or the network went away
    session.tick()
    assert session.phase == "waiting" and not session.players
    with pytest.raises(ProtocolError) as info:
        send(session, type="poll", token=token, since=0)
    assert info.value.status == 403
    (episode,) = episodes(archive)
    assert episode.meta["steps"] == 2 and episode.meta["cut_short"] is True
    assert episode.meta["end_reason"] == "disconnected" and not episode.dones.any()


def test_leaving_and_stopping_record_what_was_played(solo_game, archive):
    session, _ = session_of(solo_game, archive)
    token = join(session)
    send(session, type="ready", token=token)
    session.tick()
    send(session, type="leave", token=token)  # left before any step: nothing to record
    token = join(session)
    send(session, type="ready", token=token)
    session.tick()
    session.tick()
    send(session, type="leave", token=token)
    token = join(session)
    send(session, type="ready", token=token)
    for _ in range(4):
        session.tick()
    session.close()
    session.close()  # idempotent
    with pytest.raises(ProtocolError) as info:
        send(session, type="poll", token=token, since=0)
    assert info.value.status == 503
    left, stopped = episodes(archive)
    assert (left.meta["steps"], left.meta["end_reason"], left.meta["cut_short"]) == (1, "left", True)
    assert (stopped.meta["steps"], stopped.meta["end_reason"]) == (3, "server stopped")
    assert left.meta["play_episode"] == 1 and stopped.meta["play_episode"] == 2


def test_two_people_play_one_game(duo_game, archive):
    session, _ = session_of(duo_game, archive, first_seat=1, max_episodes=1)
    second = join(session)
    first = join(session)
    assert session.players[second].seat == 1 and session.players[first].seat == 0
    for fields, status in (({}, 409), ({"seat": 0}, 409), ({"seat": 2}, 409)):
        with pytest.raises(ProtocolError) as info:
            join(session, **fields)
        assert info.value.status == status
    with pytest.raises(ProtocolError) as info:
        send(session, type="ready", token="not-a-token")
    assert info.value.status == 403
    send(session, type="ready", token=first)
    session.tick()
    assert session.phase == "waiting"  # the other person has not pressed start
    poll = send(session, type="poll", token=second, since=0)
    assert poll["joined"] == [0, 1] and poll["ready"] == [0] and poll["recipe"] is not None
    send(session, type="ready", token=second)
    session.tick()
    assert session.phase == "playing"
    send(session, type="action", token=first, action="interact")
    send(session, type="action", token=second, action="left")
    for _ in range(STEPS):
        session.tick()
    assert session.finished.is_set()
    send(session, type="ready", token=first)
    send(session, type="ready", token=second)
    session.tick()
    assert session.phase == "over"  # --episodes reached: no new episode starts
    (episode,) = episodes(archive)
    assert episode.actions[0].tolist() == [INTERACT, LEFT] and episode.meta["human_seats"] == [0, 1]
    assert episode.meta["policies"] == ["human", "human"] and episode.meta["partner"] == "human"


# ---------------------------------------------------------------------------------------------------
# HTTP
# ---------------------------------------------------------------------------------------------------


def _request(server, method, path, body=None, headers=None, key=True):
    """One request to ``server`` as its page sends it (its key in the query), unless told otherwise."""
    if key:
        path += ("&" if "?" in path else "?") + f"key={server.key}"
    connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        connection.close()


def _api(server, message, **headers) -> tuple[int, dict]:
    body = message if isinstance(message, bytes) else json.dumps(message).encode()
    status, _, data = _request(server, "POST", "/api", body, {"Content-Type": "application/json", **headers})
    return status, json.loads(data)


def _running_server(solo_game, archive, request_timeout: float, **options):
    """A started server (four player slots) whose session nobody joined; stopped after the test.

    ``request_timeout`` is the new connections' head deadline too, unless ``head_timeout`` is given.
    """
    options = {"head_timeout": request_timeout, "max_connections": 4, **options}
    server = PlayServer("127.0.0.1", 0, request_timeout=request_timeout, **options)
    server.start(GameSession(solo_game, archive, seed=1, fps=5))
    yield server
    server.stop()


@pytest.fixture
def served(solo_game, archive):
    """A running server with a short request timeout."""
    yield from _running_server(solo_game, archive, request_timeout=0.5)


def test_the_server_rejects_bad_requests_and_the_game_goes_on(solo_game, archive, monkeypatch):
    session = GameSession(solo_game, archive, seed=1, fps=100, max_episodes=1)
    server = PlayServer("127.0.0.1", 0)
    assert server.url.startswith("http://127.0.0.1:") and server.url.endswith(f"/?key={server.key}")
    server.start(session)
    try:
        status, headers, page = _request(server, "GET", "/")
        assert status == 200 and b"ocv2 play" in page and "default-src 'none'" in headers["Content-Security-Policy"]
        assert _request(server, "GET", "/secrets")[0] == 404
        assert _request(server, "POST", "/elsewhere", b"{}")[0] == 404
        assert _api(server, b"garbage") == (400, {"ok": False, "error": "message is not UTF-8 JSON"})
        assert (
            _request(server, "POST", "/api", b"x", {"Content-Length": "999999", "Content-Type": "application/json"})[0]
            == 413
        )
        status, reply = _api(server, {"type": "join"})
        token = reply["token"]
        assert status == 200 and reply["seat"] == 0
        assert _api(server, {"type": "action", "token": token, "action": "fly"})[0] == 400
        original = session.handle
        monkeypatch.setattr(session, "handle", lambda message: 1 / 0)  # a bug in one request ...
        assert _api(server, {"type": "ready", "token": token}) == (
            500,
            {"ok": False, "error": "internal error (ZeroDivisionError)"},
        )
        monkeypatch.setattr(session, "handle", original)  # ... and the game still plays
        assert _api(server, {"type": "ready", "token": token})[0] == 200
        since = 0
        while not session.finished.wait(0):
            status, poll = _api(server, {"type": "poll", "token": token, "since": since})
            assert status == 200
            since = poll["version"]
            _api(server, {"type": "action", "token": token, "action": "up"})
    finally:
        server.stop()
        server.stop()
    (episode,) = episodes(archive)
    assert episode.meta["steps"] == STEPS and not episode.meta["cut_short"]


JOIN = {"type": "join"}


def test_a_deeply_nested_message_is_a_400_not_a_500(served):
    status, reply = _api(served, b"[" * 2040 + b"]" * 2040)
    assert status == 400 and "nests deeper than 2 levels" in reply["error"]
    assert _api(served, JOIN)[0] == 200  # the server goes on


@pytest.mark.parametrize("origin", ["http://evil.example", "null", "http://localhost:{port}"])
def test_a_post_from_another_origin_is_refused(served, origin):
    """Another page (elsewhere, sandboxed, or another origin on this machine) posting a "simple" request."""
    status, reply = _api(served, JOIN, Origin=origin.format(port=served.port))
    assert status == 403 and "not accepted" in reply["error"]
    assert not served.session.players


@pytest.mark.parametrize("host", ["evil.example:{port}", "127.0.0.1:{next_port}", ""])
def test_a_request_for_another_host_is_refused(served, host):
    """DNS rebinding: the attacker's name resolves to this machine, but the Host header still says it."""
    status, reply = _api(served, JOIN, Host=host.format(port=served.port, next_port=served.port + 1))
    assert status == 403 and "not this server's address" in reply["error"]
    assert not served.session.players


def test_requests_without_the_key_are_refused(served):
    for query in ("", "?key=wrong", f"?key={served.key[:-1]}"):
        status, _, data = _request(
            served, "POST", "/api" + query, json.dumps(JOIN).encode(), {"Content-Type": "application/json"}, key=False
        )
        assert status == 403 and "wrong key" in json.loads(data)["error"], query
        assert _request(served, "GET", "/" + query, key=False)[0] == 403
    assert not served.session.players


@pytest.mark.parametrize(
    "content_type", ["text/plain", "application/x-www-form-urlencoded", "multipart/form-data", None]
)
def test_a_message_that_is_not_json_typed_is_refused(served, content_type):
    """The content types a cross-site form or a preflight-free fetch can send."""
    status, _, data = _request(
        served, "POST", "/api", json.dumps(JOIN).encode(), {"Content-Type": content_type} if content_type else {}
    )
    assert status == 415 and "application/json" in json.loads(data)["error"]
    assert not served.session.players


def test_the_page_itself_is_served(served):
    """Its own Host and Origin, the key, JSON with a charset."""
    status, _, page = _request(served, "GET", "/", headers={"Host": f"localhost:{served.port}"})
    assert status == 200 and b"encodeURIComponent" in page
    status, reply = _api(
        served, JOIN, Origin=f"http://127.0.0.1:{served.port}", **{"Content-Type": "application/json; charset=utf-8"}
    )
    assert status == 200 and reply["seat"] == 0


def test_host_names_of_a_wildcard_bind(solo_game, archive):
    server = PlayServer("0.0.0.0", 0)
    try:
        port = server.port
        allowed = server.http.host_allowed
        assert allowed(f"127.0.0.1:{port}") and allowed(f"localhost:{port}") and allowed(f"192.168.1.20:{port}")
        assert allowed(f"[::1]:{port}") and allowed(f"{socket.gethostname()}:{port}")
        assert not allowed(f"evil.example:{port}") and not allowed(f"192.168.1.20:{port + 1}")
        assert not allowed(f"user@127.0.0.1:{port}") and not allowed("127.0.0.1:notaport") and not allowed(None)
    finally:
        server.stop()


def _connect(server) -> socket.socket:
    client = socket.create_connection(("127.0.0.1", server.port), timeout=5)
    client.settimeout(5)
    return client


def test_a_slow_client_is_cut_off(served):
    """A request trickling in a byte at a time (slowloris) gets its deadline in all, not per byte."""
    client = _connect(served)
    request = f"POST /api?key={served.key} HTTP/1.1\r\nHost: 127.0.0.1:{served.port}\r\n".encode()
    cut = False
    try:
        for byte in request:  # 0.1 s a byte, far below the 0.5 s timeout, over several seconds
            client.sendall(bytes([byte]))
            if not wait_readable(client, 0.1):
                continue
            cut = client.recv(1024) == b""
            break
    except (BrokenPipeError, ConnectionResetError):
        cut = True
    finally:
        client.close()
    assert cut, "the server still waited for the rest of the request"
    idle = _connect(served)  # a connection that sends nothing is closed too
    try:
        assert idle.recv(1024) == b""
    finally:
        idle.close()


def wait_readable(client: socket.socket, seconds: float) -> bool:
    return bool(select.select([client], [], [], seconds)[0])


@pytest.fixture
def patient(solo_game, archive):
    """A running server that waits long for requests (idle connections stay open)."""
    yield from _running_server(solo_game, archive, request_timeout=60)


def _keyed_connection(server) -> http.client.HTTPConnection:
    """A connection that loaded the page (showing the key) and stays open, as a tab's keep-alive one."""
    connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    connection.request("GET", f"/?key={server.key}")
    response = connection.getresponse()
    assert response.status == 200 and response.read()
    return connection


def test_a_flood_of_connections_is_capped(patient):
    """Connections that showed the key hold the ``max_connections`` slots; one more gets 503 (and no
    slot), connections without the key take none, and a freed slot serves again."""
    served = patient
    threads = threading.active_count()
    held = [_keyed_connection(served) for _ in range(4)]
    idle = [_connect(served) for _ in range(3)]
    try:
        _wait_for(lambda: (served.http.player_connections, served.http.pending_connections) == (4, 3))
        for _ in range(3):
            status, _, data = _request(served, "GET", "/")
            assert status == 503 and "serving 4 connections" in json.loads(data)["error"]
        assert served.http.player_connections == 4
        # one thread per open connection and none left over: a 503's handler thread ends just after its answer
        # is read, so the count is awaited rather than read once (a single read saw that thread still alive)
        _wait_for(lambda: threading.active_count() <= threads + 4 + 3)
    finally:
        for client in held + idle:
            client.close()
    _wait_for(lambda: served.http.player_connections == served.http.pending_connections == 0)
    assert _api(served, {"type": "join"})[0] == 200


def test_the_oldest_connection_without_the_key_makes_room(solo_game, archive):
    """With ``max_pending`` connections open that never show the key, a new one closes the oldest:
    a page load still gets in, and the threads stay bounded."""
    for server in _running_server(solo_game, archive, request_timeout=60, max_pending=4):
        idle = [_connect(server) for _ in range(4)]
        try:
            _wait_for(lambda: server.http.pending_connections == 4)
            threads = threading.active_count()
            idle.append(_connect(server))
            assert idle[0].recv(1024) == b"", "the oldest connection without the key was not closed"
            assert _request(server, "GET", "/")[0] == 200  # pushes out the next oldest, and is served
            assert idle[1].recv(1024) == b""
            # The page load left ``pending`` when it showed the key, and its slot when it closed.
            _wait_for(lambda: (server.http.pending_connections, server.http.player_connections) == (3, 0))
            assert threading.active_count() <= threads
        finally:
            for client in idle:
                client.close()


def _hold_unkeyed_connections(port: int, count: int, opened: threading.Event, stop: threading.Event, limit_s: float):
    """Keep ``count`` connections to ``port`` open that never show the key, until ``stop`` or ``limit_s``.

    Even ones trickle a request head (a header that never ends) a byte every 0.2 s, odd ones send
    nothing; one the server closes or answers is reopened, as an attacker would. ``opened`` is set
    once all are open.
    """
    head = f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-Slow: ".encode()
    clients: list[socket.socket | None] = [None] * count
    sent = [0] * count
    deadline = time.monotonic() + limit_s
    try:
        while not stop.is_set() and time.monotonic() < deadline:
            for i in range(count):
                if clients[i] is None:
                    try:
                        clients[i] = socket.create_connection(("127.0.0.1", port), timeout=1)
                    except OSError:
                        continue
                    sent[i] = 0
            opened.set()
            live = [c for c in clients if c is not None]
            for client in select.select(live, [], [], 0.2)[0]:  # closed, or answered (a 503): reopen
                clients[clients.index(client)] = None
                client.close()
            for i in range(0, count, 2):
                if clients[i] is not None:
                    byte = head[sent[i] : sent[i] + 1] or b"x"
                    try:
                        clients[i].sendall(byte)
                        sent[i] += 1
                    except OSError:
                        clients[i].close()
                        clients[i] = None
    finally:
        for client in clients:
            if client is not None:
                client.close()


def test_connections_without_the_key_do_not_starve_the_players(solo_game, archive):
    """40 slow or idle connections that never show the key, each reopened when the
    server closes it, for longer than their deadline: page loads and a joined player's polls, on its
    open connection and on new ones, are all still served."""
    server = PlayServer("127.0.0.1", 0)
    server.start(GameSession(solo_game, archive, seed=1, fps=5))
    opened, stop = threading.Event(), threading.Event()
    flood = threading.Thread(target=_hold_unkeyed_connections, args=(server.port, 40, opened, stop, 15.0), daemon=True)
    tab = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)  # the player's keep-alive connection
    headers = {"Content-Type": "application/json"}

    def kept_poll() -> int:
        tab.request("POST", f"/api?key={server.key}", poll, headers)
        response = tab.getresponse()
        response.read()
        return response.status

    def status(request) -> int | str:
        try:
            return request()
        except OSError as error:  # refused before the request was sent, or cut before the answer
            return type(error).__name__

    try:
        poll = json.dumps({"type": "poll", "token": _api(server, JOIN)[1]["token"], "since": 0}).encode()
        assert kept_poll() == 200
        flood.start()
        assert opened.wait(10)
        time.sleep(0.5)  # the server has accepted them all
        statuses = []
        end = time.monotonic() + 3.0  # past the unkeyed connections' deadline: they are cut and reopened
        while time.monotonic() < end:
            statuses.append(("page", status(lambda: _request(server, "GET", "/")[0])))
            statuses.append(("poll", status(lambda: _request(server, "POST", "/api", poll, headers)[0])))
            statuses.append(("kept poll", status(kept_poll)))
            time.sleep(0.1)
    finally:
        stop.set()
        flood.join(20)
        tab.close()
        server.stop()
    failed = [s for s in statuses if s[1] != 200]
    assert not flood.is_alive() and len(statuses) >= 15
    assert not failed, f"{len(failed)} of {len(statuses)} requests failed: {failed[:6]}"


def _wait_for(condition, seconds: float = 10.0):
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_a_client_leaving_mid_answer_costs_one_log_line(served, caplog, capsys):
    caplog.set_level(logging.INFO, logger="cluster.play")
    token = _api(served, {"type": "join"})[1]["token"]
    client = _connect(served)
    body = json.dumps({"type": "poll", "token": token, "since": 10**9}).encode()  # answered after a second
    client.sendall(
        f"POST /api?key={served.key} HTTP/1.1\r\nHost: 127.0.0.1:{served.port}\r\n"
        f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n".encode()
        + body
    )
    time.sleep(0.2)  # the server has read the request and waits in the poll
    client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    client.close()  # a reset: the answer cannot be written
    deadline = time.monotonic() + 10
    while "ended mid-request" not in caplog.text and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.2)
    records = [r for r in caplog.records if r.name.startswith("cluster.play")]
    assert len(records) == 1 and "ended mid-request" in records[0].getMessage(), caplog.text
    assert "Traceback" not in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------------
# partners from run directories
# ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rnn_run(tmp_path_factory):
    """A run directory with one RNN checkpoint (untrained parameters: only loading is tested)."""
    run = tmp_path_factory.mktemp("runs") / "rnn"
    config = load_config(
        SMOKE,
        [
            "model.kind=rnn",
            "model.gru_dim=8",
            "model.mixer_features=[8]",
            "model.conv_features=[8]",
            "model.conv_kernels=[3]",
            "model.fc_dim=8",
            f"env.max_steps={STEPS}",
        ],
    )
    RunDir(run).create(config)
    env = ppo.eval_env(config)
    network = ppo.make_trainer(config).network
    # Jitted: op by op, the GRU's scan compiles anew on every call (seconds).
    params = jax.jit(lambda key: init_params(network, key, env.obs_shape))(jax.random.PRNGKey(3))
    for update in (0, 2):
        ckpt.save(ckpt.checkpoint_path(run, 0, update), {"params": params}, config.fingerprint(), seed=0, update=update)
    return run


def test_a_policy_partner_acts_on_its_own_observation_and_keeps_its_hidden_state(rnn_run):
    partner = load_policy_partner(rnn_run / "checkpoints" / "seed_0")
    assert partner.label == "seed_0@update_2" and partner.hidden_size == 8
    assert partner.checkpoint.endswith("update_0000002.msgpack")
    assert load_policy_partner(ckpt.checkpoint_path(rnn_run, 0, 0)).label == "seed_0@update_0"
    assert partner.env_kwargs == load_config(rnn_run / "config.yaml").env_kwargs
    assert partner.config_fingerprint == load_config(rnn_run / "config.yaml").fingerprint()
    game = make_game(ocv2.make(**partner.env_kwargs), partner, [0], tile_size=8)
    carry = game.reset(jax.random.PRNGKey(0))
    stay = np.full((2,), STAY, np.int32)
    after_one, record = game.step(partner.params, carry, stay, jax.random.PRNGKey(1))
    after_two, _ = game.step(partner.params, after_one, stay, jax.random.PRNGKey(2))
    # The same hidden states as the network applied by hand to seat 1's observations, reset flag first.
    apply = partner.apply
    hidden = np.zeros((1, 8), np.float32)
    hidden, _, _ = apply(partner.params, hidden, carry.obs[1][None, None], np.ones((1, 1), bool))
    np.testing.assert_allclose(after_one.hidden[1], hidden[0], rtol=1e-5, atol=1e-6)
    hidden, _, _ = apply(partner.params, hidden, after_one.obs[1][None, None], np.zeros((1, 1), bool))
    np.testing.assert_allclose(after_two.hidden[1], hidden[0], rtol=1e-5, atol=1e-6)
    assert int(record.actions[0]) == STAY and np.abs(np.asarray(after_two.hidden[1])).sum() > 0


def test_an_exported_policy_file_is_a_partner(rnn_run, tmp_path, capsys):
    exported = policies.export_checkpoint(
        rnn_run, tmp_path / "cook.ocv2policy", checkpoint="latest", meta={"name": "cook"}
    )
    partner = load_policy_partner(exported)
    original = load_policy_partner(rnn_run / "checkpoints" / "seed_0")
    assert (partner.kind, partner.label, partner.run_dir, partner.config_fingerprint) == ("policy", "cook", None, None)
    assert partner.env_kwargs == original.env_kwargs and partner.hidden_size == 8
    for got, want in zip(jax.tree.leaves(partner.params), jax.tree.leaves(original.params)):
        np.testing.assert_array_equal(got, want)
    # the command plays the file's environment and refuses flags that change it, like a run's
    code, err = _cli_error(
        capsys, "--partner", str(exported), "--agent-view-size", "2", "--port", "0", "--out", str(tmp_path / "x.mcap")
    )
    assert code == 2 and "agent_view_size: the partner's run uses None" in err


def test_an_exported_file_of_any_name_is_a_partner(rnn_run, tmp_path, capsys):
    """``ocv2 export --out`` takes any name, and render, xp and population.policy.load read what it wrote."""
    assert main(["export", str(rnn_run), "--checkpoint", "latest", "--out", str(tmp_path / "e7.bin")]) == 0
    capsys.readouterr()
    partner = load_policy_partner(tmp_path / "e7.bin")
    original = load_policy_partner(rnn_run / "checkpoints" / "seed_0")
    assert (partner.kind, partner.checkpoint, partner.run_dir) == ("policy", str(tmp_path / "e7.bin"), None)
    for got, want in zip(jax.tree.leaves(partner.params), jax.tree.leaves(original.params)):
        np.testing.assert_array_equal(got, want)
    # a run's checkpoint copied out of its seed folder is not a policy of its own
    stray = tmp_path / "update_0000002.msgpack"
    stray.write_bytes(ckpt.checkpoint_path(rnn_run, 0, 2).read_bytes())
    with pytest.raises(PartnerError, match="a checkpoint must lie in RUN_DIR/checkpoints/seed_<i>/"):
        load_policy_partner(stray)


def test_the_game_is_traced_at_the_precision_the_partner_trained_with(rnn_run, tmp_path, monkeypatch):
    """As cross-play and render: on a GPU JAX's own default would be TF32 for a partner trained at float32."""
    from cluster.play import game as game_module

    seen, original = [], game_module.game_step

    def recording_game_step(*args, **kwargs):
        seen.append(jax.config.jax_default_matmul_precision)  # what the step is traced under
        return original(*args, **kwargs)

    monkeypatch.setattr(game_module, "game_step", recording_game_step)
    policy = policies.load(rnn_run, checkpoint="latest")
    files = {
        precision: policies.export(
            tmp_path / f"{precision}.bin",
            params=policy.params,
            model=policy.model,
            env=policy.env,
            meta={"precision": precision},
        )
        for precision in ("bf16", "fp16")
    }
    stay = np.full((2,), STAY, np.int32)
    for partner, expected in [
        (load_policy_partner(rnn_run / "checkpoints" / "seed_0"), "float32"),  # its run's run.precision
        (load_policy_partner(files["bf16"]), "bfloat16"),
        (scripted_partner("random"), "float32"),
    ]:
        game = make_game(ocv2.make(**policy.env), partner, [0], tile_size=8)
        game.step(partner.params, game.reset(jax.random.PRNGKey(0)), stay, jax.random.PRNGKey(1))
        assert seen[-1] == expected
    assert jax.config.jax_default_matmul_precision is None  # only while the game is called
    with pytest.raises(PartnerError, match="fp16.bin: meta precision 'fp16' is not one of float32, tf32, bf16"):
        load_policy_partner(files["fp16"])


def test_bad_partner_paths_are_clear_errors(rnn_run, tmp_path):
    cases = [
        (tmp_path / "missing", "does not exist"),
        (rnn_run, "pick a seed, e.g."),
        (rnn_run / "config.yaml", "config.yaml: not an ocv2 policy or checkpoint file"),
        (rnn_run / "checkpoints", "is not RUN_DIR/checkpoints/seed_<i>, a checkpoint file in one or an exported"),
    ]
    empty = tmp_path / "empty" / "checkpoints" / "seed_0"
    empty.mkdir(parents=True)
    cases.append((empty, "holds no checkpoint"))
    for path, words in cases:
        with pytest.raises(PartnerError, match=words):
            load_policy_partner(path)
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.yaml").write_text((rnn_run / "config.yaml").read_text().replace("lr: 0.001", "lr: 0.002"))
    copy = ckpt.checkpoint_path(other, 0, 0)
    copy.parent.mkdir(parents=True)
    copy.write_bytes(ckpt.checkpoint_path(rnn_run, 0, 0).read_bytes())
    with pytest.raises(PartnerError, match="different config"):
        load_policy_partner(copy)


# ---------------------------------------------------------------------------------------------------
# the command line: errors before anything starts
# ---------------------------------------------------------------------------------------------------


def _cli_error(capsys, *args) -> tuple[int, str]:
    return _cli_error_of("play", capsys, *args)


def _cli_error_of(command, capsys, *args) -> tuple[int, str]:
    code = main([command, *args])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def test_command_line_errors(rnn_run, tmp_path, capsys):
    seed = str(rnn_run / "checkpoints" / "seed_0")
    out = ["--out", str(tmp_path / "x.mcap"), "--port", "0"]
    cases = [
        ((), 2, "give a LAYOUT"),
        (("cramped_rom",), 2, "unknown layout 'cramped_rom'"),
        (("cramped_room", "--partner", str(tmp_path / "nope")), 2, "does not exist"),
        (("cramped_room", "--partner", str(rnn_run)), 2, "pick a seed"),
        (("cramped_room", "--seat", "2"), 2, "has 2 seat(s)"),
        (("long_room", "--partner", "human"), 2, "one cook"),
        (("coord_ring", "--partner", seed), 2, "trained on layout 'cramped_room'"),
        (("--partner", seed, "--agent-view-size", "2"), 2, "agent_view_size: the partner's run uses None"),
        (("cramped_room", "--env", "bogus=1"), 2, "unknown environment parameter"),
        (
            ("cramped_room", "--env", "max_steps=" + "[" * 5000),
            2,
            "--env max_steps=...: not a YAML value: nested deeper",
        ),
        (("cramped_room", "--env", "max_steps=2026-12-02"), 2, "--env max_steps=...: "),
        (("cramped_room", "--env", "agent_view_size=99999999999"), 2, "agent_view_size must be None or an integer"),
        (("cramped_room", "--agent-view-size", "99999999999"), 2, "below 2**31"),
        (("cramped_room", "--meta", "seed=3"), 2, "set by ocv2 play itself"),
        (("cramped_room", "--out", str(tmp_path / "x.txt"), "--port", "0"), 2, "must name a .mcap file"),
        (("cramped_room", "--out", str(tmp_path / "taken.mcap"), "--port", "0"), 2, "a recording is never replaced"),
        (("cramped_room", "--out", str(tmp_path / "left.mcap"), "--port", "0"), 2, "`ocv2 archive recover` it"),
        (("cramped_room", "--out", str(tmp_path / "taken.mcap" / "x.mcap"), "--port", "0"), 2, "which is a file"),
    ]
    (tmp_path / "taken.mcap").write_text("an earlier recording")
    (tmp_path / "left.mcap.partial").write_text("an unfinished one")
    for args, code, words in cases:
        got, err = _cli_error(capsys, *args, *(out if "--out" not in args else ()))
        assert (got, words) == (code, words) and words in err, (args, err)
    assert main(["play", "cramped_room", "--port", "70000"]) == 2
    assert "port number" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code, err = _cli_error(capsys, "cramped_room", "--port", str(port), "--out", str(tmp_path / "y.mcap"))
    assert code == 1 and f"port {port} on 127.0.0.1 is in use" in err
    assert sorted(p.name for p in tmp_path.glob("*.mcap*")) == ["left.mcap.partial", "taken.mcap"]  # none created
    assert (tmp_path / "taken.mcap").read_text() == "an earlier recording"


def test_a_tile_size_too_big_is_refused_before_anything_is_drawn(tmp_path, capsys, monkeypatch):
    """Unbounded, ``--tile-size 1500`` took 3.4 GB and 4-8 s a tick, 6000 was killed for memory.

    ``ocv2 play`` and ``ocv2 render`` share one check (``ocv2.render.check_frame_size``): the same
    one-line bound, before any frame is drawn (the drawing functions are replaced by ones that fail, so
    a missing check fails here instead of allocating GBs).
    """
    render_cli = importlib.import_module("cluster.cli.render")
    play_cli = importlib.import_module("cluster.cli.play")

    def drawn(*_args, **_kwargs):
        raise AssertionError("frames were drawn")

    monkeypatch.setattr(play_cli, "make_game", drawn)
    monkeypatch.setattr(render_cli, "rollout_states", drawn)
    out = tmp_path / "x.mcap"
    for tile in ("644", "1500", "6000"):  # cramped_room is 5x4 cells: 643 px a cell is a 4K screen's worth
        code, err = _cli_error(capsys, "cramped_room", "--tile-size", tile, "--out", str(out), "--port", "0")
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"--tile-size {tile}: " in err and "4K screen (3840x2160)" in err and "at most 643" in err, err
        code, err = _cli_error_of(
            "render", capsys, "cramped_room", "--steps", "0", "--tile-size", tile, "--out", str(tmp_path / "x.gif")
        )
        assert code == 2 and len(err.strip().splitlines()) == 1 and "at most 643" in err, err
    assert not list(tmp_path.iterdir())  # no archive, no GIF


def test_the_shared_frame_size_check():
    from ocv2.layouts import LAYOUTS
    from ocv2.render import MAX_FRAME_PIXELS, MAX_FRAMES_BYTES, check_frame_size

    for name in ("cramped_room", "long_room", "grounded_coord_ring"):
        layout = LAYOUTS[name]
        largest = int(str(_refusal(check_frame_size, layout, 10**4)).rsplit(" ", 1)[-1])
        assert layout.width * layout.height * largest**2 <= MAX_FRAME_PIXELS  # only checked: nothing is drawn
        assert layout.width * layout.height * (largest + 1) ** 2 > MAX_FRAME_PIXELS
        check_frame_size(layout, largest)
        assert "at most" in str(_refusal(check_frame_size, layout, largest + 1))
    cramped = LAYOUTS["cramped_room"]
    frames = MAX_FRAMES_BYTES // (20 * 48 * 48 * 3)  # the most 48-px frames of a 5x4 kitchen a GIF holds
    check_frame_size(cramped, 48, frames)
    assert "GiB, over 2 GiB" in str(_refusal(check_frame_size, cramped, 48, frames + 1))
    with pytest.raises(ValueError, match="tile size for cramped_room is at most 643"):
        make_game(ocv2.make("cramped_room"), scripted_partner("stay"), [0], tile_size=644)


def _refusal(check, *args) -> ValueError:
    with pytest.raises(ValueError) as refused:
        check(*args)
    return refused.value


def test_two_quick_sigterms_finish_the_archive_without_an_abort(tmp_path):
    """A second SIGTERM (or Ctrl-C) while `ocv2 play` finishes its archive once left a .partial file behind and
    could abort the interpreter ("FATAL: exception not rethrown", exit 134): it is now held back until the
    file is whole."""
    import signal
    import subprocess
    import sys

    process = subprocess.Popen(
        [sys.executable, "-m", "cluster.cli", "play", "cramped_room", "--port", "0", "--out", str(tmp_path / "p.mcap")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    watchdog = threading.Timer(120, process.kill)
    watchdog.start()
    try:
        output = []
        for line in process.stdout:
            output.append(line)
            if line.startswith("open http"):
                break
        process.send_signal(signal.SIGTERM)
        time.sleep(0.05)
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
        output.append(process.communicate(timeout=60)[0])
    finally:
        watchdog.cancel()
        process.kill()
    text = "".join(output)
    assert process.returncode in (0, 130, -signal.SIGTERM), text  # the second may come after the cleanup
    assert "Traceback" not in text and "terminate called" not in text and "FATAL" not in text, text
    assert not list(tmp_path.iterdir())  # no episode was played: no archive, and no .partial left
