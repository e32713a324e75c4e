"""The FastAPI application: storage, auth and sessions wired together.

``create_app(settings)`` builds an app whose lifespan opens the store, makes sure the admin
token exists, restores every stored session (snapshot + replay, in each session's worker)
and, on shutdown, lets every worker finish its queue and snapshot before the store closes.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import os
import time
from contextlib import asynccontextmanager
from typing import Any, AsyncIterator

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response

from hippomap import __version__

from . import model
from .api import ingest, queries, sessions, stream, tokens
from .auth import Authenticator, ensure_admin
from .limits import BodySizeLimit
from .metrics import ServiceMetrics
from .sessions import ServedElsewhere, SessionManager
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

**Operations** (no token): `GET /health` (liveness), `GET /ready` (readiness: 503 while sessions
are being restored after a restart), `GET /metrics` (Prometheus; a token only if
`HIPPOMAP_METRICS_TOKEN` is set).
"""


class SafeJSONResponse(JSONResponse):
    """JSON without NaN/Infinity (not JSON): such values are sent as null."""

    def render(self, content: Any) -> bytes:
        return json.dumps(model.json_safe(content), ensure_ascii=False, allow_nan=False,
                          separators=(",", ":")).encode("utf-8")


def open_store(settings: ServerSettings) -> Store:
    """The store named by ``settings.database``: unset or a file path → SQLite (the embedded
    default, ``<data_dir>/hippomap.sqlite3`` when unset); ``sqlite:///path`` → that SQLite file;
    ``postgresql://`` or ``postgres://`` URL → PostgreSQL (several replicas may share it).
    Errors never repeat the URL (it may hold a password)."""
    location = settings.database or ""
    scheme = location.split("://", 1)[0].lower() if "://" in location else ""
    if scheme in ("postgresql", "postgres"):
        try:
            from .postgres_store import PostgresStore
        except ImportError as exc:
            raise RuntimeError(f"a PostgreSQL database needs psycopg: pip install 'hippomap[postgres]' ({exc})") from None
        return PostgresStore(location, settings.durability)
    if scheme == "sqlite":
        settings = settings.model_copy(update={"database": location[len("sqlite://"):]})
    elif scheme:
        raise RuntimeError(f"unsupported database URL scheme {scheme + '://'!r}; accepted: a SQLite file path, "
                           "sqlite:///path/to/file.sqlite3, or postgresql://user:password@host:port/dbname "
                           "(postgres:// also accepted)")
    return SQLiteStore(settings.database_path, settings.durability)


def _warm_up() -> None:
    """Import the model and image code now, not inside the first request (it would stall it)."""
    import cv2  # noqa: F401

    import hippomap.mapper  # noqa: F401
    import hippomap.visual_memory  # noqa: F401

    from . import views  # noqa: F401


async def _log_restores(manager: SessionManager, started: float, poll_s: float = 0.05) -> None:
    """Log the start of each session's restore after a restart, and when the server became ready
    (every restore done; ``duration_s`` since the restores began). Each session's worker logs the
    end of its own restore with its duration."""
    waiting = set(manager.restoring())
    if not waiting:
        log.info("ready: no session to restore")
        return
    log.info("restoring %d sessions", len(waiting), extra={"sessions": len(waiting)})
    for sid in sorted(waiting):
        log.info("session %s restore started", sid, extra={"session": sid})
    while waiting:
        await asyncio.sleep(poll_s)
        waiting &= set(manager.restoring())
    log.info("ready: every session restored", extra={"duration_s": round(time.monotonic() - started, 3)})


def _metrics_token(settings: ServerSettings) -> str | None:
    """The bearer token ``GET /metrics`` requires, if any: ``metrics_token`` / ``HIPPOMAP_METRICS_TOKEN``."""
    return getattr(settings, "metrics_token", None) or os.environ.get("HIPPOMAP_METRICS_TOKEN") or None


def create_app(settings: ServerSettings | None = None) -> FastAPI:
    settings = settings or ServerSettings.from_env()
    metrics = ServiceMetrics()
    metrics_token = _metrics_token(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await asyncio.to_thread(_warm_up)
        store = open_store(settings)
        secret, created = ensure_admin(store, settings.token_file, settings.admin_token)
        app.state.store = store
        app.state.auth = Authenticator(store)
        app.state.admin_token = secret
        app.state.admin_token_created = created
        manager = SessionManager(store, settings, metrics)
        metrics.track(manager.queue_depths, lambda: app.state.serving and not manager.restoring())
        started = time.monotonic()
        manager.start(asyncio.get_running_loop())
        app.state.manager = manager
        app.state.serving = True
        restores = asyncio.create_task(_log_restores(manager, started))
        try:
            yield
        finally:
            app.state.serving = False  # /ready answers 503 while the sessions stop
            restores.cancel()
            await asyncio.to_thread(app.state.viewer_hub.close_all)
            await asyncio.to_thread(manager.stop)
            store.close()

    app = FastAPI(title="hippomap server", version=__version__, description=DESCRIPTION, lifespan=lifespan,
                  default_response_class=SafeJSONResponse)
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.serving = False
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)

    @app.exception_handler(ServedElsewhere)
    async def served_elsewhere(request: Request, exc: ServedElsewhere) -> JSONResponse:
        # 421 Misdirected Request: this replica cannot answer for the session; the one named can
        return SafeJSONResponse({"detail": str(exc), "replica": exc.replica}, status_code=421,
                                headers={"X-Hippomap-Replica": exc.replica})

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = model.json_safe(jsonable_encoder(exc.errors(), custom_encoder={bytes: lambda b: f"<{len(b)} bytes>"}))
        return SafeJSONResponse({"detail": errors}, status_code=422)

    @app.get("/health", tags=["server"], summary="Liveness (no token needed)")
    async def health() -> dict[str, Any]:
        manager = getattr(app.state, "manager", None)  # answers even before the start-up finished
        return {"status": "ok", "version": __version__, "sessions": 0 if manager is None else len(manager.sessions)}

    @app.get("/ready", tags=["server"], summary="Readiness (no token needed): 503 while sessions are being restored",
             responses={503: {"description": "not ready: starting, stopping, or sessions still being restored "
                                             "(`restoring` lists them)"}})
    async def ready() -> Any:
        manager: SessionManager | None = getattr(app.state, "manager", None)
        if manager is None or not app.state.serving:
            return SafeJSONResponse({"ready": False, "restoring": [],
                                     "sessions": 0 if manager is None else len(manager.sessions), "reason": "starting" if manager is None else "stopping"}, status_code=503)
        restoring = sorted(manager.restoring())
        body = {"ready": not restoring, "restoring": restoring, "sessions": len(manager.sessions)}
        if restoring:
            return SafeJSONResponse({**body, "reason": "restoring sessions"}, status_code=503)
        return body

    @app.get("/metrics", tags=["server"], response_class=Response,
             summary="Prometheus metrics (text format; a bearer token only if HIPPOMAP_METRICS_TOKEN is set)",
             responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text exposition format"},
                        401: {"description": "HIPPOMAP_METRICS_TOKEN is set and the request does not carry it"}})
    async def prometheus_metrics(request: Request) -> Response:
        if metrics_token is not None:
            given = request.headers.get("authorization", "")
            if not hmac.compare_digest(given.encode(), f"Bearer {metrics_token}".encode()):
                return SafeJSONResponse({"detail": "GET /metrics needs the metrics token (Authorization: Bearer ...)"},
                                        status_code=401, headers={"WWW-Authenticate": "Bearer"})
        body, content_type = await asyncio.to_thread(metrics.render)
        return Response(body, media_type=content_type)

    for module in (sessions, ingest, stream, queries, tokens):
        app.include_router(module.router)
    from web.service import viewer_router  # the live 3D viewer: /viewer/ (web/routes.py)

    app.include_router(viewer_router(app))
    return app
