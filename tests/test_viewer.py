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
from hippomap.spatial_pathway import SpatialPathway
from tests.support.simfeed import sim_inputs
from web.images import trace_panel
from web.panels.evidence import evidence_curves
from web.routes import SUBPROTOCOL, SessionEntry, make_router
from web.scene.chunks import ChunkTracker, chunk_layout
from web.scene.place_field import field_heatmap
from web.scene.trajectories import TrajectorySampler
from web.session_viewer import SessionViewer, ViewerHub
from web.settings import ViewerSettings
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
@given(
    st.lists(
        st.tuples(st.integers(0, 9), st.lists(st.floats(-0.05, 0.05), min_size=1, max_size=6)), min_size=1, max_size=12
    ),
    st.integers(1, 6),
    st.integers(1, 6),
)
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
        parts.add(start, rows[start : start + p])
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
        s.add(start, rows[start : start + p])
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
    for k, (ev, out) in enumerate(
        [([(3, 0.2), (7, 0.1)], "start"), ([(3, 0.5), (7, 0.3)], "confirmed"), ([(3, 0.95), (9, 0.4)], "confirmed")]
    ):
        steps.append(
            {
                "attempt": 0,
                "fixation": [40.0 + 30 * k, 50.0],
                "target": [42.0 + 30 * k, 50.0],
                "predicted_frame": 3,
                "predicted_feature": k,
                "found_frame": 3,
                "found_feature": k,
                "similarity": 0.8,
                "outcome": out,
                "evidence": [list(e) for e in ev],
                "event": None,
            }
        )
    return {
        "id": 4,
        "t": 12.5,
        "node": 9,
        "frame_id": 3,
        "accepted": True,
        "evidence": 0.95,
        "confidence": 1.0,
        "n_resets": 0,
        "n_fixations": 3,
        "image_size": [160, 120],
        "reason": "",
        "steps": steps,
    }


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


# ----------------------------------------------------------- a SessionViewer over a real Mapper


def _small_run():
    world = sim.loop_world(seed=3, size=(6.0, 4.0), corridor_width=2.0, laps=2, speed_mps=0.5)
    return sim.simulate(world, rate_hz=5, frame_every=2, seed=3, odometry_noise=sim.OdometryNoise())


@pytest.fixture(scope="module")
def fed_session():
    """A LocalSession fed the first half of a two-lap simulated run, and the rest of its inputs."""
    run = _small_run()
    cfg = HippomapConfig.with_overrides({"mapper": {"keyframe_interval": 3}})
    session = LocalSession("s1", config=cfg, title="small loop")
    half = len(run) // 2
    session.feed(sim_inputs(run, 0, half))
    return session, run, half


def _faded_links(m) -> int:
    """Loop links of ``m``'s map whose robust weight has fallen below ``USED_WEIGHT``."""
    from hippomap.cognitive_map import LOOP
    from hippomap.robust_kernel import USED_WEIGHT

    kinds = m.cmap.links["kind_code"]
    return int(((kinds == LOOP) & (m.cmap.link_weights() < USED_WEIGHT)).sum())


def test_viewer_mirrors_the_mapper_and_sends_only_changes(fed_session):
    session, run, half = fed_session
    viewer = SessionViewer(session, ViewerSettings(chunk_size=32, tail_size=8), start=False)
    try:
        m = session.mapper
        up = viewer.last_update
        assert up is not None
        assert viewer.map.nodes.tracker.n == m.cmap.node_count > 10
        assert viewer.map.links.tracker.n + viewer.map.loop_links.tracker.n == m.cmap.link_count - _faded_links(m)
        assert up.map.nodes.chunks == tuple(chunk_layout(m.cmap.node_count, 32, 8))
        # nothing changed: nothing is sent
        again = viewer.update_graph()
        assert again.items_sent == 0
        # the rest of the run: new nodes arrive in new chunks; loop closures are drawn
        session.feed(sim_inputs(run, half))
        up = viewer.update_graph()
        assert viewer.map.nodes.tracker.n == m.cmap.node_count
        rows = m.cmap.loop_rows()
        used = [r for r in rows if r["used"]]
        faded = [r for r in rows if r["status"] == "accepted" and not r["used"]]
        rejected = [r for r in rows if r["status"] == "rejected"]
        assert used, "the simulated loop should close"
        assert viewer.loops.accepted.tracker.n == len(used)
        assert viewer.loops.faded.tracker.n == len(faded)
        assert viewer.loops.rejected.tracker.n == len(rejected)
        # the shared scene holds all; each browser hides the faded and rejected ones by default (web.panels.layers)
        assert viewer.loops.rejected.visible and viewer.loops.accepted.visible and viewer.loops.faded.visible
        defaults = {sp.key: sp.visible for sp in viewer.layer_specs}
        assert defaults["rejected"] is False and defaults["faded"] is False and defaults["accepted"] is True
        # loop closures are thin lines; their end dots are smaller than nodes
        assert viewer.loops.accepted.style == viewer.loops.rejected.style == "thin"
        assert viewer.loops.accepted_ends.point_size <= viewer.map.nodes.point_size
        assert viewer.loops.accepted_ends.tracker.n == 2 * len(used)
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


def test_a_faded_closure_is_drawn_apart_from_the_used_ones():
    """A closure the robust kernel has faded is still an accepted decision, but the viewer draws it in
    its own layer (hidden by default), not as a used closure nor as a loop link of the map, and its
    details say so with its weight."""
    from hippomap.mapper import Mapper
    from tests.test_loop_closure import square_with_a_false_closure

    # no retraction (loop_retract_below None): the false closure stays an accepted, faded link
    cfg = {"map": {"prune_online": False, "relax_loops": 200, "loop_retract_below": None}}
    m = Mapper(HippomapConfig.with_overrides(cfg))
    square_with_a_false_closure(m.cmap)
    rows = m.cmap.loop_rows()
    used = [r for r in rows if r["used"]]
    faded = [r for r in rows if r["status"] == "accepted" and not r["used"]]
    assert used and [r["hypothesis"]["source"] for r in faded] == ["false"]
    viewer = SessionViewer(LocalSession("faded", mapper=m), ViewerSettings(), start=False)
    try:
        assert viewer.loops.accepted.tracker.n == len(used) and viewer.loops.faded.tracker.n == 1
        assert viewer.map.loop_links.tracker.n == len(used) and _faded_links(m) == 1
        # the faded closure's segment is where its two nodes are on the map
        poses = m.cmap.poses
        d = faded[0]
        ends = [poses[d["from_node"], :2], poses[d["hypothesis"]["node"], :2]]
        np.testing.assert_allclose(viewer.loops.faded.tracker._geom[0].reshape(2, 3)[:, :2], ends, atol=1e-4)
        assert f"{len(used)} used of {len(used) + 1} accepted" in viewer.stats.markdown.content
        viewer._show_loop(d["id"])
        text = viewer.loop_list.details.content
        assert "accepted, faded" in text and f"robust weight {d['weight']:.3f}" in text
        assert viewer.loops._selected_key is not None and viewer.loops._selected_key[:3] == (d["id"], "accepted", False)
        # the details follow the weight as the kernel revises it (a refresh on each update of the chosen loop)
        viewer.loop_list.refresh(m.cmap.loop_decisions[d["id"]], 0.9)
        refreshed = viewer.loop_list.details.content
        assert "accepted, used" in refreshed and "robust weight 0.900" in refreshed
        viewer._show_loop(used[-1]["id"])
        assert "accepted, used" in viewer.loop_list.details.content
        # the time slider's replay draws the same: the used closures and loop links, not the faded one
        # (the map was driven without odometry inputs: one trajectory row at its last node stands for them)
        last = np.array([[0.0, 0.0, 0.0, 0.0, m.cmap.node_count - 1, 0.0, 0.0, 0.0]])
        end = replay_at(viewer._snapshot, last, None, 1e9)
        assert end.n_nodes == m.cmap.node_count
        assert len(end.accepted) == len(end.loop_links) == len(used)
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
    return zstandard.ZstdDecompressor().decompress(frame[16 : 16 + packed], max_output_size=size)


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


# ------------------------------------------------- readable views: camera, ground truth, replay, layers
from web.panels.layers import ClientLayers, layer_specs, legend_html  # noqa: E402
from web.scene.camera_fit import fit_camera, map_bounds  # noqa: E402
from web.scene.ground_truth import GroundTruthLayer, origin_alignment  # noqa: E402
from web.scene.replay import replay_at  # noqa: E402


def _project(points, pos, look, fov, aspect):
    """Pinhole projection (+z up) of world points to normalised screen coordinates in [-1, 1]."""
    f = (look - pos) / np.linalg.norm(look - pos)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = np.asarray(points, float) - pos
    zc = d @ f
    t = math.tan(fov / 2)
    return np.column_stack([(d @ r) / (zc * t * aspect), (d @ u) / (zc * t)])


@settings(max_examples=60, deadline=None)
@given(
    cx=st.floats(-50, 50),
    cy=st.floats(-50, 50),
    w=st.floats(0.5, 200),
    h=st.floats(0.5, 200),
    aspect=st.floats(0.6, 2.5),
    covered=st.floats(0.0, 0.4),
    left=st.floats(0.0, 0.3),
    fov=st.floats(0.5, 1.6),
)
def test_fitted_camera_shows_the_whole_map_in_the_free_canvas_and_fills_it(cx, cy, w, h, aspect, covered, left, fov):
    lo, hi = np.array([cx - w / 2, cy - h / 2]), np.array([cx + w / 2, cy + h / 2])
    pos, look = fit_camera(lo, hi, fov, aspect, margin=1.15, covered=covered, covered_left=left)
    corners = np.array([[x, y, 0.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])])
    uv = _project(corners, pos, look, fov, aspect)
    x_lo, x_hi = -1 + 2 * left, 1 - 2 * covered
    assert np.all(uv[:, 0] >= x_lo - 1e-9) and np.all(uv[:, 0] <= x_hi + 1e-9)
    assert np.all(np.abs(uv[:, 1]) <= 1 + 1e-9)
    # it fills the free area along at least one axis (within the margin and the tilt's perspective)
    fill_x = (uv[:, 0].max() - uv[:, 0].min()) / (x_hi - x_lo)
    fill_y = (uv[:, 1].max() - uv[:, 1].min()) / 2
    assert max(fill_x, fill_y) > 0.7


def test_map_bounds_and_bad_camera_parameters():
    assert map_bounds(np.empty((0, 3)), None) is None
    lo, hi = map_bounds(np.array([[0.0, 0.0, 0.0], [10.0, 0.5, 0.0]]), np.array([[2.0, -4.0]]))
    assert np.allclose(lo, [0.0, -4.0]) and np.allclose(hi, [10.0, 0.5])
    lo, hi = map_bounds(np.zeros((1, 3)))  # one node: a minimum box around it
    assert np.allclose(hi - lo, 2.0)
    with pytest.raises(ValueError):
        fit_camera(np.zeros(2), np.ones(2), fov=0.0, aspect=1.0)
    with pytest.raises(ValueError):
        fit_camera(np.zeros(2), np.ones(2), fov=1.0, aspect=1.0, covered=0.5, covered_left=0.5)


class _Handle:
    def __init__(self, scene, name, kind, **kw):
        self.scene, self.name, self.kind, self.kw = scene, name, kind, kw
        self.visible = kw.get("visible", True)

    def remove(self):
        self.scene.nodes.pop(self.name, None)


class _Scene:
    """Records scene nodes by name, like viser's scene API (re-adding a name replaces it)."""

    def __init__(self):
        self.nodes = {}

    def _add(self, kind, name, **kw):
        h = _Handle(self, name, kind, **kw)
        self.nodes[name] = h
        return h

    def add_frame(self, name, **kw):
        return self._add("frame", name, **kw)

    def add_mesh_simple(self, name, vertices, faces, **kw):
        return self._add("mesh", name, vertices=vertices, faces=faces, **kw)

    def add_point_cloud(self, name, points, colors, **kw):
        return self._add("points", name, points=points, colors=colors, **kw)

    def add_line_segments(self, name, points, colors, **kw):
        return self._add("segments", name, points=points, colors=colors, **kw)


class _Box:
    def __init__(self, value):
        self.value = value
        self.callbacks = []

    def on_update(self, fn):
        self.callbacks.append(fn)


class _Gui:
    def add_checkbox(self, label, initial_value):
        return _Box(initial_value)


class _Client:
    def __init__(self):
        self.scene, self.gui = _Scene(), _Gui()


def test_ground_truth_is_carried_into_the_map_frame_at_the_first_pose():
    t = np.arange(200) * 0.25
    gt_world = np.column_stack([5.0 + np.cos(t / 5) * 3, -2.0 + np.sin(t / 5) * 3, t / 5 + np.pi / 2])
    raw0 = np.array([0.0, 0.0, 0.0])
    rows = np.column_stack([t, gt_world])
    first_row = np.r_[t[0], raw0, 0, 0, 0, 0]
    A = origin_alignment(rows, first_row)
    from hippomap.geometry import compose

    assert np.allclose(compose(A, gt_world[0]), raw0, atol=1e-12)
    # rigid: distances along the path are kept
    mapped = compose(A, gt_world)
    assert np.allclose(np.hypot(*np.diff(mapped[:, :2], axis=0).T), np.hypot(*np.diff(gt_world[:, :2], axis=0).T))
    assert origin_alignment(rows, np.r_[t[-1] + 5.0, raw0, 0, 0, 0, 0]) is None  # no overlap in time
    # the layer: waits for the map's first row, then draws incrementally, append-only
    layer = GroundTruthLayer(_Scene(), ViewerSettings(trajectory_spacing_m=0.1))
    assert layer.update(rows[:50], None) is None and not layer.present
    assert layer.seen == 50
    layer.update(rows[50:120], first_row)
    n1 = len(layer.samples)
    layer.update(rows[120:], first_row)
    assert layer.present and len(layer.samples) > n1 and layer.seen == 200
    assert np.allclose(layer.samples[0, 1:4], raw0, atol=1e-9)
    d = np.hypot(*np.diff(layer.samples[:, 1:3], axis=0).T)
    assert d.min() > 0.05  # sampled by path length, not every pose


def test_replay_cuts_the_map_back_in_time(fed_session):
    session, run, half = fed_session
    viewer = SessionViewer(session, ViewerSettings(), start=False)
    try:
        snap = viewer._snapshot
        samples = viewer.trajectories.sampler.samples
        t0, t1 = samples[0, 0], samples[-1, 0]
        frames = [replay_at(snap, samples, None, t0 + f * (t1 - t0)) for f in (0.0, 0.3, 0.6, 1.0)]
        counts = [fr.n_nodes for fr in frames]
        assert counts == sorted(counts) and counts[-1] == len(snap.node_poses) and counts[0] < counts[-1]
        n_links = [len(fr.links) + len(fr.loop_links) for fr in frames]
        assert n_links == sorted(n_links) and n_links[-1] == len(snap.link_source) - _faded_links(session.mapper)
        mid = frames[1]
        # every drawn link joins two drawn nodes
        drawn = {tuple(np.round(p[:2], 4)) for p in mid.nodes}
        for seg in np.concatenate([mid.links, mid.loop_links]):
            assert tuple(np.round(seg[0, :2], 4)) in drawn and tuple(np.round(seg[1, :2], 4)) in drawn
        assert len(mid.corrected) < len(frames[-1].corrected)
        thin = replay_at(snap, samples, None, t1, max_nodes=10)
        assert len(thin.nodes) <= 10 and thin.n_nodes == len(snap.node_poses)
    finally:
        viewer.close()


def test_legend_names_every_layer_and_ground_truth_only_when_present():
    specs = layer_specs(ViewerSettings())
    with_gt, without = legend_html(specs, True), legend_html(specs, False)
    for sp in specs:
        if sp.key not in ("ground_truth", "place_field"):
            assert sp.label in with_gt and sp.label in without
    assert "ground truth" in with_gt and "ground truth" not in without
    assert "linear-gradient" in with_gt  # the place field's colour scale
    hidden = legend_html(specs, True, {"odometry": False})
    assert 'line-through" data-layer="odometry"' in hidden and 'line-through" data-layer="nodes"' not in hidden


def test_layer_toggles_shadow_groups_for_one_browser_only():
    specs = layer_specs(ViewerSettings())
    a, b = _Client(), _Client()
    la, lb = ClientLayers(a, specs), ClientLayers(b, specs)
    # faded and rejected loop closures start hidden in every browser, nothing else
    hidden = {"/loops/rejected", "/loops/faded"}
    assert set(a.scene.nodes) == hidden and not any(a.scene.nodes[g].visible for g in hidden)
    la.set("ground_truth", False)
    la.set("links", False)
    assert {"/ground_truth", "/map/links", "/map/loop_links"} <= set(a.scene.nodes)
    assert set(b.scene.nodes) == hidden  # the other browser is untouched
    la.set("rejected", True)
    la.set("faded", True)
    assert not hidden & set(a.scene.nodes)
    # the replay hides every live layer, and afterwards each is back as toggled
    la.set_replaying(True)
    groups = {g for sp in specs for g in sp.groups}
    assert groups == set(a.scene.nodes)
    la.set_replaying(False)
    assert set(a.scene.nodes) == {"/ground_truth", "/map/links", "/map/loop_links"}
    la.set("ground_truth", True)
    assert la.shown("ground_truth") and "/ground_truth" not in a.scene.nodes
    assert lb.shown("ground_truth") and not lb.shown("rejected")


def test_ground_truth_travels_with_odometry_and_never_reaches_the_mapper():
    from hippomap.client import odometry_reading
    from hippomap.errors import InputError
    from hippomap.inputs import Odometry
    from server.formats.ingest import odometry_bytes, odometry_from_bytes

    o = Odometry(1.5, v=0.2, omega=0.1, gt=(1.0, -2.0, 0.5))
    assert odometry_from_bytes(odometry_bytes(o)) == o
    assert odometry_reading(o)["gt"] == [1.0, -2.0, 0.5]
    plain = Odometry(1.5, v=0.2, omega=0.1)
    assert b"gt" not in odometry_bytes(plain) and "gt" not in odometry_reading(plain)
    for bad in ((1.0, 2.0), (1.0, float("nan"), 0.0)):
        with pytest.raises(InputError):
            Odometry(1.0, v=0.0, omega=0.0, gt=bad)
    # the mapper's result does not depend on the ground truth
    run = _small_run()
    a, b = LocalSession("a"), LocalSession("b")
    for item in sim_inputs(run, 0, 60):
        if hasattr(item, "gt"):
            a.step(item)
            b.step(Odometry(item.t, v=item.v, omega=item.omega))
    assert np.array_equal(a.mapper.cmap.poses, b.mapper.cmap.poses)
    assert len(a.ground_truth()) == 60 and b.ground_truth() is None
    assert np.allclose(a.ground_truth()[:, 1:], run.groundtruth[:60])


def test_replay_interpolates_a_data_sets_ground_truth_for_each_reading():
    from hippomap.client.replay import ground_truth_at

    assert ground_truth_at(None) is None
    t = np.array([0.0, 1.0, 2.0])
    poses = np.array([[0.0, 0.0, 3.0], [1.0, 2.0, -3.0], [3.0, 2.0, -2.0]])  # heading crosses +-pi
    at = ground_truth_at((t, poses))
    assert at(-0.1) is None and at(2.1) is None
    assert np.allclose(at(1.0), poses[1]) and np.allclose(at(0.5)[:2], [0.5, 1.0])
    # half way from 3.0 to -3.0 (= 3.28 unwrapped) is pi +- a little, not 0
    assert abs(abs(at(0.5)[2]) - math.pi) < 0.2


def test_fitting_the_points_of_a_round_map_fills_more_than_its_box():
    th = np.linspace(0, 2 * np.pi, 400)
    pts = np.column_stack([10 * np.cos(th), 10 * np.sin(th)])
    lo, hi = pts.min(0), pts.max(0)
    fov, aspect = math.radians(75), 1.0  # with a panel over 30 % of the width: the width limits the fit
    box_pos, box_look = fit_camera(lo, hi, fov, aspect, covered=0.3)
    pts_pos, pts_look = fit_camera(lo, hi, fov, aspect, covered=0.3, points=pts)
    floor = np.column_stack([pts, np.zeros(len(pts))])
    uv = _project(floor, pts_pos, pts_look, fov, aspect)
    assert np.abs(uv[:, 1]).max() <= 1 + 1e-9 and uv[:, 0].min() >= -1 - 1e-9 and uv[:, 0].max() <= 0.4 + 1e-9
    assert np.linalg.norm(pts_pos - pts_look) < np.linalg.norm(box_pos - box_look)  # closer: the circle fills more


# ------------------------------------------------------ a run in a saved map: replay and raw odometry
from hippomap.inputs import Odometry  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402
from web.scene.placement import placement  # noqa: E402

REUSE_NOISE = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)
ANCHOR_M = 1.0  # the raw odometry's first point to the map trajectory's (0 measured; 7.1 m in the run's own frame)
NEAR_PATH_M = 1.0  # the raw odometry's first 3 m to the map trajectory (0.04 m measured: drift only)


@pytest.fixture
def localising_session():
    """A localisation session in a saved map (the scenario of tests/test_viewer_localise.py), fed
    nothing yet, and its run: the base is 80 s of the 8 m x 5 m corridor loop, the run starts
    elsewhere in the same world (a pose the mapper is not told)."""
    world = sim.loop_world(seed=3, size=(8.0, 5.0))
    run1 = sim.simulate(world, None, rate_hz=5.0, seed=1, odometry_noise=REUSE_NOISE)
    base = Mapper()
    for x in sim_inputs(run1, 0, 400):
        base.step(x) if isinstance(x, Odometry) else base.observe(x)
    plan = sim.RoutePlan(((0.0, 5.0), (0.0, 0.0), (8.0, 0.0), (8.0, 5.0)), closed=True, laps=1, seed=2)
    run2 = sim.simulate(world, plan, rate_hz=5.0, seed=2, odometry_noise=REUSE_NOISE)
    session = LocalSession(
        "loc", mapper=Mapper.from_base(base.to_bytes(), {"mapper": {"mode": "localise"}}), title="localising run"
    )
    return session, run2


def test_a_run_in_a_saved_map_is_drawn_from_its_placement_live_and_in_replay(localising_session):
    session, run = localising_session
    session.feed(sim_inputs(run, 0, 10))  # 2 s: not placed yet
    assert session.mapper.lost
    viewer = SessionViewer(session, ViewerSettings(), start=False)
    try:
        n_base = int(session.mapper.stats()["base_nodes"])
        # while lost: neither the map trajectory nor the raw odometry (the run's own frame is not the map's)
        assert len(viewer.trajectories.sampler.samples) > 1
        assert viewer.trajectories.corrected.tracker.n == 0 and viewer.trajectories.odometry.tracker.n == 0
        # placed, then 8 s more: what the live layers draw then is what the replay must draw later
        fed = 10
        while session.mapper.lost and fed < len(run):
            session.feed(sim_inputs(run, fed, fed + 1))
            fed += 1
        assert not session.mapper.lost, "the run should be placed by recognition"
        session.feed(sim_inputs(run, fed, fed + 40))
        viewer.update_graph()
        snap = viewer._snapshot
        placed = placement(snap.stats, snap.decisions)
        assert placed.based and placed.localise and math.isfinite(placed.on_map_from_t)
        t_mid = float(viewer.trajectories.sampler.samples[-1, 0])
        live_map = viewer.trajectories.corrected.tracker._geom[: viewer.trajectories.corrected.tracker.n].copy()
        live_odo = viewer.trajectories.odometry.tracker._geom[: viewer.trajectories.odometry.tracker.n].copy()
        assert len(live_map) > 10 and len(live_odo) == len(live_map)
        # the raw odometry starts where the map trajectory starts (the placement) and stays near it
        first_odo, first_map = live_odo[0, :2], live_map[0, :2]
        assert np.hypot(*(first_odo - first_map)) < ANCHOR_M
        samples = viewer.trajectories.sampler.samples
        on = samples[samples[:, 0] >= placed.on_map_from_t]
        raw_gap = np.hypot(*(on[0, 1:3] - first_map))  # where the run's own odometry frame has it
        assert raw_gap > 2 * ANCHOR_M, raw_gap  # the check above is a real one
        path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(live_odo[:, :2], axis=0).T))])
        early = live_odo[path < 3.0, :2]
        near = np.sqrt(((early[:, None, :] - live_map[None, :, :2]) ** 2).sum(-1)).min(axis=1)
        assert near.max() < NEAR_PATH_M, near.max()
        # the rest of the run; then replay
        session.feed(sim_inputs(run, fed + 40, 150))
        viewer.update_graph()
        snap, samples, gt = viewer._view_state()
        tol = viewer.settings.move_tolerance_m + 1e-4
        before = replay_at(snap, samples, gt, placed.on_map_from_t - 1.0)
        assert len(before.corrected) == 0 and len(before.odometry) == 0 and before.robot is None
        assert before.n_nodes == n_base  # the saved map was there from the start
        assert len(before.accepted) == 0  # the placing decisions are not drawn from the base's last node
        mid = replay_at(snap, samples, gt, t_mid)
        assert mid.corrected.shape == live_map.reshape(-1, 2, 3).shape
        assert np.max(np.abs(mid.corrected.reshape(-1, 6) - live_map)) <= tol
        assert np.max(np.abs(mid.odometry.reshape(-1, 6) - live_odo)) <= tol
        assert np.allclose(mid.robot[:2], mid.corrected[-1, 1, :2], atol=1e-4)
        # at the end the replay is the live view
        end = replay_at(snap, samples, gt, float(samples[-1, 0]))
        held = viewer.trajectories.corrected.tracker
        assert np.max(np.abs(end.corrected.reshape(-1, 6) - held._geom[: held.n])) <= tol
    finally:
        viewer.close()
