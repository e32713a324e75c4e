"""Aggregate mapping throughput of the session backends: frames/s for 1, 2, 4, 8 concurrent sessions,
in-process vs Ray, measured in the same run.

    python bench/bench_backends.py [--sessions 1 2 4 8] [--frames 400] [--odometry-per-frame 2]
                                   [--keyframe-interval K] [--backends inprocess ray]

A real server (``python -m server``, SQLite with ``synchronous=FULL``, the default model
config) runs in a subprocess on 127.0.0.1, once per backend and session count. Each session
is a robot streaming over its own websocket as fast as acknowledgements allow (window 64):
``--frames`` camera frames of **640x480** (windows of :func:`tests.support.synthetic.view`'s textured
panorama scaled to 640x480, JPEG quality 85, ~60-70 kB) each preceded by
``--odometry-per-frame`` odometry readings (the robot circles, so loops are closed).
Measured: from the first message to the moment every session's mapper has processed its
last input (``GET /stats``), so the figure is *mapping* throughput, not just storage. With the model's
default config (``keyframe_interval`` 100) frames are cheap for the mapper and the server's
ingest path (decode, SQLite commit, websocket) dominates; ``--keyframe-interval 3`` makes the
mapper the bottleneck (recognition + learning on every third frame, loops closed).
Reported: aggregate frames/s (frames with their odometry), frames/s per core (``os.cpu_count()``),
and the Ray/in-process ratio per session count.

Ray: one private Ray head (``ray start --head`` on 127.0.0.1, ``--num-cpus`` = the machine's
cores) is started for the whole run and each server joins it (``--backend ray --ray-address``),
so Ray's start-up is not timed; actors are created when sessions are created, before the
clock starts. The clients run on the same machine as the server (and Ray), so on a small
machine the figures are a lower bound for a server with its own cores.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.client import AsyncStream  # noqa: E402
from hippomap.inputs import Odometry  # noqa: E402
from tests.support.live import LiveServer  # noqa: E402
from tests.support.ray_head import LocalRayHead  # noqa: E402
from tests.support.synthetic import view  # noqa: E402


def make_inputs(
    frames: int, odo_per_frame: int, rate_hz: float = 20.0, speed: float = 0.5, radius: float = 1.0
) -> list[tuple]:
    """``("odometry", Odometry)`` / ``("frame", t, jpeg)`` items: 640x480 frames of a robot circling."""
    import cv2

    dt = 1.0 / rate_hz
    omega = speed / radius
    out: list[tuple] = []
    k = 0
    for _ in range(frames):
        for _ in range(odo_per_frame):
            k += 1
            out.append(("odometry", Odometry(round(k * dt, 6), v=speed, omega=omega)))
        tf = round(k * dt + dt / 2, 6)
        img = cv2.resize(view(omega * tf, 0, width=320), (640, 480), interpolation=cv2.INTER_LINEAR)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        out.append(("frame", tf, buf.tobytes()))
    return out


async def _stream(url: str, token: str, sid: str, items: list[tuple]) -> None:
    async with AsyncStream(url, token, sid, max_in_flight=64) as st:
        futs = []
        for it in items:
            futs.append(await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2])))
        await asyncio.gather(*futs)


def run_level(backend: str, n: int, items: list[tuple], head: LocalRayHead | None, config: dict | None = None) -> dict:
    env = {"HIPPOMAP_RATE_PER_S": "100000", "HIPPOMAP_RATE_BURST": "100000"}
    args = ["--backend", backend]
    if backend == "ray":
        assert head is not None
        env.update(head.env)
        args += ["--ray-address", head.address]
    with tempfile.TemporaryDirectory(prefix="hm-bench-backends-") as tmp:
        srv = LiveServer(Path(tmp) / "data", env=env, args=args).start(timeout=180)
        try:
            with srv.client() as c:
                sids = [c.create_session(f"robot-{k}", config or {})["id"] for k in range(n)]
                t0 = time.perf_counter()

                async def all_streams() -> None:
                    await asyncio.gather(*(_stream(srv.url, srv.token, sid, items) for sid in sids))

                asyncio.run(all_streams())
                t_acked = time.perf_counter() - t0
                stats = [c.wait_processed(sid, timeout=1800) for sid in sids]
                elapsed = time.perf_counter() - t0
            n_frames = sum(1 for it in items if it[0] == "frame")
            assert all(s["processed_seq"] == len(items) - 1 for s in stats)
            loops = sum(s["mapper"]["loop_closures_accepted"] for s in stats)
            return {
                "backend": backend,
                "sessions": n,
                "frames": n * n_frames,
                "elapsed_s": elapsed,
                "acked_s": t_acked,
                "fps": n * n_frames / elapsed,
                "loops": loops,
            }
        finally:
            srv.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--frames", type=int, default=400, help="camera frames per session")
    ap.add_argument("--odometry-per-frame", type=int, default=2)
    ap.add_argument(
        "--keyframe-interval",
        type=int,
        default=None,
        help="session config mapper.keyframe_interval (default: the model's default, 100); 3 makes "
        "every third frame a key frame: recognition + learning, loops closed (a mapping-heavy load)",
    )
    ap.add_argument("--backends", nargs="+", default=["inprocess", "ray"], choices=["inprocess", "ray"])
    args = ap.parse_args()
    cores = os.cpu_count() or 1
    items = make_inputs(args.frames, args.odometry_per_frame)
    config = {} if args.keyframe_interval is None else {"mapper": {"keyframe_interval": args.keyframe_interval}}
    jpeg = np.mean([len(it[2]) for it in items if it[0] == "frame"])
    print(
        f"machine: {cores} cores; per session: {args.frames} frames 640x480 (mean JPEG {jpeg / 1e3:.0f} kB) "
        f"+ {args.odometry_per_frame} odometry readings each; session config {config or 'default'}",
        flush=True,
    )
    head = None
    if "ray" in args.backends:
        t = time.perf_counter()
        head = LocalRayHead(num_cpus=cores).start()
        print(f"Ray head on {head.address} started in {time.perf_counter() - t:.1f} s (not timed below)", flush=True)
    rows = []
    try:
        warm = items[: 20 * (args.odometry_per_frame + 1)]
        for backend in args.backends:  # warm-up (not reported): first imports, caches, Ray worker pool
            run_level(backend, 1, warm, head, config)
        for n in args.sessions:
            for backend in args.backends:
                r = run_level(backend, n, items, head, config)
                rows.append(r)
                print(
                    f"  {backend:9s} sessions={n}: {r['fps']:7.1f} frames/s  ({r['frames']} frames in "
                    f"{r['elapsed_s']:.1f} s; all acked after {r['acked_s']:.1f} s; loops {r['loops']})",
                    flush=True,
                )
    finally:
        if head is not None:
            head.stop()
    print()
    print("| sessions | backend | frames/s (aggregate) | frames/s per core | vs in-process |")
    print("|---:|---|---:|---:|---:|")
    base = {r["sessions"]: r["fps"] for r in rows if r["backend"] == "inprocess"}
    for r in rows:
        ratio = f"{r['fps'] / base[r['sessions']]:.2f}x" if r["sessions"] in base else "-"
        print(f"| {r['sessions']} | {r['backend']} | {r['fps']:.1f} | {r['fps'] / cores:.1f} | {ratio} |")


if __name__ == "__main__":
    main()
