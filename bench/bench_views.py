"""Cost of the readable-viewer features, against the work they sit beside (measured in one run).

* Place cells made visible: recording the iteration at the current pose
  (``SpatialPathway.record``, done only on request) against one step's ``localise`` (the hot
  path, unchanged), and drawing the Fig. 8 figure (side panel and the PNG endpoint's layout).
* Time slider: cutting a 50k-node map back in time (``web.scene.replay.replay_at``) against
  copying the map's snapshot arrays (what every viewer update already does).
* Camera fit: ``web.scene.camera_fit.fit_camera`` per call.

    .venv/bin/python bench/bench_views.py [--nodes 50000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.cognitive_map import LINK_KINDS  # noqa: E402
from hippomap.config import SpatialConfig  # noqa: E402
from hippomap.spatial_pathway import SpatialPathway  # noqa: E402
from hippomap.viz.place_field_figure import place_field_figure  # noqa: E402
from timing import timings  # noqa: E402
from web.scene.camera_fit import fit_camera  # noqa: E402
from web.scene.replay import replay_at  # noqa: E402
from web.snapshot import MapSnapshot  # noqa: E402


def _best(fn, repeat: int) -> float:
    return float(timings(fn, repeat).min())


def _synthetic_map(n: int, rng: np.random.Generator) -> tuple[MapSnapshot, np.ndarray]:
    """A long corridor run: n nodes along laps of a 200 m x 120 m loop, odometry links in order plus
    5 % loop links, and a trajectory sampled every 5 cm."""
    s = np.linspace(0, 1, n) * 40
    ang = 2 * math.pi * s
    poses = np.column_stack([100 * np.cos(ang), 60 * np.sin(ang), ang + math.pi / 2]) + rng.normal(0, 0.3, (n, 3))
    src = np.r_[np.arange(n - 1), rng.integers(0, n, n // 20)]
    dst = np.r_[np.arange(1, n), rng.integers(0, n, n // 20)]
    kind = np.r_[np.zeros(n - 1, np.int8), np.full(n // 20, list(LINK_KINDS).index("loop"), np.int8)]
    k = 10 * n
    rows = np.zeros((k, 8))
    rows[:, 0] = np.linspace(0, 3600, k)
    rows[:, 4] = np.minimum(np.arange(k) // 10, n - 1)
    rows[:, 1:4] = poses[rows[:, 4].astype(int)]
    snap = MapSnapshot(
        node_poses=poses,
        node_frames=np.where(np.arange(n) % 7 == 0, np.arange(n), -1),
        link_source=src,
        link_target=dst,
        link_kind=kind,
        link_weight=np.ones(len(src)),
        trajectory_start=0,
        trajectory=rows[:0],
        trajectory_total=k,
        current_node=n - 1,
        robot_pose=poses[-1],
        decisions=(),
        loop_weights=np.zeros(0),
        recognition_count=0,
        last_recognition=None,
        place_field=None,
        stats={},
    )
    return snap, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", type=int, default=50000)
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args()
    rng = np.random.default_rng(0)

    p = SpatialPathway(SpatialConfig())
    _ = p.place_cells.tables  # build the shared tables once (not measured)
    for _ in range(3):
        p.step_increment(0.02, 0.01, 0.05)
    T = p.discharges()
    t_localise = _best(lambda: p.place_cells.localise(T), 20 * a.repeat)
    t_record = _best(p.record, a.repeat)
    rec = p.record()
    place_field_figure(rec, vertical=True, dpi=80, max_steps=6)  # warm matplotlib up
    t_panel = _best(lambda: place_field_figure(rec, vertical=True, dpi=80, max_steps=6), a.repeat)
    t_png = _best(lambda: place_field_figure(rec), a.repeat)
    print(f"place cells ({len(rec.applied)} products at the defaults: 32 cells, 801 x 801):")
    print(f"  localise (hot path, per step)     {1e3 * t_localise:8.2f} ms")
    print(f"  record (on request)               {1e3 * t_record:8.2f} ms   = {t_record / t_localise:6.1f} x localise")
    print(f"  Fig. 8 figure, viewer side panel  {1e3 * t_panel:8.1f} ms")
    print(f"  Fig. 8 figure, PNG endpoint       {1e3 * t_png:8.1f} ms")

    snap, rows = _synthetic_map(a.nodes, rng)
    t_copy = _best(
        lambda: (
            snap.node_poses.copy(),
            snap.link_source.copy(),
            snap.link_target.copy(),
            snap.link_kind.copy(),
            rows.copy(),
        ),
        a.repeat,
    )
    t_replay = _best(lambda: replay_at(snap, rows, None, 1800.0), a.repeat)
    fr = replay_at(snap, rows, None, 1800.0)
    print(f"time slider on a {a.nodes}-node map ({len(snap.link_source)} links, {len(rows)} trajectory samples):")
    print(f"  snapshot-size array copy          {1e3 * t_copy:8.2f} ms")
    print(
        f"  replay_at(half the run)           {1e3 * t_replay:8.2f} ms   = {t_replay / t_copy:6.1f} x the copy"
        f"   ({fr.n_nodes} nodes, {len(fr.links) + len(fr.loop_links)} links)"
    )
    lo, hi = snap.node_poses[:, :2].min(0), snap.node_poses[:, :2].max(0)
    t_fit = _best(lambda: fit_camera(lo, hi, math.radians(75), 1.6, 1.15, 0.3, covered_left=0.2), 20 * a.repeat)
    print(f"camera fit                          {1e3 * t_fit:8.3f} ms")


if __name__ == "__main__":
    main()
