"""The HTTP side of ``ocv2 play``: a standard-library server with one page and one JSON endpoint.

    GET  /      the game page (``cluster/play/static/play.html``, package data; no build step)
    POST /api   one JSON message (``docs/play.md``). The answer is JSON: ``{"ok": true, ...}``, or
                ``{"ok": false, "error": "..."}`` with status 400 (malformed), 403 (unknown token),
                409 (seat taken), 413 (too large) or 503 (shutting down)

Why no websockets: the standard library has none, and at a few ticks per second a long poll (the
page asks for anything newer than the version it has; the server answers as soon as there is, or
after a second) is as responsive on one machine or a LAN and needs no dependency. Each request
runs on its own thread; the session's lock serialises them with the clock thread, so a bad or
failing request gets an error answer and the game goes on.
"""

from __future__ import annotations

import json
import socket
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from urllib.parse import urlsplit

from cluster.play.protocol import MAX_MESSAGE_BYTES, ProtocolError, parse_message
from cluster.play.session import GameSession

PAGE = "play.html"
_SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    # One self-contained page: inline script and style, frames as data: URLs, requests to itself only.
    "Content-Security-Policy": "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
                               "img-src data:; connect-src 'self'",
}


def page_html() -> bytes:
    return resources.files("cluster.play").joinpath("static", PAGE).read_bytes()


class _Server(ThreadingHTTPServer):
    daemon_threads = True  # a tab's open keep-alive connection never blocks shutdown

    def __init__(self, address, verbose: bool):
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        self.session: GameSession | None = None  # set by PlayServer.start, before serving
        self.verbose, self.page = verbose, page_html()
        super().__init__(address, _Handler)


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    server_version = "ocv2-play"
    protocol_version = "HTTP/1.1"  # keep-alive: a poll every tick reuses one connection

    def do_GET(self):
        path = urlsplit(self.path).path
        if path in ("/", "/index.html"):
            self._send(200, self.server.page, "text/html; charset=utf-8")
        elif path == "/favicon.ico":
            self._send(204, b"", "image/x-icon")
        else:
            self._json(404, {"ok": False, "error": f"no page {path!r} here; the game is at /"})

    def do_POST(self):
        if urlsplit(self.path).path != "/api":
            self._json(404, {"ok": False, "error": "messages go to POST /api"})
            return
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            self.close_connection = True  # the body's end is unknown: the connection cannot be reused
            self._json(411, {"ok": False, "error": "a message needs a Content-Length"})
            return
        if not 0 <= length <= MAX_MESSAGE_BYTES:
            self.close_connection = True  # not read: the connection cannot be reused
            self._json(413, {"ok": False, "error": f"messages are at most {MAX_MESSAGE_BYTES} bytes"})
            return
        body = self.rfile.read(length)
        try:
            reply = self.server.session.handle(parse_message(body))
        except ProtocolError as error:
            self._json(error.status, {"ok": False, "error": str(error)})
            return
        except Exception as error:  # a bug in one request must not take the game down
            print(f"ocv2 play: request failed: {type(error).__name__}: {error}", file=sys.stderr)
            self._json(500, {"ok": False, "error": f"internal error ({type(error).__name__})"})
            return
        self._json(200, reply)

    def _json(self, status: int, payload: dict):
        self._send(status, json.dumps(payload).encode(), "application/json")

    def _send(self, status: int, body: bytes, content_type: str):
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        for name, value in _SECURITY_HEADERS.items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format, *args):  # noqa: A002 (the base class's name)
        if self.server.verbose:
            super().log_message(format, *args)


class PlayServer:
    """The HTTP server and a session's clock, each on a thread; ``stop`` ends both and the session.

    The constructor binds (an ``OSError`` for a port in use comes before anything slow happens);
    ``start(session)`` starts serving and ticking.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, verbose: bool = False):
        self.http = _Server((host, port), verbose)
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
        return f"http://[{host}]:{self.port}/" if ":" in host else f"http://{host}:{self.port}/"

    def start(self, session: GameSession) -> "PlayServer":
        self.session = self.http.session = session
        self._threads = [threading.Thread(target=session.run, args=(self._stop,), name="ocv2-play-clock", daemon=True),
                         threading.Thread(target=self.http.serve_forever, name="ocv2-play-http", daemon=True)]
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
