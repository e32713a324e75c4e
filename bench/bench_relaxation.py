"""Benchmark of map relaxation (hippomap.relaxation) and of the cognitive map's per-step cost.

Run: ``python bench/bench_relaxation.py`` (``--quick`` for a short run). Prints

1. the cost of ONE full sweep (every link visited once) at 1k / 10k / 100k nodes, for the
   vectorised [ORS] relaxation (``relax``, by edge colour) and the degree-normalised Jacobi
   Eq. 14 (``relax_jacobi``), median and p95, with the literal [ORS] Python loop as the
   reference at 1k / 10k (ratio = reference / vectorised, same run);
2. the Gauss-Newton pose-graph solver (``solve_lsq``) at the same sizes;
3. convergence on a 500-node loop with a heading bias: sweeps (or iterations) needed to bring
   the map error down to 10 % and 1 % of the open-loop error;
4. the cognitive map's cost per ``update()`` on a long synthetic run.

Graphs: a chain of N nodes wandering in a bounded area plus N/50 loop links between nodes that
are close in space and far apart in time (see ``chain_with_loops``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.cognitive_map import CognitiveMap, LoopHypothesis  # noqa: E402
from hippomap.config import MapConfig  # noqa: E402
from hippomap.geometry import between, compose, integrate  # noqa: E402
from hippomap.least_squares import solve_lsq  # noqa: E402
from hippomap.relaxation import (  # noqa: E402
    ColourGroups,
    edge_colouring,
    relax,
    relax_jacobi,
    relax_ors_reference,
)
from timing import timings  # noqa: E402


def chain_with_loops(n: int, seed: int = 0):
    """A robot-like graph: a chain of N nodes ~0.25 m apart wandering in a square area sized so
    that the path crosses itself, plus N/50 loop links between nodes < 1 m apart in space and
    > 100 nodes apart in time. Transforms are true + noise (1 cm, 0.002 rad: wheel odometry over
    0.25 m); start poses true + noise (a warm start, as the map's incremental solves have)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    side = 3.0 * np.sqrt(n)  # about one path length per 9 m^2: many crossings
    turn = np.cumsum(rng.normal(0, 0.05, n))  # smoothly varying heading rate
    th = np.cumsum(0.1 * np.sin(turn) + rng.normal(0, 0.02, n))
    xy = np.cumsum(0.25 * np.column_stack([np.cos(th), np.sin(th)]), axis=0)
    xy = np.abs((xy + side) % (2 * side) - side)  # fold (reflect) into [0, side]^2
    true = np.column_stack([xy, th])
    pairs = np.array(sorted(cKDTree(xy).query_pairs(1.0)), dtype=np.int64).reshape(-1, 2)
    pairs = pairs[np.abs(pairs[:, 0] - pairs[:, 1]) > 100]
    k = min(len(pairs), max(1, n // 50))
    pick = pairs[rng.choice(len(pairs), k, replace=False)] if len(pairs) else np.zeros((0, 2), np.int64)
    src = np.concatenate([np.arange(n - 1), pick[:, 1]])
    dst = np.concatenate([np.arange(1, n), pick[:, 0]])
    T = between(true[src], true[dst]) + rng.normal(0, 1, (len(src), 3)) * [0.01, 0.01, 0.002]
    start = true + rng.normal(0, 1, true.shape) * [0.05, 0.05, 0.01]
    return start, src, dst, T


def ms(a: np.ndarray) -> str:
    return f"median {np.median(a) * 1e3:8.2f} ms  p95 {np.percentile(a, 95) * 1e3:8.2f} ms"


def sweep_costs(sizes, repeats):
    print("1. one full sweep (all links once)")
    for n in sizes:
        P0, src, dst, T = chain_with_loops(n)
        colours = edge_colouring(src, dst, n)
        groups = ColourGroups(src, dst, T, colours, n)
        P = P0.copy()
        t_relax = timings(lambda: relax(P, src, dst, T, 1, groups=groups), repeats)
        t_groups = timings(lambda: ColourGroups(src, dst, T, colours, n, check=False), max(3, repeats // 4))
        P = P0.copy()
        t_jac = timings(lambda: relax_jacobi(P, src, dst, T, 1), repeats)
        print(f"  N={n:>7,} nodes, {len(src):>7,} links, {colours.max() + 1} colours")
        print(
            f"    relax (vectorised ORS)   {ms(t_relax)}   (+ grouping by colour once per change: "
            f"{np.median(t_groups) * 1e3:.2f} ms)"
        )
        print(f"    relax_jacobi             {ms(t_jac)}")
        if n <= 10_000:
            P = P0.copy()
            t_ref = timings(lambda: relax_ors_reference(P, src, dst, T, 1), max(3, repeats // 5))
            print(
                f"    ORS reference (Python)   {ms(t_ref)}   "
                f"ratio ref/relax {np.median(t_ref) / np.median(t_relax):6.1f}x"
                f"   ref/jacobi {np.median(t_ref) / np.median(t_jac):6.1f}x"
            )


def lsq_costs(sizes, repeats):
    print("2. Gauss-Newton pose-graph solve (solve_lsq, to convergence, from noisy poses)")
    for n in sizes:
        P0, src, dst, T = chain_with_loops(n)
        its = []

        def run():
            P = P0.copy()
            its.append(solve_lsq(P, src, dst, T, iterations=10).iterations)

        t = timings(run, repeats if n < 100_000 else max(2, repeats // 5))
        print(
            f"  N={n:>7,} nodes, {len(src):>7,} links: {ms(t)}   GN iterations {int(np.median(its))}"
            f"   per iteration {np.median(t) / np.median(its) * 1e3:.1f} ms"
        )


def convergence(n=500, bias=0.001, cap=100_000, ors_cap=20_000):
    print(f"3. convergence on a {n}-node loop (heading bias {bias} rad/link, closing link exact)")
    ang = 2 * np.pi / n
    step = 2 * 10.0 * np.sin(ang / 2)
    inc = np.tile([step, 0, ang], (n, 1))
    gt = integrate(inc[:-1])
    noisy = inc.copy()
    noisy[:, 2] += bias
    odo = integrate(noisy[:-1])
    src = np.append(np.arange(n - 1), n - 1)
    dst = np.append(np.arange(1, n), 0)
    T = np.vstack([noisy[:-1], between(gt[-1], gt[0])])

    def err(P):
        Q = between(P[0], P)  # seen from node 0 (gauge-free)
        G = between(gt[0], gt)
        return float(np.sqrt(np.mean(np.sum((Q[:, :2] - G[:, :2]) ** 2, axis=1))))

    e0 = err(odo)
    Pl = odo.copy()
    r = solve_lsq(Pl, src, dst, T)
    print(f"  open-loop error {e0:.3f} m; lsq: {r.iterations} iterations -> {err(Pl):.4f} m (the floor)")
    floor = err(Pl)
    for name, fn, limit in (
        ("relax", lambda P, k: relax(P, src, dst, T, k, anchor=None), cap),
        ("relax_jacobi", lambda P, k: relax_jacobi(P, src, dst, T, k, anchor=None), cap),
        ("ORS reference", lambda P, k: relax_ors_reference(P, src, dst, T, k), ors_cap),
    ):
        P = odo.copy()
        done, marks, chunk = 0, {}, 10
        t0 = time.perf_counter()
        while done < limit and len(marks) < 2:
            fn(P, chunk)
            done += chunk
            e = err(P)
            for frac in (0.1, 0.01):
                if frac not in marks and e - floor <= frac * (e0 - floor):
                    marks[frac] = done
            chunk = min(chunk * 2, 2000)
        sec = time.perf_counter() - t0
        fmt = lambda f: f"{marks[f]:>7,}" if f in marks else f">{done:,}"  # noqa: E731
        print(f"  {name:14s} sweeps to 10 %: {fmt(0.1)}   to 1 %: {fmt(0.01)}   ({sec:.1f} s)")


def map_update_cost(steps: int):
    print(f"4. CognitiveMap.update(), {steps:,} steps of 0.1 m on a figure-of-eight-ish loop, with loop proposals")
    rng = np.random.default_rng(1)
    turn = np.where((np.arange(steps) // 400) % 2 == 0, 2 * np.pi / 400, -2 * np.pi / 400)
    inc = np.column_stack([np.full(steps, 0.1), np.zeros(steps), turn + rng.normal(0, 0.002, steps)])
    gt_inc = inc.copy()
    gt_inc[:, 2] = turn
    gt = integrate(gt_inc)
    odo = integrate(inc)
    for solver in ("relax", "jacobi", "lsq"):
        cm = CognitiveMap(MapConfig(solver=solver, prune_online=False))
        node_at, off = [0], [np.zeros(3)]
        t = []
        for k in range(1, steps + 1):
            t0 = time.perf_counter()
            cm.update(odo[k], inc[k - 1], float(k))
            if k > 800 and k % 10 == 0:
                j = k - 800  # the same place one figure-of-eight earlier
                rel = compose(compose(cm.robot_offset, between(gt[k], gt[j])), between(off[j], np.zeros(3)))
                cm.propose_loop(LoopHypothesis(node=int(node_at[j]), transform=tuple(rel), source="bench"))
            t.append(time.perf_counter() - t0)
            node_at.append(cm.current)
            off.append(cm.robot_offset)
        t = np.array(t)
        acc = sum(d.status == "accepted" for d in cm.loop_decisions)
        print(
            f"  solver={solver:6s} {cm.node_count:,} nodes {cm.link_count:,} links, {acc} loops accepted: "
            f"per step median {np.median(t) * 1e6:.0f} us  p95 {np.percentile(t, 95) * 1e6:.0f} us  "
            f"max {t.max() * 1e3:.1f} ms  total {t.sum():.2f} s"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smaller sizes and fewer repeats")
    args = ap.parse_args()
    sizes = [1_000, 10_000] if args.quick else [1_000, 10_000, 100_000]
    repeats = 5 if args.quick else 30
    print(f"numpy {np.__version__}")
    sweep_costs(sizes, repeats)
    lsq_costs(sizes, max(3, repeats // 3))
    convergence(cap=20_000 if args.quick else 100_000, ors_cap=2_000 if args.quick else 20_000)
    map_update_cost(4_000 if args.quick else 20_000)


if __name__ == "__main__":
    main()
