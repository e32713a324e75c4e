"""Cost of the spatial pathway (odometry -> grid cells -> place cells) per odometry step.

Drives ``SpatialPathway.step_velocity`` along a realistic 5 Hz trajectory at 0.5 m/s (10 cm per step, so
the 40 cm coding area is left — and the phases reset — every few steps) at the paper's scale
(40 cm x 40 cm, delta = 0.05 cm, 801 x 801 matrices, 32 cells). Prints:

* one-time setup: building the shared rate tables, and their memory;
* per-step cost (median, p95) of the fast iteration, in both iteration orders;
* the literal full-matrix iteration (``localise_literal``) on the first steps of the same trajectory, in
  the same run, with the speed-up ratios and a check that both give identical fields.

Run: ``python bench/bench_spatial.py [--steps 2000] [--literal-steps 150]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.config import SpatialConfig  # noqa: E402
from hippomap.grid_cells import GridCells  # noqa: E402
from hippomap.place_cells import localise_literal  # noqa: E402
from hippomap.spatial_pathway import SpatialPathway  # noqa: E402


class _Literal:
    """Drop-in for PlaceCells that runs the literal full-matrix product."""

    def __init__(self, grid: GridCells, cfg: SpatialConfig):
        self.grid, self.cfg, self.tables = grid, cfg, grid.tables

    def localise(self, T):
        return localise_literal(self.tables, T, self.cfg)


def trajectory(n: int, seed: int = 0, v: float = 0.5, rate_hz: float = 5.0):
    rng = np.random.default_rng(seed)
    omega = np.clip(np.cumsum(rng.normal(0, 0.15, n)), -1.0, 1.0)  # smooth turning, |omega| <= 1 rad/s
    speed = np.clip(v + rng.normal(0, 0.05, n), 0.0, None)
    return [(float(s), float(w), 1.0 / rate_hz) for s, w in zip(speed, omega)]


def run(cfg: SpatialConfig, traj, literal: bool = False):
    sp = SpatialPathway(cfg)
    sp.localise()  # tables built outside the timing
    if literal:
        sp.place_cells = _Literal(sp.grid, cfg)
    times, codes = np.empty(len(traj)), []
    for k, (v, w, dt) in enumerate(traj):
        t0 = time.perf_counter()
        codes.append(sp.step_velocity(v, w, dt))
        times[k] = time.perf_counter() - t0
    return times, codes, sp


def fmt(times) -> str:
    return f"median {np.median(times) * 1e3:7.3f} ms   p95 {np.percentile(times, 95) * 1e3:7.3f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--literal-steps", type=int, default=150)
    args = ap.parse_args()
    base = SpatialConfig()
    print(
        f"area {base.area_size_m * 100:.0f} cm x {base.area_size_m * 100:.0f} cm, "
        f"delta {base.resolution_m * 100} cm, {base.n_modules} modules x {base.cells_per_module} cells, "
        f"window {base.window}, T_s {base.variance_threshold_m2} m^2"
    )

    t0 = time.perf_counter()
    grid = GridCells(base)
    tables = grid.tables
    setup = time.perf_counter() - t0
    print(f"setup (rate matrices + argsort + histogram, once per config, shared): {setup:.2f} s")
    print(
        f"cached tables: {tables.nbytes / 1e6:.1f} MB = levels uint16 {tables.levels.nbytes / 1e6:.1f} MB "
        f"+ argsort int32 {tables.order.nbytes / 1e6:.1f} MB "
        f"+ level histogram int32 {tables.cum.nbytes / 1e6:.1f} MB "
        f"({tables.size}^2 x {tables.n_cells} cells)"
    )

    traj = trajectory(args.steps)
    n_lit = min(args.literal_steps, args.steps)
    print(f"trajectory: {args.steps} steps at 5 Hz, ~0.5 m/s")
    results = {}
    for order in ("narrowest_first", "cyclic"):
        cfg = base.model_copy(update={"iteration_order": order})
        times, codes, sp = run(cfg, traj)
        its = np.array([c.iterations for c in codes if c is not None])
        n_none = sum(c is None for c in codes)
        print(
            f"\nfast, order={order:15s} {fmt(times)}   "
            f"(first {n_lit} steps: median {np.median(times[:n_lit]) * 1e3:.3f} ms)"
        )
        print(f"   phase resets {sp.resets}, no-field steps {n_none}, iterations mean {its.mean():.2f} max {its.max()}")
        lt, lcodes, _ = run(cfg, traj[:n_lit], literal=True)
        same = all(
            (a is None and b is None)
            or (
                a is not None
                and b is not None
                and np.array_equal(a.field.indices, b.field.indices)
                and a.iterations == b.iterations
                and (a.x, a.y) == (b.x, b.y)
            )
            for a, b in zip(codes[:n_lit], lcodes)
        )
        print(f"literal, order={order:12s} {fmt(lt)}   over {n_lit} steps; identical outputs: {same}")
        results[order] = (times, lt)
    fast, lit_same = results["narrowest_first"][0], results["narrowest_first"][1]
    lit_paper = results["cyclic"][1]
    print(f"\nspeed-up of the default (fast, narrowest_first), medians over the same first {n_lit} steps:")
    print(f"   vs literal, same order:            x{np.median(lit_same) / np.median(fast[:n_lit]):.0f}")
    print(f"   vs literal, paper order (cyclic):  x{np.median(lit_paper) / np.median(fast[:n_lit]):.0f}")
    cyclic_ratio = np.median(lit_paper) / np.median(results["cyclic"][0][:n_lit])
    print(f"   fast cyclic vs literal cyclic:     x{cyclic_ratio:.0f}")


if __name__ == "__main__":
    main()
