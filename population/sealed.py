"""Files whose every byte is under a checksum: checkpoints and exported policies.

A sealed file is one msgpack map ``{"format", "version", "sha256", "body"}``: ``body`` is the msgpack
bytes of the content (metadata and arrays alike) and ``sha256`` its SHA-256. Damage anywhere is
refused: in ``body`` by the checksum, in the checksum itself by the mismatch, in the frame (keys,
lengths, ``format``, ``version``) because the map no longer reads as a sealed file of the expected
kind. Checking happens before anything of the content is decoded.
"""

from __future__ import annotations

import hashlib

import msgpack
from flax import serialization


class SealError(ValueError):
    """A sealed file that is damaged or of another kind; the message says what (the caller adds the file)."""


def seal(format_name: str, version: int, content: dict) -> bytes:
    """The file bytes of ``content`` (msgpack-able: flax serializes numpy arrays) under a checksum."""
    body = serialization.msgpack_serialize(content)
    # msgpack itself, not flax (whose tree_map sorts keys): the body stays last, so damage near the
    # file's end lands in the body and reads as a checksum mismatch.
    return msgpack.packb(
        {"format": format_name, "version": version, "sha256": hashlib.sha256(body).hexdigest(), "body": body},
        use_bin_type=True,
    )


def is_sealed(payload) -> bool:
    """Whether a restored top-level map has the sealed frame (it may still fail ``unseal``)."""
    return isinstance(payload, dict) and "body" in payload and "sha256" in payload


def unseal(payload: dict, format_name: str, version: int) -> dict:
    """The content of a restored sealed map, checked: its kind, its version and its checksum."""
    if payload.get("format") != format_name:
        raise SealError(f"not an {format_name} file (format {payload.get('format')!r})")
    if payload.get("version") != version:
        raise SealError(f"{format_name} version {payload.get('version')!r}; this ocv2 reads version {version}")
    body = payload["body"]
    if not isinstance(body, bytes) or hashlib.sha256(body).hexdigest() != payload["sha256"]:
        raise SealError("checksum mismatch (the file was damaged after it was written)")
    try:
        content = serialization.msgpack_restore(body)
    except Exception as error:  # noqa: BLE001 -- checksummed yet unreadable: written by something else
        raise SealError(f"unreadable content ({type(error).__name__})") from None
    if not isinstance(content, dict):
        raise SealError(f"content is a {type(content).__name__}, not a map")
    return content


__all__ = ["SealError", "is_sealed", "seal", "unseal"]
