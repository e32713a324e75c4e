"""Nothing a writer sends can stop the server or wedge a session.

Each test reproduces one way a request used to take the service (or a session) down and checks
it no longer does: a deeply nested websocket message followed by a dropped connection (the
store's writer thread died), a writer that dies anyway (health turns 503, the process exits),
coerced and absurd odometry, a reading the mapper raises on, config overrides without upper
bounds, a corrupt JPEG, a mapper queue bounded only by count, and a fuzzed websocket protocol.
All in-process (TestClient) with tiny grid-cell tables, except one real process for the exit.
"""

from __future__ import annotations

import json
import math
import re
import struct
import sys
import threading
import time
from concurrent.futures import CancelledError
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hippomap.config import HippomapConfig
from hippomap.grid_cells import GridCells
from server.app import create_app
from server.formats.images import check_jpeg_strict
from server.formats.ingest import IngestError, check_frame
from server.formats.protocol import json_depth, pack_frame, parse_text_message
from server.runtime import sessions as sessions_module
from server.security.quotas import SAFE_RANGES, check_config, grid_table_bytes
from server.settings import ServerSettings
from server.storage.store import InputRecord, StoreDead
from tests.support.live import anonymous_bytes

TOKEN = "hm_hardening_admin_token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}  # websocket_connect adds to the dict it gets: pass it dict(AUTH)
SMALL = {"spatial": {"resolution_m": 0.004}}  # 101 x 101 rate tables: a session is built in milliseconds
ROOT = Path(__file__).resolve().parents[1]


def _settings(tmp_path, **kw) -> ServerSettings:
    return ServerSettings(data_dir=tmp_path / "data", admin_token=TOKEN, **kw)


def _session(c: TestClient, config: dict | None = None) -> str:
    r = c.post("/sessions", json={"name": "t", "config": config or SMALL}, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _odo(t: float, mid: int | None = None, v: float = 0.1, omega: float = 0.0) -> str:
    return json.dumps({"type": "odometry", "id": mid, "t": t, "v": v, "omega": omega})


def _reply(ws) -> dict:
    """The next reply that answers a message (``busy`` notices skipped)."""
    while True:
        msg = json.loads(ws.receive_text())
        if msg["type"] != "busy":
            return msg


def _corrupt(jpeg: bytes, seed: int, length: int) -> bytes:
    """The JPEG with ``length`` bytes in its middle overwritten by random bytes."""
    rng = np.random.default_rng(seed)
    out = bytearray(jpeg)
    start = len(out) // 2 - length // 2
    out[start : start + length] = rng.integers(0, 256, length, dtype=np.uint8).tobytes()
    return bytes(out)


def _jpeg(seed: int = 0, w: int = 320, h: int = 240) -> bytes:
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur((rng.random((h, w)) * 255).astype(np.uint8), (5, 5), 2)
    return cv2.imencode(".jpg", img)[1].tobytes()


# ------------------------------------------------------------ the writer thread survives any request
def test_nested_message_after_odometry_then_disconnect_keeps_every_write_working(tmp_path):
    """The critical bug: 10 odometry messages, then '['*100000 + ']'*100000 on the websocket. The
    message used to raise RecursionError in json.loads, the handler cancelled the sender awaiting
    durability futures, and settling a cancelled future killed the store's writer thread."""
    app = create_app(_settings(tmp_path))
    with TestClient(app) as c:
        sid = _session(c)
        with c.websocket_connect(f"/sessions/{sid}/stream", headers=dict(AUTH)) as ws:
            assert json.loads(ws.receive_text())["type"] == "hello"
            for k in range(10):
                ws.send_text(_odo(0.1 * (k + 1), mid=k))
            ws.send_text("[" * 100000 + "]" * 100000)
            replies = [_reply(ws) for _ in range(11)]
            assert [r["type"] for r in replies] == ["ack"] * 10 + ["error"]
            assert replies[-1]["status"] == 422 and "nested" in replies[-1]["detail"]
            ws.send_text(_odo(1.5, mid=99))  # the stream stays open and keeps acknowledging
            assert _reply(ws) == {"type": "ack", "id": 99, "seq": 10, "last_seq": 10, "count": 1}
            # the same again, and the client leaves without waiting for its acks
            for k in range(10):
                ws.send_text(_odo(2.0 + 0.1 * k, mid=100 + k))
            ws.send_text("[" * 100000 + "]" * 100000)
        # every write path on the server still works, at once
        assert c.get("/health").status_code == 200 and c.get("/ready").status_code == 200
        assert c.post("/tokens", json={"role": "viewer"}, headers=AUTH).status_code == 201
        sid2 = _session(c)
        r = c.post(f"/sessions/{sid2}/odometry", json={"t": 1.0, "v": 0.1, "omega": 0.0}, headers=AUTH)
        assert r.status_code == 200, r.text
        # the session itself goes on: (unacknowledged messages may or may not have been stored
        # when the client left) the next input follows the stored ones without a gap
        r = c.post(f"/sessions/{sid}/odometry", json={"t": 10.0, "v": 0.1, "omega": 0.0}, headers=AUTH)
        assert r.status_code == 200, r.text
        seq = r.json()["seq"]
        assert 11 <= seq <= 21
        stats = _wait_processed(c, sid, seq)
        assert stats["error"] is None and stats["inputs_stored"] == seq + 1


from tests.test_server_units import store  # noqa: E402, F401  (each store backend on an empty database)


def test_the_issue_reproduction_on_a_real_server(tmp_path):
    """As reported, over uvicorn: 10 odometry messages then the nested text, the client leaving
    at once; afterwards every write on the server (new sessions, tokens, ingest) still answers."""
    import asyncio

    from websockets.asyncio.client import connect

    from tests.support.live import LiveServer

    with LiveServer(tmp_path / "data", token=TOKEN) as srv:
        sid = httpx.post(f"{srv.url}/sessions", json={"config": SMALL}, headers=AUTH, timeout=60).json()["id"]
        url = srv.url.replace("http", "ws", 1) + f"/sessions/{sid}/stream"

        async def attack() -> None:
            async with connect(url, additional_headers=dict(AUTH), max_size=None) as ws:
                json.loads(await ws.recv())
                for k in range(10):
                    await ws.send(_odo(0.1 * (k + 1), mid=k))
                await ws.send("[" * 100000 + "]" * 100000)

        for _ in range(3):
            try:
                asyncio.run(attack())
            except Exception as exc:
                raise AssertionError("".join(srv.output)[-3000:]) from exc
        with httpx.Client(base_url=srv.url, headers=AUTH, timeout=10) as h:
            assert h.get("/health").status_code == 200 and h.get("/ready").status_code == 200
            assert h.post("/tokens", json={"role": "viewer"}).status_code == 201
            assert h.post("/sessions", json={"config": SMALL}).status_code == 201
            r = h.post(f"/sessions/{sid}/odometry", json={"t": 5.0, "v": 0.1, "omega": 0.0})
            assert r.status_code == 200, r.text
            assert h.get(f"/sessions/{sid}/stats").json()["error"] is None
        srv.stop(timeout=30)  # SIGTERM still stops it (LiveServer would SIGKILL it after 30 s)
        assert srv.proc.returncode in (0, -15), srv.proc.returncode


def test_store_settles_around_cancelled_futures_and_survives_failing_batches(store):
    gate, inside = threading.Event(), threading.Event()
    blocker = store._submit(lambda conn: inside.set() or gate.wait(10))  # holds the writer while we cancel
    assert inside.wait(10)
    durable: list[int] = []
    futs = [
        store.append_inputs(
            "s", [InputRecord(k, "odometry", float(k), b"{}")], on_durable=lambda k=k: durable.append(k)
        )
        for k in range(4)
    ]
    assert futs[1].cancel() and futs[2].cancel()  # waiters gone: the writes still happen
    gate.set()
    assert blocker.result(10) is True
    assert futs[0].result(10) is None and futs[3].result(10) is None
    with pytest.raises(CancelledError):
        futs[1].result()
    assert durable == [0, 1, 2, 3]  # every durable input reaches the mapper, in order
    assert [r.seq for r in store.read_inputs("s", -1, 10)] == [0, 1, 2, 3]

    def fail(conn):
        raise RecursionError("maximum recursion depth exceeded")

    assert isinstance(store._submit(fail).exception(10), RecursionError)
    store.append_inputs("s", [InputRecord(4, "odometry", 4.0, b"{}")]).result(10)
    assert store.fatal is None and store.last_input("s") == (4, 4.0)


def test_a_dead_writer_fails_every_write_at_once_and_says_so(store):
    told: list[str] = []
    store.on_fatal(told.append)
    gate, inside = threading.Event(), threading.Event()
    blocker = store._submit(lambda conn: inside.set() or gate.wait(10))
    assert inside.wait(10)  # the writer runs the blocker alone; what follows is queued behind it
    doomed = store._submit(_kill_writer)
    queued = store.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"{}")])
    gate.set()
    blocker.result(10)
    assert isinstance(doomed.exception(10), StoreDead) and isinstance(queued.exception(10), StoreDead)
    assert "_WriterKilled" in store.fatal and len(told) == 1 and "_WriterKilled" in told[0]
    with pytest.raises(StoreDead):
        store.append_inputs("s", [InputRecord(1, "odometry", 1.0, b"{}")])
    late: list[str] = []
    store.on_fatal(late.append)  # registered after the death: told at once
    assert late == told


class _WriterKilled(BaseException):
    """Something no batch handler may swallow: it stops the writer thread itself."""


def _kill_writer(conn):
    raise _WriterKilled("injected")


def test_dead_writer_turns_health_and_ready_503_and_exits(tmp_path, monkeypatch):
    exits: list[int] = []
    monkeypatch.setattr(sessions_module, "exit_process", exits.append)
    app = create_app(_settings(tmp_path, fatal_exit_s=0.0))
    with TestClient(app) as c:
        sid = _session(c)
        assert (
            c.post(f"/sessions/{sid}/odometry", json={"t": 1.0, "v": 0.1, "omega": 0.0}, headers=AUTH).status_code
            == 200
        )
        store = app.state.store
        doomed = store._submit(_kill_writer)
        assert isinstance(doomed.exception(10), StoreDead)
        assert "_WriterKilled" in store.fatal
        h, r = c.get("/health"), c.get("/ready")
        assert h.status_code == 503 and "storage stopped" in h.json()["detail"]
        assert r.status_code == 503 and r.json()["ready"] is False
        deadline = time.monotonic() + 10
        while not exits:
            assert time.monotonic() < deadline, "the process was not told to exit"
            time.sleep(0.01)
        assert exits == [sessions_module.EXIT_STORE_DEAD]
        # meanwhile a write is refused at once (never a hang)
        r = c.post(f"/sessions/{sid}/odometry", json={"t": 2.0, "v": 0.1, "omega": 0.0}, headers=AUTH)
        assert r.status_code == 503


_DYING_SERVER = """
import sys
from server import cli
from server.storage.sqlite import SQLiteStore
from server.storage.store import TokenRecord

original = SQLiteStore.add_token

def add_token(self, secret_hash, token):
    if token.label == "kill-the-writer":
        def op(conn):
            raise SystemExit("injected writer failure")
        return self._submit(op)
    return original(self, secret_hash, token)

SQLiteStore.add_token = add_token
sys.exit(cli.main(sys.argv[1:]))
"""


def test_a_real_server_exits_nonzero_when_its_writer_dies(tmp_path):
    """The process, not only the app: after the writer dies, /health answers 503 and the server
    exits with a non-zero status of its own (a supervisor restarts it)."""
    from tests.support.live import LiveServer

    srv = LiveServer(tmp_path / "data", token=TOKEN, env={"HIPPOMAP_FATAL_EXIT_S": "1.5"})
    script = tmp_path / "dying_server.py"
    script.write_text(_DYING_SERVER)
    srv.start = _start_with(srv, script)  # type: ignore[method-assign]
    srv.start()
    try:
        r = httpx.post(
            f"{srv.url}/tokens", json={"role": "viewer", "label": "kill-the-writer"}, headers=AUTH, timeout=30
        )
        assert r.status_code >= 500
        assert httpx.get(f"{srv.url}/health", timeout=10).status_code == 503
        assert srv.proc is not None
        code = srv.proc.wait(30)
        assert code == sessions_module.EXIT_STORE_DEAD
    finally:
        srv.kill()


def _start_with(srv, script: Path):
    """``srv.start`` running ``script`` (which patches the store, then runs the serve command), then
    waiting until the server is ready."""
    plain_start = srv.start
    srv.command = [sys.executable, str(script)]

    def start(timeout: float = 60.0):
        plain_start(timeout)
        deadline = time.monotonic() + timeout
        while True:
            try:
                if httpx.get(f"{srv.url}/ready", timeout=5).status_code == 200:
                    return srv
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "".join(srv.output)
            time.sleep(0.1)

    return start


# ------------------------------------------------------------------ bounded websocket parsing
def test_json_depth_is_the_nesting_outside_strings():
    assert json_depth('{"a": [1, [2, {"b": "[[[[{{{"}]]}') == 4
    assert json_depth('"\\"[[["') == 0 and json_depth("") == 0 and json_depth("[]") == 1


@settings(max_examples=60, deadline=None)
@given(
    st.recursive(
        st.none() | st.booleans() | st.floats(allow_nan=False) | st.text(max_size=5),
        lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=3), inner, max_size=3),
        max_leaves=20,
    )
)
def test_json_depth_matches_the_structure(value):
    def depth(v):
        if isinstance(v, list):
            return 1 + max((depth(x) for x in v), default=0)
        if isinstance(v, dict):
            return 1 + max((depth(x) for x in v.values()), default=0)
        return 0

    assert json_depth(json.dumps(value)) == depth(value)


def test_parse_text_message_bounds_size_depth_and_never_raises_anything_else():
    with pytest.raises(ValueError, match="exceeds the limit of 100"):
        parse_text_message("x" * 101, 100, 16)
    for text in ("[" * 100000, "[" * 100000 + "]" * 100000, '{"a":' * 5000 + "1" + "}" * 5000):
        with pytest.raises(ValueError, match="nested"):
            parse_text_message(text, 1 << 20, 16)
    with pytest.raises(ValueError, match="not JSON"):
        parse_text_message('{"a": ', 100, 16)
    assert parse_text_message('{"type": "ping", "id": "[[["}', 100, 16) == {"type": "ping", "id": "[[["}


# ------------------------------------------------------------- physical bounds and strict types
BAD_READINGS = [
    ({"t": "300", "v": "0.1", "omega": 0.0}, "t"),
    ({"t": 300.0, "v": True, "omega": 0.0}, "v"),
    ({"t": 300.0, "v": 0.1, "omega": "0"}, "omega"),
    ({"t": 300.0, "v": 0.1, "omega": 1e308}, "omega"),
    ({"t": 1e308, "v": 0.1, "omega": 0.0}, "t"),
    ({"t": 300.0, "v": -1e6, "omega": 0.0}, "v"),
    ({"t": 300.0, "increment": [1e9, 0.0, 0.0]}, "dx"),
    ({"t": 300.0, "increment": [0.0, -500.0, 0.0]}, "dy"),
    ({"t": 300.0, "increment": [0.0, 0.0, 40.0]}, "dtheta"),
    ({"t": 300.0, "increment": [0.0, False, 0.0]}, "increment"),
    ({"t": 1.0 + 2_592_000.5, "v": 0.1, "omega": 0.0}, "t"),  # more than 30 days after the session's clock
]


def _names(detail, field: str) -> bool:
    """Does an error ``detail`` name ``field``: in a validation error's ``loc``, or as a word?"""
    if isinstance(detail, list):
        return any(field in [str(x) for x in err.get("loc", [])] for err in detail)
    return re.search(rf"(?<![\w.]){re.escape(field)}(?![\w])", detail) is not None


def test_absurd_or_coerced_odometry_is_422_naming_the_field_and_the_session_goes_on(tmp_path):
    app = create_app(_settings(tmp_path))
    with TestClient(app) as c:
        sid = _session(c)
        assert (
            c.post(f"/sessions/{sid}/odometry", json={"t": 1.0, "v": 0.1, "omega": 0.0}, headers=AUTH).status_code
            == 200
        )
        for body, field in BAD_READINGS:
            r = c.post(
                f"/sessions/{sid}/odometry",
                content=json.dumps(body),
                headers={**AUTH, "Content-Type": "application/json"},
            )
            assert r.status_code == 422, (body, r.text)
            assert _names(r.json()["detail"], field), (body, r.text)
        batch = {"readings": [{"t": 2.0, "v": 0.1, "omega": 0.0}, {"t": 3e6, "v": 0.1, "omega": 0.0}]}
        r = c.post(f"/sessions/{sid}/odometry", json=batch, headers=AUTH)
        assert r.status_code == 422 and "readings[1]" in r.text and "max_time_jump_s" in r.text
        with c.websocket_connect(f"/sessions/{sid}/stream", headers=dict(AUTH)) as ws:
            json.loads(ws.receive_text())
            for k, (body, field) in enumerate(BAD_READINGS):
                ws.send_text(json.dumps({"type": "odometry", "id": k, **body}))
                reply = _reply(ws)
                assert reply["type"] == "error" and reply["status"] == 422 and reply["id"] == k, reply
                assert _names(reply["detail"], field), (body, reply)
            ws.send_text(_odo(2.0, mid=77))
            assert _reply(ws)["type"] == "ack"
        # a frame timestamp is bounded too
        frame_t = c.post(
            f"/sessions/{sid}/frames?t=1e300", content=_jpeg(), headers={**AUTH, "Content-Type": "image/jpeg"}
        )
        assert frame_t.status_code == 422 and "frame t" in frame_t.text
        r = c.post(f"/sessions/{sid}/odometry", json={"t": 3.0, "v": 0.1, "omega": 0.0}, headers=AUTH)
        assert r.status_code == 200 and r.json()["seq"] == 2  # nothing refused was stored
        stats = c.get(f"/sessions/{sid}/stats", headers=AUTH).json()
        assert stats["error"] is None and stats["inputs_stored"] == 3


def test_a_reading_the_mapper_raises_on_is_skipped_live_and_on_replay(tmp_path):
    """omega = 1e308 with the turn-rate bound lifted: the mapper raises (math domain error). It used
    to stop the session for good (503 on every later input, again after each restart)."""
    s = _settings(tmp_path, max_turn_rate_rad_s=math.inf, snapshot_every_inputs=1000, snapshot_every_s=3600)
    app = create_app(s)
    with TestClient(app) as c:
        sid = _session(c)
        for t, omega in ((1.0, 0.0), (3.0, 1e308), (3.1, 0.1), (3.2, 0.0)):  # 1e308 x 2 s overflows
            r = c.post(f"/sessions/{sid}/odometry", json={"t": t, "v": 0.1, "omega": omega}, headers=AUTH)
            assert r.status_code == 200, r.text
        stats = _wait_processed(c, sid, 3)
        assert stats["error"] is None and stats["input_errors"] == 1
        assert stats["last_input_error"].startswith("seq 1:")
        assert stats["mapper"]["odometry_steps"] >= 2
        events = c.get(f"/sessions/{sid}/events", headers=AUTH).json()
        failed = [e for e in events if e["type"] == "input_failed"]
        assert [e["seq"] for e in failed] == [1]
        steps_before = stats["mapper"]["odometry_steps"]
    app = create_app(s)  # a restart replays every input: the bad one is skipped the same way
    with TestClient(app) as c:
        stats = _wait_processed(c, sid, 3)
        assert stats["error"] is None and stats["mapper"]["odometry_steps"] == steps_before
        r = c.post(f"/sessions/{sid}/odometry", json={"t": 3.4, "v": 0.1, "omega": 0.0}, headers=AUTH)
        assert r.status_code == 200


def _wait_processed(c: TestClient, sid: str, seq: int) -> dict:
    deadline = time.monotonic() + 60
    while True:
        stats = c.get(f"/sessions/{sid}/stats", headers=AUTH).json()
        if stats["processed_seq"] >= seq and not stats["replaying"]:
            return stats
        assert time.monotonic() < deadline, stats
        time.sleep(0.05)


# ------------------------------------------------------------------------ config overrides
@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"spatial": {"n_modules": 100000}}, "n_modules"),
        ({"spatial": {"cells_per_module": 1000}}, "cells_per_module"),
        ({"spatial": {"resolution_m": 0.0002}}, "grid-cell tables"),  # 2001^2 cells: 770 MB
        ({"map": {"relax_loops": 20000}}, "relax_loops"),
        ({"map": {"lsq_iterations": 10**6}}, "lsq_iterations"),
        ({"visual": {"working_width": 100000}}, "working_width"),
        ({"visual": {"vgc_frequencies": [0.001] * 500}}, "vgc_frequencies"),
        ({"spatial": {"seed": -1}}, "seed"),
        ({"spatial": {"seed": 2**64}}, "seed"),
        ({"map": {"mu_p": 1e999}}, "mu_p"),  # sent as 1e999: JSON's way to say infinity
        ({"visual": {"give_up_frames": [40, 40]}}, "give_up_frames"),
        ({"visual": {"give_up_frames": [0, 320]}}, "give_up_frames"),
    ],
)
def test_config_overrides_outside_safe_ranges_are_422(tmp_path, overrides, field):
    app = create_app(_settings(tmp_path))
    with TestClient(app) as c:
        body = json.dumps({"name": "x", "config": overrides}).replace("Infinity", "1e999")
        r = c.post("/sessions", content=body, headers={**AUTH, "Content-Type": "application/json"})
        assert r.status_code == 422, r.text
        assert field in r.text
        assert c.get("/sessions", headers=AUTH).json() == []


def test_defaults_and_every_safe_range_bound_are_accepted():
    defaults = HippomapConfig().model_dump()
    check_config(HippomapConfig(), ServerSettings())
    known = [(section, field) for section, field in SAFE_RANGES if field in defaults[section]]
    assert len(known) >= len(SAFE_RANGES) - 2  # the ranges name the model's real fields
    for section, field in known:
        lo, hi = SAFE_RANGES[(section, field)]
        assert defaults[section][field] is None or lo <= defaults[section][field] <= hi, (section, field)


@pytest.mark.parametrize(
    "spatial",
    [
        {"resolution_m": 0.004},
        {"resolution_m": 0.008, "n_modules": 3},
        {"area_size_m": 0.2, "resolution_m": 0.005, "cells_per_module": 2},
    ],
)
def test_documented_grid_table_memory_is_what_the_model_allocates(spatial):
    cfg = HippomapConfig.with_overrides({"spatial": spatial}).spatial
    assert grid_table_bytes(cfg) == GridCells(cfg).tables.nbytes


def test_per_token_quotas_on_grid_memory_and_session_count(tmp_path):
    one = grid_table_bytes(HippomapConfig.with_overrides(SMALL).spatial)  # about 10 MB
    app = create_app(_settings(tmp_path, max_token_grid_bytes=int(2.5 * one), max_sessions_per_token=4))
    with TestClient(app) as c:
        seeds = [_session(c, {"spatial": {**SMALL["spatial"], "seed": s}}) for s in (1, 2)]
        r = c.post("/sessions", json={"config": {"spatial": {**SMALL["spatial"], "seed": 3}}}, headers=AUTH)
        assert r.status_code == 403 and "grid-cell tables" in r.json()["detail"]
        _session(c, {"spatial": {**SMALL["spatial"], "seed": 2}})  # shares seed 2's tables: free
        # another writer has its own quota
        w = c.post("/tokens", json={"role": "writer"}, headers=AUTH).json()["token"]
        r = c.post(
            "/sessions",
            json={"config": {"spatial": {**SMALL["spatial"], "seed": 3}}},
            headers={"Authorization": f"Bearer {w}"},
        )
        assert r.status_code == 201
        assert c.delete(f"/sessions/{seeds[0]}", headers=AUTH).status_code == 204  # frees seed 1's share
        _session(c, {"spatial": {**SMALL["spatial"], "seed": 3}})
        _session(c, {"spatial": {**SMALL["spatial"], "seed": 3}})
        r = c.post("/sessions", json={"config": SMALL}, headers=AUTH)
        assert r.status_code == 429 and "limit 4" in r.json()["detail"]


# ------------------------------------------------------------------------------ corrupt images
@pytest.mark.parametrize("seed", range(6))
def test_jpeg_with_random_middle_is_rejected(seed):
    good = _jpeg(seed)
    check_jpeg_strict(good)
    bad = _corrupt(good, seed, length=50 + 200 * seed)
    assert cv2.imdecode(np.frombuffer(bad, np.uint8), cv2.IMREAD_GRAYSCALE) is not None  # OpenCV would take it
    with pytest.raises(IngestError) as exc:
        check_frame(bad, 1.0, ServerSettings())
    assert exc.value.status == 422 and "corrupt" in exc.value.detail


def test_corrupt_jpeg_is_refused_over_http_and_websocket(tmp_path):
    app = create_app(_settings(tmp_path))
    with TestClient(app) as c:
        sid = _session(c)
        bad = _corrupt(_jpeg(7), 7, 400)
        r = c.post(f"/sessions/{sid}/frames?t=1.0", content=bad, headers={**AUTH, "Content-Type": "image/jpeg"})
        assert r.status_code == 422 and "corrupt" in r.text
        with c.websocket_connect(f"/sessions/{sid}/stream", headers=dict(AUTH)) as ws:
            json.loads(ws.receive_text())
            ws.send_bytes(pack_frame(5, 1.0, bad))
            reply = _reply(ws)
            assert reply["type"] == "error" and reply["status"] == 422 and reply["id"] == 5
            ws.send_bytes(pack_frame(6, 1.0, _jpeg(7)))
            assert _reply(ws)["type"] == "ack"


# ----------------------------------------------------------------- the mapper queue, in bytes
def _big_frame(w: int = 2000, h: int = 1000) -> bytes:
    """Small as a JPEG, large decoded (a smooth gradient): 2 MB a frame once decoded."""
    x = np.linspace(0, 255, w, dtype=np.float32)[None, :] + np.linspace(0, 60, h, dtype=np.float32)[:, None]
    return cv2.imencode(".jpg", np.clip(x, 0, 255).astype(np.uint8))[1].tobytes()


def test_mapper_queue_is_bounded_in_bytes_and_memory_returns_on_delete(tmp_path, monkeypatch):
    from server.runtime import mapper_host

    gate = threading.Event()
    original = mapper_host.InProcessHost.process

    def slow(self, batch):  # a mapper that does not keep up until the gate opens
        gate.wait(60)
        return original(self, batch)

    monkeypatch.setattr(mapper_host.InProcessHost, "process", slow)
    frame = _big_frame()
    decoded = 2000 * 1000
    limit = 64 * decoded  # 128 MB
    app = create_app(_settings(tmp_path, max_pending_bytes=limit, backpressure_wait_s=0.2, max_pending=10_000))
    try:
        with TestClient(app) as c:
            sid = _session(c)
            base = anonymous_bytes()
            headers = {**AUTH, "Content-Type": "image/jpeg"}
            accepted = 0
            for k in range(80):
                r = c.post(f"/sessions/{sid}/frames?t={k + 1}", content=frame, headers=headers)
                if r.status_code == 429:
                    assert "MB of images" in r.json()["detail"]
                    break
                assert r.status_code == 200, r.text
                accepted += 1
            # the count limit (10,000) never bit: the bytes did, at 64 frames of 2 MB
            assert accepted == 64
            live = app.state.manager.sessions[sid]
            assert live.pending_bytes == limit
            grown = anonymous_bytes() - base
            assert grown > 0.6 * limit, grown  # the queue really holds the decoded frames
            gate.set()
            assert c.delete(f"/sessions/{sid}", headers=AUTH).status_code == 204
            after = anonymous_bytes() - base
            assert after < 0.25 * limit, (grown, after)  # returned, not kept by the deleted session
    finally:
        gate.set()


def test_backpressure_releases_when_the_mapper_catches_up(tmp_path, monkeypatch):
    from server.runtime import mapper_host

    gate = threading.Event()
    original = mapper_host.InProcessHost.process

    def slow(self, batch):
        gate.wait(60)
        return original(self, batch)

    monkeypatch.setattr(mapper_host.InProcessHost, "process", slow)
    frame = _big_frame(1200, 1000)
    app = create_app(_settings(tmp_path, max_pending_bytes=3 * 1200 * 1000, backpressure_wait_s=0.1))
    with TestClient(app) as c:
        sid = _session(c)
        headers = {**AUTH, "Content-Type": "image/jpeg"}
        codes = [
            c.post(f"/sessions/{sid}/frames?t={k + 1}", content=frame, headers=headers).status_code for k in range(4)
        ]
        assert codes == [200, 200, 200, 429]
        gate.set()
        r = c.post(f"/sessions/{sid}/frames?t=4", content=frame, headers={**headers})
        assert r.status_code == 200  # backpressure waits for room, then takes it
        gate.set()


# ---------------------------------------------------------------------------- protocol fuzzing
_KEYS = st.sampled_from(["type", "id", "v", "omega", "increment", "readings", "x", ""])  # never "t"
_JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats()
    | st.text(max_size=20)
    | st.sampled_from(["odometry", "ping", "frame"]),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_KEYS, inner, max_size=4),
    max_leaves=12,
)
_TEXT = st.one_of(
    st.text(max_size=200),
    _JSON.map(lambda v: json.dumps(v)),
    st.dictionaries(_KEYS, _JSON, max_size=5).map(lambda d: json.dumps({"type": "odometry", **d})),
    st.integers(17, 3000).map(lambda n: "[" * n + "]" * n),
    st.integers(1, 3000).map(lambda n: '{"a":' * n),
)
_BINARY = st.one_of(
    st.binary(max_size=300),
    st.tuples(st.integers(0, 2**32 - 1), st.floats(), st.binary(max_size=200)).map(
        lambda x: struct.pack("<4sId", b"HMF1", *x[:2]) + x[2]
    ),
    st.integers(0, 5).map(lambda s: pack_frame(1, 1e9, _corrupt(_jpeg(s), s, 300))),
)
_MESSAGES = st.lists(
    st.one_of(_TEXT.map(lambda s: ("text", s)), _BINARY.map(lambda b: ("bytes", b))), min_size=1, max_size=6
)


def test_fuzzed_websocket_messages_never_stop_valid_input_being_acknowledged(tmp_path):
    app = create_app(_settings(tmp_path))
    with TestClient(app) as c:
        sid = _session(c)
        clock = {"t": 0.0, "seq": -1}

        @settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
        @given(_MESSAGES)
        def run(messages):
            with c.websocket_connect(f"/sessions/{sid}/stream", headers=dict(AUTH)) as ws:
                assert json.loads(ws.receive_text())["type"] == "hello"
                for kind, payload in messages:
                    clock["t"] += 0.05
                    ws.send_text(_odo(clock["t"], mid=-1))  # a valid reading before each fuzzed message
                    ack = _reply(ws)
                    assert ack["type"] == "ack" and ack["id"] == -1, ack
                    assert ack["seq"] == clock["seq"] + 1
                    clock["seq"] = ack["seq"]
                    if kind == "text":
                        ws.send_text(payload)
                    else:
                        ws.send_bytes(payload)
                    reply = _reply(ws)
                    assert reply["type"] in ("error", "pong", "ack"), reply
                    if reply["type"] == "error":
                        assert reply["status"] in (409, 413, 415, 422), reply
                    if reply["type"] == "ack":  # a fuzzed message that happens to be valid
                        clock["seq"] = reply["last_seq"]

        run()
        stats = c.get(f"/sessions/{sid}/stats", headers=AUTH).json()
        assert stats["error"] is None and stats["inputs_stored"] == clock["seq"] + 1
        assert c.get("/health").status_code == 200


def test_time_jump_limit_is_relative_to_the_session_clock_and_configurable(tmp_path):
    app = create_app(_settings(tmp_path, max_time_jump_s=10.0))
    with TestClient(app) as c:
        sid = _session(c)

        def post(t: float):
            return c.post(f"/sessions/{sid}/odometry", json={"t": t, "v": 0.1, "omega": 0.0}, headers=AUTH)

        assert post(1e9).status_code == 200  # the first input sets the clock (Unix time is fine)
        assert post(1e9 + 9.0).status_code == 200
        r = post(1e9 + 20.0)
        assert r.status_code == 422 and "max_time_jump_s" in r.text
        headers = {**AUTH, "Content-Type": "image/jpeg"}
        r = c.post(f"/sessions/{sid}/frames?t={1e9 + 30.0}", content=_jpeg(), headers=headers)
        assert r.status_code == 422 and "frame t" in r.text  # the clock is the newest input of either kind
        assert c.post(f"/sessions/{sid}/frames?t={1e9 + 18.0}", content=_jpeg(), headers=headers).status_code == 200
        assert post(1e9 + 20.0).status_code == 200  # 2 s after the frame: within the limit now


def test_websocket_ids_are_echoed_only_when_plain(tmp_path):
    app = create_app(_settings(tmp_path))
    with TestClient(app) as c:
        sid = _session(c)
        with c.websocket_connect(f"/sessions/{sid}/stream", headers=dict(AUTH)) as ws:
            json.loads(ws.receive_text())
            for bad in ("x" * 1000, [1] * 3, {"a": 1}, True):
                ws.send_text(json.dumps({"type": "ping", "id": bad}))
                reply = _reply(ws)
                assert reply["type"] == "error" and reply["id"] is None and "message id" in reply["detail"]
            ws.send_text('{"type": "ping", "id": NaN}')
            raw = ws.receive_text()
            assert "NaN" not in raw and json.loads(raw)["status"] == 422
            for good in (7, 2.5, "robot-1"):
                ws.send_text(json.dumps({"type": "ping", "id": good}))
                assert _reply(ws) == {"type": "pong", "id": good}


@pytest.mark.parametrize("quality", [50, 90])
@pytest.mark.parametrize("colour", [False, True])
def test_the_strict_check_decodes_the_frame_replay_decodes(quality, colour):
    """Ingest keeps the strict check's image as the frame (one decode); replay decodes with
    hippomap.inputs.decode_jpeg. The two must agree pixel for pixel, or a restored session
    would not be the session that was acknowledged."""
    from hippomap.inputs import decode_jpeg
    from server.formats.images import check_jpeg_strict

    rng = np.random.default_rng(quality)
    img = cv2.GaussianBlur(rng.integers(0, 255, (240, 320, 3) if colour else (240, 320), dtype=np.uint8), (5, 5), 0)
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
    strict = check_jpeg_strict(data)
    assert strict is not None and strict.shape == (240, 320) and strict.dtype == np.uint8
    np.testing.assert_array_equal(strict, decode_jpeg(data))
