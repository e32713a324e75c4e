"""Trajectory metrics through evo: ATE and RPE against ground truth, matched by timestamp."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from ..errors import InputError
from ..extras import requires
from ..io.exports import to_evo

#: a loop closure is true when ground truth puts its two places closer than this [ours]
LOOP_TRUTH_DISTANCE_M = 2.0
#: the parts of a loop link's ground-truth error (``hippomap run``'s ``link_error_*`` per closure), by the name
#: ``metrics.json`` gives them: position, along and beside the view of the node it names, heading
LINK_ERROR_PARTS = {
    "m": "link_error_m",
    "along_m": "link_error_along_m",
    "beside_m": "link_error_beside_m",
    "heading_rad": "link_error_rad",
}


def link_error_parts(rows: list[dict[str, Any]]) -> dict[str, list[float]]:
    """The absolute value of each part of the ground-truth errors of the loop decisions' ``rows`` that have one
    (``link_error_*``), by the names of :data:`LINK_ERROR_PARTS`; empty when no row has an error."""
    rows = [r for r in rows if LINK_ERROR_PARTS["m"] in r]
    return {part: [abs(r[key]) for r in rows] for part, key in LINK_ERROR_PARTS.items()} if rows else {}


def groundtruth_at(gt: tuple[np.ndarray, np.ndarray], t: float, tol: float = 0.5) -> np.ndarray | None:
    """The ground-truth pose nearest in time to ``t`` (times sorted), or None when the
    nearest is more than ``tol`` seconds away (a gap in the ground truth)."""
    tg, pg = gt
    k = int(np.clip(np.searchsorted(tg, t), 1, len(tg) - 1))
    k = k if abs(tg[k] - t) < abs(tg[k - 1] - t) else k - 1
    return pg[k] if abs(tg[k] - t) <= tol else None


def groundtruth_distance(gt: tuple[np.ndarray, np.ndarray], t_a: float, t_b: float) -> float | None:
    """Ground-truth distance (m, in the plane) between where the robot was at ``t_a`` and at ``t_b``
    (:func:`groundtruth_at`), or None when the ground truth misses either time."""
    a, b = groundtruth_at(gt, t_a), groundtruth_at(gt, t_b)
    return None if a is None or b is None else float(np.linalg.norm(a[:2] - b[:2]))


def _stats(metric) -> dict[str, float]:
    s = metric.get_all_statistics()
    return {k: float(s[k]) for k in ("rmse", "mean", "median", "std", "min", "max")}


def _aligned_ate(metrics: Any, ref: Any, est: Any, correct_scale: bool) -> tuple[dict[str, float], float]:
    """The translation ATE statistics of ``est`` against ``ref`` after aligning ``est`` to it in place
    (Umeyama, with or without the scale; evo's ``metrics`` module passed in), and the scale applied."""
    try:
        scale = float(est.align(ref, correct_scale=correct_scale)[2])
    except Exception as exc:  # evo's GeometryException: e.g. all poses on one line
        raise InputError(f"cannot align estimate to ground truth: {exc}") from exc
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return _stats(ape), scale


def trajectory_metrics(
    est_times: Any,
    est_poses: Any,
    ref_times: Any,
    ref_poses: Any,
    max_time_diff: float = 0.1,
    rpe_delta_m: float = 10.0,
    scaled: bool = False,
) -> dict[str, Any]:
    """ATE (translation, after an SE(3) Umeyama alignment without scale, evo's ``-a``)
    and RPE (translation over ``rpe_delta_m`` metres of travel) of an estimate against
    ground truth. Poses are associated by nearest timestamp within ``max_time_diff``.

    ``scaled``: also ``ate_scaled``, the ATE after an alignment that corrects the scale too (evo's
    ``-as``), with the ``scale`` applied: odometry whose distances are off by a constant factor draws
    a map that is a scaled copy at best (no camera-only cue tells the metre), and this tells such a
    map's shape apart from its scale."""
    with requires("eval", "the trajectory metrics"):
        from evo.core import metrics, sync
        from evo.core.units import Unit

    est = to_evo(est_times, est_poses, "estimate")
    ref = to_evo(ref_times, ref_poses, "reference")
    try:
        ref_s, est_s = sync.associate_trajectories(ref, est, max_diff=max_time_diff)
    except Exception as exc:  # evo raises its own SyncException
        raise InputError(f"cannot match estimate and ground truth by timestamp: {exc}") from exc
    if ref_s.num_poses < 3:
        raise InputError(f"only {ref_s.num_poses} poses matched ground truth by timestamp")
    est_c = copy.deepcopy(est_s) if scaled else None  # before est_s is aligned in place
    ate, _ = _aligned_ate(metrics, ref_s, est_s, correct_scale=False)
    out: dict[str, Any] = {"matched_poses": int(ref_s.num_poses), "ate": ate}
    if est_c is not None:
        ate_c, scale = _aligned_ate(metrics, ref_s, est_c, correct_scale=True)
        out["ate_scaled"] = {**ate_c, "scale": scale}
    try:
        rpe = metrics.RPE(
            metrics.PoseRelation.translation_part, delta=rpe_delta_m, delta_unit=Unit.meters, all_pairs=False
        )
        rpe.process_data((ref_s, est_s))
        out["rpe"] = {"delta_m": rpe_delta_m, **_stats(rpe)}
    except Exception as exc:  # too short a trajectory for the delta
        out["rpe"] = {"delta_m": rpe_delta_m, "error": str(exc)}
    return out
