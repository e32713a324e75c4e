"""Shared dependencies of the routes: the caller's token, the session it names, rate limits."""

from __future__ import annotations

import math
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Path, Query, Request
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ..runtime.sessions import Forbidden, LiveSession, NotFound, SessionManager
from ..security.auth import Authenticator
from ..settings import ServerSettings
from ..storage.store import Store, TokenRecord

bearer = HTTPBearer(auto_error=False, description="a hippomap token (admin, writer or viewer)")

SessionId = Annotated[str, Path(description="session id")]  # any other string is simply not found (404)

ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"description": "missing or unknown bearer token"},
    404: {"description": "no such session, or one this token may not see"},
    429: {
        "description": "rate limit exceeded (see Retry-After): the session's ingest budget, or for queries the "
        "token's read budget on the session"
    },
}
WRITE_ERRORS: dict[int | str, dict[str, Any]] = {**ERRORS, 403: {"description": "read-only (viewer) token"}}


def store(request: Request) -> Store:
    return request.app.state.store


def manager(request: Request) -> SessionManager:
    return request.app.state.manager


def settings(request: Request) -> ServerSettings:
    return request.app.state.settings


def token(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)] = None,
    query_token: Annotated[
        str | None,
        Query(alias="token", description="token for browsers (GET only; one longer than 512 characters is unknown)"),
    ] = None,
) -> TokenRecord:
    """The caller's token, from ``Authorization: Bearer`` (or ``?token=`` on GET requests)."""
    auth: Authenticator = request.app.state.auth
    secret = credentials.credentials if credentials is not None else None
    if secret is None and request.method == "GET":
        secret = query_token
    rec = auth.authenticate(secret)
    if rec is None:
        raise HTTPException(401, "missing or unknown bearer token", headers={"WWW-Authenticate": "Bearer"})
    return rec


Token = Annotated[TokenRecord, Depends(token)]


def _session(request: Request, tok: TokenRecord, session_id: str, write: bool) -> LiveSession:
    try:
        live = manager(request).get(tok, session_id, write=write)
    except NotFound:
        raise HTTPException(404, f"session {session_id!r} not found") from None
    except Forbidden:
        raise HTTPException(403, "this token is read-only") from None
    if write:  # ingest (and delete): the session's budget
        wait, what = live.bucket.take(), f"request rate limit of {live.settings.rate_per_s:g}/s"
    else:  # queries: this token's own read budget on the session, apart from ingest
        limits = request.app.state.read_limits
        wait, what = limits.take((live.id, tok.id)), f"read rate limit of {limits.rate:g}/s (per token)"
    if wait > 0:
        live.rejected[429] += 1
        raise HTTPException(
            429, f"{what} exceeded for session {session_id}", headers={"Retry-After": str(max(1, math.ceil(wait)))}
        )
    return live


def read_session(request: Request, tok: Token, session_id: SessionId) -> LiveSession:
    return _session(request, tok, session_id, write=False)


def write_session(request: Request, tok: Token, session_id: SessionId) -> LiveSession:
    return _session(request, tok, session_id, write=True)


ReadSession = Annotated[LiveSession, Depends(read_session)]
WriteSession = Annotated[LiveSession, Depends(write_session)]


def problem(status: int, detail: Any, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=status, headers=headers)
