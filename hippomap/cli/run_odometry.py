"""Offline run of the spatial pathway and the cognitive map on a g2o odometry data set.

``hippomap run-odometry DATA_DIR --loops FILE --out OUT_DIR`` feeds every odometry
increment through the grid cells -> place cells -> cognitive map, offers each loop
proposal of FILE to the map as a :class:`~hippomap.cognitive_map.LoopHypothesis` at the
time its later pose occurs, and writes the exports and ``metrics.json``.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, cast

import numpy as np

from ..cognitive_map import CognitiveMap, LoopHypothesis
from ..config import HippomapConfig
from ..errors import InputError
from ..eval.evaluation import LOOP_TRUTH_DISTANCE_M, groundtruth_distance, trajectory_metrics
from ..eval.revisits import closed_revisits
from ..extras import check
from ..geometry import between, compose, integrate
from ..io.datasets import LoopEdge, OdometryDataset, load_odometry_dataset
from ..io.exports import export_map, write_json
from ..spatial_pathway import SpatialPathway
from . import add_progress_argument, progress_enabled


@dataclass
class OdometryRun:
    """Everything a run produced: per-pose trajectories and the final map."""

    times: np.ndarray
    odometry: np.ndarray  # (N, 3) raw integrated odometry
    corrected: np.ndarray  # (N, 3) map trajectory after the final relaxation
    node_at_pose: np.ndarray  # (N,) current node at each pose
    cmap: CognitiveMap
    decisions: list[dict[str, Any]] = field(default_factory=list)
    steps_without_field: int = 0
    seconds: float = 0.0
    #: (pose index, map trajectory up to it as it stood then): the online map along the run
    checkpoints: list[tuple[int, np.ndarray]] = field(default_factory=list)


def _loop_information(e: LoopEdge) -> tuple[float, float] | None:
    """The (x/y, heading) information of a proposal from its g2o edge (the mean of the x and y
    diagonal, and the heading's), or None (the map's default) when the file gives unit
    information or none that is positive."""
    i11, _, _, i22, _, i33 = (float(v) for v in e.information)
    if (i11, i22, i33) == (1.0, 1.0, 1.0) or min(i11, i22, i33) <= 0 or not np.isfinite([i11, i22, i33]).all():
        return None
    return (0.5 * (i11 + i22), i33)


#: a loop proposal indexed by its later pose: earlier pose, its pose in the later frame, g2o line, information
_Proposal = tuple[int, np.ndarray, int, "tuple[float, float] | None"]


def _loops_by_pose(dataset: OdometryDataset) -> dict[int, list[_Proposal]]:
    """Index loop proposals by their later pose: {later: [(earlier, earlier-in-later-frame, line,
    information)]}; the information is the edge's own (:func:`_loop_information`)."""
    out: dict[int, list[_Proposal]] = defaultdict(list)
    for e in dataset.graph.loops:
        t = np.asarray(e.transform, dtype=float)
        info = _loop_information(e)
        if e.i > e.j:
            out[e.i].append((e.j, t, e.line, info))
        else:  # the edge measures the later pose j in the frame of i: invert it
            out[e.j].append((e.i, between(t, np.zeros(3)), e.line, info))
    return out


def _offer_loops(
    cmap: CognitiveMap,
    k: int,
    t: float,
    proposals: Iterable[_Proposal],
    node_at_pose: np.ndarray,
    offset_at_pose: np.ndarray,
) -> None:
    """Offer the map the loop proposals whose later pose is ``k`` (time ``t``), each as a
    hypothesis from the current node to the node of its earlier pose."""
    for j, t_kj, line, info in proposals:
        # pose of node_at_pose[j] in the frame of the current node, through the two
        # short odometric offsets of the robot from its node at k and at j
        rel = compose(compose(cmap.robot_offset, t_kj), between(offset_at_pose[j], np.zeros(3)))
        hyp = LoopHypothesis(
            node=int(node_at_pose[j]),
            transform=cast("tuple[float, float, float]", tuple(float(v) for v in rel)),
            evidence=1.0,
            source="dataset",
            time=t,
            meta={"poses": [k, j], "line": line},
            information=info,
        )
        cmap.propose_loop(hyp)


def run_odometry(
    dataset: OdometryDataset, config: HippomapConfig | None = None, progress: bool = False, checkpoints: int = 8
) -> OdometryRun:
    """Run the spatial pathway + cognitive map over the whole data set; ``checkpoints``
    snapshots of the map trajectory are kept along the way (to show the online map,
    not only the final one, against odometry)."""
    cfg = config or HippomapConfig()
    inc = dataset.graph.odometry
    times = dataset.times
    n = len(times)
    pathway = SpatialPathway(cfg.spatial)
    # measured loop proposals: online pruning on unless the config says otherwise (MapConfig.prune_online)
    map_cfg = cfg.map if cfg.map.prune_online is not None else cfg.map.model_copy(update={"prune_online": True})
    cmap = CognitiveMap(map_cfg)
    loops = _loops_by_pose(dataset)
    node_at_pose = np.empty(n, dtype=np.int64)
    offset_at_pose = np.empty((n, 3))
    decisions: list[dict[str, Any]] = []
    no_field = 0
    marks = set(np.linspace(0, n - 1, checkpoints + 1, dtype=int)[1:-1].tolist()) if checkpoints else set()
    snaps: list[tuple[int, np.ndarray]] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="pose", desc="run-odometry")
    t0 = time.perf_counter()
    for k in range(n):
        if k > 0:
            code = pathway.step_increment(*inc[k - 1])
            if code is None:
                no_field += 1
            cmap.update(None if code is None else (code.x, code.y, code.theta), inc[k - 1], float(times[k]))
        _offer_loops(cmap, k, float(times[k]), loops.get(k, ()), node_at_pose, offset_at_pose)
        node_at_pose[k] = cmap.current
        offset_at_pose[k] = cmap.robot_offset
        if k in marks:
            snaps.append((k, compose(cmap.poses[node_at_pose[: k + 1]], offset_at_pose[: k + 1])))
        if bar is not None:
            bar.update(1)
    cmap.finish()
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t0
    corrected = compose(cmap.poses[node_at_pose], offset_at_pose)
    decisions.extend(cmap.loop_rows())
    odometry = integrate(inc, cfg.map.initial_pose)
    snaps.append((n - 1, corrected))
    return OdometryRun(times, odometry, corrected, node_at_pose, cmap, decisions, no_field, seconds, snaps)


def _loop_truth(run: OdometryRun, gt: tuple[np.ndarray, np.ndarray] | None) -> None:
    """Mark each decision with the ground-truth distance between its two poses."""
    if gt is None:
        return
    for d in run.decisions:
        poses = d.get("hypothesis", {}).get("meta", {}).get("poses")
        if not poses:
            continue
        dist = groundtruth_distance(gt, *(float(run.times[p]) for p in poses))
        if dist is not None:
            d["groundtruth_distance_m"] = dist
            d["groundtruth_true"] = dist < LOOP_TRUTH_DISTANCE_M


def summarise(run: OdometryRun, dataset: OdometryDataset) -> dict[str, Any]:
    """metrics.json content: ATE/RPE of raw odometry and map, loop-closure counts."""
    _loop_truth(run, dataset.groundtruth)
    status = [d["status"] for d in run.decisions]
    accepted = [d for d in run.decisions if d["status"] == "accepted"]
    metrics: dict[str, Any] = {
        "data": str(dataset.loops_file),
        "poses": int(len(run.times)),
        "nodes": int(run.cmap.node_count),
        "links": int(run.cmap.link_count),
        "steps_without_place_field": run.steps_without_field,
        "run_seconds": round(run.seconds, 3),
        "loop_closures": {
            "proposed": len(dataset.graph.loops),
            "accepted": status.count("accepted"),
            "used": sum(bool(d.get("used")) for d in run.decisions),
            "rejected": status.count("rejected"),
            "pending_at_end": status.count("pending"),
        },
    }
    if dataset.groundtruth is not None:
        metrics["odometry"] = trajectory_metrics(run.times, run.odometry, *dataset.groundtruth)
        metrics["map"] = trajectory_metrics(run.times, run.corrected, *dataset.groundtruth)
        rows = []
        for k, traj in run.checkpoints:
            try:
                odo_ate = trajectory_metrics(run.times[: k + 1], run.odometry[: k + 1], *dataset.groundtruth)["ate"][
                    "rmse"
                ]
                map_ate = trajectory_metrics(run.times[: k + 1], traj, *dataset.groundtruth)["ate"]["rmse"]
            except InputError:  # too few ground-truth poses so far
                continue
            rows.append({"pose": int(k), "odometry_ate_rmse": odo_ate, "map_ate_rmse": map_ate})
        metrics["online"] = rows
        # 1 µm: before the first correction the two are the same trajectory up to rounding
        metrics["map_never_worse_than_odometry"] = all(r["map_ate_rmse"] <= r["odometry_ate_rmse"] + 1e-6 for r in rows)
        judged = [d for d in accepted if "groundtruth_true" in d]
        metrics["loop_closures"]["accepted_true"] = sum(d["groundtruth_true"] for d in judged)
        metrics["loop_closures"]["accepted_false"] = sum(not d["groundtruth_true"] for d in judged)
        metrics["loop_closures"]["used_false"] = sum(not d["groundtruth_true"] for d in judged if d["used"])
        metrics["loop_closures"]["true_distance_m"] = LOOP_TRUTH_DISTANCE_M
        # which ground-truth revisits a true closure the map used closed (made at the later pose of its pair)
        true_used = [
            float(run.times[max(d["hypothesis"]["meta"]["poses"])])
            for d in judged
            if d["used"] and d["groundtruth_true"]
        ]
        metrics["loop_closures"]["revisits"] = closed_revisits(dataset.groundtruth, true_used)
    return metrics


def write_outputs(run: OdometryRun, dataset: OdometryDataset, out_dir: str | Path) -> dict[str, Any]:
    """Write the exports (see :func:`hippomap.io.exports.export_map`) and metrics.json."""
    metrics = summarise(run, dataset)
    accepted = [d["hypothesis"]["meta"]["poses"] for d in run.decisions if d["used"]]
    segs = [[run.corrected[a, :2], run.corrected[b, :2]] for a, b in accepted]
    ate = {k: metrics.get(k, {}).get("ate", {}).get("rmse", float("nan")) for k in ("odometry", "map")}
    out = export_map(
        out_dir,
        run.cmap,
        run.times,
        run.odometry,
        run.corrected,
        run.decisions,
        dataset.groundtruth,
        segs,
        title=f"{Path(dataset.loops_file).name}: ATE odometry {ate['odometry']:.2f} m, map {ate['map']:.2f} m",
    )
    write_json(out / "metrics.json", metrics)
    return metrics


def _cmd(args: argparse.Namespace) -> int:
    check("eval", "hippomap run-odometry (TUM files, metrics, map plot)")
    dataset = load_odometry_dataset(args.data_dir, args.loops)
    run = run_odometry(dataset, HippomapConfig.from_file(args.config), progress=progress_enabled(args))
    metrics = write_outputs(run, dataset, args.out)
    lc = metrics["loop_closures"]
    line = (
        f"{metrics['nodes']} nodes, loop closures accepted {lc['accepted']} (used {lc['used']}, "
        f"false used {lc.get('used_false', 'n/a')}) / rejected {lc['rejected']}"
    )
    if "map" in metrics:
        line += (
            f"; ATE rmse odometry {metrics['odometry']['ate']['rmse']:.3f} m "
            f"-> map {metrics['map']['ate']['rmse']:.3f} m"
        )
    print(line)
    print(f"wrote {args.out}/metrics.json, map.tum, odometry.tum, map.g2o, map.json, map.png")
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "run-odometry",
        help="run grid cells -> place cells -> cognitive map on a g2o odometry data set",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("data_dir", help="data folder, e.g. ../shared/data/bicocca25b")
    p.add_argument("--loops", required=True, help="g2o file with odometry and loop proposals (e.g. B25b_1.000.g2o)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help='JSON file of config overrides, e.g. {"map": {"alpha": 0.5}}')
    add_progress_argument(p)
    p.set_defaults(func=_cmd)
