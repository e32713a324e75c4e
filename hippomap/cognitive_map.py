"""The cognitive map: nodes, links, loop closure, relaxation and pruning (paper §2.4; spec §4).

:class:`CognitiveMap` is built in layers, one concept per module, each using only those beneath it: the
graph (:mod:`hippomap.map_graph`: nodes, links, the robot's place, read-only views), map correction
(:mod:`hippomap.map_correction`: relaxation and robust reweighting), loop closing
(:mod:`hippomap.loop_gate`, :mod:`hippomap.loop_record`, :mod:`hippomap.loop_closing`, with its data and
maths in :mod:`hippomap.loop_closure`) and pruning (:mod:`hippomap.pruning`). This module adds the
per-step update and the map's state.

A node ``e_i = {p_i, V_i, l_i}`` (Eq. 11) holds the place code ``p_i`` (x, y, θ) that
created it, the id ``V_i`` of the key frame learned there (-1: none) and its pose ``l_i`` in
the map, which relaxation (Eq. 14) moves. The robot is tracked as its SE(2) pose ``Δ``
*relative to the current node* (in that node's frame).

Per :meth:`CognitiveMap.update` (one odometry increment, maybe a place code):

1. ``Δ ← Δ ⊕ increment``.
2. If a place code ``p`` exists and ``S_cur = μ_p ‖p_cur − p‖ > S_th`` (Eq. 12–13):
   CREATE_NODE at ``l_cur ⊕ Δ`` linked from the current node — unless online pruning
   (Eq. 15, Fig. 7) finds an older node A in the new node's block (side b), which is
   neither current nor among the last ``N_excl`` nodes: then no node is created, the current
   node is linked to A and A becomes current, with the robot's residual offset kept.
3. Pending loop hypotheses older than ``loop_support_window`` updates are rejected.
4. After any change of the graph, the map is corrected (``MapConfig.solver``, see
   :mod:`hippomap.relaxation`).

Loop closures enter through one door, :meth:`CognitiveMap.propose_loop`, and are checked
by (a) a place-code gate whose radius grows with the path travelled since the matched node
and (b) cycle consistency between hypotheses (see :meth:`CognitiveMap.propose_loop`).
Every decision is kept in :attr:`CognitiveMap.loop_decisions`.
"""

from __future__ import annotations

import math
from typing import Any, Self

import numpy as np

from .config import MapConfig
from .errors import InputError, finite, vec3
from .geometry import se2_between, se2_compose, se2_inverse
from .loop_closure import LoopBook, LoopDecision, LoopHypothesis
from .map_events import (
    LoopAccepted,
    LoopPending,
    LoopRejected,
    MapEvent,
    MapRelaxed,
    NodeCreated,
    NodeMerged,
    NodesPruned,
)
from .map_graph import LINK_KINDS, LOOP, ODOMETRY, PRUNE
from .pruning import Pruning

# names long imported from this module (tests, server, viewer, benchmarks)
__all__ = [
    "CognitiveMap",
    "LINK_KINDS",
    "ODOMETRY",
    "LOOP",
    "PRUNE",
    "LoopDecision",
    "LoopHypothesis",
    "MapEvent",
    "NodeCreated",
    "NodeMerged",
    "LoopPending",
    "LoopAccepted",
    "LoopRejected",
    "MapRelaxed",
    "NodesPruned",
]

_STATE_VERSION = 1

_compose3, _inv3, _between3 = se2_compose, se2_inverse, se2_between
_vec3 = vec3


# --------------------------------------------------------------------------- the map
class CognitiveMap(Pruning):
    """The cognitive map of [S] §2.4 (spec §4). See the module doc for the algorithm.

    Public read-only views: :attr:`poses` (N, 3) map poses ``l``, :attr:`place_codes`
    (N, 3) ``p`` (NaN for the first node until a place code arrives), :attr:`frames` (N,)
    ``V`` (-1: none), :attr:`times` (N,) creation times, :attr:`links` (dict of arrays),
    :attr:`current`, :attr:`robot_offset`, :attr:`robot_pose`, :attr:`loop_decisions`.
    """

    #: a run that only localises in a saved map (:class:`~hippomap.map_reuse.ReuseMap`) starts on one of its
    #: nodes, whose time it keeps
    localise_only = False

    # ------------------------------------------------------------------ the per-step update
    def update(self, place_code, increment, t: float) -> list[MapEvent]:
        """One step: robot-frame odometry ``increment`` (dx, dy, dθ) since the last call, the
        place code (x, y, θ) of this step or ``None`` (no single place field), time ``t``.

        Returns the events of this step, preceded by any queued since the last call and not
        taken with :meth:`take_events` (loop decisions made by :meth:`propose_loop`, frames assigned).
        """
        inc = _vec3(increment, "odometry increment")
        code = None if place_code is None else _vec3(place_code, "place code")
        t = finite("time t", t)
        if self._t is not None and t < self._t:
            raise InputError(f"time t={t} is before the previous update's time {self._t}")
        if self._t is None:  # a run's first step: its first node's time starts here, not at t = 0
            self._t_arrive = t
            if not self.localise_only:  # the current node is the run's start node, made before any time was known
                self._Tn[self._cur] = t
        self._t = t
        self._delta = _compose3(self._delta, inc)
        self._odom = _compose3(self._odom, inc)
        self._path += math.hypot(inc[0], inc[1])
        self._step += 1
        events, self._events = self._events, []
        changed = False
        if code is not None:
            self._code, self._code_odom = code, self._odom
            if self._anchor is None:
                self._anchor = _compose3(code, _inv3(self._delta))
                if np.isnan(self._C[self._cur, 0]):
                    self._C[self._cur] = self._anchor
            s_cur = self.cfg.mu_p * math.hypot(code[0] - self._anchor[0], code[1] - self._anchor[1])
            if s_cur > self.cfg.node_spacing_m:
                events.append(self._create_or_merge(code, t))
                changed = True
        events.extend(self._expire())
        if changed or self._dirty:
            events.extend(self._optimise(t))
        return events

    def _create_or_merge(self, code, t: float) -> MapEvent:
        cfg = self.cfg
        cur = self._cur
        dt = t - self._t_arrive
        # where the new node would be: with the odometry's estimated heading bias (0 unless the whole
        # solves found one) taken off, so that the map grown between closures does not carry the raw
        # drift a later closure would have to undo (beyond π, its heading residual would wrap)
        q = _compose3(self._P[cur], self._delta)
        q = (q[0], q[1], q[2] - self._bias * dt)
        if cfg.prune_online and self._n > 1:
            a = self._merge_target(q)
            if a is not None:
                offset = _between3(self._P[a], q)
                link = self._add_link(cur, a, _between3(self._P[cur], self._P[a]), PRUNE, dt)
                self._set_current(a, offset, t, link)
                return NodeMerged(a, cur, link, offset, t)
        new = self._add_node(q, code, t)
        link = self._add_link(cur, new, self._delta, ODOMETRY, dt)
        self._cur, self._delta, self._t_arrive, self._anchor, self._arrival = new, (0.0, 0.0, 0.0), t, code, -1
        return NodeCreated(new, cur, link, q, code, t)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The whole map as plain dicts / lists / numpy arrays (see :meth:`from_state`)."""
        n, m = self._n, self._m
        return {
            "version": _STATE_VERSION,
            "nodes": {
                "pose": self._P[:n].copy(),
                "place_code": self._C[:n].copy(),
                "frame": self._F[:n].copy(),
                "time": self._Tn[:n].copy(),
                "path": self._S[:n].copy(),
            },
            "links": {
                "source": self._src[:m].copy(),
                "target": self._dst[:m].copy(),
                "transform": self._tr[:m].copy(),
                "dt": self._dt[:m].copy(),
                "kind": self._kind[:m].astype(np.int64),
                "colour": self._col[:m].copy(),
                "weight": self._w[:m].copy(),
                "information": self._linfo[:m].copy(),
                "kernel_width": self._lkw[:m].copy(),
                "coupling": self._lcoup[:m].copy(),
                "kernel_position_information": self._lkpos[:m].copy(),
            },
            "robot": {
                "current": self._cur,
                "delta": list(self._delta),
                "odom": list(self._odom),
                "path": self._path,
                "step": self._step,
                "t": self._t,
                "t_arrive": self._t_arrive,
                "arrival": self._arrival,
                "code": None if self._code is None else list(self._code),
                "code_odom": list(self._code_odom),
                "anchor": None if self._anchor is None else list(self._anchor),
                "dirty": self._dirty,
                "touched": list(self._touched),
                "local_solves": self._local_solves,
                "local_moved": self._local_moved,
                "local_work": self._local_work,
                "whole_work": self._whole_work,
                "solved_path": None if math.isinf(self._solved_path) else self._solved_path,
                "solved_t": None if math.isinf(self._solved_t) else self._solved_t,
                "odometry_bias": self._bias,
                "odometry_bias_sd": self._bias_sd,
                "odometry_bias_unkept": self._bias_unkept,
            },
            "loop": self._loops.state_dict(),
            "events": [e.to_dict() for e in self._events],
        }

    @classmethod
    def from_state(cls, cfg: MapConfig, state: dict[str, Any]) -> Self:
        """Rebuild a map from :meth:`state_dict`; it produces the same future outputs."""
        try:
            if state.get("version") != _STATE_VERSION:
                raise InputError(f"unsupported cognitive-map state version {state.get('version')!r}")
            nodes, links, robot, loop = state["nodes"], state["links"], state["robot"], state["loop"]
            P = np.asarray(nodes["pose"], dtype=float).reshape(-1, 3)
            n = len(P)
            m = len(np.asarray(links["source"]))
            cmap = cls(cfg, capacity=max(n, m, 4))
            cmap._n, cmap._m = n, m
            cmap._P[:n] = P
            cmap._C[:n] = np.asarray(nodes["place_code"], dtype=float).reshape(n, 3)
            cmap._F[:n] = np.asarray(nodes["frame"], dtype=np.int64)
            cmap._Tn[:n] = np.asarray(nodes["time"], dtype=float)
            cmap._S[:n] = np.asarray(nodes["path"], dtype=float)
            cmap._src[:m] = np.asarray(links["source"], dtype=np.int64)
            cmap._dst[:m] = np.asarray(links["target"], dtype=np.int64)
            cmap._tr[:m] = np.asarray(links["transform"], dtype=float).reshape(m, 3)
            cmap._dt[:m] = np.asarray(links["dt"], dtype=float)
            cmap._kind[:m] = np.asarray(links["kind"], dtype=np.int8)
            cmap._w[:m] = np.asarray(links.get("weight", np.ones(m)), dtype=float)
            li = links.get("information")
            li = np.tile(cfg.loop_information, (m, 1)) if li is None else np.asarray(li, dtype=float)
            li = li.reshape(m, 2 if li.size == 2 * m else 3)  # (x/y, heading) in states before (x, y, heading)
            cmap._linfo[:m] = li if li.shape[1] == 3 else li[:, [0, 0, 1]]
            cmap._lkw[:m] = np.asarray(links.get("kernel_width", np.full(m, cfg.loop_kernel_width)), dtype=float)
            cmap._lcoup[:m] = np.asarray(links.get("coupling", np.zeros(m)), dtype=float)
            kpos = links.get("kernel_position_information")  # states before it: the link's own x
            cmap._lkpos[:m] = cmap._linfo[:m, 0] if kpos is None else np.asarray(kpos, dtype=float)
            if n == 0 or not np.all(np.isfinite(cmap._P[:n])):
                raise InputError("cognitive-map state: node poses missing or not finite")
            ends = np.concatenate([cmap._src[:m], cmap._dst[:m]])
            if m and (ends.max() >= n or ends.min() < 0):
                raise InputError("cognitive-map state: a link names a node that does not exist")
            cmap._rebuild_link_index(links.get("colour"))
            cmap._restore_robot(robot)
            cmap._loops = LoopBook.from_state(loop)
            cmap._events = [MapEvent.from_dict(e) for e in state.get("events", [])]
            cmap._version += 1
            return cmap
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"malformed cognitive-map state: {exc!r}") from exc

    def _restore_robot(self, robot: dict[str, Any]) -> None:
        """The robot's part of :meth:`from_state`: its node, offset, clocks and the correction's state."""
        self._cur = int(robot["current"])
        if not 0 <= self._cur < self._n:
            raise InputError(f"cognitive-map state: current node {self._cur} does not exist")
        self._delta = _vec3(robot["delta"], "state robot.delta")
        self._odom = _vec3(robot["odom"], "state robot.odom")
        self._path = float(robot["path"])
        self._step = int(robot["step"])
        self._t = None if robot["t"] is None else float(robot["t"])
        self._t_arrive = float(robot["t_arrive"])
        self._arrival = int(robot.get("arrival", -1))
        self._code = None if robot["code"] is None else _vec3(robot["code"], "state robot.code")
        self._code_odom = _vec3(robot["code_odom"], "state robot.code_odom")
        self._anchor = None if robot["anchor"] is None else _vec3(robot["anchor"], "state robot.anchor")
        self._dirty = bool(robot["dirty"])
        self._touched = [int(k) for k in robot.get("touched", [-1] if self._dirty else [])]
        self._local_solves = int(robot.get("local_solves", 0))
        self._local_moved = int(robot.get("local_moved", 0))
        self._local_work = int(robot.get("local_work", 0))
        self._whole_work = int(robot.get("whole_work", 0))
        sp = robot.get("solved_path")
        self._solved_path = -math.inf if sp is None else float(sp)
        st = robot.get("solved_t")
        self._solved_t = -math.inf if st is None else float(st)
        self._bias = float(robot.get("odometry_bias", 0.0))
        self._bias_sd = float(robot.get("odometry_bias_sd", 0.0))
        self._bias_unkept = float(robot.get("odometry_bias_unkept", 0.0))
