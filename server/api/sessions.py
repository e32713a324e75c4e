"""Sessions: create (with validated config overrides), list, get, delete, stats."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, HTTPException, Request, Response

from ..formats.ingest import IngestError
from ..formats.schemas import SessionCreate, SessionDetail, SessionInfo, Stats
from ..runtime.sessions import Forbidden, LiveSession, NotFound
from ..storage.store import SessionRecord
from . import deps

router = APIRouter(prefix="/sessions", tags=["sessions"])


def _record_info(r: SessionRecord, stats: dict[str, Any] | None, replica: str) -> dict[str, Any]:
    return {
        "id": r.id,
        "name": r.name,
        "created": r.created,
        "config_overrides": r.config,
        "stats": stats,
        "replica": replica,
    }


def _info(live: LiveSession, stats: dict[str, Any]) -> dict[str, Any]:
    return _record_info(live.record, stats, live.replica)


def _links(request: Request, sid: str) -> dict[str, str]:
    base = str(request.base_url).rstrip("/") + f"/sessions/{sid}"
    return {
        "self": base,
        "stats": f"{base}/stats",
        "odometry": f"{base}/odometry",
        "frames": f"{base}/frames",
        "stream": base.replace("http", "ws", 1) + "/stream",
        "map": f"{base}/map",
        "loop_closures": f"{base}/loop-closures",
        "place_field": f"{base}/place-field",
        "events": f"{base}/events",
        "viewer": str(request.base_url).rstrip("/") + f"/viewer/{sid}/",
    }


@router.post(
    "",
    status_code=201,
    response_model=SessionDetail,
    responses={
        **deps.ERRORS,
        404: {"description": "no such base_session, or one this token may not see"},
        403: {"description": "read-only token, or the token's grid-cell memory quota is used up"},
        422: {"description": "invalid config overrides, or outside the server's safe ranges"},
        429: {"description": "the token owns max_sessions_per_token sessions already"},
    },
    summary="Create a session (its own mapper, configured by overrides)",
)
async def create_session(body: SessionCreate, request: Request, tok: deps.Token) -> Any:
    try:
        live = await deps.manager(request).create(tok, body.name, body.config, body.base_session)
    except Forbidden:
        raise HTTPException(403, "this token is read-only") from None
    except IngestError as exc:
        raise HTTPException(exc.status, exc.detail) from None
    stats = await asyncio.to_thread(live.stats)
    return {**_info(live, stats), "config": live.config.model_dump(mode="json"), "links": _links(request, live.id)}


@router.get("", response_model=list[SessionInfo], responses=deps.ERRORS, summary="Sessions visible to this token")
async def list_sessions(request: Request, tok: deps.Token) -> Any:
    manager = deps.manager(request)
    lives = manager.visible(tok)
    stats = await asyncio.gather(*(asyncio.to_thread(s.stats) for s in lives))
    # replicas sharing the database: the token's sessions that other replicas run, without stats
    elsewhere = await asyncio.to_thread(manager.visible_elsewhere, tok)
    return [_info(s, st) for s, st in zip(lives, stats)] + [_record_info(r, None, owner) for r, owner in elsewhere]


@router.get("/{session_id}", response_model=SessionDetail, responses=deps.ERRORS, summary="One session")
async def get_session(live: deps.ReadSession, request: Request) -> Any:
    stats = await asyncio.to_thread(live.stats)
    return {**_info(live, stats), "config": live.config.model_dump(mode="json"), "links": _links(request, live.id)}


@router.delete(
    "/{session_id}",
    status_code=204,
    responses=deps.WRITE_ERRORS,
    summary="Delete a session and everything stored for it",
)
async def delete_session(live: deps.WriteSession, request: Request, tok: deps.Token) -> Response:
    try:
        await deps.manager(request).delete(tok, live.id)
    except NotFound:
        raise HTTPException(404, f"session {live.id!r} not found") from None
    return Response(status_code=204)


@router.get(
    "/{session_id}/stats",
    response_model=Stats,
    responses=deps.ERRORS,
    summary="Progress (stored / processed / pending inputs, snapshot) and the mapper's statistics",
)
async def session_stats(live: deps.ReadSession) -> Any:
    return await asyncio.to_thread(live.stats)
