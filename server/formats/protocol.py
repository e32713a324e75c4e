"""The websocket stream ``/sessions/{id}/stream``: one connection carries odometry and frames.

Client to server:

* **text** — JSON ``{"type": "odometry", "id": 7, "t": 1.5, "v": 0.2, "omega": 0.0}`` (one
  reading, or ``"increment": [dx, dy, dtheta]`` instead of ``v``/``omega``), or
  ``{"type": "odometry", "id": 8, "readings": [{...}, ...]}`` (a batch), or
  ``{"type": "ping", "id": 9}``.
* **binary** — a camera frame: the 16-byte header :data:`FRAME_HEADER` (magic ``b"HMF1"``,
  ``uint32`` message id, ``float64`` timestamp; little-endian) followed by the JPEG (or PNG).
  The format is defined once, in :mod:`hippomap.protocol` (the client packs frames with it);
  this module re-exports its names for the service.

Server to client (all JSON text):

* ``{"type": "hello", "session": ..., "last_seq": ..., "last_t": ..., "last_odometry_t": ...,
  "last_frame_t": ..., "max_pending": ...}`` on connect (the next odometry reading / frame must be
  later than ``last_odometry_t`` / ``last_frame_t`` — lets a robot resume);
* ``{"type": "ack", "id": 7, "seq": 41, "last_seq": 41, "count": 1}`` once the message's inputs are
  durable (``seq``..``last_seq`` are their sequence numbers in the session); acks come in message order;
* ``{"type": "error", "id": 7, "status": 422, "detail": "odometry v must be finite, got nan"}`` for a
  rejected message (same status codes as HTTP); nothing of it was stored, the stream stays open;
* ``{"type": "busy", "pending": 256, "max_pending": 256}`` when the mapper's queue is full: the server
  stops reading until there is room again (the robot is slowed, never dropped);
* ``{"type": "pong", "id": 9}``.

Every text message is parsed with bounded cost: longer than ``max_text_message_bytes`` or nested
deeper than ``max_json_depth`` (checked by a linear scan before any parsing) and it is refused
with a 413 / 422 error naming the problem; the stream stays open.

The connection is closed with code 4401 (no or bad token), 4403 (read-only token) or 4404 (no such
session).
"""

from __future__ import annotations

import json
import re
from typing import Any

import numpy as np

# the binary frame format, shared with the client (re-exported: server.api uses these names from here)
from hippomap.protocol import FRAME_HEADER as FRAME_HEADER
from hippomap.protocol import FRAME_MAGIC as FRAME_MAGIC
from hippomap.protocol import pack_frame as pack_frame
from hippomap.protocol import unpack_frame as unpack_frame

CLOSE_UNAUTHORIZED = 4401
CLOSE_FORBIDDEN = 4403
CLOSE_NOT_FOUND = 4404
CLOSE_ELSEWHERE = 4421  # the session is run by another replica (HTTP 421)


_STEP = np.zeros(256, dtype=np.int32)
_STEP[[0x5B, 0x7B]] = 1  # [ {
_STEP[[0x5D, 0x7D]] = -1  # ] }
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"?', re.DOTALL)


def json_depth(text: str) -> int:
    """Deepest nesting of ``[``/``{`` in a JSON text, ignoring brackets inside strings: one linear
    pass in C (regex + numpy), so a hostile message costs no more than its length."""
    if "[" not in text and "{" not in text:  # e.g. a number, or a string without brackets
        return 0
    data = _STRING.sub("", text).encode("utf-8", "surrogatepass")
    if not data:
        return 0
    step = _STEP[np.frombuffer(data, dtype=np.uint8)]
    return int(np.cumsum(step, dtype=np.int32).max(initial=0))


def parse_text_message(text: str, max_chars: int, max_depth: int) -> Any:
    """The JSON value of a websocket text message, with bounded cost. Raises :class:`MessageError`
    (status 413 or 422, a message naming the problem) for a message too long, nested too deep or
    not JSON; never anything else."""
    if len(text) > max_chars:
        raise MessageError(413, f"text message of {len(text)} characters exceeds the limit of {max_chars}")
    # a text with at most max_depth brackets cannot nest deeper than that: the scan is for the others
    if text.count("[") + text.count("{") > max_depth:
        depth = json_depth(text)
        if depth > max_depth:
            raise MessageError(422, f"text message nested {depth} levels deep exceeds the limit of {max_depth}")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise MessageError(422, f"text message is not JSON: {exc}") from None


class MessageError(ValueError):
    """A websocket message refused before interpretation: ``status`` (413, 422) and why."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
