"""End to end in a real browser: the service streams a simulated run; headless Chromium opens the viewer.

The service runs as ``python -m server`` (uvicorn on a free loopback port); a simulated robot
streams a two-lap corridor loop over the service's websocket; a read-only viewer token opens the
landing page, follows the session's link, and the test waits for the map in viser's scene tree
(``window.__viserSceneTree``), checks that the 3D canvas is not blank and that the saccade-trace
image is drawn, and keeps the screenshots in ``test-artifacts/`` (git-ignored).

Chromium is Debian's (/usr/bin/chromium) driven by Playwright with software WebGL.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest
from playwright.sync_api import sync_playwright

from hippomap import sim
from hippomap.client import encode_image
from hippomap.inputs import Odometry
from tests.support.chromium import launch
from tests.support.live import ROOT, LiveServer
from tests.support.simfeed import sim_inputs

ARTIFACTS = ROOT / "test-artifacts"


def _colourful_pixels(img: np.ndarray) -> int:
    """Pixels with clearly unequal RGB channels (the trace is coloured, the camera frames are gray)."""
    c = img.astype(int)
    return int(((c.max(axis=2) - c.min(axis=2)) > 60).sum())


@pytest.fixture(scope="module")
def streamed(tmp_path_factory):
    """A live service with one session holding a two-lap simulated run, and a viewer token for it."""
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    server = LiveServer(tmp_path_factory.mktemp("service"), env=env).start()
    try:
        world = sim.loop_world(seed=3, size=(6.0, 4.0), corridor_width=2.0, laps=2, speed_mps=0.5)
        run = sim.simulate(world, rate_hz=5, frame_every=2, seed=3, odometry_noise=sim.OdometryNoise())
        with server.client() as c:
            s = c.create_session(name="e2e loop", config={"mapper": {"keyframe_interval": 3}})
            sid = s["id"]
            viewer_token = c.create_token("viewer", session=sid, label="e2e")["token"]
            with c.stream(sid) as stream:
                acks = []
                for item in sim_inputs(run):
                    if isinstance(item, Odometry):
                        acks.append(stream.send_odometry(item))
                    else:
                        acks.append(stream.send_frame(item.t, encode_image(item.image)))
                stream.drain()
            assert all(a.result(60) for a in acks)
            stats = c.wait_processed(sid, timeout=180)
        yield server, sid, viewer_token, stats
    finally:
        server.stop()


def test_viewer_shows_the_live_map_and_saccades_in_chromium(streamed):
    server, sid, token, stats = streamed
    assert stats["mapper"]["nodes"] > 10 and stats["mapper"]["recognitions"] > 0
    ARTIFACTS.mkdir(exist_ok=True)
    with sync_playwright() as p:
        browser = launch(p)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            # the landing page lists the session for this read-only token and links to its viewer
            page.goto(f"{server.url}/viewer/?token={token}")
            link = page.locator(f"a[href='/viewer/{sid}/']")
            assert link.inner_text() == "e2e loop"
            link.click()  # the token now travels in the HttpOnly cookie, as it must for the websocket
            page.wait_for_url(f"{server.url}/viewer/{sid}/")
            page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=60_000)
            for node in (
                "/map/nodes/0",
                "/map/links/0",
                "/trajectories/odometry/0",
                "/trajectories/map/0",
                "/loops/accepted/0",
                "/place_field",
                "/robot",
                "/ground_truth/0",
            ):
                page.wait_for_function("n => !!window.__viserSceneTree?.getState()[n]", arg=node, timeout=60_000)
            # the panel: stats of this session, the saccade trace of the last recognition
            page.wait_for_function("n => document.body.innerText.includes(n)", arg="loop closures", timeout=30_000)
            text = page.inner_text("body")
            assert "nodes" in text and "key frames" in text
            # the on-canvas legend, with the ground truth the simulated robot streamed with its odometry
            page.wait_for_function("() => document.body.innerText.includes('ground truth')", timeout=30_000)
            assert page.locator(".hippomap-legend").first.is_visible()
            page.wait_for_function(
                "() => Array.from(document.images).filter(i => i.complete && i.naturalWidth === 484).length >= 1",
                timeout=30_000,
            )
            page.wait_for_timeout(1500)  # let the renderer draw the received scene
            shot = page.screenshot(path=str(ARTIFACTS / "viewer-e2e.png"))
            canvas = page.locator("canvas").first
            canvas_png = canvas.screenshot(path=str(ARTIFACTS / "viewer-e2e-canvas.png"))
            # the recognition image: query frame with its trace | key frame thumbnail (320 + 4 + 160 px)
            trace = page.evaluate_handle("() => Array.from(document.images).find(i => i.naturalWidth === 484)")
            trace_png = trace.as_element().screenshot(path=str(ARTIFACTS / "viewer-e2e-saccades.png"))
        finally:
            browser.close()
    assert len(shot) > 10_000
    scene = cv2.imdecode(np.frombuffer(canvas_png, np.uint8), cv2.IMREAD_COLOR)
    gray = cv2.cvtColor(scene, cv2.COLOR_BGR2GRAY)
    assert gray.std() > 5.0, "the 3D canvas is blank"
    assert _colourful_pixels(scene) > 200, "no coloured map layers on the canvas"
    sacc = cv2.imdecode(np.frombuffer(trace_png, np.uint8), cv2.IMREAD_COLOR)
    assert sacc.shape[1] > 200 and sacc.std() > 10.0
    assert _colourful_pixels(sacc) > 30, "the saccade trace (coloured fixations) is not drawn"


def test_place_field_png_draws_the_iteration_like_fig_8(streamed):
    """GET /sessions/{id}/place-field/png: the grid cells' binarised matrices and the product shrinking
    to one field, with axes and a colour scale — not a black matrix with one white pixel."""
    import httpx

    server, sid, _, _ = streamed
    r = httpx.get(
        f"{server.url}/sessions/{sid}/place-field/png", headers={"Authorization": f"Bearer {server.token}"}, timeout=60
    )
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    ARTIFACTS.mkdir(exist_ok=True)
    (ARTIFACTS / "place-field.png").write_bytes(r.content)
    h, w = img.shape[:2]
    assert w > 1000 and h > 400  # a multi-panel figure, not the 801 x 801 position matrix
    white = (img.min(axis=2) > 245).mean()
    assert 0.3 < white < 0.95  # a white figure background with panels on it
    b, g, r_ = (img[:, :, i].astype(int) for i in range(3))
    assert ((r_ > 230) & (g > 190) & (b < 90)).sum() > 1000  # binarised grid-cell windows (MB = 1)
    assert ((r_ < 90) & (g > 200) & (b > 230)).sum() > 100  # the position matrix (POS = 1)
    meta = httpx.get(
        f"{server.url}/sessions/{sid}/place-field", headers={"Authorization": f"Bearer {server.token}"}, timeout=60
    ).json()
    step = meta["step"]
    past = httpx.get(
        f"{server.url}/sessions/{sid}/place-fields/{step}/png",
        headers={"Authorization": f"Bearer {server.token}"},
        timeout=60,
    )
    assert past.status_code == 200 and past.content[:4] == b"\x89PNG"


def test_viewer_refuses_other_tokens_and_unknown_sessions(streamed):
    import httpx

    server, sid, token, _ = streamed
    assert httpx.get(f"{server.url}/viewer/").status_code == 401
    assert httpx.get(f"{server.url}/viewer/?token=hm_not_a_token").status_code == 401
    assert httpx.get(f"{server.url}/viewer/{sid}/").status_code == 404
    assert httpx.get(f"{server.url}/viewer/s_nosuch/?token={token}").status_code == 404
    r = httpx.get(f"{server.url}/viewer/{sid}/?token={token}")
    assert r.status_code == 200 and "<script" in r.text
    # the session's API lists the viewer link
    r = httpx.get(f"{server.url}/sessions/{sid}", headers={"Authorization": f"Bearer {token}"})
    assert r.json()["links"]["viewer"].endswith(f"/viewer/{sid}/")
