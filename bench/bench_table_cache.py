"""The grid-cell table cache (``HIPPOMAP_TABLE_CACHE``, the server's ``table_cache``): what a new mapper
process pays for its tables with and without it, measured in the same run.

    python bench/bench_table_cache.py [--repeats 5] [--sessions 4] [--skip-ray]

1. **A new process's tables** (the default config: 32 cells of 801 x 801). Fresh Python processes, one
   after the other, alternating "no cache" and "cache" (the cache folder written beforehand): CPU seconds
   of ``GridCells(...).tables`` (the imports are not timed) and the process's anonymous memory afterwards
   (``Anonymous`` of ``/proc/self/smaps_rollup``: the pages no file backs, which each process holds for
   itself; a mapped file's pages are the page cache's, one copy for every process that maps it).
2. **A session on the Ray backend**, where every session is a new actor process. Two servers join one
   private Ray head, one with ``table_cache`` off and one with a cache folder (written by a session made
   before the clock starts); sessions are made on them in turn. Timed: from ``POST /sessions`` to the
   session's first odometry reading processed (the actor has started, built or read its tables and
   mapped the reading); and the actor's anonymous memory then.

Medians, and the ratio cache / no cache of each.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hippomap.grid_cells import TABLE_CACHE_ENV as ENV  # noqa: E402
from tests.support.live import LiveServer, anonymous_bytes  # noqa: E402

CHILD = """
import json, sys, time
from hippomap.config import SpatialConfig
from hippomap.grid_cells import GridCells
t = time.process_time()
GridCells(SpatialConfig()).tables
cpu = time.process_time() - t
print(json.dumps({"cpu_s": cpu, "anonymous_mb": __import__("bench_table_cache").anonymous_mb(None)}))
"""


def anonymous_mb(pid: int | None) -> float:
    """:func:`tests.support.live.anonymous_bytes` of process ``pid`` (None: this one), in MB."""
    return anonymous_bytes(pid) / 2**20


def one_process(cache: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != ENV}
    if cache:
        env[ENV] = cache
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "bench"), env.get("PYTHONPATH", "")])
    r = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, env=env, check=True)
    import json

    return json.loads(r.stdout.strip().splitlines()[-1])


def line(name: str, off: list[float], on: list[float], unit: str) -> None:
    a, b = statistics.median(off), statistics.median(on)
    print(f"{name}: no cache {a:.2f} {unit}, cache {b:.2f} {unit}, ratio {b / a:.3f}  (medians of {len(off)})")


def processes(repeats: int, folder: str) -> None:
    one_process(folder)  # writes the cache
    rows: dict[str, list[dict]] = {"off": [], "on": []}
    for i in range(repeats):
        for key in ("off", "on") if i % 2 == 0 else ("on", "off"):
            rows[key].append(one_process(folder if key == "on" else None))
    print("\n1. a new process's tables (default config)")
    line("  CPU", [r["cpu_s"] for r in rows["off"]], [r["cpu_s"] for r in rows["on"]], "s")
    line("  anonymous memory", [r["anonymous_mb"] for r in rows["off"]], [r["anonymous_mb"] for r in rows["on"]], "MB")


def ray_sessions(sessions: int, folder: str, tmp: Path) -> None:
    from tests.support.ray_head import LocalRayHead

    head = LocalRayHead().start()
    try:
        env = {"HIPPOMAP_RAY_ADDRESS": head.address, **head.env}
        servers = {
            "off": LiveServer(tmp / "off", env={**env, ENV: "off"}, args=["--backend", "ray"]).start(),
            "on": LiveServer(tmp / "on", env={**env, ENV: folder}, args=["--backend", "ray"]).start(),
        }
        clients = {k: s.client() for k, s in servers.items()}
        times: dict[str, list[float]] = {"off": [], "on": []}
        memory: dict[str, list[float]] = {"off": [], "on": []}

        def session(key: str, name: str) -> tuple[float, float]:
            c = clients[key]
            t = time.perf_counter()
            sid = c.create_session(name, {})["id"]
            c.send_odometry(sid, [{"t": 0.0, "v": 0.2, "omega": 0.0}])
            stats = c.wait_processed(sid)
            dt = time.perf_counter() - t
            mb = anonymous_mb(int(stats["backend"]["pid"]))
            c.delete_session(sid)
            return dt, mb

        session("on", "warm-up")  # writes the cache folder
        for i in range(sessions):
            for key in ("off", "on") if i % 2 == 0 else ("on", "off"):
                dt, mb = session(key, f"{key}-{i}")
                times[key].append(dt)
                memory[key].append(mb)
        print(f"\n2. a session on the Ray backend (a new actor each, {sessions} per server)")
        line("  POST /sessions to the first reading processed", times["off"], times["on"], "s")
        line("  the actor's anonymous memory", memory["off"], memory["on"], "MB")
        for c in clients.values():
            c.close()
        for s in servers.values():
            s.stop()
    finally:
        head.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5, help="fresh processes per kind (default 5)")
    ap.add_argument("--sessions", type=int, default=4, help="Ray sessions per server (default 4)")
    ap.add_argument("--skip-ray", action="store_true", help="only the fresh processes")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-table-cache-") as tmp:
        folder = str(Path(tmp) / "tables")
        processes(a.repeats, folder)
        if not a.skip_ray:
            ray_sessions(a.sessions, folder, Path(tmp))


if __name__ == "__main__":
    main()
