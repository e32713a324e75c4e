"""HTTP ingest: odometry batches and single frames (raw body or multipart)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, HTTPException, Query, Request
from starlette.datastructures import UploadFile

from ..formats.ingest import Accepted, IngestError, check_odometry
from ..formats.schemas import IngestAck, OdometryBatch, OdometryReading
from ..runtime.sessions import LiveSession, NotFound
from . import deps
from .docs import EXAMPLE_FRAME_URLS

router = APIRouter(prefix="/sessions/{session_id}", tags=["ingest"])

INGEST_ERRORS: dict[int | str, dict[str, Any]] = {
    **deps.WRITE_ERRORS,
    409: {"description": "timestamp does not exceed the session's last input"},
    413: {"description": "body, frame, image dimensions or batch too large"},
    415: {"description": "frame is not a JPEG or PNG"},
    422: {"description": "malformed or non-finite values, corrupt image"},
    429: {"description": "rate limit exceeded, or the mapper queue is full (retry after a moment)"},
    503: {"description": "the session's worker stopped (see stats.error)"},
}


async def accept(live: LiveSession, items: list[Accepted], wait_s: float) -> dict[str, Any]:
    """Store validated inputs; returns once they are durable."""
    try:
        first, last, fut = await live.submit(items, wait_s)
    except IngestError as exc:
        live.rejected[exc.status] += 1
        headers = None if exc.retry_after is None else {"Retry-After": str(int(exc.retry_after))}
        raise HTTPException(exc.status, exc.detail, headers=headers) from None
    except NotFound:
        raise HTTPException(404, f"session {live.id!r} not found") from None
    try:
        await fut
    except Exception as exc:
        raise HTTPException(503, f"inputs could not be stored: {exc}") from None
    return {"session": live.id, "seq": first, "last_seq": last, "count": len(items)}


#: request examples of POST /sessions/{id}/odometry (shown by /docs and /redoc)
ODOMETRY_EXAMPLES: dict[str, dict[str, Any]] = {
    "velocities": {
        "summary": "one reading: velocities held since the previous reading",
        "value": {"t": 12.5, "v": 0.4, "omega": 0.05},
    },
    "increment": {
        "summary": "one reading: a pose increment in the previous pose's frame",
        "value": {"t": 12.55, "increment": [0.02, 0.0, 0.0025]},
    },
    "ground truth": {
        "summary": "one reading with the simulator's ground-truth pose (drawn by the viewer only)",
        "value": {"t": 12.6, "v": 0.4, "omega": 0.0, "gt": [3.1, -0.4, 1.57]},
    },
    "batch": {
        "summary": "a batch, acknowledged together",
        "value": {"readings": [{"t": 12.65, "v": 0.4, "omega": 0.05}, {"t": 12.7, "v": 0.4, "omega": 0.04}]},
    },
}


@router.post(
    "/odometry",
    response_model=IngestAck,
    responses=INGEST_ERRORS,
    summary="Odometry: one reading or a batch; acknowledged once stored",
)
async def post_odometry(
    live: deps.WriteSession,
    request: Request,
    body: Annotated[OdometryBatch | OdometryReading, Body(openapi_examples=ODOMETRY_EXAMPLES)],
) -> Any:
    readings = body.readings if isinstance(body, OdometryBatch) else [body]
    try:
        items = check_odometry(readings, live.settings.max_odometry_batch, live.settings)
    except IngestError as exc:
        live.rejected[exc.status] += 1
        raise HTTPException(exc.status, exc.detail) from None
    return await accept(live, items, live.settings.backpressure_wait_s)


_FRAME_BODY = {
    "required": True,
    "content": {
        # binary bodies: the examples are real files the service serves (an OpenAPI externalValue)
        "image/jpeg": {
            "schema": {"type": "string", "format": "binary"},
            "examples": {
                "frame": {
                    "summary": "a 320x240 camera frame, sent with ?t=12.5",
                    "externalValue": EXAMPLE_FRAME_URLS["jpeg"],
                }
            },
        },
        "image/png": {
            "schema": {"type": "string", "format": "binary"},
            "examples": {
                "frame": {
                    "summary": "a 320x240 camera frame, sent with ?t=12.5",
                    "externalValue": EXAMPLE_FRAME_URLS["png"],
                }
            },
        },
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": ["t", "image"],
                "properties": {
                    "t": {"type": "number", "description": "timestamp, seconds"},
                    "image": {"type": "string", "format": "binary", "description": "JPEG or PNG"},
                },
            }
        },
    },
}


@router.post(
    "/frames",
    response_model=IngestAck,
    responses=INGEST_ERRORS,
    openapi_extra={"requestBody": _FRAME_BODY},
    summary="A camera frame: raw JPEG/PNG body with ?t=, or multipart (t, image)",
)
async def post_frame(
    live: deps.WriteSession, request: Request, t: float | None = Query(None, description="timestamp (raw body uploads)")
) -> Any:
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    t_value: str | float | None
    try:
        if ctype == "multipart/form-data":
            form = await request.form(max_files=1, max_fields=8)
            image, t_form = form.get("image"), form.get("t")
            if not isinstance(image, UploadFile):
                raise IngestError(422, "multipart frame needs a file field 'image'")
            if t_form is None or isinstance(t_form, UploadFile):
                raise IngestError(422, "multipart frame needs a field 't' (timestamp)")
            data, t_value = await image.read(), t_form
        elif ctype in ("image/jpeg", "image/png", "application/octet-stream", ""):
            data, t_value = await request.body(), t
            if t_value is None:
                raise IngestError(422, "frame timestamp missing: pass ?t=<seconds>")
        else:
            raise IngestError(
                415, f"unsupported content type {ctype!r}: send image/jpeg, image/png or multipart/form-data"
            )
        item = await live.validate_frame(data, t_value)
    except IngestError as exc:
        live.rejected[exc.status] += 1
        raise HTTPException(exc.status, exc.detail) from None
    return await accept(live, [item], live.settings.backpressure_wait_s)
