"""The HTTP side of ``ocv2 play``: a standard-library server with one page and one JSON endpoint.

    GET  /?key=K      the game page (``cluster/play/static/play.html``, package data; no build step)
    POST /api?key=K   one JSON message (``docs/play.md``). The answer is JSON: ``{"ok": true, ...}``, or
                      ``{"ok": false, "error": "..."}`` with status 400 (malformed), 403 (refused: see
                      below, or an unknown player token), 409 (seat taken), 413 (too large),
                      415 (not ``application/json``) or 503 (shutting down, or the player slots full)

Only the person given the printed URL drives the game, not any web page their browser has open:

* ``K`` is a per-launch secret (``secrets.token_urlsafe``) in the printed URL; the page passes it on.
* The ``Host`` header must name the bound address (a loopback name for a loopback or wildcard bind; an
  IP literal or this machine's name for a wildcard bind) and the port: a DNS-rebinding page's
  requests carry its own domain name and are refused.
* An ``Origin`` header, when present (browsers send one with every POST), must be ``http://`` + Host:
  another page's requests are refused even though a "simple" POST needs no CORS preflight.
* ``POST /api`` must say ``Content-Type: application/json``: a cross-site form or ``text/plain`` fetch
  cannot, without a preflight this server never grants.
* A new connection is *pending* until a request on it shows the key: it has ``head_timeout`` seconds
  (from being accepted) to deliver that request's line and headers, and it takes no player slot. At
  most ``max_pending`` pending connections are open; a new one closes the oldest, so connections that
  never show the key cannot lock out a browser, whose request follows its connection at once.
* A connection whose request showed the key takes one of ``max_connections`` player slots for the
  rest of its life (a full house answers 503 and closes). It gets ``request_timeout`` seconds to
  deliver each request (however slowly it trickles; an idle keep-alive connection counts as slow).
  Every connection has a thread, so threads are bounded by the two caps. A client that goes away
  mid-answer costs one log line, not a traceback.

Why no websockets: the standard library has none, and at a few ticks per second a long poll (the
page asks for anything newer than the version it has; the server answers as soon as there is, or
after a second) is as responsive on one machine or a LAN and needs no dependency. The session's
lock serialises the request threads with the clock thread, so a bad or failing request gets an
error answer and the game goes on.
"""

from __future__ import annotations

import hmac
import io
import ipaddress
import json
import logging
import secrets
import socket
import sys
import threading
import time
from collections import OrderedDict
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import parse_qs, urlsplit

from cluster.play.protocol import MAX_MESSAGE_BYTES, ProtocolError, parse_message
from cluster.play.session import GameSession

log = logging.getLogger(__name__)

PAGE = "play.html"
REQUEST_TIMEOUT_S = 10.0  # a player's connection, to deliver one whole request; the page's take milliseconds
HEAD_TIMEOUT_S = 2.0  # a new connection, to deliver its first request head: a browser sends it on connecting
WRITE_TIMEOUT_S = 10.0  # to take one answer (a few KiB: normally the socket buffer takes it at once)
MAX_CONNECTIONS = 32  # player slots (connections that showed the key): two players' tabs use about six each
MAX_PENDING = 64  # new connections that have not shown the key yet; one more closes the oldest
_LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
_SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",  # the page's URL holds the key
    # One self-contained page: inline script and style, frames as data: URLs, requests to itself only.
    "Content-Security-Policy": "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
    "img-src data:; connect-src 'self'",
}


def page_html() -> bytes:
    return resources.files("cluster.play").joinpath("static", PAGE).read_bytes()


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def _is_wildcard(host: str) -> bool:
    return host in ("", "0.0.0.0", "::")


def host_names(bound: str) -> frozenset[str]:
    """The host names (lower case) a request may address a server bound to ``bound`` by."""
    names = {bound.lower()}
    loopback = bound.lower() == "localhost" or (_is_ip(bound) and ipaddress.ip_address(bound).is_loopback)
    if loopback or _is_wildcard(bound):
        names |= _LOOPBACK_NAMES
    if _is_wildcard(bound):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    return frozenset(names)


class _DeadlineSocketIO(socket.SocketIO):
    """A socket reader whose every ``recv`` waits only until the request's deadline.

    A plain socket timeout bounds each ``recv``, so a client trickling one byte per timeout keeps a
    thread forever (slowloris); arming the timeout with the time left bounds the whole request.
    """

    def __init__(self, sock: socket.socket):
        super().__init__(sock, "rb")
        self.deadline = time.monotonic() + REQUEST_TIMEOUT_S

    def readinto(self, buffer) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request did not arrive in time")
        self._sock.settimeout(left)
        return super().readinto(buffer)


class _Server(ThreadingHTTPServer):
    daemon_threads = True  # a tab's open keep-alive connection never blocks shutdown ...
    block_on_close = False  # ... nor does server_close wait for it (its thread ends at its timeout)
    # A burst of connects (a flood, or a browser opening several) must not overflow the kernel's accept
    # queue (socketserver's default is 5): a dropped connect costs the client a one-second retry.
    request_queue_size = 128

    def __init__(
        self,
        address,
        verbose: bool,
        key: str,
        request_timeout: float,
        max_connections: int,
        head_timeout: float,
        max_pending: int,
    ):
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        self.session: GameSession | None = None  # set by PlayServer.start, before serving
        self.verbose, self.page, self.key = verbose, page_html(), key
        self.request_timeout, self.head_timeout = float(request_timeout), float(head_timeout)
        self.max_connections, self.max_pending = int(max_connections), int(max_pending)
        self._lock = threading.Lock()
        # Every open connection is in one of these (or, for the moment of a refusal or an eviction, none).
        self._pending: OrderedDict[socket.socket, None] = OrderedDict()  # no key shown yet; oldest first
        self._players: set[socket.socket] = set()  # showed the key: the ``max_connections`` slots
        self._evicting = self._refusing = False  # a flood is logged once, not once per connection
        super().__init__(address, _Handler)
        self.hosts = host_names(address[0]) | host_names(self.server_address[0])  # as given, and as bound
        self.wildcard = _is_wildcard(address[0])

    @property
    def pending_connections(self) -> int:
        return len(self._pending)

    @property
    def player_connections(self) -> int:
        return len(self._players)

    def host_allowed(self, header: str | None) -> bool:
        """``Host`` names this server: an allowed name (any IP literal on a wildcard bind) and its port."""
        if not header:
            return False
        try:
            parts = urlsplit("//" + header)
            name, port = parts.hostname, parts.port or 80
        except ValueError:
            return False
        if not name or parts.username is not None or parts.path or port != self.server_address[1]:
            return False
        return name in self.hosts or (self.wildcard and _is_ip(name))

    def process_request(self, request, client_address):
        """Serve a new connection as pending; with ``max_pending`` already pending, close the oldest.

        Closing the oldest rather than refusing the newest: a browser's request arrives right after
        its connection, so it shows the key long before ``max_pending`` newer connections push it out,
        while connections that never show the key only ever push each other out.
        """
        with self._lock:
            oldest = self._pending.popitem(last=False)[0] if len(self._pending) >= self.max_pending else None
            if oldest is not None:
                # Under the lock: a thread closes its socket only after leaving ``_pending`` (``_release``).
                self._shut(oldest)
            self._pending[request] = None
        if oldest is None:
            self._evicting = False
        elif not self._evicting:
            self._evicting = True
            log.warning(
                "ocv2 play: %d connections have not shown the key; closing the oldest for each new one",
                self.max_pending,
            )
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._release(request)
            raise

    def process_request_thread(self, request, client_address):
        # ThreadingMixIn's, with the connection released before its socket is closed (see process_request).
        try:
            self.finish_request(request, client_address)
        except Exception:
            self.handle_error(request, client_address)
        finally:
            self._release(request)
            self.shutdown_request(request)

    def admit(self, request) -> str:
        """A pending connection showed the key: ``"player"`` (it has a slot), ``"full"`` or ``"closed"``."""
        with self._lock:
            if request not in self._pending:
                return "closed"  # pushed out by newer connections meanwhile: its socket is shut
            del self._pending[request]
            if len(self._players) >= self.max_connections:
                full = True
            else:
                self._players.add(request)
                full = False
        if not full:
            self._refusing = False
        elif not self._refusing:
            self._refusing = True
            log.warning("ocv2 play: %d connections with the key are open; refusing more", self.max_connections)
        return "full" if full else "player"

    def _release(self, request) -> None:
        with self._lock:
            self._pending.pop(request, None)
            self._players.discard(request)

    @staticmethod
    def _shut(request) -> None:
        """End a connection another thread serves: its blocked read returns end-of-file at once."""
        try:
            request.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def handle_error(self, request, client_address):
        error = sys.exc_info()[1]
        if isinstance(error, (ConnectionError, TimeoutError)):  # the client went away: nothing to debug
            log.info("ocv2 play: connection from %s ended mid-request (%s)", client_address[0], type(error).__name__)
            return
        super().handle_error(request, client_address)


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    server_version = "ocv2-play"
    protocol_version = "HTTP/1.1"  # keep-alive: a poll every tick reuses one connection

    def setup(self):
        super().setup()
        self.rfile.close()  # the plain reader is replaced by one that keeps the request deadline
        self._reader = _DeadlineSocketIO(self.connection)
        self.rfile = io.BufferedReader(self._reader)
        # Pending until a request shows the key: its line and headers must come within the short deadline.
        self.pending = True
        self._reader.deadline = time.monotonic() + self.server.head_timeout

    def handle_one_request(self):
        self._started = time.monotonic()
        if not self.pending:
            # The deadline covers the wait for the request line too: an idle keep-alive connection is closed.
            self._reader.deadline = self._started + self.server.request_timeout
        super().handle_one_request()

    def parse_request(self) -> bool:
        """Read the headers; a pending connection showing the key becomes a player's (or is refused)."""
        if not super().parse_request():
            return False
        if not self.pending:
            return True
        if not self._key_given():
            # Answered (403, 404, the favicon's 204) and closed: a keyless connection never takes a slot.
            self.close_connection = True
            return True
        admitted = self.server.admit(self.connection)
        if admitted == "closed":
            self.close_connection = True
            return False
        if admitted == "full":
            self._reject(503, f"the server is serving {self.server.max_connections} connections; try again later")
            return False
        self.pending = False
        self._reader.deadline = self._started + self.server.request_timeout  # the body: a player's deadline
        return True

    def do_GET(self):
        if self._refused():
            return
        path = urlsplit(self.path).path
        if path == "/favicon.ico":
            self._send(204, b"", "image/x-icon")
        elif path not in ("/", "/index.html"):
            self._json(404, {"ok": False, "error": f"no page {path!r} here; the game is at /"})
        elif not self._key_given():
            self._send(
                403,
                b"ocv2 play: open the whole address 'ocv2 play' printed (it ends with ?key=...)\n",
                "text/plain; charset=utf-8",
            )
        else:
            self._send(200, self.server.page, "text/html; charset=utf-8")

    def do_POST(self):
        if self._refused():
            return
        if urlsplit(self.path).path != "/api":
            self._reject(404, "messages go to POST /api")
            return
        if not self._key_given():
            self._reject(403, "missing or wrong key: open the whole address 'ocv2 play' printed")
            return
        if _media_type(self.headers.get("Content-Type")) != "application/json":
            self._reject(415, "a message must be sent as Content-Type: application/json")
            return
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            self._reject(411, "a message needs a Content-Length")
            return
        if not 0 <= length <= MAX_MESSAGE_BYTES:
            self._reject(413, f"messages are at most {MAX_MESSAGE_BYTES} bytes")
            return
        body = self.rfile.read(length)
        try:
            reply = self.server.session.handle(parse_message(body))
        except ProtocolError as error:
            self._json(error.status, {"ok": False, "error": str(error)})
            return
        except Exception as error:  # a bug in one request must not take the game down
            log.error("ocv2 play: request failed: %s: %s", type(error).__name__, error)
            self._json(500, {"ok": False, "error": f"internal error ({type(error).__name__})"})
            return
        self._json(200, reply)

    def _refused(self) -> bool:
        """Refuse (403) a request not addressed to this server by its own name, or sent by another page."""
        host, origin = self.headers.get("Host"), self.headers.get("Origin")
        if not self.server.host_allowed(host):
            self._reject(403, f"Host {host!r} is not this server's address")
            return True
        if origin is not None and origin.lower() != f"http://{host}".lower():
            self._reject(403, f"requests from {origin!r} are not accepted; only the game page's own")
            return True
        return False

    def _key_given(self) -> bool:
        given = parse_qs(urlsplit(self.path).query).get("key", [""])[-1]
        return hmac.compare_digest(given.encode(), self.server.key.encode())

    def _reject(self, status: int, error: str):
        self.close_connection = True  # the body (if any) is not read: the connection cannot be reused
        self._json(status, {"ok": False, "error": error})

    def _json(self, status: int, payload: dict):
        self._send(status, json.dumps(payload).encode(), "application/json")

    def _send(self, status: int, body: bytes, content_type: str):
        self.connection.settimeout(WRITE_TIMEOUT_S)  # the read deadline must not cut the answer
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        for name, value in _SECURITY_HEADERS.items():
            self.send_header(name, value)
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format, *args):  # noqa: A002 (the base class's name)
        # The base class writes every request to stderr; here they are log records, shown with --verbose.
        if self.server.verbose:
            log.info("%s - %s", self.address_string(), format % args)


def _media_type(header: str | None) -> str:
    """``application/json`` of ``application/json; charset=utf-8`` (lower case; "" when absent)."""
    return (header or "").split(";", 1)[0].strip().lower()


class PlayServer:
    """The HTTP server and a session's clock, each on a thread; ``stop`` ends both and the session.

    The constructor binds (an ``OSError`` for a port in use comes before anything slow happens) and
    draws the per-launch ``key`` (``url`` carries it); ``start(session)`` starts serving and ticking.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        verbose: bool = False,
        *,
        request_timeout: float = REQUEST_TIMEOUT_S,
        max_connections: int = MAX_CONNECTIONS,
        head_timeout: float = HEAD_TIMEOUT_S,
        max_pending: int = MAX_PENDING,
    ):
        self.key = secrets.token_urlsafe(16)
        self.http = _Server(
            (host, port), verbose, self.key, request_timeout, max_connections, head_timeout, max_pending
        )
        self.session: GameSession | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def port(self) -> int:
        return self.http.server_address[1]

    @property
    def url(self) -> str:
        host = self.http.server_address[0]
        host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)  # every interface: loopback is one of them
        address = f"[{host}]:{self.port}" if ":" in host else f"{host}:{self.port}"
        return f"http://{address}/?key={self.key}"

    def start(self, session: GameSession) -> PlayServer:
        self.session = self.http.session = session
        self._threads = [
            threading.Thread(target=session.run, args=(self._stop,), name="ocv2-play-clock", daemon=True),
            threading.Thread(target=self.http.serve_forever, name="ocv2-play-http", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        return self

    def stop(self, reason: str = "server stopped") -> None:
        """Stop ticking, record the episode in progress (cut short), answer waiting polls, stop serving.

        Safe to call before ``start`` (it then only closes the socket) and twice.
        """
        self._stop.set()
        if self._threads:
            clock, http = self._threads
            clock.join()
            self.session.close(reason)
            if http.is_alive():
                self.http.shutdown()
            self._threads = []
        self.http.server_close()
