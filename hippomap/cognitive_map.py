"""The cognitive map: nodes, links, loop closure, relaxation and pruning (paper §2.4; spec §4).

A node ``e_i = {p_i, V_i, l_i}`` (Eq. 11) holds the place code ``p_i`` (x, y, θ) that
created it, the id ``V_i`` of the key frame learned there (-1: none) and its pose ``l_i`` in
the map, which relaxation (Eq. 14) moves. Links follow [ORS] ``on_create_link``: each stores
the pose of its target in the frame of its source (``transform``; the [ORS] ``d``,
``heading``, ``facing`` are derived from it), the time ``dt`` spent on it, and its kind
(``odometry``, ``loop`` or ``prune``).

Storage is struct-of-arrays: growable numpy arrays (capacity doubling), no Python object per
node or link. The robot is tracked as its SE(2) pose ``Δ`` *relative to the current node*
(in that node's frame), so nothing is lost when the current node changes.

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
from dataclasses import replace
from typing import Any, Self, cast

import numpy as np

from .config import MapConfig
from .errors import InputError, finite
from .geometry import between, compose, wrap_angle
from .loop_closure import (
    Candidate,
    LoopBook,
    LoopDecision,
    LoopHypothesis,
    USED_WEIGHT,
    align_group,
    consistent,
    drift_path,
    gate_limit,
    node_id,
    place_of,
    robust_weight,
    se2_between,
    se2_compose,
    se2_inverse,
    vec3,
)
from .map_events import (
    FrameAssigned,
    LoopAccepted,
    LoopPending,
    LoopRejected,
    MapEvent,
    MapRelaxed,
    NodeCreated,
    NodeMerged,
    NodesPruned,
)
from .relaxation import (
    ColourGroups,
    colour_link,
    edge_colouring,
    graph_cost,
    link_residuals,
    relax,
    relax_jacobi,
    rotation_first_init,
    solve_lsq,
)

#: link kinds, stored as small integer codes
LINK_KINDS = ("odometry", "loop", "prune")
ODOMETRY, LOOP, PRUNE = 0, 1, 2

_STATE_VERSION = 1


_compose3, _inv3, _between3 = se2_compose, se2_inverse, se2_between
_vec3, _node_id = vec3, node_id


# --------------------------------------------------------------------------- the map
class CognitiveMap:
    """The cognitive map of [S] §2.4 (spec §4). See the module doc for the algorithm.

    Public read-only views: :attr:`poses` (N, 3) map poses ``l``, :attr:`place_codes`
    (N, 3) ``p`` (NaN for the first node until a place code arrives), :attr:`frames` (N,)
    ``V`` (-1: none), :attr:`times` (N,) creation times, :attr:`links` (dict of arrays),
    :attr:`current`, :attr:`robot_offset`, :attr:`robot_pose`, :attr:`loop_decisions`.
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
        self._linfo = np.zeros((cap, 2))  # information (x/y, heading) of loop links
        self._lkw = np.ones(cap)  # robust kernel width of loop links (standard deviations)
        self._pairs: set[tuple[int, int]] = set()
        self._groups: ColourGroups | None = None
        self._groups_key = -1
        self._version = 0
        self._dirty = False  # lsq: a link with a non-zero residual was added since the last solve
        self._touched: list[int] = []  # links added or changed since the last solve; -1: the whole map
        self._local_solves = 0  # local solves since the last solve of the whole map
        self._bias = 0.0  # the odometry's heading bias (rad/s), estimated by the whole solves (see _bias_args)
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
        self._add_node(self._odom, (np.nan, np.nan, np.nan), 0.0)

    # ------------------------------------------------------------------ read-only views
    @staticmethod
    def _ro(a: np.ndarray) -> np.ndarray:
        v = a.view()
        v.flags.writeable = False
        return v

    @property
    def path_since_verified(self) -> float:
        """Odometric path (m) since the last verified loop closure, or since the start."""
        return self._path - (self._loops.last_verified_path or 0.0)

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

    @property
    def loop_decisions(self) -> list[LoopDecision]:
        """One decision per proposed hypothesis (index = decision id), latest status."""
        return list(self._loops.decisions)

    @property
    def pending_count(self) -> int:
        return len(self._loops.pending)

    # ------------------------------------------------------------------ storage
    def _grow_nodes(self) -> None:
        cap = 2 * len(self._P)
        for name in ("_P", "_C", "_F", "_Tn", "_S", "_mask"):
            old = getattr(self, name)
            new = np.empty((cap,) + old.shape[1:], dtype=old.dtype)
            new[: len(old)] = old
            new[len(old):] = np.nan if name == "_C" else (-1 if name == "_F" else 0)
            setattr(self, name, new)

    def _grow_links(self) -> None:
        cap = 2 * len(self._src)
        for name in ("_src", "_dst", "_tr", "_dt", "_kind", "_col", "_w", "_linfo", "_lkw"):
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

    def _add_link(self, a: int, b: int, tr, kind: int, dt: float, allow_duplicate: bool = False,
                  info: tuple[float, float] | None = None, kernel_width: float | None = None) -> int:
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
        self._linfo[k] = self.cfg.loop_information if info is None else info
        self._lkw[k] = self.cfg.loop_kernel_width if kernel_width is None else kernel_width
        self._col[k] = colour_link(self._mask, a, b)
        self._pairs.add(key)
        self._m += 1
        self._version += 1
        r = link_residuals(self._P[: self._n], [a], [b], np.asarray(tr, dtype=float).reshape(1, 3))
        if np.max(np.abs(r)) > 1e-9:
            self._dirty = True
            self._touched.append(k)
        if kind == LOOP and self.cfg.loop_weight_init == "kernel":
            self._w[k] = self._kernel_weights(r, self._linfo[k: k + 1], self._lkw[k: k + 1])[0]
        return k

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
        q = _compose3(self._P[cur], self._delta)  # where the new node would be
        dt = t - self._t_arrive
        if cfg.prune_online and self._n > 1:
            n = self._n
            b = cfg.prune_block_m
            same = np.all(np.floor(self._P[:n, :2] / b) == np.floor(np.array(q[:2]) / b), axis=1)
            same[cur] = False
            same[max(0, n - cfg.exclude_recent):] = False
            if same.any() and cfg.prune_graph_radius_m is not None:
                same &= self._graph_distance(cur, cfg.prune_graph_radius_m) <= cfg.prune_graph_radius_m
            if same.any():
                a = int(np.argmax(same))  # the oldest node of the block
                offset = _between3(self._P[a], q)
                link = self._add_link(cur, a, _between3(self._P[cur], self._P[a]), PRUNE, dt)
                self._set_current(a, offset, t, link)
                return NodeMerged(a, cur, link, offset, t)
        new = self._add_node(q, code, t)
        link = self._add_link(cur, new, self._delta, ODOMETRY, dt)
        self._cur, self._delta, self._t_arrive, self._anchor, self._arrival = new, (0.0, 0.0, 0.0), t, code, -1
        return NodeCreated(new, cur, link, q, code, t)

    def _graph_distance(self, source: int, limit: float) -> np.ndarray:
        """Shortest path length (m, along links, either direction) from ``source`` to every node,
        ``inf`` beyond ``limit``. Builds a sparse graph: O(M).

        Loop links the robust kernel has faded (weight < ``USED_WEIGHT``) are not paths: a false
        closure would otherwise let online pruning merge the robot into a node it only reaches
        through that closure, a second false closure made as stiff as odometry (measured on a
        simulated loop: a faded link 162 → 3 let node 164 merge into node 4 across a lap of drift,
        1.1 rad apart, and that merge then held the first lap's seam open)."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import dijkstra

        n, m = self._n, self._m
        path = (self._kind[:m] != LOOP) | (self._w[:m] >= USED_WEIGHT)
        if not path.any():
            d = np.full(n, np.inf)
            d[source] = 0.0
            return d
        a = np.minimum(self._src[:m], self._dst[:m])[path]
        b = np.maximum(self._src[:m], self._dst[:m])[path]
        w = np.hypot(self._tr[:m, 0], self._tr[:m, 1])[path] + 1e-9  # explicit zeros would vanish
        key, inv = np.unique(a * n + b, return_inverse=True)  # parallel links: keep the shortest
        wmin = np.full(len(key), np.inf)
        np.minimum.at(wmin, inv.reshape(-1), w)
        g = csr_matrix((wmin, (key // n, key % n)), shape=(n, n))
        return dijkstra(g, directed=False, indices=source, limit=limit)

    def _optimise(self, t: float, force: bool = False, sweeps: int | None = None) -> list[MapEvent]:
        """Correct node poses while the graph disagrees with itself (``MapConfig.solver``).

        Nothing is done while the map is consistent (every link added since the last
        correction agreed with the poses, as a new node's odometric link does): between loop
        closures the cost per step does not grow with the map. After a closure, 'relax' runs
        ``relax_loops`` sweeps per step until the largest shift of a sweep falls below
        ``relax_tolerance_m``; 'lsq' and 'gtsam' solve at once. Once converged, the loop links'
        robust weights are revised (:meth:`_reweight`); a change of weight starts it again.
        """
        m, n = self._m, self._n
        if m == 0 or not (self._dirty or force):
            return []
        P = self._P[:n]
        src, dst, tr = self._src[:m], self._dst[:m], self._tr[:m]
        cfg = self.cfg
        sweeps = cfg.relax_loops if sweeps is None else int(sweeps)
        w = self._w[:m]
        window = None
        if cfg.solver == "lsq" and not force and self._local_solves < cfg.lsq_window_every:
            window = self._local_window()
        self._touched = []  # what is solved now; the reweighting below may add to it
        if cfg.solver == "lsq":
            info = (self.link_information() if cfg.lsq_weighted else np.ones((m, 3))) * w[:, None]
            bias = self._bias_args()
            if window is None:
                if cfg.lsq_rotation_init:
                    self._rotation_init(P, src, dst, tr, info, bias)
                    if bias:
                        bias["bias"] = self._bias  # the initialisation may have moved it
                res = solve_lsq(P, src, dst, tr, iterations=cfg.lsq_iterations, anchor=0, information=info, **bias)
                self._bias = res.bias
                self._local_solves = 0
            else:
                self._local_solves += 1
                nodes, links, fixed = window
                local = np.full(n, -1, dtype=np.int64)
                local[nodes] = np.arange(len(nodes))
                Q = P[nodes].copy()
                if bias:
                    bias = {**bias, "bias_dt": bias["bias_dt"][links], "estimate_bias": False}
                res = solve_lsq(Q, local[src[links]], local[dst[links]], tr[links], iterations=cfg.lsq_iterations,
                                anchor=None, information=info[links], fixed=local[fixed], **bias)
                P[nodes] = Q
            # a solve cut off by lsq_iterations has not converged: the weights are revised only on a
            # converged map (IRLS), else a closure still being applied looks like an outlier and fades
            converged = res.iterations < cfg.lsq_iterations or res.max_shift < cfg.relax_tolerance_m
        elif sweeps <= 0:
            return []
        elif cfg.solver == "jacobi":
            res = relax_jacobi(P, src, dst, tr, sweeps, cfg.alpha, anchor=0)
            converged = res.max_shift < cfg.relax_tolerance_m
        else:
            if self._groups_key != self._version:
                self._groups = ColourGroups(src, dst, tr, self._col[:m], n, check=False, weights=w)
                self._groups_key = self._version
            res = relax(P, src, dst, tr, sweeps, cfg.alpha, anchor=0, groups=self._groups)
            converged = res.max_shift < cfg.relax_tolerance_m
        # robust weights are revised on a map solved whole only: a window holds the rest of the map
        # fixed, and the strain at its edge would fade true links
        self._dirty = not converged or (self._local_solves == 0 and self._reweight())
        return [MapRelaxed(res.solver, res.iterations, res.max_shift, t)]

    def _bias_args(self) -> dict[str, Any]:
        """Keyword arguments of :func:`solve_lsq` for the odometry's heading bias (empty when
        ``odometry_bias_sigma`` is 0): every odometric link's heading change is taken to include
        ``bias × its duration`` (a gyro's or wheel odometry's constant turn rate error), and the
        whole solves estimate the bias with the poses, from a zero-mean prior of that sigma."""
        sigma = self.cfg.odometry_bias_sigma
        if sigma <= 0:
            return {}
        m = self._m
        bdt = np.where(self._kind[:m] == ODOMETRY, self._dt[:m], 0.0)
        return {"bias_dt": bdt, "bias": self._bias, "bias_information": 1.0 / sigma ** 2}

    def _rotation_init(self, P: np.ndarray, src: np.ndarray, dst: np.ndarray, tr: np.ndarray, info: np.ndarray,
                       bias: dict[str, Any]) -> None:
        """Headings-first re-initialisation before a whole solve (with the bias when it is
        estimated), kept only when it lowers the weighted cost (it cannot on a map that is
        already at its optimum)."""

        before = graph_cost(P, src, dst, tr, info, **bias)
        Q = P.copy()
        _, b = rotation_first_init(Q, src, dst, tr, info, anchor=0, **bias)
        if graph_cost(Q, src, dst, tr, info, **{**bias, "bias": b}) < before:
            P[:] = Q
            if bias:
                self._bias = b

    def _reweight(self) -> bool:
        """Revise the robust weights of the loop links from their residuals on the converged
        map (iteratively reweighted relaxation): each link's residual is whitened by
        ``loop_information`` and the kernel width, and ``loop_kernel`` turns it into a weight in
        (0, 1]. Returns whether a weight changed by more than ``reweight_tolerance``."""
        cfg = self.cfg
        if cfg.loop_kernel == "none":
            return False
        m = self._m
        loop = np.flatnonzero(self._kind[:m] == LOOP)
        if not len(loop):
            return False
        new = self._kernel_weights(link_residuals(self._P[: self._n], self._src[loop], self._dst[loop], self._tr[loop]),
                                   self._linfo[loop], self._lkw[loop])
        changed = np.abs(new - self._w[loop]) > cfg.reweight_tolerance
        if not changed.any():
            return False
        self._w[loop] = new
        self._touched.extend(loop[changed].tolist())
        self._version += 1  # rebuild the relaxation groups with the new gains
        return True

    def _local_window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(nodes, links, fixed) of a local solve, or None for a solve of the whole map.

        When every link changed since the last solve disagrees with the map by less than
        ``lsq_window_residual_m``, the correction is local (the robot is re-localising along a
        mapped path, not closing a new loop): only the nodes within ``lsq_window_hops`` links of
        their ends move, the nodes just outside hold the rest of the map in place. The cost of
        such a step then depends on the window, not on the map (:meth:`finish` solves the
        whole map)."""
        cfg, n, m = self.cfg, self._n, self._m
        touched = self._touched
        if cfg.lsq_window_hops <= 0 or not touched or -1 in touched:
            return None
        k = np.unique(np.asarray(touched, dtype=np.int64))
        k = k[k < m]
        if not len(k):
            return None
        src, dst = self._src[:m], self._dst[:m]
        r = link_residuals(self._P[:n], src[k], dst[k], self._tr[k])
        if float(np.max(np.hypot(r[:, 0], r[:, 1]))) > cfg.lsq_window_residual_m:
            return None
        active = np.zeros(n, dtype=bool)
        active[src[k]] = active[dst[k]] = True
        for _ in range(cfg.lsq_window_hops):
            grow = active[src] | active[dst]
            nxt = active.copy()
            nxt[src[grow]] = nxt[dst[grow]] = True
            if nxt.sum() == active.sum():
                break
            active = nxt
        active[0] = False  # the anchor never moves
        links = np.flatnonzero(active[src] | active[dst])
        if not len(links) or 2 * active.sum() > n:
            return None  # the window is most of the map: solve it all
        nodes = np.unique(np.concatenate([src[links], dst[links]]))
        fixed = nodes[~active[nodes]]
        if not len(fixed):
            return None
        return nodes, links, fixed

    def _trust(self, k: int) -> None:
        """A verified loop link: weight 1, and (``trust_verified``) out of the kernel's reach,
        so that a true closure is applied fully even where it strains an odometry model that
        claims more precision than it has; only unverified links are weighted down."""
        self._w[k] = 1.0
        if self.cfg.trust_verified:
            self._lkw[k] = np.inf

    def _kernel_weights(self, e: np.ndarray, info: np.ndarray, width: np.ndarray) -> np.ndarray:
        """Kernel weights of loop links with residuals ``e`` (K, 3), information ``info`` (K, 2)
        and kernel widths ``width`` (K,): whitened by both (isotropic in x/y, so the residual's
        frame does not matter), floored so that no link is divided away entirely."""
        cfg = self.cfg
        chi2 = ((e[:, 0] ** 2 + e[:, 1] ** 2) * info[:, 0] + e[:, 2] ** 2 * info[:, 1]) / width ** 2
        return np.maximum(robust_weight(chi2, cfg.loop_kernel), 1e-4)

    def loop_rows(self) -> list[dict[str, Any]]:
        """Every loop decision as a JSON-ready dict, with the current robust ``weight`` of its
        link (absent without a link) and ``used``: accepted with weight >= ``USED_WEIGHT``."""
        w = self._w[: self._m]
        rows = []
        for d in self._loops.decisions:
            row = d.to_dict()
            if 0 <= d.link < len(w):
                row["weight"] = float(w[d.link])
            row["used"] = d.status == "accepted" and row.get("weight", 1.0) >= USED_WEIGHT
            rows.append(row)
        return rows

    def link_weights(self) -> np.ndarray:
        """(M,) robust weight of every link: 1 for odometric and prune links, the revised kernel
        weight for loop links (0 < w ≤ 1; a false closure fades towards 0)."""
        return self._w[: self._m].copy()

    def weighted_link_information(self) -> np.ndarray:
        """(M, 3) diagonal information (x, y, θ) the map gives each link when it solves: the
        solver's weights (:meth:`link_information`; unit information when ``lsq_weighted`` is
        off) times each link's robust weight (a faded loop link counts for little). This is what
        the g2o export writes on each edge."""
        info = self.link_information() if self.cfg.lsq_weighted else np.ones((self._m, 3))
        return info * self._w[: self._m, None]

    def link_information(self) -> np.ndarray:
        """(M, 3) diagonal information of every link (x, y, θ) for the weighted solver: odometric
        and prune links ``odometry_information_per_m / length`` (variance grows with the path;
        lengths below 5 cm count as 5 cm), the heading's variance also ``odometry_turn_variance``
        per radian turned; loop links ``loop_information``."""
        m = self._m
        cfg = self.cfg
        length = np.maximum(np.hypot(self._tr[:m, 0], self._tr[:m, 1]), 0.05)
        xy, th = cfg.odometry_information_per_m
        turn = np.abs(self._tr[:m, 2])
        info = np.column_stack([xy / length, xy / length, 1.0 / (length / th + cfg.odometry_turn_variance * turn)])
        loop = self._kind[:m] == LOOP
        li = self._linfo[:m][loop]
        info[loop] = np.column_stack([li[:, 0], li[:, 0], li[:, 1]])
        return info

    def finish(self, iterations: int | None = None) -> list[MapEvent]:
        """End of a run: one more correction (``iterations`` sweeps, default ``relax_loops``; an
        exact solve for 'lsq') and the queued events. Pending hypotheses stay pending."""
        events, self._events = self._events, []
        events.extend(self._optimise(self._t if self._t is not None else 0.0, force=True, sweeps=iterations))
        return events

    def take_events(self) -> list[MapEvent]:
        """The events queued since the last call that returned events (by :meth:`propose_loop`,
        :meth:`set_frame`, :meth:`prune`), emptying the queue: a caller returns them from the call
        that caused them instead of the next :meth:`update`."""
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------------ loop closure
    def robot_map_pose(self) -> tuple[float, float, float]:
        """The robot's pose on the map: the current node's pose composed with the offset."""
        return _compose3(self._P[self._cur], self._delta)

    def loop_candidates(self, limit: int | None = None) -> np.ndarray:
        """Ids of the nodes a visual hypothesis made now could name and pass the gate with:
        within :func:`~hippomap.loop_closure.gate_limit` of the robot (unmeasured hypothesis, no
        offset), not current nor among the last ``N_excl`` nodes; nearest first."""
        n = self._n
        r = self.robot_map_pose()
        d = np.hypot(self._P[:n, 0] - r[0], self._P[:n, 1] - r[1])
        lim = gate_limit(self.cfg, False, drift_path(self._path, self._S[:n], self._loops.last_verified_path))
        mask = d < lim
        mask[max(0, n - self.cfg.exclude_recent):] = False
        mask[self._cur] = False
        ids = np.flatnonzero(mask)
        ids = ids[np.argsort(d[ids], kind="stable")]
        return ids if limit is None else ids[:limit]

    def propose_loop(self, h: LoopHypothesis) -> LoopDecision:
        """Offer a loop closure; returns the decision. Its events are queued: the caller takes them
        with :meth:`take_events` (else they come out of the next :meth:`update`).

        Checks, in order (see :mod:`hippomap.loop_closure`):

        * ``node`` must be an existing node, not the current one nor among the last ``N_excl``.
        * (a) gate: where the hypothesis puts the node (the robot's map pose ⊕ the node's pose in
          the robot's frame) must lie within :func:`~hippomap.loop_closure.gate_limit` of the
          node's map pose (``loop_gate = 'map'``), or of its place code from the robot's place
          code (``'place_code'``, Eq. 13 as in [S]).
        * (b) with ``loop_min_support`` ≥ 2, cycle consistency with the other hypotheses made
          within ``loop_support_window_m`` metres of path: with ``loop_min_support`` − 1
          consistent pending ones, or one consistent accepted one, it is accepted; if it
          contradicts every loop accepted in the window it is rejected; else it waits.

        Accepting a group of visual hypotheses first fits their relative pose together
        (:func:`~hippomap.loop_closure.align_group`), then adds a ``loop`` link per hypothesis
        from the node that was current at the proposal to ``node``; the newest relocalises the
        robot (current = its node, the robot's offset kept); then the map is corrected.
        Rejected hypotheses never touch node poses.
        """
        if not isinstance(h, LoopHypothesis):
            raise InputError(f"propose_loop needs a LoopHypothesis, got {type(h).__name__}")
        n = self._n
        if not 0 <= h.node < n:
            raise InputError(f"LoopHypothesis.node {h.node} is not a node id of this map [0, {n})")
        cfg = self.cfg
        book = self._loops
        did = len(book.decisions)
        if h.transform is not None:
            link_tr = h.transform
        else:
            link_tr = self._delta if h.offset is None else _compose3(self._delta, _inv3(h.offset))
        info = h.information or (cfg.loop_information if h.transform is not None else cfg.visual_loop_information)
        cand = Candidate(did, h.node, self._cur, link_tr, _between3(self._delta, link_tr), self._odom, self._step,
                         self._arrival if h.node == self._cur else -1, h.transform is not None, self._path,
                         cast("tuple[float, float]", tuple(float(v) for v in info)),
                         cfg.loop_kernel_width if h.transform is not None else cfg.visual_kernel_width)
        t = self._t if self._t is not None else h.time
        base = LoopDecision(did, "pending", "", h, self._cur, proposed_step=self._step)
        reason = ""
        outside = False
        if h.node != self._cur and h.node >= n - cfg.exclude_recent:
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
        book.decisions.append(base)
        if outside and h.meta.get("search") == "global" and not h.measured and cfg.outside_min_support > 0:
            return self._propose_outside(cand, t, reason)
        if reason:
            return self._reject(did, reason, t)
        if cfg.loop_accept == "robust":
            return self._accept_robust(cand, t)
        if cfg.loop_min_support <= 1:
            self._accept([cand], cand, t)
            return book.decisions[did]
        P, S = self._P, self._S
        pend = [c for c in book.pending if c.step != cand.step]
        acc = [c for c in book.accepted if c.step != cand.step]
        ok_pend = [c for c, ok in zip(pend, consistent(cfg, pend, cand, P, S)) if ok]
        ok_acc = [c for c, ok in zip(acc, consistent(cfg, acc, cand, P, S)) if ok]
        if ok_acc or (not acc and 1 + len(ok_pend) >= cfg.loop_min_support):
            support = tuple(c.id for c in ok_pend + ok_acc)
            self._accept(ok_pend + [cand], cand, t, support, ok_acc)
            return book.decisions[did]
        if acc:
            ids = ", ".join(str(c.id) for c in acc)
            return self._reject(did, f"contradicts the loop closure(s) accepted within the window: {ids}", t)
        book.pending.append(cand)
        book.decisions[did] = replace(base, support=tuple(c.id for c in ok_pend))
        self._events.append(LoopPending(did, h.node, cand.from_node, len(ok_pend), t))
        return book.decisions[did]

    def _propose_outside(self, cand: Candidate, t: float, gate_reason: str) -> LoopDecision:
        """A visual hypothesis from a global search (``meta['search'] == 'global'``) that names a
        node outside the gate: after a long excursion the map's drift exceeds any gate, so the
        gate cannot judge it. It waits, without a link, for ``outside_min_support`` − 1 others of
        the same kind within ``outside_window_m`` of path that agree with it in space
        (:func:`consistent`: the distance driven between two proposals equals the distance between
        the places they name) and in sequence (the old path between the two named nodes is as long
        as the path driven between the proposals, within ``loop_consistency_m`` + 10 %); the group
        must then fit one SE(2) transform (:meth:`_fit_group`). A fitted group
        becomes verified loop links at weight 1 and the whole map is solved; a lone or
        contradicted hypothesis expires without touching the map."""
        cfg, book = self.cfg, self._loops
        P, S = self._P, self._S
        self._expire_outside(t)
        older = [c for c in book.outside if c.step != cand.step]
        # consistent in space, and in sequence: a revisit retraces the old path, so the old path between
        # the two named nodes is as long as the robot's path between the two proposals
        ok = [c for c, good in zip(older, consistent(cfg, older, cand, P, S))
              if good and abs((S[cand.node] - S[c.node]) - (cand.path - c.path))
              < cfg.loop_consistency_m + 0.1 * abs(cand.path - c.path)]
        group = self._fit_group(ok + [cand], []) if 1 + len(ok) >= cfg.outside_min_support else None
        if group is None:
            book.outside.append(cand)
            d = replace(book.decisions[cand.id], reason=f"{gate_reason}: waits for consistent global recognitions",
                        support=tuple(c.id for c in ok))
            book.decisions[cand.id] = d
            self._events.append(LoopPending(cand.id, cand.node, cand.from_node, len(ok), t))
            return d
        ids = {c.id for c in group}
        for c in sorted(group, key=lambda c: c.id):
            link = self._add_loop_link(c)
            if link >= 0:
                self._trust(link)
            sup = tuple(sorted(ids - {c.id}))
            book.decisions[c.id] = replace(book.decisions[c.id], status="accepted", link=link, support=sup,
                                           reason="outside the gate; verified by a group of consistent global "
                                                  "recognitions", decided_step=self._step, transform=c.link_tr)
            self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, sup, False, t))
        book.outside = [c for c in book.outside if c.id not in ids]
        book.accepted.extend(group)
        book.last_verified_path = self._path
        self._version += 1
        self._dirty = True
        self._events.extend(self._optimise(t))  # the links disagree with the map by far: a whole solve
        return book.decisions[cand.id]

    def _gate(self, c: Candidate) -> tuple[float | None, float, str]:
        """(distance, limit, what) of the gate for candidate ``c``; distance None: cannot gate."""
        cfg = self.cfg
        drift = float(drift_path(self._path, self._S[c.node], None if c.measured else self._loops.last_verified_path))
        limit = float(gate_limit(cfg, c.measured, drift))
        if cfg.loop_gate == "map":
            pred = _compose3(self.robot_map_pose(), c.M)
            return math.hypot(pred[0] - self._P[c.node, 0], pred[1] - self._P[c.node, 1]), limit, "map"
        code = self._robot_code()
        if code is None or np.isnan(self._C[c.node, 0]):
            return None, limit, "place-code"
        pred = _compose3(code, c.M)
        return cfg.mu_p * math.hypot(pred[0] - self._C[c.node, 0], pred[1] - self._C[c.node, 1]), limit, "place-code"

    def _reject(self, did: int, reason: str, t: float) -> LoopDecision:
        book = self._loops
        d = replace(book.decisions[did], status="rejected", reason=reason, decided_step=self._step)
        book.decisions[did] = d
        self._events.append(LoopRejected(did, d.hypothesis.node, d.from_node, reason, t))
        return d

    def _fit_group(self, group: list[Candidate], anchors: list[Candidate]) -> list[Candidate] | None:
        """The group's visual candidates with the offsets of one SE(2) fit of the robot's
        dead-reckoned poses onto the places they name (``anchors``: accepted candidates of the
        window that back the fit but keep their links). ``None`` when the fit does not hold:
        a member lies more than ``loop_consistency_m`` from where the fit puts it, or the fit
        turns the robot more than ``loop_view_rad`` away from the way a member's key frame
        looked (recognising a view means facing roughly as it was learned)."""
        vis = [c for c in group + anchors if not c.measured]
        if len(vis) < 2:
            return group
        P, cfg = self._P, self.cfg
        odom = np.array([c.odom for c in vis])
        targets = np.array([place_of(c, P) for c in vis])
        T = align_group(odom, targets, cfg.loop_fit_min_spread_m)
        fitted = compose(T, odom)
        if (np.max(np.hypot(*(fitted[:, :2] - targets[:, :2]).T)) > cfg.loop_consistency_m
                or np.max(np.abs(wrap_angle(fitted[:, 2] - targets[:, 2]))) > cfg.loop_view_rad):
            return None
        out = []
        for c in group:
            if c.measured:
                out.append(c)
                continue
            robot = _compose3(T, c.odom)  # where the fit puts the robot on the map at the proposal
            out.append(c.with_offset(_between3(P[c.node], robot)))
        return out

    def _accept(self, group: list[Candidate], reloc: Candidate, t: float, support: tuple[int, ...] = (),
                anchors: list[Candidate] | None = None) -> None:
        book = self._loops
        ids = {c.id for c in group}
        group = sorted(self._fit_group(group, anchors or []) or group, key=lambda c: c.id)
        reloc = next(c for c in group if c.id == reloc.id)
        arrival = -1
        for c in group:
            link = self._add_loop_link(c)
            if link >= 0:
                self._trust(link)
            if c is reloc:
                arrival = link
            sup = tuple(sorted((set(support) | ids) - {c.id}))
            reason = "gate" if self.cfg.loop_min_support <= 1 else "gate and cycle consistency"
            if link < 0:
                reason += "; names the node it was proposed from: robot offset corrected, no link"
            book.decisions[c.id] = replace(book.decisions[c.id], status="accepted", reason=reason, link=link,
                                           support=sup, decided_step=self._step, transform=c.link_tr)
            self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, sup, c is reloc, t))
            book.accepted.append(c)
        book.pending = [c for c in book.pending if c.id not in ids]
        book.last_verified_path = self._path
        if self.cfg.loop_relocalise:
            self._set_current(reloc.node, _inv3(reloc.M), t, arrival)
        # the remaining pending hypotheses: supported by the accepted group, or contradicted by it
        still = []
        for c in book.pending:
            others = [g for g in group if g.step != c.step]
            if not others:
                still.append(c)
                continue
            if np.any(consistent(self.cfg, others, c, self._P, self._S)):  # the cycle test is symmetric in the pair
                link = self._add_loop_link(c)
                sup = tuple(sorted(ids))
                book.decisions[c.id] = replace(book.decisions[c.id], status="accepted",
                                               reason="supported by an accepted loop closure", link=link,
                                               support=sup, decided_step=self._step, transform=c.link_tr)
                self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, sup, False, t))
                book.accepted.append(c)
            else:
                self._reject(c.id, "contradicted by the accepted loop closure(s) " + ", ".join(map(str, sorted(ids))), t)
        book.pending = still
        self._events.extend(self._optimise(t))

    def _accept_robust(self, cand: Candidate, t: float) -> LoopDecision:
        """``loop_accept = 'robust'``: a hypothesis that passed the gate becomes a loop link at
        once, with the kernel weight of its residual (:meth:`_kernel_weights`), revised as the map
        converges. Cycle consistency no longer decides whether a link exists, only whether it is
        *verified*: a verified group has its relative pose fitted, its weights set to 1 and
        relocalises the robot; unverified links can only pull as far as their weight lets them."""
        cfg, book = self.cfg, self._loops
        link = self._add_loop_link(cand)
        P, S = self._P, self._S
        pend = [c for c in book.pending if c.step != cand.step]
        acc = [c for c in book.accepted if c.step != cand.step]
        ok_pend = [c for c, ok in zip(pend, consistent(cfg, pend, cand, P, S)) if ok]
        ok_acc = [c for c, ok in zip(acc, consistent(cfg, acc, cand, P, S)) if ok]
        verified = bool(ok_acc) or 1 + len(ok_pend) >= cfg.loop_min_support
        group = self._fit_group(ok_pend + [cand], ok_acc) if verified else None
        verified = group is not None
        support = tuple(c.id for c in ok_pend + ok_acc)
        reason = "gate; weighted by the robust kernel" + ("; verified by cycle consistency" if verified else "")
        book.decisions[cand.id] = replace(book.decisions[cand.id], status="accepted", reason=reason, link=link,
                                          support=support, decided_step=self._step, transform=cand.link_tr)
        reloc = verified and cfg.loop_relocalise
        self._events.append(LoopAccepted(cand.id, cand.node, cand.from_node, link, support, reloc, t))
        if not verified:
            book.pending.append(cand)
        else:
            assert group is not None  # verified
            for c in group:
                k = book.decisions[c.id].link
                if k >= 0 and c.node != c.from_node:
                    self._tr[k] = c.link_tr
                    self._trust(k)
                    self._touched.append(k)
                    book.decisions[c.id] = replace(book.decisions[c.id], transform=c.link_tr)
            self._version += 1
            self._dirty = True
            ids = {c.id for c in group}
            book.pending = [c for c in book.pending if c.id not in ids]
            book.accepted.extend(group)
            book.last_verified_path = self._path
            if reloc:
                c = group[-1]
                self._set_current(c.node, _inv3(c.M), t, link)
        self._events.extend(self._optimise(t))
        return book.decisions[cand.id]

    def _add_loop_link(self, c: Candidate) -> int:
        """The loop link of an accepted hypothesis ``from_node → node`` with the measured transform.

        A hypothesis may name the node it was proposed from: the robot had already reached that
        node A by online pruning (or an earlier loop) through the *arrival* link prev → A. The
        measurement then says where A is seen from prev: ``arrival ⊕ transform``. An unverified
        prune link is overwritten by it (and becomes a loop link); otherwise a loop link
        prev → A is added. Without an arrival link there is nothing to link (-1): the hypothesis
        only corrects the robot's offset when it relocalises.
        """
        if c.node != c.from_node:
            return self._add_link(c.from_node, c.node, c.link_tr, LOOP, 0.0, allow_duplicate=True, info=c.info,
                                  kernel_width=c.kernel_width)
        k = c.arrival
        if k < 0 or k >= self._m or self._dst[k] != c.node:
            return -1
        tr = _compose3(self._tr[k], c.link_tr)
        if self._kind[k] == PRUNE:
            self._tr[k] = tr
            self._kind[k] = LOOP
            self._w[k] = 1.0
            self._linfo[k] = c.info
            self._lkw[k] = c.kernel_width
            self._version += 1
            self._dirty = True
            self._touched.append(k)
            return k
        return self._add_link(int(self._src[k]), c.node, tr, LOOP, 0.0, allow_duplicate=True, info=c.info,
                                  kernel_width=c.kernel_width)

    def _expire_outside(self, t: float) -> None:
        w = self.cfg.outside_window_m
        for c in self._loops.expired_outside(self._path, w):
            self._reject(c.id, f"outside the gate, and no consistent support within {w:g} m of path", t)

    def _expire(self) -> list[MapEvent]:
        w = self.cfg.loop_support_window_m
        t = self._t if self._t is not None else 0.0
        for c in self._loops.expired(self._path, w):
            if self.cfg.loop_accept == "verified":
                self._reject(c.id, f"expired: no consistent support within {w:g} m of path", t)
        self._expire_outside(t)
        out, self._events = self._events, []
        return out

    # ------------------------------------------------------------------ queries and frames
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
            mask[max(0, n - self.cfg.exclude_recent):] = False
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

    # ------------------------------------------------------------------ batch pruning
    def prune(self) -> np.ndarray:
        """Batch pruning pass (Eq. 15; spec §4, optional): in each block of side b keep the
        oldest node; the others' links are moved to it (their transforms re-expressed through
        the map's current relative pose of the two nodes, self-links and duplicate pairs
        dropped), their key frame moves to it if it has none. Node ids are compacted.

        Returns ``old_to_new`` (N_old,) mapping every old node id to its new id. The robot's
        current node and offset, and pending hypotheses, are remapped.
        """
        n, m = self._n, self._m
        b = self.cfg.prune_block_m
        P = self._P[:n].copy()
        blocks = np.floor(P[:, :2] / b).astype(np.int64)
        _, inv = np.unique(blocks, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        ids = np.arange(n)
        order = np.lexsort((ids, inv))
        first = np.ones(n, dtype=bool)
        first[1:] = inv[order][1:] != inv[order][:-1]
        rep_of_group = np.empty(inv.max() + 1, dtype=np.int64)
        rep_of_group[inv[order][first]] = order[first]
        rep = rep_of_group[inv]  # the oldest node of each node's block
        keep = rep == ids
        new_id = np.cumsum(keep) - 1
        old_to_new = new_id[rep]
        # frames: the representative's own, else the oldest member's
        F = self._F[:n].copy()
        has = F >= 0
        fr_order = np.lexsort((ids, inv))
        fr_order = fr_order[has[fr_order]]
        grp = inv[fr_order]
        firstf = np.ones(len(fr_order), dtype=bool)
        firstf[1:] = grp[1:] != grp[:-1]
        frame_of_group = np.full(inv.max() + 1, -1, dtype=np.int64)
        frame_of_group[grp[firstf]] = F[fr_order[firstf]]
        newF = np.where(F[keep] >= 0, F[keep], frame_of_group[inv[keep]])
        frames_dropped = int(has.sum() - (newF >= 0).sum())
        # links: re-express through the map's relative pose of member -> representative
        src, dst = self._src[:m], self._dst[:m]
        tr = self._tr[:m]
        rs, rd = rep[src], rep[dst]
        new_tr = compose(compose(between(P[rs], P[src]), tr), between(P[dst], P[rd]))
        keep_link = rs != rd
        a, c = np.minimum(rs, rd), np.maximum(rs, rd)
        key = a * n + c
        _, first_idx = np.unique(key, return_index=True)
        dedup = np.zeros(m, dtype=bool)
        dedup[first_idx] = True
        keep_link &= dedup | (self._kind[:m] == LOOP)
        # robot
        cur_rep = int(rep[self._cur])
        delta = _between3(P[cur_rep], _compose3(P[self._cur], self._delta))
        # compact nodes
        kn = int(keep.sum())
        for name in ("_P", "_C", "_Tn", "_S"):
            arr = getattr(self, name)
            arr[:kn] = arr[:n][keep]
        self._F[:kn] = newF
        self._F[kn:] = -1
        self._n = kn
        # compact links and recolour
        kl = np.flatnonzero(keep_link)
        ml = len(kl)
        s_new, d_new = old_to_new[src[kl]], old_to_new[dst[kl]]
        self._tr[:ml] = new_tr[kl]
        self._dt[:ml] = self._dt[:m][kl]
        self._w[:ml] = self._w[:m][kl]
        self._linfo[:ml] = self._linfo[:m][kl]
        self._lkw[:ml] = self._lkw[:m][kl]
        self._kind[:ml] = self._kind[:m][kl]
        self._src[:ml], self._dst[:ml] = s_new, d_new
        self._m = ml
        self._rebuild_link_index()
        self._version += 1
        self._dirty = True
        self._touched = [-1]
        self._cur = int(old_to_new[self._cur])
        self._delta = delta
        code = self._robot_code()
        self._anchor = None if code is None else _compose3(code, _inv3(delta))
        t = self._t if self._t is not None else 0.0
        self._arrival = -1
        remap = lambda c: replace(c, node=int(old_to_new[c.node]), from_node=int(old_to_new[c.from_node]),  # noqa: E731
                                  arrival=-1)
        book = self._loops
        for cand in book.pending:
            if old_to_new[cand.node] == old_to_new[cand.from_node]:
                self._reject(cand.id, "prune() merged its node into the node it was proposed from", t)
        book.pending = [remap(c) for c in book.pending if old_to_new[c.node] != old_to_new[c.from_node]]
        book.accepted = [remap(c) for c in book.accepted]
        self._events.append(NodesPruned(n - kn, kn, ml, frames_dropped, t))
        self._events.extend(self._optimise(t, force=True))
        return old_to_new

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

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """The whole map as plain dicts / lists / numpy arrays (see :meth:`from_state`)."""
        n, m = self._n, self._m
        return {
            "version": _STATE_VERSION,
            "nodes": {"pose": self._P[:n].copy(), "place_code": self._C[:n].copy(), "frame": self._F[:n].copy(),
                      "time": self._Tn[:n].copy(), "path": self._S[:n].copy()},
            "links": {"source": self._src[:m].copy(), "target": self._dst[:m].copy(),
                      "transform": self._tr[:m].copy(), "dt": self._dt[:m].copy(),
                      "kind": self._kind[:m].astype(np.int64), "colour": self._col[:m].copy(),
                      "weight": self._w[:m].copy(), "information": self._linfo[:m].copy(),
                      "kernel_width": self._lkw[:m].copy()},
            "robot": {"current": self._cur, "delta": list(self._delta), "odom": list(self._odom), "path": self._path,
                      "step": self._step, "t": self._t, "t_arrive": self._t_arrive, "arrival": self._arrival,
                      "code": None if self._code is None else list(self._code), "code_odom": list(self._code_odom),
                      "anchor": None if self._anchor is None else list(self._anchor), "dirty": self._dirty,
                      "touched": list(self._touched), "local_solves": self._local_solves,
                      "odometry_bias": self._bias},
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
            cmap._linfo[:m] = (np.tile(cfg.loop_information, (m, 1)) if li is None
                               else np.asarray(li, dtype=float).reshape(m, 2))
            cmap._lkw[:m] = np.asarray(links.get("kernel_width", np.full(m, cfg.loop_kernel_width)), dtype=float)
            if n == 0 or not np.all(np.isfinite(cmap._P[:n])):
                raise InputError("cognitive-map state: node poses missing or not finite")
            if m and (cmap._src[:m].max() >= n or cmap._dst[:m].max() >= n or min(cmap._src[:m].min(), cmap._dst[:m].min()) < 0):
                raise InputError("cognitive-map state: a link names a node that does not exist")
            cmap._rebuild_link_index(links.get("colour"))
            cmap._cur = int(robot["current"])
            if not 0 <= cmap._cur < n:
                raise InputError(f"cognitive-map state: current node {cmap._cur} does not exist")
            cmap._delta = _vec3(robot["delta"], "state robot.delta")
            cmap._odom = _vec3(robot["odom"], "state robot.odom")
            cmap._path = float(robot["path"])
            cmap._step = int(robot["step"])
            cmap._t = None if robot["t"] is None else float(robot["t"])
            cmap._t_arrive = float(robot["t_arrive"])
            cmap._arrival = int(robot.get("arrival", -1))
            cmap._code = None if robot["code"] is None else _vec3(robot["code"], "state robot.code")
            cmap._code_odom = _vec3(robot["code_odom"], "state robot.code_odom")
            cmap._anchor = None if robot["anchor"] is None else _vec3(robot["anchor"], "state robot.anchor")
            cmap._dirty = bool(robot["dirty"])
            cmap._touched = [int(k) for k in robot.get("touched", [-1] if cmap._dirty else [])]
            cmap._local_solves = int(robot.get("local_solves", 0))
            cmap._bias = float(robot.get("odometry_bias", 0.0))
            cmap._loops = LoopBook.from_state(loop)
            cmap._events = [MapEvent.from_dict(e) for e in state.get("events", [])]
            cmap._version += 1
            return cmap
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"malformed cognitive-map state: {exc!r}") from exc
