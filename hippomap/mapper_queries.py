"""The reads a service or a viewer makes of a live :class:`~hippomap.mapper.Mapper`, as typed values.

Why values and not functions: a session's mapper may run in another process (a child process, a
Ray actor), and a read must cross to it. A frozen dataclass naming the operation and its
arguments pickles with the standard library, can be checked before it runs (only the operations
listed here run: anything else is refused with an :class:`~hippomap.errors.InputError` that
names it), and says what it returns (``Query[T]``). Every read of the map's internals is here,
so the service and the viewer never reach into ``mapper.cmap`` or ``mapper.pathway``.

Each query's :meth:`Query.run` only reads and copies: it runs between two inputs, under the
session's lock, so it must be short (the viewer's :class:`ViewerState` copies arrays and nothing
more). Run one with :meth:`Mapper.answer <hippomap.mapper.Mapper.answer>` (or :func:`run_query`),
or build one from an operation name and arguments with :func:`query_named`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Literal, TypeVar

import numpy as np

from .errors import InputError
from .robust_kernel import used_flags

if TYPE_CHECKING:
    from .config import HippomapConfig, SpatialConfig
    from .iteration_record import IterationRecord
    from .loop_closure import LoopDecision
    from .mapper import Mapper
    from .spatial_pathway import PlaceCode

__all__ = [
    "Query",
    "Stats",
    "GraphArrays",
    "Trajectory",
    "LoopDecisions",
    "LoopReport",
    "Recognitions",
    "RecognitionById",
    "ViewerState",
    "MapView",
    "PlaceCellIteration",
    "MapperConfig",
    "LastInputTime",
    "BaseSnapshot",
    "MapperState",
    "QUERY_TYPES",
    "check_query",
    "run_query",
    "query_named",
]

T = TypeVar("T")


@dataclass(frozen=True)
class Query(Generic[T]):
    """A read of a mapper: ``op`` names it, the fields are its arguments, :meth:`run` answers it."""

    op: ClassVar[str] = ""

    def run(self, mapper: "Mapper") -> T:
        raise NotImplementedError


def _int(name: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise InputError(f"query argument {name} must be an integer >= {low}, got {value!r}")


@dataclass(frozen=True)
class Stats(Query[dict[str, Any]]):
    """The mapper's counters (``Mapper.stats``)."""

    op: ClassVar[str] = "stats"

    def run(self, mapper: "Mapper") -> dict[str, Any]:
        return mapper.stats()


@dataclass(frozen=True)
class GraphArrays(Query[dict[str, np.ndarray]]):
    """Copies of the map's arrays: ``poses``, ``place_codes``, ``frames``, ``times`` per node;
    ``source``, ``target``, ``transform``, ``kind`` (names) per link; with ``information``, each
    link's information as the map weighs it (``CognitiveMap.weighted_link_information``: what the g2o export writes)."""

    op: ClassVar[str] = "graph_arrays"
    information: bool = False

    def run(self, mapper: "Mapper") -> dict[str, np.ndarray]:
        cm = mapper.cmap
        links = cm.links
        out = {
            "poses": np.array(cm.poses),
            "place_codes": np.array(cm.place_codes),
            "frames": np.array(cm.frames),
            "times": np.array(cm.times),
            "source": np.array(links["source"]),
            "target": np.array(links["target"]),
            "transform": np.array(links["transform"]),
            "kind": np.array(links["kind"]),
        }
        if self.information:
            out["information"] = np.array(cm.weighted_link_information())
            out["coupling"] = np.array(cm.link_coupling())
        return out


@dataclass(frozen=True)
class Trajectory(Query[tuple[np.ndarray, np.ndarray]]):
    """``(times, (N, 3) poses)`` of every odometry step: on the corrected map (``source='map'``)
    or raw path integration (``'odometry'``)."""

    op: ClassVar[str] = "trajectory"
    source: Literal["map", "odometry"] = "map"

    def __post_init__(self) -> None:
        if self.source not in ("map", "odometry"):
            raise InputError(f"trajectory source must be 'map' or 'odometry', got {self.source!r}")

    def run(self, mapper: "Mapper") -> tuple[np.ndarray, np.ndarray]:
        poses = mapper.corrected_trajectory() if self.source == "map" else mapper.odometry_trajectory()
        return mapper.trajectory_times, poses


@dataclass(frozen=True)
class LoopReport:
    """Every loop decision with its link's robust weight now, read at one instant.

    A decision is an immutable record (the map replaces, never mutates it), but the robust kernel
    revises its link's weight whenever the map is solved: an accepted closure the map no longer
    agrees with fades without its decision changing. So the weights come with the decisions."""

    decisions: tuple["LoopDecision", ...]
    weights: np.ndarray  # (len(decisions),) float64: robust weight of each decision's link, NaN without one

    def used(self) -> list[bool]:
        """Per decision, whether the map uses it (:func:`~hippomap.robust_kernel.used_flags`)."""
        return used_flags(self.decisions, self.weights)


@dataclass(frozen=True)
class LoopDecisions(Query[LoopReport]):
    """Every loop decision, latest status, with its link's robust weight (:class:`LoopReport`)."""

    op: ClassVar[str] = "loop_decisions"

    def run(self, mapper: "Mapper") -> LoopReport:
        cm = mapper.cmap
        return LoopReport(tuple(cm.loop_decisions), cm.loop_weights())


@dataclass(frozen=True)
class Recognitions(Query[list[dict[str, Any]]]):
    """Up to ``limit`` recognition records with an id above ``since_id``, oldest first."""

    op: ClassVar[str] = "recognitions"
    since_id: int = -1
    limit: int = 1000

    def __post_init__(self) -> None:
        _int("since_id", self.since_id, -1)
        _int("limit", self.limit, 0)

    def run(self, mapper: "Mapper") -> list[dict[str, Any]]:
        start = self.since_id + 1
        return list(mapper.recognitions[start : start + self.limit])


@dataclass(frozen=True)
class RecognitionById(Query["dict[str, Any] | None"]):
    """Recognition record ``id`` (with its saccade trace), or None if there is none."""

    op: ClassVar[str] = "recognition"
    id: int

    def __post_init__(self) -> None:
        _int("id", self.id, 0)

    def run(self, mapper: "Mapper") -> dict[str, Any] | None:
        recs = mapper.recognitions
        return recs[self.id] if self.id < len(recs) else None


@dataclass(frozen=True)
class MapView:
    """What one viewer update draws, copied at one instant (see :class:`ViewerState`)."""

    node_poses: np.ndarray  # (N, 3) map poses after relaxation
    node_frames: np.ndarray  # (N,) key frame id per node, -1 = none
    link_source: np.ndarray  # (M,) int64
    link_target: np.ndarray  # (M,) int64
    link_kind: np.ndarray  # (M,) int8 codes of hippomap.cognitive_map.LINK_KINDS
    link_weight: np.ndarray  # (M,) robust weight: 1 for odometric links, the kernel's for loop links
    trajectory_start: int  # index of the first row of ``trajectory``
    trajectory: np.ndarray  # (K, 8) rows from trajectory_start: t, raw x y theta, node, offset x y theta
    current_node: int
    robot_pose: np.ndarray  # (3,) the robot on the map
    decisions: tuple["LoopDecision", ...]
    loop_weights: np.ndarray  # (len(decisions),) robust weight of each decision's link, NaN without one
    recognition_count: int
    last_recognition: dict[str, Any] | None  # the newest recognition record
    place_code: "PlaceCode | None"  # the current step's place code (its field), if it has one
    spatial: "SpatialConfig"  # the spatial pathway's config (its grid-cell tables: GridCells(spatial).tables)
    odometric_pose: np.ndarray  # (3,) path-integrated pose (the place code's frame)
    stats: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ViewerState(Query[MapView]):
    """The viewer's copy: node poses, key frames and links whole (a relaxation moves every pose, a
    batch prune renumbers nodes), the append-only trajectory from row ``trajectory_start`` on, the
    loop decisions, the newest recognition (by reference: a stored record is never mutated), the
    place code and poses. Arrays only, so the session's lock is held for a copy's time."""

    op: ClassVar[str] = "viewer_state"
    trajectory_start: int = 0

    def __post_init__(self) -> None:
        _int("trajectory_start", self.trajectory_start, 0)

    def run(self, mapper: "Mapper") -> MapView:
        cm = mapper.cmap
        links = cm.links
        stats = mapper.stats()
        start = self.trajectory_start
        if start > stats["odometry_steps"]:  # beyond the history (a cursor of another mapper): restart
            start = 0
        rows = mapper.trajectory_rows(start)
        recs = mapper.recognitions
        code = mapper.place_field
        return MapView(
            node_poses=np.array(cm.poses, dtype=float),
            node_frames=np.array(cm.frames, dtype=np.int64),
            link_source=np.array(links["source"], dtype=np.int64),
            link_target=np.array(links["target"], dtype=np.int64),
            link_kind=np.array(links["kind_code"], dtype=np.int8),
            link_weight=cm.link_weights(),
            trajectory_start=start,
            trajectory=np.asarray(rows, dtype=float),
            current_node=int(cm.current),
            robot_pose=np.array(cm.robot_pose_estimate, dtype=float),
            decisions=tuple(cm.loop_decisions),
            loop_weights=cm.loop_weights(),
            recognition_count=len(recs),
            last_recognition=recs[-1] if recs else None,
            place_code=code if code is not None and code.field is not None else None,
            spatial=mapper.pathway.cfg,
            odometric_pose=np.array(mapper.pathway.pose, dtype=float),
            stats=stats,
        )


@dataclass(frozen=True)
class PlaceCellIteration(Query["IterationRecord | None"]):
    """The current step's place-field iteration, recorded (the paper's Fig. 8); None before the
    first odometry step with a place field."""

    op: ClassVar[str] = "place_cell_iteration"

    def run(self, mapper: "Mapper") -> "IterationRecord | None":
        return mapper.pathway.record() if mapper.place_field is not None else None


@dataclass(frozen=True)
class MapperConfig(Query["HippomapConfig"]):
    """The mapper's validated config."""

    op: ClassVar[str] = "config"

    def run(self, mapper: "Mapper") -> "HippomapConfig":
        return mapper.config


@dataclass(frozen=True)
class LastInputTime(Query["float | None"]):
    """Time stamp of the newest input the mapper processed (either kind), None before any."""

    op: ClassVar[str] = "last_input_time"

    def run(self, mapper: "Mapper") -> float | None:
        return mapper.last_t


@dataclass(frozen=True)
class BaseSnapshot(Query[bytes]):
    """The state of a new run in a copy of this mapper's map (``Mapper.from_base``, which only
    reads the mapper) with config ``overrides`` (``{"section": {"field": value}}``), as bytes."""

    op: ClassVar[str] = "base_snapshot"
    overrides: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.overrides, dict):
            raise InputError(f"query argument overrides must be a mapping, got {type(self.overrides).__name__}")

    def run(self, mapper: "Mapper") -> bytes:
        return type(mapper).from_base(mapper, self.overrides).to_bytes()


@dataclass(frozen=True)
class MapperState(Query[bytes]):
    """The whole mapper state as bytes (``Mapper.to_bytes``): a saved map to reuse offline."""

    op: ClassVar[str] = "mapper_state"

    def run(self, mapper: "Mapper") -> bytes:
        return mapper.to_bytes()


QUERY_TYPES: dict[str, type[Query[Any]]] = {
    c.op: c
    for c in (
        Stats,
        GraphArrays,
        Trajectory,
        LoopDecisions,
        Recognitions,
        RecognitionById,
        ViewerState,
        PlaceCellIteration,
        MapperConfig,
        LastInputTime,
        BaseSnapshot,
        MapperState,
    )
}
"""The operations a mapper answers, by name."""


def check_query(query: Any) -> None:
    """InputError unless ``query`` is one of the operations of :data:`QUERY_TYPES` (a function,
    or a subclass that runs its own code, is refused): checked before a query is sent to a
    mapper in another process, and again where it runs."""
    cls = QUERY_TYPES.get(getattr(type(query), "op", ""))
    if cls is None or type(query) is not cls:
        raise InputError(
            f"unknown mapper query {query!r}: a query is one of hippomap.mapper_queries' operations "
            f"({', '.join(sorted(QUERY_TYPES))})"
        )


def run_query(mapper: "Mapper", query: Query[T]) -> T:
    """``query``'s answer from ``mapper`` (:func:`check_query` first)."""
    check_query(query)
    return query.run(mapper)


def query_named(op: str, **args: Any) -> Query[Any]:
    """The query of operation ``op`` with ``args``; InputError naming an unknown operation or argument."""
    cls = QUERY_TYPES.get(op)
    if cls is None:
        raise InputError(f"unknown mapper query operation {op!r}; known: {', '.join(sorted(QUERY_TYPES))}")
    known = {f.name for f in fields(cls)}
    extra = sorted(set(args) - known)
    if extra:
        raise InputError(f"query {op!r} takes no argument(s) {extra}; it takes: {sorted(known) or 'none'}")
    try:
        return cls(**args)
    except TypeError as exc:
        raise InputError(f"query {op!r}: {exc}") from None
