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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

from hippomap.cognitive_map import LoopDecision


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
