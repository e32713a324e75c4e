"""GTSAM as the map's exact solver, against hippomap's own, on the pose graphs a mapper really solves.

The map's exact correction (``map.solver: lsq``) is hippomap's own Gauss–Newton
(:func:`hippomap.least_squares.solve_lsq`), started headings first
(:func:`hippomap.headings_first.rotation_first_init`). GTSAM is the reference pose-graph library
(Pose2 between factors, Gauss–Newton, Levenberg–Marquardt, and iSAM2 for incremental solving), and
the question this bench answers is whether the map should hand its solves to it. One mapper (the
default config, or ``--config``) runs over a recorded run, and every *whole-map* solve it makes is
recorded: the poses before it, the links, their transforms and their information (robust weights
included). Then, CPU of this process (``time.process_time``) throughout:

1. **Batch.** Every ``--every``-th recorded solve is solved again from the same headings-first start
   by ``solve_lsq`` and by GTSAM's Gauss–Newton and Levenberg–Marquardt, each with the map's
   ``lsq_iterations`` as its iteration cap, on the same problem: the same diagonal information, no
   visual heading coupling and no odometry bias (GTSAM has no factor for either), the first node
   held. Printed per solve: CPU and the cost of each result under both objectives. The two
   libraries define a link's residual differently (hippomap: the position error in the source's
   frame and the wrapped heading error; GTSAM: the SE(2) logarithm of the error), so each reaches the
   lower cost under its own. Building GTSAM's graph in Python is timed apart and left out of its
   ratios.
2. **Incremental.** The last recorded graph is fed to iSAM2 (default parameters, or ``--relinearize``)
   node by node, each node with the links that end at it (:func:`incremental_batches`) and started where
   iSAM2's estimate of the node before and the odometric link between them put it, as a robot would; CPU
   per update, first third against last third, then extra updates until the estimate settles, and the
   cost of the result. Beside it, the CPU the map's own correction (``CognitiveMap``'s ``_optimise``: local
   and whole solves, robust reweighting) spent over the same run, by the map's node count at the time.

    python bench/bench_solvers.py SIM [--every 8] [--config FILE] [--skip-isam] [--relinearize SKIP THRESHOLD]

Needs ``gtsam`` (the ``bench`` extra: ``pip install -e ".[bench]"``).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.cli.run import dataset_config, open_dataset, run_dataset  # noqa: E402
from hippomap.config import HippomapConfig  # noqa: E402
from hippomap.headings_first import rotation_first_init  # noqa: E402
from hippomap.least_squares import graph_cost, solve_lsq  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402


@dataclass
class Problem:
    """One whole-map solve as the map posed it."""

    poses: np.ndarray  # (N, 3) before the solve
    src: np.ndarray
    dst: np.ndarray
    transforms: np.ndarray  # (M, 3)
    information: np.ndarray  # (M, 3) diagonals, robust weights included

    def cost(self, poses: np.ndarray) -> float:
        """The cost of ``poses`` under hippomap's objective (:func:`~hippomap.least_squares.graph_cost`)."""
        return graph_cost(poses, self.src, self.dst, self.transforms, information=self.information)

    def headings_first(self) -> tuple[np.ndarray, float]:
        """The recorded poses re-initialised headings first, as the map starts a whole solve, and the CPU
        seconds that took."""
        start = self.poses.copy()
        t = time.process_time()
        rotation_first_init(start, self.src, self.dst, self.transforms, information=self.information, anchor=0)
        return start, time.process_time() - t

    def solve(self, start: np.ndarray, iterations: int, tol: float) -> tuple[np.ndarray, float, int]:
        """hippomap's Gauss-Newton solve from ``start``: the poses, the CPU seconds and the linear solves."""
        q = start.copy()
        t = time.process_time()
        res = solve_lsq(q, self.src, self.dst, self.transforms, iterations, 0, tol, information=self.information)
        return q, time.process_time() - t, res.iterations


def incremental_batches(src: np.ndarray, dst: np.ndarray, n: int) -> list[np.ndarray]:
    """For each node k of ``n``, the links (indices, ascending) whose later end is k: what an incremental
    solver gets when node k is added. Node 0's batch holds the links between node 0 and itself (none in
    a map)."""
    later = np.maximum(np.asarray(src), np.asarray(dst))
    order = np.argsort(later, kind="stable")
    cuts = np.searchsorted(later[order], np.arange(n + 1))
    return [order[cuts[k] : cuts[k + 1]] for k in range(n)]


def record_run(sim: Path, config: HippomapConfig | None) -> tuple[list[Problem], list[tuple[int, float]]]:
    """Run one mapper over the recorded run ``sim``; returns its whole-map solves and, for every call of
    the map's correction, ``(nodes at the time, CPU seconds)``."""
    ds = open_dataset(sim)
    m = Mapper(dataset_config(ds, config or HippomapConfig()))
    cmap = m.cmap
    problems: list[Problem] = []
    calls: list[tuple[int, float]] = []
    whole, optimise = cmap._whole_solve, cmap._optimise

    def record_whole(P: np.ndarray, src: Any, dst: Any, tr: Any, info: Any, *args: Any, **kw: Any) -> Any:
        problems.append(Problem(P.copy(), src.copy(), dst.copy(), tr.copy(), info.copy()))
        return whole(P, src, dst, tr, info, *args, **kw)

    def timed(*args: Any, **kw: Any) -> Any:
        t = time.process_time()
        out = optimise(*args, **kw)
        calls.append((int(cmap._n), time.process_time() - t))
        return out

    # instance attributes shadow the methods of this map only (as bench_mapper_parts times its parts)
    cmap._whole_solve, cmap._optimise = record_whole, timed  # type: ignore[method-assign]
    run_dataset(ds, mapper=m)
    return problems, calls


def between(p: Problem, k: int) -> Any:
    """Link ``k`` of ``p`` as a GTSAM Pose2 between factor with the link's diagonal information."""
    import gtsam

    sigmas = 1.0 / np.sqrt(np.maximum(p.information[k], 1e-12))
    model = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    return gtsam.BetweenFactorPose2(int(p.src[k]), int(p.dst[k]), gtsam.Pose2(*p.transforms[k]), model)


def anchor(pose: np.ndarray) -> Any:
    """A tight prior holding node 0 at ``pose`` (the map's anchor)."""
    import gtsam

    return gtsam.PriorFactorPose2(0, gtsam.Pose2(*pose), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6)))


def gtsam_graph(p: Problem, poses: np.ndarray) -> tuple[Any, Any]:
    """GTSAM's factor graph of ``p`` (:func:`between` every link, :func:`anchor` node 0) and its values at
    ``poses``."""
    import gtsam

    g = gtsam.NonlinearFactorGraph()
    for k in range(len(p.src)):
        g.add(between(p, k))
    g.add(anchor(poses[0]))
    return g, to_values(poses)


def to_values(poses: np.ndarray) -> Any:
    import gtsam

    v = gtsam.Values()
    for i, q in enumerate(poses):
        v.insert(i, gtsam.Pose2(*q))
    return v


def from_values(v: Any, n: int) -> np.ndarray:
    return np.array([[v.atPose2(i).x(), v.atPose2(i).y(), v.atPose2(i).theta()] for i in range(n)])


def batch(problems: list[Problem], iterations: int, tol: float) -> list[dict[str, float]]:
    """Part 1: each problem from the same headings-first start, by ``solve_lsq`` and by GTSAM."""
    import gtsam

    rows = []
    for p in problems:
        start, init_s = p.headings_first()
        ours, ours_s, ours_iterations = p.solve(start, iterations, tol)
        row = {"nodes": len(start), "links": len(p.src), "init": init_s, "ours": ours_s}
        row["ours_iterations"] = ours_iterations
        t = time.process_time()
        g, v = gtsam_graph(p, start)
        row["build"] = time.process_time() - t
        results = {"ours": ours}
        for name, make in (
            ("gn", lambda: gtsam.GaussNewtonOptimizer(g, v, gn)),
            ("lm", lambda: gtsam.LevenbergMarquardtOptimizer(g, v, lm)),
        ):
            gn, lm = gtsam.GaussNewtonParams(), gtsam.LevenbergMarquardtParams()
            gn.setMaxIterations(iterations)
            lm.setMaxIterations(iterations)
            t = time.process_time()
            out = make().optimize()
            row[name] = time.process_time() - t
            results[name] = from_values(out, len(start))
        for name, q in results.items():
            row[f"cost_{name}"] = p.cost(q)
            row[f"gcost_{name}"] = float(g.error(to_values(q)))
        rows.append(row)
    return rows


def incremental(
    p: Problem, iterations: int, tol: float, settle: int = 20, relinearize: tuple[int, float] | None = None
) -> dict[str, Any]:
    """Part 2: ``p`` fed to iSAM2 node by node (CPU per update), then up to ``settle`` extra updates until
    no pose moves more than 1 mm; the result's cost beside a batch ``solve_lsq`` of the same graph.
    ``relinearize``: iSAM2's ``(relinearizeSkip, relinearizeThreshold)``, its defaults when None."""
    import gtsam

    n = len(p.poses)
    params = gtsam.ISAM2Params()
    if relinearize is not None:
        params.relinearizeSkip = int(relinearize[0])
        params.setRelinearizeThreshold(float(relinearize[1]))
    isam = gtsam.ISAM2(params)
    per = np.zeros(n)
    for k, links in enumerate(incremental_batches(p.src, p.dst, n)):
        g = gtsam.NonlinearFactorGraph()
        if k == 0:
            g.add(anchor(p.poses[0]))
        start = gtsam.Pose2(*p.poses[k])  # a node without an odometric link from k - 1: its recorded pose
        for j in links:
            g.add(between(p, int(j)))
            if p.src[j] == k - 1 and p.dst[j] == k:  # dead reckoning from iSAM2's estimate, as online
                start = isam.calculateEstimatePose2(k - 1).compose(gtsam.Pose2(*p.transforms[j]))
        v = gtsam.Values()
        v.insert(k, start)
        t = time.process_time()
        isam.update(g, v)
        per[k] = time.process_time() - t
    est = from_values(isam.calculateEstimate(), n)
    cost_fed = p.cost(est)
    extra, t = 0, time.process_time()
    for extra in range(1, settle + 1):  # noqa: B007 (the count is reported)
        isam.update()
        new = from_values(isam.calculateEstimate(), n)
        moved = float(np.max(np.hypot(*(new[:, :2] - est[:, :2]).T)))
        est = new
        if moved < 1e-3:
            break
    settle_s = time.process_time() - t
    start, init_s = p.headings_first()
    ours, ours_s, _ = p.solve(start, iterations, tol)
    return {
        "per": per,
        "cost_fed": cost_fed,
        "extra": extra,
        "settle": settle_s,
        "cost": p.cost(est),
        "ours_cost": p.cost(ours),
        "ours_s": init_s + ours_s,
    }


def thirds_by_node(nodes: np.ndarray, seconds: np.ndarray, n: int) -> tuple[float, float, float]:
    """Total CPU seconds, and those spent while the map had its first third / last third of ``n`` nodes."""
    first = seconds[nodes <= n / 3].sum()
    last = seconds[nodes > 2 * n / 3].sum()
    return float(seconds.sum()), float(first), float(last)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sim", type=Path, help="a recorded run (hippomap simulate --out SIM)")
    ap.add_argument("--config", help="a config file (JSON or YAML) for the mapper; default config otherwise")
    ap.add_argument("--every", type=int, default=8, help="solve again every k-th recorded whole solve")
    ap.add_argument("--skip-isam", action="store_true")
    ap.add_argument(
        "--relinearize",
        nargs=2,
        metavar=("SKIP", "THRESHOLD"),
        help="iSAM2's relinearizeSkip and relinearizeThreshold (its defaults otherwise: 10, 0.1)",
    )
    a = ap.parse_args(argv)
    try:
        import gtsam  # noqa: F401
    except ImportError:
        print('bench_solvers needs gtsam: pip install -e ".[bench]"', file=sys.stderr)
        return 2
    config = HippomapConfig.from_file(a.config) if a.config else None
    problems, calls = record_run(a.sim, config)
    mc = (config or HippomapConfig()).map
    print(f"{a.sim.name}: {len(problems)} whole-map solves recorded; CPU of this process")
    if not problems:
        return 0
    rows = batch(problems[:: max(1, a.every)], mc.lsq_iterations, mc.lsq_step_tolerance)
    print("\n1. batch, from the same headings-first start (ms; cost under hippomap's objective / GTSAM's)")
    head = f"{'nodes':>6} {'links':>6} {'init':>6} {'ours':>7} {'it':>3} {'GN':>7} {'LM':>7} {'build':>7}"
    print(head + "   cost ours / GN / LM")
    for r in rows:
        print(
            f"{r['nodes']:6d} {r['links']:6d} {r['init'] * 1e3:6.1f} {r['ours'] * 1e3:7.1f} {r['ours_iterations']:3d} "
            f"{r['gn'] * 1e3:7.1f} {r['lm'] * 1e3:7.1f} {r['build'] * 1e3:7.1f}   "
            f"{r['cost_ours']:.5g} / {r['cost_gn']:.5g} / {r['cost_lm']:.5g}   "
            f"(GTSAM's: {r['gcost_ours']:.5g} / {r['gcost_gn']:.5g} / {r['gcost_lm']:.5g})"
        )
    s = {k: sum(r[k] for r in rows) for k in ("ours", "gn", "lm", "build")}
    lowest = sum(r["cost_ours"] <= min(r["cost_gn"], r["cost_lm"]) * (1 + 1e-9) for r in rows)
    print(
        f"sum: ours {s['ours'] * 1e3:.0f} ms, GTSAM GN {s['gn'] * 1e3:.0f} ms ({s['gn'] / s['ours']:.2f} x), "
        f"LM {s['lm'] * 1e3:.0f} ms ({s['lm'] / s['ours']:.2f} x), graph building {s['build'] * 1e3:.0f} ms apart; "
        f"ours lowest under hippomap's objective in {lowest} of {len(rows)}"
    )
    nodes = np.array([c[0] for c in calls])
    secs = np.array([c[1] for c in calls])
    if not a.skip_isam:
        last = problems[-1]
        n = len(last.poses)
        relin = None if a.relinearize is None else (int(a.relinearize[0]), float(a.relinearize[1]))
        inc = incremental(last, mc.lsq_iterations, mc.lsq_step_tolerance, relinearize=relin)
        per = inc["per"]
        f, l3 = per[: n // 3].sum(), per[2 * n // 3 :].sum()
        print(f"\n2. incremental: the last graph ({n} nodes, {len(last.src)} links) fed to iSAM2 node by node")
        print(
            f"iSAM2: {per.sum():.2f} s in {n} updates (mean {per.mean() * 1e3:.2f} ms, p95 "
            f"{np.percentile(per, 95) * 1e3:.2f} ms); first third {f:.2f} s, last third {l3:.2f} s "
            f"({l3 / max(f, 1e-9):.1f} x); cost when fed {inc['cost_fed']:.5g}, after {inc['extra']} extra updates "
            f"({inc['settle']:.2f} s) {inc['cost']:.5g}; a batch solve of it by hippomap: {inc['ours_cost']:.5g} "
            f"in {inc['ours_s'] * 1e3:.0f} ms"
        )
        tot, f, l3 = thirds_by_node(nodes, secs, n)
        print(
            f"the map's own correction over the run: {tot:.2f} s in {len(calls)} calls; with its first third of "
            f"the nodes {f:.2f} s, its last third {l3:.2f} s ({l3 / max(f, 1e-9):.1f} x)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
