"""The server as a robot sees it: a real uvicorn on loopback (``python -m server`` in a subprocess).

* several sessions streaming at once over websockets each end in exactly the state of an
  in-process mapper fed the same inputs; the query endpoints serve that state;
* HTTP ingest (raw and multipart) is equivalent to the stream;
* every kind of bad input gets its own 4xx naming the problem, is never stored, and the
  session ends exactly as if only the good inputs had been sent;
* tokens: sessions are invisible (404) to other tokens; viewers read but never write;
* backpressure and the rate limit slow or tell the client, and nothing is lost.
"""

from __future__ import annotations

import asyncio
import io
import json
import re
import struct
import time

import cv2
import httpx
import networkx as nx
import numpy as np
import pytest
import websockets
from websockets.asyncio.client import connect

from hippomap.client import ServerError
from tests.support.live import LiveServer, stream_items
from tests.support.reference import offline_reference, session_state
from tests.support.synthetic import synthetic_inputs

CONFIG = {"mapper": {"keyframe_interval": 5}}
ITEMS = synthetic_inputs(n_odometry=300, frame_every=3)


@pytest.fixture(scope="module")
def server(tmp_path_factory, variant):
    env = {
        "HIPPOMAP_MAX_BODY_BYTES": "400000",
        "HIPPOMAP_MAX_FRAME_BYTES": "300000",
        "HIPPOMAP_MAX_IMAGE_SIDE": "2000",
        "HIPPOMAP_SNAPSHOT_EVERY_INPUTS": "150",
    }
    srv = variant.server(tmp_path_factory.mktemp("live"), env=env).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server):
    with server.client() as c:
        yield c


def _ws_url(server, sid):
    return server.url.replace("http", "ws", 1) + f"/sessions/{sid}/stream"


def test_concurrent_sessions_stream_and_match_the_offline_mapper(server, client):
    runs = [synthetic_inputs(n_odometry=300, frame_every=3, seed=s, speed=0.4 + 0.1 * s) for s in range(3)]
    sids = [client.create_session(f"robot{k}", CONFIG)["id"] for k in range(3)]

    async def all_at_once():
        return await asyncio.gather(
            *(stream_items(server.url, server.token, sid, items) for sid, items in zip(sids, runs))
        )

    acks = asyncio.run(all_at_once())
    for sid, items, session_acks in zip(sids, runs, acks):
        assert [a["seq"] for a in session_acks] == list(range(len(items)))  # every message acked, in order
        stored = client.all_inputs(sid)
        assert [(r["seq"], r["kind"], r["t"]) for r in stored] == [
            (k, "odometry" if it[0] == "odometry" else "frame", it[1].t if it[0] == "odometry" else it[1])
            for k, it in enumerate(items)
        ]
        assert session_state(client, sid) == offline_reference(items, CONFIG)
    listed = {s["id"] for s in client.sessions()}
    assert set(sids) <= listed


LOOPY = synthetic_inputs(n_odometry=400, frame_every=2, speed=0.6)  # closes loops: accepted and rejected
# the paper's rules (place-code gate with a tight radius, every key frame learned, the recent track
# recognised, online merging) reject some hypotheses, so both statuses are there to query
# relocalising onto the matched nodes, the circling robot also proposes closures that the gate rejects
LOOPY_CONFIG = {
    "mapper": {**CONFIG["mapper"], "recognition_min_path_m": 0.0, "learn_recognised": True},
    "map": {
        "loop_gate": "place_code",
        "loop_radius_m": 0.3,
        "loop_radius_per_m": 0.0,
        "loop_relocalise": True,
        "prune_online": True,
    },
}


def test_queries_serve_the_session_state(server, client):
    sid = client.create_session("queries", LOOPY_CONFIG)["id"]
    asyncio.run(stream_items(server.url, server.token, sid, LOOPY))
    st = client.wait_processed(sid)
    ref = offline_reference(LOOPY, LOOPY_CONFIG)
    g = client.map(sid)
    n_nodes, n_links = len(g["nodes"]), len(g["links"])
    assert n_nodes == st["mapper"]["nodes"] and n_links == st["mapper"]["links"] and n_nodes > 3

    # downloads
    g2o = client.map_g2o(sid).splitlines()
    assert sum(ln.startswith("VERTEX_SE2") for ln in g2o) == n_nodes
    assert sum(ln.startswith("EDGE_SE2") for ln in g2o) == n_links
    first = [float(x) for x in g2o[0].split()[2:5]]
    assert np.allclose(first, g["nodes"][0]["pose"], atol=1e-8)
    graph = nx.read_graphml(io.StringIO(client.map_graphml(sid)))
    assert graph.number_of_nodes() == n_nodes and graph.number_of_edges() == n_links
    for source in ("map", "odometry"):
        tum = [ln for ln in client.trajectory_tum(sid, source).splitlines() if ln and not ln.startswith("#")]
        assert len(tum) == st["mapper"]["odometry_steps"]

    # loop closures (accepted and rejected) and recognitions with their saccade traces
    loops = client.loop_closures(sid)
    assert [r["decision"] for r in loops] == ref["loop_closures"]
    # each with its link's robust weight now, and whether the map uses it (accepted, weight >= 0.5)
    assert [[r["weight"], r["used"]] for r in loops] == ref["loop_weights"]
    for r in loops:
        assert (r["weight"] is None) == (r["decision"]["link"] < 0)
        assert r["used"] == (r["status"] == "accepted" and (r["weight"] is None or r["weight"] >= 0.5))
    used = client.loop_closures(sid, used=True)
    assert used and [r["id"] for r in used] == [r["id"] for r in loops if r["used"]]
    assert [r["id"] for r in client.loop_closures(sid, used=False)] == [r["id"] for r in loops if not r["used"]]
    assert len(used) == st["mapper"]["loop_closures_used"]
    statuses = {r["status"] for r in loops}
    assert "accepted" in statuses and statuses - {"accepted"} <= {"pending", "rejected"} and len(statuses) > 1, statuses
    recs = client.recognitions(sid)
    assert len(recs) == len(ref["recognitions"]) > 0
    # each says which key frames competed, as the mapper's own record does
    assert [(r["search"], r["candidates"], r["primed"]) for r in recs] == [
        (r["search"], r["candidates"], r.get("primed")) for r in ref["recognitions"]
    ]
    assert all(r["search"] in ("gated", "global") and r["candidates"] >= 1 for r in recs)
    assert all(r["primed"] is None or 1 <= r["primed"] <= r["candidates"] for r in recs)
    for lc in loops:
        d = lc["decision"]
        assert lc["nodes"] == [d["from_node"], d["hypothesis"]["node"]] and lc["t"] == d["hypothesis"]["time"]
        assert lc["evidence"] == d["hypothesis"]["evidence"] and lc["source"] == "visual"
        assert lc["saccades"].endswith(f"/saccades/{lc['recognition']}")
        assert client.saccades(sid, lc["recognition"])["t"] == lc["t"]  # the recognition behind it
    accepted = client.loop_closures(sid, status="accepted")
    assert accepted and all(r["status"] == "accepted" for r in accepted)
    assert len(accepted) == st["mapper"]["loop_closures_accepted"]
    t_mid = sorted(r["t"] for r in loops)[len(loops) // 2]
    assert [r["id"] for r in client.loop_closures(sid, t_min=t_mid)] == [r["id"] for r in loops if r["t"] >= t_mid]
    assert [r["id"] for r in client.loop_closures(sid, t_max=t_mid)] == [r["id"] for r in loops if r["t"] <= t_mid]
    assert [r["id"] for r in client.loop_closures(sid, since_id=loops[2]["id"])] == [r["id"] for r in loops[3:]]
    trace = client.saccades(sid, recs[-1]["id"])
    assert trace == ref["recognitions"][-1] and len(trace["steps"]) == trace["n_fixations"]
    jpeg = client.saccade_image(sid, recs[-1]["id"])
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[:2] == (240, 320)
    with pytest.raises(ServerError) as e:
        client.saccades(sid, 10_000)
    assert e.value.status == 404

    # place fields: current and past, JSON / npy / PNG agree
    cur = client.place_field(sid)
    past = client.place_fields(sid, limit=10_000)
    assert cur["step"] == past[-1]["step"] and len(past) > 10
    mat = client.place_field(sid, fmt="npy")
    assert mat.shape == (cur["size"], cur["size"]) and int(mat.sum()) == len(cur["indices"]) > 0
    iy, ix = np.divmod(np.array(cur["indices"]), cur["size"])
    assert np.allclose(cur["centroid"], [ix.mean() * cur["resolution"], iy.mean() * cur["resolution"]])
    # the PNG is the paper's Fig. 8 for this step (binarised matrices and the shrinking product):
    # a real figure, not a one-pixel image
    png = cv2.imdecode(np.frombuffer(client.place_field(sid, fmt="png"), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert png is not None and png.shape[0] > 200 and png.shape[1] > 400 and png.std() > 10
    old = client.place_field(sid, step=past[3]["step"])
    assert old["t"] == past[3]["t"] and old["step"] == past[3]["step"]

    # events: everything the mapper reported, in order, pageable
    events = client.events(sid, limit=10_000)
    assert [e["id"] for e in events] == list(range(len(events)))
    assert sum(e["type"] == "recognition" for e in events) == len(recs)
    assert client.events(sid, since_id=events[-2]["id"]) == events[-1:]
    # frames come back exactly as sent
    frame_seq = next(k for k, it in enumerate(LOOPY) if it[0] == "frame")
    assert client.frame(sid, frame_seq) == LOOPY[frame_seq][2]
    # the OpenAPI document lists every route
    paths = client._http.get("/openapi.json").json()["paths"]
    for p in (
        "/sessions",
        "/sessions/{session_id}/odometry",
        "/sessions/{session_id}/frames",
        "/sessions/{session_id}/map.graphml",
        "/sessions/{session_id}/loop-closures",
        "/sessions/{session_id}/place-fields/{step}/png",
        "/sessions/{session_id}/saccades/{recognition_id}/image",
        "/tokens",
    ):
        assert p in paths


def test_http_ingest_raw_and_multipart_equals_the_stream(server, client):
    items = ITEMS[:120]
    sid = client.create_session("http", CONFIG)["id"]
    batch = []
    for k, it in enumerate(items):
        if it[0] == "odometry":
            batch.append(it[1])
            continue
        if batch:
            ack = client.send_odometry(sid, batch)
            assert ack["count"] == len(batch)
            batch = []
        ack = client.send_frame(sid, it[1], it[2], multipart=bool(k % 2))
        assert ack["seq"] == ack["last_seq"] == k
    if batch:
        client.send_odometry(sid, batch)
    assert session_state(client, sid) == offline_reference(items, CONFIG)


def _status(fn, *args, **kw):
    try:
        fn(*args, **kw)
    except ServerError as exc:
        return exc.status, str(exc.detail)
    return 200, ""


def test_bad_inputs_get_their_4xx_and_the_session_stays_correct(server, client):
    items = ITEMS[:90]
    sid = client.create_session("bad inputs", CONFIG)["id"]
    jpeg = next(it[2] for it in items if it[0] == "frame")
    big = np.zeros((1100, 2100), np.uint8)
    noisy = np.random.default_rng(0).integers(0, 255, (600, 900), dtype=np.uint8)
    tiny = cv2.imencode(".jpg", np.full((20, 20), 9, np.uint8))[1].tobytes()
    gif = b"GIF89a" + bytes(300)
    h = client._http

    def raw_post(path, content, ctype="application/json"):
        return h.post(f"/sessions/{sid}/{path}", content=content, headers={"Content-Type": ctype})

    good_sent = 0
    last_odo = last_frame = None
    for k, it in enumerate(items):
        t_last = items[k - 1][1].t if k and items[k - 1][0] == "odometry" else (items[k - 1][1] if k else 0.0)
        # a bad input of every kind before each good one, rotating
        kind = k % 14
        if kind == 0:
            assert _status(client.send_odometry, sid, {"t": t_last + 1e-4, "v": float("nan"), "omega": 0})[0] == 422
        elif kind == 1:
            code, msg = _status(client.send_odometry, sid, {"t": t_last + 1e-4, "v": 0.1, "omega": float("inf")})
            assert code == 422 and "omega must be finite" in msg
        elif kind == 2 and last_odo is not None:  # timestamps must increase within each stream
            code, msg = _status(client.send_odometry, sid, {"t": last_odo, "v": 0.1, "omega": 0.0})
            assert code == 409 and "does not follow" in msg
            if last_frame is not None:
                code, msg = _status(client.send_frame, sid, last_frame - 0.01, jpeg)
                assert code == 409 and "frame timestamp" in msg
        elif kind == 3:
            r = raw_post("odometry", b'{"readings": [{"t": 1e9, "v": 0.1}]}')
            assert r.status_code == 422 and "v and omega" in r.text
        elif kind == 4:
            r = raw_post("odometry", b'{"readings": [{"t": 1e9, "v": "fast", "omega": 0}]}')
            assert r.status_code == 422 and "readings" in r.text
        elif kind == 5:
            code, msg = _status(client.send_frame, sid, t_last + 1e-4, jpeg[: len(jpeg) // 2])
            assert code == 422 and "corrupt" in msg
        elif kind == 6:
            code, msg = _status(client.send_frame, sid, t_last + 1e-4, gif)
            assert code == 415 and "JPEG" in msg
        elif kind == 7:
            code, msg = _status(client.send_frame, sid, t_last + 1e-4, jpeg + bytes(450_000))
            assert code == 413 and "limit" in msg
        elif kind == 8:
            truncated = cv2.imencode(".png", noisy)[1].tobytes()[:390_000]
            code, msg = _status(client.send_frame, sid, t_last + 1e-4, truncated)
            assert code in (413, 422)  # oversize frame bytes (413) or truncated (422): either names the problem
            code, msg = _status(client.send_frame, sid, t_last + 1e-4, cv2.imencode(".jpg", big)[1].tobytes())
            assert code == 413 and "2100x1100" in msg
        elif kind == 9:
            code, msg = _status(client.send_frame, sid, t_last + 1e-4, tiny)
            assert code == 422 and "too small" in msg
        elif kind == 10:
            code, msg = _status(client.send_frame, sid, float("nan"), jpeg)
            assert code == 422 and "finite" in msg
        elif kind == 11:
            r = raw_post("frames", jpeg, "image/jpeg")  # no ?t=
            assert r.status_code == 422 and "timestamp" in r.text
            r = raw_post("frames", jpeg, "text/plain")
            assert r.status_code == 415
        elif kind == 12:
            r = raw_post("odometry", b"x" * 500_000)
            assert r.status_code == 413 and "400000" in r.text
            r = raw_post("odometry", b'{"readings": [')
            assert r.status_code == 422
        elif kind == 13:
            code, msg = _status(
                client.send_odometry,
                sid,
                [{"t": t_last + 1.0, "v": 0, "omega": 0}, {"t": t_last + 0.5, "v": 0, "omega": 0}],
            )
            assert code == 409 and "readings[1]" in msg
        if it[0] == "odometry":
            client.send_odometry(sid, it[1])
            last_odo = it[1].t
        else:
            client.send_frame(sid, it[1], it[2])
            last_frame = it[1]
        good_sent += 1

    async def bad_stream():
        async with connect(_ws_url(server, sid), additional_headers={"Authorization": f"Bearer {server.token}"}) as ws:
            hello = json.loads(await ws.recv())
            t = hello["last_t"]
            assert hello["last_odometry_t"] == last_odo and hello["last_frame_t"] == last_frame
            msgs = [
                (
                    "text",
                    json.dumps({"type": "odometry", "id": 1, "t": t + 1, "v": "NaN", "omega": 0}).replace(
                        '"NaN"', "NaN"
                    ),
                    422,
                ),
                ("text", "{not json", 422),
                ("text", json.dumps({"type": "teleport", "id": 3}), 422),
                ("text", json.dumps({"type": "odometry", "id": 4, "t": last_odo, "v": 0, "omega": 0}), 409),
                ("bytes", b"HMF1\x05\x00", 422),
                ("bytes", b"XXXX" + struct.pack("<Id", 6, t + 1) + jpeg, 422),
                ("bytes", b"HMF1" + struct.pack("<Id", 7, t + 1) + gif, 415),
                ("bytes", b"HMF1" + struct.pack("<Id", 8, t + 1) + jpeg[:-300], 422),
            ]
            out = []
            for _kind, payload, status in msgs:
                await ws.send(payload)
                reply = json.loads(await ws.recv())
                out.append((reply["type"], reply["status"], status, reply["detail"]))
            await ws.send(json.dumps({"type": "ping", "id": 99}))
            pong = json.loads(await ws.recv())
            return out, pong

    replies, pong = asyncio.run(bad_stream())
    for typ, got, want, detail in replies:
        assert typ == "error" and got == want and detail
    assert pong == {"type": "pong", "id": 99}
    stored = client.all_inputs(sid)
    assert len(stored) == good_sent == len(items)
    st = client.stats(sid)
    assert st["error"] is None and sum(st["rejected"].values()) >= 20
    assert session_state(client, sid) == offline_reference(items, CONFIG)


def test_tokens_isolate_sessions(server, client):
    sid = client.create_session("mine", CONFIG)["id"]
    client.send_odometry(sid, ITEMS[0][1])
    other = client.create_token("writer", label="robot B")
    viewer = client.create_token("viewer", label="viewer of all")
    viewer_one = client.create_token("viewer", session=sid, label="viewer of one")
    sid2 = client.create_session("mine too", CONFIG)["id"]
    from hippomap.client import Client

    with (
        Client(server.url, other["token"]) as b,
        Client(server.url, viewer["token"]) as v,
        Client(server.url, viewer_one["token"]) as v1,
        Client(server.url, "hm_nobody") as nobody,
    ):
        assert b.sessions() == []
        for call, args in [
            (b.session, (sid,)),
            (b.map, (sid,)),
            (b.stats, (sid,)),
            (b.delete_session, (sid,)),
            (b.send_odometry, (sid, {"t": 99.0, "v": 0, "omega": 0})),
            (b.place_fields, (sid,)),
            (b.frame, (sid, 0)),
            (b.inputs, (sid,)),
        ]:
            assert _status(call, *args)[0] == 404, call.__name__
        bs = b.create_session("B's")["id"]
        assert _status(client.session, bs)[0] == 404  # even the admin cannot see B's session
        assert _status(b.create_token, "writer")[0] == 403 and _status(b.create_token, "viewer", sid)[0] == 404
        assert {sid, sid2} <= {s["id"] for s in v.sessions()}
        assert v.map(sid)["nodes"] is not None and v.stats(sid)["inputs_stored"] == 1
        for call, args in [
            (v.send_odometry, (sid, {"t": 99.0, "v": 0, "omega": 0})),
            (v.delete_session, (sid,)),
            (v.create_session, ("x",)),
            (v.create_token, ("viewer",)),
        ]:
            assert _status(call, *args)[0] == 403, call.__name__
        assert [s["id"] for s in v1.sessions()] == [sid] and _status(v1.map, sid2)[0] == 404
        assert _status(nobody.sessions)[0] == 401 and _status(nobody.map, sid)[0] == 401
        # ?token= works for browsers on GET
        url = f"{server.url}/sessions/{sid}/stats"
        assert httpx.get(url, params={"token": viewer["token"]}).status_code == 200
        assert httpx.get(url, params={"token": "hm_nobody"}).status_code == 401

        async def ws_close(token, session):
            async with connect(_ws_url(server, session), additional_headers={"Authorization": f"Bearer {token}"}) as ws:
                try:
                    await ws.recv()
                except websockets.ConnectionClosed as exc:
                    return exc.rcvd.code
            return None

        assert asyncio.run(ws_close(other["token"], sid)) == 4404
        assert asyncio.run(ws_close(viewer["token"], sid)) == 4403
        assert asyncio.run(ws_close("hm_nobody", sid)) == 4401
        # revoking a token locks it out
        client.delete_token(viewer_one["id"])
        assert _status(v1.sessions)[0] == 401
        b.delete_session(bs)
    assert client.stats(sid)["inputs_stored"] == 1


def test_invalid_config_overrides_are_422(client):
    for cfg, text in [({"map": {"alpha": 2.0}}, "alpha"), ({"nope": {}}, "nope"), ({"map": {"bogus": 1}}, "bogus")]:
        code, msg = _status(client.create_session, "bad", cfg)
        assert code == 422 and text in msg


def test_backpressure_and_rate_limit_slow_or_tell_and_lose_nothing(tmp_path, variant):
    env = {
        "HIPPOMAP_MAX_PENDING": "3",
        "HIPPOMAP_BACKPRESSURE_WAIT_S": "0",
        "HIPPOMAP_RATE_PER_S": "40",
        "HIPPOMAP_RATE_BURST": "40",
        "HIPPOMAP_READ_RATE_PER_S": "40",
        "HIPPOMAP_READ_RATE_BURST": "40",
    }
    config = {"mapper": {"keyframe_interval": 1}}  # every frame is learned: the mapper is the bottleneck
    items = synthetic_inputs(n_odometry=50, frame_every=1, seed=7)
    from hippomap.client import AsyncStream

    with variant.server(tmp_path / "bp", env=env) as srv, srv.client() as c:
        # websocket: the server stops reading when the queue is full and says so; all is acked
        sid = c.create_session("ws", config)["id"]

        async def stream():
            async with AsyncStream(srv.url, srv.token, sid, max_in_flight=64) as st:
                futs = [
                    await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2]))
                    for it in items
                ]
                return await asyncio.gather(*futs), st.busy_notices

        acks, busy = asyncio.run(stream())
        assert [a["seq"] for a in acks] == list(range(len(items))) and busy > 0
        # HTTP: a full queue answers 429 with Retry-After; the robot retries; nothing is lost.
        # Batches of 100 readings: one fits only into an empty queue, so the next one, sent while the
        # mapper still works on it, is told the session is busy.
        sid2 = c.create_session("http", config)["id"]
        odo = [it[1] for it in synthetic_inputs(n_odometry=500, frame_every=10**6, seed=8) if it[0] == "odometry"]
        told = {"busy": 0, "rate": 0}
        for k in range(0, len(odo), 100):
            while True:
                try:
                    c.send_odometry(sid2, odo[k : k + 100])
                    break
                except ServerError as exc:
                    assert exc.status == 429, exc
                    told["busy" if "busy" in str(exc.detail) else "rate"] += 1
                    time.sleep(0.01)
        assert told["busy"] > 0
        c.wait_processed(sid2)
        r = c._http.post(
            f"/sessions/{sid2}/odometry",
            content=json.dumps({"readings": [{"t": 1e6 + 0.05 * i, "v": 0.5, "omega": 0.3} for i in range(2000)]}),
            headers={"Content-Type": "application/json"},
        )
        r2 = c._http.post(
            f"/sessions/{sid2}/odometry",
            content=json.dumps({"readings": [{"t": 2e6 + i, "v": 0, "omega": 0} for i in range(100)]}),
            headers={"Content-Type": "application/json"},
        )
        assert r.status_code == 200 and r2.status_code == 429 and r2.headers["Retry-After"] == "1" and "busy" in r2.text

        # reads have a rate limit too (their own budget, per token: see test_hardening_api)
        async def burst():
            async with httpx.AsyncClient(base_url=srv.url, headers={"Authorization": f"Bearer {srv.token}"}) as h:
                return await asyncio.gather(
                    *(h.get(f"/sessions/{sid2}/events", params={"limit": 1}) for _ in range(80))
                )

        limited = [r for r in asyncio.run(burst()) if r.status_code == 429]
        assert limited and "rate limit" in limited[0].text and int(limited[0].headers["Retry-After"]) >= 1
        time.sleep(1.1)
        assert c.wait_processed(sid2)["inputs_stored"] == len(odo) + 2000
        assert [x["seq"] for x in c.all_inputs(sid2)] == list(range(len(odo) + 2000))
        assert [x["seq"] for x in c.all_inputs(sid)] == list(range(len(items)))
        assert session_state(c, sid) == offline_reference(items, config)


def test_serve_demo_streams_a_simulated_robot_and_prints_the_viewer_url(tmp_path):
    with LiveServer(tmp_path / "demo", args=["--demo", "--demo-rate", "20"]) as srv:
        deadline = time.monotonic() + 60
        while not any("viewer:" in line for line in srv.output) and time.monotonic() < deadline:
            time.sleep(0.1)
        line = next(line for line in srv.output if "viewer:" in line)
        m = re.search(r"(http://\S+)/viewer/(s_[0-9a-f]+)/\?token=(hm_\S+)", line)
        assert m and m.group(1) == srv.url
        sid, viewer_token = m.group(2), m.group(3)
        page = httpx.get(f"{srv.url}/viewer/{sid}/", params={"token": viewer_token}, timeout=30)
        assert page.status_code == 200 and "text/html" in page.headers["content-type"]
        from hippomap.client import Client

        with Client(srv.url, viewer_token) as viewer:  # the printed token reads that session
            while viewer.stats(sid)["processed_seq"] < 40 and time.monotonic() < deadline:
                time.sleep(0.2)
            st = viewer.stats(sid)
            assert st["processed_seq"] >= 40 and st["error"] is None
            kinds = {r["kind"] for r in viewer.inputs(sid)}
            assert kinds == {"odometry", "frame"}
            assert _status(viewer.send_odometry, sid, {"t": 1e9, "v": 0, "omega": 0})[0] == 403
