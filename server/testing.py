"""Helpers for tests and benchmarks: a real server in a subprocess, and synthetic robot data.

:class:`LiveServer` runs ``python -m server`` (uvicorn on loopback, port chosen by the OS)
so tests exercise exactly what a robot talks to, including being killed with SIGKILL.
:func:`synthetic_inputs` drives a robot round a circle facing a textured panorama: laps
repeat the same views, so the visual memory recognises places and closes loops.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hippomap.inputs import Odometry

ROOT = Path(__file__).resolve().parents[1]
_BANNER = re.compile(r"hippomap server on (http://\S+)")


class LiveServer:
    """``python -m server`` on 127.0.0.1 with its own data folder and admin token."""

    def __init__(self, data_dir: str | Path, token: str = "hm_test_admin_token", env: dict[str, str] | None = None,
                 args: list[str] | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.token = token
        pythonpath = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
        self.env = {**os.environ, "HIPPOMAP_ADMIN_TOKEN": token, "PYTHONPATH": pythonpath, **(env or {})}
        self.args = args or []
        self.proc: subprocess.Popen | None = None
        self.url = ""
        self.output: list[str] = []

    def start(self, timeout: float = 60.0) -> "LiveServer":
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "server", "--host", "127.0.0.1", "--port", "0", "--data-dir", str(self.data_dir),
             *self.args],
            cwd=ROOT, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        found = threading.Event()

        def pump() -> None:
            assert self.proc is not None and self.proc.stdout is not None
            for line in self.proc.stdout:
                self.output.append(line)
                m = _BANNER.search(line)
                if m and not found.is_set():
                    self.url = m.group(1)
                    found.set()
            found.set()

        threading.Thread(target=pump, daemon=True).start()
        if not found.wait(timeout) or not self.url:
            self.kill()
            raise RuntimeError("server did not start:\n" + "".join(self.output))
        return self

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs (a crash)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(30)

    def stop(self, timeout: float = 60.0) -> None:
        """SIGTERM: a graceful shutdown."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()

    def client(self, token: str | None = None) -> Any:
        from hippomap.client import Client

        return Client(self.url, token or self.token)

    def __enter__(self) -> "LiveServer":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


@dataclass(frozen=True)
class ServiceVariant:
    """One way to run the service under test: a session backend and a store.

    The service suite (tests/test_server_live.py, test_server_crash.py, test_client_replay.py)
    runs once per entry of :data:`SERVICE_VARIANTS` through the ``variant`` fixture, so every
    backend and store passes the same tests. ``env_for(data_dir)`` gives the environment that
    points a server at its store (e.g. a PostgreSQL database of its own for that data folder);
    it must return the same store for the same folder, so a restarted server finds its data."""

    name: str
    args: tuple[str, ...] = ()
    env_for: Callable[[Path], dict[str, str]] | None = field(default=None, compare=False)

    def env(self, data_dir: str | Path) -> dict[str, str]:
        return self.env_for(Path(data_dir)) if self.env_for is not None else {}

    def server(self, data_dir: str | Path, env: dict[str, str] | None = None,
               args: list[str] | None = None) -> LiveServer:
        """A (not yet started) :class:`LiveServer` of this variant on ``data_dir``."""
        return LiveServer(data_dir, env={**self.env(data_dir), **(env or {})}, args=[*self.args, *(args or [])])

    def open_store(self, data_dir: str | Path) -> Any:
        """The store a server of this variant on ``data_dir`` uses (to inspect it directly)."""
        from .app import open_store
        from .settings import ServerSettings

        return open_store(ServerSettings(data_dir=Path(data_dir), database=self.env(data_dir).get("HIPPOMAP_DATABASE")))


#: every backend x store combination the service suite runs against
SERVICE_VARIANTS: list[ServiceVariant] = [ServiceVariant("inprocess-sqlite")]


@lru_cache(maxsize=4)
def panorama(seed: int = 0, width: int = 2400, height: int = 240) -> np.ndarray:
    """A 360-degree gray panorama with smooth shading and many high-contrast shapes (corners)."""
    import cv2

    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.random((6, width // 40)).astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
    img = np.clip(60 + 120 * base, 0, 255).astype(np.uint8)
    for _ in range(width // 12):
        x, y = int(rng.integers(0, width - 30)), int(rng.integers(0, height - 30))
        w, h = int(rng.integers(8, 40)), int(rng.integers(8, 40))
        g = int(rng.integers(0, 256))
        if rng.random() < 0.6:
            cv2.rectangle(img, (x, y), (x + w, y + h), g, -1)
        else:
            cv2.circle(img, (x + w // 2, y + h // 2), max(w, h) // 2, g, -1)
    return img


def view(heading: float, seed: int = 0, width: int = 320) -> np.ndarray:
    """The camera image facing ``heading`` (radians): a window of the panorama."""
    pano = panorama(seed)
    W = pano.shape[1]
    x0 = int(round((heading % (2 * np.pi)) / (2 * np.pi) * W))
    return np.take(pano, np.arange(x0, x0 + width), axis=1, mode="wrap")


@lru_cache(maxsize=8)
def synthetic_inputs(n_odometry: int = 400, rate_hz: float = 20.0, frame_every: int = 4, speed: float = 0.5,
                     radius: float = 1.0, seed: int = 0, quality: int = 85) -> tuple[tuple, ...]:
    """Inputs of a robot circling (``speed`` m/s, ``radius`` m): ``("odometry", Odometry)`` and
    ``("frame", t, jpeg)`` items in strictly increasing time order; a frame follows every
    ``frame_every``-th reading by half a period."""
    import cv2

    dt = 1.0 / rate_hz
    omega = speed / radius
    out: list[tuple] = []
    for k in range(n_odometry):
        t = round((k + 1) * dt, 6)
        out.append(("odometry", Odometry(t, v=speed, omega=omega)))
        if k % frame_every == 0:
            tf = round(t + dt / 2, 6)
            ok, buf = cv2.imencode(".jpg", view(omega * tf, seed), [cv2.IMWRITE_JPEG_QUALITY, quality])
            out.append(("frame", tf, buf.tobytes()))
    return tuple(out)


def decoded(items: tuple) -> list:
    """The inputs as the mapper takes them (frames decoded like the server does)."""
    from hippomap.inputs import Frame, decode_jpeg

    return [it[1] if it[0] == "odometry" else Frame(it[1], decode_jpeg(it[2])) for it in items]


def offline_reference(items: tuple, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a session fed ``items`` must report: the same mapper run in-process, through the
    server's own query functions and a JSON round trip (as a client sees it)."""
    import json

    from hippomap.inputs import Odometry as _Odo

    from . import model

    m = model.new_mapper(model.effective_config(overrides))
    for value in decoded(items):
        (m.step if isinstance(value, _Odo) else m.observe)(value)
    out = {"map": model.graph(m), "stats": model.stats(m),
           "loop_closures": [r["decision"] for r in model.loop_closures(m)],
           "recognitions": model.recognitions(m, -1, 10**9)}
    return json.loads(json.dumps(model.json_safe(out)))


def session_state(client: Any, session_id: str) -> dict[str, Any]:
    """The same four things, as the server reports them (after it has processed everything)."""
    client.wait_processed(session_id)
    return {"map": client.map(session_id), "stats": client.stats(session_id)["mapper"],
            "loop_closures": [r["decision"] for r in client.loop_closures(session_id, limit=10_000)],
            "recognitions": [client.saccades(session_id, r["id"]) for r in client.recognitions(session_id, limit=10_000)]}


async def stream_items(url: str, token: str, session_id: str, items: tuple, window: int = 64) -> list[dict]:
    """Send ``items`` over one websocket (pipelined); returns the acks in order."""
    import asyncio

    from hippomap.client import AsyncStream

    futs = []
    async with AsyncStream(url, token, session_id, max_in_flight=window) as st:
        for it in items:
            futs.append(await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2])))
        return list(await asyncio.gather(*futs))
