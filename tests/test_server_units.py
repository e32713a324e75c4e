"""Unit tests of the server's parts that need no running server: store, auth, limits,
image header sniffing, the websocket frame header and input validation."""

from __future__ import annotations

import json
import math
import threading
import time

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.errors import InputError
from hippomap.inputs import Odometry
from server.formats.images import image_dimensions
from server.formats.ingest import (
    IngestError,
    check_frame,
    check_odometry,
    odometry_bytes,
    odometry_from_bytes,
    parse_odometry_message,
)
from server.formats.protocol import pack_frame, unpack_frame
from server.formats.schemas import OdometryReading
from server.security.auth import Authenticator, can_read, can_write, ensure_admin, hash_secret
from server.security.limits import TokenBucket
from server.settings import ServerSettings
from server.storage.postgres import PostgresStore
from server.storage.sqlite import SQLiteStore
from server.storage.store import EventRecord, InputRecord, PlaceFieldRecord, SessionRecord, TokenRecord
from tests.support.postgres_cluster import postgres_url_for


@pytest.fixture(params=["sqlite", "postgres"])
def store(request, tmp_path):
    """Each store backend on an empty database of its own (both must pass the same contract)."""
    if request.param == "sqlite":
        s = SQLiteStore(tmp_path / "db.sqlite3")
    else:
        s = PostgresStore(postgres_url_for(tmp_path, fresh=True))
    yield s
    s.close()


def _reopen(store):
    """A second, independent store on the same database (as another process would open it)."""
    return SQLiteStore(store.path) if isinstance(store, SQLiteStore) else PostgresStore(store.url)


def _jpeg(w: int, h: int, seed: int = 0) -> bytes:
    img = (np.random.default_rng(seed).random((h, w)) * 255).astype(np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


# ---------------------------------------------------------------- store
def test_store_inputs_durable_in_order_and_callbacks_in_commit_order(store, tmp_path):
    order: list[int] = []
    futs = []
    for k in range(50):
        rec = InputRecord(seq=k, kind="odometry" if k % 3 else "frame", t=float(k), data=bytes([k]))
        futs.append(store.append_inputs("s1", [rec], on_durable=lambda k=k: order.append(k)))
    for f in futs:
        f.result(10)
    assert order == list(range(50))
    # a second connection (another process would see the same) reads everything back
    other = _reopen(store)
    try:
        rows = other.read_inputs("s1", -1, 1000)
        assert [r.seq for r in rows] == list(range(50))
        assert [r.data for r in rows] == [bytes([k]) for k in range(50)]
        assert rows[0].kind == "frame" and rows[1].kind == "odometry"
        assert other.last_input("s1") == (49, 49.0)
        assert other.last_times("s1") == {"odometry": 49.0, "frame": 48.0} and other.last_times("none") == {}
        assert other.frame_at("s1", 3.0).seq == 3 and other.frame_at("s1", 4.0) is None
    finally:
        other.close()


def test_store_failed_write_does_not_spoil_its_batch(store):
    ok1 = store.append_inputs("s", [InputRecord(0, "odometry", 0.0, b"a")])
    dup = store.append_inputs("s", [InputRecord(0, "odometry", 0.5, b"dup")])  # same primary key
    ok2 = store.append_inputs("s", [InputRecord(1, "odometry", 1.0, b"b")])
    ok1.result(10)
    ok2.result(10)
    with pytest.raises(Exception):
        dup.result(10)
    assert [r.data for r in store.read_inputs("s", -1, 10)] == [b"a", b"b"]


def test_store_snapshots_keep_newest_and_derived_truncation(store):
    for seq in (10, 20, 30):
        store.put_snapshot("s", seq, f"snap{seq}".encode(), keep=2).result(10)
    assert store.latest_snapshot("s") == (30, b"snap30")
    ev = [
        EventRecord(id=i, seq=i * 10, type="recognition" if i % 2 else "node_created", t=float(i), data={"i": i}, ref=i)
        for i in range(6)
    ]
    pf = [PlaceFieldRecord(step=i, seq=i * 10, t=float(i), data=b"x") for i in range(6)]
    store.append_derived("s", ev, pf).result(10)
    assert store.derived_counts("s") == (6, 6)
    assert [e.id for e in store.query_events("s", types=["recognition"])] == [1, 3, 5]
    assert [e.id for e in store.query_events("s", since_id=2, t_max=4.0)] == [3, 4]
    assert store.event_by_ref("s", "recognition", 3).data == {"i": 3}
    store.truncate_derived("s", 25).result(10)  # drop what inputs after seq 25 produced
    assert store.derived_counts("s") == (3, 3)
    assert store.place_field("s", 3) is None and store.place_field("s", 2).seq == 20


def test_store_sessions_and_tokens(store):
    store.create_session(SessionRecord("a", "tokA", "one", {"map": {"alpha": 0.3}}, 1.0)).result(10)
    store.append_inputs("a", [InputRecord(0, "odometry", 0.0, b"{}")]).result(10)
    assert store.list_sessions()[0].config == {"map": {"alpha": 0.3}}
    store.delete_session("a").result(10)
    assert store.list_sessions() == [] and store.read_inputs("a", -1, 10) == []
    store.add_token(hash_secret("s3cret"), TokenRecord("t1", "writer", owner="admin")).result(10)
    assert store.token_by_hash(hash_secret("s3cret")).id == "t1"
    assert store.token_by_hash(hash_secret("other")) is None


def test_store_group_commit_from_many_threads(store):
    def work(sid: str) -> None:
        for k in range(40):
            store.append_inputs(sid, [InputRecord(k, "odometry", float(k), b"x")]).result(10)

    threads = [threading.Thread(target=work, args=(f"s{i}",)) for i in range(6)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for i in range(6):
        assert [r.seq for r in store.read_inputs(f"s{i}", -1, 100)] == list(range(40))


# ----------------------------------------------------------------- auth
def test_token_visibility_rules():
    owner = TokenRecord("w1", "writer")
    other = TokenRecord("w2", "writer")
    viewer_all = TokenRecord("v1", "viewer", owner="w1")
    viewer_one = TokenRecord("v2", "viewer", owner="w1", session="s2")
    s1, s2 = SessionRecord("s1", "w1"), SessionRecord("s2", "w1")
    assert can_read(owner, s1) and can_write(owner, s1)
    assert not can_read(other, s1) and not can_write(other, s1)
    assert can_read(viewer_all, s1) and can_read(viewer_all, s2) and not can_write(viewer_all, s1)
    assert can_read(viewer_one, s2) and not can_read(viewer_one, s1) and not can_write(viewer_one, s2)


def test_admin_token_generated_once_and_kept(store, tmp_path):
    f = tmp_path / "admin.token"
    secret, created = ensure_admin(store, f, None)
    assert created and f.read_text().strip() == secret and (f.stat().st_mode & 0o777) == 0o600
    again, created2 = ensure_admin(store, f, None)
    assert again == secret and not created2
    auth = Authenticator(store)
    assert auth.authenticate(secret).role == "admin"
    assert auth.authenticate("hm_wrong") is None and auth.authenticate(None) is None
    rotated, _ = ensure_admin(store, f, "hm_configured")  # a configured secret replaces it, same id
    assert auth.authenticate("hm_configured").id == "admin"
    auth.forget()
    assert auth.authenticate(secret) is None


# --------------------------------------------------------------- limits
def test_token_bucket_limits_rate():
    b = TokenBucket(rate=10.0, burst=3.0)
    assert [b.take() for _ in range(3)] == [0.0, 0.0, 0.0]
    wait = b.take()
    assert 0 < wait <= 0.1 + 1e-9
    time.sleep(0.12)
    assert b.take() == 0.0
    assert b.reserve(5.0) > 0.3  # pacing: debt is paid back at the rate


# --------------------------------------------------------------- images
@settings(max_examples=25, deadline=None)
@given(w=st.integers(16, 700), h=st.integers(16, 500), png=st.booleans())
def test_image_dimensions_match_the_decoder(w, h, png):
    img = np.zeros((h, w), np.uint8)
    data = cv2.imencode(".png" if png else ".jpg", img)[1].tobytes()
    assert image_dimensions(data) == (w, h)


def test_image_dimensions_rejects_garbage():
    with pytest.raises(InputError, match="not a JPEG or PNG"):
        image_dimensions(b"GIF89a....")
    with pytest.raises(InputError, match="corrupt JPEG"):
        image_dimensions(b"\xff\xd8\xff\xe0\x00\x10JFIF" + b"\x00" * 3)


# ------------------------------------------------------------- protocol
def test_frame_header_roundtrip_and_errors():
    msg = pack_frame(77, 12.5, b"\xff\xd8\xffjpeg")
    assert unpack_frame(msg) == (77, 12.5, b"\xff\xd8\xffjpeg")
    with pytest.raises(InputError, match="shorter"):
        unpack_frame(b"HMF1")
    with pytest.raises(InputError, match="magic"):
        unpack_frame(b"XXXX" + msg[4:])


# ------------------------------------------------------------ ingest
def _readings(*rows):
    return [OdometryReading(**r) for r in rows]


def test_odometry_validation_names_the_problem():
    ok = check_odometry(_readings({"t": 1.0, "v": 0.1, "omega": 0.0}, {"t": 2.0, "increment": (0.1, 0, 0)}), 10)
    assert [a.t for a in ok] == [1.0, 2.0]
    assert odometry_from_bytes(ok[1].data) == Odometry(2.0, increment=(0.1, 0.0, 0.0))
    cases = [
        ([{"t": 1.0, "v": math.nan, "omega": 0.0}], 422, "v must be finite"),
        ([{"t": math.inf, "v": 0.0, "omega": 0.0}], 422, "t must be finite"),
        ([{"t": 1.0, "v": 0.1}], 422, "needs v and omega"),
        ([{"t": 1.0, "v": 0.1, "omega": 0, "increment": (0, 0, 0)}], 422, "not both"),
        ([{"t": 2.0, "v": 0.1, "omega": 0}, {"t": 2.0, "v": 0.1, "omega": 0}], 409, "readings[1]"),
    ]
    for rows, status, text in cases:
        with pytest.raises(IngestError) as e:
            check_odometry(_readings(*rows), 10)
        assert e.value.status == status and text in e.value.detail
    with pytest.raises(IngestError) as e:
        check_odometry(_readings(*[{"t": float(i), "v": 0, "omega": 0} for i in range(11)]), 10)
    assert e.value.status == 413


def test_websocket_odometry_messages():
    one = parse_odometry_message({"type": "odometry", "id": 1, "t": 1.0, "v": 0.2, "omega": 0.1}, 10)
    assert one[0].value == Odometry(1.0, v=0.2, omega=0.1)
    many = parse_odometry_message(
        {"type": "odometry", "readings": [{"t": 1, "v": 0, "omega": 0}, {"t": 2, "v": 0, "omega": 0}]}, 10
    )
    assert len(many) == 2
    for msg, status in [
        ({"type": "odometry", "t": "x", "v": 0, "omega": 0}, 422),
        ({"type": "odometry", "t": 1, "v": 0, "omega": 0, "bogus": 1}, 422),
        ({"type": "odometry", "readings": "no"}, 422),
        ({"type": "odometry", "readings": [{"t": i, "v": 0, "omega": 0} for i in range(20)]}, 413),
    ]:
        with pytest.raises(IngestError) as e:
            parse_odometry_message(msg, 10)
        assert e.value.status == status


def test_frame_validation_statuses():
    s = ServerSettings(max_frame_bytes=200_000, max_image_side=1000, max_image_pixels=500_000)
    good = check_frame(_jpeg(320, 240), 1.5, s)
    assert good.value.image.shape == (240, 320) and good.t == 1.5
    png = cv2.imencode(".png", np.full((60, 80), 7, np.uint8))[1].tobytes()
    assert check_frame(png, 2, s).value.image.shape == (60, 80)
    jpeg = _jpeg(320, 240)
    cases = [
        (b"", 1.0, 422, "empty"),
        (b"GIF89a" + b"\x00" * 100, 1.0, 415, "not a JPEG or PNG"),
        (jpeg[:200], 1.0, 422, "corrupt"),
        (jpeg[: len(jpeg) // 2], 1.0, 422, "truncated"),
        (jpeg[:3] + b"\x00" * 500, 1.0, 422, "corrupt"),
        (jpeg, math.nan, 422, "finite"),
        (jpeg, "soon", 422, "number"),
        (_jpeg(1200, 100), 1.0, 413, "1200x100"),
        (b"\xff\xd8\xff" + b"\x00" * 200_001, 1.0, 413, "200004 bytes"),
    ]
    for data, t, status, text in cases:
        with pytest.raises(IngestError) as e:
            check_frame(data, t, s)
        assert e.value.status == status, (status, e.value.detail)
        assert text in e.value.detail


def test_odometry_record_roundtrip_is_exact():
    o = Odometry(0.1 + 0.2, v=1 / 3, omega=-2 / 7)
    assert odometry_from_bytes(odometry_bytes(o)) == o
    assert json.loads(odometry_bytes(o))["t"] == 0.1 + 0.2


def test_the_worker_stores_each_event_under_the_input_that_caused_it(tmp_path):
    """A key frame's assignment to its node (an event of the map, raised while the frame was observed)
    is stored under that frame's sequence number, beside the key frame it assigns; every stored
    event has its time in ``t``, and a query that is not one of the model's is refused."""
    from server.runtime.mapper_host import InProcessHost
    from tests.support.synthetic import synthetic_inputs
    from tests.worker_harness import run_worker

    items = synthetic_inputs(n_odometry=120, frame_every=3)
    _, _, w, events, _ = run_worker(tmp_path, items, {"mapper": {"keyframe_interval": 3}}, lambda sid: InProcessHost())
    learned = {e.data["frame"]: e.seq for e in events if e.type == "keyframe_learned"}
    assigned = {e.data["frame"]: e.seq for e in events if e.type == "frame_assigned"}
    assert learned and assigned == learned
    assert all(items[seq][0] == "frame" for seq in learned.values())
    assert all(e.t == e.data["t"] and isinstance(e.t, float) and "time" not in e.data for e in events)
    with pytest.raises(InputError, match="unknown mapper query"):
        w.query(lambda m: m.stats())  # type: ignore[arg-type]
