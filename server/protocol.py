"""The websocket stream ``/sessions/{id}/stream``: one connection carries odometry and frames.

Client to server:

* **text** — JSON ``{"type": "odometry", "id": 7, "t": 1.5, "v": 0.2, "omega": 0.0}`` (one
  reading, or ``"increment": [dx, dy, dtheta]`` instead of ``v``/``omega``), or
  ``{"type": "odometry", "id": 8, "readings": [{...}, ...]}`` (a batch), or
  ``{"type": "ping", "id": 9}``.
* **binary** — a camera frame: the 16-byte header :data:`FRAME_HEADER` (magic ``b"HMF1"``,
  ``uint32`` message id, ``float64`` timestamp; little-endian) followed by the JPEG (or PNG).

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

The connection is closed with code 4401 (no or bad token), 4403 (read-only token) or 4404 (no such
session).
"""

from __future__ import annotations

import struct

from hippomap.errors import InputError

FRAME_MAGIC = b"HMF1"
FRAME_HEADER = struct.Struct("<4sId")

CLOSE_UNAUTHORIZED = 4401
CLOSE_FORBIDDEN = 4403
CLOSE_NOT_FOUND = 4404
CLOSE_ELSEWHERE = 4421  # the session is run by another replica (HTTP 421)


def pack_frame(message_id: int, t: float, image: bytes) -> bytes:
    """A binary frame message (used by the Python client)."""
    return FRAME_HEADER.pack(FRAME_MAGIC, int(message_id) & 0xFFFFFFFF, float(t)) + image


def unpack_frame(data: bytes) -> tuple[int, float, bytes]:
    """``(message id, t, image bytes)`` of a binary message; InputError on a bad header."""
    if len(data) < FRAME_HEADER.size:
        raise InputError(f"binary message of {len(data)} bytes is shorter than the {FRAME_HEADER.size}-byte frame header")
    magic, mid, t = FRAME_HEADER.unpack_from(data)
    if magic != FRAME_MAGIC:
        raise InputError(f"binary message does not start with the frame magic {FRAME_MAGIC!r} (got {magic!r})")
    return int(mid), float(t), data[FRAME_HEADER.size:]
