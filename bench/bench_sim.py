"""Camera-simulator speed: render time per frame (median, p95) at 320x240 and 640x480
on the loop world and on the Bicocca world (walls built around the real ground-truth
path), with the Bicocca grid-accelerated ray caster compared against brute force
(every wall segment for every column) in the same run.

    python bench/bench_sim.py [--data ../shared/data/bicocca25b] [--frames 300]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap import sim  # noqa: E402
from hippomap.sim.world import World  # noqa: E402


def time_frames(world, poses, camera, repeat=1):
    out = []
    sim.render(world, poses[0], camera)  # warm caches
    for _ in range(repeat):
        for p in poses:
            t0 = time.perf_counter()
            sim.render(world, p, camera)
            out.append(time.perf_counter() - t0)
    return np.array(out) * 1000.0


def line(name, ms):
    print(f"  {name:<44s} median {np.median(ms):7.2f} ms   p95 {np.percentile(ms, 95):7.2f} ms   ({len(ms)} frames)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default = Path(__file__).resolve().parents[2] / "shared" / "data" / "bicocca25b"
    ap.add_argument("--data", type=Path, default=default, help="Bicocca 25b folder (default %(default)s)")
    ap.add_argument("--frames", type=int, default=300, help="poses rendered per case")
    args = ap.parse_args(argv)
    cams = {"320x240": sim.Camera(), "640x480": sim.Camera(width=640, height=480)}

    t0 = time.perf_counter()
    loop = sim.loop_world(seed=0)
    t_world = time.perf_counter() - t0
    t0 = time.perf_counter()
    run = sim.simulate(loop, rate_hz=5.0, odometry_noise=sim.OdometryNoise())
    t_sim = time.perf_counter() - t0
    poses = run.groundtruth[np.linspace(0, len(run) - 1, args.frames).astype(int)]
    print(
        f"loop world: {len(loop.segments)} wall segments, texture {loop.atlas.shape[1]} texels long; "
        f"build {t_world * 1000:.0f} ms, simulate {len(run)} steps {t_sim * 1000:.0f} ms"
    )
    for name, cam in cams.items():
        line(f"loop {name}", time_frames(loop, poses, cam))

    with tempfile.TemporaryDirectory() as tmp:
        short = sim.simulate(loop, rate_hz=5.0, frame_every=len(run) // 100 or 1, odometry_noise=sim.OdometryNoise())
        t0 = time.perf_counter()
        short.write(tmp)
        dt = time.perf_counter() - t0
        print(
            f"  write(): {short.n_frames} PNG frames 320x240 + csv in {dt * 1000:.0f} ms "
            f"({dt / short.n_frames * 1000:.2f} ms/frame incl. rendering)"
        )

    if not args.data.is_dir():
        print(f"Bicocca folder {args.data} not found: Bicocca figures skipped")
        return 0
    t0 = time.perf_counter()
    bic = sim.bicocca_world(args.data)
    t_world = time.perf_counter() - t0
    traj = bic.route
    print(
        f"Bicocca world: {len(bic.segments)} wall segments around {len(traj)} ground-truth poses, "
        f"texture {bic.atlas.shape[1]} texels long, grid {bic.grid.shape}; build {t_world * 1000:.0f} ms"
    )
    t0 = time.perf_counter()
    brun = sim.simulate(bic, odometry_noise=sim.OdometryNoise())
    print(
        f"  simulate(): {len(brun)} steps, {brun.n_frames} frames (lazy) in {(time.perf_counter() - t0) * 1000:.0f} ms"
    )
    poses = traj.poses[np.linspace(0, len(traj) - 1, args.frames).astype(int)]
    brute = World(bic.name, bic.segments, bic.u0, bic.atlas, bic.texture)
    brute.grid = None
    for name, cam in cams.items():
        g = time_frames(bic, poses, cam)
        b = time_frames(brute, poses, cam)
        line(f"Bicocca {name} (segment grid)", g)
        line(f"Bicocca {name} (brute force, reference)", b)
        print(f"  {'':<44s} grid / brute median ratio {np.median(g) / np.median(b):.2f}")
    # a denser wall set (finer simplification): where the grid matters
    dense_polys = sim.walls_around_path(traj.poses[:, :2], simplify_m=0.02)
    dense = World.from_polylines(dense_polys, seed=0)
    dense_brute = World(dense.name, dense.segments, dense.u0, dense.atlas, dense.texture)
    dense_brute.grid = None
    cam = cams["320x240"]
    g = time_frames(dense, poses, cam)
    b = time_frames(dense_brute, poses, cam)
    print(f"Bicocca walls simplified to 2 cm: {len(dense.segments)} segments")
    line("Bicocca-dense 320x240 (segment grid)", g)
    line("Bicocca-dense 320x240 (brute force, reference)", b)
    print(f"  {'':<44s} grid / brute median ratio {np.median(g) / np.median(b):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
