"""Map reuse: merge one session into another, and export a session's map for offline reuse.

* ``POST /sessions/{id}/merge {"from": other}`` makes a new session holding ``other``'s run merged
  into ``id``'s map: a new run in a copy of ``id``'s map fed ``other``'s stored inputs (see
  :meth:`server.runtime.sessions.SessionManager.merge`); the recognitions of ``id``'s key frames go through
  the same loop-closure path as every other closure. Neither session changes.
* ``GET /sessions/{id}/snapshot`` is the session's mapper state (``Mapper.to_bytes``): the saved
  map of ``hippomap run DATA --base-map FILE``.

Starting a session from a saved map is ``POST /sessions`` with ``base_session``
(:mod:`server.api.sessions`).
"""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, HTTPException, Request, Response
from pydantic import ConfigDict, Field

from ..formats.ingest import IngestError
from ..formats.schemas import SessionDetail, _In
from ..runtime import model
from ..runtime.sessions import Forbidden
from . import deps
from .sessions import _info, _links

router = APIRouter(prefix="/sessions", tags=["map reuse"])


class MergeRequest(_In):
    model_config = ConfigDict(
        extra="forbid",
        populate_by_name=False,
        json_schema_extra={"examples": [{"from": "0f3c2a9e5b7d4e1f", "name": "second run merged into the first"}]},
    )

    from_: str = Field(
        alias="from",
        max_length=100,
        description="the session whose run is merged into this one's map (one the token can read)",
    )
    name: str = Field("", max_length=200, description="label of the new, merged session")


@router.post(
    "/{session_id}/merge",
    status_code=201,
    response_model=SessionDetail,
    responses={
        **deps.ERRORS,
        403: {"description": "read-only token, or the token's quota is used up"},
        404: {"description": "no such session (path or 'from'), or one this token may not see"},
        422: {"description": "'from' names the session itself"},
    },
    summary="A new session: another session's run merged into this session's map",
)
async def merge_sessions(body: MergeRequest, live: deps.ReadSession, request: Request, tok: deps.Token) -> Any:
    try:
        merged = await deps.manager(request).merge(tok, live, body.from_, body.name)
    except Forbidden:
        raise HTTPException(403, "this token is read-only") from None
    except IngestError as exc:
        raise HTTPException(exc.status, exc.detail) from None
    stats = await asyncio.to_thread(merged.stats)
    return {
        **_info(merged, stats),
        "config": merged.config.model_dump(mode="json"),
        "links": _links(request, merged.id),
    }


@router.get(
    "/{session_id}/snapshot",
    responses={
        **deps.ERRORS,
        200: {
            "content": {"application/octet-stream": {}},
            "description": "the mapper state (npz of arrays and a JSON header)",
        },
    },
    summary="The session's mapper state, for `hippomap run --base-map`",
    response_class=Response,
)
async def session_snapshot(live: deps.ReadSession) -> Response:
    data = await asyncio.to_thread(live.worker.query, model.queries.MapperState())
    if data is None:
        raise HTTPException(503, f"session {live.id} is being restored; retry shortly", headers={"Retry-After": "1"})
    return Response(
        data,
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{live.id}.npz"'},
    )
