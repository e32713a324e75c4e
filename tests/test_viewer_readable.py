"""A ten-lap session in a real browser: the viewer stays readable.

A simulated robot drives ten laps of a corridor loop with noisy odometry and ground truth into a
:class:`web.source.LocalSession`; the viewer's routes (the same FastAPI proxy the service mounts)
run under uvicorn on a free loopback port, and Debian's Chromium (Playwright, software WebGL)
opens the viewer. Checked through viser's scene tree and the page text, not pixels where
possible: the on-canvas legend names every layer, the ground truth is in the scene, loop closures
are thin lines whose end dots are no larger than a node, the raw odometry is drawn and can be
hidden, the camera is fitted to the map, the layer toggles and the time slider act on one browser
only, and the place-cell figure is drawn.
Screenshots go to pytest's tmp dir.
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
import uvicorn
from fastapi import FastAPI
from playwright.sync_api import sync_playwright

from hippomap import sim
from hippomap.config import HippomapConfig
from tests.browser_viewer import LEGEND_LABELS, blue, canvas, legend_text, message_types, open_viewer, tan, teal
from tests.support.chromium import launch
from tests.support.simfeed import sim_inputs
from web.routes import SessionEntry, make_router
from web.settings import ViewerSettings
from web.source import LocalSession

TOKEN = "viewer-token"


class _Access:
    def __init__(self, session: LocalSession) -> None:
        self.session = session

    def list_sessions(self, token):
        return [SessionEntry(self.session.session_id, self.session.title)] if token == TOKEN else None

    def open_session(self, token, session_id):
        return self.session if token == TOKEN and session_id == self.session.session_id else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ten_laps():
    """A LocalSession holding ten laps with ground truth, served by the viewer's routes."""
    world = sim.loop_world(seed=3, size=(5.0, 3.5), corridor_width=2.0, laps=10, speed_mps=0.6)
    run = sim.simulate(
        world, rate_hz=4, frame_every=4, seed=3, odometry_noise=sim.OdometryNoise(sigma_omega=0.02, omega_bias=0.005)
    )
    session = LocalSession(
        "s_ten", config=HippomapConfig.with_overrides({"mapper": {"keyframe_interval": 3}}), title="ten laps"
    )
    session.feed(sim_inputs(run))  # each odometry reading carries its ground-truth pose (gt)
    app = FastAPI()
    router = make_router(_Access(session), settings=ViewerSettings(idle_timeout_s=120.0))
    app.include_router(router)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.started
    try:
        yield f"http://127.0.0.1:{port}", session, router.hub, run
    finally:
        router.hub.close_all()
        server.should_exit = True
        thread.join(timeout=10)


def _open(browser, url: str, sid: str):
    return open_viewer(browser, url, sid, TOKEN)


def test_ten_laps_stay_readable_in_chromium(ten_laps, tmp_path):
    url, session, hub, run = ten_laps
    stats = session.mapper.stats()
    assert stats["loop_closures_accepted"] >= 5, "ten laps must close loops"
    with sync_playwright() as p:
        browser = launch(p)
        try:
            page = _open(browser, url, session.session_id)
            viewer = hub.get(session.session_id)
            assert viewer is not None
            # the legend is on the canvas (a floating panel, not inside a collapsed folder): every layer named
            text = legend_text(page)
            for label in LEGEND_LABELS:
                assert label in text
            # loop closures are thin lines; their end dots are no larger than a node
            state = message_types(page, "/loops/", "/map/nodes/")
            assert state["/loops/accepted/0"] == "MeshMessage"  # a wireframe mesh: 1-pixel GL lines, no discs
            assert viewer.loops.accepted.style == "thin"
            assert viewer.loops.accepted_ends.point_size <= viewer.map.nodes.point_size
            assert viewer.loops.accepted.tracker.n == stats["loop_closures_used"]
            assert viewer.loops.faded.tracker.n == stats["loop_closures_accepted"] - stats["loop_closures_used"]
            # ground truth: in the scene, in the map frame, starting where the map starts
            gt = viewer.ground_truth.samples
            assert len(gt) > 100
            first = viewer.trajectories.sampler.samples[0]
            assert np.allclose(gt[0, 1:3], first[1:3], atol=0.2)
            # the camera is fitted: the map's bounding box fills most of the free canvas
            page.wait_for_timeout(2000)
            img = canvas(page, tmp_path / "viewer-ten-laps.png")
            page.screenshot(path=str(tmp_path / "viewer-ten-laps-page.png"))
            h, w = img.shape[:2]
            gt_px, map_px, odo_px = teal(img), blue(img), tan(img)
            assert gt_px > 300 and map_px > 300, (gt_px, map_px)
            assert odo_px > 1000, odo_px  # the raw odometry, shown by default (14,408 px measured)
            ink = np.abs(img.astype(int) - img[5, w // 2].astype(int)).max(axis=2) > 40
            ink[:, int(0.66 * w) :] = False  # the control panel floats over the right third
            ink[: int(0.5 * h), : int(0.2 * w)] = False  # the legend floats top left
            ys, xs = np.nonzero(ink)
            assert (xs.max() - xs.min()) > 0.45 * w or (ys.max() - ys.min()) > 0.6 * h
            # the place cells: the Fig. 8 figure is drawn in the panel
            deadline = time.monotonic() + 60
            while not viewer.place_cells.drawn and time.monotonic() < deadline:
                time.sleep(0.2)
            assert viewer.place_cells.drawn
            page.wait_for_function("() => document.body.innerText.includes('products; the field')", timeout=30_000)
            # per browser: a second browser hides layers and replays; the first one is untouched
            other = _open(browser, url, session.session_id)
            views = viewer.views.all()
            assert len(views) == 2
            mine, theirs = sorted(views, key=lambda v: v.client.client_id)
            before = canvas(page, tmp_path / "viewer-ten-laps-before.png")
            theirs.layers.set("ground_truth", False)
            theirs.layers.set("odometry", False)
            theirs.slider.value = 40
            theirs.refresh_replay()
            other.wait_for_function("() => document.body.innerText.includes('replay: t =')", timeout=30_000)
            other.wait_for_function(
                "n => !!window.__viserSceneTree?.getState()[n]", arg="/replay/nodes", timeout=30_000
            )
            other.wait_for_timeout(1500)
            replay = canvas(other, tmp_path / "viewer-ten-laps-replay.png")
            assert teal(replay) < 0.1 * gt_px  # hidden in that browser
            assert theirs.replay.frame is not None
            assert 0 < theirs.replay.frame.n_nodes < stats["nodes"]
            page.wait_for_timeout(1000)
            after = canvas(page, tmp_path / "viewer-ten-laps-after.png")
            assert teal(after) > 0.8 * teal(before) and tan(after) > 0.8 * tan(before)
            assert "replay" not in page.inner_text("body").split("View (this browser)")[-1][:200]
            # back to live in the other browser: the replay is gone, its layers come back as toggled
            theirs.slider.value = 100
            theirs.refresh_replay()
            assert theirs.replay.frame is None
            other.wait_for_function("() => document.body.innerText.includes('live map')", timeout=30_000)
            other.wait_for_function("n => !window.__viserSceneTree?.getState()[n]", arg="/replay/nodes", timeout=30_000)
            other.wait_for_timeout(1500)
            live = canvas(other, tmp_path / "viewer-ten-laps-other-live.png")
            assert blue(live) > 0.5 * map_px and teal(live) < 0.1 * gt_px
            assert tan(live) < 0.05 * odo_px  # the raw odometry is optional: off in that browser (7 px measured)
            other.screenshot(path=str(tmp_path / "viewer-ten-laps-other-page.png"))
        finally:
            browser.close()
