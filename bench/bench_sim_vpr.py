"""Place recognition on simulated runs: eval-vpr's protocol on sets the simulator renders, for choosing.

``hippomap eval-vpr`` scores the recognition memory on the two real image sets (rtabmap_samples,
corridor); those sets are what its figures are reported on, so a change of the recognition memory
must not be chosen on them. This bench builds sets of the same kind from rendered runs, as many as
wanted, with ground truth for every image: the first half of a run's path is the reference pass,
the second half the query pass.

* **References**: a frame every ``--ref-spacing`` metres of true path over the first half of the
  path (the key frames of a first pass).
* **Queries**: a frame every ``--query-spacing`` metres over the second half.
* **Positives** of a query: the references learned within ``--positive-m`` of its true position and
  facing within ``--positive-rad`` of its true heading. A query without one still counts.
* An accepted reference is *true* when it is a positive, *false* when it was learned more than 2 m from
  the query or facing more than 0.8 rad away (what the benchmarks call a false closure; the loop gate's
  heading radius), *near* otherwise (neither).

Every reference is learned, every query recognised against all of them (``candidates = None``, as
eval-vpr does; :func:`hippomap.eval.vpr_eval._run_ours`), with the visual config of ``--config`` (a
JSON file of :class:`~hippomap.config.VisualConfig` fields, or a full config with ``visual``) and
``--set KEY=VALUE`` overrides as eval-vpr reads them (:func:`hippomap.eval.vpr_eval.read_visual_config`),
over ``--memory-seeds`` seeds. Printed per set: references, queries with a positive, true, near and false
acceptances summed over the seeds, recall and the mean fixations per query; then the totals. Renders come
from :func:`bench_maps.simulate` (cached as there).

    python bench/bench_sim_vpr.py --worlds loop corridor figure8 grid hall bicocca --seeds 1 2 \\
        --textures procedural rtabmap [--set verify_saccades=1]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_maps import parse_size, simulate  # noqa: E402
from hippomap.cli.run import open_dataset  # noqa: E402
from hippomap.config import VisualConfig  # noqa: E402
from hippomap.eval.vpr_datasets import VPRDataset, read_image  # noqa: E402
from hippomap.eval.vpr_eval import _run_ours, read_visual_config  # noqa: E402
from hippomap.geometry import path_lengths, wrap_angle  # noqa: E402
from peers import cache_root  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
#: an accepted reference is false when learned further than this from the query (m; the benchmarks' false closure)
FALSE_M = 2.0
#: ... or facing further away than this (rad; the loop gate's heading radius)
FALSE_RAD = 0.8


def _spaced(path: np.ndarray, idx: np.ndarray, spacing: float) -> list[int]:
    """Of the frame indices ``idx`` (in time order), one every ``spacing`` metres of the true path ``path``."""
    out: list[int] = []
    last = -np.inf
    for i in idx.tolist():
        if path[i] - last >= spacing:
            out.append(i)
            last = path[i]
    return out


def build_set(
    folder: Path, ref_spacing: float, query_spacing: float, pos_m: float, pos_rad: float
) -> tuple[VPRDataset, np.ndarray]:
    """The references, queries and positives of the rendered run in ``folder`` (see the module docstring), and
    each query's true distance (m) and heading difference (rad) to every reference, shape (queries, refs, 2)."""
    dataset = open_dataset(folder)
    assert dataset.groundtruth is not None, f"{folder} has no ground truth"
    tg, pg = dataset.groundtruth
    t = np.array([f.t for f in dataset.frames])
    pose = np.column_stack([np.interp(t, tg, pg[:, k]) for k in (0, 1)])
    # headings: the first ground-truth row at or after the frame (the simulator writes one at every frame's time;
    # interpolating an angle across the wrap would be wrong)
    heading = pg[np.clip(np.searchsorted(tg, t), 0, len(tg) - 1), 2]
    path = path_lengths(pose)
    half = path[-1] / 2
    order = np.arange(len(t))
    refs = _spaced(path, order[path <= half], ref_spacing)
    queries = _spaced(path, order[path > half], query_spacing)
    d = np.hypot(pose[queries, None, 0] - pose[None, refs, 0], pose[queries, None, 1] - pose[None, refs, 1])
    a = np.abs(wrap_angle(heading[queries, None] - heading[None, refs]))
    positives = [set(np.flatnonzero(row).tolist()) for row in (d <= pos_m) & (a <= pos_rad)]
    protocol = f"references every {ref_spacing} m of the first half, queries every {query_spacing} m of the second"
    files = [Path(f.path) for f in dataset.frames]  # a folder's frames are files on disk (FrameRef)
    ds = VPRDataset(folder.name, [files[i] for i in refs], [files[i] for i in queries], positives, protocol)
    return ds, np.stack([d, a], axis=-1)


def score(ds: VPRDataset, truth: np.ndarray, cfg: VisualConfig, seeds: int) -> dict[str, Any]:
    """True and false positives of ``seeds`` memories (seeds ``cfg.seed``, ``cfg.seed + 1``, ...) on ``ds``: an
    accepted reference is true when it is a positive, false when it was learned more than ``FALSE_M`` from the
    query or facing more than ``FALSE_RAD`` away (``truth``, from :func:`build_set`), near otherwise."""
    refs = [read_image(p) for p in ds.references]
    queries = [read_image(p) for p in ds.queries]
    runs = [_run_ours(cfg.model_copy(update={"seed": cfg.seed + s}), ds, refs, queries) for s in range(seeds)]
    rows = [(q, row["reference"]) for r in runs for q, row in enumerate(r["rows"]) if row["reference"] is not None]
    tp = sum(ref in ds.positives[q] for q, ref in rows)
    fp = sum(bool(truth[q, ref, 0] > FALSE_M or truth[q, ref, 1] > FALSE_RAD) for q, ref in rows)
    fix = [row["fixations"] for r in runs for row in r["rows"]]
    n_pos = sum(1 for p in ds.positives if p) * seeds
    return {
        "refs": len(refs),
        "with_positive": n_pos,
        "tp": tp,
        "near": len(rows) - tp - fp,
        "fp": fp,
        "fixations": float(np.mean(fix)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", nargs="+", default=["loop", "corridor", "figure8", "grid", "hall", "bicocca"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--sizes", nargs="+", type=parse_size, default=[(320, 240)])
    ap.add_argument("--textures", nargs="+", default=["procedural", "rtabmap"])
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    ap.add_argument("--config", default=None, help="JSON: VisualConfig fields, or a full config with 'visual'")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE", help="repeatable")
    ap.add_argument("--memory-seeds", type=int, default=2, help="recognition memories per set (seeds 0, 1, ...)")
    ap.add_argument("--ref-spacing", type=float, default=1.0, help="metres of path between references")
    ap.add_argument("--query-spacing", type=float, default=2.0, help="metres of path between queries")
    ap.add_argument("--positive-m", type=float, default=1.0, help="a positive is learned within this of the query")
    ap.add_argument("--positive-rad", type=float, default=0.35, help="... and facing within this of its heading")
    args = ap.parse_args(argv)
    cfg = read_visual_config(args.config, args.sets)
    print(f"{'set':48s} {'refs':>5s} {'pos':>5s} {'TP':>5s} {'near':>4s} {'FP':>4s} {'recall':>7s} {'fix':>5s}")
    tot = {"with_positive": 0, "tp": 0, "near": 0, "fp": 0}
    fixations = 0.0
    for world, seed, size, texture in itertools.product(args.worlds, args.seeds, args.sizes, args.textures):
        folder, _ = simulate(world, seed, size, texture, args.shared, None, cache_root())
        ds, truth = build_set(folder, args.ref_spacing, args.query_spacing, args.positive_m, args.positive_rad)
        r = score(ds, truth, cfg, args.memory_seeds)
        for key in tot:
            tot[key] += r[key]
        fixations += r["fixations"] * len(ds.queries) * args.memory_seeds
        rec = r["tp"] / r["with_positive"] if r["with_positive"] else float("nan")
        counts = f"{r['refs']:5d} {r['with_positive']:5d} {r['tp']:5d} {r['near']:4d} {r['fp']:4d}"
        print(f"{folder.name.rsplit('-', 1)[0]:48s} {counts} {rec:7.3f} {r['fixations']:5.1f}", flush=True)
    print(
        f"total: {tot['tp']} of {tot['with_positive']} queries with a positive recognised (recall "
        f"{tot['tp'] / max(1, tot['with_positive']):.3f}), {tot['near']} near, {tot['fp']} false "
        f"(> {FALSE_M:g} m or > {FALSE_RAD:g} rad); {fixations:.0f} fixations"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
