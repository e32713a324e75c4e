"""The FastAPI application: storage, auth and sessions wired together.

``create_app(settings)`` builds an app whose lifespan opens the store, makes sure the admin
token exists, restores every stored session (snapshot + replay, in each session's worker)
and, on shutdown, lets every worker finish its queue and snapshot before the store closes.
"""

from __future__ import annotations

import asyncio
import json
import logging
from contextlib import asynccontextmanager
from typing import Any, AsyncIterator

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from hippomap import __version__

from . import model
from .api import ingest, queries, sessions, stream, tokens
from .auth import Authenticator, ensure_admin
from .limits import BodySizeLimit
from .sessions import SessionManager
from .settings import ServerSettings
from .sqlite_store import SQLiteStore
from .store import Store

log = logging.getLogger("hippomap.server")

DESCRIPTION = """
Serves hippomap's mapper to robots: one mapper per session, fed in order; every
acknowledged input is stored first (SQLite, WAL) and sessions are restored exactly after a
restart (snapshot + replay).

**Auth**: `Authorization: Bearer <token>`. A session is visible only to the token that
created it (404 for anyone else); viewer tokens (`POST /tokens`) are read-only.

**Ingest**: `POST /sessions/{id}/odometry`, `POST /sessions/{id}/frames`, or the websocket
`/sessions/{id}/stream` (JSON odometry, binary frames with a 16-byte header `<4sId`:
`b"HMF1"`, message id, timestamp; each message is acknowledged with its sequence numbers
once durable). See `server/protocol.py`.
"""


class SafeJSONResponse(JSONResponse):
    """JSON without NaN/Infinity (not JSON): such values are sent as null."""

    def render(self, content: Any) -> bytes:
        return json.dumps(model.json_safe(content), ensure_ascii=False, allow_nan=False,
                          separators=(",", ":")).encode("utf-8")


def open_store(settings: ServerSettings) -> Store:
    """The store named by the settings: a SQLite file (the embedded default). Other backends
    (PostgreSQL) implement :class:`~server.store.Store` and are chosen here by URL scheme."""
    location = settings.database or ""
    if "://" in location and not location.startswith("sqlite://"):
        raise RuntimeError(f"unsupported database {location!r}: only SQLite files are built in")
    if location.startswith("sqlite://"):
        settings = settings.model_copy(update={"database": location[len("sqlite://"):]})
    return SQLiteStore(settings.database_path, settings.durability)


def _warm_up() -> None:
    """Import the model and image code now, not inside the first request (it would stall it)."""
    import cv2  # noqa: F401

    import hippomap.mapper  # noqa: F401
    import hippomap.visual_memory  # noqa: F401

    from . import views  # noqa: F401


def create_app(settings: ServerSettings | None = None) -> FastAPI:
    settings = settings or ServerSettings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await asyncio.to_thread(_warm_up)
        store = open_store(settings)
        secret, created = ensure_admin(store, settings.token_file, settings.admin_token)
        app.state.store = store
        app.state.auth = Authenticator(store)
        app.state.admin_token = secret
        app.state.admin_token_created = created
        manager = SessionManager(store, settings)
        manager.start(asyncio.get_running_loop())
        app.state.manager = manager
        try:
            yield
        finally:
            await asyncio.to_thread(app.state.viewer_hub.close_all)
            await asyncio.to_thread(manager.stop)
            store.close()

    app = FastAPI(title="hippomap server", version=__version__, description=DESCRIPTION, lifespan=lifespan,
                  default_response_class=SafeJSONResponse)
    app.state.settings = settings
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = model.json_safe(jsonable_encoder(exc.errors(), custom_encoder={bytes: lambda b: f"<{len(b)} bytes>"}))
        return SafeJSONResponse({"detail": errors}, status_code=422)

    @app.get("/health", tags=["server"], summary="Liveness (no token needed)")
    async def health() -> dict[str, Any]:
        return {"status": "ok", "version": __version__, "sessions": len(app.state.manager.sessions)}

    for module in (sessions, ingest, stream, queries, tokens):
        app.include_router(module.router)
    from web.service import viewer_router  # the live 3D viewer: /viewer/ (web/routes.py)

    app.include_router(viewer_router(app))
    return app
