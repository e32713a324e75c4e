"""Offline run of the whole mapper (odometry + camera) over a recorded data set.

``hippomap run DATA_DIR --out OUT_DIR`` reads a hippomap data folder (``frames/``,
``frames.csv``, ``odometry.csv``, optional ``groundtruth.csv`` — also what the simulator
writes), a TUM RGB-D folder, or a ROS 1/2 bag (``--image-topic``, ``--odom-topic``),
feeds every input in time order to one :class:`~hippomap.mapper.Mapper` and writes
``map.tum``, ``odometry.tum``, ``map.g2o``, ``map.json``, ``loop_closures.json``,
``map.png`` and ``metrics.json``, and ``groundtruth.tum`` when the data set has ground truth
(e.g. ``groundtruth.csv``), so that evo compares the map with it directly.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..config import HippomapConfig
from ..errors import InputError
from ..eval.evaluation import (
    LOOP_TRUTH_DISTANCE_M,
    groundtruth_at,
    groundtruth_distance,
    link_error_parts,
    trajectory_metrics,
)
from ..eval.revisits import closed_revisits, describe_missed, explain_missed
from ..extras import check
from ..geometry import between
from ..inputs import Odometry
from ..io.datasets import SensorDataset, read_folder_dataset, read_tum_rgbd
from ..io.exports import export_map, write_json, write_tum
from ..mapper import Mapper
from . import add_progress_argument, progress_enabled


def open_dataset(
    path: str | Path,
    image_topic: str | None = None,
    odom_topic: str | None = None,
    groundtruth_topic: str | None = None,
) -> SensorDataset:
    """Pick the reader by what the path holds."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"data set {path} does not exist")
    if path.is_dir() and (path / "frames.csv").is_file():
        return read_folder_dataset(path)
    if path.is_dir() and (path / "rgb.txt").is_file():
        return read_tum_rgbd(path)
    if path.suffix == ".bag" or (path.is_dir() and (path / "metadata.yaml").is_file()):
        if not (image_topic and odom_topic):
            raise InputError("a ROS bag needs --image-topic and --odom-topic")
        from ..io.rosbag import read_rosbag

        return read_rosbag(path, image_topic, odom_topic, groundtruth_topic=groundtruth_topic)
    raise InputError(f"{path}: not a hippomap data folder (frames.csv), a TUM RGB-D folder (rgb.txt) or a ROS bag")


def dataset_config(dataset: SensorDataset, config: HippomapConfig | None = None) -> HippomapConfig:
    """``config`` (default: the defaults) with the camera's field of view the data set states
    (:func:`~hippomap.io.datasets.read_camera_hfov`) where the config leaves it unset: a calibrated
    camera's image shift then gives each recognition its heading (docs/MODEL.md items 25 and 56)."""
    cfg = config or HippomapConfig()
    if cfg.mapper.camera_hfov_deg is None and dataset.camera_hfov_deg is not None:
        cfg = cfg.model_copy(
            update={"mapper": cfg.mapper.model_copy(update={"camera_hfov_deg": dataset.camera_hfov_deg})}
        )
    return cfg


def run_dataset(
    dataset: SensorDataset, config: HippomapConfig | None = None, progress: bool = False, mapper: Mapper | None = None
) -> tuple[Mapper, dict[str, Any]]:
    """Feed the data set to a mapper; returns it and timing figures."""
    m = mapper or Mapper(config)
    total = len(dataset.odometry) + len(dataset.frames)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="input", desc="run")
    decode_s, frame_s, odo_s = [], [], []
    for item in dataset.events():
        if isinstance(item, Odometry):
            t0 = time.perf_counter()
            m.step(item)
            odo_s.append(time.perf_counter() - t0)
        else:
            t0 = time.perf_counter()
            frame = item.load()
            t1 = time.perf_counter()
            m.observe(frame)
            decode_s.append(t1 - t0)
            frame_s.append(time.perf_counter() - t1)
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()

    def ms(xs: list[float]) -> dict[str, float]:
        a = np.array(xs) * 1e3 if xs else np.zeros(1)
        return {"mean": float(a.mean()), "p95": float(np.percentile(a, 95)), "n": len(xs)}

    return m, {"frame_ms": ms(frame_s), "decode_ms": ms(decode_s), "odometry_ms": ms(odo_s)}


def loop_report(m: Mapper, gt: tuple[np.ndarray, np.ndarray] | None) -> list[dict[str, Any]]:
    """Every loop decision, with the ground-truth distance between its two places and, for an
    accepted one, the error of its link against ground truth (see :func:`link_error`)."""
    out = []
    times = m.cmap.times
    for d, row in zip(m.cmap.loop_decisions, m.cmap.loop_rows()):
        # nodes of a saved map (--base-map) were made in another run, whose ground truth this is not
        if gt is not None and min(d.hypothesis.node, d.from_node) >= m.base_nodes:
            h = d.hypothesis
            dist = groundtruth_distance(gt, float(h.time), float(times[h.node]))
            if dist is not None:
                row["groundtruth_distance_m"] = dist
            if d.status == "accepted" and d.transform is not None:
                row.update(link_error(gt, float(times[d.from_node]), float(times[h.node]), d.transform))
        out.append(row)
    return out


def recognition_report(m: Mapper, gt: tuple[np.ndarray, np.ndarray]) -> list[dict[str, Any]]:
    """Every recognition's time, search and competing key frames, and the ground-truth distance from
    the robot to the key frame it named (the robot's pose when that key frame's node was made; None
    when it named none, or a saved map's key frame)."""
    out = []
    times = m.cmap.times
    for r in m.recognitions:
        node = m.frame_node.get(r["frame_id"]) if r.get("frame_id") is not None else None
        known = node is not None and node >= m.base_nodes
        d = groundtruth_distance(gt, float(r["t"]), float(times[node])) if known else None
        out.append(
            {"t": r["t"], "search": r.get("search"), "candidates": r.get("candidates"), "groundtruth_distance_m": d}
        )
    return out


def link_error(gt: tuple[np.ndarray, np.ndarray], t_from: float, t_to: float, transform) -> dict[str, float]:
    """Error of a loop link against ground truth: the link says where node ``to`` lies in the
    frame of node ``from``; ground truth says it from the robot's true poses when the two nodes
    were made (a node is made at the robot's pose). Empty when ground truth misses a time.

    ``link_error_m`` and ``link_error_rad``: the position and heading error. The position error in
    the frame the link puts node ``to`` in, signed: ``link_error_along_m`` along that node's heading
    (for a visual link, the key frame's view: the direction looming reads; positive when the node truly
    lies further ahead than the link says, a reading that put the robot too near its key frame) and
    ``link_error_beside_m`` across it (positive to its left)."""
    a, b = groundtruth_at(gt, t_from), groundtruth_at(gt, t_to)
    if a is None or b is None:
        return {}
    e = between(np.asarray(transform, dtype=float), between(a, b))
    return {
        "link_error_m": float(np.hypot(e[0], e[1])),
        "link_error_rad": float(abs(e[2])),
        "link_error_along_m": float(e[0]),
        "link_error_beside_m": float(e[1]),
    }


def _summary(values: list[float]) -> dict[str, float]:
    """Mean, median and max of ``values`` (not empty)."""
    return {"mean": float(np.mean(values)), "median": float(np.median(values)), "max": float(np.max(values))}


def _link_errors(used: list[dict[str, Any]]) -> dict[str, Any]:
    """``link_error_m``: the summary of the ``used`` links' errors against ground truth (:func:`link_error`);
    ``link_error_parts``: of their absolute parts, along the view of the key frame each names, beside it and in
    heading: which part of the links is off. Empty when no used link has a ground-truth error."""
    parts = link_error_parts(used)
    if not parts:
        return {}
    return {
        "link_error_m": _summary(parts.pop("m")),
        "link_error_parts": {part: _summary(v) for part, v in parts.items()},
    }


def write_run(
    m: Mapper, dataset: SensorDataset, out_dir: str | Path, timing: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write the exports (see :func:`hippomap.io.exports.export_map`), ``groundtruth.tum`` (when
    the data set has ground truth) and metrics.json."""
    t = m.trajectory_times
    odo = m.odometry_trajectory()
    cor = m.corrected_trajectory()
    loops = loop_report(m, dataset.groundtruth)
    accepted = [r for r in loops if r["status"] == "accepted"]
    metrics: dict[str, Any] = {"data": str(dataset.source), "stats": m.stats(), "timing": timing or {}}
    used = [r for r in loops if r["used"]]
    metrics["loop_closures"] = {
        "accepted": len(accepted),
        "used": len(used),
        "rejected": sum(r["status"] == "rejected" for r in loops),
    }
    if dataset.groundtruth is not None and len(t) > 3:
        metrics["odometry"] = trajectory_metrics(t, odo, *dataset.groundtruth, scaled=True)
        metrics["map"] = trajectory_metrics(t, cor, *dataset.groundtruth, scaled=True)
        metrics["map_ate_ratio"] = metrics["map"]["ate"]["rmse"] / max(metrics["odometry"]["ate"]["rmse"], 1e-12)
        judged = [r for r in accepted if "groundtruth_distance_m" in r]
        metrics["loop_closures"]["accepted_false"] = sum(
            r["groundtruth_distance_m"] >= LOOP_TRUTH_DISTANCE_M for r in judged
        )
        metrics["loop_closures"]["used_false"] = sum(
            r["groundtruth_distance_m"] >= LOOP_TRUTH_DISTANCE_M for r in judged if r["used"]
        )
        metrics["loop_closures"]["max_accepted_distance_m"] = max(
            (r["groundtruth_distance_m"] for r in judged), default=None
        )
        # which ground-truth revisits the map closed (a true closure it used along each)
        true_used = [
            r["hypothesis"]["time"] for r in used if r.get("groundtruth_distance_m", np.inf) < LOOP_TRUTH_DISTANCE_M
        ]
        metrics["loop_closures"]["revisits"] = closed_revisits(dataset.groundtruth, true_used)
        missed = metrics["loop_closures"]["revisits"]["missed"]
        if missed:  # the recognitions' ground truth is only needed to explain a miss
            explain_missed(missed, recognition_report(m, dataset.groundtruth), loops)
        metrics["loop_closures"].update(_link_errors(used))
    segs = []
    if len(t):
        for r in used:
            h = r["hypothesis"]
            k = int(np.clip(np.searchsorted(t, h["time"]), 0, len(t) - 1))
            segs.append([cor[k, :2], m.cmap.poses[h["node"], :2]])
    title = Path(dataset.source).name
    if "map" in metrics:
        title += f": ATE odometry {metrics['odometry']['ate']['rmse']:.2f} m, map {metrics['map']['ate']['rmse']:.2f} m"
    out = export_map(out_dir, m.cmap, t, odo, cor, loops, dataset.groundtruth, segs, title=title)
    if dataset.groundtruth is not None:
        write_tum(out / "groundtruth.tum", *dataset.groundtruth)
    write_json(out / "metrics.json", metrics)
    return metrics


def base_mapper(snapshot: str | Path, config_file: str | None = None) -> Mapper:
    """A new run in the saved map of ``snapshot`` (a mapper snapshot: ``Mapper.to_bytes``, or a
    session's ``GET /sessions/{id}/snapshot``); the JSON overrides of ``config_file`` change the
    saved map's config (e.g. ``{"mapper": {"mode": "localise"}}``)."""
    try:
        data = Path(snapshot).read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read base map {snapshot}: {exc}") from None
    overrides = None
    if config_file:
        import json

        try:
            overrides = json.loads(Path(config_file).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read config {config_file}: {exc}") from None
    return Mapper.from_base(data, overrides)


def _cmd(args: argparse.Namespace) -> int:
    check("eval", "hippomap run (TUM files, metrics, map plot)")
    dataset = open_dataset(args.data_dir, args.image_topic, args.odom_topic, args.groundtruth_topic)
    if args.base_map:
        base = base_mapper(args.base_map, args.config)
        m, timing = run_dataset(dataset, None, progress=progress_enabled(args), mapper=base)
    else:
        cfg = dataset_config(dataset, HippomapConfig.from_file(args.config))
        m, timing = run_dataset(dataset, cfg, progress=progress_enabled(args))
    metrics = write_run(m, dataset, args.out, timing)
    s = metrics["stats"]
    lc = metrics["loop_closures"]
    line = (
        f"{s['nodes']} nodes, {s['keyframes']} key frames, loop closures accepted {lc['accepted']} "
        f"(used {lc['used']}) / rejected {lc['rejected']}"
    )
    if "map" in metrics:
        line += (
            f"; ATE rmse odometry {metrics['odometry']['ate']['rmse']:.3f} m"
            f" -> map {metrics['map']['ate']['rmse']:.3f} m"
            f" ({metrics['map']['ate_scaled']['rmse']:.3f} m with the scale corrected,"
            f" x{metrics['map']['ate_scaled']['scale']:.3f})"
        )
    print(line)
    revisits = lc.get("revisits")
    if revisits and revisits["episodes"]:
        missed = "; ".join(describe_missed(e) for e in revisits["missed"])
        print(
            f"revisits closed {revisits['closed']} of {revisits['episodes']}"
            + (
                f"; missed (length at path, heading from the earlier pass, true links faded there): {missed}"
                if missed
                else ""
            )
        )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "run",
        help="run the whole mapper (odometry + camera) over a data set",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("data_dir", help="hippomap data folder, TUM RGB-D folder, or ROS bag")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--image-topic", help="ROS bag: image or compressed-image topic")
    p.add_argument("--odom-topic", help="ROS bag: nav_msgs/Odometry topic")
    p.add_argument(
        "--groundtruth-topic", help="ROS bag (optional): ground truth, geometry_msgs/PoseStamped or nav_msgs/Odometry"
    )
    p.add_argument("--config", help="JSON file of config overrides")
    p.add_argument(
        "--base-map",
        help="start in this saved map (a mapper snapshot, e.g. a session's /snapshot): "
        "the run starts from an unknown pose and is placed by recognition; --config then changes the "
        "saved map's config",
    )
    add_progress_argument(p)
    p.set_defaults(func=_cmd)
