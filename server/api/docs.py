"""Offline API docs: ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) with their assets served by the app.

FastAPI's default pages load Swagger UI and ReDoc from a CDN, so on an air-gapped robot network
they stay blank. The ``fastapi-offline`` wheel (a dependency of the ``server`` extra) ships the
Swagger UI bundle, its CSS, ReDoc's standalone bundle and a favicon; they are mounted at
:data:`ASSETS_URL` and the pages are built with FastAPI's documented helpers
(``get_swagger_ui_html`` / ``get_redoc_html``, the app created with ``docs_url=None``,
``redoc_url=None``). Swagger UI's online validator badge (a request to an outside host) is off,
and ReDoc does not load Google Fonts. Both pages carry a Content-Security-Policy limiting the browser
to this server, so that nothing in the bundles reaches another host.

The request examples of ``POST /sessions/{id}/frames`` (binary bodies) are real images served at
:data:`EXAMPLE_FRAME_URLS`. Use: ``mount_docs(app)`` once, after the app is created.
"""

from __future__ import annotations

import base64
import hashlib
import re
from functools import lru_cache
from pathlib import Path

import fastapi_offline
import numpy as np
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

#: where the Swagger UI / ReDoc files are served
ASSETS_URL = "/docs-assets"
#: the folder of the installed wheel holding them
ASSETS_DIR = Path(fastapi_offline.__file__).parent / "static"
#: the files the pages need (checked at mount time: a broken install fails at start, not in a browser)
ASSET_FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "favicon.png")

#: Swagger UI options: no online validator (its badge fetches an outside host); the token typed into
#: "Authorize" is not persisted (it would sit in the browser's local storage)
SWAGGER_PARAMETERS = {"validatorUrl": None, "persistAuthorization": False, "displayRequestDuration": True}


#: example camera frames for the request examples of POST /sessions/{id}/frames (binary bodies cannot be
#: written in the OpenAPI document: their examples name these files with ``externalValue``)
EXAMPLE_FRAME_URLS = {"jpeg": "/docs/examples/frame.jpg", "png": "/docs/examples/frame.png"}


@lru_cache(maxsize=2)
def example_frame(kind: str) -> bytes:
    """A 320x240 grey camera frame with texture (blocks of varied brightness and a gradient) encoded as
    ``kind`` (jpeg or png): an image the service accepts as a frame."""
    import cv2

    y, x = np.mgrid[0:240, 0:320]
    rng = np.random.default_rng(0)
    blocks = rng.integers(40, 216, size=(6, 8)).repeat(40, axis=0).repeat(40, axis=1)
    image = (0.7 * blocks + 0.3 * (255 * x / 319)).astype(np.uint8) ^ ((y // 8 + x // 8) % 2 * 24).astype(np.uint8)
    ok, data = cv2.imencode(".jpg" if kind == "jpeg" else ".png", image)
    if not ok:
        raise RuntimeError(f"cannot encode the example frame as {kind}")
    return data.tobytes()


_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.DOTALL)


def content_security_policy(page: str) -> str:
    """A policy letting ``page`` load from this server only: its inline scripts by hash, styles inline
    (both UIs inject them), images from here or ``data:``, ReDoc's search worker from ``blob:``. The
    browser then cannot reach any other host, whatever the bundles name (ReDoc's sidebar logo is an
    image on a CDN: refused, it hides itself)."""
    hashes = " ".join(
        f"'sha256-{base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()}'"
        for body in _INLINE_SCRIPT.findall(page)
    )
    return (
        f"default-src 'self'; script-src 'self' {hashes}".rstrip() + "; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'; "
        "object-src 'none'; base-uri 'self'; form-action 'self'; frame-ancestors 'self'"
    )


def _confined(response: HTMLResponse) -> HTMLResponse:
    response.headers["Content-Security-Policy"] = content_security_policy(bytes(response.body).decode())
    return response


def _missing_assets(folder: Path) -> list[str]:
    return [name for name in ASSET_FILES if not (folder / name).is_file()]


def mount_docs(app: FastAPI, assets_dir: Path = ASSETS_DIR) -> None:
    """Serve ``/docs``, ``/docs/oauth2-redirect`` and ``/redoc`` on ``app`` with local assets.

    ``app`` must have been created with ``docs_url=None`` and ``redoc_url=None`` (else FastAPI's
    CDN pages answer first). Raises RuntimeError naming the missing files if the assets are not
    installed."""
    if app.docs_url is not None or app.redoc_url is not None:
        raise RuntimeError("create the app with docs_url=None and redoc_url=None: mount_docs serves both pages")
    missing = _missing_assets(assets_dir)
    if missing:
        raise RuntimeError(
            f"the offline API-docs assets {missing} are missing from {assets_dir}: "
            "pip install 'hippomap[server]' (it installs fastapi-offline)"
        )
    app.mount(ASSETS_URL, StaticFiles(directory=assets_dir), name="docs-assets")
    oauth2_redirect = "/docs/oauth2-redirect"

    def root(request: Request) -> str:
        return request.scope.get("root_path", "").rstrip("/")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        base = root(request)
        return _confined(
            get_swagger_ui_html(
                openapi_url=f"{base}{app.openapi_url}",
                title=f"{app.title} - API docs",
                oauth2_redirect_url=f"{base}{oauth2_redirect}",
                swagger_js_url=f"{base}{ASSETS_URL}/swagger-ui-bundle.js",
                swagger_css_url=f"{base}{ASSETS_URL}/swagger-ui.css",
                swagger_favicon_url=f"{base}{ASSETS_URL}/favicon.png",
                swagger_ui_parameters=SWAGGER_PARAMETERS,
            )
        )

    @app.get(oauth2_redirect, include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get(EXAMPLE_FRAME_URLS["jpeg"], include_in_schema=False)
    async def example_jpeg() -> Response:
        return Response(example_frame("jpeg"), media_type="image/jpeg")

    @app.get(EXAMPLE_FRAME_URLS["png"], include_in_schema=False)
    async def example_png() -> Response:
        return Response(example_frame("png"), media_type="image/png")

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        base = root(request)
        return _confined(
            get_redoc_html(
                openapi_url=f"{base}{app.openapi_url}",
                title=f"{app.title} - ReDoc",
                redoc_js_url=f"{base}{ASSETS_URL}/redoc.standalone.js",
                redoc_favicon_url=f"{base}{ASSETS_URL}/favicon.png",
                with_google_fonts=False,
            )
        )
