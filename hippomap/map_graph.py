"""The map's graph: node and link storage, the robot's place on it, read-only views (paper §2.4; spec §4).

A node ``e_i = {p_i, V_i, l_i}`` (Eq. 11) holds the place code ``p_i`` (x, y, θ) that
created it, the id ``V_i`` of the key frame learned there (-1: none) and its pose ``l_i`` in
the map, which relaxation (Eq. 14) moves. Links follow [ORS] ``on_create_link``: each stores
the pose of its target in the frame of its source (``transform``; the [ORS] ``d``,
``heading``, ``facing`` are derived from it), the time ``dt`` spent on it, and its kind
(``odometry``, ``loop`` or ``prune``).

Storage is struct-of-arrays: growable numpy arrays (capacity doubling), no Python object per
node or link. The robot is tracked as its SE(2) pose ``Δ`` *relative to the current node*
(in that node's frame), so nothing is lost when the current node changes.

:class:`MapGraph` is the lowest layer of :class:`~hippomap.cognitive_map.CognitiveMap`: it holds the
whole state of the map (also the loop book and the solver's bookkeeping, so that one constructor and one
:meth:`~hippomap.cognitive_map.CognitiveMap.state_dict` see all of it); the layers above it add map
correction (:mod:`hippomap.map_correction`), loop closing (:mod:`hippomap.loop_gate`,
:mod:`hippomap.loop_record`, :mod:`hippomap.loop_closing`) and pruning (:mod:`hippomap.pruning`), each
using only the layers beneath it.
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np

from .config import MapConfig
from .errors import InputError, finite, node_id, vec3
from .geometry import se2_between, se2_compose, se2_inverse, wrap_angle
from .graph_paths import GraphPaths
from .loop_closure import LoopBook, bias_drift, bias_rate_error, drift_path, gate_limit, link_errors, link_info3
from .map_events import FrameAssigned, MapEvent
from .relaxation import ColourGroups, colour_link, edge_colouring
from .robust_kernel import USED_WEIGHT, kernel_weights

__all__ = ["LINK_KINDS", "ODOMETRY", "LOOP", "PRUNE", "MapGraph"]

#: link kinds, stored as small integer codes
LINK_KINDS = ("odometry", "loop", "prune")
ODOMETRY, LOOP, PRUNE = 0, 1, 2

_compose3, _inv3, _between3 = se2_compose, se2_inverse, se2_between
_vec3, _node_id = vec3, node_id


class MapGraph:
    """Nodes, links and the robot's pose relative to its current node (see the module doc).

    Public read-only views: :attr:`poses` (N, 3) map poses ``l``, :attr:`place_codes`
    (N, 3) ``p`` (NaN for the first node until a place code arrives), :attr:`frames` (N,)
    ``V`` (-1: none), :attr:`times` (N,) creation times, :attr:`links` (dict of arrays),
    :attr:`current`, :attr:`robot_offset`, :attr:`robot_pose`.
    """

    def __init__(self, cfg: MapConfig | None = None, capacity: int = 256):
        self.cfg = cfg if cfg is not None else MapConfig()
        if not isinstance(self.cfg, MapConfig):
            raise InputError(f"CognitiveMap needs a MapConfig, got {type(cfg).__name__}")
        cap = max(int(capacity), 4)
        self._n = 0
        self._P = np.zeros((cap, 3))  # map poses l_i
        self._C = np.full((cap, 3), np.nan)  # place codes p_i
        self._F = np.full(cap, -1, dtype=np.int64)  # key frame V_i
        self._Tn = np.zeros(cap)  # creation time
        self._S = np.zeros(cap)  # odometric path length at creation (m)
        self._mask = np.zeros(cap, dtype=np.int64)  # edge-colour bitmask of each node
        self._m = 0
        self._src = np.zeros(cap, dtype=np.int64)
        self._dst = np.zeros(cap, dtype=np.int64)
        self._tr = np.zeros((cap, 3))
        self._dt = np.zeros(cap)
        self._kind = np.zeros(cap, dtype=np.int8)
        self._col = np.zeros(cap, dtype=np.int64)
        self._w = np.ones(cap)  # robust weight of each link (loop links: revised, see _reweight)
        self._linfo = np.zeros((cap, 3))  # information (x, y, heading; source frame) of loop links
        self._lkw = np.ones(cap)  # robust kernel width of loop links (standard deviations)
        self._lcoup = np.zeros(cap)  # heading-lateral coupling of visual loop links (m^-1; loop_closure.couple)
        self._lkpos = np.zeros(cap)  # information the kernel weighs a loop link's position error at (_kernel_weights)
        self._pairs: set[tuple[int, int]] = set()
        self._groups: ColourGroups | None = None
        self._groups_key = -1
        self._version = 0
        self._dirty = False  # lsq: a link with a non-zero residual was added since the last solve
        self._touched: list[int] = []  # links added or changed since the last solve; -1: the whole map
        self._local_solves = 0  # local solves since the last solve of the whole map
        self._local_moved = 0  # nodes those local solves moved, summed (see MapCorrection._whole_due)
        self._local_work = 0  # those local solves' work (RelaxResult.work: factor nonzeros), summed
        self._whole_work = 0  # the last whole solve's work (see MapCorrection._whole_due)
        self._solved_path = -math.inf  # odometric path (m) at the last correction (see MapCorrection._deferred)
        self._solved_t = -math.inf  # time of the last correction
        self._bias = 0.0  # the odometry's heading bias (rad/s), estimated by the whole solves (see _bias_args)
        self._bias_sd = 0.0  # its posterior standard deviation (rad/s) when a whole solve kept it (or, with
        # loop_bias_unkept, did not); 0: none
        self._bias_unkept = 0.0  # the size (rad/s) of the last whole solve's estimate when it was not kept
        # robot state
        self._cur = 0
        self._delta = (0.0, 0.0, 0.0)  # robot pose in the current node's frame
        self._odom = _vec3(self.cfg.initial_pose, "initial_pose")  # dead-reckoned robot pose
        self._path = 0.0
        self._step = 0
        self._t: float | None = None
        self._t_arrive = 0.0
        self._arrival = -1  # link by which the robot reached the current node by a merge or a loop (-1: none)
        self._code: tuple[float, float, float] | None = None
        self._code_odom = self._odom
        self._anchor: tuple[float, float, float] | None = None  # place code of the current node, re-anchored
        self._events: list[MapEvent] = []
        self._loops = LoopBook()
        self._paths = GraphPaths()  # graph_path's memo (not state: rebuilt from the links on demand)
        self._add_node(self._odom, (np.nan, np.nan, np.nan), 0.0)  # dated by the first update

    # ------------------------------------------------------------------ read-only views
    @staticmethod
    def _ro(a: np.ndarray) -> np.ndarray:
        v = a.view()
        v.flags.writeable = False
        return v

    @property
    def node_count(self) -> int:
        return self._n

    @property
    def link_count(self) -> int:
        return self._m

    @property
    def current(self) -> int:
        """Id of the current node (the robot's node)."""
        return self._cur

    @property
    def robot_offset(self) -> np.ndarray:
        """The robot's pose relative to the current node, in that node's frame (Δ)."""
        return np.array(self._delta)

    @property
    def robot_pose(self) -> np.ndarray:
        """The robot's pose in the map: ``l_current ⊕ Δ``."""
        return np.array(_compose3(self._P[self._cur], self._delta))

    @property
    def time_at_node(self) -> float:
        """Seconds since the robot arrived at its current node (``t − t_arrive``): the time over which
        the odometry's heading bias has turned Δ (see :meth:`debiased`)."""
        return 0.0 if self._t is None else self._t - self._t_arrive

    def debiased(self, offsets: np.ndarray, times: np.ndarray) -> np.ndarray:
        """(K, 3) robot offsets from their nodes with the estimated heading bias taken off over the
        ``times`` (K,) since the robot arrived at each node: ``Δθ − b τ``, as a new node's pose is
        placed (:meth:`~hippomap.cognitive_map.CognitiveMap._create_or_merge`). The offsets are kept
        as the odometry measured them, because the links made from them are charged the bias by the
        solves; a robot that stands or turns on the spot makes no node, so its raw offset turns at the
        gyro's bias for as long as it stays (docs/MODEL.md)."""
        out = np.array(offsets, dtype=float, copy=True).reshape(-1, 3)
        if self._bias:
            out[:, 2] = wrap_angle(out[:, 2] - self._bias * np.asarray(times, dtype=float))
        return out

    @property
    def robot_pose_estimate(self) -> np.ndarray:
        """The robot's pose on the map with the estimated bias taken off its offset (:meth:`debiased`):
        what the service and the viewer show. :attr:`robot_pose` keeps the raw offset, the frame the
        loop hypotheses are made in."""
        off = self.debiased(np.array(self._delta), np.array([self.time_at_node]))[0]
        return np.array(_compose3(self._P[self._cur], tuple(off.tolist())))

    def robot_map_pose(self) -> tuple[float, float, float]:
        """The robot's pose on the map: the current node's pose composed with the offset."""
        return _compose3(self._P[self._cur], self._delta)

    @property
    def poses(self) -> np.ndarray:
        return self._ro(self._P[: self._n])

    @property
    def place_codes(self) -> np.ndarray:
        return self._ro(self._C[: self._n])

    @property
    def frames(self) -> np.ndarray:
        return self._ro(self._F[: self._n])

    @property
    def times(self) -> np.ndarray:
        return self._ro(self._Tn[: self._n])

    @property
    def links(self) -> dict[str, np.ndarray]:
        """Arrays of the links: ``source``, ``target``, ``transform`` (M, 3) = target in the source
        frame, [ORS] ``d``, ``heading``, ``facing``, ``dt``, ``kind`` (strings), ``kind_code``."""
        m = self._m
        tr = self._tr[:m]
        return {
            "source": self._ro(self._src[:m]),
            "target": self._ro(self._dst[:m]),
            "transform": self._ro(tr),
            "d": np.hypot(tr[:, 0], tr[:, 1]),
            "heading": np.arctan2(tr[:, 1], tr[:, 0]),
            "facing": tr[:, 2].copy(),
            "dt": self._ro(self._dt[:m]),
            "kind": np.asarray(LINK_KINDS)[self._kind[:m]],
            "kind_code": self._ro(self._kind[:m]),
        }

    def link_weights(self) -> np.ndarray:
        """(M,) robust weight of every link: 1 for odometric and prune links, the revised kernel
        weight for loop links (0 < w ≤ 1; a false closure fades towards 0)."""
        return self._w[: self._m].copy()

    # ------------------------------------------------------------------ storage
    def _grow_nodes(self) -> None:
        cap = 2 * len(self._P)
        for name in ("_P", "_C", "_F", "_Tn", "_S", "_mask"):
            old = getattr(self, name)
            new = np.empty((cap,) + old.shape[1:], dtype=old.dtype)
            new[: len(old)] = old
            new[len(old) :] = np.nan if name == "_C" else (-1 if name == "_F" else 0)
            setattr(self, name, new)

    def _grow_links(self) -> None:
        cap = 2 * len(self._src)
        for name in ("_src", "_dst", "_tr", "_dt", "_kind", "_col", "_w", "_linfo", "_lkw", "_lcoup", "_lkpos"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[: len(old)] = old
            setattr(self, name, new)

    def _add_node(self, pose, code, t: float) -> int:
        if self._n == len(self._P):
            self._grow_nodes()
        i = self._n
        self._P[i] = pose
        self._C[i] = code
        self._F[i] = -1
        self._Tn[i] = t
        self._S[i] = self._path
        self._mask[i] = 0
        self._n += 1
        return i

    def _add_link(
        self,
        a: int,
        b: int,
        tr,
        kind: int,
        dt: float,
        allow_duplicate: bool = False,
        info: tuple[float, ...] | None = None,
        kernel_width: float | None = None,
        coupling: float = 0.0,
        along_sigma: float = 0.0,
        loosen: float = 1.0,
    ) -> int:
        """Append link a→b (ORS ``on_create_link``); -1 if the pair is already linked (either way)."""
        key = (min(a, b), max(a, b))
        if key in self._pairs and not allow_duplicate:
            return -1
        if self._m == len(self._src):
            self._grow_links()
        k = self._m
        self._src[k], self._dst[k] = a, b
        self._tr[k] = tr
        self._dt[k] = dt
        self._kind[k] = kind
        self._w[k] = 1.0
        self._set_info(k, self.cfg.loop_information if info is None else info, along_sigma, loosen)
        self._lkw[k] = self.cfg.loop_kernel_width if kernel_width is None else kernel_width
        self._lcoup[k] = coupling
        self._col[k] = colour_link(self._mask, a, b)
        self._pairs.add(key)
        self._m += 1
        self._version += 1
        ends = np.array([a, b], dtype=np.int64)
        tr3 = np.asarray(tr, dtype=float).reshape(1, 3)
        r = link_errors(self._P[: self._n], ends[:1], ends[1:], tr3, self._lcoup[k : k + 1])
        if np.max(np.abs(r)) > 1e-9:
            self._dirty = True
            self._touched.append(k)
        if kind == LOOP and self.cfg.loop_weight_init == "kernel":
            self._w[k] = self._kernel_weights(r, np.array([k]))[0]
        return k

    def _set_info(self, k: int, info: tuple[float, ...], along_sigma: float = 0.0, loosen: float = 1.0) -> None:
        """Link ``k``'s information; for the solve x loosened by ``along_sigma`` (m), x and y divided by ``loosen``."""
        x, y, heading = link_info3(info)
        self._lkpos[k] = x
        self._linfo[k] = ((1.0 / (1.0 / x + along_sigma**2) if along_sigma else x) / loosen, y / loosen, heading)

    def _kernel_weights(self, r: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The ``loop_kernel`` weights of the loop links ``k`` with residuals ``r`` (K, 3) in their source frames
        (:func:`~hippomap.loop_closure.link_errors`), whitened by their kernel widths and information, the position
        residual a distance at the x information the link had before the solve's loosening (``_lkpos``; MODEL items
        57, 84, 88): looser x or y lets odometry place the robot; a link far off its key frame is no likelier true."""
        info = np.column_stack((self._lkpos[k], self._lkpos[k], self._linfo[k][:, 2]))
        return kernel_weights(r, info, self._lkw[k], self.cfg.loop_kernel)

    def _rebuild_link_index(self, colours=None) -> None:
        m, n = self._m, self._n
        src, dst = self._src[:m], self._dst[:m]
        self._col[:m] = edge_colouring(src, dst, n) if colours is None else np.asarray(colours, dtype=np.int64)
        self._mask[:] = 0
        ok = self._col[:m] >= 0
        bits = np.left_shift(np.int64(1), np.where(ok, self._col[:m], 0)) * ok
        np.bitwise_or.at(self._mask, src, bits)
        np.bitwise_or.at(self._mask, dst, bits)
        self._pairs = set(zip(np.minimum(src, dst).tolist(), np.maximum(src, dst).tolist()))

    def _set_current(self, node: int, delta, t: float, arrival: int = -1) -> None:
        """on_set_experience: the robot is now at ``delta`` in the frame of ``node``. The
        current node's place code is re-anchored to the robot's place code, so that Eq. 13
        measures distance travelled from here, not odometric drift accumulated since the
        node was created."""
        self._cur = int(node)
        self._delta = cast("tuple[float, float, float]", tuple(float(v) for v in delta))
        self._t_arrive = t
        self._arrival = int(arrival)
        code = self._robot_code()
        self._anchor = None if code is None else _compose3(code, _inv3(self._delta))

    def _robot_code(self) -> tuple[float, float, float] | None:
        """The robot's place code now: the last one, moved by the odometry since it arrived."""
        if self._code is None:
            return None
        return _compose3(self._code, _between3(self._code_odom, self._odom))

    # ------------------------------------------------------------------ queries, frames and events
    def nodes_near(self, place_code, radius: float, exclude_recent: bool = True) -> np.ndarray:
        """Ids of nodes whose place code is within ``radius`` (Eq. 13, μ_p‖p_i − p‖), nearest first.

        ``exclude_recent`` drops the current node and the last ``N_excl`` nodes (spec §4 set C).
        """
        p = _vec3(place_code, "place code")
        r = finite("radius", radius)
        n = self._n
        d = self.cfg.mu_p * np.hypot(self._C[:n, 0] - p[0], self._C[:n, 1] - p[1])
        mask = d < r
        if exclude_recent:
            mask[max(0, n - self.cfg.exclude_recent) :] = False
            mask[self._cur] = False
        ids = np.flatnonzero(mask)
        return ids[np.argsort(d[ids], kind="stable")]

    def set_frame(self, node: int, frame_id: int) -> None:
        """Attach key frame ``frame_id`` (V, -1 to clear) to ``node``."""
        node = _node_id(node, "node")
        frame_id = _node_id(frame_id, "frame_id")
        if not 0 <= node < self._n:
            raise InputError(f"node {node} is not a node id of this map [0, {self._n})")
        if frame_id < -1:
            raise InputError(f"frame_id must be >= -1, got {frame_id}")
        self._F[node] = frame_id
        self._events.append(FrameAssigned(node, frame_id, self._t if self._t is not None else 0.0))

    def graph_path(self, nodes: np.ndarray) -> np.ndarray:
        """Shortest path (m) from the current node to each of ``nodes`` through the odometric links
        and the used loop links (robust weight >= ``USED_WEIGHT``), each as long as its translation
        (a loop link joins two places a few decimetres apart: it shortens the path by the loop).

        The distances are remembered for the graph they were computed on (:class:`~hippomap.graph_paths.GraphPaths`,
        keyed on the kept links themselves, not on a version counter): the loop gate asks again
        for each hypothesis of a frame on the graph its candidates were chosen on."""
        m, n = self._m, self._n
        keep = (self._kind[:m] != LOOP) | (self._w[:m] >= USED_WEIGHT)
        length = np.hypot(self._tr[:m, 0], self._tr[:m, 1])[keep] + 1e-9  # 0 would be no edge
        dist = self._paths.distances(n, self._src[:m][keep], self._dst[:m][keep], length, int(self._cur))
        return dist[np.asarray(nodes, dtype=np.int64)]

    def _drift(self, nodes: np.ndarray, measured: bool) -> np.ndarray:
        """Path (m) over which odometric drift may separate ``nodes`` from the robot, for the gate of a
        hypothesis (``MapConfig.loop_drift``; a measured transform's gate always counts the path since
        the node was made, :func:`~hippomap.loop_closure.drift_path`). A node the graph does not reach
        (a saved map's, before a used closure joins this run to it) gets the 'verified' path: no
        infinite gate."""
        path = drift_path(self._path, self._S[nodes], None if measured else self._loops.last_verified_path)
        if not measured and self.cfg.loop_drift == "graph":
            graph = self.graph_path(nodes)
            return np.where(np.isfinite(graph), graph, path)
        return path

    @property
    def path_since_verified(self) -> float:
        """Odometric path (m) since the last verified loop closure, or since the start."""
        return self._path - (self._loops.last_verified_path or 0.0)

    def _gate_limit(self, nodes: np.ndarray, measured: bool) -> np.ndarray:
        """:func:`~hippomap.loop_closure.gate_limit` of ``nodes``: the base radius, their drift path's
        allowance (:meth:`_drift`) and the bias estimate's (:meth:`_bias_drift`)."""
        bias = self._bias_drift(nodes if self.cfg.loop_bias_per_node else None)
        return np.asarray(gate_limit(self.cfg, measured, self._drift(nodes, measured), bias))

    def _bias_pace(self) -> float:
        """Seconds per metre of the nodes made since the last verified closure (or the start): the robot's pace
        over the drift; 0 while fewer than two nodes span some path."""
        n = self._n
        first = int(np.searchsorted(self._S[:n], self._loops.last_verified_path or 0.0))  # nodes: in path order
        if n - first < 2 or not self._S[n - 1] > self._S[first]:
            return 0.0
        return float((self._Tn[n - 1] - self._Tn[first]) / (self._S[n - 1] - self._S[first]))

    def _bias_drift(self, nodes: np.ndarray | None = None) -> float | np.ndarray:
        """:func:`~hippomap.loop_closure.bias_drift` since the last verified closure (or the start), at the pace
        over that path (:meth:`_bias_pace`); with an estimate the whole solve did not keep, its size too
        (``map.loop_bias_unkept``)."""
        if self._bias_sd <= 0:
            return 0.0
        node_m = None if nodes is None else self._path - self._S[nodes]
        return bias_drift(
            self.cfg,
            self._bias_sd,
            self.path_since_verified,
            self._bias_pace(),
            node_m,
            self._bias_unkept,
            self._run_seconds(),
        )

    def _run_seconds(self) -> float:
        """Seconds from the first node to the newest: how long the bias the whole solves estimate as one rate may
        have wandered (``map.loop_bias_walk``)."""
        n = self._n
        return float(self._Tn[n - 1] - self._Tn[0]) if n > 1 else 0.0

    def _bias_turn(self) -> float:
        """How far (rad) the heading-rate error the gate allows for (:func:`~hippomap.loop_closure.bias_rate_error`)
        may have turned the robot since the last verified closure, e t over those seconds (``map.loop_heading_bias``;
        0 when off or no estimate bounds it)."""
        if not self.cfg.loop_heading_bias or self._bias_sd <= 0:
            return 0.0
        e = bias_rate_error(self.cfg, self._bias_sd, self._bias_unkept, self._run_seconds())
        return e * self.path_since_verified * self._bias_pace()

    def take_events(self) -> list[MapEvent]:
        """The events queued since the last call that returned events (by :meth:`propose_loop`,
        :meth:`set_frame`, :meth:`prune`), emptying the queue: a caller returns them from the call
        that caused them instead of the next :meth:`update`."""
        events, self._events = self._events, []
        return events
