"""The PostgreSQL store against a real server on loopback (``HIPPOMAP_TEST_POSTGRES_URL``, or a
private cluster started by ``tests.support.postgres_cluster``), next to the SQLite store where the contract is
shared: group commit with failures inside a batch, many writer threads, session leases raced
by threads and processes, URL and connection errors, and a connection dropped mid-write."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import psycopg
import pytest

from server.app import open_store
from server.settings import ServerSettings
from server.storage.postgres import PostgresStore, StoreConnectionError, describe_url
from server.storage.sqlite import SQLiteStore
from server.storage.store import EventRecord, InputRecord, SessionRecord, TokenRecord
from tests.support.live import ROOT, free_port
from tests.support.postgres_cluster import postgres_test_url, postgres_url_for
from tests.support.variants import SERVICE_VARIANTS


def _location(kind: str, tmp_path) -> str:
    return str(tmp_path / "db.sqlite3") if kind == "sqlite" else postgres_url_for(tmp_path, fresh=True)


def _open(location: str):
    return PostgresStore(location) if location.startswith("postgresql://") else SQLiteStore(location)


@pytest.fixture(params=["sqlite", "postgres"])
def location(request, tmp_path):
    """An empty database of each backend (a SQLite path or a PostgreSQL URL)."""
    return _location(request.param, tmp_path)


@pytest.fixture()
def store(location):
    s = _open(location)
    yield s
    s.close()


@pytest.fixture()
def pg(tmp_path):
    s = PostgresStore(postgres_url_for(tmp_path, fresh=True))
    yield s
    s.close()


def _hold_writer(store):
    """Park the writer thread until the returned event is set, so what is submitted meanwhile
    lands in one batch (one transaction)."""
    gate, parked = threading.Event(), threading.Event()

    def op(conn):
        parked.set()
        gate.wait(30)

    store._submit(op)
    assert parked.wait(30)
    return gate


# ------------------------------------------------------------ group commit
def test_failed_writes_inside_one_batch_fail_alone_and_callbacks_keep_order(store):
    gate = _hold_writer(store)
    order: list[int] = []
    futs = {}
    for k in range(30):
        seq = 5 if k in (10, 20) else k  # writes 10 and 20 repeat the key of write 5
        futs[k] = store.append_inputs(
            "s", [InputRecord(seq, "odometry", float(k), bytes([k]))], on_durable=lambda k=k: order.append(k)
        )
    gate.set()
    good = [k for k in range(30) if k not in (10, 20)]
    for k in good:
        futs[k].result(30)
    for k in (10, 20):
        with pytest.raises(Exception):
            futs[k].result(30)
    assert order == good  # only committed writes call back, in submission order
    rows = store.read_inputs("s", -1, 100)
    assert [r.seq for r in rows] == good and rows[5].data == bytes([5])


def test_mixed_batch_keeps_submission_order(store):
    gate = _hold_writer(store)
    a = [store.append_inputs("s", [InputRecord(k, "odometry", float(k), b"old")]) for k in range(3)]
    d = store.delete_session("s")  # between appends of the same keys: order decides what survives
    b = [store.append_inputs("s", [InputRecord(k, "frame", 10.0 + k, b"new")]) for k in range(2)]
    snap = store.put_snapshot("s", 1, b"snap", keep=2)
    gate.set()
    for f in [*a, d, *b, snap]:
        f.result(30)
    assert [(r.seq, r.kind, r.data) for r in store.read_inputs("s", -1, 10)] == [
        (0, "frame", b"new"),
        (1, "frame", b"new"),
    ]
    assert store.latest_snapshot("s") == (1, b"snap") and store.last_times("s") == {"frame": 11.0}


def test_batch_of_one_failing_write_then_store_still_works(store):
    store.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"a")]).result(30)
    with pytest.raises(Exception):
        store.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"again")]).result(30)
    store.append_inputs("s", [InputRecord(1, "frame", 1.0, b"b")]).result(30)
    assert [r.data for r in store.read_inputs("s", -1, 10)] == [b"a", b"b"]


def test_concurrent_group_commit_from_many_threads_in_order(store):
    n_threads, n_each = 8, 60
    done: dict[str, list[int]] = {f"s{i}": [] for i in range(n_threads)}

    def work(sid: str) -> None:
        futs = [
            store.append_inputs(
                sid,
                [InputRecord(k, "frame" if k % 4 == 0 else "odometry", k * 0.05, bytes(100 + k))],
                on_durable=lambda k=k: done[sid].append(k),
            )
            for k in range(n_each)
        ]
        for f in futs:
            f.result(60)

    with ThreadPoolExecutor(n_threads) as pool:
        list(pool.map(work, done))
    for sid, seen in done.items():
        assert seen == list(range(n_each))
        rows = store.read_inputs(sid, -1, 1000)
        assert [r.seq for r in rows] == list(range(n_each))
        assert all(len(r.data) == 100 + r.seq for r in rows)
    store.flush()


def test_free_text_and_nan_round_trip(store):
    store.create_session(SessionRecord("a", "w", "nul\x00 and ünïcode ✓", {"map": {"alpha": 0.25}}, 2.5)).result(30)
    store.add_token("h", TokenRecord("t", "viewer", owner="w", session="a", label="x\x00y", created=1.0)).result(30)
    store.append_derived("a", [EventRecord(0, 0, "e", None, {"v": math.nan, "s": "q\x00"}, None)], []).result(30)
    (rec,) = store.list_sessions()
    assert rec == SessionRecord("a", "w", "nul\x00 and ünïcode ✓", {"map": {"alpha": 0.25}}, 2.5)
    assert store.token_by_hash("h") == TokenRecord("t", "viewer", owner="w", session="a", label="x\x00y", created=1.0)
    (ev,) = store.query_events("a")
    assert math.isnan(ev.data["v"]) and ev.data["s"] == "q\x00" and ev.t is None and ev.ref is None


def test_snapshot_replaced_at_same_seq_and_keep(store):
    for seq, data in ((1, b"a"), (2, b"b"), (2, b"b2"), (3, b"c")):
        store.put_snapshot("s", seq, data, keep=2).result(30)
    assert store.latest_snapshot("s") == (3, b"c")
    store.truncate_derived("s", 0).result(30)
    store.put_snapshot("s", 4, b"d", keep=1).result(30)
    assert store.latest_snapshot("s") == (4, b"d") and store.latest_snapshot("other") is None


# ----------------------------------------------------------------- leases
def test_lease_claim_renew_release_expire(store):
    assert store.session_owner("s") is None
    assert store.claim_session("s", "r1", 30) == "r1"
    assert store.claim_session("s", "r2", 30) == "r1"  # held: r2 is told who holds it
    assert store.claim_session("s", "r1", 30) == "r1"  # renewal
    assert store.session_owner("s") == "r1"
    assert store.release_session("s", "r2") is False  # not r2's to release
    assert store.release_session("s", "r1") is True
    assert store.session_owner("s") is None
    assert store.claim_session("s", "r2", 0.2) == "r2"
    time.sleep(0.4)  # r2's lease runs out
    assert store.session_owner("s") is None
    assert store.claim_session("s", "r3", 30) == "r3"
    store.delete_session("s").result(30)
    assert store.session_owner("s") is None and store.claim_session("s", "r4", 30) == "r4"
    with pytest.raises(ValueError):
        store.claim_session("s", "r4", 0)


def test_lease_race_between_threads_with_own_connections(location):
    n = 8
    stores = [_open(location) for _ in range(n)]
    try:
        for round_ in range(3):
            barrier = threading.Barrier(n)
            sid = f"race{round_}"

            def claim(i: int) -> str:
                barrier.wait(30)
                return stores[i].claim_session(sid, f"replica{i}", 30)

            with ThreadPoolExecutor(n) as pool:
                results = list(pool.map(claim, range(n)))
            assert len(set(results)) == 1, results  # everybody agrees on one owner...
            winner = results[0]
            assert winner in {f"replica{i}" for i in range(n)}  # ...who is one of the claimants
            assert stores[0].session_owner(sid) == winner
    finally:
        for s in stores:
            s.close()


_CLAIMER = """
import sys, time
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SQLiteStore
loc, name, start = sys.argv[1], sys.argv[2], float(sys.argv[3])
s = PostgresStore(loc) if loc.startswith("postgresql://") else SQLiteStore(loc)
time.sleep(max(0.0, start - time.time()))
print(s.claim_session("shared", name, 30), flush=True)
s.close()
"""


def test_lease_race_between_processes(location):
    _open(location).close()  # schema in place before the race
    start = time.time() + 3.0  # every process claims at the same moment, after its imports
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _CLAIMER, location, f"proc{i}", str(start)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(4)
    ]
    outs = []
    for p in procs:
        out, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
        outs.append(out.strip())
    assert len(set(outs)) == 1 and outs[0] in {f"proc{i}" for i in range(4)}, outs


# ---------------------------------------------------------- URLs and errors
def test_open_store_picks_backend_by_url(tmp_path):
    url = postgres_url_for(tmp_path / "a", fresh=True)
    for u in (url, "postgres://" + url[len("postgresql://") :]):
        s = open_store(ServerSettings(data_dir=tmp_path, database=u))
        try:
            assert isinstance(s, PostgresStore)
        finally:
            s.close()
    for db in (None, str(tmp_path / "x.sqlite3"), f"sqlite://{tmp_path}/y.sqlite3"):
        s = open_store(ServerSettings(data_dir=tmp_path, database=db))
        try:
            assert isinstance(s, SQLiteStore)
        finally:
            s.close()
    assert (tmp_path / "hippomap.sqlite3").exists() and (tmp_path / "x.sqlite3").exists()
    assert (tmp_path / "y.sqlite3").exists()


def test_unsupported_scheme_names_accepted_forms_without_the_password(tmp_path):
    with pytest.raises(RuntimeError) as exc:
        open_store(ServerSettings(data_dir=tmp_path, database="mysql://root:hunter2@db/x"))
    msg = str(exc.value)
    assert "mysql://" in msg and "postgresql://" in msg and "sqlite://" in msg and "hunter2" not in msg


def test_unreachable_server_names_host_and_database_not_password(tmp_path):
    port = free_port()  # nothing listens there
    url = f"postgresql://robot:hunter2@127.0.0.1:{port}/fleet_maps"
    with pytest.raises(StoreConnectionError) as exc:
        open_store(ServerSettings(data_dir=tmp_path, database=url))
    msg = str(exc.value)
    assert f"127.0.0.1:{port}/fleet_maps" in msg and "robot" in msg and "hunter2" not in msg
    assert describe_url(url) == f"robot@127.0.0.1:{port}/fleet_maps"


def test_wrong_password_is_reported_without_it(tmp_path):
    url = postgres_url_for(tmp_path, fresh=True)
    user_at = url.index("@")
    bad = url[: url.index(":", len("postgresql://")) + 1] + "not-the-pw-42" + url[user_at:]
    with pytest.raises(StoreConnectionError) as exc:
        PostgresStore(bad)
    assert "not-the-pw-42" not in str(exc.value) and "password" in str(exc.value).lower()


def test_schema_version_mismatch_is_refused(pg):
    with psycopg.connect(pg.url, autocommit=True) as c:
        c.execute("UPDATE meta SET value='99' WHERE key='schema'")
    with pytest.raises(RuntimeError, match="schema 99"):
        PostgresStore(pg.url)


def test_replicas_opening_a_new_database_together(tmp_path):
    url = postgres_url_for(tmp_path, fresh=True)
    with ThreadPoolExecutor(6) as pool:
        stores = list(pool.map(lambda _: PostgresStore(url), range(6)))
    try:
        stores[0].append_inputs("s", [InputRecord(0, "odometry", 0.0, b"x")]).result(30)
        assert all(s.last_input("s") == (0, 0.0) for s in stores)
    finally:
        for s in stores:
            s.close()


def test_missing_postgresql_programs_say_what_to_install(tmp_path, monkeypatch):
    import tests.support.postgres_cluster as postgres_cluster

    monkeypatch.setattr(postgres_cluster, "POSTGRES_LIB", tmp_path / "none")
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(RuntimeError, match=r"apt-get install -y postgresql"):
        postgres_cluster.postgres_bin_dir()


# ----------------------------------------------------- a dropped connection
def _terminate(url: str, pid: int) -> None:
    with psycopg.connect(url, autocommit=True) as c:
        assert c.execute("SELECT pg_terminate_backend(%s)", (pid,)).fetchone()[0]


def test_connection_dropped_mid_write_fails_the_batch_not_hangs(pg):
    pg.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"kept")]).result(30)
    started = threading.Event()

    def slow(conn):  # a write in progress on the server when its connection is killed
        started.set()
        conn.execute("SELECT pg_sleep(30)")

    gate = _hold_writer(pg)
    doomed = pg._submit(slow)
    queued = pg.append_inputs("s", [InputRecord(1, "odometry", 1.0, b"lost")])  # same batch, after it
    gate.set()
    assert started.wait(30)
    time.sleep(0.2)  # let the sleep reach the server
    _terminate(postgres_test_url(), pg._writer_conn.info.backend_pid)
    with pytest.raises(StoreConnectionError, match="127.0.0.1"):
        doomed.result(30)
    with pytest.raises(StoreConnectionError):
        queued.result(30)  # its batch was not committed: not durable, not acknowledged
    # the writer reconnects: the next write goes through and the lost one is not there
    pg.append_inputs("s", [InputRecord(1, "odometry", 1.0, b"retried")]).result(30)
    assert [r.data for r in pg.read_inputs("s", -1, 10)] == [b"kept", b"retried"]


def test_idle_connections_dropped_by_the_server_are_replaced_without_failing(pg):
    pg.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"x")]).result(30)
    assert pg.last_input("s") == (0, 0.0)  # a pooled read connection now exists
    dbname = pg.url.rsplit("/", 1)[1]
    with psycopg.connect(postgres_test_url(), autocommit=True) as c:  # as a database restart would
        n = c.execute(
            "SELECT count(pg_terminate_backend(pid, 10000)) FROM pg_stat_activity WHERE datname=%s "
            "AND application_name='hippomap'",
            (dbname,),
        ).fetchone()[0]
    assert n >= 2  # the writer and the reader
    pg.append_inputs("s", [InputRecord(1, "odometry", 1.0, b"y")]).result(30)
    assert pg.last_input("s") == (1, 1.0) and [r.data for r in pg.read_inputs("s", -1, 5)] == [b"x", b"y"]


def test_durability_normal_is_accepted(tmp_path):
    s = PostgresStore(postgres_url_for(tmp_path, fresh=True), durability="normal")
    try:
        s.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"x")]).result(30)
        assert s._writer_conn.execute("SHOW synchronous_commit").fetchone()[0] == "off"
    finally:
        s.close()


# ------------------------------------------------------- service variant
def test_postgres_service_variant_gives_each_data_folder_its_own_database(tmp_path):
    (variant,) = [v for v in SERVICE_VARIANTS if v.name == "inprocess-postgres"]
    env = variant.env(tmp_path / "d1")
    assert env["HIPPOMAP_DATABASE"].startswith("postgresql://")
    assert variant.env(tmp_path / "d1") == env != variant.env(tmp_path / "d2")
    a = variant.open_store(tmp_path / "d1")
    try:
        assert isinstance(a, PostgresStore)
        a.create_session(SessionRecord("x", "w", created=1.0)).result(30)
    finally:
        a.close()
    b, c = variant.open_store(tmp_path / "d1"), variant.open_store(tmp_path / "d2")
    try:
        assert [r.id for r in b.list_sessions()] == ["x"] and c.list_sessions() == []
    finally:
        b.close()
        c.close()
    assert json.loads(json.dumps(env))  # plain strings: passable to a subprocess
