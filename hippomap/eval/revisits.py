"""Revisits in the ground truth, and which of them a map closed: loop-closure recall by place.

A map's ATE says how far off it is, and the closures' precision says whether any was false; neither
says *which* loops the map never closed. One lost revisit (the robot back at its start after a long
excursion, say) can cost a map tens of metres while every closure it made was true. So the ground
truth is cut into *revisit episodes* — stretches of path along which the robot stands within
``radius_m`` of a place it passed at least ``min_path_m`` of path earlier, facing within
``max_heading_rad`` of the way it faced then (a forward camera driven back the other way sees the
other side of the corridor: nothing to recognise) — and an episode counts as closed when a true loop
closure the map used was made along it. The episodes come from the ground
truth alone, so every system run on the same data (hippomap, OpenRatSLAM) is scored on the same ones.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ..errors import InputError
from ..geometry import path_lengths, wrap_angle
from .evaluation import LOOP_TRUTH_DISTANCE_M, link_error_parts

#: within this of an earlier place, the robot revisits it [ours]
REVISIT_RADIUS_M = 1.5
#: ... when it passed there at least this much path earlier (not its own recent track) [ours]
REVISIT_MIN_PATH_M = 30.0
#: revisited stretches closer than this along the path are one episode [ours]
REVISIT_JOIN_M = 2.0
#: an episode shorter than this is a graze, not a revisit [ours]
REVISIT_MIN_LENGTH_M = 2.0
#: ... facing within this of the way it faced then (ground truth with headings) [ours]
REVISIT_MAX_HEADING_RAD = math.pi / 2
#: the ground truth is sampled every this much path (its own rate may be anything) [ours]
SAMPLE_STEP_M = 0.25


@dataclass(frozen=True)
class Revisit:
    """One revisit episode of the ground truth: from ``t0`` to ``t1`` (s), starting ``path_m`` metres
    of path into the run and ``length_m`` long, revisiting places first passed around ``earlier_t``.
    ``heading_deg``: the smallest difference of heading between the robot along the episode and the
    earlier places it revisits (None when headings were not compared). An episode near the heading
    limit is a graze of a crossing or a turn, where a forward camera sees little of the earlier view."""

    t0: float
    t1: float
    path_m: float
    length_m: float
    earlier_t: float
    heading_deg: float | None = None


def revisit_episodes(
    times: Any,
    poses: Any,
    radius_m: float = REVISIT_RADIUS_M,
    min_path_m: float = REVISIT_MIN_PATH_M,
    join_m: float = REVISIT_JOIN_M,
    min_length_m: float = REVISIT_MIN_LENGTH_M,
    max_heading_rad: float | None = REVISIT_MAX_HEADING_RAD,
) -> list[Revisit]:
    """The revisit episodes of a ground-truth trajectory (``times`` (N,), sorted; ``poses`` (N, >=2),
    x and y first, then the heading when there is one). Vectorised: the trajectory is sampled every
    :data:`SAMPLE_STEP_M` of path, every pair of samples within ``radius_m`` is found at once (a k-d
    tree), and a sample revisits when a partner lies ``min_path_m`` or more of path behind it, facing
    within ``max_heading_rad`` of it (None, or poses without headings: any heading)."""
    t, p = _checked(times, poses, radius_m, min_path_m, join_m, min_length_m)
    if len(t) < 2:
        return []
    s_all = path_lengths(p[:, :2])
    # one sample per SAMPLE_STEP_M of path (the first pose at or past each step)
    idx = np.unique(np.searchsorted(s_all, np.arange(0.0, s_all[-1] + SAMPLE_STEP_M, SAMPLE_STEP_M)))
    idx = idx[idx < len(t)]
    heading = p[idx, 2] if max_heading_rad is not None and p.shape[1] >= 3 else None
    s = s_all[idx]
    rev, earlier, turn = _revisiting(p[idx, :2], s, heading, radius_m, min_path_m, max_heading_rad)
    if rev.size == 0:
        return []
    # episodes: runs of revisiting samples less than join_m of path apart
    cut = np.flatnonzero(np.diff(s[rev]) > join_m) + 1
    starts = np.concatenate(([0], cut))
    ends = np.concatenate((cut, [len(rev)])) - 1
    ts = t[idx]
    out = []
    for a, b in zip(starts.tolist(), ends.tolist()):  # one per episode (a handful per run)
        length = float(s[rev[b]] - s[rev[a]])
        if length >= min_length_m:
            first = float(ts[earlier[a : b + 1].min()])
            deg = None if heading is None else math.degrees(float(turn[a : b + 1].min()))
            out.append(Revisit(float(ts[rev[a]]), float(ts[rev[b]]), float(s[rev[a]]), length, first, deg))
    return out


def _checked(
    times: Any, poses: Any, radius_m: float, min_path_m: float, join_m: float, min_length_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """``times`` and ``poses`` as float arrays, or an :class:`InputError` naming what is wrong with them
    or with the episode parameters."""
    t = np.asarray(times, dtype=float).ravel()
    p = np.asarray(poses, dtype=float)
    if p.ndim != 2 or p.shape[1] < 2 or len(p) != len(t):
        raise InputError(f"revisit_episodes needs N times and N poses with x, y; got {t.shape} and {p.shape}")
    if not (np.isfinite(t).all() and np.isfinite(p[:, : min(p.shape[1], 3)]).all()):
        raise InputError("revisit_episodes: times and positions must be finite")
    if len(t) > 1 and np.any(np.diff(t) < 0):
        raise InputError("revisit_episodes: times must be sorted")
    if min(radius_m, min_path_m, join_m) <= 0 or min_length_m < 0:
        raise InputError("revisit_episodes: radius, minimum path and join distance must be positive")
    return t, p


def _revisiting(
    pts: np.ndarray,
    s: np.ndarray,
    heading: np.ndarray | None,
    radius_m: float,
    min_path_m: float,
    max_heading_rad: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rev, earlier, turn)``: the samples (positions ``pts``, path lengths ``s``) that revisit an earlier
    one, ascending, for each the earliest sample it revisits, and the smallest heading difference (rad) to
    any sample it revisits (0 without headings); every pair within ``radius_m`` in one k-d tree query, kept
    when ``min_path_m`` of path apart (and facing within ``max_heading_rad``)."""
    none = np.zeros(0, dtype=np.int64)
    pairs = cKDTree(pts).query_pairs(radius_m, output_type="ndarray")  # i < j
    if pairs.size == 0:
        return none, none, np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    far = s[j] - s[i] >= min_path_m
    dth = np.zeros(len(i))
    if heading is not None:
        dth = np.abs(wrap_angle(heading[j] - heading[i]))
        if max_heading_rad is not None:
            far &= dth <= max_heading_rad
    if not far.any():
        return none, none, np.zeros(0)
    i, j, dth = i[far], j[far], dth[far]
    order = np.lexsort((i, j))  # by revisiting sample, then earliest partner first
    j_sorted, i_sorted = j[order], i[order]
    first = np.concatenate(([True], j_sorted[1:] != j_sorted[:-1]))
    turn = np.minimum.reduceat(dth[order], np.flatnonzero(first))  # per revisiting sample, over its partners
    return j_sorted[first], i_sorted[first], turn


def revisit_recall(
    episodes: list[Revisit], times: Any, poses: Any, closure_times: Any, join_m: float = REVISIT_JOIN_M
) -> dict[str, Any]:
    """How many ``episodes`` (of the ground truth ``times``, ``poses``) a map closed: an episode is
    closed when one of ``closure_times`` (when the robot made each true loop closure the map used)
    lies on its stretch of path, give or take ``join_m`` (a recognition may come a little before
    the robot is within the episode's radius). Returns the counts, the recall (None without
    episodes) and the episodes missed."""
    t = np.asarray(times, dtype=float).ravel()
    s_all = path_lengths(np.asarray(poses, dtype=float)[:, :2])
    ct = np.asarray(closure_times, dtype=float).ravel()
    cs = np.interp(ct, t, s_all) if ct.size and t.size else np.zeros(0)
    lo = np.array([e.path_m - join_m for e in episodes])
    hi = np.array([e.path_m + e.length_m + join_m for e in episodes])
    closed: np.ndarray = np.zeros(len(episodes), dtype=bool)
    if len(episodes) and cs.size:
        closed = np.any((cs[None, :] >= lo[:, None]) & (cs[None, :] <= hi[:, None]), axis=1)
    n = len(episodes)
    return {
        "episodes": n,
        "closed": int(closed.sum()),
        "recall": float(closed.mean()) if n else None,
        "missed": [asdict(e) for e, c in zip(episodes, closed) if not c],
    }


def explain_missed(
    missed: list[dict[str, Any]], recognitions: list[dict[str, Any]], loops: list[dict[str, Any]]
) -> None:
    """Add to each of ``missed`` (the ``missed`` episodes of :func:`revisit_recall`) a ``why``: what
    the mapper did between the episode's ``t0`` and ``t1``. From ``recognitions`` (dicts with ``t``,
    ``search``, ``candidates`` and ``groundtruth_distance_m``, the ground-truth distance from the robot
    to the key frame named, None when none was): how many ran, how many were global searches, the
    median number of competing key frames, and how many named a key frame within / beyond
    ``LOOP_TRUTH_DISTANCE_M`` of the robot. From ``loops`` (the loop decisions' rows, as ``hippomap run``
    writes them): how many true ones the map accepted and uses, and how many it accepted and faded. An
    episode nothing recognised lost its loop in recognition; one whose true links faded, in
    verification, and then ``faded_link_error`` says how far those links were from ground truth (the
    median of each part of their ``link_error_*``: position ``m``, ``along_m`` and ``beside_m`` the key
    frame's view, ``heading_rad``; absolute values), which says what misled them: looming's reading along
    the view, the image shift's across it, or neither (None when no faded link has a ground-truth error)."""
    rt = np.array([float(r["t"]) for r in recognitions])
    lt = np.array([float(r["hypothesis"]["time"]) for r in loops])
    for e in missed:
        recs = [recognitions[i] for i in np.flatnonzero((rt >= e["t0"]) & (rt <= e["t1"]))]
        rows = [loops[i] for i in np.flatnonzero((lt >= e["t0"]) & (lt <= e["t1"]))]
        named = [r["groundtruth_distance_m"] for r in recs if r.get("groundtruth_distance_m") is not None]
        cands = [r["candidates"] for r in recs if r.get("candidates") is not None]
        true_acc = [
            r
            for r in rows
            if r["status"] == "accepted" and r.get("groundtruth_distance_m", np.inf) < LOOP_TRUTH_DISTANCE_M
        ]
        e["why"] = {
            "recognitions": len(recs),
            "global_searches": sum(r.get("search") == "global" for r in recs),
            "candidates_median": float(np.median(cands)) if cands else None,
            "named_true": sum(d < LOOP_TRUTH_DISTANCE_M for d in named),
            "named_false": sum(d >= LOOP_TRUTH_DISTANCE_M for d in named),
            "true_links_used": sum(bool(r["used"]) for r in true_acc),
            "true_links_faded": sum(not r["used"] for r in true_acc),
            "faded_link_error": _median_errors([r for r in true_acc if not r["used"]]),
        }


def _median_errors(rows: list[dict[str, Any]]) -> dict[str, float] | None:
    """The median absolute value of each part of the rows' link errors; None when no row has one."""
    parts = link_error_parts(rows)
    return {part: float(np.median(v)) for part, v in parts.items()} if parts else None


def describe_missed(e: dict[str, Any]) -> str:
    """One missed episode (a ``missed`` entry of :func:`revisit_recall`, with :func:`explain_missed`'s ``why``) in
    words: its length at its path, the heading from the earlier pass, and when true links faded there how many and
    how far off at the median (position: along / beside the key frame's view); each part only when the entry has it
    (entries written before it was measured have not). What ``hippomap run`` prints and the benchmark lists."""
    text = f"{e['length_m']:.0f} m at {e['path_m']:.0f} m"
    if e.get("heading_deg") is not None:
        text += f" ({e['heading_deg']:.0f}°)"
    why = e.get("why") or {}
    err = why.get("faded_link_error")
    if why.get("true_links_faded") and err:
        text += (
            f" [{why['true_links_faded']} true faded, {err['m']:.2f} m off: "
            f"{err['along_m']:.2f} / {err['beside_m']:.2f} m]"
        )
    return text


def closed_revisits(groundtruth: tuple[Any, Any], closure_times: Any) -> dict[str, Any]:
    """:func:`revisit_recall` of the ground truth's own episodes (:func:`revisit_episodes`, default
    parameters): what ``hippomap run``, ``hippomap run-odometry`` and the benchmark's peers report."""
    t, p = groundtruth
    return revisit_recall(revisit_episodes(t, p), t, p, closure_times)
