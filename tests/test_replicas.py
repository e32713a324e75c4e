"""Several server replicas sharing sessions through one PostgreSQL database.

Two real servers (``python -m server`` subprocesses) on the same database, each with its own
replica id: a session runs in exactly one of them (the lease holder); the other answers 421
naming it, over HTTP and the websocket. When the running replica is SIGKILLed, the other
takes the session over after the lease expires — restored from the snapshot plus replay
of the stored inputs — and the robot goes on streaming into it: nothing acknowledged is
lost and the session ends in the state of an uninterrupted run. A replica restarted while
the other holds the lease does not run the session a second time.
"""

from __future__ import annotations

import asyncio
import time

import httpx
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from tests.support.live import LiveServer, stream_items
from tests.support.postgres_cluster import postgres_url_for
from tests.support.reference import offline_reference, session_state
from tests.support.synthetic import synthetic_inputs

CONFIG = {"mapper": {"keyframe_interval": 3}}
ITEMS = synthetic_inputs(n_odometry=300, frame_every=3)  # closes loops (as in test_server_crash)
TTL = 1.5


def _replica(tmp_path, name: str, url: str) -> LiveServer:
    env = {
        "HIPPOMAP_DATABASE": url,
        "HIPPOMAP_REPLICA_ID": name,
        "HIPPOMAP_LEASE_TTL_S": str(TTL),
        "HIPPOMAP_SNAPSHOT_EVERY_INPUTS": "60",
    }
    return LiveServer(tmp_path / name, env=env)


def _get(srv: LiveServer, path: str) -> httpx.Response:
    return httpx.get(srv.url + path, headers={"Authorization": f"Bearer {srv.token}"}, timeout=30)


async def _ws_close_code(srv: LiveServer, sid: str) -> tuple[int, str]:
    url = srv.url.replace("http", "ws", 1) + f"/sessions/{sid}/stream"
    async with connect(url, additional_headers={"Authorization": f"Bearer {srv.token}"}) as ws:
        try:
            await ws.recv()
        except ConnectionClosed as exc:
            return exc.rcvd.code, exc.rcvd.reason
    return 0, ""


def test_one_replica_runs_a_session_and_the_other_takes_over_when_it_dies(tmp_path):
    url = postgres_url_for(tmp_path / "shared", fresh=True)
    a = _replica(tmp_path, "replica-a", url).start()
    b = _replica(tmp_path, "replica-b", url).start()
    try:
        with a.client() as ca:
            sid = ca.create_session("fleet", CONFIG)["id"]
        half = len(ITEMS) // 2
        acks = asyncio.run(stream_items(a.url, a.token, sid, ITEMS[:half]))
        assert [x["seq"] for x in acks] == list(range(half))

        # B knows the session (shared database) but does not run it: 421 naming A, HTTP and websocket
        r = _get(b, f"/sessions/{sid}/stats")
        assert r.status_code == 421 and r.json()["replica"] == "replica-a" and "replica-a" in r.json()["detail"]
        assert r.headers["X-Hippomap-Replica"] == "replica-a"
        code, reason = asyncio.run(_ws_close_code(b, sid))
        assert code == 4421 and "replica-a" in reason
        assert _get(b, "/sessions/s_0000000000000000/stats").status_code == 404  # unknown stays 404
        # both list it, each naming A as the replica that runs it (stats only where it runs)
        listed = {x["id"]: x for x in _get(b, "/sessions").json()}
        assert listed[sid]["replica"] == "replica-a" and listed[sid]["stats"] is None
        listed = {x["id"]: x for x in _get(a, "/sessions").json()}
        assert listed[sid]["replica"] == "replica-a" and listed[sid]["stats"]["inputs_stored"] == half
        # A runs it and B's /metrics shows no such session
        assert _get(a, f"/sessions/{sid}/stats").status_code == 200
        assert sid not in _get(b, "/metrics").text

        a.kill()  # crash: no lease release, no final snapshot
        time.sleep(TTL + 0.5)
        with b.client() as cb:
            st = cb.wait_processed(sid)  # B takes it over on this request: snapshot + replay
            assert st["inputs_stored"] == half
            assert session_state(cb, sid) == offline_reference(ITEMS[:half], CONFIG)
            acks2 = asyncio.run(stream_items(b.url, b.token, sid, ITEMS[half:]))
            assert [x["seq"] for x in acks2] == list(range(half, len(ITEMS)))
            final = session_state(cb, sid)
        assert final == offline_reference(ITEMS, CONFIG)
        assert final["stats"]["loop_closures_accepted"] > 0

        # A comes back with the same replica id while B holds the lease: it must not run the session too
        a2 = _replica(tmp_path, "replica-a", url).start()
        try:
            r = _get(a2, f"/sessions/{sid}/stats")
            assert r.status_code == 421 and r.json()["replica"] == "replica-b"
            # B renews its lease: still B's after several TTLs
            time.sleep(2 * TTL)
            assert _get(a2, f"/sessions/{sid}/stats").status_code == 421
            assert _get(b, f"/sessions/{sid}/stats").json()["inputs_stored"] == len(ITEMS)
        finally:
            a2.stop()
    finally:
        a.kill()
        b.stop()


def test_a_graceful_stop_hands_sessions_over_at_once(tmp_path):
    """A replica that stops cleanly writes its last snapshot and releases its leases: the other
    takes the session over on the next request without waiting for the lease to expire."""
    url = postgres_url_for(tmp_path / "shared", fresh=True)
    env_ttl = 60.0  # long: only the release can explain an immediate takeover
    a = LiveServer(
        tmp_path / "a", env={"HIPPOMAP_DATABASE": url, "HIPPOMAP_REPLICA_ID": "a", "HIPPOMAP_LEASE_TTL_S": str(env_ttl)}
    ).start()
    b = LiveServer(
        tmp_path / "b", env={"HIPPOMAP_DATABASE": url, "HIPPOMAP_REPLICA_ID": "b", "HIPPOMAP_LEASE_TTL_S": str(env_ttl)}
    ).start()
    try:
        from urllib.parse import urlsplit

        password = urlsplit(url).password
        banner = "".join(a.output)
        assert "data: PostgreSQL " in banner and password and password not in banner  # never print the secret
        items = ITEMS[:90]
        with a.client() as ca:
            sid = ca.create_session("handover", CONFIG)["id"]
        asyncio.run(stream_items(a.url, a.token, sid, items))
        assert _get(b, f"/sessions/{sid}/stats").status_code == 421
        a.stop()
        with b.client() as cb:
            st = cb.wait_processed(sid)
            assert st["snapshot_seq"] == len(items) - 1  # A's final snapshot: nothing to replay
            assert session_state(cb, sid) == offline_reference(items, CONFIG)
    finally:
        a.kill()
        b.stop()


@pytest.mark.parametrize("ttl", ["0", "-1", "abc"])
def test_bad_lease_ttl_is_refused_at_start(tmp_path, ttl):
    srv = LiveServer(tmp_path / "bad", env={"HIPPOMAP_LEASE_TTL_S": ttl})
    with pytest.raises(RuntimeError, match="lease_ttl_s"):
        srv.start(timeout=30)
