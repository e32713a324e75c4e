"""Where the server's CPU goes under the load of ``bench/bench_load.py``, per thread.

    python bench/profile_load.py 8 16 [--duration 8] [--backend inprocess|process] [--config JSON]

Runs the given numbers of robots (the same robots as ``bench_load.py``: 50 odometry messages/s
and 10 JPEG frames/s each, over one websocket) against one real server (``python -m server``,
SQLite ``synchronous=FULL``), one level after another. For each level it prints the ack latency
percentiles per kind of message, whether the mappers kept up (``drain``: seconds until every
input is processed once the robots stop) and the CPU time the server's threads used per
robot-second, from ``/proc/<pid>/task/*/stat``: the event loop (``MainThread``), the session
workers with their mappers (``session-*``), the store's writer (``sqlite-writer``), the frame
decoders (``uvloop_*``, the loop's default executor) — ``sys:`` is the kernel part. Thread
names come from ``py-spy dump`` (``pip install py-spy``); without it the threads are summed.
With ``--backend process`` the mappers run in a child process, not counted here.
Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_load as bl  # noqa: E402
from hippomap.client import AsyncStream  # noqa: E402
from hippomap.inputs import Odometry  # noqa: E402
from tests.support.live import LiveServer  # noqa: E402

TICK = os.sysconf("SC_CLK_TCK")


def thread_cpu(pid: int) -> dict[str, tuple[float, float]]:
    """``tid -> (user + system seconds, system seconds)`` of every thread of ``pid``."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            st = open(f"/proc/{pid}/task/{tid}/stat").read().rsplit(")", 1)[1].split()
        except FileNotFoundError:  # the thread ended
            continue
        out[tid] = ((int(st[11]) + int(st[12])) / TICK, int(st[12]) / TICK)
    return out


def thread_names(pid: int) -> dict[str, str]:
    """``tid -> Python thread name`` via ``py-spy dump`` (empty without py-spy)."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    if not os.path.exists(spy):
        return {}
    out = subprocess.run([spy, "dump", "--nonblocking", "-p", str(pid)], capture_output=True, text=True).stdout
    return {m.group(1): m.group(2) for m in re.finditer(r'Thread (\d+) \(\w+\): "([^"]+)"', out)}


def group(before: dict, after: dict, names: dict[str, str]) -> dict[str, float]:
    g: dict[str, float] = {}
    for tid, (cpu, sys_cpu) in after.items():
        name = names.get(tid, "threads")
        name = re.sub(r"session-s_\w+", "session-*", name)
        name = re.sub(r"uvloop_\d+", "uvloop_*", name)
        cpu0, sys0 = before.get(tid, (0.0, 0.0))
        g[name] = g.get(name, 0.0) + cpu - cpu0
        g["sys:" + name] = g.get("sys:" + name, 0.0) + sys_cpu - sys0
    return g


async def robot(
    url: str, token: str, sid: str, duration: float, frames: list[bytes], start: float, lat: dict[str, list[float]]
) -> int:
    """``bench_load.robot`` with the latencies kept per kind; returns the messages sent."""
    sent = 0

    def keep(kind: str):
        def done(fut: asyncio.Future) -> None:
            if fut.exception() is None:
                lat[kind].append(fut.result()["latency_s"])

        return done

    per_frame = bl.ODO_HZ // bl.FRAME_HZ
    async with AsyncStream(url, token, sid, max_in_flight=1024) as st:
        for k in range(int(duration * bl.ODO_HZ)):
            t = (k + 1) / bl.ODO_HZ
            delay = start + t - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            (await st.send_odometry(Odometry(t, v=0.4, omega=0.2))).add_done_callback(keep("odometry"))
            sent += 1
            if k % per_frame == 0:
                (await st.send_frame(t + 1e-3, frames[(k // per_frame) % len(frames)])).add_done_callback(keep("frame"))
                sent += 1
        await st.drain()
    return sent


def level(srv: LiveServer, n: int, duration: float, frames: list[bytes]) -> None:
    pid = srv.proc.pid
    with srv.client() as c:
        sids = [c.create_session(f"profile-{n}-{i}", bl.SESSION_CONFIG)["id"] for i in range(n)]
    lat: dict[str, list[float]] = {"odometry": [], "frame": []}

    async def all_robots() -> list[int]:
        start = time.perf_counter() + 0.2
        return await asyncio.gather(*(robot(srv.url, srv.token, sid, duration, frames, start, lat) for sid in sids))

    names: dict[str, str] = {}
    namer = threading.Timer(duration / 2, lambda: names.update(thread_names(pid)))  # while the workers live
    namer.start()
    load = os.getloadavg()[0]
    before, cb = thread_cpu(pid), resource.getrusage(resource.RUSAGE_SELF)
    sent = sum(bl._run(all_robots()))
    after, ca = thread_cpu(pid), resource.getrusage(resource.RUSAGE_SELF)
    namer.join()
    with srv.client() as c:
        stored = sum(c.stats(sid)["inputs_stored"] for sid in sids)
        t0 = time.perf_counter()
        for sid in sids:
            c.wait_processed(sid, timeout=300)
        drain = time.perf_counter() - t0
        for sid in sids:
            c.delete_session(sid)
    acked = len(lat["odometry"]) + len(lat["frame"])
    both = np.array(lat["odometry"] + lat["frame"]) * 1e3
    print(
        f"N={n} (load average {load:.2f}): sent {sent}, acked {acked}, stored {stored}; ack p50 "
        f"{np.percentile(both, 50):.1f} ms, p99 {np.percentile(both, 99):.1f} ms (odometry p99 "
        f"{np.percentile(lat['odometry'], 99) * 1e3:.1f}, frames p99 {np.percentile(lat['frame'], 99) * 1e3:.1f}); "
        f"drain {drain:.1f} s",
        flush=True,
    )
    robot_s = n * duration
    g = group(before, after, names)
    total = sum(v for k, v in g.items() if not k.startswith("sys:"))
    client = (ca.ru_utime + ca.ru_stime) - (cb.ru_utime + cb.ru_stime)
    parts = ", ".join(f"{k} {v / robot_s * 1e3:.1f}" for k, v in sorted(g.items(), key=lambda x: -x[1]) if v > 0.005)
    print(
        f"   CPU ms per robot-second: server {total / robot_s * 1e3:.1f} ({parts}); this client "
        f"{client / robot_s * 1e3:.1f}",
        flush=True,
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("levels", nargs="+", type=int, help="numbers of robots, one level each")
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--config", help="JSON session config overrides")
    ap.add_argument("--backend", choices=["inprocess", "process"], default=None)
    args = ap.parse_args()
    bl.SESSION_CONFIG = None if args.config is None else json.loads(args.config)
    frames = bl.jpeg_pool()
    env = {
        "HIPPOMAP_RATE_PER_S": "100000",
        "HIPPOMAP_RATE_BURST": "100000",
        "HIPPOMAP_DURABILITY": "full",
        "HIPPOMAP_MAX_SESSIONS_PER_TOKEN": "1000",
    }
    server_args = [] if args.backend is None else ["--backend", args.backend]
    with tempfile.TemporaryDirectory() as tmp, LiveServer(Path(tmp) / "data", env=env, args=server_args) as srv:
        bl.run_level(srv, 1, 2.0, frames)  # warm-up
        for n in args.levels:
            level(srv, n, args.duration, frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
