"""The live viewer without a browser: chunked layers, trajectory sampling, the place-field heatmap,
panels, a SessionViewer over a real Mapper fed by the camera simulator, and the FastAPI proxy."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st
from starlette.websockets import WebSocketDisconnect

from hippomap import sim
from hippomap.config import HippomapConfig
from hippomap.place_cells import SpatialPathway
from hippomap.visual_memory import VisualMemory
from web.chunks import ChunkTracker, chunk_layout
from web.images import recognition_from_dict, trace_panel
from web.panel_evidence import evidence_curves
from web.routes import SUBPROTOCOL, SessionEntry, make_router
from web.scene_place_field import field_heatmap
from web.scene_trajectories import TrajectorySampler
from web.session_viewer import SessionViewer, ViewerHub
from web.settings import ViewerSettings
from web.simfeed import sim_inputs
from web.snapshot import PlaceFieldView
from web.source import LocalSession

# ----------------------------------------------------------------------------- chunked layers


def test_chunk_layout_seals_full_blocks_and_tails_the_rest():
    assert chunk_layout(0, 8, 2) == []
    assert chunk_layout(5, 8, 2) == [(0, 2), (2, 4), (4, 5)]
    assert chunk_layout(8, 8, 2) == [(0, 8)]
    assert chunk_layout(19, 8, 4) == [(0, 8), (8, 16), (16, 19)]


def test_chunks_growth_sends_only_the_tail():
    tr = ChunkTracker(chunk_size=8, tolerance=0.01, width=3, tail_size=2)
    g = np.arange(30, dtype=float).reshape(10, 3)
    c = np.zeros((10, 3), np.uint8)
    up = tr.plan(g, c)
    assert up.chunks == ((0, 8), (8, 10)) and up.items == 10 and up.removed == ()
    g2 = np.vstack([g, np.ones((1, 3))])
    up = tr.plan(g2, np.zeros((11, 3), np.uint8))
    assert up.chunks == ((10, 11),) and up.items == 1  # one new tail chunk; nothing else is resent
    assert tr.plan(g2, np.zeros((11, 3), np.uint8)).chunks == ()
    # filling the block seals it: its tail chunks are replaced by one sealed chunk
    g3 = np.vstack([g2, np.full((5, 3), 2.0)])
    up = tr.plan(g3, np.zeros((16, 3), np.uint8))
    assert up.chunks == ((8, 16),) and up.removed == (10,)  # chunk 8 is replaced in place
    assert tr.layout == {0: 8, 8: 16}


def test_chunks_resend_only_moved_chunks_beyond_tolerance():
    tr = ChunkTracker(chunk_size=4, tolerance=0.01, width=3)
    g = np.zeros((12, 3))
    c = np.zeros((12, 3), np.uint8)
    tr.plan(g, c)
    g[5, 0] += 0.005  # below tolerance: nothing to send
    assert tr.plan(g, c).chunks == ()
    g[5, 0] += 0.01  # now 0.015 from what the browser holds
    assert tr.plan(g, c).chunks == ((4, 8),)
    c[11] = (1, 2, 3)  # a colour change also resends
    assert tr.plan(g, c).chunks == ((8, 12),)


def test_chunks_shrinking_resends_everything():
    tr = ChunkTracker(chunk_size=4, tolerance=0.01, width=3, tail_size=2)
    tr.plan(np.zeros((9, 3)), np.zeros((9, 3), np.uint8))
    up = tr.plan(np.ones((5, 3)), np.zeros((5, 3), np.uint8))
    assert up.chunks == ((0, 4), (4, 5)) and up.removed == (8,) and tr.n == 5


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 9), st.lists(st.floats(-0.05, 0.05), min_size=1, max_size=6)),
                min_size=1, max_size=12), st.integers(1, 6), st.integers(1, 6))
def test_chunks_browser_copy_stays_within_tolerance(ops, chunk, tail):
    """Whatever appends and moves happen, what the browser holds is within tolerance of the map, a
    chunk that was not resent still holds exactly what it held before, and the chunks it holds
    always tile the items exactly."""
    tail = min(tail, chunk)
    tol = 0.02
    tr = ChunkTracker(chunk_size=chunk, tolerance=tol, width=2, tail_size=tail)
    g = np.zeros((0, 2))
    rng = np.random.default_rng(len(ops))
    for grow, moves in ops:
        g = np.vstack([g, rng.normal(size=(grow, 2))])
        if len(g):
            idx = rng.integers(0, len(g), size=len(moves))
            g[idx, 0] += moves
        before = tr._geom[: tr.n].copy()
        up = tr.plan(g, np.zeros((len(g), 3), np.uint8))
        held = tr._geom[: tr.n]
        assert tr.n == len(g)
        assert np.all(np.abs(held - g.astype(np.float32)) <= tol + 1e-6)
        untouched = np.ones(len(before), bool)
        for a, b in up.chunks:
            untouched[a:b] = False
        assert np.array_equal(held[: len(before)][untouched], before[untouched])
        spans = sorted(tr.layout.items())
        if spans:
            assert [a for a, _ in spans] == [0] + [b for _, b in spans[:-1]] and spans[-1][1] == len(g)
        assert all(b - a <= tail for a, b in spans if b - a != chunk)


# ------------------------------------------------------------------------- trajectory sampling


def _rows(xy: np.ndarray) -> np.ndarray:
    rows = np.zeros((len(xy), 8))
    rows[:, 0] = np.arange(len(xy))
    rows[:, 1:3] = xy
    return rows


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 40), min_size=1, max_size=8))
def test_trajectory_sampling_is_independent_of_how_rows_arrive(pieces):
    rng = np.random.default_rng(sum(pieces))
    n = sum(pieces)
    rows = _rows(np.cumsum(rng.uniform(0, 0.03, size=(n, 2)), axis=0))
    whole = TrajectorySampler(0.05)
    whole.add(0, rows)
    parts = TrajectorySampler(0.05)
    start = 0
    for p in pieces:
        parts.add(start, rows[start:start + p])
        start += p
    assert np.array_equal(whole.samples, parts.samples)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(1, 300), min_size=1, max_size=6), st.integers(3, 40))
def test_trajectory_budget_thins_exactly_like_sampling_coarser(pieces, budget):
    rng = np.random.default_rng(sum(pieces) + budget)
    rows = _rows(np.cumsum(rng.uniform(0, 0.04, size=(sum(pieces), 2)), axis=0))
    s = TrajectorySampler(0.05, budget)
    start = 0
    for p in pieces:
        s.add(start, rows[start:start + p])
        start += p
        assert len(s.samples) <= budget
    coarse = TrajectorySampler(s.spacing)
    coarse.add(0, rows)
    assert np.array_equal(s.samples, coarse.samples)
    finer = TrajectorySampler(s.spacing / 2)
    finer.add(0, rows)
    assert s.spacing == 0.05 or len(finer.samples) > budget  # doubled only when the budget forced it


def test_trajectory_sampling_keeps_one_row_per_spacing():
    x = np.linspace(0, 10, 1001)  # 1 cm steps along a straight 10 m line
    s = TrajectorySampler(0.5)
    s.add(0, _rows(np.column_stack([x, np.zeros_like(x)])))
    kept = s.samples[:, 1]
    assert kept[0] == 0.0 and len(kept) == 21
    assert np.allclose(np.diff(kept), 0.5, atol=0.011)


# ------------------------------------------------------------------------------ place field


def _place_view(map_pose=None) -> PlaceFieldView:
    pw = SpatialPathway()
    code = None
    for _ in range(5):
        code = pw.step_increment(0.013, 0.004, 0.01)
    assert code is not None and code.field is not None
    odo = np.asarray(pw.pose)
    return PlaceFieldView(code, pw.place_cells.tables, pw.cfg, odo, odo if map_pose is None else np.asarray(map_pose))


def test_place_field_heatmap_peaks_at_the_field_and_lies_under_the_robot():
    view = _place_view()
    hm = field_heatmap(view, 101)
    assert hm.values.shape == hm.mask.shape and 0.0 <= hm.values.min() and hm.values.max() <= 1.0
    assert hm.mask.any()
    # the field's pixels are where (almost) every applied grid-cell window agrees, the rest is far lower
    assert hm.values[hm.mask].max() >= 0.8
    assert hm.values.mean() < 0.6
    jy, jx = np.nonzero(hm.values == hm.values.max())
    my, mx = np.nonzero(hm.mask)
    assert np.min(np.hypot(jy[:, None] - my, jx[:, None] - mx)) <= 2
    # identity map frame: the heatmap covers the coding area whose corner is the place code's origin
    o = np.asarray(view.code.origin)
    assert np.allclose(hm.centre[:2], o + hm.side_m / 2, atol=1e-9)
    assert hm.side_m == pytest.approx(view.spatial.area_size_m, rel=0.02)


def test_place_field_heatmap_follows_the_map_frame():
    base = _place_view()
    moved = np.array([5.0, -2.0, base.odometric_pose[2] + math.pi / 2])
    view = PlaceFieldView(base.code, base.tables, base.spatial, base.odometric_pose, moved)
    hm = field_heatmap(view, 81)
    # the field (place code p) is carried with the robot: in the map it lies where the robot is
    c = hm.centre
    local = np.array([base.code.x, base.code.y]) - (np.asarray(base.code.origin) + hm.side_m / 2)
    ca, sa = math.cos(c[2]), math.sin(c[2])
    field_in_map = c[:2] + np.array([ca * local[0] - sa * local[1], sa * local[0] + ca * local[1]])
    assert np.linalg.norm(field_in_map - moved[:2]) < 0.01


# ---------------------------------------------------------------------------------- panels


def _recognition_dict() -> dict:
    steps = []
    for k, (ev, out) in enumerate([([(3, 0.2), (7, 0.1)], "start"), ([(3, 0.5), (7, 0.3)], "confirmed"),
                                   ([(3, 0.95), (9, 0.4)], "confirmed")]):
        steps.append({"attempt": 0, "fixation": [40.0 + 30 * k, 50.0], "target": [42.0 + 30 * k, 50.0],
                      "predicted_frame": 3, "predicted_feature": k, "found_frame": 3, "found_feature": k,
                      "similarity": 0.8, "outcome": out, "evidence": [list(e) for e in ev], "event": None})
    return {"id": 4, "t": 12.5, "node": 9, "frame_id": 3, "accepted": True, "evidence": 0.95, "confidence": 1.0,
            "n_resets": 0, "n_fixations": 3, "image_size": [160, 120], "reason": "", "steps": steps}


def test_evidence_curves_put_the_accepted_frame_first():
    x, frames, curves = evidence_curves(_recognition_dict())
    assert list(x) == [1.0, 2.0, 3.0]
    assert frames[0] == 3 and set(frames) == {3, 7, 9}
    assert list(curves[0]) == [0.2, 0.5, 0.95]
    assert list(curves[frames.index(7)]) == [0.1, 0.3, 0.0]  # absent from a step's leaders -> 0


def test_trace_panel_draws_query_and_thumbnail():
    rec = _recognition_dict()
    query = np.full((120, 160), 128, np.uint8)
    key = np.full((120, 160, 3), 30, np.uint8)
    img = trace_panel(query, rec, key, 320, 160)
    assert img.dtype == np.uint8 and img.shape == (240, 320 + 4 + 160, 3)
    left = img[:, :320].astype(int)
    assert (np.abs(left - 128).sum(axis=2) > 60).sum() > 200  # fixations, numbers and saccade lines drawn
    rejected = trace_panel(None, {**rec, "frame_id": None, "accepted": False}, None, 320, 160)
    assert rejected.shape == (240, 484, 3)


def test_recognition_dict_round_trip_with_the_real_memory():
    run = _small_run()
    mem = VisualMemory()
    for i in range(0, 12, 3):
        mem.learn(run.frame(i))
    rec = mem.recognise(run.frame(4))
    d = rec.to_dict()
    assert recognition_from_dict(d).to_dict() == d


# ----------------------------------------------------------- a SessionViewer over a real Mapper


def _small_run():
    world = sim.loop_world(seed=3, size=(6.0, 4.0), corridor_width=2.0, laps=2, speed_mps=0.5)
    return sim.simulate(world, rate_hz=5, frame_every=2, seed=3)


@pytest.fixture(scope="module")
def fed_session():
    """A LocalSession fed the first half of a two-lap simulated run, and the rest of its inputs."""
    run = _small_run()
    cfg = HippomapConfig.with_overrides({"mapper": {"keyframe_interval": 3}})
    session = LocalSession("s1", config=cfg, title="small loop")
    half = len(run) // 2
    session.feed(sim_inputs(run, 0, half))
    return session, run, half


def test_viewer_mirrors_the_mapper_and_sends_only_changes(fed_session):
    session, run, half = fed_session
    viewer = SessionViewer(session, ViewerSettings(chunk_size=32, tail_size=8), start=False)
    try:
        m = session.mapper
        up = viewer.last_update
        assert up is not None
        assert viewer.map.nodes.tracker.n == m.cmap.node_count > 10
        assert viewer.map.links.tracker.n + viewer.map.loop_links.tracker.n == m.cmap.link_count
        assert up.map.nodes.chunks == tuple(chunk_layout(m.cmap.node_count, 32, 8))
        # nothing changed: nothing is sent
        again = viewer.update_graph()
        assert again.items_sent == 0
        # the rest of the run: new nodes arrive in new chunks; loop closures are drawn
        session.feed(sim_inputs(run, half))
        up = viewer.update_graph()
        assert viewer.map.nodes.tracker.n == m.cmap.node_count
        accepted = [d for d in m.cmap.loop_decisions if d.status == "accepted"]
        rejected = [d for d in m.cmap.loop_decisions if d.status == "rejected"]
        assert accepted, "the simulated loop should close"
        assert viewer.loops.accepted.tracker.n == len(accepted)
        assert viewer.loops.rejected.tracker.n == len(rejected)
        assert not viewer.loops.rejected.visible and viewer.loops.accepted.visible
        # trajectories: one sample per spacing of raw path, raw and corrected alike
        n_samples = len(viewer.trajectories.sampler.samples)
        assert viewer.trajectories.odometry.tracker.n == n_samples - 1
        assert viewer.trajectories.corrected.tracker.n == n_samples - 1
        raw = m.odometry_trajectory()[:, :2]
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(raw, axis=0).T))])
        assert n_samples == len(np.unique(np.floor(cum / viewer.trajectories.sampler.spacing)))
        # the held corrected trajectory matches the Mapper's own corrected trajectory at the samples
        rows = viewer.trajectories.sampler.samples
        held = viewer.trajectories.corrected.tracker._geom[: n_samples - 1, :2]
        idx = rows[:-1, 0]
        times = m.trajectory_times
        truth = m.corrected_trajectory()[np.searchsorted(times, idx)][:, :2]
        assert np.max(np.abs(held - truth)) <= viewer.settings.move_tolerance_m + 1e-4
        # the robot marker is at the map pose, the place field was drawn
        assert np.allclose(viewer.robot._last[:2], m.cmap.robot_pose[:2], atol=1e-3)
        assert viewer.place_field.last is not None
    finally:
        viewer.close()


def test_viewer_panels_show_camera_recognition_and_loops(fed_session):
    session, run, half = fed_session
    viewer = SessionViewer(session, ViewerSettings(), start=False)
    try:
        assert viewer.update_camera() is True  # the latest frame
        assert viewer.update_camera() is False  # unchanged
        assert viewer.camera.trace_shown  # the last recognition, with its trace
        assert viewer.evidence.frames
        st = session.mapper.stats()
        assert f"| nodes | {st['nodes']} |" in viewer.stats.markdown.content
        accepted = [d for d in session.mapper.cmap.loop_decisions if d.status == "accepted"]
        d = accepted[-1]
        label = next(k for k, v in viewer.loop_list._labels.items() if v == d.id)
        viewer.loop_list.dropdown.value = label  # as a click in the list does
        deadline = time.monotonic() + 10
        while viewer.loops._selected_key is None and time.monotonic() < deadline:
            time.sleep(0.02)  # viser runs the callback in its thread pool
        assert viewer.loops._selected_key is not None and viewer.loops._selected_key[0] == d.id
        assert "accepted" in viewer.loop_list.details.content
        img = viewer.loop_list.image.image
        assert img.shape[1] == 2 * viewer.settings.thumbnail_width + 4
    finally:
        viewer.close()


def test_hub_reuses_and_closes_idle_viewers(fed_session):
    session, _, _ = fed_session
    hub = ViewerHub(ViewerSettings(idle_timeout_s=5.0), reap_every_s=3600)
    try:
        v1 = hub.open(session)
        assert hub.open(session) is v1
        hub.connected(v1)
        assert hub.reap(time.monotonic() + 100) == []  # connected: kept
        hub.disconnected(v1)
        assert hub.reap(time.monotonic() + 1) == []  # idle, but not for long
        assert hub.reap(time.monotonic() + 100) == ["s1"]
        assert v1.closed and hub.get("s1") is None
        v2 = hub.open(session)  # a new view creates a new viewer
        assert v2 is not v1 and not v2.closed
        session_closed = LocalSession("gone")
        v3 = hub.open(session_closed)
        session_closed.close()
        assert "gone" in hub.reap()
        assert v3.closed
    finally:
        hub.close_all()


# ------------------------------------------------------------------------ routes and proxy


class _Access:
    def __init__(self, sessions: dict[str, LocalSession]) -> None:
        self.sessions = sessions

    def list_sessions(self, token):
        if token not in ("writer", "viewer"):
            return None
        return [SessionEntry(s.session_id, s.title) for s in self.sessions.values()]

    def open_session(self, token, session_id):
        if token not in ("writer", "viewer"):
            return None
        return self.sessions.get(session_id)


@pytest.fixture
def client(fed_session):
    session, _, _ = fed_session
    app = FastAPI()
    router = make_router(_Access({"s1": session}), settings=ViewerSettings(idle_timeout_s=5.0))
    app.include_router(router)
    with TestClient(app) as c:
        yield c
    router.hub.close_all()


def test_landing_page_lists_visible_sessions_and_remembers_the_token(client):
    r = client.get("/viewer/")
    assert r.status_code == 401 and "token" in r.text.lower()
    assert client.get("/viewer/?token=nope").status_code == 401
    r = client.get("/viewer/?token=viewer")
    assert r.status_code == 200
    assert "href='/viewer/s1/'" in r.text and "small loop" in r.text
    assert r.cookies.get("hippomap_viewer") == "viewer"
    assert "httponly" in r.headers["set-cookie"].lower()
    # the cookie alone now authenticates (as the page's websocket will)
    assert client.get("/viewer/").status_code == 200
    client.cookies.clear()
    assert client.get("/viewer/", headers={"Authorization": "Bearer writer"}).status_code == 200


def test_viewer_page_is_viser_and_unknown_sessions_are_404(client):
    assert client.get("/viewer/nosuch/?token=viewer").status_code == 404
    assert client.get("/viewer/s1/").status_code == 404  # no token: same answer as a missing session
    r = client.get("/viewer/s1/?token=viewer")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "<script" in r.text and len(r.content) > 100_000  # viser's bundled client
    r = client.get("/viewer/s1?token=viewer", follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"] == "/viewer/s1/?token=viewer"


def _viser_payload(frame: bytes) -> bytes:
    """The msgpack part of a viser websocket frame: [uint64 size][uint64 zstd size][zstd msgpack][binary]."""
    import zstandard

    size = int.from_bytes(frame[:8], "little")
    packed = int.from_bytes(frame[8:16], "little")
    return zstandard.ZstdDecompressor().decompress(frame[16:16 + packed], max_output_size=size)


def test_websocket_proxy_forwards_the_viser_protocol(client):
    with pytest.raises(WebSocketDisconnect) as exc:
        with client.websocket_connect("/viewer/s1", subprotocols=[SUBPROTOCOL]) as ws:
            ws.receive_bytes()
    assert exc.value.code == 1008  # no token
    client.cookies.set("hippomap_viewer", "viewer")
    with client.websocket_connect("/viewer/s1", subprotocols=[SUBPROTOCOL]) as ws:
        assert ws.accepted_subprotocol == SUBPROTOCOL
        seen = b""
        while b"/map/nodes/0" not in seen or b"/trajectories/map/0" not in seen:
            seen += _viser_payload(ws.receive_bytes())
        assert b"/map/nodes/0" in seen and b"/trajectories/map/0" in seen
    # a client of another viser version is refused by viser itself (close 1002), through the proxy
    with pytest.raises(WebSocketDisconnect) as exc:
        with client.websocket_connect("/viewer/s1", subprotocols=["viser-v0.0.1"]) as ws:
            ws.receive_bytes()
    assert exc.value.code == 1002
