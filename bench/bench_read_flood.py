"""A reader flooding queries must not slow down or refuse the robot's ingest.

    python bench/bench_read_flood.py [--duration 6] [--readers 8] [--ingest-rate 100] [--read-rate 20]

A real server (``python -m server``, SQLite) runs on 127.0.0.1 with small budgets so that the
flood exceeds one of them: ingest ``--ingest-rate`` requests/s per session (the robot needs 50),
reads ``--read-rate``/s per session and token (both bursts equal to the rate). One robot posts odometry
over HTTP in real time (50 readings/s, one request each) and measures each request's latency
(the answer comes once the reading is durable). Two phases of ``--duration`` s on the same
session: the robot alone (the reference), then the robot while ``--readers`` concurrent clients
holding a viewer token poll ``GET /sessions/{id}/stats`` as fast as they can. Reported: the
robot's p50/p99 latency and its 429 answers in both phases, their ratio, and the readers'
request rate and how many of their requests were refused (429, their own budget).

Client and server share the machine (2 cores here), so the flood also competes for CPU.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.support.live import LiveServer  # noqa: E402

ODO_HZ = 50


async def robot(url: str, token: str, sid: str, t0: float, duration: float, lat: list[float]) -> dict:
    """Real-time odometry over HTTP; readings continue the session's clock from ``t0``."""
    refused = other = 0
    async with httpx.AsyncClient(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=30) as http:
        start = time.perf_counter()
        k = 0
        while (now := time.perf_counter()) - start < duration:
            due = start + k / ODO_HZ
            if due > now:
                await asyncio.sleep(due - now)
            t = t0 + k / ODO_HZ
            sent = time.perf_counter()
            r = await http.post(f"/sessions/{sid}/odometry", json={"t": t, "v": 0.4, "omega": 0.2})
            if r.status_code == 200:
                lat.append(time.perf_counter() - sent)
            elif r.status_code == 429:
                refused += 1
            else:
                other += 1
            k += 1
    return {"sent": k, "refused": refused, "other": other, "last_t": t0 + (k - 1) / ODO_HZ}


async def reader(url: str, token: str, sid: str, stop: asyncio.Event, counts: dict) -> None:
    async with httpx.AsyncClient(base_url=url, headers={"Authorization": f"Bearer {token}"}, timeout=30) as http:
        while not stop.is_set():
            r = await http.get(f"/sessions/{sid}/stats")
            counts[r.status_code] = counts.get(r.status_code, 0) + 1


async def phase(url: str, token: str, viewer: str | None, sid: str, t0: float, duration: float, readers: int) -> dict:
    lat: list[float] = []
    counts: dict[int, int] = {}
    stop = asyncio.Event()
    flood = [asyncio.create_task(reader(url, viewer, sid, stop, counts)) for _ in range(readers if viewer else 0)]
    started = time.perf_counter()
    res = await robot(url, token, sid, t0, duration, lat)
    stop.set()
    await asyncio.gather(*flood)
    elapsed = time.perf_counter() - started
    ms = np.asarray(lat) * 1000 if lat else np.zeros(1)
    return {
        **res,
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "reads": sum(counts.values()),
        "reads_refused": counts.get(429, 0),
        "reads_per_s": sum(counts.values()) / elapsed,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--readers", type=int, default=8)
    ap.add_argument("--ingest-rate", type=float, default=100.0)
    ap.add_argument("--read-rate", type=float, default=20.0)
    args = ap.parse_args()
    env = {
        "HIPPOMAP_RATE_PER_S": str(args.ingest_rate),
        "HIPPOMAP_RATE_BURST": str(args.ingest_rate),
        "HIPPOMAP_READ_RATE_PER_S": str(args.read_rate),
        "HIPPOMAP_READ_RATE_BURST": str(args.read_rate),
    }
    with tempfile.TemporaryDirectory() as tmp, LiveServer(Path(tmp) / "data", env=env) as srv, srv.client() as c:
        sid = c.create_session("robot")["id"]
        viewer = c.create_token("viewer", session=sid, label="flooding reader")["token"]
        alone = asyncio.run(phase(srv.url, srv.token, None, sid, 1.0, args.duration, 0))
        flooded = asyncio.run(
            phase(srv.url, srv.token, viewer, sid, alone["last_t"] + 1.0, args.duration, args.readers)
        )
        stored = c.wait_processed(sid)["inputs_stored"]
    print(
        f"robot: {ODO_HZ} odometry requests/s over HTTP for {args.duration:g} s per phase; budgets: ingest "
        f"{args.ingest_rate:g}/s per session, reads {args.read_rate:g}/s per session and token"
    )
    for name, r in (("alone (reference)", alone), (f"with {args.readers} readers flooding /stats", flooded)):
        print(
            f"  {name:36s} p50 {r['p50_ms']:6.1f} ms  p99 {r['p99_ms']:6.1f} ms  robot 429s {r['refused']:4d}"
            f"  other errors {r['other']}  reads {r['reads_per_s']:7.1f}/s ({r['reads_refused']} refused 429)"
        )
    print(
        f"p99 ratio flooded/alone: {flooded['p99_ms'] / max(alone['p99_ms'], 1e-9):.2f}; "
        f"p50 ratio: {flooded['p50_ms'] / max(alone['p50_ms'], 1e-9):.2f}"
    )
    sent = alone["sent"] + flooded["sent"]
    ok = flooded["refused"] == alone["refused"] == 0 and stored == sent - alone["other"] - flooded["other"]
    print(f"inputs stored {stored} of {sent} sent; robot never refused: {flooded['refused'] == 0}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
