"""Load test of the server on loopback: how many robots can stream at once?

    python bench/bench_load.py [--duration 8] [--max-sessions 64] [--throughput-frames 600]
                               [--backend inprocess|process] [--config JSON]

A real server (``python -m server``, uvicorn, SQLite with ``synchronous=FULL``, the default
model config; ``--backend``: where the sessions' mappers run, the server's default when
omitted) runs in a subprocess on 127.0.0.1. Each simulated robot is one session
streaming over the websocket in real time: 50 odometry messages/s and 10 camera frames/s
(320x240 JPEG, ~25 kB). The acknowledgement latency of every message (send -> ack, which
the server sends only once the input is durable) is measured by the client.

1. **Sessions held**: N = 1, 2, 4, 8, ... robots stream for ``--duration`` s; a level passes
   when p99 ack latency <= 100 ms, every message is acknowledged and every input is stored
   (the server's count equals the client's). After the first failure the largest passing N
   is refined by bisection; a failing level is run once more (``--retries``) because the
   machine may be shared. A 2-s warm-up level runs first. Reported: the largest N held.
2. **Throughput**: one session sends frames (and 5 odometry readings per frame) as fast as
   acknowledgements allow (window 128); reported: frames/s acknowledged (stored) and
   frames/s through the mapper.

Client and server share the machine (2 cores here), so the figures are a lower bound for a
server with its own cores. Bounded: each level lasts ``--duration`` s plus draining.
"""

from __future__ import annotations

import argparse
import asyncio
import json
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
from tests.support.synthetic import view  # noqa: E402

ODO_HZ = 50
FRAME_HZ = 10
P99_LIMIT_S = 0.100


def jpeg_pool(n: int = 40, quality: int = 90) -> list[bytes]:
    import cv2

    return [
        cv2.imencode(".jpg", view(2 * np.pi * k / n, seed=11), [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()
        for k in range(n)
    ]


async def robot(
    url: str, token: str, sid: str, duration: float, frames: list[bytes], lat: list[float], start: float
) -> dict:
    """Stream in real time for ``duration`` s; returns counts."""
    sent = acked = failed = 0
    v, omega = 0.4, 0.2

    def done(fut: asyncio.Future) -> None:
        nonlocal acked, failed
        if fut.exception() is None:
            acked += 1
            lat.append(fut.result()["latency_s"])
        else:
            failed += 1

    async with AsyncStream(url, token, sid, max_in_flight=1024) as st:
        n_steps = int(duration * ODO_HZ)
        per_frame = ODO_HZ // FRAME_HZ
        for k in range(n_steps):
            t = (k + 1) / ODO_HZ
            delay = start + t - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            (await st.send_odometry(Odometry(t, v=v, omega=omega))).add_done_callback(done)
            sent += 1
            if k % per_frame == 0:
                (await st.send_frame(t + 1e-3, frames[(k // per_frame) % len(frames)])).add_done_callback(done)
                sent += 1
        await st.drain()
    return {"sent": sent, "acked": acked, "failed": failed}


def _run(coro):
    """The client's event loop: uvloop when installed (as the server uses), else asyncio."""
    try:
        import uvloop

        return uvloop.run(coro)
    except ImportError:
        return asyncio.run(coro)


#: session config overrides of every session the bench creates (``--config``); None = the model's defaults
SESSION_CONFIG: dict | None = None


def run_level(srv: LiveServer, n: int, duration: float, frames: list[bytes]) -> dict:
    with srv.client() as c:
        sids = [c.create_session(f"load-{n}-{i}", SESSION_CONFIG)["id"] for i in range(n)]
    lat: list[float] = []

    async def all_robots() -> list[dict]:
        start = time.perf_counter() + 0.2
        return await asyncio.gather(*(robot(srv.url, srv.token, sid, duration, frames, lat, start) for sid in sids))

    results = _run(all_robots())
    sent = sum(r["sent"] for r in results)
    acked = sum(r["acked"] for r in results)
    t0 = time.perf_counter()
    with srv.client() as c:
        stored = sum(c.stats(sid)["inputs_stored"] for sid in sids)
        for sid in sids:  # let the mappers finish before the next level, then free the sessions
            c.wait_processed(sid, timeout=300)
        drain_s = time.perf_counter() - t0
        for sid in sids:
            c.delete_session(sid)
    a = np.array(lat) * 1e3 if lat else np.array([np.inf])
    return {
        "n": n,
        "sent": sent,
        "acked": acked,
        "stored": stored,
        "p50": float(np.percentile(a, 50)),
        "p95": float(np.percentile(a, 95)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
        "drain_s": drain_s,
        "ok": bool(acked == sent == stored and np.percentile(a, 99) <= P99_LIMIT_S * 1e3),
    }


def throughput(srv: LiveServer, n_frames: int, frames: list[bytes]) -> dict:
    with srv.client() as c:
        sid = c.create_session("throughput", SESSION_CONFIG)["id"]
    lat: list[float] = []

    async def blast() -> float:
        async with AsyncStream(srv.url, srv.token, sid, max_in_flight=128) as st:
            t0 = time.perf_counter()
            futs = []
            for k in range(n_frames):
                t = (k + 1) * 0.1
                futs.append(await st.send_odometry([Odometry(t - 0.08 + 0.02 * j, v=0.4, omega=0.2) for j in range(5)]))
                futs.append(await st.send_frame(t + 1e-3, frames[k % len(frames)]))
            acks = await asyncio.gather(*futs)
            lat.extend(a["latency_s"] for a in acks)
            return time.perf_counter() - t0

    start = time.perf_counter()
    elapsed = _run(blast())
    with srv.client() as c:
        st = c.wait_processed(sid, timeout=600)
        processed = time.perf_counter() - start
        assert st["inputs_stored"] == 6 * n_frames, st
    return {
        "frames": n_frames,
        "ack_fps": n_frames / elapsed,
        "mapper_fps": n_frames / processed,
        "p50_ms": float(np.median(lat) * 1e3),
        "p99_ms": float(np.percentile(lat, 99) * 1e3),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=8.0, help="seconds each level streams")
    ap.add_argument("--config", help='JSON session config overrides, e.g. \'{"mapper": {"keyframe_interval": 100}}\'')
    ap.add_argument("--max-sessions", type=int, default=64)
    ap.add_argument("--throughput-frames", type=int, default=600, help="frames of the full-speed run (0: skip it)")
    ap.add_argument("--durability", choices=["full", "normal"], default="full")
    ap.add_argument(
        "--backend",
        choices=["inprocess", "process"],
        default=None,
        help="session backend of the server (default: the server's default)",
    )
    ap.add_argument(
        "--retries",
        type=int,
        default=1,
        help="a failing level is run again this many times (the machine may be shared)",
    )
    args = ap.parse_args()
    global SESSION_CONFIG
    SESSION_CONFIG = None if args.config is None else json.loads(args.config)
    frames = jpeg_pool()
    print(
        f"frames: 320x240 JPEG, mean {np.mean([len(f) for f in frames]) / 1e3:.1f} kB; robot = {ODO_HZ} odometry "
        f"msg/s + {FRAME_HZ} frames/s over one websocket; {os.cpu_count()} CPUs shared by client and server; "
        f"SQLite synchronous={args.durability.upper()}; backend {args.backend or 'default'}; "
        f"load average {os.getloadavg()[0]:.2f}",
        flush=True,
    )
    env = {
        "HIPPOMAP_RATE_PER_S": "100000",
        "HIPPOMAP_RATE_BURST": "100000",
        "HIPPOMAP_DURABILITY": args.durability,
        "HIPPOMAP_MAX_SESSIONS_PER_TOKEN": "1000",
    }
    server_args = [] if args.backend is None else ["--backend", args.backend]
    with tempfile.TemporaryDirectory() as tmp, LiveServer(Path(tmp) / "data", env=env, args=server_args) as srv:
        print(
            f"\n{'N':>4} {'msgs':>7} {'acked':>7} {'stored':>7} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8} "
            f"{'max ms':>8} {'drain s':>8}  held",
            flush=True,
        )

        run_level(srv, 1, 2.0, frames)  # warm-up (first connections, caches), not reported

        def level(n: int) -> dict:
            for attempt in range(1 + args.retries):
                r = run_level(srv, n, args.duration, frames)
                print(
                    f"{r['n']:>4} {r['sent']:>7} {r['acked']:>7} {r['stored']:>7} {r['p50']:>8.1f} {r['p95']:>8.1f} "
                    f"{r['p99']:>8.1f} {r['max']:>8.1f} {r['drain_s']:>8.1f}  {'yes' if r['ok'] else 'NO'}"
                    + (" (retry)" if attempt else "")
                    + f"  [load {os.getloadavg()[0]:.2f}]",
                    flush=True,
                )
                if r["ok"]:
                    break
            return r

        best, fail, n = 0, None, 1
        while n <= args.max_sessions:
            if level(n)["ok"]:
                best, n = n, n * 2
            else:
                fail = n
                break
        while fail is not None and fail - best > 1 and fail - best > best // 8:
            mid = (best + fail) // 2
            if level(mid)["ok"]:
                best = mid
            else:
                fail = mid
        print(
            f"\nlargest N held (p99 ack latency <= {P99_LIMIT_S * 1e3:.0f} ms, nothing lost): {best}"
            + ("" if fail is not None else f" (the search stopped at --max-sessions {args.max_sessions})"),
            flush=True,
        )
        if args.throughput_frames <= 0:
            return 0  # the throughput part is skipped
        tp = throughput(srv, args.throughput_frames, frames)
        print(
            f"one session at full speed ({tp['frames']} frames + 5 odometry readings each, window 128): "
            f"{tp['ack_fps']:.0f} frames/s acknowledged (stored), "
            f"{tp['mapper_fps']:.0f} frames/s through the mapper; "
            f"ack latency p50 {tp['p50_ms']:.1f} ms, p99 {tp['p99_ms']:.1f} ms",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
