"""The process session backend (server/runtime/process_host.py): the sessions' mappers in child processes.

* a process host gives the same results as the in-process host for the same inputs, answers the
  model's typed queries (with no cloudpickle installed: the standard pickle carries them), refuses
  anything else before sending it, and its snapshot restores in process to the same mapper;
* a session worker whose mapper process is SIGKILLed restores a new one from the store and ends
  in the uninterrupted state, every input reported once and in order;
* a live server with ``--backend process``: a robot streams while the mapper process is killed;
  no acknowledged input is lost and the session ends in the state of the offline reference.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hippomap.client import AsyncStream
from hippomap.errors import InputError
from server.runtime import model
from server.runtime.mapper_host import HostDied, InProcessHost
from server.runtime.process_host import ProcessBackend
from server.settings import ServerSettings
from tests.support.live import LiveServer
from tests.support.reference import offline_reference, session_state
from tests.support.synthetic import decoded, synthetic_inputs
from tests.worker_harness import assert_host_matches_inprocess, run_worker

CONFIG = {"mapper": {"keyframe_interval": 3}, "spatial": {"resolution_m": 0.004}}
ITEMS = synthetic_inputs(n_odometry=240, frame_every=3)


@pytest.fixture()
def backend():
    b = ProcessBackend(workers=1, max_batch=8)
    b.start()
    yield b
    b.shutdown()


def test_process_and_inprocess_hosts_give_identical_results(backend):
    remote = backend.factory("unit")
    try:
        local = assert_host_matches_inprocess(remote, "process", ITEMS[:120], CONFIG)
        with pytest.raises(InputError, match="unknown config section"):  # raised in the child, reaches the caller
            remote.query(model.queries.BaseSnapshot({"nosuch": {}}))
        with pytest.raises(InputError, match="unknown mapper query"):  # a function is refused before it is sent
            remote.query(lambda m: m.to_bytes())  # type: ignore[arg-type]
        assert remote.query(model.queries.Stats()) == local.query(model.queries.Stats())  # the host goes on
    finally:
        remote.close()


def test_mapper_processes_share_the_grid_cell_tables_through_the_table_cache(tmp_path, monkeypatch):
    """``table_cache``: the first mapper process writes the tables of a session's config into the folder; a
    later one (another server's, or a restarted one) reads them instead of building them again; the
    setting's default is ``<data_dir>/grid-tables``, ``off`` turns it off, and a Ray actor is handed it."""
    settings = ServerSettings(data_dir=tmp_path / "data")
    assert settings.table_cache_dir == str((tmp_path / "data" / "grid-tables").resolve())
    assert ServerSettings(table_cache="off").table_cache_dir == "off"  # handed on as it is: none in the child
    monkeypatch.setenv("HIPPOMAP_TABLE_CACHE", str(tmp_path / "elsewhere"))
    assert ServerSettings.from_env().table_cache_dir == str(tmp_path / "elsewhere")
    monkeypatch.delenv("HIPPOMAP_TABLE_CACHE")

    folder = tmp_path / "tables"
    config = model.effective_config({})  # the default tables: 32 cells of 801 x 801
    written = None
    for _ in range(2):
        b = ProcessBackend(workers=1, table_cache=str(folder))
        b.start()
        host = b.factory("s")
        try:
            host.restore(None, config)
            host.process(list(enumerate(decoded(ITEMS[:20]))))
        finally:
            host.close()
            b.shutdown()
        files = {p.name: (p.stat().st_ino, p.stat().st_size) for p in folder.glob("grid-tables-*.npy")}
        assert len(files) == 3 and sum(size for _, size in files.values()) > 100e6
        assert written is None or files == written  # the second process read them: nothing written again
        written = files

    from server.runtime.ray_backend import MapperActor  # the class alone: no Ray needed

    MapperActor(str(folder))
    assert os.environ["HIPPOMAP_TABLE_CACHE"] == str(folder)


def test_process_backend_answers_queries_without_cloudpickle(tmp_path):
    """Queries are values the standard pickle carries: with cloudpickle made unimportable (in the
    server and, through the environment, in its spawned mapper process) a process host still answers
    every query the routes and the viewer make, as the in-process host does."""
    (tmp_path / "cloudpickle.py").write_text('raise ImportError("cloudpickle is blocked in this test")\n')
    root = Path(__file__).resolve().parents[1]
    code = """
import sys
import numpy as np
np.set_printoptions(threshold=sys.maxsize)  # repr compares whole arrays
from hippomap import mapper_queries as mq
from server.runtime import model
from server.runtime.mapper_host import InProcessHost
from server.runtime.process_host import ProcessBackend
from tests.support.synthetic import decoded, synthetic_inputs
try:
    import cloudpickle  # noqa: F401
    raise SystemExit("cloudpickle is importable")
except ImportError:
    pass
config = model.effective_config({"mapper": {"keyframe_interval": 3}, "spatial": {"resolution_m": 0.004}})
batch = list(enumerate(decoded(synthetic_inputs(n_odometry=240, frame_every=3))))
backend = ProcessBackend(workers=1, max_batch=8)
backend.start()
try:
    remote, local = backend.factory("s"), InProcessHost()
    remote.restore(None, config)
    local.restore(None, config)
    assert [r.events for r in remote.process(batch)] == [r.events for r in local.process(batch)]
    for q in (mq.Stats(), mq.Recognitions(), mq.RecognitionById(0), mq.LastInputTime(), mq.MapperState()):
        assert remote.query(q) == local.query(q), q
    for q in (mq.GraphArrays(information=True), mq.ViewerState(5)):
        a, b = remote.query(q), local.query(q)
        assert repr(a) == repr(b), q
    assert model.loop_closures(remote.query(mq.LoopDecisions())) == model.loop_closures(local.query(mq.LoopDecisions()))
    assert remote.query(mq.PlaceCellIteration()) is not None
    assert "cloudpickle" not in sys.modules or sys.modules["cloudpickle"] is None
finally:
    backend.shutdown()
print("ok")
"""
    res = subprocess.run(
        [sys.executable, "-c", code],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=240,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(root)])},
    )
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stdout + res.stderr


def test_a_killed_mapper_process_is_reported_and_replaced(backend):
    config = model.effective_config(CONFIG)
    first = backend.factory("a")
    first.restore(None, config)
    pid = first.info()["pid"]
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(HostDied):
        first.process(list(enumerate(decoded(ITEMS[:3]))))
    second = backend.factory("a")  # a new process
    assert second.restore(None, config)["odometry_steps"] == 0 and second.info()["pid"] != pid


def _run_worker(tmp_path, host_factory, kill_at=None):
    state, processed, w, _, _ = run_worker(tmp_path, ITEMS, CONFIG, host_factory, kill_at)
    return state, processed, w


def test_worker_replaces_a_killed_mapper_process_and_ends_in_the_uninterrupted_state(tmp_path, backend):
    ref, processed_ref, _ = _run_worker(tmp_path / "a", lambda sid: InProcessHost())
    killed: list[int] = []

    def kill(w):  # once a snapshot exists, so the new process restores it and replays after it
        deadline = time.monotonic() + 60
        while w.snapshot_seq < 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.snapshot_seq >= 0
        killed.append(w.host_info["pid"])
        os.kill(killed[0], signal.SIGKILL)

    state, processed, w = _run_worker(tmp_path / "b", backend.factory, kill)
    assert killed and w.restarts >= 1 and w.host_info["pid"] != killed[0]
    assert state == ref
    assert processed == processed_ref == list(range(len(ITEMS)))  # each input reported once, in order


def test_live_server_on_processes_loses_nothing_when_the_mapper_process_dies(tmp_path):
    srv = LiveServer(
        tmp_path / "data", env={"HIPPOMAP_SNAPSHOT_EVERY_INPUTS": "60"}, args=["--backend", "process"]
    ).start()
    try:
        with srv.client() as c:
            sid = c.create_session("proc-kill", CONFIG)["id"]
            pid0 = c.stats(sid)["backend"]["pid"]
            assert c.stats(sid)["backend"]["kind"] == "process" and pid0 != srv.proc.pid

        async def stream() -> list[dict]:
            async with AsyncStream(srv.url, srv.token, sid, max_in_flight=32) as st:
                futs = []
                for k, it in enumerate(ITEMS):
                    if k == len(ITEMS) // 2:  # the robot keeps streaming while the mapper process is killed
                        await asyncio.to_thread(os.kill, pid0, signal.SIGKILL)
                    futs.append(await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2])))
                return list(await asyncio.gather(*futs))

        acks = asyncio.run(stream())
        assert [a["seq"] for a in acks] == list(range(len(ITEMS)))
        with srv.client() as c:
            state = session_state(c, sid)
            stats = c.stats(sid)
        assert stats["inputs_stored"] == len(ITEMS) and stats["error"] is None
        assert stats["backend"]["restarts"] >= 1 and stats["backend"]["pid"] != pid0
        assert state == offline_reference(ITEMS, CONFIG)
    finally:
        srv.stop()
