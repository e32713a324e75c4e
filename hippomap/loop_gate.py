"""The loop gate: which loop hypotheses the map may take at once (paper §2.4, Eq. 13; spec §4).

The layer of :class:`~hippomap.cognitive_map.CognitiveMap` between its correction
(:class:`~hippomap.map_correction.MapCorrection`) and its loop closing
(:class:`~hippomap.loop_closing.LoopClosing`): where a hypothesis puts the node it names must lie within
:func:`~hippomap.loop_closure.gate_limit` of the node (the map's pose, or its place code as in Eq. 13), a radius
that grows with the drift path (docs/MODEL.md items 21, 47 and 58); a visual hypothesis must also give the node a
heading within ``loop_heading_radius_rad`` + ``loop_heading_per_m`` x the drift path of its map heading (item 90),
once a verified closure has anchored the map within ``loop_heading_anchored_rad`` + the odometry's heading walk over
that path (item 107), and then, to wait for a group, within a few standard deviations of that walk (item 111);
beyond, it waits for a long group (item 130). The mapper's recognition candidates are the nodes inside the same gate
(:meth:`LoopGate.loop_candidates`). A hypothesis outside the gate is rejected, or waits for a consistent group
(:mod:`hippomap.loop_closing`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .geometry import se2_compose, wrap_angle
from .loop_closure import Candidate, LoopDecision, LoopHypothesis
from .map_correction import MapCorrection

__all__ = ["OBLIQUE", "OUTER_PART", "LoopGate"]

# where a hypothesis inside the gate that waits for a consistent group lies: its pending and accepted reasons say so
OUTER_PART = "in the gate's outer part"
#: how the reason of a hypothesis recognised across a wide turn (``loop_oblique_turn_rad``) says so
OBLIQUE = "across a wide turn"


class LoopGate(MapCorrection):
    """The gate of loop hypotheses, over :class:`~hippomap.map_correction.MapCorrection`."""

    def loop_candidates(self, limit: int | None = None) -> np.ndarray:
        """Ids of the nodes a visual hypothesis made now could name and pass the gate with:
        within :func:`~hippomap.loop_closure.gate_limit` of the robot (unmeasured hypothesis, no
        offset), not current nor among the last ``N_excl`` nodes; nearest first."""
        n = self._n
        r = self.robot_map_pose()
        d = np.hypot(self._P[:n, 0] - r[0], self._P[:n, 1] - r[1])
        lim = self._gate_limit(np.arange(n), False)
        mask = d < lim
        mask[max(0, n - self.cfg.exclude_recent) :] = False
        mask[self._cur] = False
        ids = np.flatnonzero(mask)
        ids = ids[np.argsort(d[ids], kind="stable")]
        return ids if limit is None else ids[:limit]

    def _screen(self, h: LoopHypothesis, cand: Candidate) -> tuple[LoopDecision, str, bool, bool]:
        """The first checks of :meth:`propose_loop`: (pending decision with its gate distance and
        limit, reason to reject or "", whether the hypothesis fell outside the gate, whether it is turned beyond a
        group's heading bound and may wait only for a long group, ``loop_turned_group``)."""
        cfg = self.cfg
        base = LoopDecision(cand.id, "pending", "", h, self._cur, proposed_step=self._step)
        reason = ""
        outside = turned = False
        if h.node != self._cur and h.node >= self._n - cfg.exclude_recent:
            reason = f"node {h.node} is among the {cfg.exclude_recent} most recent nodes"
        else:
            dist, limit, what = self._gate(cand)
            if dist is None:
                reason = "no place code yet to gate the hypothesis"
            else:
                base = replace(base, gate_distance=dist, gate_limit=limit)
                if not dist < limit:
                    reason = f"{what} distance {dist:.3f} m exceeds the gate {limit:.3f} m"
                    outside = True
                elif math.isfinite(limit):  # a waived gate (a run not yet placed on a saved map) waives both parts
                    reason = self._heading_gate(cand) or self._outer_gate(cand, dist, limit, what) or self._oblique(h)
                    outside = bool(reason)
                beyond = self._beyond_group_heading(cand) if outside else ""
                if beyond:  # only a long group can make it right (item 130), or none: rejected at once (item 111)
                    reason, turned = f"{reason}, and {beyond}", cfg.loop_turned_group is not None
                    outside = turned
        return base, reason, outside, turned

    def _heading_gate(self, c: Candidate) -> str:
        """Why visual candidate ``c`` is outside the gate's heading part, or "": the heading it gives the named node
        (the robot's map heading ⊕ the hypothesis) must be within ``loop_heading_radius_rad`` +
        ``loop_heading_per_m`` × the drift path (the position gate's, :meth:`_drift`) of the node's map heading. The
        position gate alone let a recognition through that turns the map by a right angle a few metres after a
        verified closure (docs/MODEL.md). Once a verified closure has anchored the map (and the odometry's bias), the
        part is at most ``loop_heading_anchored_rad`` + ``loop_heading_anchored_sd`` × the odometry's heading sd over
        the drift path: a lateral alias read as a turn of 0.7-0.8 rad passed 0.8 + 0.02 rad/m at the end of a long
        route (docs/MODEL.md item 107), plus the turn of the heading-rate error the gate allows for since that closure
        (``loop_heading_bias``, item 125). Measured transforms keep their own heading check."""
        cfg = self.cfg
        if cfg.loop_heading_radius_rad is None or c.measured:
            return ""
        turn, drift, walk = self._turn(c)
        limit = cfg.loop_heading_radius_rad + cfg.loop_heading_per_m * drift
        if cfg.loop_heading_anchored_rad is not None and self._loops.last_verified_path is not None:
            limit = min(limit, cfg.loop_heading_anchored_rad + cfg.loop_heading_anchored_sd * walk + self._bias_turn())
        return f"heading {turn:.3f} rad from the node's exceeds the gate {limit:.3f} rad" if turn > limit else ""

    def _beyond_group_heading(self, c: Candidate) -> str:
        """Why visual candidate ``c``, outside the gate, may wait only for a long group (``loop_turned_group``; None:
        it is rejected at once), or "": once a verified closure has anchored the map, the heading it gives its node
        must be within ``loop_heading_anchored_rad`` + ``loop_heading_group_sd`` × the odometry's heading sd over the
        drift path of the node's map heading. Three
        recognitions that named places 3.7-5.7 m away and turned them by 2.1 rad, 13 standard deviations of that
        walk, agreed with each other, were linked as a group at full weight and bent the long path between them and
        their nodes for 630 s of a run (docs/MODEL.md item 111); the bound, too, adds the turn of the heading-rate
        error the gate allows for (``loop_heading_bias``, item 125). A gyro bias that wanders turns the map by up to
        2 rad over a long excursion, so that the right recognitions at its end lie beyond too: a long group may take
        them (item 130). Measured transforms keep their own heading check."""
        cfg = self.cfg
        if cfg.loop_heading_group_sd is None or cfg.loop_heading_anchored_rad is None or c.measured:
            return ""
        if self._loops.last_verified_path is None:  # before the first verified closure the bias turns true ones far
            return ""
        turn, _, walk = self._turn(c)
        bound = cfg.loop_heading_anchored_rad + cfg.loop_heading_group_sd * walk + self._bias_turn()
        return f"its heading {turn:.3f} rad is beyond a group's {bound:.3f} rad" if turn > bound else ""

    def _turn(self, c: Candidate) -> tuple[float, float, float]:
        """(how far visual candidate ``c`` turns its node's map heading, the drift path (:meth:`_drift`), the
        odometry's heading sd over that path: √(path / its heading information per metre))."""
        turn = abs(wrap_angle(se2_compose(self.robot_map_pose(), c.M)[2] - float(self._P[c.node, 2])))
        drift = float(self._drift(np.array([c.node]), False)[0])
        return turn, drift, math.sqrt(drift / self.cfg.odometry_information_per_m[1])

    def _outer_gate(self, c: Candidate, dist: float, limit: float, what: str) -> str:
        """Why visual candidate ``c``, inside the gate at ``dist`` of ``limit``, lies in its outer part
        (``loop_outer_gate``), or "": such a hypothesis waits for a consistent group as one outside does."""
        f = self.cfg.loop_outer_gate
        if f is None or c.measured or dist < f * limit:
            return ""
        return f"{what} distance {dist:.3f} m is {OUTER_PART} (from {f * limit:.3f} m)"

    def _oblique(self, h: LoopHypothesis) -> str:
        """Why visual hypothesis ``h`` was recognised across a turn of at least ``loop_oblique_turn_rad`` from its key
        frame's view (``meta['view_turn']``, the mapper's image-shift heading), or "": such a hypothesis waits for a
        consistent group as one outside the gate does. Of the recognitions of the simulated tuning runs that named a
        key frame, 0.4 % of those read below 0.15 rad were more than 2 m from it, 16 % of those at 0.4 rad or more
        (docs/MODEL.md item 124)."""
        bar, turn = self.cfg.loop_oblique_turn_rad, h.meta.get("view_turn")
        if bar is None or turn is None or abs(turn) < bar:
            return ""
        return f"{OBLIQUE}: view turned {abs(turn):.3f} rad from its key frame's (from {bar:.3f} rad)"

    def _gate(self, c: Candidate) -> tuple[float | None, float, str]:
        """(distance, limit, what) of the gate for candidate ``c``; distance None: cannot gate."""
        cfg = self.cfg
        limit = float(self._gate_limit(np.array([c.node]), c.measured)[0])
        if cfg.loop_gate == "map":
            pred = se2_compose(self.robot_map_pose(), c.M)
            return math.hypot(pred[0] - self._P[c.node, 0], pred[1] - self._P[c.node, 1]), limit, "map"
        code = self._robot_code()
        if code is None or np.isnan(self._C[c.node, 0]):
            return None, limit, "place-code"
        pred = se2_compose(code, c.M)
        return cfg.mu_p * math.hypot(pred[0] - self._C[c.node, 0], pred[1] - self._C[c.node, 1]), limit, "place-code"
