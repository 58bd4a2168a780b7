"""The browser messages of ``ocv2 play``: what a valid message is (``docs/play.md``, "Message protocol").

Validation only, no state: ``parse_message`` turns request bytes into a ``Message`` or raises
``ProtocolError`` carrying the HTTP status to answer with, so a malformed message is an error reply
and never reaches the game.
"""

from __future__ import annotations

from typing import NamedTuple

from ocv2 import boundedjson
from ocv2 import items as it

ACTIONS = {
    "right": it.Action.RIGHT,
    "down": it.Action.DOWN,
    "left": it.Action.LEFT,
    "up": it.Action.UP,
    "stay": it.Action.STAY,
    "interact": it.Action.INTERACT,
}
MAX_MESSAGE_BYTES = 4096
MAX_TOKEN_CHARS = 64
#: Every message is one flat JSON object; deeper text is refused before anything walks it.
MAX_MESSAGE_DEPTH = 2

# message type -> (required keys, optional keys) besides "type"
_FIELDS = {
    "join": ((), ("seat",)),
    "ready": (("token",), ()),
    "action": (("token", "action"), ()),
    "poll": (("token",), ("since",)),
    "leave": (("token",), ()),
}


class ProtocolError(Exception):
    """A message the session rejects; ``status`` is the HTTP status the server answers with."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


class Message(NamedTuple):
    """One validated browser message."""

    type: str
    token: str | None = None
    action: int | None = None  # an ocv2 action index
    since: int = 0  # poll: the last version the client has
    seat: int | None = None  # join: the seat asked for (None: any free human seat)


def parse_message(body: bytes) -> Message:
    """Validate one message (a JSON object); anything else is a ``ProtocolError``, never a crash."""
    if len(body) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(body)} bytes is over the {MAX_MESSAGE_BYTES}-byte limit", 413)
    try:
        data = boundedjson.loads(body.decode("utf-8"), MAX_MESSAGE_DEPTH)
    except boundedjson.JSONDepthError:
        raise ProtocolError(
            f"message nests deeper than {MAX_MESSAGE_DEPTH} levels; it must be one flat JSON object"
        ) from None
    except (UnicodeDecodeError, ValueError):
        raise ProtocolError("message is not UTF-8 JSON") from None
    if not isinstance(data, dict):
        raise ProtocolError(f"message must be a JSON object, got {type(data).__name__}")
    kind = data.get("type")
    if kind not in _FIELDS:
        raise ProtocolError(f"unknown message type {kind!r}; expected one of {', '.join(_FIELDS)}")
    required, optional = _FIELDS[kind]
    missing = [k for k in required if k not in data]
    extra = sorted(set(data) - set(required) - set(optional) - {"type"})
    if missing or extra:
        raise ProtocolError(f"{kind!r} message: missing {missing}, unexpected {extra}")
    token = data.get("token")
    if token is not None and (not isinstance(token, str) or not 0 < len(token) <= MAX_TOKEN_CHARS):
        raise ProtocolError("token must be the string the join reply gave")
    return Message(
        kind,
        token,
        _action(data["action"]) if kind == "action" else None,
        _non_negative(data.get("since", 0), "since"),
        _seat(data.get("seat")),
    )


def _action(value) -> int:
    if isinstance(value, str) and value in ACTIONS:
        return int(ACTIONS[value])
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < it.NUM_ACTIONS:
        return value
    raise ProtocolError(f"action must be one of {', '.join(ACTIONS)} (or 0..{it.NUM_ACTIONS - 1}), got {value!r}")


def _non_negative(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ProtocolError(f"{name} must be a non-negative integer, got {value!r}")
    return value


def _seat(value) -> int | None:
    return None if value is None else _non_negative(value, "seat")
