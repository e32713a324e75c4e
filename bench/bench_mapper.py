"""Whole-mapper cost per frame over a simulated run, and its map quality.

Renders the loop world (drifting odometry) at the given resolution, JPEG-encodes every
frame (as a robot would send it), then feeds odometry + frames to one Mapper and times:
JPEG decode (reported separately), and the mapper's work per frame (the frame's
``observe`` plus the odometry ``step`` that precedes it). Prints mean / p95 per frame,
the map's ATE against ground truth vs raw odometry, and the loop closures.

    python bench/bench_mapper.py                       # 640x480, key frame every 100 frames [S]
    python bench/bench_mapper.py --keyframe-interval 5 # a key frame per second at 5 Hz
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap import sim  # noqa: E402
from hippomap.config import HippomapConfig  # noqa: E402
from hippomap.eval.evaluation import trajectory_metrics  # noqa: E402
from hippomap.inputs import Frame, Odometry, decode_jpeg  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--keyframe-interval", type=int, default=100)
    ap.add_argument("--laps", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    world = sim.loop_world(seed=args.seed, laps=args.laps)
    run = sim.simulate(
        world,
        None,
        rate_hz=5.0,
        seed=args.seed,
        camera=sim.Camera(width=args.width, height=args.height),
        odometry_noise=sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01),
    )
    jpegs = [cv2.imencode(".jpg", run.frame(i), [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes() for i in range(len(run))]
    cfg = HippomapConfig.with_overrides({"mapper": {"keyframe_interval": args.keyframe_interval}})
    t0 = time.perf_counter()
    m = Mapper(cfg)
    m.pathway.localise()  # builds the grid cells' shared rate tables (once per geometry, not per frame)
    setup_s = time.perf_counter() - t0
    decode_ms, frame_ms = [], []
    for i in range(len(run)):
        t, v, w = run.odometry[i]
        t0 = time.perf_counter()
        img = decode_jpeg(jpegs[i])
        t1 = time.perf_counter()
        m.step(Odometry(float(t), v=float(v), omega=float(w)))
        m.observe(Frame(float(t), img))
        t2 = time.perf_counter()
        decode_ms.append((t1 - t0) * 1e3)
        frame_ms.append((t2 - t1) * 1e3)
    d, f = np.array(decode_ms), np.array(frame_ms)
    s = m.stats()
    print(
        f"{len(run)} frames at {args.width}x{args.height}, key frame every {args.keyframe_interval}: "
        f"{s['keyframes']} key frames, {s['nodes']} nodes, {s['recognitions']} recognitions"
    )
    print(f"set-up (Mapper + shared grid-cell tables, once): {setup_s:.2f} s")
    print(
        f"mapper per frame (odometry step + observe): mean {f.mean():.3f} ms, p95 {np.percentile(f, 95):.3f} ms, "
        f"max {f.max():.1f} ms"
    )
    print(f"JPEG decode per frame (excluded above):     mean {d.mean():.3f} ms, p95 {np.percentile(d, 95):.3f} ms")
    t = m.trajectory_times
    gt = (run.times, run.groundtruth)
    odo = trajectory_metrics(t, m.odometry_trajectory(), *gt)["ate"]["rmse"]
    cor = trajectory_metrics(t, m.corrected_trajectory(), *gt)["ate"]["rmse"]
    print(
        f"ATE rmse: odometry {odo:.3f} m, map {cor:.3f} m (ratio {cor / odo:.2f}); loop closures accepted "
        f"{s['loop_closures_accepted']}, rejected {s['loop_closures_rejected']}"
    )


if __name__ == "__main__":
    main()
