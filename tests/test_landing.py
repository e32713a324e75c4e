"""The landing page ``GET /``: links to the docs and the viewer; with a token, exactly that token's
sessions with their viewer links and statistics; without one, how to get a token and no session."""

from __future__ import annotations

import re
import time
from html import unescape

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.settings import ServerSettings

ADMIN = "hm_landing_admin_token_0123456789"


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _rows(page: str) -> dict[str, list[str]]:
    """The sessions table of a landing page: session id -> its cells' text."""
    rows = {}
    for sid, body in re.findall(r"<tr data-session='([^']+)'>(.*?)</tr>", page, re.DOTALL):
        rows[unescape(sid)] = [
            unescape(re.sub(r"<[^>]+>", " ", c)).strip() for c in re.findall(r"<td[^>]*>(.*?)</td>", body, re.DOTALL)
        ]
    return rows


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """A service with two writers' sessions: the admin's "admin lap" (fed odometry) and a writer's "writer lap"."""
    app = create_app(ServerSettings(data_dir=tmp_path_factory.mktemp("landing") / "data", admin_token=ADMIN))
    with TestClient(app) as c:
        writer = c.post("/tokens", json={"role": "writer", "label": "robot"}, headers=_bearer(ADMIN)).json()["token"]
        mine = c.post("/sessions", json={"name": "admin lap"}, headers=_bearer(ADMIN)).json()["id"]
        other = c.post("/sessions", json={"name": "writer lap <b>"}, headers=_bearer(writer)).json()["id"]
        readings = [{"t": 0.1 * (k + 1), "v": 0.5, "omega": 0.3} for k in range(60)]
        sent = c.post(f"/sessions/{mine}/odometry", json={"readings": readings}, headers=_bearer(ADMIN))
        assert sent.status_code == 200
        deadline = time.monotonic() + 60
        while c.get(f"/sessions/{mine}/stats", headers=_bearer(ADMIN)).json()["pending"] > 0:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        yield c, writer, mine, other


def test_without_a_token_it_explains_how_to_get_one_and_lists_nothing(service):
    c, writer, mine, other = service
    r = c.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert r.headers["cache-control"] == "no-store"
    for link in ('href="/docs"', 'href="/redoc"', 'href="/viewer/"'):
        assert link in r.text
    assert "admin.token" in r.text and "POST /tokens" in r.text and 'name="token"' in r.text
    assert "http://testserver/tokens" in r.text  # the command to mint a token names this server
    assert _rows(r.text) == {} and mine not in r.text and other not in r.text and "admin lap" not in r.text
    assert "set-cookie" not in r.headers


def test_an_invalid_token_is_refused_and_lists_nothing(service):
    c, writer, mine, other = service
    for r in (c.get("/", params={"token": "hm_not_a_token"}), c.get("/", headers=_bearer("hm_not_a_token"))):
        assert r.status_code == 401
        assert "not valid" in r.text and "POST /tokens" in r.text
        assert _rows(r.text) == {} and mine not in r.text and other not in r.text
        assert "set-cookie" not in r.headers


def test_a_token_sees_its_sessions_with_viewer_links_and_statistics(service):
    c, writer, mine, other = service
    r = c.get("/", headers=_bearer(ADMIN))
    assert r.status_code == 200
    rows = _rows(r.text)
    assert list(rows) == [mine]  # the writer's session is not the admin's
    assert f"href='/viewer/{mine}/'" in r.text and "admin lap" in rows[mine][0]
    stats = c.get(f"/sessions/{mine}/stats", headers=_bearer(ADMIN)).json()
    nodes, used, accepted, rejected, inputs, pending = rows[mine][2:]
    assert int(inputs) == stats["inputs_stored"] == 60 and int(pending) == 0
    assert int(nodes) == stats["mapper"]["nodes"] >= 1
    assert (int(used), int(accepted), int(rejected)) == (
        stats["mapper"]["loop_closures_used"],
        stats["mapper"]["loop_closures_accepted"],
        stats["mapper"]["loop_closures_rejected"],
    )
    # the writer sees its own session only; its name is escaped
    page = c.get("/", headers=_bearer(writer)).text
    assert list(_rows(page)) == [other] and "writer lap &lt;b&gt;" in page and "<b>" not in page.split("<body>")[1]
    assert mine not in page


def test_a_viewer_token_sees_what_its_writer_lets_it_see(service):
    c, writer, mine, other = service
    everything = c.post("/tokens", json={"role": "viewer"}, headers=_bearer(ADMIN)).json()["token"]
    assert list(_rows(c.get("/", headers=_bearer(everything)).text)) == [mine]
    second = c.post("/sessions", json={"name": "second"}, headers=_bearer(ADMIN)).json()["id"]
    one = c.post("/tokens", json={"role": "viewer", "session": second}, headers=_bearer(ADMIN)).json()["token"]
    assert list(_rows(c.get("/", headers=_bearer(one)).text)) == [second]
    assert set(_rows(c.get("/", headers=_bearer(everything)).text)) == {mine, second}
    assert c.delete(f"/sessions/{second}", headers=_bearer(ADMIN)).status_code == 204


def test_a_token_in_the_query_opens_the_viewer_links_like_the_viewer_does(tmp_path):
    """?token= on / is kept in the viewer's own cookie (HttpOnly, SameSite=Strict, path /viewer): the
    session links then open without the token, and the cookie is not sent to the API."""
    app = create_app(ServerSettings(data_dir=tmp_path / "data", admin_token=ADMIN))
    with TestClient(app) as c:
        sid = c.post("/sessions", json={"name": "linked"}, headers=_bearer(ADMIN)).json()["id"]
        r = c.get("/", params={"token": ADMIN})
        assert r.status_code == 200 and list(_rows(r.text)) == [sid]
        assert r.headers["referrer-policy"] == "no-referrer"
        cookie = r.headers["set-cookie"].lower()
        assert cookie.startswith("hippomap_viewer=") and "httponly" in cookie and "samesite=strict" in cookie
        assert "path=/viewer" in cookie
        # the browser now presents the token to the viewer, not to / nor to the API
        assert sid in c.get("/viewer/").text
        assert _rows(c.get("/").text) == {}
        assert c.get("/sessions").status_code == 401
