"""The landing page ``GET /``: the first address ``hippomap serve`` prints, for a person with a browser.

It says what the service is and links to the API docs (``/docs``, ``/redoc``) and the live viewer
(``/viewer/``). Authentication is the viewer's (:mod:`web.routes`): the token is read from
``Authorization: Bearer``, the ``token`` query parameter, or the viewer's cookie, and a token given
in the query is kept in the viewer's HttpOnly, SameSite=Strict cookie (limited to ``/viewer``, as
the viewer sets it), so that the session links open without typing it again.

* With a valid token: the sessions that token may see (exactly those of ``GET /sessions``), each
  with its viewer link and statistics (nodes, loop closures, inputs stored, pending).
* Without one: how to get a token (the admin token file, ``POST /tokens``) and a form to enter it;
  never a session.
* With an invalid one: 401, the same explanation, and no session.
"""

from __future__ import annotations

import asyncio
import html
from typing import Annotated, Any
from urllib.parse import quote

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse, Response

from hippomap import __version__

from .routes import _remember, token_from  # the viewer's token rules

router = APIRouter(tags=["server"])

STYLE = """body{font-family:system-ui,sans-serif;max-width:60rem;margin:2rem auto;padding:0 1rem;color:#222}
table{border-collapse:collapse;margin:.5rem 0}td,th{padding:.25rem .7rem;border-bottom:1px solid #ddd;text-align:left}
td.n{text-align:right;font-variant-numeric:tabular-nums}code,pre{background:#eee;padding:0 .2em}
pre{padding:.5em;overflow-x:auto}
.d{color:#777;font-size:.9em}nav a{margin-right:1.2rem}"""


def _page(body: str, status: int = 200) -> HTMLResponse:
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>hippomap server</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{STYLE}</style></head>
<body><h1>hippomap server <span class="d">{html.escape(__version__)}</span></h1>
<p>A bio-inspired SLAM service: robots stream odometry and camera frames into sessions, and each
session's mapper builds a cognitive map the way the rat hippocampus is thought to (grid cells, place
cells, a visual recognition memory that closes loops).</p>
<nav><a href="/docs">API docs (Swagger UI)</a><a href="/redoc">API reference (ReDoc)</a>
<a href="/viewer/">Live viewer</a><a href="/health">Health</a></nav>
{body}</body></html>"""
    # no-store: the page may list a token's sessions; no-referrer: a token in the URL never leaves it
    headers = {"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"}
    return HTMLResponse(doc, status_code=status, headers=headers)


def how_to_get_a_token(message: str, base_url: str) -> str:
    """The explanation and form shown without a (valid) token; ``base_url`` is this server's address."""
    return f"""<h2>Sign in</h2><p id="no-token">{html.escape(message)}</p>
<form method="get" action="/"><label>Token <input name="token" type="password" size="50" autocomplete="off"></label>
<button>Show my sessions</button></form>
<h2>Getting a token</h2>
<ul><li>The <b>admin token</b> is printed by <code>hippomap serve</code> at its first start and kept in the file
<code>admin.token</code> in the server's data folder (or set by <code>HIPPOMAP_ADMIN_TOKEN</code>).</li>
<li>A writer (or the admin) mints a read-only <b>viewer token</b>, for all its sessions or one of them, with
<code>POST /tokens</code>:
<pre>curl -X POST -H "Authorization: Bearer $HIPPOMAP_TOKEN" -H "Content-Type: application/json" \\
     -d '{{"role": "viewer", "label": "dashboard"}}' {html.escape(base_url.rstrip("/"))}/tokens</pre>
The admin also mints <b>writer tokens</b> for robots (<code>"role": "writer"</code>).</li></ul>"""


def _number(stats: dict[str, Any] | None, *path: str) -> str:
    value: Any = stats
    for key in path:
        value = value.get(key) if isinstance(value, dict) else None
    return "–" if value is None else html.escape(str(value))


def session_rows(entries: list[dict[str, Any]]) -> str:
    """The table of the token's sessions: name and id, viewer link, statistics."""
    if not entries:
        return (
            "<p id='sessions'>No sessions yet. A robot creates one with <code>POST /sessions</code> "
            "(or try <code>hippomap serve --demo</code>).</p>"
        )
    rows = []
    for e in entries:
        st = e["stats"]
        sid = html.escape(e["id"])
        link = f"/viewer/{quote(e['id'], safe='')}/"
        where = "" if st is not None else f" <span class='d'>(runs on replica {html.escape(e['replica'])})</span>"
        error = f" <span class='d'>error: {html.escape(str(st['error']))}</span>" if st and st.get("error") else ""
        rows.append(
            f"<tr data-session='{sid}'><td>{html.escape(e['name'] or e['id'])}<br><span class='d'>{sid}</span>{where}"
            f"{error}</td><td><a href='{link}'>viewer</a></td>"
            f"<td class='n'>{_number(st, 'mapper', 'nodes')}</td>"
            f"<td class='n'>{_number(st, 'mapper', 'loop_closures_used')}</td>"
            f"<td class='n'>{_number(st, 'mapper', 'loop_closures_accepted')}</td>"
            f"<td class='n'>{_number(st, 'mapper', 'loop_closures_rejected')}</td>"
            f"<td class='n'>{_number(st, 'inputs_stored')}</td><td class='n'>{_number(st, 'pending')}</td></tr>"
        )
    return (
        "<table id='sessions'><thead><tr><th>session</th><th></th><th>nodes</th><th>loop closures used</th>"
        "<th>accepted</th><th>rejected</th><th>inputs</th><th>pending</th></tr></thead><tbody>"
        + "".join(rows)
        + "</tbody></table>"
    )


async def visible_sessions(request: Request, token: Any) -> list[dict[str, Any]]:
    """The sessions ``token`` may see, newest first, with their statistics (None for those another
    replica runs): what ``GET /sessions`` answers."""
    manager = request.app.state.manager
    lives = sorted(manager.visible(token), key=lambda s: -s.record.created)
    stats = await asyncio.gather(*(asyncio.to_thread(s.stats) for s in lives))
    out = [{"id": s.id, "name": s.record.name, "stats": st, "replica": s.replica} for s, st in zip(lives, stats)]
    elsewhere = await asyncio.to_thread(manager.visible_elsewhere, token)
    return out + [{"id": r.id, "name": r.name, "stats": None, "replica": owner} for r, owner in elsewhere]


@router.get(
    "/",
    response_class=HTMLResponse,
    summary="Landing page (HTML): links to the docs and the viewer; with a token, its sessions and their statistics",
    responses={
        401: {
            "content": {"text/html": {}},
            "description": "a token was given but is not valid: how to get one, no sessions",
        }
    },
)
async def landing(
    request: Request,
    token: Annotated[
        str | None,
        Query(
            description="a token, for a browser (also read from Authorization: Bearer or the viewer's cookie); "
            "kept in the viewer's cookie for /viewer"
        ),
    ] = None,
) -> Response:
    secret = token_from(request.headers, request.query_params, request.cookies)
    if not secret:
        return _page(how_to_get_a_token("Give a token to see your sessions.", str(request.base_url)))
    tok = request.app.state.auth.authenticate(secret)
    if tok is None:
        return _page(how_to_get_a_token("That token is not valid.", str(request.base_url)), status=401)
    entries = await visible_sessions(request, tok)
    who = f"{html.escape(tok.role)} token <code>{html.escape(tok.id)}</code>"
    response = _page(f"<h2>Sessions</h2><p class='d'>Visible to the {who}.</p>{session_rows(entries)}")
    _remember(response, request, secret)
    return response
