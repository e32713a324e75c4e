"""Tokens: writers mint read-only viewer tokens; the admin also mints writer tokens."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Request, Response

from ..formats.schemas import TokenCreate, TokenCreated, TokenInfo
from ..runtime.sessions import NotFound
from . import deps

router = APIRouter(prefix="/tokens", tags=["tokens"])
log = logging.getLogger("hippomap.server")


def _rehome(manager: Any, old_owner: str, heir: str) -> None:
    """The sessions this replica runs for ``old_owner`` now belong to ``heir`` (as in the store)."""
    for live in list(manager.sessions.values()):
        if live.record.owner == old_owner:
            live.record = dataclasses.replace(live.record, owner=heir)


def _info(t: Any) -> dict[str, Any]:
    return {"id": t.id, "role": t.role, "owner": t.owner, "session": t.session, "label": t.label, "created": t.created}


@router.post(
    "",
    status_code=201,
    response_model=TokenCreated,
    responses={
        **deps.ERRORS,
        403: {"description": "viewer tokens cannot mint; only the admin mints writers"},
        422: {"description": "a writer token cannot be limited to a session"},
    },
    summary="Mint a token: a viewer (read-only, optionally one session) or, for the admin, a writer",
)
async def create_token(body: TokenCreate, request: Request, tok: deps.Token) -> Any:
    if tok.role == "viewer":
        raise HTTPException(403, "viewer tokens cannot create tokens")
    if body.role == "writer":
        if tok.role != "admin":
            raise HTTPException(403, "only the admin token can create writer tokens")
        if body.session is not None:
            raise HTTPException(422, "a writer token cannot be limited to a session")
    if body.session is not None:
        try:
            deps.manager(request).get(tok, body.session, write=True)
        except NotFound:
            raise HTTPException(404, f"session {body.session!r} not found") from None
    auth = request.app.state.auth
    secret, rec = await asyncio.to_thread(auth.mint, body.role, tok.id, body.session, body.label)
    return {**_info(rec), "token": secret}


@router.get(
    "",
    response_model=list[TokenInfo],
    responses=deps.ERRORS,
    summary="This token and the tokens it minted (never their secrets)",
)
async def list_tokens(request: Request, tok: deps.Token) -> Any:
    rows = await asyncio.to_thread(deps.store(request).list_tokens, tok.id)
    return [_info(t) for t in rows]


@router.delete(
    "/{token_id}",
    status_code=204,
    responses={**deps.ERRORS, 404: {"description": "no such token minted by this token"}},
    summary="Revoke a token this token minted",
    description="Revoking a writer token also revokes every viewer token it minted, and gives its "
    "sessions to the caller (the admin), who can then read, list and delete them.",
)
async def delete_token(request: Request, tok: deps.Token, token_id: Annotated[str, Path(max_length=64)]) -> Response:
    rows = await asyncio.to_thread(deps.store(request).list_tokens, tok.id)
    if tok.role == "viewer" or token_id == tok.id or not any(t.id == token_id and t.owner == tok.id for t in rows):
        raise HTTPException(404, f"token {token_id!r} not found")
    inherited = await asyncio.wrap_future(deps.store(request).revoke_token(token_id, tok.id))
    request.app.state.auth.forget()
    _rehome(deps.manager(request), token_id, tok.id)
    if inherited:
        log.info(
            "token %s revoked: its viewer tokens too; its %d sessions now belong to %s",
            token_id,
            len(inherited),
            tok.id,
            extra={"sessions": inherited},
        )
    return Response(status_code=204)
