"""The relative pose of a loop hypothesis: where the robot stands relative to the node it is
taken back to (MODEL items 25 and 37).

A visual recognition names a node; how far the robot is from it comes from two places:

* :func:`looming_offset` — one recognition: how far the camera stands ahead of where the matched
  key frame was taken, along its view, from the scale change of the scene between the two
  images (the saccade correspondences), measured on the viewing sphere (:func:`view_sphere`) when
  the camera's field of view is known, so that a turn does not read as a step.
* :func:`align_group` — a group of consistent hypotheses (:func:`~hippomap.loop_closure.consistent`):
  one SE(2) transform that puts the robot's recent dead-reckoned path onto the matched nodes (a
  2-D Procrustes fit); each hypothesis' offset is then where the fit puts the robot relative to
  its node. Single matches are off along the track by up to the key-frame spacing; the fit
  averages that out, and the heading comes from the shape of the path.
* :func:`fit_group` — :func:`align_group` on a group of candidates and the map, checked, each
  candidate's offset set from the fit.
* :func:`reanchor` — one recognition's offset moved to the node of the old path nearest the place it
  claims, so that its loop link joins nodes that stand where the robot stood.

The map's decisions that use them are in :mod:`hippomap.loop_closing` and :mod:`hippomap.mapper`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .config import MapConfig
from .errors import InputError, vec3
from .geometry import compose, se2_between, se2_compose, wrap_angle
from .loop_closure import Candidate, place_of

__all__ = [
    "align_group",
    "fit_group",
    "looming_distance",
    "looming_offset",
    "looming_scale",
    "focal_px",
    "reanchor",
    "view_sphere",
]


def align_group(odom: np.ndarray, targets: np.ndarray, min_spread_m: float) -> np.ndarray:
    """The SE(2) pose ``T`` of the odometry frame in the map that best puts the robot's
    dead-reckoned poses ``odom`` (K, 3) onto ``targets`` (K, 3), the places the hypotheses name.

    Translation and rotation by least squares on the positions (2-D Procrustes) when the
    positions spread over at least ``min_spread_m``; otherwise the rotation is the circular mean
    of the heading differences (a short or bunched path says little about direction).
    """
    odom = np.asarray(odom, dtype=float).reshape(-1, 3)
    targets = np.asarray(targets, dtype=float).reshape(-1, 3)
    a, b = odom[:, :2], targets[:, :2]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    A, B = a - ca, b - cb
    spread = float(np.sqrt((A**2).sum(axis=1).max())) * 2 if len(a) > 1 else 0.0
    if spread >= min_spread_m:
        num = float(np.sum(A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]))
        den = float(np.sum(A[:, 0] * B[:, 0] + A[:, 1] * B[:, 1]))
        phi = math.atan2(num, den)
    else:
        d = wrap_angle(targets[:, 2] - odom[:, 2])
        phi = math.atan2(float(np.sin(d).sum()), float(np.cos(d).sum()))
    c, s = math.cos(phi), math.sin(phi)
    t = cb - np.array([c * ca[0] - s * ca[1], s * ca[0] + c * ca[1]])
    return np.array([t[0], t[1], phi])


def looming_scale(
    query: Any, memory: Any, min_separation_px: float = 10.0, camera: tuple[float, float, float] | None = None
) -> float | None:
    """The scale change of the scene from a key frame to a query: the median ratio of the distances
    between pairs of the same K scene points in the query and in memory (``query``, ``memory`` (K, 2),
    px; a recognition's saccade correspondences), taken as the exponential of the median log ratio.
    Pairs closer than ``min_separation_px`` in memory are left out (their ratio is pixel noise); a
    pairwise ratio ignores the image shift that a turn causes. ``None`` with fewer than three points
    or no usable pair. ``camera`` = (width, height, horizontal field of view in degrees): the points are first
    taken to the viewing sphere (:func:`view_sphere`), so that the scale change is the camera's step and not its
    turn."""
    if camera is not None:
        query, memory = (view_sphere(p, *camera) for p in (query, memory))
    q = np.asarray(query, dtype=float).reshape(-1, 2)
    m = np.asarray(memory, dtype=float).reshape(-1, 2)
    if q.shape != m.shape:
        raise InputError(f"looming: {len(q)} query points but {len(m)} memory points")
    if len(q) < 3:
        return None
    i, j = np.triu_indices(len(q), 1)
    dm = np.hypot(m[i, 0] - m[j, 0], m[i, 1] - m[j, 1])
    dq = np.hypot(q[i, 0] - q[j, 0], q[i, 1] - q[j, 1])
    ok = (dm >= min_separation_px) & (dq > 0)
    if not ok.any():
        return None
    return math.exp(float(np.median(np.log(dq[ok] / dm[ok]))))


def focal_px(width: float, hfov_deg: float) -> float:
    """The focal length (px) of a pinhole camera ``width`` px wide with horizontal field of view ``hfov_deg``."""
    if not (math.isfinite(hfov_deg) and 0 < hfov_deg < 180):
        raise InputError(f"hfov_deg must lie in (0, 180), got {hfov_deg!r}")
    return 0.5 * width / math.tan(math.radians(hfov_deg) / 2)


def view_sphere(points: Any, width: float, height: float, hfov_deg: float) -> np.ndarray:
    """Image points (K, 2; px, origin at the top-left corner) as directions on the viewing sphere of
    a pinhole camera with horizontal field of view ``hfov_deg``: (azimuth, elevation) times the focal
    length, so that near the image centre they are the pixels themselves.

    A turn of the camera about its vertical axis moves every direction by the same azimuth and leaves
    the elevations as they were, so distances between them change only when the camera moves. In the
    image plane the same turn stretches a pair of points that comes towards the centre by up to
    ``1 / cos²`` of its angle from it and changes their vertical spacing with the depth along the view:
    read as looming, a 0.4 rad turn of a 60° camera on the spot is a step of 0.18 m at the median over
    random scenes 3–6 m away (docs/MODEL.md item 122)."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    f = focal_px(width, hfov_deg)
    x, y = p[:, 0] - 0.5 * width, p[:, 1] - 0.5 * height
    return f * np.column_stack([np.arctan2(x, f), np.arctan2(y, np.hypot(x, f))])


def looming_offset(
    query: Any,
    memory: Any,
    view_distance_m: float,
    min_separation_px: float = 10.0,
    camera: tuple[float, float, float] | None = None,
) -> float | None:
    """How far the camera stands ahead of where a key frame was taken, along the key frame's
    view (m; negative: behind it), from the scale change of the scene between the two images.

    ``query``, ``memory`` (K, 2): the same K scene points in the query and in the key frame
    (a recognition's saccade correspondences, px). A camera that moves ``d`` towards a surface
    ``D`` away sees it magnified by ``s = D / (D - d)`` (looming), so ``d = D (1 - 1 / s)``,
    with ``s`` from :func:`looming_scale`. The scene's
    depth is not measured: ``view_distance_m`` stands for it (one typical distance, a model
    parameter). The result is bounded by ±``view_distance_m`` / 2 (a scale change beyond
    2 : 3 is no plausible recognition). ``None`` with fewer than three points or no usable
    pair: then the recognition says nothing about the along-view offset. ``camera``: as for
    :func:`looming_scale`, the scale read on the viewing sphere."""
    if not (math.isfinite(view_distance_m) and view_distance_m > 0):
        raise InputError(f"view_distance_m must be a positive number, got {view_distance_m!r}")
    scale = looming_scale(query, memory, min_separation_px, camera)
    return None if scale is None else float(looming_distance(scale, view_distance_m))


def looming_distance(scale: Any, view_distance_m: float) -> Any:
    """:func:`looming_offset` of a scale change ``s`` (a number or an array of them): ``D (1 - 1 / s)``
    with ``D`` = ``view_distance_m``, bounded by ±``D`` / 2."""
    d = view_distance_m * (1.0 - 1.0 / np.asarray(scale, dtype=float))
    return np.clip(d, -0.5 * view_distance_m, 0.5 * view_distance_m)


def fit_group(
    group: list[Candidate], anchors: list[Candidate], P: np.ndarray, cfg: MapConfig
) -> list[Candidate] | None:
    """The group's visual candidates with the offsets of one SE(2) fit (:func:`align_group`) of the
    robot's dead-reckoned poses onto the places they name on the map ``P`` (``anchors``: accepted
    candidates of the last ``loop_fit_window_m`` of path, which back the fit but keep their links: a
    rigid transform cannot follow the odometry's heading drift over a longer stretch). A coupled
    candidate (:attr:`~hippomap.loop_closure.LoopHypothesis.coupling`) keeps the fit's place and is
    turned so that heading + coupling × lateral is what its recognition measured. ``None`` when the
    fit does not hold: a member lies more than ``loop_consistency_m`` from where the fit puts it, or
    the fit turns the robot more than ``loop_view_rad`` away from the way a member's key frame looked
    (recognising a view means facing roughly as it was learned)."""
    fit_m = cfg.loop_fit_window_m
    if fit_m is not None and group:
        newest = max(g.path for g in group)
        anchors = [c for c in anchors if newest - c.path <= fit_m]
    vis = [c for c in group + anchors if not c.measured]
    if len(vis) < 2:
        return group
    odom = np.array([c.odom for c in vis])
    targets = np.array([place_of(c, P) for c in vis])
    T = align_group(odom, targets, cfg.loop_fit_min_spread_m)
    fitted = compose(T, odom)
    if (
        np.max(np.hypot(*(fitted[:, :2] - targets[:, :2]).T)) > cfg.loop_consistency_m
        or np.max(np.abs(wrap_angle(fitted[:, 2] - targets[:, 2]))) > cfg.loop_view_rad
    ):
        return None
    out = []
    for c in group:
        if c.measured:
            out.append(c)
            continue
        robot = se2_compose(T, c.odom)  # where the fit puts the robot on the map at the proposal
        off = se2_between(P[c.node], robot)
        if c.coupling:  # the fit's place, turned so that heading + coupling x lateral is what was measured
            off = (off[0], off[1], c.coupled_heading - c.coupling * off[1])
        out.append(c.with_offset(off))
    return out


def reanchor(P: np.ndarray, node: int, offset: Any, span: int, end: int) -> tuple[int, tuple[float, float, float]]:
    """The node nearest the place a recognition claims, and the robot's offset from it.

    The recognition puts the robot at ``offset`` in the frame of ``node`` (the matched key frame's node)
    on the map ``P`` (N, 3). The looming and the key frame's own offset can put that place metres
    along the old path from ``node``; the loop link would then join two nodes that never stood at
    the same place. The nodes ``node - span`` .. ``node + span`` (ids below ``end``: the node ids
    count along the path, so these are the old path around it) are searched for the one nearest
    the claimed place, and the offset is re-expressed in its frame: the claimed pose is unchanged.
    What a coupled heading reads (:attr:`~hippomap.loop_closure.LoopHypothesis.coupling`, heading +
    coupling x lateral) moves with the frame only approximately, off by about coupling x the turn
    between the two nodes x the new offset's length, small because that offset is short.
    ``(node, offset)`` unchanged when ``node`` is nearest.
    """
    off = vec3(offset, "offset")
    lo, hi = max(0, node - span), min(len(P), end, node + span + 1)
    if hi <= lo + 1 or not lo <= node < hi:
        return node, off
    claim = se2_compose([float(v) for v in P[node]], off)
    k = lo + int(np.argmin(np.hypot(P[lo:hi, 0] - claim[0], P[lo:hi, 1] - claim[1])))
    if k == node:
        return node, off
    return k, se2_between([float(v) for v in P[k]], claim)
