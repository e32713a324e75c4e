"""The service describes itself, offline: ``/docs`` and ``/redoc`` with their assets served by the app
(checked in HTML and in a real Chromium that may reach nothing but loopback), a request example on
every operation that takes a body (each one accepted by the server), the websocket protocol in the
OpenAPI document (real stream messages validated against its schemas), and no untagged operation."""

from __future__ import annotations

import re
from urllib.parse import urlsplit

import cv2
import httpx
import jsonschema
import pytest
from fastapi.testclient import TestClient
from playwright.sync_api import sync_playwright
from starlette.websockets import WebSocketDisconnect

from server.api.docs import ASSETS_URL
from server.app import create_app
from server.formats.protocol import pack_frame
from server.settings import ServerSettings
from tests.support.chromium import launch
from tests.support.live import LiveServer
from tests.support.synthetic import view

ADMIN = "hm_api_docs_admin_token_0123456789"
AUTH = {"Authorization": f"Bearer {ADMIN}"}
#: every URL a page may name: src=, href=, spec-url= attributes and Swagger UI's `url: '...'`
URL_IN_HTML = re.compile(r"""(?:src|href|spec-url)\s*=\s*["']([^"']+)["']|\burl:\s*["']([^"']+)["']""")
CONTENT_TYPES = {".js": "javascript", ".css": "text/css", ".png": "image/png", ".json": "application/json"}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app(ServerSettings(data_dir=tmp_path_factory.mktemp("docs") / "data", admin_token=ADMIN))
    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def document(client):
    r = client.get("/openapi.json")
    assert r.status_code == 200
    return r.json()


def _operations(document):
    for path, item in document["paths"].items():
        for method, op in item.items():
            yield path, method, op


def _validator(document, ref: str) -> jsonschema.Draft202012Validator:
    """A validator for ``ref`` (e.g. ``#/components/schemas/X``) resolving refs within the document."""
    return jsonschema.Draft202012Validator({**document, "$ref": ref})


# ------------------------------------------------------------------------ offline /docs and /redoc
@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_every_asset_from_the_app_itself(client, page):
    r = client.get(page)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert not re.search(r"https?://", r.text), (page, re.findall(r"https?://\S+", r.text))
    urls = [a or b for a, b in URL_IN_HTML.findall(r.text)]
    assert urls, r.text
    suffixes = set()
    for url in urls:
        parts = urlsplit(url)
        assert not parts.scheme and not parts.netloc and url.startswith("/"), url
        asset = client.get(url)
        suffix = url[url.rfind(".") :]
        suffixes.add(suffix)
        assert asset.status_code == 200, url
        assert CONTENT_TYPES[suffix] in asset.headers["content-type"], (url, asset.headers["content-type"])
        assert len(asset.content) > (10_000 if suffix in (".js", ".css") else 100), url
    # the page's script and the document it renders are among them
    assert {".js", ".json"} <= suffixes and any(u.startswith(ASSETS_URL) for u in urls)
    # the browser is confined to this server whatever the bundles name
    csp = dict(d.strip().split(" ", 1) for d in r.headers["content-security-policy"].split(";"))
    assert csp["default-src"] == "'self'" and csp["connect-src"] == "'self'" and csp["img-src"] == "'self' data:"
    assert "unsafe-inline" not in csp["script-src"] and "*" not in r.headers["content-security-policy"]
    if page == "/docs":
        assert "'sha256-" in csp["script-src"]  # its one inline script, by hash
        assert ".css" in suffixes and '"validatorUrl": null' in r.text  # no badge fetched from an outside host


def test_fastapi_cdn_pages_are_gone(client):
    # the default pages would name the CDN; the assets folder does not list itself
    assert client.get("/docs").text.count("cdn.") == 0 and client.get("/redoc").text.count("cdn.") == 0
    assert client.get(ASSETS_URL + "/").status_code == 404
    assert client.get(ASSETS_URL + "/../server/app.py").status_code == 404


def test_mount_docs_refuses_a_broken_install_or_an_app_with_cdn_pages(tmp_path):
    from fastapi import FastAPI

    from server.api.docs import mount_docs

    (tmp_path / "swagger-ui.css").write_text("body{}")
    with pytest.raises(RuntimeError, match="swagger-ui-bundle.js.*redoc.standalone.js.*fastapi-offline"):
        mount_docs(FastAPI(docs_url=None, redoc_url=None), assets_dir=tmp_path)
    with pytest.raises(RuntimeError, match="docs_url=None"):
        mount_docs(FastAPI())


def _offline_page(p, url: str):
    """A Chromium page that may reach loopback only; returns (page, browser, outside requests seen)."""
    browser = launch(p)
    outside: list[str] = []
    page = browser.new_page()
    violations: list[str] = []
    page.on("console", lambda m: violations.append(m.text) if "Content Security Policy" in m.text else None)
    page.violations = violations

    def guard(route) -> None:
        host = urlsplit(route.request.url).hostname or ""
        if route.request.url.startswith(("data:", "blob:")) or host in ("127.0.0.1", "localhost"):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", guard)
    page.goto(url)
    return page, browser, outside


def test_docs_render_in_chromium_without_any_outside_network(tmp_path):
    server = LiveServer(tmp_path / "data").start()
    try:
        document = httpx.get(f"{server.url}/openapi.json", timeout=30).json()
        n_operations = sum(1 for _ in _operations(document))
        with sync_playwright() as p:
            page, browser, outside = _offline_page(p, f"{server.url}/docs")
            try:
                page.wait_for_selector(".opblock", timeout=60_000)
                page.wait_for_function(
                    "n => document.querySelectorAll('.opblock').length >= n", arg=n_operations, timeout=30_000
                )
                text = page.inner_text("body")
                assert "hippomap server" in text and "Websockets" in text  # the description, with the protocol
                for tag in ("sessions", "ingest", "queries", "tokens", "server", "viewer"):
                    assert page.locator(f"#operations-tag-{tag}").count() == 1, tag
                assert page.locator("#operations-tag-default").count() == 0
                # an operation opened shows its request example
                page.locator("#operations-ingest-post_odometry_sessions__session_id__odometry_post").click()
                page.wait_for_function("() => document.body.innerText.includes('\"omega\": 0.05')", timeout=30_000)
                assert page.locator(".opblock").count() == n_operations
                assert page.violations == []  # the policy refused nothing Swagger UI needs
            finally:
                browser.close()
            page, browser, outside_redoc = _offline_page(p, f"{server.url}/redoc")
            try:
                page.wait_for_function("() => document.body.innerText.includes('Create a session')", timeout=60_000)
                assert "Websockets" in page.inner_text("body")
                # the request sample of POST /sessions is its example
                page.wait_for_function("() => document.body.innerText.includes('keyframe_interval')", timeout=30_000)
                # only the sidebar's CDN logo is refused (it hides itself): ReDoc needs nothing else outside
                assert all("redoc.ly" in v for v in page.violations), page.violations
            finally:
                browser.close()
    finally:
        server.stop()
    assert outside == [] and outside_redoc == [], (outside, outside_redoc)


# ------------------------------------------------------------------------------- request examples
def _examples(document, media: dict) -> list:
    """The examples of a request body's media type: its own (``example``/``examples``), else its schema's."""
    if "example" in media:
        return [media["example"]]
    if "examples" in media:  # named examples: a value, or (binary bodies) a file's URL
        return [
            e["value"] if "value" in e else {"externalValue": e["externalValue"]} for e in media["examples"].values()
        ]
    schema = media.get("schema", {})
    if "$ref" in schema:
        schema = document["components"]["schemas"][schema["$ref"].rsplit("/", 1)[1]]
    return list(schema.get("examples", []))


def test_every_operation_with_a_body_has_valid_examples(document):
    with_body = 0
    for path, method, op in _operations(document):
        body = op.get("requestBody")
        if body is None:
            continue
        with_body += 1
        found = 0
        for media_type, media in body["content"].items():
            examples = _examples(document, media)
            found += len(examples)
            if media_type == "application/json" and examples:
                validator = jsonschema.Draft202012Validator({**document, **media["schema"]})
                for ex in examples:
                    errors = [e.message for e in validator.iter_errors(ex)]
                    assert not errors, (method, path, ex, errors)
        assert found, f"{method.upper()} {path} has a request body but no example"
    assert with_body >= 4  # sessions, odometry, frames, tokens


def test_the_json_examples_are_accepted_by_the_server(client, document):
    """Each JSON example, sent as it stands, is accepted (2xx): they are requests that work."""

    def body_examples(path: str) -> list:
        return _examples(document, document["paths"][path]["post"]["requestBody"]["content"]["application/json"])

    sessions = body_examples("/sessions")
    created = [client.post("/sessions", json=ex, headers=AUTH) for ex in sessions]
    assert [r.status_code for r in created] == [201] * len(sessions), [r.text for r in created]
    mapper_cfg = created[0].json()["config"]["mapper"]
    assert mapper_cfg["keyframe_interval"] == sessions[0]["config"]["mapper"]["keyframe_interval"]
    sid = created[0].json()["id"]
    odometry = body_examples("/sessions/{session_id}/odometry")
    assert len(odometry) >= 3 and any("readings" in ex for ex in odometry) and any("increment" in ex for ex in odometry)
    for ex in odometry:  # in the order given: their timestamps increase
        r = client.post(f"/sessions/{sid}/odometry", json=ex, headers=AUTH)
        assert r.status_code == 200, (ex, r.text)
        assert r.json()["count"] == len(ex.get("readings", [ex]))
    for ex in body_examples("/tokens"):
        r = client.post("/tokens", json=ex, headers=AUTH)
        assert r.status_code == 201 and r.json()["role"] == ex["role"], r.text
    # the frames' examples are images the service serves: each, sent as a raw body, is accepted
    frames = document["paths"]["/sessions/{session_id}/frames"]["post"]["requestBody"]["content"]
    t = 100.0
    for media_type in ("image/jpeg", "image/png"):
        (example,) = _examples(document, frames[media_type])
        url = example["externalValue"]
        assert url.startswith("/") and not urlsplit(url).netloc  # served here, offline
        image = client.get(url)
        assert image.status_code == 200 and image.headers["content-type"] == media_type
        t += 1
        r = client.post(
            f"/sessions/{sid}/frames",
            params={"t": t},
            content=image.content,
            headers={**AUTH, "Content-Type": media_type},
        )
        assert r.status_code == 200, r.text


# ------------------------------------------------------------------------------------------ tags
def test_no_operation_is_untagged(document):
    untagged = [f"{m.upper()} {p}" for p, m, op in _operations(document) if not op.get("tags")]
    assert untagged == []
    tags = {t for _, _, op in _operations(document) for t in op["tags"]}
    assert "default" not in tags and {"viewer", "server", "sessions", "ingest", "queries", "tokens"} <= tags
    assert document["paths"]["/viewer/"]["get"]["tags"] == ["viewer"]
    assert document["paths"]["/"]["get"]["tags"] == ["server"]


# ---------------------------------------------------------------------------- websocket protocol
def test_the_websocket_protocol_is_in_the_openapi_document(document):
    description = document["info"]["description"]
    ws = document["x-websockets"]
    stream = ws["/sessions/{session_id}/stream"]
    for kind in ("hello", "ack", "error", "busy", "pong", "ping", "odometry"):
        assert f"`{kind}`" in description or f"Ws{kind.capitalize()}" in description, kind
    for code in ("4401", "4403", "4404", "4421"):
        assert code in description and code in stream["close_codes"]
    assert stream["client_messages"]["binary"]["header_struct"] == "<4sId"
    assert stream["client_messages"]["binary"]["header_bytes"] == 16 and "HMF1" in description
    refs = [b["$ref"] for b in stream["client_messages"]["text"]["oneOf"] + stream["server_messages"]["oneOf"]]
    for ref in refs:  # every message schema named is in the document, with an example valid against it
        schema = document["components"]["schemas"][ref.rsplit("/", 1)[1]]
        assert schema["examples"]
        for ex in schema["examples"]:
            _validator(document, ref).validate(ex)
    assert "viser-v" in ws["/viewer/{session_id}"]["subprotocol"]


def _receive(ws) -> dict:
    return ws.receive_json()


def test_real_stream_messages_match_the_documented_schemas(client, document):
    stream = document["x-websockets"]["/sessions/{session_id}/stream"]
    server_messages = _validator(document, "#/x-websockets/~1sessions~1{session_id}~1stream/server_messages")
    client_text = _validator(document, "#/x-websockets/~1sessions~1{session_id}~1stream/client_messages/text")
    sid = client.post("/sessions", json={"name": "ws doc"}, headers=AUTH).json()["id"]
    received: list[dict] = []
    with client.websocket_connect(f"/sessions/{sid}/stream", headers=AUTH) as ws:
        received.append(_receive(ws))
        assert received[0]["type"] == "hello"
        # every documented client example, as it stands, in order, is acknowledged (a ping gets its pong)
        sent = []
        for ref in stream["client_messages"]["text"]["oneOf"]:
            for ex in document["components"]["schemas"][ref["$ref"].rsplit("/", 1)[1]]["examples"]:
                client_text.validate(ex)
                ws.send_json(ex)
                sent.append(ex)
                reply = _receive(ws)
                received.append(reply)
                assert reply["id"] == ex["id"] and reply["type"] == ("pong" if ex["type"] == "ping" else "ack"), reply
        # a binary frame as documented: the header, then the JPEG
        ok, jpeg = cv2.imencode(".jpg", view(0.5))
        last_t = max(r["t"] for ex in sent for r in ex.get("readings", [ex]) if "t" in r)
        ws.send_bytes(pack_frame(77, last_t + 0.05, jpeg.tobytes()))
        received.append(_receive(ws))
        assert received[-1]["type"] == "ack" and received[-1]["id"] == 77
        # what the document forbids, the server refuses: an undocumented field; a message type it does not list
        for bad in (
            {"type": "odometry", "id": 90, "t": last_t + 1, "v": 0.1, "omega": 0.0, "speed": 3},
            {"type": "frame", "id": 91},
        ):
            assert not client_text.is_valid(bad)
            ws.send_json(bad)
            received.append(_receive(ws))
            assert received[-1]["type"] == "error" and received[-1]["status"] == 422, received[-1]
    for msg in received:
        server_messages.validate(msg)
        _validator(document, stream["server_messages"]["discriminator"]["mapping"][msg["type"]]).validate(msg)


def test_documented_close_codes_are_the_ones_sent(client, document):
    codes = document["x-websockets"]["/sessions/{session_id}/stream"]["close_codes"]
    sid = client.post("/sessions", json={"name": "closes"}, headers=AUTH).json()["id"]
    viewer = client.post("/tokens", json={"role": "viewer"}, headers=AUTH).json()["token"]
    for headers, path in (({}, sid), ({"Authorization": f"Bearer {viewer}"}, sid), (AUTH, "no-such-session")):
        with client.websocket_connect(f"/sessions/{path}/stream", headers=headers) as ws:
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
        assert str(closed.value.code) in codes, closed.value.code
