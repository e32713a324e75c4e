"""A localisation session in a real browser: the base map, the run placed on it, its ground truth.

The service runs as ``python -m server``. A base session maps 80 s of the 8 m x 5 m simulated
corridor loop (the scenario of ``tests/test_map_reuse.py``), streamed over the websocket with
ground truth on every odometry reading; a session created from it with ``base_session`` and
``{"mapper": {"mode": "localise"}}`` streams a second run of the same world from another start
(the pose the mapper is not told) until its recognitions place it. Debian's Chromium opens that
session's viewer and the test reads viser's scene tree (the messages the browser holds) and the
canvas: the legend names every layer; the nodes drawn are exactly the base map's; the ground truth
lies along them (in the base's frame, not in the run's own odometric frame); the map trajectory
starts at the placement, not at the guess before it, and so does the raw odometry, re-anchored
on the map there; the loop closures are thin lines. The
screenshots go to pytest's tmp dir.
"""

from __future__ import annotations

import asyncio
import os

import numpy as np
import pytest
from playwright.sync_api import sync_playwright

from hippomap import sim
from hippomap.client import encode_image
from hippomap.inputs import Odometry
from tests.browser_viewer import LEGEND_LABELS, blue, canvas, legend_text, message_types, open_viewer, teal
from tests.support.chromium import launch
from tests.support.live import ROOT, LiveServer, stream_items
from tests.support.simfeed import sim_inputs

NOISE = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)
BASE_STEPS, RUN_STEPS = 400, 150  # 80 s of the base run; 30 s of the localising one (placed after ~7 s)
NEAR_M = 0.75  # the ground truth's mean distance to the nearest base node (0.18 m measured; 1.55 m in the run's frame)
ODOMETRY_START_M = 0.1  # raw odometry start to the map trajectory's (0 measured; 7.1 m unanchored: test_viewer.py)
# longest loop segment drawn: 1.77 m measured (on a familiar path key frames come 1 m apart, and one that
# is not recognised adds 0.5 m before the next); a decision made while lost would join the base's last node,
# about 8 m from where this run is placed
LOOP_M = 2.5


def _items(run: sim.SimRun, steps: int) -> tuple:
    """``stream_items`` items of the first ``steps`` steps: odometry with its ground truth, JPEG frames."""
    return tuple(
        ("odometry", x) if isinstance(x, Odometry) else ("frame", x.t, encode_image(x.image))
        for x in sim_inputs(run, 0, steps)
    )


@pytest.fixture(scope="module")
def localising(tmp_path_factory):
    """A live service with a base session and a localisation session placed on its map."""
    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    server = LiveServer(tmp_path_factory.mktemp("service"), env=env).start()
    try:
        world = sim.loop_world(seed=3, size=(8.0, 5.0))
        run1 = sim.simulate(world, None, rate_hz=5.0, seed=1, odometry_noise=NOISE)
        plan = sim.RoutePlan(((0.0, 5.0), (0.0, 0.0), (8.0, 0.0), (8.0, 5.0)), closed=True, laps=1, seed=2)
        run2 = sim.simulate(world, plan, rate_hz=5.0, seed=2, odometry_noise=NOISE)
        client = server.client()
        base = client.create_session("base run")["id"]
        asyncio.run(stream_items(server.url, server.token, base, _items(run1, BASE_STEPS)))
        client.wait_processed(base, timeout=180)
        base_map = client.map(base)
        sid = client._json(
            "POST",
            "/sessions",
            {"name": "localising run", "base_session": base, "config": {"mapper": {"mode": "localise"}}},
        )["id"]
        asyncio.run(stream_items(server.url, server.token, sid, _items(run2, RUN_STEPS)))
        stats = client.wait_processed(sid, timeout=180)["mapper"]
        token = client.create_token("viewer", session=sid, label="localise")["token"]
        yield server, sid, token, stats, base_map, client.loop_closures(sid, status="accepted")
    finally:
        server.stop()


def _scene_points(page, prefix: str, but: str = "") -> np.ndarray:
    """The (N, 3) points of the scene nodes under ``prefix`` and not under ``but`` (point clouds, or
    thin line meshes' vertices: two per segment)."""
    flat = page.evaluate(
        "([p, b]) => { const s = window.__viserSceneTree.getState(); const out = [];"
        " for (const [k, v] of Object.entries(s)) { if (!k.startsWith(p + '/') || (b && k.startsWith(b))) continue;"
        "   const props = v?.message?.props ?? {};"
        "   const a = props.points ?? props.vertices; if (!a) continue;"
        "   const f = new Float32Array(a.buffer.slice(a.byteOffset, a.byteOffset + a.byteLength));"
        "   for (const x of f) out.push(x); }"
        " return out; }",
        [prefix, but],
    )
    return np.asarray(flat, float).reshape(-1, 3)


def test_localisation_session_draws_the_base_map_and_its_ground_truth(localising, tmp_path):
    server, sid, token, stats, base_map, accepted = localising
    assert stats["mode"] == "localise" and stats["lost"] is False, stats  # placed by recognition
    n_base = len(base_map["nodes"])
    assert stats["nodes"] == stats["base_nodes"] == n_base  # localising adds nothing to the map
    with sync_playwright() as p:
        browser = launch(p)
        try:
            page = open_viewer(browser, server.url, sid, token)
            text = legend_text(page)
            for label in LEGEND_LABELS:
                assert label in text
            types = message_types(page, "/loops/accepted/", "/map/nodes/")
            assert types["/loops/accepted/0"] == "MeshMessage"  # a wireframe mesh: 1-pixel GL lines
            page.wait_for_timeout(2000)
            img = canvas(page, tmp_path / "viewer-localise.png")
            page.screenshot(path=str(tmp_path / "viewer-localise-page.png"))
            # the nodes drawn are the base map's, where the base map has them
            nodes = _scene_points(page, "/map/nodes")
            base_xy = np.array([n["pose"][:2] for n in base_map["nodes"]], float)
            assert len(nodes) == n_base
            assert np.allclose(np.sort(nodes[:, 0]), np.sort(base_xy[:, 0]), atol=1e-3)
            # the ground truth is drawn in the base map's frame: along its nodes
            gt = _scene_points(page, "/ground_truth")[:, :2]
            assert len(gt) > 50
            near = np.sqrt(((gt[:, None, :] - base_xy[None]) ** 2).sum(-1)).min(axis=1)
            assert near.mean() < NEAR_M, near.mean()
            # the map trajectory starts at the placement, on the map near where the ground truth then is
            traj = _scene_points(page, "/trajectories/map")[:, :2]
            assert len(traj)
            assert np.sqrt(((traj[:, None, :] - base_xy[None]) ** 2).sum(-1)).min(axis=1).max() < 1.5
            # the raw odometry starts there too, re-anchored on the map (not in the run's own frame)
            odo = _scene_points(page, "/trajectories/odometry")[:, :2]
            assert len(odo) and np.hypot(*(odo[0] - traj[0])) < ODOMETRY_START_M
            # loop closures: thin lines, the ones made while lost not drawn from the base's last node
            seg = _scene_points(page, "/loops/accepted", but="/loops/accepted/ends").reshape(-1, 2, 3)
            placing = [lc for lc in accepted if lc["decision"]["gate_distance_m"] is None]
            assert placing and len(seg) == len(accepted) - len(placing)
            # a relocalisation joins the robot's node to a node recognised a key frame or two later
            lengths = np.linalg.norm(seg[:, 0, :2] - seg[:, 1, :2], axis=1)
            assert lengths.max() < LOOP_M, lengths
        finally:
            browser.close()
    gt_px, map_px = teal(img), blue(img)
    assert gt_px > 300 and map_px > 300, (gt_px, map_px)
