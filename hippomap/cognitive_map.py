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
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np

from .config import MapConfig
from .errors import InputError, finite
from .geometry import between, compose
from .relaxation import (
    ColourGroups,
    colour_link,
    edge_colouring,
    link_residuals,
    relax,
    relax_jacobi,
    solve_lsq,
)

#: link kinds, stored as small integer codes
LINK_KINDS = ("odometry", "loop", "prune")
ODOMETRY, LOOP, PRUNE = 0, 1, 2

_TWO_PI = 2.0 * math.pi
_STATE_VERSION = 1


# --------------------------------------------------------------------------- small SE(2) scalars
def _wrap(a: float) -> float:
    return (a + math.pi) % _TWO_PI - math.pi


def _compose3(a, b) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap(a[2] + b[2]))


def _inv3(a) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], _wrap(-a[2]))


def _between3(a, b) -> tuple[float, float, float]:
    return _compose3(_inv3(a), b)


def _jsonable(x: Any) -> Any:
    """Plain Python (JSON-ready) copy of numbers, strings, tuples, lists, dicts and numpy values."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def _vec3(value: Any, name: str) -> tuple[float, float, float]:
    """A finite (x, y, θ) triple from a sequence (or an object with x, y, theta), else InputError."""
    if hasattr(value, "x") and hasattr(value, "y") and hasattr(value, "theta"):
        value = (value.x, value.y, value.theta)
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be three numbers (x, y, theta), got {value!r}") from None
    if arr.shape != (3,):
        raise InputError(f"{name} must be three numbers (x, y, theta), got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _node_id(value: Any, name: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an integer node id, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------- events
@dataclass(frozen=True)
class MapEvent:
    """Base of the map's events: small, immutable, serialisable with :meth:`to_dict`."""

    type: ClassVar[str] = "event"

    def to_dict(self) -> dict[str, Any]:
        out = {"type": self.type}
        out.update({f.name: _jsonable(getattr(self, f.name)) for f in fields(self)})
        return out

    @staticmethod
    def from_dict(data: dict[str, Any]) -> "MapEvent":
        cls = _EVENT_TYPES.get(data.get("type", ""))
        if cls is None:
            raise InputError(f"unknown map event type {data.get('type')!r}")
        kwargs = {}
        for f in fields(cls):
            v = data[f.name]
            kwargs[f.name] = tuple(v) if isinstance(v, list) else v
        return cls(**kwargs)


@dataclass(frozen=True)
class NodeCreated(MapEvent):
    """CREATE_NODE (Eq. 12): ``node`` at ``pose``, linked from ``from_node`` by ``link``."""

    type: ClassVar[str] = "node_created"
    node: int
    from_node: int
    link: int
    pose: tuple[float, float, float]
    place_code: tuple[float, float, float]
    time: float


@dataclass(frozen=True)
class NodeMerged(MapEvent):
    """Online pruning (Eq. 15, Fig. 7): the would-be node fell in the block of older ``node``,
    which became current; ``link`` (-1 if that pair was already linked) joins ``from_node`` to it;
    ``offset`` is the robot's pose in the frame of ``node``."""

    type: ClassVar[str] = "node_merged"
    node: int
    from_node: int
    link: int
    offset: tuple[float, float, float]
    time: float


@dataclass(frozen=True)
class LoopPending(MapEvent):
    """Hypothesis ``decision`` passed the gate and waits for consistent support."""

    type: ClassVar[str] = "loop_pending"
    decision: int
    node: int
    from_node: int
    support: int
    time: float


@dataclass(frozen=True)
class LoopAccepted(MapEvent):
    """Hypothesis ``decision`` closed a loop: ``link`` from ``from_node`` to ``node``.
    ``relocalised``: the robot's current node became ``node``."""

    type: ClassVar[str] = "loop_accepted"
    decision: int
    node: int
    from_node: int
    link: int
    support: tuple[int, ...]
    relocalised: bool
    time: float


@dataclass(frozen=True)
class LoopRejected(MapEvent):
    """Hypothesis ``decision`` was rejected for ``reason``; node poses were not touched."""

    type: ClassVar[str] = "loop_rejected"
    decision: int
    node: int
    from_node: int
    reason: str
    time: float


@dataclass(frozen=True)
class MapRelaxed(MapEvent):
    """The map's node poses were corrected by ``solver``."""

    type: ClassVar[str] = "map_relaxed"
    solver: str
    iterations: int
    max_shift: float
    time: float


@dataclass(frozen=True)
class NodesPruned(MapEvent):
    """Batch pruning pass: ``removed`` nodes merged into their block's oldest node."""

    type: ClassVar[str] = "nodes_pruned"
    removed: int
    nodes: int
    links: int
    frames_dropped: int
    time: float


@dataclass(frozen=True)
class FrameAssigned(MapEvent):
    """Key frame ``frame`` was attached to ``node`` (its ``V``)."""

    type: ClassVar[str] = "frame_assigned"
    node: int
    frame: int
    time: float


_EVENT_TYPES: dict[str, type[MapEvent]] = {
    c.type: c for c in (NodeCreated, NodeMerged, LoopPending, LoopAccepted, LoopRejected, MapRelaxed,
                        NodesPruned, FrameAssigned)
}


# --------------------------------------------------------------------------- loop closure records
@dataclass(frozen=True)
class LoopHypothesis:
    """A proposed loop closure: the robot is back near earlier ``node``.

    ``transform``: pose of ``node`` in the frame of the CURRENT node (at the time of the
    proposal), or ``None`` for "same place" (the node is at the robot's pose), as a visual
    recognition gives. ``evidence``: the proposer's score (kept, not weighted). ``source``:
    who proposed it ('dataset', 'visual', ...). ``meta``: free-form, JSON-able.
    """

    node: int
    transform: tuple[float, float, float] | None = None
    evidence: float = 1.0
    source: str = "visual"
    time: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "node", _node_id(self.node, "LoopHypothesis.node"))
        if self.node < 0:
            raise InputError(f"LoopHypothesis.node must be >= 0, got {self.node}")
        if self.transform is not None:
            object.__setattr__(self, "transform", _vec3(self.transform, "LoopHypothesis.transform"))
        object.__setattr__(self, "evidence", finite("LoopHypothesis.evidence", self.evidence))
        object.__setattr__(self, "time", finite("LoopHypothesis.time", self.time))
        if not isinstance(self.source, str):
            raise InputError(f"LoopHypothesis.source must be a string, got {self.source!r}")
        if not isinstance(self.meta, dict):
            raise InputError(f"LoopHypothesis.meta must be a dict, got {self.meta!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"node": self.node, "transform": None if self.transform is None else list(self.transform),
                "evidence": self.evidence, "source": self.source, "time": self.time, "meta": _jsonable(self.meta)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LoopHypothesis":
        t = d.get("transform")
        return cls(node=d["node"], transform=None if t is None else tuple(t), evidence=d.get("evidence", 1.0),
                   source=d.get("source", "visual"), time=d.get("time", 0.0), meta=dict(d.get("meta", {})))


@dataclass(frozen=True)
class LoopDecision:
    """The map's verdict on one hypothesis: ``status`` 'pending' | 'accepted' | 'rejected'.

    ``id`` indexes :attr:`CognitiveMap.loop_decisions`; ``from_node`` was the current node
    at proposal; ``support`` the ids of the consistent hypotheses that backed it;
    ``gate_distance``/``gate_limit`` the place-code gate (m); ``link`` the loop link created
    (-1 if none); ``proposed_step``/``decided_step`` count :meth:`CognitiveMap.update` calls.
    """

    id: int
    status: str
    reason: str
    hypothesis: LoopHypothesis
    from_node: int
    support: tuple[int, ...] = ()
    gate_distance: float = float("nan")
    gate_limit: float = float("nan")
    link: int = -1
    proposed_step: int = 0
    decided_step: int = -1

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "status": self.status, "reason": self.reason, "hypothesis": self.hypothesis.to_dict(),
                "from_node": self.from_node, "support": list(self.support),
                "gate_distance_m": None if math.isnan(self.gate_distance) else self.gate_distance,
                "gate_limit_m": None if math.isnan(self.gate_limit) else self.gate_limit,
                "link": self.link, "proposed_step": self.proposed_step, "decided_step": self.decided_step}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LoopDecision":
        nan = float("nan")
        return cls(id=int(d["id"]), status=d["status"], reason=d["reason"],
                   hypothesis=LoopHypothesis.from_dict(d["hypothesis"]), from_node=int(d["from_node"]),
                   support=tuple(int(s) for s in d.get("support", ())),
                   gate_distance=nan if d.get("gate_distance_m") is None else float(d["gate_distance_m"]),
                   gate_limit=nan if d.get("gate_limit_m") is None else float(d["gate_limit_m"]),
                   link=int(d.get("link", -1)), proposed_step=int(d.get("proposed_step", 0)),
                   decided_step=int(d.get("decided_step", -1)))


@dataclass(frozen=True)
class _Candidate:
    """What the consistency check needs of a gated hypothesis (internal)."""

    id: int
    node: int
    from_node: int
    link_tr: tuple[float, float, float]  # node in the frame of from_node
    M: tuple[float, float, float]  # node in the frame of the robot at proposal
    odom: tuple[float, float, float]  # robot's dead-reckoned pose at proposal
    step: int
    arrival: int = -1  # when node == from_node: the link by which the robot had reached it
    measured: bool = False  # the hypothesis carried a measured transform
    path: float = 0.0  # path travelled by the robot at proposal (m)


    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "node": self.node, "from_node": self.from_node, "link_tr": list(self.link_tr),
                "M": list(self.M), "odom": list(self.odom), "step": self.step, "arrival": self.arrival,
                "measured": self.measured, "path": self.path}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "_Candidate":
        return cls(int(d["id"]), int(d["node"]), int(d["from_node"]), tuple(map(float, d["link_tr"])),
                   tuple(map(float, d["M"])), tuple(map(float, d["odom"])), int(d["step"]), int(d.get("arrival", -1)),
                   bool(d.get("measured", False)), float(d.get("path", 0.0)))


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
        self._pairs: set[tuple[int, int]] = set()
        self._groups: ColourGroups | None = None
        self._groups_key = -1
        self._version = 0
        self._dirty = False  # lsq: a link with a non-zero residual was added since the last solve
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
        self._decisions: list[LoopDecision] = []
        self._pending: list[_Candidate] = []
        self._accepted: list[_Candidate] = []
        self._add_node(self._odom, (np.nan, np.nan, np.nan), 0.0)

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
        return list(self._decisions)

    @property
    def pending_count(self) -> int:
        return len(self._pending)

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
        for name in ("_src", "_dst", "_tr", "_dt", "_kind", "_col"):
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

    def _add_link(self, a: int, b: int, tr, kind: int, dt: float, allow_duplicate: bool = False) -> int:
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
        self._col[k] = colour_link(self._mask, a, b)
        self._pairs.add(key)
        self._m += 1
        self._version += 1
        r = link_residuals(self._P[: self._n], [a], [b], np.asarray(tr, dtype=float).reshape(1, 3))[0]
        if np.max(np.abs(r)) > 1e-9:
            self._dirty = True
        return k

    def _set_current(self, node: int, delta, t: float, arrival: int = -1) -> None:
        """on_set_experience: the robot is now at ``delta`` in the frame of ``node``. The
        current node's place code is re-anchored to the robot's place code, so that Eq. 13
        measures distance travelled from here, not odometric drift accumulated since the
        node was created."""
        self._cur = int(node)
        self._delta = tuple(float(v) for v in delta)
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

        Returns the events of this step, preceded by any queued since the last call (loop
        decisions made by :meth:`propose_loop`, frames assigned).
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
        if changed:
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
        ``inf`` beyond ``limit``. Builds a sparse graph: O(M)."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import dijkstra

        n, m = self._n, self._m
        if m == 0:
            d = np.full(n, np.inf)
            d[source] = 0.0
            return d
        a = np.minimum(self._src[:m], self._dst[:m])
        b = np.maximum(self._src[:m], self._dst[:m])
        w = np.hypot(self._tr[:m, 0], self._tr[:m, 1]) + 1e-9  # explicit zeros would vanish
        key, inv = np.unique(a * n + b, return_inverse=True)  # parallel links: keep the shortest
        wmin = np.full(len(key), np.inf)
        np.minimum.at(wmin, inv.reshape(-1), w)
        g = csr_matrix((wmin, (key // n, key % n)), shape=(n, n))
        return dijkstra(g, directed=False, indices=source, limit=limit)

    def _optimise(self, t: float, force: bool = False, sweeps: int | None = None) -> list[MapEvent]:
        """Correct node poses after a change of the graph (``MapConfig.solver``)."""
        m, n = self._m, self._n
        if m == 0:
            return []
        P = self._P[:n]
        src, dst, tr = self._src[:m], self._dst[:m], self._tr[:m]
        cfg = self.cfg
        sweeps = cfg.relax_loops if sweeps is None else int(sweeps)
        if cfg.solver == "lsq":
            if not (self._dirty or force):
                return []
            info = self.link_information() if cfg.lsq_weighted else None
            res = solve_lsq(P, src, dst, tr, iterations=cfg.lsq_iterations, anchor=0, information=info)
            self._dirty = False
        elif sweeps <= 0:
            return []
        elif cfg.solver == "jacobi":
            res = relax_jacobi(P, src, dst, tr, sweeps, cfg.alpha, anchor=0)
        else:
            if self._groups_key != self._version:
                self._groups = ColourGroups(src, dst, tr, self._col[:m], n, check=False)
                self._groups_key = self._version
            res = relax(P, src, dst, tr, sweeps, cfg.alpha, anchor=0, groups=self._groups)
        return [MapRelaxed(res.solver, res.iterations, res.max_shift, t)]

    def link_information(self) -> np.ndarray:
        """(M, 3) diagonal information of every link (x, y, θ) for the weighted solver: odometric
        and prune links ``odometry_information_per_m / length`` (variance grows with the path;
        lengths below 5 cm count as 5 cm), loop links ``loop_information``."""
        m = self._m
        cfg = self.cfg
        length = np.maximum(np.hypot(self._tr[:m, 0], self._tr[:m, 1]), 0.05)
        xy, th = cfg.odometry_information_per_m
        info = np.column_stack([xy / length, xy / length, th / length])
        loop = self._kind[:m] == LOOP
        info[loop] = (cfg.loop_information[0], cfg.loop_information[0], cfg.loop_information[1])
        return info

    def finish(self, iterations: int | None = None) -> list[MapEvent]:
        """End of a run: one more correction (``iterations`` sweeps, default ``relax_loops``; an
        exact solve for 'lsq') and the queued events. Pending hypotheses stay pending."""
        events, self._events = self._events, []
        events.extend(self._optimise(self._t if self._t is not None else 0.0, force=True, sweeps=iterations))
        return events

    # ------------------------------------------------------------------ loop closure
    def propose_loop(self, h: LoopHypothesis) -> LoopDecision:
        """Offer a loop closure; returns the decision (its events come out of the next :meth:`update`).

        Checks, in order:

        * ``node`` must be an existing node, not the current one nor among the last ``N_excl``.
        * (a) place-code gate: the node's place code must lie within
          ``loop_radius_m + loop_radius_per_m × (path travelled since the node was created)``
          (``loop_transform_radius_m`` instead of ``loop_radius_m`` when the hypothesis carries a
          measured transform: then only odometric drift separates the two) of where the hypothesis puts it (``p_robot ⊕`` the node's pose in the robot's frame;
          for ``transform=None`` simply ``‖p_node − p_robot‖``, Eq. 13).
        * (b) with ``loop_min_support`` ≥ 2, cycle consistency: for two hypotheses a (older)
          and b made at different updates, the cycle robot_a → robot_b (dead-reckoned
          odometry) → node_b (hypothesis b) → node_a (the map's current relative pose) →
          robot_a (hypothesis a, inverted) must compose to identity within
          ``loop_consistency_m`` / ``loop_consistency_rad`` (when both carry a measured transform:
          ``loop_transform_consistency_rad`` + ``loop_consistency_rad_per_m`` × the cycle's odometric
          length). A hypothesis waits (pending) up to
          ``loop_support_window`` updates; with ``loop_min_support`` − 1 consistent pending ones,
          or one consistent accepted in the window, it is accepted; if it contradicts every
          loop accepted in the window it is rejected.

        Accepting adds a ``loop`` link (measured transform) from the node that was current at the
        proposal to ``node``; the newest accepted hypothesis relocalises the robot (current =
        its node, the robot's residual offset kept); then the map is corrected. Rejected
        hypotheses never touch node poses.
        """
        if not isinstance(h, LoopHypothesis):
            raise InputError(f"propose_loop needs a LoopHypothesis, got {type(h).__name__}")
        n = self._n
        if not 0 <= h.node < n:
            raise InputError(f"LoopHypothesis.node {h.node} is not a node id of this map [0, {n})")
        cfg = self.cfg
        did = len(self._decisions)
        link_tr = self._delta if h.transform is None else h.transform
        cand = _Candidate(did, h.node, self._cur, link_tr, _between3(self._delta, link_tr), self._odom, self._step,
                          self._arrival if h.node == self._cur else -1, h.transform is not None, self._path)
        t = self._t if self._t is not None else h.time
        base = LoopDecision(did, "pending", "", h, self._cur, proposed_step=self._step)
        reason = ""
        if h.node != self._cur and h.node >= n - cfg.exclude_recent:
            reason = f"node {h.node} is among the {cfg.exclude_recent} most recent nodes"
        else:
            code = self._robot_code()
            if code is None or np.isnan(self._C[h.node, 0]):
                reason = "no place code yet to gate the hypothesis"
            else:
                pred = _compose3(code, cand.M)
                dist = cfg.mu_p * math.hypot(pred[0] - self._C[h.node, 0], pred[1] - self._C[h.node, 1])
                radius = cfg.loop_radius_m if h.transform is None else cfg.loop_transform_radius_m
                limit = radius + cfg.loop_radius_per_m * (self._path - self._S[h.node])
                base = replace(base, gate_distance=dist, gate_limit=limit)
                if not dist < limit:
                    reason = f"place-code distance {dist:.3f} m exceeds the gate {limit:.3f} m"
        self._decisions.append(base)
        if reason:
            return self._reject(did, reason, t)
        if cfg.loop_min_support <= 1:
            self._accept([cand], cand, t)
            return self._decisions[did]
        pend = [c for c in self._pending if c.step != cand.step]
        acc = [c for c in self._accepted if c.step != cand.step]
        ok_pend = [c for c, ok in zip(pend, self._consistent(pend, cand)) if ok]
        ok_acc = [c for c, ok in zip(acc, self._consistent(acc, cand)) if ok]
        if ok_acc or (not acc and 1 + len(ok_pend) >= cfg.loop_min_support):
            support = tuple(c.id for c in ok_pend + ok_acc)
            self._accept(ok_pend + [cand], cand, t, support)
            return self._decisions[did]
        if acc:
            ids = ", ".join(str(c.id) for c in acc)
            return self._reject(did, f"contradicts the loop closure(s) accepted within the window: {ids}", t)
        self._pending.append(cand)
        self._decisions[did] = replace(base, support=tuple(c.id for c in ok_pend))
        self._events.append(LoopPending(did, h.node, cand.from_node, len(ok_pend), t))
        return self._decisions[did]

    def _consistent(self, older: list[_Candidate], b: _Candidate) -> np.ndarray:
        """Cycle-consistency of ``b`` with each of ``older`` (vectorised over them)."""
        if not older:
            return np.zeros(0, dtype=bool)
        odom = np.array([c.odom for c in older])
        Ma = np.array([c.M for c in older])
        na = np.array([c.node for c in older])
        P = self._P
        # robot_a -> robot_b -> node_b -> node_a -> robot_a
        e = compose(between(odom, np.asarray(b.odom)), np.asarray(b.M))
        e = compose(e, between(P[b.node], P[na]))
        e = compose(e, between(Ma, np.zeros(3)))
        # two measured transforms: the cycle's rotation error is their disagreement plus the heading
        # drift of its odometric parts (robot path between the proposals, map path between the nodes)
        both_measured = np.array([c.measured for c in older]) & b.measured
        cycle_m = np.abs(b.path - np.array([c.path for c in older])) + np.abs(self._S[b.node] - self._S[na])
        cfg = self.cfg
        rad = np.where(both_measured, cfg.loop_transform_consistency_rad + cfg.loop_consistency_rad_per_m * cycle_m,
                       cfg.loop_consistency_rad)
        return (np.hypot(e[:, 0], e[:, 1]) < cfg.loop_consistency_m) & (np.abs(e[:, 2]) < rad)

    def _reject(self, did: int, reason: str, t: float) -> LoopDecision:
        d = replace(self._decisions[did], status="rejected", reason=reason, decided_step=self._step)
        self._decisions[did] = d
        self._events.append(LoopRejected(did, d.hypothesis.node, d.from_node, reason, t))
        return d

    def _accept(self, group: list[_Candidate], reloc: _Candidate, t: float, support: tuple[int, ...] = ()) -> None:
        ids = {c.id for c in group}
        group = sorted(group, key=lambda c: c.id)
        arrival = -1
        for c in group:
            link = self._add_loop_link(c)
            if c is reloc:
                arrival = link
            sup = tuple(sorted((set(support) | ids) - {c.id}))
            reason = "place-code gate" if self.cfg.loop_min_support <= 1 else "place-code gate and cycle consistency"
            if link < 0:
                reason += "; names the node it was proposed from: robot offset corrected, no link"
            self._decisions[c.id] = replace(self._decisions[c.id], status="accepted", reason=reason, link=link,
                                            support=sup, decided_step=self._step)
            self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, sup, c is reloc, t))
            self._accepted.append(c)
        self._pending = [c for c in self._pending if c.id not in ids]
        if self.cfg.loop_relocalise:
            self._set_current(reloc.node, _inv3(reloc.M), t, arrival)
        # the remaining pending hypotheses: supported by the accepted group, or contradicted by it
        still = []
        for c in self._pending:
            others = [g for g in group if g.step != c.step]
            if not others:
                still.append(c)
                continue
            if np.any(self._consistent(others, c)):  # the cycle test is symmetric in the pair
                link = self._add_loop_link(c)
                sup = tuple(sorted(ids))
                self._decisions[c.id] = replace(self._decisions[c.id], status="accepted",
                                                reason="supported by an accepted loop closure", link=link,
                                                support=sup, decided_step=self._step)
                self._events.append(LoopAccepted(c.id, c.node, c.from_node, link, sup, False, t))
                self._accepted.append(c)
            else:
                self._reject(c.id, "contradicted by the accepted loop closure(s) " + ", ".join(map(str, sorted(ids))), t)
        self._pending = still
        self._events.extend(self._optimise(t))

    def _add_loop_link(self, c: _Candidate) -> int:
        """The loop link of an accepted hypothesis ``from_node → node`` with the measured transform.

        A hypothesis may name the node it was proposed from: the robot had already reached that
        node A by online pruning (or an earlier loop) through the *arrival* link prev → A. The
        measurement then says where A is seen from prev: ``arrival ⊕ transform``. An unverified
        prune link is overwritten by it (and becomes a loop link); otherwise a loop link
        prev → A is added. Without an arrival link there is nothing to link (-1): the hypothesis
        only corrects the robot's offset when it relocalises.
        """
        if c.node != c.from_node:
            return self._add_link(c.from_node, c.node, c.link_tr, LOOP, 0.0, allow_duplicate=True)
        k = c.arrival
        if k < 0 or k >= self._m or self._dst[k] != c.node:
            return -1
        tr = _compose3(self._tr[k], c.link_tr)
        if self._kind[k] == PRUNE:
            self._tr[k] = tr
            self._kind[k] = LOOP
            self._version += 1
            self._dirty = True
            return k
        return self._add_link(int(self._src[k]), c.node, tr, LOOP, 0.0, allow_duplicate=True)

    def _expire(self) -> list[MapEvent]:
        w = self.cfg.loop_support_window
        t = self._t if self._t is not None else 0.0
        keep = []
        for c in self._pending:
            if self._step - c.step > w:
                self._reject(c.id, f"expired: no consistent support within {w} updates", t)
            else:
                keep.append(c)
        self._pending = keep
        self._accepted = [c for c in self._accepted if self._step - c.step <= w]
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
        self._kind[:ml] = self._kind[:m][kl]
        self._src[:ml], self._dst[:ml] = s_new, d_new
        self._m = ml
        self._rebuild_link_index()
        self._version += 1
        self._dirty = True
        self._cur = int(old_to_new[self._cur])
        self._delta = delta
        code = self._robot_code()
        self._anchor = None if code is None else _compose3(code, _inv3(delta))
        t = self._t if self._t is not None else 0.0
        self._arrival = -1
        remap = lambda c: replace(c, node=int(old_to_new[c.node]), from_node=int(old_to_new[c.from_node]),  # noqa: E731
                                  arrival=-1)
        for c in self._pending:
            if old_to_new[c.node] == old_to_new[c.from_node]:
                self._reject(c.id, "prune() merged its node into the node it was proposed from", t)
        self._pending = [remap(c) for c in self._pending if old_to_new[c.node] != old_to_new[c.from_node]]
        self._accepted = [remap(c) for c in self._accepted]
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
                      "kind": self._kind[:m].astype(np.int64), "colour": self._col[:m].copy()},
            "robot": {"current": self._cur, "delta": list(self._delta), "odom": list(self._odom), "path": self._path,
                      "step": self._step, "t": self._t, "t_arrive": self._t_arrive, "arrival": self._arrival,
                      "code": None if self._code is None else list(self._code), "code_odom": list(self._code_odom),
                      "anchor": None if self._anchor is None else list(self._anchor), "dirty": self._dirty},
            "loop": {"decisions": [d.to_dict() for d in self._decisions],
                     "pending": [c.to_dict() for c in self._pending],
                     "accepted": [c.to_dict() for c in self._accepted]},
            "events": [e.to_dict() for e in self._events],
        }

    @classmethod
    def from_state(cls, cfg: MapConfig, state: dict[str, Any]) -> "CognitiveMap":
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
            cmap._decisions = [LoopDecision.from_dict(d) for d in loop["decisions"]]
            cmap._pending = [_Candidate.from_dict(d) for d in loop["pending"]]
            cmap._accepted = [_Candidate.from_dict(d) for d in loop["accepted"]]
            cmap._events = [MapEvent.from_dict(e) for e in state.get("events", [])]
            cmap._version += 1
            return cmap
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"malformed cognitive-map state: {exc!r}") from exc
