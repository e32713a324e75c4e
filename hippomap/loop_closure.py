"""Loop-closure data and maths: hypotheses and their verification.

The cognitive map (:mod:`hippomap.cognitive_map`) keeps nodes, links, relaxation and pruning, and decides on loop
hypotheses in :mod:`hippomap.loop_closing`; this module holds the data and the maths those decisions use, free of the
map's state (a hypothesis' relative pose, fitted or from an image's looming, is :mod:`hippomap.loop_pose`):

* :class:`LoopHypothesis` — a proposal "the robot is back near node ``node``", with a measured transform (a data
  set's loop edge) or, for a visual recognition, the robot's estimated offset from the node (where the matched key
  frame was learned, moved along its view by the image's scale change and turned by its shift, from the saccade
  correspondences: :func:`~hippomap.loop_pose.looming_offset`).
* :class:`Candidate` — what verification needs of a gated hypothesis: the robot's dead-reckoned pose and path at the
  proposal, the node's pose in the robot's frame.
* :func:`gate_limit` — the radius a hypothesis must fall within: a base radius plus an allowance for odometric drift
  that grows with the path travelled since the node was made or since the last verified closure, whichever is
  shorter, and one for the error of the odometry's estimated bias (:func:`bias_drift`), which grows with its square
  (per node: over the path between the node and the robot).
* :func:`cycle_errors` / :func:`consistent` — geometric verification: two hypotheses made at different times and the
  odometry between them form a cycle through the map, which must compose to identity.
* :func:`link_info3` — a loop link's information in its source frame, which the robust kernel
  (:mod:`hippomap.robust_kernel`) whitens its residual (:func:`link_errors`) by.
* :class:`LoopBook` — the decisions, pending and recently accepted candidates, and their serialisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np

from .config import MapConfig
from .errors import InputError, finite, node_id, vec3
from .geometry import between, compose, se2_compose, se2_inverse
from .least_squares import couple, link_errors

_Pose = tuple[float, float, float]  # (x, y, theta): the fixed length the type checker needs

__all__ = [
    "LoopHypothesis",
    "LoopDecision",
    "Candidate",
    "LoopBook",
    "gate_limit",
    "bias_drift",
    "bias_rate_error",
    "cycle_errors",
    "consistent",
    "couple",
    "link_errors",
    "link_info3",
    "jsonable",
]


def jsonable(x: Any) -> Any:
    """Plain Python (JSON-ready) copy of numbers, strings, tuples, lists, dicts and numpy values."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


# --------------------------------------------------------------------------- records
@dataclass(frozen=True)
class LoopHypothesis:
    """A proposed loop closure: the robot is back near earlier ``node``.

    ``transform``: a *measured* pose of ``node`` in the frame of the CURRENT node (at the time of
    the proposal), as a data set's loop edge gives; or ``None`` for a visual recognition, which
    says "same place": then ``offset`` is the proposer's estimate of the robot's pose in the
    node's frame (where the matched key frame was taken, moved along its view by the looming and
    turned by the image shift), ``None`` meaning "exactly on the node". ``information``: (x/y in
    m⁻², heading in rad⁻²) of the estimate, ``None`` for the map's default of its kind
    (``loop_information`` for a measured transform, ``visual_loop_information`` for a visual one).
    ``evidence``: the proposer's score. ``source``: who proposed it ('dataset', 'visual', ...).
    ``meta``: free-form, JSON-able. ``coupling`` (m⁻¹, visual only): what the estimate's heading
    measures is the heading plus ``coupling`` × the robot's offset beside the node, not the heading
    alone (an image shift is a turn plus a sideways step over the scene's depth, so ``coupling`` =
    1 / that depth); 0 = the heading alone. The link then holds ``heading + coupling · lateral``
    with the heading's information and the lateral offset with its own (:func:`couple`).
    ``along_sigma`` (m, visual only): how uncertain ``offset`` is along the key frame's view, on top of
    ``information``: a recognition's looming reads the robot's step along the view through a scene depth
    it does not know, so the larger the step, the less sure it is. The link's information along its x
    axis (the robot's heading, which faces roughly as the key frame looked) is lowered to match in the
    solve; the robust kernel still weighs the link at ``information``. 0 = ``information`` alone.
    """

    node: int
    transform: tuple[float, float, float] | None = None
    evidence: float = 1.0
    source: str = "visual"
    time: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)
    offset: tuple[float, float, float] | None = None
    information: tuple[float, float] | None = None
    coupling: float = 0.0
    along_sigma: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "node", node_id(self.node, "LoopHypothesis.node"))
        if self.node < 0:
            raise InputError(f"LoopHypothesis.node must be >= 0, got {self.node}")
        if self.transform is not None:
            object.__setattr__(self, "transform", vec3(self.transform, "LoopHypothesis.transform"))
        if self.offset is not None:
            if self.transform is not None:
                raise InputError("LoopHypothesis: give a measured transform or an offset, not both")
            object.__setattr__(self, "offset", vec3(self.offset, "LoopHypothesis.offset"))
        if self.information is not None:
            info = tuple(finite("LoopHypothesis.information", v) for v in self.information)
            if len(info) != 2 or min(info) <= 0:
                raise InputError(f"LoopHypothesis.information must be two positive numbers, got {self.information!r}")
            object.__setattr__(self, "information", info)
        object.__setattr__(self, "coupling", finite("LoopHypothesis.coupling", self.coupling))
        if self.coupling < 0 or (self.coupling and self.transform is not None):
            raise InputError(
                f"LoopHypothesis.coupling must be >= 0 and only on a visual hypothesis, got {self.coupling!r}"
            )
        object.__setattr__(self, "along_sigma", finite("LoopHypothesis.along_sigma", self.along_sigma))
        if self.along_sigma < 0 or (self.along_sigma and self.transform is not None):
            raise InputError(
                f"LoopHypothesis.along_sigma must be >= 0 and only on a visual hypothesis, got {self.along_sigma!r}"
            )
        object.__setattr__(self, "evidence", finite("LoopHypothesis.evidence", self.evidence))
        object.__setattr__(self, "time", finite("LoopHypothesis.time", self.time))
        if not isinstance(self.source, str):
            raise InputError(f"LoopHypothesis.source must be a string, got {self.source!r}")
        if not isinstance(self.meta, dict):
            raise InputError(f"LoopHypothesis.meta must be a dict, got {self.meta!r}")

    @property
    def measured(self) -> bool:
        return self.transform is not None

    def to_dict(self) -> dict[str, Any]:
        out = {
            "node": self.node,
            "transform": None if self.transform is None else list(self.transform),
            "offset": None if self.offset is None else list(self.offset),
            "information": None if self.information is None else list(self.information),
            "evidence": self.evidence,
            "source": self.source,
            "time": self.time,
            "meta": jsonable(self.meta),
        }
        if self.coupling:  # absent when 0, as in records written before the field
            out["coupling"] = self.coupling
        if self.along_sigma:  # absent when 0, as in records written before the field
            out["along_sigma"] = self.along_sigma
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LoopHypothesis":
        t, o, i = d.get("transform"), d.get("offset"), d.get("information")
        return cls(
            node=d["node"],
            transform=None if t is None else tuple(t),
            evidence=d.get("evidence", 1.0),
            source=d.get("source", "visual"),
            time=d.get("time", 0.0),
            meta=dict(d.get("meta", {})),
            offset=None if o is None else tuple(o),
            information=None if i is None else tuple(i),
            coupling=d.get("coupling", 0.0),
            along_sigma=d.get("along_sigma", 0.0),
        )


@dataclass(frozen=True)
class LoopDecision:
    """The map's verdict on one hypothesis: ``status`` 'pending' | 'accepted' | 'rejected'.

    ``id`` indexes :attr:`CognitiveMap.loop_decisions`; ``from_node`` was the current node at
    proposal; ``support`` the ids of the consistent hypotheses that backed it;
    ``gate_distance``/``gate_limit`` the gate (m); ``link`` the loop link created (-1 if none);
    ``transform`` the link's transform as applied (node in the frame of ``from_node``, after the
    group's relative-pose fit); ``proposed_step``/``decided_step`` count map updates.
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
    transform: tuple[float, float, float] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "status": self.status,
            "reason": self.reason,
            "hypothesis": self.hypothesis.to_dict(),
            "from_node": self.from_node,
            "support": list(self.support),
            "gate_distance_m": None if math.isnan(self.gate_distance) else self.gate_distance,
            "gate_limit_m": None if math.isnan(self.gate_limit) else self.gate_limit,
            "link": self.link,
            "proposed_step": self.proposed_step,
            "decided_step": self.decided_step,
            "transform": None if self.transform is None else list(self.transform),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "LoopDecision":
        nan = float("nan")
        tr = d.get("transform")
        return cls(
            id=int(d["id"]),
            status=d["status"],
            reason=d["reason"],
            hypothesis=LoopHypothesis.from_dict(d["hypothesis"]),
            from_node=int(d["from_node"]),
            support=tuple(int(s) for s in d.get("support", ())),
            gate_distance=nan if d.get("gate_distance_m") is None else float(d["gate_distance_m"]),
            gate_limit=nan if d.get("gate_limit_m") is None else float(d["gate_limit_m"]),
            link=int(d.get("link", -1)),
            proposed_step=int(d.get("proposed_step", 0)),
            decided_step=int(d.get("decided_step", -1)),
            transform=None if tr is None else cast(_Pose, tuple(float(v) for v in tr)),
        )


@dataclass(frozen=True)
class Candidate:
    """What verification needs of a gated hypothesis."""

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
    info: tuple[float, ...] = (100.0, 1000.0)  # information of the link (x/y, heading) or (x, y, heading)
    kernel_width: float = 1.0  # robust kernel width of the link, in its standard deviations
    coupling: float = 0.0  # the hypothesis' heading-lateral coupling (m^-1; LoopHypothesis.coupling)
    coupled_heading: float = 0.0  # what it measured: heading + coupling x lateral of the robot in the node frame
    along_sigma: float = 0.0  # the hypothesis' along-track uncertainty (m; LoopHypothesis.along_sigma)
    turned: bool = False  # beyond the group heading bound: it waits for a long group (MapConfig.loop_turned_group)

    @property
    def delta(self) -> tuple[float, float, float]:
        """The robot's pose in the frame of ``from_node`` at the proposal."""
        return se2_compose(self.link_tr, se2_inverse(self.M))

    @property
    def ahead(self) -> float:
        """How far ahead of its node, along the node's heading, the hypothesis puts the robot (m; its offset's
        x: the looming of item 37): the place it names lies that far on along the old path."""
        return se2_inverse(self.M)[0]

    def with_offset(self, offset) -> "Candidate":
        """The same candidate with the robot at ``offset`` in the node's frame."""
        M = se2_inverse(offset)
        return replace(self, link_tr=se2_compose(self.delta, M), M=M)

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "node": self.node,
            "from_node": self.from_node,
            "link_tr": list(self.link_tr),
            "M": list(self.M),
            "odom": list(self.odom),
            "step": self.step,
            "arrival": self.arrival,
            "measured": self.measured,
            "path": self.path,
            "info": list(self.info),
            "kernel_width": self.kernel_width,
        } | (
            ({"coupling": self.coupling, "coupled_heading": self.coupled_heading} if self.coupling else {})
            | ({"along_sigma": self.along_sigma} if self.along_sigma else {})
            | ({"turned": True} if self.turned else {})
        )

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Candidate":
        return cls(
            int(d["id"]),
            int(d["node"]),
            int(d["from_node"]),
            cast(_Pose, tuple(map(float, d["link_tr"]))),
            cast(_Pose, tuple(map(float, d["M"]))),
            cast(_Pose, tuple(map(float, d["odom"]))),
            int(d["step"]),
            int(d.get("arrival", -1)),
            bool(d.get("measured", False)),
            float(d.get("path", 0.0)),
            tuple(float(v) for v in d.get("info", (100.0, 1000.0))),
            float(d.get("kernel_width", 1.0)),
            float(d.get("coupling", 0.0)),
            float(d.get("coupled_heading", 0.0)),
            float(d.get("along_sigma", 0.0)),
            bool(d.get("turned", False)),
        )


# --------------------------------------------------------------------------- verification
def drift_path(path: float, node_path, last_verified_path: float | None = None):
    """Odometric path over which drift may separate the robot's map pose from a node's: the
    path travelled since the node was made, or since the last verified closure if that is
    shorter (that closure re-anchored the robot on the corrected map). The map passes
    ``last_verified_path`` for visual hypotheses only: a measured transform's gate is tight
    (``loop_transform_radius_m``), and measured on Bicocca the reset made it reject true
    closures while the map was still absorbing the last ones."""
    d = path - np.asarray(node_path, dtype=float)
    if last_verified_path is not None:
        d = np.minimum(d, path - last_verified_path)
    return np.maximum(d, 0.0)


def gate_limit(cfg: MapConfig, measured: bool, drift, bias_m: Any = 0.0) -> Any:
    """Gate radius (m): base radius (smaller for a measured transform, which says where the
    node is) plus ``loop_radius_per_m`` per metre of drift path, plus ``bias_m``, what the error of
    the odometry's estimated bias may have moved the robot (:func:`bias_drift`)."""
    base = cfg.loop_transform_radius_m if measured else cfg.loop_radius_m
    return base + cfg.loop_radius_per_m * np.asarray(drift, dtype=float) + bias_m


def bias_rate_error(cfg: MapConfig, bias_sd: float, unkept: float = 0.0, seconds: float = 0.0) -> float:
    """The heading-rate error (rad/s) the gate allows for: ``loop_radius_bias_sd`` posterior standard deviations
    ``bias_sd`` of the whole solve's bias estimate, plus ``unkept``, the size of an estimate it did not keep (the map
    applies no bias then, so the odometry's may be that much plus the doubt; ``map.loop_bias_unkept``, docs/MODEL.md
    item 125). 0 with the option off, or when no estimate bounds it (``bias_sd`` 0 or not finite). ``seconds``: the
    run's length ``T``; a bias wandering as a random walk of ``map.loop_bias_walk`` (rad/s)/√s stands off its average
    over the run by ``walk √(T / 3)`` (sd), added to ``bias_sd`` in quadrature (docs/MODEL.md item 126)."""
    if cfg.loop_radius_bias_sd <= 0 or not 0 < bias_sd < math.inf:
        return 0.0
    wander = cfg.loop_bias_walk**2 * max(seconds, 0.0) / 3.0
    return cfg.loop_radius_bias_sd * math.sqrt(bias_sd * bias_sd + wander) + unkept


def bias_drift(
    cfg: MapConfig,
    bias_sd: float,
    path_m: float,
    seconds_per_m: float,
    node_m: Any = None,
    unkept: float = 0.0,
    seconds: float = 0.0,
) -> Any:
    """How far (m) the error of the odometry's estimated heading bias may have moved the robot's map
    pose over the ``path_m`` metres since the map last anchored it (the last verified closure).

    A bias error ``e`` (rad/s) turns the heading by ``e t`` after ``t`` seconds; each metre driven then is off by
    that angle, so at a steady ``seconds_per_m`` the position is off by ``∫ e t ds = e path_m² seconds_per_m / 2``.
    The gate allows it for ``e`` = ``loop_radius_bias_sd`` posterior standard deviations ``bias_sd`` of the estimate
    (0 when no bias estimate is applied): the drift allowance ``loop_radius_per_m`` grows with the path, this one
    with its square, which is how a heading-rate error grows. A ``bias_sd`` that is not finite (an estimate kept by
    a config without the significance test while the graph does not determine it) bounds nothing: no allowance,
    rather than a gate over the whole map. ``node_m`` (the path since each node was made): the error between the
    robot and a node ``d`` metres back is the heading error over those metres only, ``e d (D - d/2) seconds_per_m``
    for ``d`` below ``D`` = ``path_m`` (``map.loop_bias_per_node``). ``unkept``: the size (rad/s) of an estimate the
    whole solve did not keep, and ``seconds`` (the run's length), as :func:`bias_rate_error`."""
    e = bias_rate_error(cfg, bias_sd, unkept, seconds)
    if e <= 0 or path_m <= 0 or seconds_per_m <= 0:
        return 0.0
    if node_m is None:
        return float(e * path_m * path_m * seconds_per_m / 2.0)
    d = np.minimum(np.asarray(node_m, dtype=float), path_m)
    return e * seconds_per_m * d * (path_m - d / 2.0)


def cycle_errors(older: list[Candidate], b: Candidate, P: np.ndarray) -> np.ndarray:
    """(K, 3) error of the cycle robot_a → robot_b (dead-reckoned odometry) → node_b (hypothesis
    b) → node_a (the map's current relative pose) → robot_a (hypothesis a, inverted), one row
    per older candidate a."""
    odom = np.array([c.odom for c in older])
    Ma = np.array([c.M for c in older])
    na = np.array([c.node for c in older])
    e = compose(between(odom, np.asarray(b.odom)), np.asarray(b.M))
    e = compose(e, between(P[b.node], P[na]))
    return compose(e, between(Ma, np.zeros(3)))


def place_of(c: Candidate, P: np.ndarray) -> np.ndarray:
    """Where candidate ``c`` puts the robot on the map: the node's pose ⊕ the robot's offset."""
    return compose(P[c.node], between(np.asarray(c.M), np.zeros(3)))


def consistent(cfg: MapConfig, older: list[Candidate], b: Candidate, P: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Consistency of ``b`` with each of ``older`` (vectorised over them).

    Two measured hypotheses: their cycle (:func:`cycle_errors`) must close, in translation within
    ``loop_consistency_m``, in rotation within ``loop_transform_consistency_rad`` plus
    ``loop_consistency_rad_per_m`` × the cycle's odometric length (robot path between the
    proposals plus map path between the nodes).

    Otherwise (a visual hypothesis says where the robot is, not which way it faces): the
    distance the robot drove between the two proposals (dead reckoning) must equal the distance
    between the two places they name on the map, within ``loop_consistency_m``. This test needs
    no heading, so the robot's unknown heading relative to the key frame cannot fail a true pair;
    the group's rotation is fitted when it is accepted (:func:`~hippomap.loop_pose.align_group`).
    """
    if not older:
        return np.zeros(0, dtype=bool)
    both_measured = np.array([c.measured for c in older]) & b.measured
    ok = np.zeros(len(older), dtype=bool)
    if both_measured.any():
        sel = [c for c, m in zip(older, both_measured) if m]
        e = cycle_errors(sel, b, P)
        na = np.array([c.node for c in sel])
        cycle_m = np.abs(b.path - np.array([c.path for c in sel])) + np.abs(S[b.node] - S[na])
        rad = cfg.loop_transform_consistency_rad + cfg.loop_consistency_rad_per_m * cycle_m
        ok[both_measured] = (np.hypot(e[:, 0], e[:, 1]) < cfg.loop_consistency_m) & (np.abs(e[:, 2]) < rad)
    if not both_measured.all():
        sel = [c for c, m in zip(older, both_measured) if not m]
        odom = np.array([c.odom for c in sel])
        places = np.array([place_of(c, P) for c in sel])
        d_odom = np.hypot(odom[:, 0] - b.odom[0], odom[:, 1] - b.odom[1])
        pb = place_of(b, P)
        d_map = np.hypot(places[:, 0] - pb[0], places[:, 1] - pb[1])
        ok[~both_measured] = np.abs(d_odom - d_map) < cfg.loop_consistency_m
    return ok


# --------------------------------------------------------------------------- link information
def link_info3(info: Any) -> tuple[float, float, float]:
    """A loop link's diagonal information as (x, y, heading) in its source node's frame: a pair
    (x/y, heading) is isotropic in position; a triple gives x (along the robot's heading at the
    source node) and y (beside it) apart."""
    v = tuple(float(x) for x in info)
    if len(v) == 2:
        return (v[0], v[0], v[1])
    if len(v) != 3:
        raise InputError(f"loop-link information must be (x/y, heading) or (x, y, heading), got {len(v)} values")
    return cast("tuple[float, float, float]", v)


# --------------------------------------------------------------------------- bookkeeping
class LoopBook:
    """Every decision, the pending candidates and the recently accepted ones."""

    def __init__(self) -> None:
        self.decisions: list[LoopDecision] = []
        self.pending: list[Candidate] = []
        self.accepted: list[Candidate] = []
        self.last_verified_path: float | None = None
        #: visual hypotheses that named a node outside the gate (``outside_searches`` says whose): no link
        #: until a group of them agrees (:meth:`CognitiveMap.propose_loop`)
        self.outside: list[Candidate] = []
        #: accepted links left unverified when their support window ended, and a group's links (path counted
        #: from its acceptance): retracted if still faded later (:meth:`LoopClosing._judge_faded`)
        self.faded: list[Candidate] = []

    def expired(self, path: float, window_m: float) -> list[Candidate]:
        """Drop pending candidates older than ``window_m`` metres of path (returned, to be
        rejected) and forget accepted ones as old."""
        old = [c for c in self.pending if path - c.path > window_m]
        if old:
            self.pending = [c for c in self.pending if path - c.path <= window_m]
        self.accepted = [c for c in self.accepted if path - c.path <= window_m]
        return old

    def expired_outside(self, path: float, window_m: float) -> list[Candidate]:
        """Drop the outside-the-gate candidates older than ``window_m`` metres of path (returned)."""
        old = [c for c in self.outside if path - c.path > window_m]
        if old:
            self.outside = [c for c in self.outside if path - c.path <= window_m]
        return old

    def state_dict(self) -> dict[str, Any]:
        return {
            "decisions": [d.to_dict() for d in self.decisions],
            "pending": [c.to_dict() for c in self.pending],
            "accepted": [c.to_dict() for c in self.accepted],
            "last_verified_path": self.last_verified_path,
            "outside": [c.to_dict() for c in self.outside],
            "faded": [c.to_dict() for c in self.faded],
        }

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> "LoopBook":
        book = cls()
        book.decisions = [LoopDecision.from_dict(x) for x in d["decisions"]]
        book.pending = [Candidate.from_dict(x) for x in d["pending"]]
        book.accepted = [Candidate.from_dict(x) for x in d["accepted"]]
        lv = d.get("last_verified_path")
        book.last_verified_path = None if lv is None else float(lv)
        book.outside = [Candidate.from_dict(x) for x in d.get("outside", [])]
        book.faded = [Candidate.from_dict(x) for x in d.get("faded", [])]
        return book
