"""The cognitive map's events: small, immutable records of what one map action did
(node created or merged, loop decisions, relaxation, pruning, frames assigned), serialisable
with :meth:`MapEvent.to_dict` and rebuilt by :meth:`MapEvent.from_dict`."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar

from .errors import InputError
from .loop_closure import jsonable as _jsonable

__all__ = ["MapEvent", "NodeCreated", "NodeMerged", "LoopPending", "LoopAccepted", "LoopRejected", "MapRelaxed",
           "NodesPruned", "FrameAssigned"]


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
