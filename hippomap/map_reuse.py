"""The cognitive map of a run started in a saved map (``Mapper.from_base``) or localising only.

:class:`ReuseMap` is :class:`~hippomap.cognitive_map.CognitiveMap` with the two states a saved
map needs (lost: no pose on the map yet; localise only: the map never changes), kept out of the
map's own module; :class:`~hippomap.mapper.Mapper` always builds its map as one, and the states
are off in an ordinary run.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np

from .cognitive_map import CognitiveMap
from .geometry import compose, se2_between, se2_compose, se2_inverse, wrap_angle
from .loop_closure import LoopBook, LoopDecision, LoopHypothesis

__all__ = ["ReuseMap"]


class ReuseMap(CognitiveMap):
    """The cognitive map with two states a saved map needs, kept out of the map's own module.

    * ``lost``: the robot has no pose on the map yet (a new run in a saved map). Hypotheses
      skip the loop gate (there is no pose to gate with) and are accepted only when verified by
      cycle consistency (``loop_accept = 'verified'``, whatever the config says: one recognition
      must not place the robot); the first accepted group places the run. In map mode the run's
      own nodes (``component_from`` on) float unlinked until then and are moved onto the map
      rigidly when the first loop link joins them, so the solve starts near its answer; nothing is
      solved while they float (they are not tied to the anchored map).
    * ``localise_only``: accepted hypotheses relocalise the robot but add no link, and the map is
      never solved, so node poses stay exactly as loaded.

    Everything else is :class:`CognitiveMap`'s, through its own loop-closure door
    (:meth:`CognitiveMap.propose_loop`).
    """

    def __init__(self, cfg=None, capacity: int = 256):
        super().__init__(cfg, capacity)
        self.own_cfg = self.cfg
        self.localise_only = False
        self.lost = False
        self.component_from = -1  # map mode while lost: first node of the run's own, unplaced nodes

    def configure(self, localise_only: bool, lost: bool, component_from: int = -1) -> None:
        """Set the mode and the lost state; while lost or localising only verified groups are accepted."""
        self.localise_only, self.lost, self.component_from = bool(localise_only), bool(lost), int(component_from)
        update: dict[str, Any] = {}
        if self.lost or self.localise_only:
            update.update(loop_accept="verified", loop_relocalise=True)
        if self.lost and self.own_cfg.prune_graph_radius_m is None:
            # online pruning merges along the graph only, never into the saved map the run floats over
            update["prune_graph_radius_m"] = 1e12
        self.cfg = self.own_cfg.model_copy(update=update) if update else self.own_cfg

    def start_run(self, initial_pose) -> None:
        """A new run on this map, from an unknown pose: its odometry frame starts at ``initial_pose``.
        The loop book starts empty (its candidates are the previous run's odometry); in map mode the
        run gets its own start node, linked to nothing until a loop closure places it."""
        self._loops = LoopBook()
        self._events = []
        self._t = None
        self._code = None
        self._anchor = None
        self._arrival = -1
        self._odom = cast("tuple[float, float, float]", tuple(float(v) for v in initial_pose))
        self._code_odom = self._odom
        self._t_arrive = 0.0
        if self.localise_only:
            self._delta = se2_between(tuple(self._P[self._cur]), self._odom)
            self.configure(True, True, -1)
        else:
            start = self._add_node(self._odom, (np.nan, np.nan, np.nan), 0.0)  # dated by the run's first update
            self._cur, self._delta = start, (0.0, 0.0, 0.0)
            self.configure(False, True, start)

    def propose_loop(self, h: LoopHypothesis) -> LoopDecision:
        """The map's own door; while lost, the decisions made here record no gate (there was none),
        and in localisation mode an accepted one says that it only relocalised the robot."""
        if not (self.lost or self.localise_only):
            return super().propose_loop(h)
        was_lost = self.lost
        book = self._loops
        waiting = [c.id for c in book.pending]  # the decisions this call may accept besides its own
        decision = super().propose_loop(h)
        if was_lost:
            book.decisions[decision.id] = _replace(
                book.decisions[decision.id], gate_distance=math.nan, gate_limit=math.nan
            )
        for i in waiting + [decision.id]:
            d = book.decisions[i]
            if d.status != "accepted" or d.decided_step != self._step:
                continue
            checks, _, rest = d.reason.partition(";")
            if was_lost and checks.startswith("gate"):
                checks = "no gate (the robot was not placed on the map yet)" + checks.removeprefix("gate").replace(
                    " and ", "; ", 1
                )
            if self.localise_only and d.link < 0:
                rest = " localisation only: robot relocalised, no link"
            book.decisions[i] = _replace(d, reason=checks + (";" + rest if rest else ""))
        if self.lost and decision.status == "accepted":  # placed (map mode: already, by the first link)
            self.configure(self.localise_only, False)
        return book.decisions[decision.id]

    def _gate(self, c):
        if self.lost and (self.component_from < 0 or c.node < self.component_from):
            return 0.0, math.inf, "unplaced"
        return super()._gate(c)

    def _add_loop_link(self, c) -> int:
        if self.localise_only:
            return -1
        if self.lost and self.component_from >= 0 and c.node < self.component_from <= c.from_node:
            self._place(c)
        return super()._add_loop_link(c)

    def _place(self, c) -> None:
        """Move the run's own nodes rigidly so that ``c.from_node`` sits where the (fitted)
        hypothesis puts it on the map; the run is placed from now on."""
        k = self.component_from
        new_from = se2_compose(tuple(self._P[c.node]), se2_inverse(c.link_tr))
        T = np.asarray(se2_compose(new_from, se2_inverse(tuple(self._P[c.from_node]))))
        P = self._P[k : self._n]
        P[:] = compose(T, P)
        P[:, 2] = wrap_angle(P[:, 2])
        self.configure(self.localise_only, False)

    def _optimise(self, t: float, force: bool = False, sweeps: int | None = None):
        if self.localise_only or (self.lost and self.component_from >= 0):
            return []
        return super()._optimise(t, force, sweeps)


def _replace(d: LoopDecision, **kw: Any) -> LoopDecision:
    from dataclasses import replace

    return replace(d, **kw)
