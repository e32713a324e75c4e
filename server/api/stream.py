"""The websocket stream (protocol in :mod:`server.formats.protocol`): odometry and frames on one connection.

The receive loop validates each message and submits it; a sender task awaits each
message's durability future *in message order* and only then sends its ack, so an ack
always means "stored". Validation and storage are pipelined: the robot need not wait for
one ack before sending the next message, while ``max_pending`` bounds what is in flight.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from typing import Any, MutableMapping

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from starlette.websockets import WebSocketState

from hippomap.errors import InputError

from ..formats.ingest import IngestError, parse_odometry_message
from ..formats.protocol import (
    CLOSE_ELSEWHERE,
    CLOSE_FORBIDDEN,
    CLOSE_NOT_FOUND,
    CLOSE_UNAUTHORIZED,
    MessageError,
    parse_text_message,
    unpack_frame,
)
from ..runtime.sessions import Forbidden, LiveSession, NotFound, ServedElsewhere
from ..settings import ServerSettings

router = APIRouter(tags=["ingest"])
log = logging.getLogger("hippomap.server")


def _secret(ws: WebSocket) -> str | None:
    auth = ws.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return ws.query_params.get("token")


async def _sender(ws: WebSocket, out: asyncio.Queue) -> None:
    """Send queued messages in order; an ack waits for its inputs to be durable."""
    while True:
        item = await out.get()
        if item is None:
            return
        if isinstance(item, tuple):  # ("ack", future, id, first, last, count)
            _, fut, mid, first, last, count = item
            try:
                await fut
                msg: dict[str, Any] = {"type": "ack", "id": mid, "seq": first, "last_seq": last, "count": count}
            except Exception as exc:
                msg = {"type": "error", "id": mid, "status": 503, "detail": f"inputs could not be stored: {exc}"}
        else:
            msg = item
        try:
            await ws.send_text(json.dumps(msg))
        except Exception:  # the client went away; inputs already accepted stay stored
            return


async def _handle(live: LiveSession, message: MutableMapping[str, Any], out: asyncio.Queue) -> None:
    """Validate and submit one websocket message; errors are queued as error messages (with the message's id
    once it is known)."""
    mid: Any = None
    settings = live.settings
    try:
        if message.get("bytes") is not None:
            mid, t, image = _unpack(message["bytes"], settings.max_body_bytes)
            items = [await live.validate_frame(image, t)]
        else:
            d = _parse_text(message.get("text") or "", settings)
            mid = _message_id(d)
            kind = d.get("type")
            if kind == "ping":
                await out.put({"type": "pong", "id": mid})
                return
            if kind != "odometry":
                raise IngestError(
                    422, f"unknown message type {kind!r}: expected 'odometry' or 'ping' (frames are binary messages)"
                )
            items = parse_odometry_message(d, settings.max_odometry_batch, settings)

        async def busy() -> None:
            await out.put({"type": "busy", "pending": live.pending, "max_pending": settings.max_pending})

        first, last, fut = await live.submit(items, wait_s=None, on_busy=busy)
        await out.put(("ack", fut, mid, first, last, len(items)))
    except IngestError as exc:
        live.rejected[exc.status] += 1
        await out.put({"type": "error", "id": mid, "status": exc.status, "detail": exc.detail})
    except NotFound:
        raise
    except Exception as exc:  # a bug must cost this message only, never the stream or the server
        log.exception("session %s: websocket message failed", live.id, extra={"session": live.id})
        live.rejected[500] += 1
        detail = f"internal error on this message ({type(exc).__name__}); it was not stored"
        await out.put({"type": "error", "id": mid, "status": 500, "detail": detail})


def _unpack(data: bytes, max_body_bytes: int) -> tuple[int, float, bytes]:
    """A binary frame message: its id, time and image; too large or malformed is an :class:`IngestError`."""
    if len(data) > max_body_bytes:
        raise IngestError(413, f"message of {len(data)} bytes exceeds the limit of {max_body_bytes}")
    try:
        return unpack_frame(data)
    except InputError as exc:
        raise IngestError(422, str(exc)) from None


def _parse_text(text: str, settings: ServerSettings) -> dict[str, Any]:
    """A text message as a JSON object, within the size and nesting limits of ``settings``."""
    try:
        d = parse_text_message(text, settings.max_text_message_bytes, settings.max_json_depth)
    except MessageError as exc:
        raise IngestError(exc.status, exc.detail) from None
    if not isinstance(d, dict):
        raise IngestError(422, "text message must be a JSON object with a 'type'")
    return d


def _message_id(d: dict[str, Any]) -> Any:
    """The message's ``id``, echoed back in its ack or error: only a plain id (a number or a short string)."""
    mid = d.get("id")
    if not (
        mid is None
        or (isinstance(mid, int) and not isinstance(mid, bool))
        or (isinstance(mid, float) and math.isfinite(mid))
        or (isinstance(mid, str) and len(mid) <= 128)
    ):
        raise IngestError(422, "message id must be a number or a string of at most 128 characters")
    return mid


@router.websocket("/sessions/{session_id}/stream")
async def stream(ws: WebSocket, session_id: str) -> None:
    """Odometry (JSON text) and frames (binary) in; ``ack``/``error`` messages out."""
    await ws.accept()
    live = await _open(ws, session_id)
    if live is None:
        return
    await ws.send_text(json.dumps(_hello(live)))
    out: asyncio.Queue = asyncio.Queue()
    sender = asyncio.create_task(_sender(ws, out))
    try:
        deleted = not await _receive(ws, live, out, sender)
        await out.put(None)
        await sender  # acks for everything accepted before the disconnect (or the deletion)
        if deleted:
            await ws.close(CLOSE_NOT_FOUND, f"session {session_id!r} was deleted")
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        if not sender.done():
            sender.cancel()
        if ws.application_state == WebSocketState.CONNECTED and ws.client_state == WebSocketState.CONNECTED:
            try:
                await ws.close()
            except RuntimeError:
                pass


async def _open(ws: WebSocket, session_id: str) -> LiveSession | None:
    """The live session the stream writes to, for the connection's token; ``None`` once the connection is closed
    with the reason (no or unknown token, no such session, a read-only token, served by another worker)."""
    app = ws.app
    token = app.state.auth.authenticate(_secret(ws))
    if token is None:
        await ws.close(CLOSE_UNAUTHORIZED, "missing or unknown bearer token")
        return None
    try:
        return app.state.manager.get(token, session_id, write=True)
    except NotFound:
        await ws.close(CLOSE_NOT_FOUND, f"session {session_id!r} not found")
    except Forbidden:
        await ws.close(CLOSE_FORBIDDEN, "this token is read-only")
    except ServedElsewhere as exc:
        await ws.close(CLOSE_ELSEWHERE, str(exc)[:120])
    return None


def _hello(live: LiveSession) -> dict[str, Any]:
    """The first message: where the session stands, so a reconnecting robot resumes after what is stored."""
    return {
        "type": "hello",
        "session": live.id,
        "last_seq": live.next_seq - 1,
        "last_t": live.last_t,
        "last_odometry_t": live.last_times.get("odometry"),
        "last_frame_t": live.last_times.get("frame"),
        "max_pending": live.settings.max_pending,
    }


async def _receive(ws: WebSocket, live: LiveSession, out: asyncio.Queue, sender: asyncio.Task) -> bool:
    """Read and handle messages at the session's rate until the client disconnects or the sender fails (the
    client is gone): True; False when the session was deleted meanwhile."""
    while True:
        receive = asyncio.ensure_future(ws.receive())
        done, _ = await asyncio.wait({receive, sender}, return_when=asyncio.FIRST_COMPLETED)
        if receive not in done:  # the sender failed: the client is gone
            receive.cancel()
            return True
        message = receive.result()
        if message["type"] == "websocket.disconnect":
            return True
        wait = live.bucket.reserve()
        if wait > 0:  # over the rate: read later (the robot is slowed, nothing dropped)
            await asyncio.sleep(wait)
        try:
            await _handle(live, message, out)
        except NotFound:
            return False
