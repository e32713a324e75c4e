"""Where a run in a saved map is on that map: what the viewer may draw in the map frame.

A session started from a base map (``POST /sessions`` with ``base_session``, or a merge) begins
``lost``: the robot's pose on the map is unknown until a verified group of recognitions places it
(:class:`hippomap.mapper.Mapper`, ``stats()["lost"]``). Until then its trajectory rows hold an
odometric guess that is not a map pose, and the loop decisions made while lost (they carry no
gate, so their ``gate_distance`` is NaN) start at ``from_node``, the node the map happened to hold
as current, not one the robot was near.

* In map mode the run's own nodes are moved onto the map when it is placed, so every row of the
  trajectory is on the map from then on.
* In localisation mode (``mapper.mode = 'localise'``) nothing moves: the rows recorded before the
  placement stay where the guess put them, so only rows from the placement on are drawn, and
  the decisions that placed the robot are not drawn as segments from ``from_node``.

The placement time is that of the first group of decisions accepted together while lost: the
newest hypothesis of the group (the one whose proposal made the group consistent).

:func:`drawn_trajectories` applies the rule to trajectory rows, for the live layers
(:mod:`web.scene.trajectories`) and the time slider's replay (:mod:`web.scene.replay`) alike: the
map trajectory is drawn from the first row on the map; the raw odometry of a run in a saved map,
which lives in the run's own odometric frame, is drawn from that row too, moved rigidly so that
its pose there is that row's map pose (where the run joined the map; it then drifts as odometry
does). A fresh run's odometry is the frame the map started in: it is drawn as recorded.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from hippomap.cognitive_map import LoopDecision
from hippomap.geometry import between, compose

from ..snapshot import TRAJ_NODE, TRAJ_OFFSET, TRAJ_RAW


def decided_while_lost(d: LoopDecision) -> bool:
    """An accepted decision made before the robot had a pose on the map (no gate: NaN distance)."""
    return d.status == "accepted" and math.isnan(d.gate_distance)


@dataclass(frozen=True)
class Placement:
    """What of a session's run is on the map.

    ``based``: the session started in a saved map (``base_nodes > 0``); ``localise``: it only
    localises; ``lost``: not placed yet; ``on_map_from_t``: trajectory rows with ``t`` at or after
    this are map poses (``-inf``: all of them, ``+inf``: none yet).
    """

    based: bool
    localise: bool
    lost: bool
    on_map_from_t: float

    @property
    def hides_lost_decisions(self) -> bool:
        """Whether the decisions made while lost are drawn without their segment (localisation mode,
        where ``from_node`` was never the robot's node)."""
        return self.localise and self.based


def placement(stats: dict[str, Any], decisions: Sequence[LoopDecision]) -> Placement:
    """The placement of the run of a session with mapper ``stats`` and loop ``decisions``."""
    based = int(stats.get("base_nodes") or 0) > 0
    localise = stats.get("mode") == "localise"
    lost = bool(stats.get("lost", False))
    if lost:
        return Placement(based, localise, True, math.inf)
    if not (based and localise):
        return Placement(based, localise, False, -math.inf)
    placing = [d for d in decisions if decided_while_lost(d)]
    if not placing:  # placed without a decision we hold (cannot happen in a live session): draw all
        return Placement(based, localise, False, -math.inf)
    first = min(d.decided_step for d in placing)
    t = max(float(d.hypothesis.time) for d in placing if d.decided_step == first)
    return Placement(based, localise, False, t)


def map_poses(rows: np.ndarray, node_poses: np.ndarray) -> np.ndarray:
    """(K, 3) map poses of trajectory ``rows``: their node's pose (+) the robot's offset from it."""
    n = len(node_poses)
    if not n or not len(rows):
        return np.empty((0, 3))
    nodes = np.clip(rows[:, TRAJ_NODE].astype(np.int64), 0, n - 1)
    return compose(node_poses[nodes], rows[:, TRAJ_OFFSET])


def drawn_trajectories(rows: np.ndarray, node_poses: np.ndarray, placed: Placement) -> tuple[np.ndarray, np.ndarray]:
    """(odometry, map): the (K, 3) raw-odometry and (J, 3) map poses the viewer draws for the
    trajectory ``rows`` (t, raw x y theta, node, offset x y theta) of a run with ``placed``.

    The map poses are those of the rows with ``t >= placed.on_map_from_t``. The odometry is the raw
    poses of every row for a fresh run; for a run in a saved map it is the raw poses of the rows on
    the map, composed with the rigid move that puts the first of them on its map pose (nothing
    before the placement: the run's own frame is not the map's)."""
    rows = np.asarray(rows, float).reshape(-1, 8)
    on = rows[rows[:, 0] >= placed.on_map_from_t]
    poses = map_poses(on, node_poses)
    if not placed.based:
        return rows[:, TRAJ_RAW], poses
    if not len(poses):
        return np.empty((0, 3)), poses
    raw = on[:, TRAJ_RAW]
    return compose(poses[0], between(raw[0], raw)), poses
