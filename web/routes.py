"""FastAPI routes of the viewer: a landing page, viser's page per session, and the websocket proxy.

* ``GET /viewer/`` — the sessions the token may see, each linking to its viewer.
* ``GET /viewer/{session}/`` — viser's own ``index.html`` (the client is bundled in the viser wheel,
  no Node, works offline). The viewer's viser server is created here on first view.
* ``WS /viewer/{session}`` — the browser derives its websocket URL from the page URL (minus the
  query and the trailing slash) and offers the subprotocol ``viser-v<version>``; this route
  accepts with that subprotocol and pipes frames both ways to the session's viser server on
  127.0.0.1. viser's ports are never exposed, and answer only connections carrying the viewer's
  random key (sent by this proxy alone: other local users cannot read the scene); authentication
  stays here.

Authentication: the service's bearer tokens, read from ``Authorization: Bearer``, a ``token``
query parameter, or the ``hippomap_viewer`` cookie. A browser cannot set headers on a page
navigation or a websocket, so a page opened with ``?token=`` stores the token in an HttpOnly,
SameSite=Strict cookie limited to ``/viewer``; the websocket then carries it. A session the token
may not see answers exactly like a missing one (404 / close 1008), as in the rest of the service.

The router only needs a :class:`ViewerAccess` (the service adapts its token store and live
sessions to it): ``app.include_router(make_router(access))``.
"""

from __future__ import annotations

import asyncio
import gzip
import html
import logging
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Protocol, runtime_checkable
from urllib.parse import quote

import viser
import websockets
from fastapi import APIRouter, Request, WebSocket
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect, WebSocketState

from .session_viewer import KEY_HEADER, ViewerHub
from .settings import ViewerSettings
from .source import SessionSource

log = logging.getLogger(__name__)

COOKIE = "hippomap_viewer"
PREFIX = "/viewer"
SUBPROTOCOL = f"viser-v{viser.__version__}"


@dataclass(frozen=True)
class SessionEntry:
    """A session as listed on the landing page."""

    id: str
    title: str
    detail: str = ""


@runtime_checkable
class ViewerAccess(Protocol):
    """What the viewer needs from the service: who may see which session. Both calls may block
    (they are run in a worker thread)."""

    def list_sessions(self, token: str | None) -> list[SessionEntry] | None:
        """Sessions ``token`` may see, or None if the token is missing or invalid."""

    def open_session(self, token: str | None, session_id: str) -> SessionSource | None:
        """The session as a :class:`SessionSource` if ``token`` may see it (and it is live), else None."""


def token_from(headers, query_params, cookies) -> str | None:
    """The bearer token of a request or websocket: header, then query, then cookie."""
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip() or None
    return query_params.get("token") or cookies.get(COOKIE) or None


@lru_cache(maxsize=1)
def _index_html() -> tuple[bytes, bytes]:
    """viser's client page (plain and gzipped), read once from the installed wheel."""
    path = Path(viser.__file__).parent / "client" / "build" / "index.html"
    data = path.read_bytes()
    return data, gzip.compress(data, 6)


def _page(title: str, body: str, status: int = 200) -> HTMLResponse:
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>body{{font-family:system-ui,sans-serif;max-width:46rem;margin:2rem auto;padding:0 1rem;color:#222}}
li{{margin:.4rem 0}} .d{{color:#777;font-size:.9em}} code{{background:#eee;padding:0 .2em}}</style></head>
<body><h1>{html.escape(title)}</h1>{body}</body></html>"""
    return HTMLResponse(doc, status_code=status, headers={"Cache-Control": "no-store"})


def _login_form(message: str) -> str:
    return (
        f"<p>{html.escape(message)}</p><form method='get' action='{PREFIX}/'>"
        "<label>Token <input name='token' type='password' size='50' autocomplete='off'></label> "
        "<button>Open</button></form>"
    )


def _remember(response: Response, request: Request, token: str | None) -> None:
    """Keep a token given in the query as an HttpOnly cookie for the page's websocket."""
    given = request.query_params.get("token")
    if given and given == token:
        response.set_cookie(
            COOKIE, given, httponly=True, samesite="strict", path=PREFIX, secure=request.url.scheme == "https"
        )


def _add_landing_routes(router: APIRouter, access: ViewerAccess) -> None:
    """``/viewer`` and ``/viewer/``: the list of the sessions the token may view (or a login form)."""

    @router.get(PREFIX, include_in_schema=False)
    async def landing_redirect(request: Request) -> Response:
        q = f"?{request.url.query}" if request.url.query else ""
        return RedirectResponse(f"{PREFIX}/{q}", status_code=307)

    @router.get(
        f"{PREFIX}/",
        response_class=HTMLResponse,
        summary="Sessions you may view",
        responses={401: {"content": {"text/html": {}}, "description": "no token, or not a valid one: a login form"}},
    )
    async def landing(request: Request) -> Response:
        token = token_from(request.headers, request.query_params, request.cookies)
        sessions = await run_in_threadpool(access.list_sessions, token)
        if sessions is None:
            msg = "Enter a token (a viewer token is enough)." if not token else "That token is not valid."
            return _page("hippomap viewer", _login_form(msg), status=401)
        if sessions:
            items = "".join(
                f"<li><a href='{PREFIX}/{quote(s.id, safe='')}/'>{html.escape(s.title or s.id)}</a>"
                f" <span class='d'>{html.escape(s.id)}{' · ' + html.escape(s.detail) if s.detail else ''}</span></li>"
                for s in sessions
            )
            body = f"<ul id='sessions'>{items}</ul>"
        else:
            body = "<p id='sessions'>No sessions yet. Start one, e.g. <code>hippomap serve --demo</code>.</p>"
        response = _page("hippomap sessions", body)
        _remember(response, request, token)
        return response


def _add_viewer_routes(router: APIRouter, access: ViewerAccess, hub: ViewerHub) -> None:
    """``/viewer/{id}/``: a session's viewer page, and its websocket piped to the session's viser server."""
    _add_viewer_page(router, access, hub)
    _add_viewer_socket(router, access, hub)


def _add_viewer_page(router: APIRouter, access: ViewerAccess, hub: ViewerHub) -> None:
    """``/viewer/{id}/`` (and its form without the slash): the page, once the token may see the session; it
    starts the session's viser server so that the page's websocket connects at once."""

    @router.get(PREFIX + "/{session_id}", include_in_schema=False)
    async def viewer_redirect(session_id: str, request: Request) -> Response:
        q = f"?{request.url.query}" if request.url.query else ""
        return RedirectResponse(f"{PREFIX}/{quote(session_id, safe='')}/{q}", status_code=307)

    @router.get(
        PREFIX + "/{session_id}/",
        response_class=HTMLResponse,
        summary="Live 3D viewer of a session",
        responses={
            404: {
                "content": {"text/html": {}},
                "description": "no such session, or one the token may not see: a login form",
            }
        },
    )
    async def viewer_page(session_id: str, request: Request) -> Response:
        token = token_from(request.headers, request.query_params, request.cookies)
        source = await run_in_threadpool(access.open_session, token, session_id)
        if source is None:
            return _page("not found", "<p>No such session.</p>" + _login_form("Or try another token."), 404)
        await run_in_threadpool(hub.open, source)  # starts its viser server now: the page connects at once
        plain, packed = await run_in_threadpool(_index_html)  # read + gzip once (~0.8 MB), off the loop
        use_gzip = "gzip" in request.headers.get("accept-encoding", "")
        response = Response(
            packed if use_gzip else plain,
            media_type="text/html; charset=utf-8",
            headers={"Cache-Control": "no-store", **({"Content-Encoding": "gzip"} if use_gzip else {})},
        )
        _remember(response, request, token)
        return response


def _add_viewer_socket(router: APIRouter, access: ViewerAccess, hub: ViewerHub) -> None:
    """The page's websocket ``/viewer/{id}``, piped both ways to the session's viser server (closed with 1008
    when the token may not see the session, 1011 when the viser server cannot be reached)."""

    @router.websocket(PREFIX + "/{session_id}")
    async def viewer_socket(websocket: WebSocket, session_id: str) -> None:
        token = token_from(websocket.headers, websocket.query_params, websocket.cookies)
        source = await run_in_threadpool(access.open_session, token, session_id)
        if source is None:
            await websocket.close(code=1008)
            return
        viewer = await run_in_threadpool(hub.open, source)
        offered = websocket.scope.get("subprotocols") or []
        wanted = [p for p in offered if p.startswith("viser-v")]
        try:
            upstream = await websockets.connect(
                f"ws://127.0.0.1:{viewer.port}",
                subprotocols=wanted or None,
                max_size=None,
                additional_headers={KEY_HEADER: viewer.access_key},
                compression=None,
                open_timeout=10,
                ping_interval=None,
            )
        except (OSError, websockets.WebSocketException, asyncio.TimeoutError) as exc:
            log.warning("viewer %s: cannot reach its viser server: %s", session_id, exc)
            await websocket.close(code=1011)
            return
        await websocket.accept(subprotocol=upstream.subprotocol)
        hub.connected(viewer)
        try:
            await _pipe(websocket, upstream)
        finally:
            hub.disconnected(viewer)


def make_router(
    access: ViewerAccess, hub: ViewerHub | None = None, settings: ViewerSettings | None = None
) -> APIRouter:
    """The viewer's routes over ``access``; ``hub`` (created if None) owns the session viewers.

    The hub is available as ``router.hub`` (e.g. to close a deleted session's viewer, or all
    viewers at shutdown: ``router.hub.close_all()``).
    """
    hub = hub or ViewerHub(settings)
    router = APIRouter(tags=["viewer"])
    router.hub = hub  # type: ignore[attr-defined]

    _add_landing_routes(router, access)
    _add_viewer_routes(router, access, hub)
    return router


async def _pipe(browser: WebSocket, upstream) -> None:
    """Forward messages both ways until either side closes; pass viser's close code on."""

    async def down() -> None:  # viser -> browser
        async for msg in upstream:
            if isinstance(msg, bytes):
                await browser.send_bytes(msg)
            else:
                await browser.send_text(msg)

    async def up() -> None:  # browser -> viser
        while True:
            msg = await browser.receive()
            if msg["type"] == "websocket.disconnect":
                return
            if msg.get("bytes") is not None:
                await upstream.send(msg["bytes"])
            elif msg.get("text") is not None:
                await upstream.send(msg["text"])

    tasks = [asyncio.ensure_future(down()), asyncio.ensure_future(up())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for t in tasks:
            t.cancel()
        for t in tasks:
            try:
                await t
            except (asyncio.CancelledError, WebSocketDisconnect, websockets.WebSocketException, RuntimeError):
                pass
        code = upstream.close_code or 1000
        await upstream.close()
        if browser.application_state == WebSocketState.CONNECTED and browser.client_state == WebSocketState.CONNECTED:
            try:
                await browser.close(code=code if 1000 <= code < 5000 and code not in (1005, 1006, 1015) else 1000)
            except RuntimeError:
                pass
