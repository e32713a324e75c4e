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
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator, Callable, MutableMapping, cast

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from hippomap import __version__

from .api import docs, ingest, queries, reuse, sessions, stream, tokens, wsdoc
from .metrics import ServiceMetrics
from .runtime import model
from .runtime.sessions import ServedElsewhere, SessionManager
from .security.auth import Authenticator, CloseOnRevoke, adopt_orphans, ensure_admin
from .security.limits import BodySizeLimit, KeyedBuckets, OriginCheck
from .settings import ServerSettings
from .storage.sqlite import SQLiteStore
from .storage.store import Store

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
once durable). See `server/formats/protocol.py`.

**Operations**: `GET /health` (liveness) and `GET /ready` (readiness: 503 while sessions are
being restored after a restart) need no token; `GET /metrics` (Prometheus) needs the metrics token
(`HIPPOMAP_METRICS_TOKEN`), or the admin token when none is set, unless the operator opts out
(`HIPPOMAP_METRICS_PUBLIC=true`): it names every session.

**Browsers**: websockets opened by a web page are accepted only from the server's own origin or
those listed in `HIPPOMAP_ALLOWED_ORIGINS`.
"""


class SafeJSONResponse(JSONResponse):
    """JSON without NaN/Infinity (not JSON): such values are sent as null."""

    def render(self, content: Any) -> bytes:
        return json.dumps(model.json_safe(content), ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode(
            "utf-8"
        )


def open_store(settings: ServerSettings) -> Store:
    """The store named by ``settings.database``: unset or a file path → SQLite (the embedded
    default, ``<data_dir>/hippomap.sqlite3`` when unset); ``sqlite:///path`` → that SQLite file;
    ``postgresql://`` or ``postgres://`` URL → PostgreSQL (several replicas may share it).
    Errors never repeat the URL (it may hold a password)."""
    location = settings.database or ""
    scheme = location.split("://", 1)[0].lower() if "://" in location else ""
    if scheme in ("postgresql", "postgres"):
        try:
            from .storage.postgres import PostgresStore
        except ImportError as exc:
            raise RuntimeError(
                f"a PostgreSQL database needs psycopg: pip install 'hippomap[postgres]' ({exc})"
            ) from None
        return PostgresStore(location, settings.durability)
    if scheme == "sqlite":
        settings = settings.model_copy(update={"database": location[len("sqlite://") :]})
    elif scheme:
        raise RuntimeError(
            f"unsupported database URL scheme {scheme + '://'!r}; accepted: a SQLite file path, "
            "sqlite:///path/to/file.sqlite3, or postgresql://user:password@host:port/dbname "
            "(postgres:// also accepted)"
        )
    return SQLiteStore(settings.database_path, settings.durability)


def _warm_up() -> None:
    """Import the model and image code now, not inside the first request (it would stall it)."""
    import cv2  # noqa: F401

    import hippomap.mapper  # noqa: F401
    import hippomap.visual_memory  # noqa: F401

    from .formats import views  # noqa: F401


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
    """The bearer token ``GET /metrics`` requires if one is configured: ``metrics_token`` /
    ``HIPPOMAP_METRICS_TOKEN`` (else the admin token, unless ``metrics_public``)."""
    return settings.metrics_token or os.environ.get("HIPPOMAP_METRICS_TOKEN") or None


def _sqlite_file(settings: ServerSettings) -> Path | None:
    """The SQLite database file ``open_store`` will open (None for PostgreSQL)."""
    location = settings.database or ""
    scheme = location.split("://", 1)[0].lower() if "://" in location else ""
    if scheme == "sqlite":
        return Path(location[len("sqlite://") :])
    return None if scheme else settings.database_path


def secure_data_files(settings: ServerSettings) -> None:
    """Keep the service's data private to its user: the data folder 0700 (created so, or tightened
    with a warning), the admin token file and the SQLite files 0600 (an older server's files are
    tightened), and the SQLite database created 0600 before SQLite opens it (SQLite gives its -wal
    and -shm files the database file's mode)."""
    db = _sqlite_file(settings)
    data_dir = Path(settings.data_dir)
    folders = [data_dir] if (not settings.admin_token or (db is not None and db.parent == data_dir)) else []
    if db is not None and db.parent not in folders and not db.parent.exists():
        folders.append(db.parent)  # a folder this server creates for its database is private too
    for folder in folders:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        if folder.stat().st_mode & 0o077:
            log.warning("data folder %s was open to other users: now 0700", folder)
            os.chmod(folder, 0o700)
    files = [settings.token_file] + (
        [] if db is None else [db] + [db.with_name(db.name + x) for x in ("-wal", "-shm", "-journal")]
    )
    for f in files:
        if f.is_file() and not f.is_symlink() and f.stat().st_mode & 0o077:
            log.warning("data file %s was open to other users: now 0600", f)
            os.chmod(f, 0o600)
    if db is not None and not db.exists():
        db.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.close(os.open(db, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))


#: FastAPI's answer (400) to a JSON body it cannot even decode; the service answers 422 like any invalid body
BODY_PARSE_ERROR = "There was an error parsing the body"


def allowed_methods(app: FastAPI, scope: MutableMapping[str, Any]) -> list[str]:
    """The methods of every route matching ``scope``'s path (for ``Allow``: Starlette names only the
    first matching route's methods when several routes share a path)."""
    methods = []
    for method in ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT"):
        probe = {**scope, "type": "http", "method": method}
        if any(route.matches(probe)[0] == Match.FULL for route in app.router.routes):
            methods.append(method)
    return methods


def document_input_bounds(schema: dict[str, Any], settings: ServerSettings) -> None:
    """Write this server's physical bounds on inputs (settings ``max_abs_t``, ``max_speed_mps``...)
    into its OpenAPI document as minimum/maximum, so that the document states what is accepted."""

    def bound(prop: dict[str, Any] | None, limit: float | None) -> None:
        if prop is None or limit is None:
            return
        for branch in (prop, *prop.get("anyOf", [])):
            if branch.get("type") == "number":
                branch["minimum"], branch["maximum"] = -float(limit), float(limit)

    limits = {
        name: getattr(settings, name, None)
        for name in ("max_abs_t", "max_speed_mps", "max_turn_rate_rad_s", "max_increment_m", "max_increment_rad")
    }
    odo = schema.get("components", {}).get("schemas", {}).get("OdometryReading", {}).get("properties", {})
    bound(odo.get("t"), limits["max_abs_t"])
    bound(odo.get("v"), limits["max_speed_mps"])
    bound(odo.get("omega"), limits["max_turn_rate_rad_s"])
    for branch in (odo.get("increment") or {}).get("anyOf", []):
        items = branch.get("prefixItems") or []
        for item, name in zip(items, ("max_increment_m", "max_increment_m", "max_increment_rad")):
            bound(item, limits[name])
    for op in schema.get("paths", {}).get("/sessions/{session_id}/frames", {}).values():
        for param in op.get("parameters", []):
            if param.get("name") == "t":
                bound(param.get("schema"), limits["max_abs_t"])


def _lifespan(
    settings: ServerSettings, metrics: ServiceMetrics
) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The app's start-up and shutdown: open the store and the admin token, start the sessions; stop them."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await asyncio.to_thread(_warm_up)
        secure_data_files(settings)
        store = open_store(settings)
        secret, created = ensure_admin(store, settings.token_file, settings.admin_token)
        for owner, sids in adopt_orphans(store).items():
            log.warning("the sessions of the revoked token %s now belong to the admin: %s", owner, ", ".join(sids))
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

    return lifespan


def _add_error_handlers(app: FastAPI) -> None:
    """The error answers FastAPI's defaults get wrong for this service: 421 naming the replica, 405 with every
    allowed method, 422 for a body that is not JSON, validation errors without raw bytes."""

    @app.exception_handler(ServedElsewhere)
    async def served_elsewhere(request: Request, exc: ServedElsewhere) -> JSONResponse:
        # 421 Misdirected Request: this replica cannot answer for the session; the one named can
        return SafeJSONResponse(
            {"detail": str(exc), "replica": exc.replica}, status_code=421, headers={"X-Hippomap-Replica": exc.replica}
        )

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        if exc.status_code == 405:  # Allow: every method of the path, not only the first route's (Starlette's)
            allowed = allowed_methods(app, request.scope)
            return SafeJSONResponse(
                {"detail": "Method Not Allowed", "allow": allowed},
                status_code=405,
                headers={"Allow": ", ".join(allowed)},
            )
        if exc.status_code == 400 and exc.detail == BODY_PARSE_ERROR:  # bytes that are not UTF-8 JSON at all
            return SafeJSONResponse({"detail": "the request body is not valid JSON (UTF-8)"}, status_code=422)
        return await http_exception_handler(request, exc)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = model.json_safe(jsonable_encoder(exc.errors(), custom_encoder={bytes: lambda b: f"<{len(b)} bytes>"}))
        return SafeJSONResponse({"detail": errors}, status_code=422)


def _add_service_routes(
    app: FastAPI, settings: ServerSettings, metrics: ServiceMetrics, metrics_token: str | None
) -> None:
    """``/health``, ``/ready`` and ``/metrics``: the routes of the service itself, not of a session."""
    _add_health(app)
    _add_ready(app)
    _add_metrics(app, settings, metrics, metrics_token)


def _add_health(app: FastAPI) -> None:
    """``/health``: liveness, 503 once the store's writer died (the process exits for a restart)."""

    @app.get(
        "/health",
        tags=["server"],
        summary="Liveness (no token needed)",
        responses={503: {"description": "the store's writer died: the process exits for a restart"}},
    )
    async def health() -> dict[str, Any]:
        manager = getattr(app.state, "manager", None)  # answers even before the start-up finished
        if manager is not None and manager.fatal:  # the store's writer died: the process is about to exit
            # a Response passes FastAPI's response model (the annotation, which documents the 200) untouched
            failed = {"status": "failed", "version": __version__, "detail": f"storage stopped: {manager.fatal}"}
            return SafeJSONResponse(failed, status_code=503)  # type: ignore[return-value]
        return {"status": "ok", "version": __version__, "sessions": 0 if manager is None else len(manager.sessions)}


def _add_ready(app: FastAPI) -> None:
    """``/ready``: readiness, 503 while starting, stopping, after a storage failure or while restoring sessions."""

    @app.get(
        "/ready",
        tags=["server"],
        summary="Readiness (no token needed): 503 while sessions are being restored",
        responses={
            503: {
                "description": "not ready: starting, stopping, or sessions still being restored "
                "(`restoring` lists them)"
            }
        },
    )
    async def ready() -> Any:
        manager: SessionManager | None = getattr(app.state, "manager", None)
        if manager is None or not app.state.serving:
            return SafeJSONResponse(
                {
                    "ready": False,
                    "restoring": [],
                    "sessions": 0 if manager is None else len(manager.sessions),
                    "reason": "starting" if manager is None else "stopping",
                },
                status_code=503,
            )
        if manager.fatal:
            return SafeJSONResponse(
                {
                    "ready": False,
                    "restoring": [],
                    "sessions": len(manager.sessions),
                    "reason": f"storage stopped: {manager.fatal}",
                },
                status_code=503,
            )
        restoring = sorted(manager.restoring())
        body = {"ready": not restoring, "restoring": restoring, "sessions": len(manager.sessions)}
        if restoring:
            return SafeJSONResponse({**body, "reason": "restoring sessions"}, status_code=503)
        return body


def _add_metrics(app: FastAPI, settings: ServerSettings, metrics: ServiceMetrics, metrics_token: str | None) -> None:
    """``/metrics``: the Prometheus metrics, behind the metrics token (else the admin token) unless public."""

    @app.get(
        "/metrics",
        tags=["server"],
        response_class=Response,
        summary="Prometheus metrics (text format): needs the metrics token (HIPPOMAP_METRICS_TOKEN), else the "
        "admin token, unless HIPPOMAP_METRICS_PUBLIC is set",
        responses={
            200: {"content": {"text/plain": {}}, "description": "Prometheus text exposition format"},
            401: {"description": "the request does not carry the metrics token (or, if none is set, the admin token)"},
        },
    )
    async def prometheus_metrics(request: Request) -> Response:
        if not settings.metrics_public:
            required = metrics_token or getattr(app.state, "admin_token", None)
            given = request.headers.get("authorization", "")
            if required is None or not hmac.compare_digest(given.encode(), f"Bearer {required}".encode()):
                which = "metrics token" if metrics_token else "admin token (or set HIPPOMAP_METRICS_TOKEN)"
                return SafeJSONResponse(
                    {"detail": f"GET /metrics needs the {which}: Authorization: Bearer ..."},
                    status_code=401,
                    headers={"WWW-Authenticate": "Bearer"},
                )
        body, content_type = await asyncio.to_thread(metrics.render)
        return Response(body, media_type=content_type)


def _add_openapi(app: FastAPI, settings: ServerSettings) -> None:
    """The OpenAPI document, completed once on first use with the input bounds and the websocket protocol."""
    default_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            document_input_bounds(default_openapi(), settings)  # fills app.openapi_schema
            wsdoc.add_websocket_docs(cast(dict[str, Any], app.openapi_schema), settings)
        assert app.openapi_schema is not None
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def create_app(settings: ServerSettings | None = None) -> FastAPI:
    """The service: middleware, error answers, the service routes, the API routers, the OpenAPI document and
    the viewer, in that order (the order of the routes is the order of the docs)."""
    settings = settings or ServerSettings.from_env()
    metrics = ServiceMetrics()
    metrics_token = _metrics_token(settings)
    app = FastAPI(
        title="hippomap server",
        version=__version__,
        description=DESCRIPTION + wsdoc.websocket_description(),
        lifespan=_lifespan(settings, metrics),
        default_response_class=SafeJSONResponse,
        docs_url=None,
        redoc_url=None,
    )
    docs.mount_docs(app)  # /docs and /redoc with their assets served here (offline), not from a CDN
    app.state.settings = settings
    app.state.metrics = metrics
    app.state.serving = False
    app.state.read_limits = KeyedBuckets(settings.read_rate_per_s, settings.read_rate_burst)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(OriginCheck, allowed=settings.allowed_origins)
    app.add_middleware(CloseOnRevoke)
    _add_error_handlers(app)
    _add_service_routes(app, settings, metrics, metrics_token)
    for module in (sessions, reuse, ingest, stream, queries, tokens):
        app.include_router(module.router)
    _add_openapi(app, settings)
    from .viewer import mount_viewer  # the live 3D viewer: /viewer/ (web/routes.py); / (web/landing.py)

    mount_viewer(app)
    return app
