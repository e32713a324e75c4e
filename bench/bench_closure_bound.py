"""How far a finished map is from what its closures, and every revisit, would allow.

A map's error has two sources: the loop links it made are a little off (each visual link carries the error
of its recognition's offset), and the stretches between closures keep the odometry's drift, which no
back-end can remove. This bench says how much of the final error each one is, so that work is aimed where
the error is. One mapper (the default config, or ``--config``) runs over a recorded run with ground truth;
then its final graph is solved again, whole, with the map's own weights and odometry heading bias, three ways:

* ``as is``: the graph unchanged (the check: it should read the map's own ATE);
* ``true links``: every loop link the map uses (weight >= ``USED_WEIGHT``) set to the ground-truth relative
  pose of its two nodes: what perfect offsets would give with the same closures;
* ``every revisit``: ``true links`` plus one true link from each node to the nearest node passed at least
  ``--revisit-path`` metres of path earlier within ``--revisit-m`` and ``--revisit-rad`` of it in ground truth:
  what a map that recognised every revisit, exactly, would give.

ATE here is the rmse of the map's node positions against ground truth at the nodes' times after an SE(2)
alignment (no scale), so it reads a little apart from the benchmark's per-frame ATE.

    python bench/bench_closure_bound.py SIM [SIM ...] [--config FILE]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.cli.run import dataset_config, open_dataset, run_dataset  # noqa: E402
from hippomap.config import HippomapConfig  # noqa: E402
from hippomap.eval.evaluation import groundtruth_at  # noqa: E402
from hippomap.geometry import between, path_lengths, wrap_angle  # noqa: E402
from hippomap.least_squares import solve_lsq  # noqa: E402
from hippomap.map_graph import LOOP  # noqa: E402
from hippomap.robust_kernel import USED_WEIGHT  # noqa: E402


def node_ate(P: np.ndarray, T: np.ndarray) -> float:
    """Rmse of positions ``P`` against ``T`` after the best rotation and translation (Umeyama, no scale)."""
    A, B = P[:, :2] - P[:, :2].mean(0), T[:, :2] - T[:, :2].mean(0)
    U, _, Vt = np.linalg.svd(A.T @ B)
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    E = A @ (Vt.T @ D @ U.T).T - B
    return float(np.sqrt((E**2).sum(1).mean()))


def revisit_pairs(T: np.ndarray, path: np.ndarray, within_m: float, within_rad: float, after_m: float):
    """For each node, the nearest node passed ``after_m`` or more of path earlier within ``within_m`` and
    ``within_rad`` of it in ground truth ``T``: (later, earlier) index arrays."""
    later, earlier = [], []
    for i in range(len(T)):  # once per node, offline: the bench's own loop, not the mapper's
        old = path[i] - path[:i] >= after_m
        d = np.hypot(T[:i, 0] - T[i, 0], T[:i, 1] - T[i, 1])
        dh = np.abs(wrap_angle(T[:i, 2] - T[i, 2]))
        ok = np.flatnonzero(old & (d < within_m) & (dh < within_rad))
        if ok.size:
            later.append(i)
            earlier.append(int(ok[np.argmin(d[ok])]))
    return np.asarray(later, np.int64), np.asarray(earlier, np.int64)


def bound(data: Path, config: str | None, args: argparse.Namespace) -> dict[str, float]:
    dataset = open_dataset(data)
    if dataset.groundtruth is None:
        raise SystemExit(f"{data}: no ground truth")
    cfg = dataset_config(dataset, HippomapConfig.from_file(config) if config else HippomapConfig())
    mapper, _ = run_dataset(dataset, cfg)
    cmap = mapper.cmap
    P = np.array(cmap.poses)
    T = np.array([groundtruth_at(dataset.groundtruth, float(t)) for t in cmap.times])
    links = cmap.links
    src, dst, tr = np.array(links["source"]), np.array(links["target"]), np.array(links["transform"])
    w = cmap.link_weights()
    info = cmap.link_information() * w[:, None]
    coupling = cmap.link_coupling()
    bias = cmap._bias_args()  # the map's own heading bias, held fixed in every solve below
    fixed_bias = {**bias, "estimate_bias": False} if bias else {}
    used = np.flatnonzero((np.asarray(links["kind_code"]) == LOOP) & (w >= USED_WEIGHT))

    def solve(s, d, t, i, c, extra: int = 0) -> float:
        Q = P.copy()
        b = {**fixed_bias, "bias_dt": np.append(fixed_bias["bias_dt"], np.zeros(extra))} if fixed_bias else {}
        solve_lsq(Q, s, d, t, iterations=args.iterations, information=i, coupling=c, **b)
        return node_ate(Q, T)

    true_tr = tr.copy()
    true_tr[used] = between(T[src[used]], T[dst[used]])
    path = path_lengths(T[:, :2])
    later, earlier = revisit_pairs(T, path, args.revisit_m, args.revisit_rad, args.revisit_path)
    visual = info[used].mean(0) if used.size else np.ones(3)  # a run that used no closure: unit information
    err = np.hypot(*(tr[used, :2] - true_tr[used, :2]).T)
    return {
        "nodes": len(P),
        "used loop links": len(used),
        "link error mean m": float(err.mean()) if used.size else float("nan"),
        "map": node_ate(P, T),
        "as is": solve(src, dst, tr, info, coupling),
        "true links": solve(src, dst, true_tr, info, coupling),
        "revisit links": len(later),
        "every revisit": solve(
            np.concatenate([src, later]),
            np.concatenate([dst, earlier]),
            np.vstack([true_tr, between(T[later], T[earlier])]),
            np.vstack([info, np.tile(visual, (len(later), 1))]),
            np.concatenate([coupling, np.zeros(len(later))]),
            extra=len(later),
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="recorded runs with ground truth (hippomap simulate --out)")
    ap.add_argument("--config", default=None, help="hippomap config file (default: the default config)")
    ap.add_argument("--iterations", type=int, default=30, help="Gauss-Newton iterations of each solve")
    ap.add_argument("--revisit-m", type=float, default=1.0, help="revisit: within this in ground truth (m)")
    ap.add_argument("--revisit-rad", type=float, default=0.8, help="... and facing within this (rad)")
    ap.add_argument("--revisit-path", type=float, default=30.0, help="... passed this much path earlier (m)")
    args = ap.parse_args()
    print("| run | nodes | used loop links (mean error m) | map ATE | as is | true links | every revisit (links) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for run in args.runs:
        r = bound(run, args.config, args)
        print(
            f"| {run.name} | {r['nodes']} | {r['used loop links']} ({r['link error mean m']:.2f}) | {r['map']:.3f} "
            f"| {r['as is']:.3f} | {r['true links']:.3f} | {r['every revisit']:.3f} ({r['revisit links']}) |",
            flush=True,
        )


if __name__ == "__main__":
    main()
