"""Hardening of the service's API and its token hygiene, one test per defect found by attacking it:

* queries before the first odometry reading (non-finite place codes) and ids beyond 64 bits;
* ``405`` answers naming every method of the path; undecodable JSON bodies answered 422;
* revoking a writer revokes its viewer tokens and hands its sessions to the admin;
* secrets never reach a log line (``?token=``, ``Authorization``, uvicorn's access lines);
* websockets refuse other web origins; ``/metrics`` needs a token; data files are private;
* reads have their own rate budget, so a reader cannot make the robot's ingest get 429;
* a session viewer's loopback viser server refuses anyone but the proxy.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import os
import stat
import threading
import time

import httpx
import networkx as nx
import pytest
import websockets
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from server.app import create_app
from server.logs import JSONFormatter, RedactSecrets, TextFormatter, configure, redact
from server.security.auth import adopt_orphans, hash_secret
from server.security.limits import OriginCheck
from server.settings import ServerSettings
from server.storage.sqlite import SQLiteStore
from server.storage.store import SessionRecord, TokenRecord
from tests.support.live import LiveServer

ADMIN = "hm_hardening_admin_token_0123456789"
AUTH = {"Authorization": f"Bearer {ADMIN}"}
BIG = 2**63  # one past SQLite's largest integer


def _app(tmp_path, **settings):
    return create_app(ServerSettings(data_dir=tmp_path / "data", admin_token=ADMIN, **settings))


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture()
def client(tmp_path):
    with TestClient(_app(tmp_path), raise_server_exceptions=False) as c:
        yield c


# ------------------------------------------------------------------- 500s found by fuzzing
def test_map_before_the_first_odometry_reading(client):
    sid = client.post("/sessions", json={"name": "fresh"}, headers=AUTH).json()["id"]
    r = client.get(f"/sessions/{sid}/map", headers=AUTH)
    assert r.status_code == 200, r.text
    nodes = r.json()["nodes"]
    assert nodes and nodes[0]["place_code"] is None and all(v == v for v in nodes[0]["pose"])
    r = client.get(f"/sessions/{sid}/map.graphml", headers=AUTH)
    assert r.status_code == 200 and b"nan" not in r.content.lower()
    g = nx.parse_graphml(r.text)
    node = g.nodes[next(iter(g.nodes))]
    assert "x" in node and "place_x" not in node  # no data rather than nan
    assert client.get(f"/sessions/{sid}/map.g2o", headers=AUTH).status_code == 200


@pytest.mark.parametrize(
    "path",
    [
        "/inputs?since_seq={n}",
        "/events?since_id={n}",
        "/place-fields?since_step={n}",
        "/loop-closures?since_id={n}",
        "/recognitions?since_id={n}",
        "/frames/{n}",
        "/saccades/{n}",
        "/place-fields/{n}",
        "/place-fields/{n}/png",
    ],
)
def test_ids_beyond_64_bits_are_422(client, path):
    sid = client.post("/sessions", json={"name": "ids"}, headers=AUTH).json()["id"]
    for n in (BIG, BIG - 1, 10**30):
        r = client.get(f"/sessions/{sid}" + path.format(n=n), headers=AUTH)
        assert r.status_code == 422, (path, n, r.status_code, r.text)
    # the largest accepted id still works (nothing there)
    r = client.get(f"/sessions/{sid}" + path.format(n=2**62), headers=AUTH)
    assert r.status_code in (200, 404), r.text


@pytest.mark.parametrize(
    "path,methods",
    [
        ("/sessions", "GET, POST"),
        ("/sessions/{sid}", "DELETE, GET"),
        ("/tokens", "GET, POST"),
        ("/sessions/{sid}/odometry", "POST"),
    ],
)
def test_405_names_every_method_of_the_path(client, path, methods):
    sid = client.post("/sessions", json={"name": "allow"}, headers=AUTH).json()["id"]
    for verb in ("OPTIONS", "PATCH", "PUT"):
        r = client.request(verb, path.format(sid=sid), headers=AUTH)
        assert r.status_code == 405 and r.headers["allow"] == methods, (verb, r.status_code, r.headers)


def test_a_body_that_is_not_utf8_json_is_422(client):
    r = client.post("/sessions", content=b"\xff\xfe{", headers={**AUTH, "Content-Type": "application/json"})
    assert r.status_code == 422 and "JSON" in r.json()["detail"]


def test_openapi_declares_the_viewer_pages_as_html(client):
    paths = client.get("/openapi.json").json()["paths"]
    page = paths["/viewer/{session_id}/"]["get"]["responses"]
    assert "text/html" in page["200"]["content"] and "text/html" in page["404"]["content"]


# ------------------------------------------------------------------------ token revocation
def test_revoking_a_writer_revokes_its_viewers_and_hands_its_sessions_to_the_admin(client):
    writer = client.post("/tokens", json={"role": "writer", "label": "robot"}, headers=AUTH).json()
    w = _bearer(writer["token"])
    sid = client.post("/sessions", json={"name": "robot's"}, headers=w).json()["id"]
    viewer_all = client.post("/tokens", json={"role": "viewer"}, headers=w).json()
    viewer_one = client.post("/tokens", json={"role": "viewer", "session": sid}, headers=w).json()
    for t in (viewer_all, viewer_one):
        assert client.get(f"/sessions/{sid}/stats", headers=_bearer(t["token"])).status_code == 200
    assert client.get(f"/sessions/{sid}", headers=AUTH).status_code == 404  # isolation before
    # a writer cannot revoke itself, nor a token it did not mint
    assert client.delete(f"/tokens/{writer['id']}", headers=w).status_code == 404
    assert client.delete(f"/tokens/{viewer_all['id']}", headers=AUTH).status_code == 404

    assert client.delete(f"/tokens/{writer['id']}", headers=AUTH).status_code == 204
    for t in (writer, viewer_all, viewer_one):
        assert client.get("/sessions", headers=_bearer(t["token"])).status_code == 401
        assert client.get(f"/sessions/{sid}/stats", headers=_bearer(t["token"])).status_code == 401
    # the session is the admin's now: listed, readable, writable, deletable
    assert sid in {s["id"] for s in client.get("/sessions", headers=AUTH).json()}
    assert client.get(f"/sessions/{sid}/map", headers=AUTH).status_code == 200
    assert (
        client.post(f"/sessions/{sid}/odometry", json={"t": 1.0, "v": 0.1, "omega": 0.0}, headers=AUTH).status_code
        == 200
    )
    listed = {t["id"] for t in client.get("/tokens", headers=AUTH).json()}
    assert not listed & {viewer_all["id"], viewer_one["id"], writer["id"]}
    assert client.delete(f"/sessions/{sid}", headers=AUTH).status_code == 204


def _close_watch(ws, seconds: float = 30.0) -> tuple[list[int], threading.Thread]:
    """A thread that reads ``ws`` (whatever was already on its way, of any kind) until it is
    closed or ``seconds`` pass, and the list it puts the close code in: a bounded wait, since a
    receive on a socket that is never closed would block the suite."""
    codes: list[int] = []

    def read() -> None:
        end = time.monotonic() + seconds
        try:
            while time.monotonic() < end:
                msg = ws.receive()
                if msg["type"] == "websocket.close":
                    codes.append(msg.get("code", 1000))
                    return
        except WebSocketDisconnect as e:
            codes.append(e.code)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    return codes, reader


def test_sockets_opened_before_a_revocation_are_closed(client):
    from server.security.auth import VIEWER_COOKIE
    from web.routes import COOKIE, SUBPROTOCOL

    assert COOKIE == VIEWER_COOKIE
    writer = client.post("/tokens", json={"role": "writer"}, headers=AUTH).json()
    w = _bearer(writer["token"])
    sid = client.post("/sessions", json={"name": "open sockets"}, headers=w).json()["id"]
    for k in range(5):
        client.post(f"/sessions/{sid}/odometry", json={"t": 0.1 * (k + 1), "v": 0.3, "omega": 0.1}, headers=w)
    viewer = client.post("/tokens", json={"role": "viewer", "session": sid}, headers=w).json()
    with (
        client.websocket_connect(f"/sessions/{sid}/stream", headers=w) as robot,
        client.websocket_connect(f"/viewer/{sid}?token={viewer['token']}", subprotocols=[SUBPROTOCOL]) as page,
    ):
        assert robot.receive_json()["type"] == "hello"
        robot.send_text(json.dumps({"type": "ping", "id": 1}))
        assert robot.receive_json()["type"] == "pong"
        assert page.receive_bytes()  # the scene flows
        assert client.delete(f"/tokens/{writer['id']}", headers=AUTH).status_code == 204  # revokes the viewer too
        # bounded waits (a receive on a socket that is never closed would block the suite)
        page_close, reader = _close_watch(page)
        deadline = time.monotonic() + 30.0
        robot_close = None
        while robot_close is None and time.monotonic() < deadline:
            try:
                robot.send_text(json.dumps({"type": "ping", "id": 2}))
                assert robot.receive_json()["type"] == "pong"  # still open: the check has not run yet
                time.sleep(0.2)
            except WebSocketDisconnect as e:
                robot_close = e.code
        assert robot_close == 4401
        reader.join(timeout=max(1.0, deadline - time.monotonic()))
        assert page_close == [4401]


@pytest.mark.parametrize("kind", ["sqlite", "postgres"])
def test_sessions_orphaned_by_an_older_server_go_to_the_admin(tmp_path, kind):
    if kind == "sqlite":
        store = SQLiteStore(tmp_path / "db.sqlite3")
    else:
        from server.storage.postgres import PostgresStore
        from tests.support.postgres_cluster import postgres_url_for

        store = PostgresStore(postgres_url_for(tmp_path, fresh=True))
    try:
        store.add_token(hash_secret("hm_w"), TokenRecord("tok_w", "writer", owner="admin")).result()
        store.add_token(hash_secret("hm_v"), TokenRecord("tok_v", "viewer", owner="tok_gone")).result()
        store.add_token(hash_secret("hm_k"), TokenRecord("tok_k", "viewer", owner="tok_w")).result()
        for sid, owner in (("s_1", "tok_gone"), ("s_2", "tok_w"), ("s_3", "admin")):
            store.create_session(SessionRecord(sid, owner)).result()
        assert adopt_orphans(store) == {"tok_gone": ["s_1"]}
        owners = {r.id: r.owner for r in store.list_sessions()}
        assert owners == {"s_1": "admin", "s_2": "tok_w", "s_3": "admin"}
        assert store.token_by_hash(hash_secret("hm_v")) is None  # the orphan's viewer is revoked
        assert store.token_by_hash(hash_secret("hm_k")) is not None  # a live writer's viewer is kept
        assert adopt_orphans(store) == {}
    finally:
        store.close()


# --------------------------------------------------------------------------- no secrets in logs
SECRET = "hm_s3cr3t_value_that_must_never_be_logged"


@pytest.mark.parametrize("fmt", ["json", "text"])
def test_log_lines_never_show_a_token(fmt):
    out = io.StringIO()
    configure(fmt, "info", stream=out)
    try:
        lg = logging.getLogger("hippomap.server")
        lg.info("GET /sessions/x/stats?limit=3&token=%s", SECRET)
        lg.info("headers %s", {"authorization": f"Bearer {SECRET}"})
        lg.info("raw Authorization: Basic dXNlcjpwYXNz and cookie token=abc%s", "def")
        lg.warning("extra", extra={"url": f"/viewer/?token={SECRET}"})
        try:
            raise ValueError(f"bad token {SECRET}")
        except ValueError:
            lg.exception("failed")
        access = logging.getLogger("uvicorn.access")
        access.setLevel(logging.INFO)
        access.info('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5", "GET", f"/sessions?token={SECRET}", "1.1", 200)
    finally:
        configure(fmt, "warning", stream=io.StringIO())
    text = out.getvalue()
    assert SECRET not in text and "dXNlcjpwYXNz" not in text and "abcdef" not in text, text
    assert text.count("[REDACTED]") >= 6
    if fmt == "json":
        lines = [json.loads(line) for line in text.splitlines()]
        acc = [x for x in lines if x["logger"] == "uvicorn.access"][0]
        assert acc["path"] == "/sessions?token=[REDACTED]" and acc["status"] == 200


def test_redaction_keeps_ordinary_text():
    for text in ("session s_1 created by token tok_ab12", "GET /sessions/s_1/map 200", "tokens: 3"):
        assert redact(text) == text
    rec = logging.LogRecord("x", logging.INFO, "x", 0, "a %s", (f"token={SECRET}",), None)
    assert RedactSecrets().filter(rec) and SECRET not in rec.getMessage()
    for fmt in (JSONFormatter(), TextFormatter()):
        rec = logging.LogRecord("x", logging.INFO, "x", 0, f"Bearer {SECRET}", None, None)
        assert SECRET not in fmt.format(rec)


# ------------------------------------------------------------------------------- origins
def test_origin_rule():
    check = OriginCheck(None, "https://ops.example.com, http://localhost:3000")
    assert check.allows(None, "hippo.example.com")  # robots send no Origin
    assert check.allows("https://hippo.example.com", "hippo.example.com")  # the server's own pages
    assert check.allows("http://hippo:8000", "hippo:8000")
    assert not check.allows("http://hippo:8001", "hippo:8000")
    assert not check.allows("https://evil.example", "hippo.example.com")
    assert not check.allows("null", "hippo.example.com")
    assert check.allows("https://ops.example.com", "hippo.example.com")
    assert check.allows("https://OPS.example.com:443", "hippo.example.com")
    assert check.allows("http://localhost:3000", "hippo:8000") and not check.allows("http://localhost:3001", "x")
    assert OriginCheck(None, "*").allows("https://anything.example", "h")


def test_websockets_refuse_other_origins(tmp_path):
    with TestClient(_app(tmp_path, allowed_origins="https://ops.example.com"), raise_server_exceptions=False) as c:
        sid = c.post("/sessions", json={"name": "ws"}, headers=AUTH).json()["id"]
        url = f"/sessions/{sid}/stream"
        with pytest.raises(WebSocketDisconnect) as exc:
            with c.websocket_connect(url, headers={**AUTH, "Origin": "https://evil.example"}):
                pass
        assert exc.value.code == 1008
        with pytest.raises(WebSocketDisconnect):
            with c.websocket_connect(f"/viewer/{sid}", headers={**AUTH, "Origin": "https://evil.example"}):
                pass
        for headers in ({}, {"Origin": "http://testserver"}, {"Origin": "https://ops.example.com"}):
            with c.websocket_connect(url, headers={**AUTH, **headers}) as ws:
                assert ws.receive_json()["type"] == "hello"
                ws.send_text(json.dumps({"type": "ping", "id": 1}))
                assert ws.receive_json()["type"] == "pong"


# ------------------------------------------------------------------------------- /metrics
def test_metrics_need_a_token_unless_public(tmp_path, monkeypatch):
    monkeypatch.delenv("HIPPOMAP_METRICS_TOKEN", raising=False)
    with TestClient(_app(tmp_path)) as c:
        assert c.get("/metrics").status_code == 401
        assert c.get("/metrics", headers=_bearer("hm_wrong")).status_code == 401
        writer = c.post("/tokens", json={"role": "writer"}, headers=AUTH).json()["token"]
        assert c.get("/metrics", headers=_bearer(writer)).status_code == 401  # it would see others' session ids
        assert c.get("/metrics", headers=AUTH).status_code == 200
    with TestClient(_app(tmp_path, metrics_token="hm_scrape")) as c:
        assert c.get("/metrics", headers=AUTH).status_code == 401
        assert c.get("/metrics", headers=_bearer("hm_scrape")).status_code == 200
    with TestClient(_app(tmp_path, metrics_public=True)) as c:
        assert "hippomap_ready" in c.get("/metrics").text


# ---------------------------------------------------------------------------- data files
def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_data_files_are_private(tmp_path):
    data = tmp_path / "data"
    with TestClient(create_app(ServerSettings(data_dir=data))) as c:  # generated admin token: a token file
        token = (data / "admin.token").read_text().strip()
        c.post("/sessions", json={"name": "x"}, headers=_bearer(token))
        files = sorted(p.name for p in data.iterdir())
        assert {"admin.token", "hippomap.sqlite3", "hippomap.sqlite3-wal", "hippomap.sqlite3-shm"} <= set(files)
        assert _mode(data) == 0o700
        for name in files:
            assert _mode(data / name) == 0o600, (name, oct(_mode(data / name)))
    # an older server's loose modes are tightened at the next start
    os.chmod(data, 0o755)
    os.chmod(data / "hippomap.sqlite3", 0o644)
    os.chmod(data / "admin.token", 0o644)
    with TestClient(create_app(ServerSettings(data_dir=data))):
        assert _mode(data) == 0o700 and _mode(data / "hippomap.sqlite3") == 0o600
        assert _mode(data / "admin.token") == 0o600


def test_a_database_elsewhere_is_created_private(tmp_path):
    db = tmp_path / "new" / "db.sqlite3"
    with TestClient(create_app(ServerSettings(data_dir=tmp_path / "d", admin_token=ADMIN, database=f"sqlite://{db}"))):
        assert _mode(db) == 0o600 and _mode(db.parent) == 0o700


# ------------------------------------------------------------------------- read budget
def test_a_flooding_reader_never_makes_ingest_429(tmp_path):
    app = _app(tmp_path, rate_per_s=1.0, rate_burst=30, read_rate_per_s=1.0, read_rate_burst=5)
    with TestClient(app) as c:
        sid = c.post("/sessions", json={"name": "flood"}, headers=AUTH).json()["id"]
        viewer = _bearer(c.post("/tokens", json={"role": "viewer", "session": sid}, headers=AUTH).json()["token"])
        codes = [c.get(f"/sessions/{sid}/stats", headers=viewer).status_code for _ in range(40)]
        assert codes[:5] == [200] * 5 and codes.count(429) >= 30
        r = c.get(f"/sessions/{sid}/stats", headers=viewer)
        assert r.status_code == 429 and "read rate" in r.json()["detail"] and int(r.headers["retry-after"]) >= 1
        # the owner's ingest budget is untouched, and its own reads have their own budget
        acks = [
            c.post(
                f"/sessions/{sid}/odometry", json={"t": 0.1 * (k + 1), "v": 0.1, "omega": 0.0}, headers=AUTH
            ).status_code
            for k in range(20)
        ]
        assert acks == [200] * 20
        assert c.get(f"/sessions/{sid}/stats", headers=AUTH).status_code == 200


# ------------------------------------------------- the live server: access log, files
def test_live_server_access_log_shows_no_token(tmp_path):
    srv = LiveServer(
        tmp_path / "data",
        token=ADMIN,
        args=["--access-log", "--log-level", "info"],
        env={"HIPPOMAP_LOG_FORMAT": "json"},
    ).start()
    try:
        with srv.client() as c:
            sid = c.create_session("logged")["id"]
        for _ in range(3):
            assert httpx.get(f"{srv.url}/sessions/{sid}/stats", params={"token": ADMIN}).status_code == 200
        assert httpx.get(f"{srv.url}/sessions", headers=AUTH).status_code == 200

        async def stream():
            async with websockets.connect(
                f"{srv.url.replace('http', 'ws', 1)}/sessions/{sid}/stream?token={ADMIN}", additional_headers=AUTH
            ) as ws:
                assert json.loads(await ws.recv())["type"] == "hello"
                await ws.send(json.dumps({"type": "ping", "id": 1}))
                return json.loads(await ws.recv())

        assert asyncio.run(stream())["type"] == "pong"
    finally:
        srv.stop()
    out = "".join(srv.output)
    assert "[REDACTED]" in out and ADMIN not in out, out[-3000:]
    assert any('"path": "/sessions/' in line and "token=[REDACTED]" in line for line in srv.output), out[-3000:]


# ----------------------------------------------------- the viewer's loopback viser server
def test_session_viewer_refuses_connections_without_its_key():
    from hippomap.config import HippomapConfig
    from web.routes import SUBPROTOCOL
    from web.session_viewer import KEY_HEADER, SessionViewer
    from web.source import LocalSession

    viewer = SessionViewer(LocalSession("s1", config=HippomapConfig()), start=False)
    try:
        url = f"ws://127.0.0.1:{viewer.port}"
        assert httpx.get(f"http://127.0.0.1:{viewer.port}/").status_code == 403
        assert httpx.get(f"http://127.0.0.1:{viewer.port}/", headers={KEY_HEADER: "wrong"}).status_code == 403

        async def attempt(headers):
            try:
                async with websockets.connect(
                    url, subprotocols=[SUBPROTOCOL], additional_headers=headers, open_timeout=10
                ) as ws:
                    return len(await asyncio.wait_for(ws.recv(), 10)) > 0
            except websockets.InvalidStatus as exc:
                return exc.response.status_code

        assert asyncio.run(attempt({})) == 403
        assert asyncio.run(attempt({KEY_HEADER: viewer.access_key[:-1]})) == 403
        assert asyncio.run(attempt({KEY_HEADER: viewer.access_key})) is True  # the proxy's way in: the scene
    finally:
        viewer.close()


def test_an_idle_socket_is_closed_when_its_token_is_revoked(client):
    """A robot that stopped sending (no message to check at) is still closed within about a
    second of its token's revocation, not at its next message."""
    writer = client.post("/tokens", json={"role": "writer"}, headers=AUTH).json()
    w = _bearer(writer["token"])
    sid = client.post("/sessions", json={"name": "idle socket"}, headers=w).json()["id"]
    with client.websocket_connect(f"/sessions/{sid}/stream", headers=w) as robot:
        assert robot.receive_json()["type"] == "hello"
        assert client.delete(f"/tokens/{writer['id']}", headers=AUTH).status_code == 204
        t0 = time.monotonic()
        closed, reader = _close_watch(robot)
        reader.join(timeout=15.0)
        assert closed == [4401]
        assert time.monotonic() - t0 < 10.0
