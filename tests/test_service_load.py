"""The parts of the ingest path that keep the service's load figure (docs/BENCHMARKS.md, "Service
load"): the mapper gate, batched wake-ups of the event loop, the frame check that does not run the
visual front end twice, and the store's group commit without per-write savepoints. Each keeps the
guarantee it replaced: order, isolation of a failing write, a 422 for a frame the model cannot use."""

from __future__ import annotations

import asyncio
import threading
import time

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from hippomap.config import HippomapConfig
from hippomap.inputs import Odometry
from server.app import create_app
from server.runtime import model
from server.runtime.loop_calls import LoopCalls
from server.runtime.mapper_host import InProcessHost, MapperGate
from server.settings import ServerSettings
from server.storage.sqlite import SQLiteStore
from server.storage.store import InputRecord

TOKEN = "hm_load_admin_token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SMALL = {"spatial": {"resolution_m": 0.004}}  # 101 x 101 rate tables: a session is built in milliseconds


# ------------------------------------------------------------------ mapper gate
class _Watched(InProcessHost):
    """An in-process host that records how many hosts are inside a step at once."""

    inside = 0
    most = 0
    lock = threading.Lock()

    def _one(self, seq, value):
        with _Watched.lock:
            _Watched.inside += 1
            _Watched.most = max(_Watched.most, _Watched.inside)
        try:
            time.sleep(0.002)  # a step long enough for the other threads to try to enter
            return super()._one(seq, value)
        finally:
            with _Watched.lock:
                _Watched.inside -= 1


@pytest.mark.parametrize("slots", [1, 2])
def test_mapper_gate_bounds_the_mappers_stepping_at_once(slots):
    _Watched.inside = _Watched.most = 0
    gate = MapperGate(slots)
    config = HippomapConfig.with_overrides(SMALL)
    hosts = [_Watched(gate) for _ in range(4)]
    for h in hosts:
        h.restore(None, config)
    results: dict[int, list] = {}

    def feed(i: int) -> None:
        results[i] = [
            r.seq for r in hosts[i].process([(k, Odometry(0.05 * (k + 1), v=0.2, omega=0.1)) for k in range(20)])
        ]

    threads = [threading.Thread(target=feed, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert _Watched.most == slots  # never more, and the slots are used
    assert all(results[i] == list(range(20)) for i in range(4))  # every input of every session, in order
    assert all(h.mapper.stats()["odometry_steps"] == 20 for h in hosts)


def test_mapper_gate_refuses_zero_slots():
    with pytest.raises(ValueError, match="slots"):
        MapperGate(0)


# ------------------------------------------------------------------ loop calls
def test_loop_calls_run_in_order_on_the_loop_with_one_wakeup_per_burst():
    async def main() -> tuple[list[int], set[int], int]:
        loop = asyncio.get_running_loop()
        calls = LoopCalls(loop)
        seen: list[int] = []
        threads_seen: set[int] = set()
        wakeups = 0
        run = calls._run

        def counted_run() -> None:
            nonlocal wakeups
            wakeups += 1
            run()

        calls._run = counted_run  # type: ignore[method-assign]

        def record(k: int) -> None:
            seen.append(k)
            threads_seen.add(threading.get_ident())

        def burst() -> None:  # the loop is blocked in this call: every call queues behind one wake-up
            t = threading.Thread(target=lambda: [calls.call(record, k) for k in range(1000)])
            t.start()
            t.join()

        burst()
        await asyncio.sleep(0.05)
        t = threading.Thread(target=lambda: [calls.call(record, k) for k in range(1000, 1010)])
        t.start()
        t.join()
        await asyncio.sleep(0.05)
        return seen, threads_seen, wakeups

    seen, threads_seen, wakeups = asyncio.run(main())
    assert seen == list(range(1010))
    assert threads_seen == {threading.get_ident()}  # asyncio.run ran the loop in this thread
    assert 2 <= wakeups <= 11  # the 1,000-call burst took one wake-up


def test_loop_calls_survive_a_failing_call_and_a_closed_loop():
    loop = asyncio.new_event_loop()
    calls = LoopCalls(loop)
    seen: list[int] = []
    calls.call(lambda: 1 / 0)
    calls.call(seen.append, 1)
    loop.run_until_complete(asyncio.sleep(0.01))
    assert seen == [1]
    loop.close()
    calls.call(seen.append, 2)  # shutdown: dropped, never raised into the calling thread
    assert seen == [1]


# ------------------------------------------------------------------ frames
def _jpeg(w: int, h: int) -> bytes:
    img = (np.random.default_rng(w * h).random((h, w)) * 255).astype(np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def test_model_frame_rules_still_refuse_a_new_shape_after_a_good_one(tmp_path, monkeypatch):
    checked: list[tuple[int, ...]] = []
    real = model.check_frame

    def counting(config, frame):  # the real check, counted
        checked.append(frame.image.shape)
        return real(config, frame)

    monkeypatch.setattr(model, "check_frame", counting)
    app = create_app(ServerSettings(data_dir=tmp_path / "data", admin_token=TOKEN))
    with TestClient(app) as c:
        r = c.post("/sessions", json={"name": "t", "config": SMALL}, headers=AUTH)
        sid = r.json()["id"]
        headers = {**AUTH, "Content-Type": "image/jpeg"}
        assert c.post(f"/sessions/{sid}/frames?t=1", content=_jpeg(320, 240), headers=headers).status_code == 200
        for t in (2, 3):  # refused each time, however many good frames came before
            r = c.post(f"/sessions/{sid}/frames?t={t}", content=_jpeg(320, 40), headers=headers)
            assert r.status_code == 422 and "fovea" in r.json()["detail"], r.text
        assert c.post(f"/sessions/{sid}/frames?t=4", content=_jpeg(320, 240), headers=headers).status_code == 200
        stats = c.get(f"/sessions/{sid}/stats", headers=AUTH).json()
        assert stats["inputs_stored"] == 2 and stats["rejected"] == {"422": 2}
    # the model's rules ran on the first good frame and on each refused one, not again on a known good shape
    assert checked == [(240, 320), (40, 320), (40, 320)]


# ------------------------------------------------------------------ store
def test_sqlite_batch_with_a_failing_write_commits_the_others_once(tmp_path):
    store = SQLiteStore(tmp_path / "db.sqlite3")
    try:
        gate, inside = threading.Event(), threading.Event()
        blocker = store._submit(lambda conn: inside.set() or gate.wait(10))
        assert inside.wait(10)  # what follows is queued behind the blocker: one batch
        durable: list[int] = []
        futs = [
            store.append_inputs(
                "s", [InputRecord(k, "odometry", float(k), b"x")], on_durable=lambda k=k: durable.append(k)
            )
            for k in range(3)
        ]
        dup = store.append_inputs("s", [InputRecord(1, "odometry", 9.0, b"dup")], on_durable=lambda: durable.append(-1))
        futs += [
            store.append_inputs(
                "s", [InputRecord(k, "odometry", float(k), b"x")], on_durable=lambda k=k: durable.append(k)
            )
            for k in range(3, 5)
        ]
        gate.set()
        blocker.result(10)
        assert [f.result(10) for f in futs] == [None] * 5
        with pytest.raises(Exception, match="UNIQUE"):
            dup.result(10)
        assert durable == [0, 1, 2, 3, 4]  # each durable write's callback once, in order; none for the failed one
        assert [(r.seq, r.data) for r in store.read_inputs("s", -1, 10)] == [(k, b"x") for k in range(5)]
    finally:
        store.close()
