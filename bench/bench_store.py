"""Store throughput: inputs/s appended with group commit, SQLite vs PostgreSQL, same run.

    python bench/bench_store.py [--duration 3] [--threads 1 8] [--window 1 32]

Both stores at full durability: SQLite ``synchronous=FULL`` (an fsync of the WAL per commit),
PostgreSQL ``synchronous_commit=on`` with ``fsync=on`` (a WAL flush per commit) — a private
cluster started by :class:`tests.support.postgres_cluster.PostgresCluster` on 127.0.0.1 (TCP, as replicas on
other hosts would connect), or ``$HIPPOMAP_TEST_POSTGRES_URL`` with ``--external``.

Each writer thread is one session appending single inputs as a robot's stream arrives: four
odometry readings (~60 B) then one camera frame (a 320x240 gray JPEG, size printed). With
``window`` 1 a thread waits for each acknowledgement (the future) before the next input; with
a larger window it keeps that many in flight (the websocket pipelines like this). Everything queued
meanwhile goes into the same commit (group commit), so more threads and wider windows mean
bigger batches. Reported per configuration: inputs/s acknowledged (all threads), median and
p95 acknowledgement latency, inputs per commit (group commit at work), and PostgreSQL/SQLite
ratios.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from server.storage.postgres import PostgresStore  # noqa: E402
from server.storage.sqlite import SQLiteStore  # noqa: E402
from server.storage.store import InputRecord  # noqa: E402
from tests.support.postgres_cluster import PostgresCluster  # noqa: E402
from tests.support.synthetic import view  # noqa: E402


def _payloads() -> tuple[bytes, bytes]:
    import cv2

    odo = b'{"t":1.234567,"v":0.5,"omega":0.25,"dt":0.05}'
    frame = cv2.imencode(".jpg", view(1.0), [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes()
    return odo, frame


def run(store, threads: int, window: int, duration: float, tag: str) -> dict:
    odo, frame = _payloads()
    stop = threading.Event()
    lat: list[list[float]] = [[] for _ in range(threads)]
    counts = [0] * threads
    start_gate = threading.Barrier(threads + 1)

    def writer(i: int) -> None:
        sid = f"{tag}-{i}"
        inflight: deque = deque()
        seq = 0
        start_gate.wait()
        while not stop.is_set() or inflight:
            if not stop.is_set() and len(inflight) < window:
                kind, data = ("frame", frame) if seq % 5 == 4 else ("odometry", odo)
                inflight.append(
                    (time.perf_counter(), store.append_inputs(sid, [InputRecord(seq, kind, seq * 0.01, data)]))
                )
                seq += 1
                if len(inflight) < window:
                    continue
            t0, fut = inflight.popleft()
            fut.result(60)
            lat[i].append(time.perf_counter() - t0)
            counts[i] += 1

    ths = [threading.Thread(target=writer, args=(i,)) for i in range(threads)]
    for th in ths:
        th.start()
    start_gate.wait()
    t0 = time.perf_counter()
    time.sleep(duration)
    stop.set()
    for th in ths:
        th.join()
    elapsed = time.perf_counter() - t0
    all_lat = np.concatenate([np.asarray(x) for x in lat]) * 1e3
    return {
        "rate": sum(counts) / elapsed,
        "p50": float(np.median(all_lat)),
        "p95": float(np.percentile(all_lat, 95)),
        "n": sum(counts),
    }


def count_batches(store) -> list[int]:
    """Count the writer's transactions (one per batch) by wrapping the store's batch runner."""
    counter = [0]
    inner = store._run_batch

    def counted(*a):
        counter[0] += 1
        return inner(*a)

    store._run_batch = counted
    return counter


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=3.0, help="seconds per configuration")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 8], help="writer threads (sessions)")
    ap.add_argument("--window", type=int, nargs="+", default=[1, 32], help="inputs in flight per thread")
    ap.add_argument("--external", action="store_true", help="use $HIPPOMAP_TEST_POSTGRES_URL, not a private cluster")
    args = ap.parse_args()

    cluster = None
    if args.external:
        url = os.environ["HIPPOMAP_TEST_POSTGRES_URL"]
    else:
        cluster = PostgresCluster(fsync=True).start()
        url = cluster.url()
    tmp = tempfile.TemporaryDirectory(prefix="bench-store-")
    stores = {"sqlite": SQLiteStore(Path(tmp.name) / "bench.sqlite3"), "postgres": PostgresStore(url)}
    print(
        f"# bench_store: {args.duration:.0f} s per configuration; 4 odometry (~60 B) : 1 frame "
        f"({len(_payloads()[1]) / 1e3:.0f} kB JPEG); full durability; {os.cpu_count()} cores"
    )
    print(
        f"{'store':9s} {'threads':>7s} {'window':>6s} {'inputs/s':>9s} {'p50 ms':>7s} {'p95 ms':>7s} "
        f"{'inputs/commit':>13s}"
    )
    results: dict[tuple, dict] = {}
    batches = {name: count_batches(store) for name, store in stores.items()}
    try:
        for k, (threads, window) in enumerate([(t, w) for w in args.window for t in args.threads]):
            run(stores["sqlite"], threads, window, 0.3, f"warm{k}")  # warm-up (connections, caches)
            run(stores["postgres"], threads, window, 0.3, f"warm{k}")
            for name, store in stores.items():
                b0 = batches[name][0]
                r = run(store, threads, window, args.duration, f"t{threads}w{window}")
                per_commit = f"{r['n'] / max(1, batches[name][0] - b0):13.1f}"
                results[(name, threads, window)] = r
                print(
                    f"{name:9s} {threads:7d} {window:6d} {r['rate']:9.0f} {r['p50']:7.2f} {r['p95']:7.2f} "
                    f"{per_commit:>13s}",
                    flush=True,
                )
        print("\n# PostgreSQL / SQLite (inputs/s)")
        for (name, threads, window), r in results.items():
            if name == "postgres":
                base = results[("sqlite", threads, window)]["rate"]
                print(f"threads={threads} window={window}: {r['rate'] / base:.2f}x")
    finally:
        for s in stores.values():
            s.close()
        tmp.cleanup()
        if cluster is not None:
            cluster.stop()


if __name__ == "__main__":
    main()
