"""The service's websockets, documented in its OpenAPI document (which cannot list websockets).

FastAPI leaves websocket routes out of ``/openapi.json``. This module adds them twice:

* :func:`websocket_description` — a Markdown section appended to the API description, so that
  ``/docs`` and ``/redoc`` show the stream's protocol to a person;
* :func:`add_websocket_docs` — an ``x-websockets`` extension at the top of the document, keyed by
  path like ``paths``, with each message's JSON schema (the models ``Ws*`` of
  :mod:`server.formats.schemas`, added to ``components/schemas``), the binary frame header, the close codes
  and this server's message limits, so that a program can read the protocol too.

Both are built from the same constants the stream uses (:mod:`server.formats.protocol`), so they cannot
drift from it silently.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel
from pydantic.json_schema import models_json_schema

from ..formats import schemas
from ..formats.protocol import (
    CLOSE_ELSEWHERE,
    CLOSE_FORBIDDEN,
    CLOSE_NOT_FOUND,
    CLOSE_UNAUTHORIZED,
    FRAME_HEADER,
    FRAME_MAGIC,
)
from ..settings import ServerSettings

STREAM_PATH = "/sessions/{session_id}/stream"
VIEWER_PATH = "/viewer/{session_id}"
REF = "#/components/schemas/{model}"

CLIENT_MESSAGES = (schemas.WsOdometry, schemas.WsOdometryBatch, schemas.WsPing)
SERVER_MESSAGES = (schemas.WsHello, schemas.WsAck, schemas.WsError, schemas.WsBusy, schemas.WsPong)

#: close codes of the stream, and why
CLOSE_CODES: dict[int, str] = {
    CLOSE_UNAUTHORIZED: "no token, an unknown one, or the token was revoked while the stream was open",
    CLOSE_FORBIDDEN: "read-only (viewer) token",
    CLOSE_NOT_FOUND: "no such session, one this token may not see, or the session was deleted",
    CLOSE_ELSEWHERE: "another replica runs the session (HTTP 421): reconnect to the replica named in the reason",
}

#: the binary frame message: header fields in order (little-endian, struct format FRAME_HEADER)
FRAME_FIELDS = [
    {"name": "magic", "type": "4 bytes", "value": FRAME_MAGIC.decode("ascii")},
    {"name": "id", "type": "uint32", "description": "message id, echoed in the ack or error"},
    {"name": "t", "type": "float64", "description": "timestamp, seconds"},
]


def _name(model: type) -> str:
    return model.__name__


def _what(model: type) -> str:
    """A message model's docstring after its "Client → server:" prefix, on one line, as Markdown."""
    return " ".join((model.__doc__ or "").split(":", 1)[-1].split()).replace("``", "`")


def _type(model: type[BaseModel]) -> str:
    """The ``type`` a message model's messages carry (its Literal)."""
    annotation: Any = model.model_fields["type"].annotation  # a Literal on every message model
    return annotation.__args__[0]


def websocket_description() -> str:
    """The Markdown section on the websockets, for the API description."""
    client = "\n".join(f"| text | `{_name(m)}` | {_what(m)} |" for m in CLIENT_MESSAGES)
    server = "\n".join(f"| `{_type(m)}` | `{_name(m)}` | {_what(m)} |" for m in SERVER_MESSAGES)
    closes = "\n".join(f"| {code} | {why} |" for code, why in CLOSE_CODES.items())
    binary = (
        f"| binary | — | a camera frame: the {FRAME_HEADER.size}-byte header `{FRAME_HEADER.format}` "
        f"(magic `{FRAME_MAGIC.decode()}`, uint32 message id, float64 timestamp; little-endian) "
        "followed by the JPEG or PNG bytes |"
    )
    return f"""
## Websockets

OpenAPI lists no websockets: they are described here, and for programs in the document's
`x-websockets` extension (message schemas in `components/schemas`, named below).

### `{STREAM_PATH}`: ingest stream

Open with a writer token (`Authorization: Bearer <token>`, or `?token=` where headers cannot be
set). One connection carries odometry (JSON text messages) and camera frames (binary messages);
every message is acknowledged, in message order, once its inputs are durable. The robot need not
wait for an ack before sending the next message.

| client → server | schema | what |
| --- | --- | --- |
{client}
{binary}

| server → client `type` | schema | what |
| --- | --- | --- |
{server}

Example: `{{"type": "odometry", "id": 7, "t": 12.5, "v": 0.4, "omega": 0.05}}` is answered by
`{{"type": "ack", "id": 7, "seq": 42, "last_seq": 42, "count": 1}}`. A refused message gets an `error`
with the HTTP status it would have had (413 too large, 422 malformed, 409 timestamp not increasing...);
the stream stays open.

| close code | why |
| --- | --- |
{closes}

### `{VIEWER_PATH}`: the live viewer's websocket

Opened by the viewer page `/viewer/{{session_id}}/` itself (viser's protocol, subprotocol
`viser-v<version>`), with the token the page stored in its cookie; closed with 1008 when the token may
not see the session. Not meant for robots.
"""


def add_websocket_docs(document: dict[str, Any], settings: ServerSettings) -> None:
    """Add ``x-websockets`` (and the message schemas in ``components/schemas``) to an OpenAPI document."""
    _, top = models_json_schema([(m, "validation") for m in (*CLIENT_MESSAGES, *SERVER_MESSAGES)], ref_template=REF)
    components = document.setdefault("components", {}).setdefault("schemas", {})
    for name, schema in top.get("$defs", {}).items():
        components.setdefault(name, schema)  # OdometryReading is there already, with this server's bounds
    session_id = {
        "name": "session_id",
        "in": "path",
        "required": True,
        "schema": {"type": "string"},
        "description": "session id",
    }
    document["x-websockets"] = {
        STREAM_PATH: _stream_doc(settings, session_id),
        VIEWER_PATH: {
            "summary": "The live viewer's websocket (viser protocol, proxied); opened by /viewer/{session_id}/",
            "tags": ["viewer"],
            "parameters": [session_id],
            "subprotocol": "viser-v<version>",
            "close_codes": {"1008": "no token, or one that may not see the session"},
        },
    }


def _one_of(models: tuple[type, ...]) -> dict[str, Any]:
    """A schema that is one of ``models`` (references to their schemas in ``components/schemas``)."""
    return {"oneOf": [{"$ref": REF.format(model=_name(m))} for m in models]}


def _stream_doc(settings: ServerSettings, session_id: dict[str, Any]) -> dict[str, Any]:
    """The ingest stream's entry: its parameters, the messages each way, this server's limits, the close codes."""
    return {
        "summary": "Ingest stream: odometry (JSON text) and camera frames (binary) in, acks out",
        "tags": ["ingest"],
        "parameters": [
            session_id,
            {
                "name": "token",
                "in": "query",
                "required": False,
                "schema": {"type": "string"},
                "description": "the token, where the client cannot set Authorization: Bearer",
            },
        ],
        "security": [{"HTTPBearer": []}],
        "client_messages": {
            "text": _one_of(CLIENT_MESSAGES),
            "binary": {
                "description": "a camera frame: header then JPEG or PNG bytes",
                "header_struct": FRAME_HEADER.format,
                "header_bytes": FRAME_HEADER.size,
                "header": FRAME_FIELDS,
                "max_bytes": settings.max_body_bytes,
            },
        },
        "server_messages": {
            **_one_of(SERVER_MESSAGES),
            "discriminator": {
                "propertyName": "type",
                "mapping": {_type(m): REF.format(model=_name(m)) for m in SERVER_MESSAGES},
            },
        },
        "limits": {
            "max_text_message_chars": settings.max_text_message_bytes,
            "max_json_depth": settings.max_json_depth,
            "max_odometry_batch": settings.max_odometry_batch,
            "max_pending": settings.max_pending,
        },
        "close_codes": {str(code): why for code, why in CLOSE_CODES.items()},
    }
