"""Benchmark: the live viewer on large maps (10k and 50k nodes), from the Mapper to a real browser.

For each map size a real :class:`hippomap.mapper.Mapper` is given a large synthetic cognitive map
(a spiral of nodes 0.25 m apart, odometry links along it, a loop link every 50 nodes to the ring
inside, 4 trajectory rows per node; built through ``ReuseMap.from_state``, the mapper's own map), a
:class:`web.session_viewer.SessionViewer` is opened on it and headless Chromium (Debian's, software
WebGL) loads the page straight from the viewer's viser server. Then these updates are timed,
``--repeat`` times each:

* ``append``   — the map grows by 20 nodes (+ links, trajectory): only the last chunks are sent;
* ``local``    — a relaxation moves the newest 1000 nodes by 5 cm: only their chunks are resent;
* ``global``   — a relaxation moves every node: everything is resent (the worst case);
* ``idle``     — nothing changed: nothing is sent.

Figures per update: ``copy`` (the snapshot taken under the session lock), ``build`` (geometry and
queueing in the viewer thread), ``bytes`` (websocket bytes from viser, counted by a raw client),
``wire`` (from the push until a raw websocket client has received it), ``browser`` (from the push
until the browser's scene holds the update — a marker node queued after the update is found with
``window.__viserSceneTree`` — and has rendered two more frames). Also: the first load (page open until every
chunk is in the scene) and the frame rate while orbiting the camera over the whole map.

    python bench/bench_viewer.py [--sizes 10000 50000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import asyncio
import re
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import viser  # noqa: E402
import websockets  # noqa: E402
import zstandard  # noqa: E402

from hippomap.inputs import Odometry  # noqa: E402
from hippomap.map_reuse import ReuseMap  # noqa: E402
from tests.support.chromium import launch  # noqa: E402
from web.scene.chunks import chunk_layout  # noqa: E402
from web.session_viewer import KEY_HEADER, SessionViewer  # noqa: E402
from web.settings import ViewerSettings  # noqa: E402
from web.source import LocalSession  # noqa: E402


# ------------------------------------------------------------------------------ the large map
def spiral(n: int, spacing: float = 0.25, ring_gap: float = 3.0) -> np.ndarray:
    """(n, 3) poses along an Archimedean spiral, ``spacing`` apart, rings ``ring_gap`` apart."""
    b = ring_gap / (2 * np.pi)
    s = np.arange(n) * spacing + 20.0
    th = np.sqrt(2 * s / b)  # arc length of r = b th is ~ b th^2 / 2
    r = b * th
    x, y = r * np.cos(th), r * np.sin(th)
    heading = np.arctan2(np.gradient(y), np.gradient(x))
    return np.column_stack([x, y, heading])


def big_state(template: dict, n: int) -> dict:
    """A cognitive-map state with ``n`` spiral nodes and chain + loop links (robot at the last node)."""
    P = spiral(n)
    src = np.arange(n - 1)
    dst = src + 1
    kind = np.zeros(n - 1, np.int64)
    loops_from = np.arange(400, n, 50)
    # the node one ring inside: nearest earlier node at least 200 nodes back
    loops_to = np.array([int(np.argmin(np.hypot(*(P[: i - 200, :2] - P[i, :2]).T))) for i in loops_from])
    src = np.concatenate([src, loops_from])
    dst = np.concatenate([dst, loops_to])
    kind = np.concatenate([kind, np.ones(len(loops_from), np.int64)])
    m = len(src)
    state = {**template}
    frames = np.where(np.arange(n) % 3 == 0, np.arange(n) // 3, -1)
    state["nodes"] = {
        "pose": P,
        "place_code": P.copy(),
        "frame": frames,
        "time": np.arange(n, dtype=float),
        "path": np.arange(n) * 0.25,
    }
    state["links"] = {
        "source": src,
        "target": dst,
        "transform": np.zeros((m, 3)),
        "dt": np.ones(m),
        "kind": kind,
        "colour": np.zeros(m, np.int64),
    }
    state["robot"] = {**template["robot"], "current": n - 1}
    state["loop"] = {"decisions": [], "pending": [], "accepted": []}
    state["events"] = []
    return state


def trajectory_rows(P: np.ndarray, start_t: float, per_node: int = 4) -> np.ndarray:
    """Trajectory rows (t, raw pose, node, offset, seconds at the node): ``per_node`` steps between consecutive
    nodes."""
    n = len(P)
    k = np.repeat(np.arange(n), per_node)
    f = np.tile(np.arange(per_node) / per_node, n)
    nxt = np.minimum(k + 1, n - 1)
    raw = P[k] + f[:, None] * (P[nxt] - P[k])
    rows = np.zeros((len(k), 9))
    rows[:, 0] = start_t + np.arange(len(k)) * 0.05
    rows[:, 1:4] = raw
    rows[:, 4] = k
    c, s = np.cos(P[k, 2]), np.sin(P[k, 2])
    d = raw[:, :2] - P[k, :2]
    rows[:, 5] = c * d[:, 0] + s * d[:, 1]
    rows[:, 6] = -s * d[:, 0] + c * d[:, 1]
    return rows


class BigSession(LocalSession):
    """A LocalSession whose Mapper holds a large synthetic map that the benchmark edits."""

    def __init__(self, n: int) -> None:
        super().__init__(f"bench{n}", title=f"{n} nodes")
        m = self.mapper
        t = 0.0
        for _ in range(20):  # a few real steps: place code, place field, trajectory store
            t += 0.05
            m.step(Odometry(t, increment=(0.02, 0.0, 0.0)))
        self.template = m.cmap.state_dict()
        self.n = n
        self.set_map(spiral(n), n)

    def set_map(self, P: np.ndarray, n: int) -> None:
        """Replace the map by the first ``n`` spiral nodes with poses ``P`` (and matching trajectory)."""
        state = big_state(self.template, n)
        state["nodes"]["pose"] = P[:n]
        with self.lock:
            m = self.mapper
            m.cmap = ReuseMap.from_state(m.config.map, state)
            m.cmap.configure(m.localise_only, False)
            rows = trajectory_rows(P[:n], 10.0)
            old = m._traj.n
            if old > len(rows):
                m._traj.n = 0
                old = 0
            grown = m._traj
            for r in rows[old:] if old else rows:
                grown.append(r)
            self.n = n


# --------------------------------------------------------------------------- byte counting
class Wire:
    """A raw websocket client of the viser server: bytes received, and marker names seen."""

    def __init__(self, port: int, key: str) -> None:
        self.port = port
        self.key = key
        self.bytes = 0
        self.seen: dict[str, tuple[float, int]] = {}
        self._zstd = zstandard.ZstdDecompressor()
        self._ready = threading.Event()
        self._loop = asyncio.new_event_loop()
        threading.Thread(target=self._loop.run_forever, daemon=True).start()
        asyncio.run_coroutine_threadsafe(self._run(), self._loop)
        self._ready.wait(10)

    async def _run(self) -> None:
        async with websockets.connect(
            f"ws://127.0.0.1:{self.port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
            compression=None,
            additional_headers={KEY_HEADER: self.key},  # the viewer's loopback server refuses any other client
        ) as ws:
            self._ready.set()
            async for frame in ws:
                self.bytes += len(frame)
                size = int.from_bytes(frame[:8], "little")
                packed = int.from_bytes(frame[8:16], "little")
                payload = self._zstd.decompress(frame[16 : 16 + packed], max_output_size=size)
                for num in re.findall(rb"/bench/mark_(\d+)", payload):
                    self.seen.setdefault(num.decode(), (time.perf_counter(), self.bytes))


# ------------------------------------------------------------------------------ measuring
def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q))


def orbit_fps(page, seconds: float = 4.0) -> float:
    """Frames per second while the mouse orbits the camera (viser renders on demand: orbiting forces
    a render every frame). Software WebGL on a shared CPU: indicative only."""
    page.evaluate(
        "() => { window.__ts = []; const f = t => { window.__ts.push(t); if (!window.__stop) "
        "requestAnimationFrame(f); }; window.__stop = false; requestAnimationFrame(f); }"
    )
    page.mouse.move(500, 400)
    page.mouse.down()
    t0 = time.perf_counter()
    i = 0
    while time.perf_counter() - t0 < seconds:
        page.mouse.move(500 + 120 * np.sin(i / 8), 400 + 40 * np.cos(i / 8))
        i += 1
        time.sleep(0.01)
    page.mouse.up()
    ts = page.evaluate("() => { window.__stop = true; return window.__ts; }")
    return (len(ts) - 1) / ((ts[-1] - ts[0]) / 1000.0) if len(ts) > 1 else 0.0


def run_size(n: int, repeat: int, page) -> dict:
    session = BigSession(n)
    viewer = SessionViewer(session, ViewerSettings(), start=False)
    wire = Wire(viewer.port, viewer.access_key)
    page.set_extra_http_headers({KEY_HEADER: viewer.access_key})  # what the service's proxy adds
    marks = 0

    def push(label: str) -> tuple[float, float, float, int, float]:
        nonlocal marks
        marks += 1
        b0 = wire.bytes
        t0 = time.perf_counter()
        up = viewer.update_graph()
        viewer.server.scene.add_label(f"/bench/mark_{marks}", label, visible=False)
        key = str(marks)
        page.wait_for_function(
            "n => !!window.__viserSceneTree?.getState()[n]", arg=f"/bench/mark_{marks}", timeout=120_000, polling=5
        )
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        t_browser = time.perf_counter() - t0
        deadline = time.time() + 60
        while key not in wire.seen and time.time() < deadline:
            time.sleep(0.002)
        nbytes = wire.seen[key][1] - b0 if key in wire.seen else -1
        t_wire = wire.seen[key][0] - t0 if key in wire.seen else float("nan")
        return up.copy_s, up.build_s, t_wire, t_browser, nbytes, up.items_sent

    out: dict = {"n": n, "links": int(session.mapper.cmap.link_count), "traj_rows": int(session.mapper._traj.n)}
    # first load: the page opens on a viewer that already holds the whole map
    t0 = time.perf_counter()
    page.goto(f"http://127.0.0.1:{viewer.port}/")
    last_chunk = chunk_layout(n, viewer.settings.chunk_size, viewer.settings.tail_size)[-1][0]
    page.wait_for_function(
        "n => !!window.__viserSceneTree?.getState()[n]", arg=f"/map/nodes/{last_chunk}", timeout=300_000, polling=20
    )
    out["first_load_s"] = time.perf_counter() - t0
    push("warm-up")
    P = spiral(n + 20 * (repeat + 1))
    rows = {"append": [], "local": [], "global": [], "idle": []}
    cur = n
    for r in range(repeat):
        cur += 20
        session.set_map(P, cur)
        rows["append"].append(push("append"))
        P = P.copy()
        P[cur - 1000 : cur, :2] += 0.05 * (1 if r % 2 else -1)
        session.set_map(P, cur)
        rows["local"].append(push("local"))
        P = P.copy()
        P[:cur, :2] += np.array([0.03, -0.02]) * (1 if r % 2 else -1)
        session.set_map(P, cur)
        rows["global"].append(push("global"))
        rows["idle"].append(push("idle"))
    out["orbit_fps"] = orbit_fps(page)
    for k, v in rows.items():
        copy, build, wire_s, browser, nbytes, items = map(list, zip(*v))
        out[k] = {
            "copy_ms": statistics.median(copy) * 1e3,
            "build_ms": statistics.median(build) * 1e3,
            "wire_ms": statistics.median(wire_s) * 1e3,
            "build_ms_p95": pct(build, 95) * 1e3,
            "browser_ms": statistics.median(browser) * 1e3,
            "browser_ms_p95": pct(browser, 95) * 1e3,
            "kbytes": statistics.median(nbytes) / 1e3,
            "items": statistics.median(items),
        }
    viewer.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 50_000])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    results = []
    with sync_playwright() as p:
        browser = launch(p)
        for n in args.sizes:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            results.append(run_size(n, args.repeat, page))
            page.close()
        browser.close()
    vs = ViewerSettings()
    print(
        f"viser {viser.__version__}, chunks of {vs.chunk_size} items (tails of {vs.tail_size}), "
        "headless Chromium (SwiftShader software WebGL)"
    )
    for r in results:
        print(f"\n== {r['n']} nodes, {r['links']} links, {r['traj_rows']} trajectory rows ==")
        print(f"first load (page open -> whole map in the browser's scene): {r['first_load_s']:.2f} s")
        print(f"orbiting the camera (a render per frame, software WebGL): {r['orbit_fps']:.1f} frames/s")
        print(
            f"{'update':8s} {'items':>7s} {'kB':>8s} {'copy ms':>8s} {'build ms':>9s} {'(p95)':>7s} "
            f"{'wire ms':>8s} {'browser ms':>11s} {'(p95)':>7s}"
        )
        for k in ("append", "local", "global", "idle"):
            u = r[k]
            print(
                f"{k:8s} {u['items']:7.0f} {u['kbytes']:8.1f} {u['copy_ms']:8.2f} {u['build_ms']:9.2f} "
                f"{u['build_ms_p95']:7.2f} {u['wire_ms']:8.1f} {u['browser_ms']:11.1f} {u['browser_ms_p95']:7.1f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
