"""Operations: liveness / readiness, Prometheus metrics and structured (JSON) logs.

In-process (TestClient) for the endpoints' rules; one live server (a subprocess, SIGKILLed and
restarted) for what only a real restart shows: readiness stays false while a long session is
replayed, the metrics the sessions export, and the JSON log lines carrying the session id.
"""

from __future__ import annotations

import asyncio
import json
import logging
import sys
import time

import httpx
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from hippomap.errors import InputError
from server import logs
from server.app import create_app
from server.settings import ServerSettings
from tests.support.live import LiveServer, stream_items
from tests.support.streams import FakeTTY
from tests.support.synthetic import synthetic_inputs

TOKEN = "hm_ops_admin_token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def samples(text: str) -> dict[tuple[str, tuple], float]:
    """Prometheus text → {(sample name, sorted labels): value}."""
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def value(parsed: dict, name: str, **labels: str) -> float | None:
    return parsed.get((name, tuple(sorted(labels.items()))))


def total(parsed: dict, name: str, **labels: str) -> float:
    """Sum over every series of ``name`` whose labels include ``labels``."""
    return sum(v for (n, ls), v in parsed.items() if n == name and set(labels.items()) <= set(ls))


# ------------------------------------------------------------------ endpoints, in-process
@pytest.fixture()
def app(tmp_path, monkeypatch):
    monkeypatch.delenv("HIPPOMAP_METRICS_TOKEN", raising=False)
    return create_app(ServerSettings(data_dir=tmp_path / "data", admin_token=TOKEN))


def test_health_and_ready_need_no_token(app):
    with TestClient(app) as c:
        h = c.get("/health")
        assert h.status_code == 200 and h.json()["status"] == "ok"
        r = c.get("/ready")
        assert r.status_code == 200 and r.json() == {"ready": True, "restoring": [], "sessions": 0}
        sid = c.post("/sessions", json={"name": "x"}, headers=AUTH).json()["id"]
        assert c.get("/ready").json()["sessions"] == 1
        assert c.get("/health").json()["sessions"] == 1
        assert c.get(f"/sessions/{sid}", headers=AUTH).status_code == 200
        assert c.get(f"/sessions/{sid}").status_code == 401  # the rest of the API does need one


def test_ready_is_false_before_start_while_restoring_and_when_stopping(app):
    c = TestClient(app)  # not entered: the lifespan (store, sessions) has not run
    r = c.get("/ready")
    assert r.status_code == 503 and r.json()["ready"] is False and r.json()["reason"] == "starting"
    assert c.get("/health").status_code == 200  # liveness: the process answers
    with TestClient(app) as c:
        manager = app.state.manager
        manager.restoring = lambda: ["s_b", "s_a"]  # as during a restart's replay
        r = c.get("/ready")
        assert r.status_code == 503
        assert r.json()["ready"] is False and r.json()["restoring"] == ["s_a", "s_b"]
        assert value(samples(c.get("/metrics", headers=AUTH).text), "hippomap_ready") == 0.0
        del manager.restoring
        assert c.get("/ready").status_code == 200
        assert value(samples(c.get("/metrics", headers=AUTH).text), "hippomap_ready") == 1.0
    r = TestClient(app).get("/ready")  # the lifespan has ended: shutting down
    assert r.status_code == 503 and r.json()["reason"] == "stopping"


def test_metrics_need_the_admin_token_by_default(app):
    with TestClient(app) as c:
        sid = c.post("/sessions", json={"name": "m"}, headers=AUTH).json()["id"]
        assert c.get("/metrics").status_code == 401  # it names every session
        r = c.get("/metrics", headers=AUTH)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        parsed = samples(r.text)
        assert value(parsed, "hippomap_queue_depth", session=sid) == 0.0
        assert value(parsed, "hippomap_sessions") == 1.0
        assert value(parsed, "hippomap_ready") == 1.0
        c.delete(f"/sessions/{sid}", headers=AUTH)
        parsed = samples(c.get("/metrics", headers=AUTH).text)
        assert value(parsed, "hippomap_queue_depth", session=sid) is None
        assert value(parsed, "hippomap_sessions") == 0.0


def test_metrics_token_when_configured(tmp_path, monkeypatch):
    monkeypatch.setenv("HIPPOMAP_METRICS_TOKEN", "hm_scrape_secret")
    app = create_app(ServerSettings(data_dir=tmp_path / "data", admin_token=TOKEN))
    with TestClient(app) as c:
        assert c.get("/metrics").status_code == 401
        assert c.get("/metrics", headers=AUTH).status_code == 401  # the admin token is not the metrics token
        r = c.get("/metrics", headers={"Authorization": "Bearer hm_scrape_secret"})
        assert r.status_code == 200 and "hippomap_ready" in r.text
        assert c.get("/health").status_code == 200 and c.get("/ready").status_code == 200  # still open


def test_operations_endpoints_are_documented(app):
    paths = TestClient(app).get("/openapi.json").json()["paths"]
    assert {"/health", "/ready", "/metrics"} <= set(paths)
    assert "503" in paths["/ready"]["get"]["responses"]
    assert "text/plain" in paths["/metrics"]["get"]["responses"]["200"]["content"]


# ------------------------------------------------------------------ log formatting
@pytest.fixture()
def clean_logging():
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    levels = {n: logging.getLogger(n).level for n in (*logs.OWN_LOGGERS, "uvicorn", "uvicorn.error", "uvicorn.access")}
    yield
    root.handlers[:] = saved[0]
    root.setLevel(saved[1])
    for n, lvl in levels.items():
        logging.getLogger(n).setLevel(lvl)


def record(msg: str, *args, name: str = "hippomap.server", level: int = logging.INFO, exc_info=None, **extra):
    return logging.getLogger(name).makeRecord(name, level, __file__, 1, msg, args, exc_info, extra=extra or None)


def test_json_formatter_fields():
    line = logs.JSONFormatter().format(
        record("session %s created", "s_1", session="s_1", duration_s=1.25, odd=object())
    )
    assert "\n" not in line
    out = json.loads(line)
    assert out["message"] == "session s_1 created" and out["session"] == "s_1"
    assert out["level"] == "INFO" and out["logger"] == "hippomap.server" and out["duration_s"] == 1.25
    assert out["odd"].startswith("<object object")
    assert out["time"].endswith("Z") and time.strptime(out["time"][:19], "%Y-%m-%dT%H:%M:%S")
    assert "session" not in json.loads(logs.JSONFormatter().format(record("no session")))


def test_json_formatter_exception_and_access_lines():
    try:
        raise ValueError("boom")
    except ValueError:
        rec = record("worker stopped", level=logging.ERROR, exc_info=sys.exc_info(), session="s_2")
    out = json.loads(logs.JSONFormatter().format(rec))
    assert out["level"] == "ERROR" and out["session"] == "s_2"
    assert "Traceback" in out["exc"] and "ValueError: boom" in out["exc"]
    access = record('%s - "%s %s HTTP/%s" %d', "127.0.0.1:5000", "GET", "/ready", "1.1", 503, name="uvicorn.access")
    out = json.loads(logs.JSONFormatter().format(access))
    assert out["method"] == "GET" and out["path"] == "/ready" and out["status"] == 503
    assert out["message"] == '127.0.0.1:5000 - "GET /ready HTTP/1.1" 503'


def test_text_formatter_keeps_the_record_intact():
    rec = record("session %s restored", "s_3", session="s_3", duration_s=0.5)
    text = logs.TextFormatter().format(rec)
    assert "[s_3] session s_3 restored" in text and "duration_s=0.5" in text and "INFO" in text
    assert json.loads(logs.JSONFormatter().format(rec))["message"] == "session s_3 restored"  # msg/args restored


def test_resolve_format(monkeypatch):
    monkeypatch.delenv(logs.ENV_FORMAT, raising=False)
    assert logs.resolve_format(None, FakeTTY(tty=True)) == "text"
    assert logs.resolve_format(None, FakeTTY(tty=False)) == "json"
    assert logs.resolve_format("json", FakeTTY(tty=True)) == "json"
    monkeypatch.setenv(logs.ENV_FORMAT, "text")
    assert logs.resolve_format(None, FakeTTY(tty=False)) == "text"
    assert logs.resolve_format("json", FakeTTY(tty=False)) == "json"  # the flag wins over the environment
    monkeypatch.setenv(logs.ENV_FORMAT, "yaml")
    with pytest.raises(InputError, match="yaml.*HIPPOMAP_LOG_FORMAT"):
        logs.resolve_format(None, FakeTTY(tty=False))
    with pytest.raises(InputError, match="xml.*--log-format"):
        logs.resolve_format("xml")


def test_configure_routes_every_logger_through_one_handler(clean_logging, monkeypatch):
    monkeypatch.delenv(logs.ENV_FORMAT, raising=False)
    stream = FakeTTY(tty=False)
    logs.configure(None, "info", FakeTTY(tty=False))
    assert logs.configure(None, "info", stream) == "json"  # configured twice: still one handler
    assert [h.get_name() for h in logging.getLogger().handlers].count("hippomap") == 1
    logging.getLogger("hippomap.server").info("session %s deleted", "s_4", extra={"session": "s_4"})
    logging.getLogger("uvicorn.error").warning("uvicorn says")
    logging.getLogger("some.library").info("chatter")  # below WARNING for other libraries: not shown
    logging.getLogger("some.library").warning("a library warning")
    lines = [json.loads(ln) for ln in stream.getvalue().splitlines()]
    assert [(r["logger"], r["message"]) for r in lines] == [
        ("hippomap.server", "session s_4 deleted"),
        ("uvicorn.error", "uvicorn says"),
        ("some.library", "a library warning"),
    ]
    assert lines[0]["session"] == "s_4"
    with pytest.raises(InputError, match="loud"):
        logs.configure("json", "loud", stream)


# ------------------------------------------------------------------ a live server, killed and restarted
CONFIG = {"mapper": {"keyframe_interval": 5}}
LONG = synthetic_inputs(n_odometry=1500, frame_every=4)  # 1875 inputs; laps repeat views: loops close
SERVER_ARGS = ["--log-format", "json", "--log-level", "info"]
SERVER_ENV = {"HIPPOMAP_SNAPSHOT_EVERY_INPUTS": "100000", "HIPPOMAP_SNAPSHOT_EVERY_S": "3600"}  # all replayed


def json_lines(output: list[str]) -> list[dict]:
    out = []
    for line in output:
        if line.startswith("{"):
            out.append(json.loads(line))  # every log line is one JSON object
    return out


def test_restart_readiness_metrics_and_json_logs(tmp_path):
    n_odo = sum(1 for it in LONG if it[0] == "odometry")
    n_frames = len(LONG) - n_odo
    srv = LiveServer(tmp_path / "data", token=TOKEN, env=SERVER_ENV, args=SERVER_ARGS).start()
    try:
        with srv.client() as c:
            sid = c.create_session("long", CONFIG)["id"]
            acks = asyncio.run(stream_items(srv.url, TOKEN, sid, LONG))
            assert len(acks) == len(LONG)
            stats = c.wait_processed(sid)
        parsed = samples(httpx.get(f"{srv.url}/metrics", headers=AUTH).text)
        assert value(parsed, "hippomap_inputs_total", session=sid, kind="odometry") == n_odo
        assert value(parsed, "hippomap_inputs_total", session=sid, kind="frame") == n_frames
        assert total(parsed, "hippomap_step_seconds_count", session=sid) == len(LONG)
        assert value(parsed, "hippomap_step_seconds_count", session=sid, kind="frame") == n_frames
        assert total(parsed, "hippomap_step_seconds_sum", session=sid) > 0
        loops = value(parsed, "hippomap_loop_closures_total", session=sid)
        assert loops is not None and loops > 0
        assert loops == stats["mapper"]["loop_closures_accepted"]
        assert value(parsed, "hippomap_queue_depth", session=sid) == 0
        assert value(parsed, "hippomap_ready") == 1 and value(parsed, "hippomap_sessions") == 1
    finally:
        srv.kill()  # SIGKILL: no snapshot was taken, the restart replays all 1875 inputs
    first_run = json_lines(srv.output)

    again = LiveServer(tmp_path / "data", token=TOKEN, env=SERVER_ENV, args=SERVER_ARGS).start()
    try:
        seen_restoring, health_while_restoring, metrics_while_restoring, ready = None, None, None, None
        deadline = time.monotonic() + 120
        with httpx.Client(base_url=again.url, timeout=10) as http:
            while time.monotonic() < deadline:
                r = http.get("/ready")
                if r.status_code == 503:
                    seen_restoring = r.json()
                    health = http.get("/health").status_code
                    metrics = samples(http.get("/metrics", headers=AUTH).text)
                    if http.get("/ready").status_code == 503:  # still restoring after both reads: they are of then
                        health_while_restoring, metrics_while_restoring = health, metrics
                elif r.status_code == 200:
                    ready = r.json()
                    break
                time.sleep(0.01)
            assert seen_restoring is not None, "the restart never reported a session being restored"
            assert seen_restoring["ready"] is False and seen_restoring["restoring"] == [sid]
            assert metrics_while_restoring is not None, "never read /health and /metrics within the restore"
            assert health_while_restoring == 200  # alive, not ready
            assert value(metrics_while_restoring, "hippomap_ready") == 0
            assert ready == {"ready": True, "restoring": [], "sessions": 1}
            parsed = samples(http.get("/metrics", headers=AUTH).text)
            restore_s = value(parsed, "hippomap_restore_seconds", session=sid)
            assert restore_s is not None and restore_s > 0
            assert value(parsed, "hippomap_ready") == 1
        with again.client() as c:
            assert c.wait_processed(sid)["processed_seq"] == len(LONG) - 1
    finally:
        again.stop()
    second_run = json_lines(again.output)

    for rec in first_run + second_run:
        assert {"time", "level", "logger", "message"} <= set(rec), rec
    assert not [ln for ln in srv.output + again.output if ln.startswith(("INFO:", "WARNING:", "ERROR:"))]
    assert any(r["logger"].startswith("uvicorn") for r in first_run)  # uvicorn's own lines are JSON too
    assert any(r.get("session") == sid for r in first_run)  # the session's creation
    mine = [r for r in second_run if r.get("session") == sid]
    assert any("restore started" in r["message"] for r in mine), second_run
    assert len(mine) >= 2, mine  # the restore's start, and its end (logged by the session's worker)
    ready_lines = [r for r in second_run if r["message"].startswith("ready: every session restored")]
    assert len(ready_lines) == 1 and ready_lines[0]["duration_s"] > 0
