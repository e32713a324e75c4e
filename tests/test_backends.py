"""Session backends (server/runtime/mapper_host.py, server/runtime/ray_backend.py, server/runtime/worker.py).

* the in-process and the Ray host give the same results for the same inputs;
* a session worker whose Ray actor is killed (``ray.kill``) restores a new one from the
  store and ends in the uninterrupted state; metrics are reported once per live input;
* with a live server on Ray, SIGKILLing a session's actor process while a robot streams
  loses no acknowledged input, the restart shows in the stats, and the final state equals
  the offline reference; a SIGKILLed server leaves no actor process behind;
* a clear error when Ray is missing, and for a bad backend name; the in-process path never
  imports Ray.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
import time

import pytest
from pydantic import ValidationError

from hippomap.client import AsyncStream
from hippomap.inputs import Odometry
from server.metrics import ServiceMetrics
from server.runtime import model
from server.runtime.mapper_host import InProcessHost
from server.settings import ServerSettings
from server.storage.sqlite import SQLiteStore
from tests.support.live import ROOT, LiveServer, stream_items
from tests.support.ray_head import local_ray_head, ray_auth_env, ray_test_env
from tests.support.reference import offline_reference, session_state
from tests.support.synthetic import synthetic_inputs
from tests.worker_harness import assert_host_matches_inprocess, run_worker

CONFIG = {"mapper": {"keyframe_interval": 3}}
ITEMS = synthetic_inputs(n_odometry=400, frame_every=3)  # 1.6 laps: loops are closed


@pytest.fixture(scope="module")
def ray_driver(tmp_path_factory):
    """This test process joined to the test run's Ray head (as a server would)."""
    head = local_ray_head()
    data = tmp_path_factory.mktemp("ray-driver")  # its actors' table cache: <data_dir>/grid-tables
    with ray_auth_env(head):  # Ray may have been imported by an earlier test of this process
        import ray

        from server.runtime.ray_backend import RayBackend

        backend = RayBackend(ServerSettings(data_dir=data, backend="ray", ray_address=head.address, ray_max_batch=8))
        backend.start()
        try:
            yield backend
        finally:
            backend.shutdown()
            assert not ray.is_initialized()


def test_inprocess_and_ray_hosts_give_identical_results(ray_driver):
    remote = ray_driver.factory("unit")
    try:
        assert_host_matches_inprocess(remote, "ray", ITEMS[:120], CONFIG)
    finally:
        remote.close()


def _run_worker(tmp_path, items, host_factory, kill_at=None, metrics=None):
    return run_worker(tmp_path, items, CONFIG, host_factory, kill_at, metrics)


def test_worker_replaces_a_killed_actor_and_ends_in_the_uninterrupted_state(tmp_path, ray_driver):
    import ray

    items = ITEMS
    ref, processed_ref, _, events_ref, fields_ref = _run_worker(tmp_path / "a", items, lambda sid: InProcessHost())
    killed = []

    def kill(w):  # once a snapshot exists, so the new actor restores it and replays after it
        deadline = time.monotonic() + 60
        while w.snapshot_seq < 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.snapshot_seq >= 0
        killed.append(w._host.info()["pid"])
        ray.kill(w._host.actor, no_restart=True)

    metrics = ServiceMetrics()
    state, processed, w, events, fields = _run_worker(tmp_path / "b", items, ray_driver.factory, kill, metrics)
    assert killed and w.restarts >= 1
    assert state == ref
    # every input reported exactly once, in order, although some were replayed into the new actor
    assert processed == processed_ref == list(range(len(items)))
    # the derived records are those of an uninterrupted run (dropped after the snapshot, then regenerated)
    assert [(e.id, e.seq, e.type, e.data) for e in events] == [(e.id, e.seq, e.type, e.data) for e in events_ref]
    assert [(f.step, f.seq, f.data) for f in fields] == [(f.step, f.seq, f.data) for f in fields_ref]
    # metrics: one step observation per input, loop closures as accepted by the map
    reg = metrics.registry
    n_odo = sum(1 for it in items if it[0] == "odometry")
    assert reg.get_sample_value("hippomap_step_seconds_count", {"session": "s_unit", "kind": "odometry"}) == n_odo
    assert (
        reg.get_sample_value("hippomap_step_seconds_count", {"session": "s_unit", "kind": "frame"})
        == len(items) - n_odo
    )
    accepted = state["stats"]["loop_closures_accepted"]
    assert accepted > 0
    assert reg.get_sample_value("hippomap_loop_closures_total", {"session": "s_unit"}) == accepted
    assert reg.get_sample_value("hippomap_restore_seconds", {"session": "s_unit"}) > 0


# --------------------------------------------------------------------- live server on Ray
def _ray_server(tmp_path, env=None):
    from tests.support.live import LiveServer

    data = tmp_path / "data"
    return LiveServer(
        data,
        env={**ray_test_env(data), "HIPPOMAP_SNAPSHOT_EVERY_INPUTS": "60", **(env or {})},
        args=["--backend", "ray"],
    )


def _kind_t(it):
    return ("odometry", it[1].t) if it[0] == "odometry" else ("frame", it[1])


def test_killing_a_sessions_actor_mid_stream_loses_no_acknowledged_input(tmp_path):
    srv = _ray_server(tmp_path).start()
    try:
        with srv.client() as c:
            sid = c.create_session("actor-kill", CONFIG)["id"]
            pid0 = c.stats(sid)["backend"]["pid"]

        async def stream() -> list[dict]:
            acks = []
            async with AsyncStream(srv.url, srv.token, sid, max_in_flight=32) as st:
                futs = []
                for k, it in enumerate(ITEMS):
                    if k == len(ITEMS) // 2:  # the robot keeps streaming while the actor's process is killed
                        await asyncio.to_thread(os.kill, pid0, signal.SIGKILL)
                    futs.append(await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2])))
                acks = list(await asyncio.gather(*futs))
            return acks

        acks = asyncio.run(stream())
        assert len(acks) == len(ITEMS) and max(a["last_seq"] for a in acks) == len(ITEMS) - 1
        with srv.client() as c:
            state = session_state(c, sid)
            stats = c.stats(sid)
            stored = c.all_inputs(sid)
        assert stats["backend_restarts"] >= 1 and stats["backend"]["pid"] != pid0
        assert stats["error"] is None
        assert [(r["kind"], r["t"]) for r in stored] == [_kind_t(it) for it in ITEMS]
        assert state == offline_reference(ITEMS, CONFIG)
        assert state["stats"]["loop_closures_accepted"] > 0
    finally:
        srv.stop()


def _ray_process(pid: int) -> str | None:
    """The command line of live process ``pid`` if it is a Ray worker (zombies count as gone)."""
    try:
        stat = open(f"/proc/{pid}/stat").read()
        cmd = open(f"/proc/{pid}/cmdline").read().replace("\0", " ")
    except OSError:
        return None
    return cmd if stat.rsplit(")", 1)[1].split()[0] != "Z" and cmd.startswith("ray::") else None


def test_a_sigkilled_ray_server_leaves_no_actor_behind(tmp_path):
    srv = _ray_server(tmp_path).start()
    try:
        with srv.client() as c:
            pids = [c.stats(c.create_session(f"s{k}", CONFIG)["id"])["backend"]["pid"] for k in range(2)]
        assert all("MapperActor" in (_ray_process(p) or "") for p in pids), [_ray_process(p) for p in pids]
    finally:
        srv.kill()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and any(_ray_process(p) for p in pids):
        time.sleep(0.2)
    assert not any(_ray_process(p) for p in pids), "actor processes outlived their server"


def test_sigterm_with_a_local_ray_shuts_down_gracefully(tmp_path):
    """``--backend ray`` without an address starts a local Ray, whose driver-side SIGTERM handler
    would exit at once; the server keeps its own, so ``docker stop`` still ends with every
    session's last snapshot written and the local Ray gone."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIPPOMAP_RAY")}
    env["HIPPOMAP_SNAPSHOT_EVERY_INPUTS"] = "100000"  # only the shutdown snapshot can cover the inputs
    srv = LiveServer(tmp_path / "local", args=["--backend", "ray"], env=env)
    srv.env.pop("HIPPOMAP_RAY_ADDRESS", None)
    srv.start(timeout=180)
    items = ITEMS[:60]
    try:
        with srv.client() as c:
            sid = c.create_session("local-ray", CONFIG)["id"]
            pid = c.stats(sid)["backend"]["pid"]
            asyncio.run(stream_items(srv.url, srv.token, sid, items))
            assert c.wait_processed(sid)["snapshot_seq"] < len(items) - 1
    finally:
        srv.stop(timeout=120)
    # uvicorn re-raises the SIGTERM it handled once its shutdown is done: -15 is a graceful end too
    assert srv.proc.returncode in (0, -signal.SIGTERM), (srv.proc.returncode, "".join(srv.output[-20:]))
    store = SQLiteStore(tmp_path / "local" / "hippomap.sqlite3")
    try:
        snap = store.latest_snapshot(sid)
    finally:
        store.close()
    assert snap is not None and snap[0] == len(items) - 1
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and _ray_process(pid):
        time.sleep(0.2)
    assert not _ray_process(pid), "the local Ray's actor outlived the server"


# ---------------------------------------------------------------------------- errors
def test_missing_ray_is_a_clear_error(monkeypatch, tmp_path, capsys):
    from server import cli
    from server.runtime.ray_backend import RayBackend, require_ray

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    with pytest.raises(RuntimeError, match=r'pip install "hippomap\[ray\]"'):
        require_ray()
    with pytest.raises(RuntimeError, match=r'pip install "hippomap\[ray\]"'):
        RayBackend(ServerSettings(backend="ray"))
    assert cli.main(["--backend", "ray", "--port", "0", "--data-dir", str(tmp_path)]) == 2
    assert 'pip install "hippomap[ray]"' in capsys.readouterr().err


def test_ray_imported_before_the_backend_is_named_when_a_token_is_at_hand(monkeypatch, caplog):
    """Ray reads its authentication mode once, on import: when something imported it before the backend
    could ask for token authentication, the backend says so instead of leaving an invalid-token error."""
    import types

    from server.runtime.ray_backend import require_ray

    fake = types.ModuleType("ray")
    monkeypatch.setitem(sys.modules, "ray", fake)  # imported earlier in this process
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    monkeypatch.setenv("RAY_AUTH_TOKEN", "a" * 32)
    with caplog.at_level(logging.WARNING, logger="hippomap.server"):
        assert require_ray() is fake
    assert "RAY_AUTH_MODE=token" in caplog.text and "imported" in caplog.text
    assert "RAY_AUTH_MODE" not in os.environ  # the backend does not pretend to fix it
    caplog.clear()
    monkeypatch.setenv("RAY_AUTH_MODE", "token")  # asked for before the import: nothing to say
    with caplog.at_level(logging.WARNING, logger="hippomap.server"):
        require_ray()
    monkeypatch.delenv("RAY_AUTH_MODE")
    monkeypatch.delenv("RAY_AUTH_TOKEN")
    monkeypatch.setenv("RAY_AUTH_TOKEN_PATH", "/nonexistent/ray-token")  # no token at hand: nothing to say
    with caplog.at_level(logging.WARNING, logger="hippomap.server"):
        require_ray()
    assert caplog.text == ""


def test_bad_backend_is_refused(monkeypatch, capsys):
    from server import cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["--backend", "spark"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--backend" in err and "spark" in err and "inprocess" in err
    monkeypatch.setenv("HIPPOMAP_BACKEND", "spark")
    with pytest.raises(ValidationError, match="backend"):
        ServerSettings.from_env()


def test_the_inprocess_path_never_imports_ray(tmp_path):
    code = f"""
import asyncio, sys
from server.app import create_app
from server.settings import ServerSettings
from fastapi.testclient import TestClient
app = create_app(ServerSettings(data_dir=r"{tmp_path}", admin_token="hm_x_admin_token"))
with TestClient(app) as c:
    sid = c.post("/sessions", json={{"name": "n"}}, headers={{"Authorization": "Bearer hm_x_admin_token"}}).json()["id"]
    r = c.post(f"/sessions/{{sid}}/odometry", json={{"t": 0.1, "v": 0.1, "omega": 0.0}},
               headers={{"Authorization": "Bearer hm_x_admin_token"}})
    assert r.status_code == 200, r.text
assert "ray" not in sys.modules, "ray was imported"
print("ok")
"""
    res = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stdout + res.stderr


def test_a_closed_ray_host_is_dead_and_batches_split_over_calls_keep_their_order(ray_driver):
    from server.runtime.mapper_host import HostDied

    config = model.effective_config({})
    host, local = ray_driver.factory("odo"), InProcessHost()
    try:
        host.restore(None, config)
        local.restore(None, config)
        batch = [(k, Odometry(0.05 * (k + 1), v=0.4, omega=0.2)) for k in range(40)]
        res = host.process(batch[:7]) + host.process(batch[7:20]) + host.process(batch[20:])
        assert [r.seq for r in res] == list(range(40))
        assert [r.events for r in res] == [r.events for r in local.process(batch)]
        assert host.query(model.queries.Stats()) == local.query(model.queries.Stats())
    finally:
        host.close()
    with pytest.raises(HostDied):
        host.query(model.queries.Stats())
