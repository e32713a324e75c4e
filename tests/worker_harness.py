"""Drives a SessionWorker the way a live session does, for the backend tests (in-process, child
processes, Ray): inputs are made durable in a store first, then handed to the worker."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from hippomap import mapper_queries as mq
from server.formats.ingest import odometry_bytes
from server.runtime import model
from server.runtime.worker import SessionWorker, WorkItem
from server.settings import ServerSettings
from server.storage.sqlite import SQLiteStore
from server.storage.store import InputRecord, SessionRecord
from tests.support.synthetic import decoded


def records(items: tuple) -> list[InputRecord]:
    """``synthetic_inputs`` items as the store's input records."""
    return [
        InputRecord(seq, "odometry", it[1].t, odometry_bytes(it[1]))
        if it[0] == "odometry"
        else InputRecord(seq, "frame", it[1], it[2])
        for seq, it in enumerate(items)
    ]


def run_worker(tmp_path, items: tuple, config: dict[str, Any], host_factory, kill_at=None, metrics=None):
    """Feed ``items`` to a SessionWorker (durable first); ``kill_at(worker)`` is called once half the
    inputs are queued. Returns the final state, the inputs reported, the worker, the stored events
    and the stored place fields."""
    store = SQLiteStore(tmp_path / "db.sqlite3", "normal")
    sid = "s_unit"
    store.create_session(SessionRecord(id=sid, owner="t", config=config)).result()
    settings = ServerSettings(data_dir=tmp_path, snapshot_every_inputs=50, backend_max_restarts=3)
    processed: list[int] = []
    w = SessionWorker(
        sid,
        model.effective_config(config),
        store,
        settings,
        replay_until=-1,
        on_processed=processed.append,
        host_factory=host_factory,
        metrics=metrics,
    )
    w.start()
    assert w.ready.wait(120) and w.error is None
    recs, values = records(items), decoded(items)
    half = len(items) // 2
    for k in range(0, len(items), 10):
        work = [WorkItem(r.seq, v) for r, v in zip(recs[k : k + 10], values[k : k + 10])]
        store.append_inputs(sid, recs[k : k + 10], on_durable=lambda work=work: w.put(work)).result()
        if kill_at is not None and k <= half < k + 10:
            kill_at(w)
    deadline = time.monotonic() + 120
    while w.processed_seq < len(items) - 1 and w.error is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert w.error is None
    state = {"graph": model.graph(w.query(mq.GraphArrays())), "stats": w.query(mq.Stats())}
    w.stop(snapshot=True)
    events = store.query_events(sid, limit=100_000)
    fields = store.place_fields(sid, limit=100_000, with_data=True)
    store.close()
    return state, processed, w, events, fields


def assert_host_matches_inprocess(remote, kind: str, items: tuple, config_overrides: dict[str, Any]):
    """``remote`` (a host of another kind: ``kind``) gives the in-process host's results on ``items``:
    the same step results, map and trajectory, and a snapshot it takes restores in process.
    Returns the in-process host, fed the same items."""
    from server.runtime.mapper_host import InProcessHost

    values = decoded(items)
    config = model.effective_config(config_overrides)
    local = InProcessHost()
    assert local.restore(None, config) == remote.restore(None, config)
    assert remote.info()["kind"] == kind and remote.info()["pid"] != os.getpid()
    batch = list(enumerate(values))
    a, b = local.process(batch), remote.process(batch)
    assert [r.seq for r in b] == list(range(len(values)))
    assert [(r.kind, r.t, r.events, r.field) for r in a] == [(r.kind, r.t, r.events, r.field) for r in b]
    assert any(r.field is not None for r in b) and any(r.events for r in b)
    assert model.graph(local.query(mq.GraphArrays())) == model.graph(remote.query(mq.GraphArrays()))
    for source in ("map", "odometry"):
        (ta, pa), (tb, pb) = local.query(mq.Trajectory(source)), remote.query(mq.Trajectory(source))
        assert ta.tolist() == tb.tolist() and pa.tolist() == pb.tolist()
    assert local.query(mq.Recognitions()) == remote.query(mq.Recognitions())
    la, lb = local.query(mq.LoopDecisions()), remote.query(mq.LoopDecisions())
    assert [d.to_dict() for d in la.decisions] == [d.to_dict() for d in lb.decisions]
    np.testing.assert_array_equal(la.weights, lb.weights)
    again = InProcessHost()  # a snapshot taken remotely restores locally to the same mapper
    again.restore(remote.snapshot(), config)
    assert again.query(mq.Stats()) == local.query(mq.Stats())
    return local
