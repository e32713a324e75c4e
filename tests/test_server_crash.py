"""Nothing acknowledged is ever lost: the server is killed with SIGKILL in the middle of a
websocket stream, restarted on the same data folder, and must hold every acknowledged input
and a session in exactly the state an uninterrupted run reaches."""

from __future__ import annotations

import asyncio
import time

from hippomap.client import AsyncStream
from tests.support.live import LiveServer, stream_items
from tests.support.reference import offline_reference, session_state
from tests.support.synthetic import synthetic_inputs
from tests.support.variants import ServiceVariant

CONFIG = {"mapper": {"keyframe_interval": 3}}
ITEMS = synthetic_inputs(n_odometry=300, frame_every=3)  # loops are closed before and after the crash
ENV = {"HIPPOMAP_SNAPSHOT_EVERY_INPUTS": "40"}


def _kind_t(it):
    return ("odometry", it[1].t) if it[0] == "odometry" else ("frame", it[1])


async def _stream_until_killed(server: LiveServer, sid: str, first_part: int, kill_after: int) -> list[dict]:
    """Stream ``first_part`` items and wait until the session has a snapshot; then stream the
    rest and SIGKILL the server as soon as ``kill_after`` acks in all have arrived."""
    acks: list[dict] = []

    def on_ack(fut: asyncio.Future) -> None:
        if fut.exception() is None:
            acks.append(fut.result())
            if len(acks) == kill_after:
                server.kill()

    def snapshot_taken() -> None:
        with server.client() as c:
            while c.stats(sid)["snapshot_seq"] < 0:
                time.sleep(0.05)

    try:
        async with AsyncStream(server.url, server.token, sid, max_in_flight=32) as st:
            for k, it in enumerate(ITEMS):
                if k == first_part:
                    await st.drain()
                    await asyncio.to_thread(snapshot_taken)
                fut = await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2]))
                fut.add_done_callback(on_ack)
            await st.drain()
    except Exception:  # the connection dies with the server
        pass
    return acks


def test_sigkill_mid_stream_then_restart_restores_exactly(tmp_path, variant: ServiceVariant):
    data = tmp_path / "data"
    srv = variant.server(data, env=ENV).start()
    with srv.client() as c:
        sid = c.create_session("crash", CONFIG)["id"]
    kill_after = int(len(ITEMS) * 0.6)
    acks = asyncio.run(_stream_until_killed(srv, sid, int(len(ITEMS) * 0.3), kill_after))
    assert srv.proc.poll() is not None, "the server should be dead"
    assert len(acks) >= kill_after and max(a["last_seq"] for a in acks) < len(ITEMS) - 1, "killed mid-stream"

    store = variant.open_store(data)  # the crash left a snapshot to restore from
    try:
        assert store.latest_snapshot(sid) is not None, "a snapshot should exist before the crash"
    finally:
        store.close()

    srv2 = variant.server(data, env=ENV).start()
    try:
        with srv2.client() as c:
            stored = c.all_inputs(sid)
            # every acknowledged input is there, unchanged, and nothing else but a prefix of what was sent
            assert [r["seq"] for r in stored] == list(range(len(stored)))
            assert [(r["kind"], r["t"]) for r in stored] == [_kind_t(it) for it in ITEMS[: len(stored)]]
            assert len(stored) >= max(a["last_seq"] for a in acks) + 1
            for r in stored:
                if r["kind"] == "odometry":
                    o = ITEMS[r["seq"]][1]
                    assert r["odometry"] == {"t": o.t, "v": o.v, "omega": o.omega}
            assert c.frame(sid, next(r["seq"] for r in stored if r["kind"] == "frame")) == next(
                it[2] for it in ITEMS if it[0] == "frame"
            )
            # restored (snapshot + replay) to exactly the state of those inputs
            n = len(stored)
            assert session_state(c, sid) == offline_reference(ITEMS[:n], CONFIG)

            # the robot resumes where the server says it is; the session ends like an uninterrupted run
            acks2 = asyncio.run(stream_items(srv2.url, srv2.token, sid, ITEMS[n:]))
            assert [a["seq"] for a in acks2] == list(range(n, len(ITEMS)))
            ref_sid = c.create_session("uninterrupted", CONFIG)["id"]
            asyncio.run(stream_items(srv2.url, srv2.token, ref_sid, ITEMS))
            crashed = session_state(c, sid)
            assert crashed == session_state(c, ref_sid)
            assert crashed["stats"]["loop_closures_accepted"] > 0
            assert crashed["stats"]["odometry_steps"] == sum(it[0] == "odometry" for it in ITEMS)
    finally:
        srv2.stop()

    # a graceful restart (final snapshot, nothing to replay) changes nothing either
    srv3 = variant.server(data, env=ENV).start()
    try:
        with srv3.client() as c:
            st = c.wait_processed(sid)
            assert st["snapshot_seq"] == len(ITEMS) - 1
            assert session_state(c, sid) == crashed
    finally:
        srv3.stop()
