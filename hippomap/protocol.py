"""The binary frame message of the websocket stream ``/sessions/{id}/stream``: its one definition.

A camera frame travels as one binary websocket message: the 16-byte header :data:`FRAME_HEADER`
(magic :data:`FRAME_MAGIC` ``b"HMF1"``, ``uint32`` message id, ``float64`` timestamp; little-endian)
followed by the image bytes (JPEG or PNG). The client (:mod:`hippomap.client`) packs it and the
service (``server.formats.protocol``, which re-exports these names) unpacks it, both from this module, so the
two ends cannot drift apart. It lives in the model package because the client does and must not
import the service; it imports nothing but the standard library and :mod:`hippomap.errors`.
"""

from __future__ import annotations

import struct

from .errors import InputError

__all__ = ["FRAME_HEADER", "FRAME_MAGIC", "pack_frame", "unpack_frame"]

#: the first four bytes of every binary frame message
FRAME_MAGIC = b"HMF1"
#: the frame header: magic, message id (uint32), timestamp in seconds (float64); little-endian, 16 bytes
FRAME_HEADER = struct.Struct("<4sId")


def pack_frame(message_id: int, t: float, image: bytes) -> bytes:
    """The binary message carrying ``image`` taken at time ``t`` (the id is taken modulo 2**32)."""
    return FRAME_HEADER.pack(FRAME_MAGIC, int(message_id) & 0xFFFFFFFF, float(t)) + image


def unpack_frame(data: bytes) -> tuple[int, float, bytes]:
    """``(message id, t, image bytes)`` of a binary message; :class:`InputError` naming the problem
    when it is shorter than the header or does not start with :data:`FRAME_MAGIC`."""
    if len(data) < FRAME_HEADER.size:
        raise InputError(
            f"binary message of {len(data)} bytes is shorter than the {FRAME_HEADER.size}-byte frame header"
        )
    magic, mid, t = FRAME_HEADER.unpack_from(data)
    if magic != FRAME_MAGIC:
        raise InputError(f"binary message does not start with the frame magic {FRAME_MAGIC!r} (got {magic!r})")
    return int(mid), float(t), data[FRAME_HEADER.size :]
