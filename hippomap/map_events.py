"""Every event of a mapping session, in one typed schema: small, immutable records of what one
call did (node created or merged, loop decisions, relaxation, pruning, frames assigned,
recognitions, key frames learned, inputs the service could not map).

One time key: every event has the field ``t``, the map or stream time (s) of the action, the
same key as the inputs, recognitions and REST answers. An event is returned by the call that
caused it (``Mapper.step`` / ``Mapper.observe``), serialised by :meth:`MapEvent.to_dict`
(JSON-ready, ``type`` first) and rebuilt by :meth:`MapEvent.from_dict`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar

from .errors import InputError
from .loop_closure import LoopDecision
from .loop_closure import jsonable as _jsonable

__all__ = [
    "MapEvent",
    "NodeCreated",
    "NodeMerged",
    "LoopPending",
    "LoopAccepted",
    "LoopRejected",
    "MapRelaxed",
    "NodesPruned",
    "FrameAssigned",
    "RecognitionMade",
    "LoopDecided",
    "KeyframeLearned",
    "InputRejected",
    "InputFailed",
    "EVENT_TYPES",
]


@dataclass(frozen=True)
class MapEvent:
    """Base of the events: small, immutable, serialisable with :meth:`to_dict`. Every subclass has
    the field ``t`` (declared in each, so that it keeps its place among the fields; checked below)."""

    type: ClassVar[str] = "event"

    def to_dict(self) -> dict[str, Any]:
        """The event as JSON-ready data: ``type`` and every field."""
        out: dict[str, Any] = {"type": self.type}
        out.update({f.name: _jsonable(getattr(self, f.name)) for f in fields(self)})
        return out

    @classmethod
    def _from_fields(cls, data: dict[str, Any]) -> "MapEvent":
        kwargs = {}
        for f in fields(cls):
            if f.name not in data:
                raise InputError(f"{cls.type} event lacks the field {f.name!r}")
            v = data[f.name]
            kwargs[f.name] = tuple(v) if isinstance(v, list) else v
        return cls(**kwargs)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> "MapEvent":
        """The event :meth:`to_dict` gave; InputError for an unknown ``type`` or a missing field."""
        cls = EVENT_TYPES.get(data.get("type", ""))
        if cls is None:
            raise InputError(f"unknown map event type {data.get('type')!r}; known: {sorted(EVENT_TYPES)}")
        if "t" not in data and "time" in data:  # a map snapshot written before the one time key, with queued events
            data = {("t" if k == "time" else k): v for k, v in data.items()}
        return cls._from_fields(data)


# ----------------------------------------------------------------- the cognitive map's
@dataclass(frozen=True)
class NodeCreated(MapEvent):
    """CREATE_NODE (Eq. 12): ``node`` at ``pose``, linked from ``from_node`` by ``link``."""

    type: ClassVar[str] = "node_created"
    node: int
    from_node: int
    link: int
    pose: tuple[float, float, float]
    place_code: tuple[float, float, float]
    t: float


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
    t: float


@dataclass(frozen=True)
class LoopPending(MapEvent):
    """Hypothesis ``decision`` passed the gate and waits for consistent support."""

    type: ClassVar[str] = "loop_pending"
    decision: int
    node: int
    from_node: int
    support: int
    t: float


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
    t: float


@dataclass(frozen=True)
class LoopRejected(MapEvent):
    """Hypothesis ``decision`` was rejected for ``reason``; node poses were not touched."""

    type: ClassVar[str] = "loop_rejected"
    decision: int
    node: int
    from_node: int
    reason: str
    t: float


@dataclass(frozen=True)
class MapRelaxed(MapEvent):
    """The map's node poses were corrected by ``solver``."""

    type: ClassVar[str] = "map_relaxed"
    solver: str
    iterations: int
    max_shift: float
    t: float


@dataclass(frozen=True)
class NodesPruned(MapEvent):
    """Batch pruning pass: ``removed`` nodes merged into their block's oldest node."""

    type: ClassVar[str] = "nodes_pruned"
    removed: int
    nodes: int
    links: int
    frames_dropped: int
    t: float


@dataclass(frozen=True)
class FrameAssigned(MapEvent):
    """Key frame ``frame`` was attached to ``node`` (its ``V``)."""

    type: ClassVar[str] = "frame_assigned"
    node: int
    frame: int
    t: float


# ------------------------------------------------------------------------ the mapper's
@dataclass(frozen=True)
class RecognitionMade(MapEvent):
    """A key frame taken at ``t`` was recognised (accepted or not) while ``node`` was current.
    ``id`` indexes ``Mapper.recognitions``; ``result`` is the recognition's outcome
    (``Recognition.to_dict``: frame_id, evidence, saccade steps...), flattened into the
    serialised event beside ``id``, ``t`` and ``node``, so the event reads like the
    recognition record the REST API serves."""

    type: ClassVar[str] = "recognition"
    id: int
    t: float
    node: int
    result: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return {"type": self.type, **self.record()}

    def record(self) -> dict[str, Any]:
        """The recognition record (``Mapper.recognitions``): the serialised event without ``type``
        (``result`` is JSON-ready already: it is shared, not copied)."""
        return {"id": self.id, "t": self.t, "node": self.node, **self.result}

    @classmethod
    def _from_fields(cls, data: dict[str, Any]) -> "RecognitionMade":
        rest = {k: v for k, v in data.items() if k not in ("type", "id", "t", "node")}
        try:
            return cls(id=int(data["id"]), t=float(data["t"]), node=int(data["node"]), result=rest)
        except KeyError as exc:
            raise InputError(f"recognition event lacks the field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class LoopDecided(MapEvent):
    """The loop closing's verdict on the hypothesis a recognition made at ``t`` (the decision as
    :meth:`CognitiveMap.propose_loop` returned it; the map's own events follow it). Serialised
    flat: ``t`` beside the decision's fields (``LoopDecision.to_dict``)."""

    type: ClassVar[str] = "loop_decision"
    t: float
    decision: LoopDecision

    def to_dict(self) -> dict[str, Any]:
        return {"type": self.type, "t": self.t, **self.decision.to_dict()}

    @classmethod
    def _from_fields(cls, data: dict[str, Any]) -> "LoopDecided":
        if "t" not in data:
            raise InputError("loop_decision event lacks the field 't'")
        rest = {k: v for k, v in data.items() if k not in ("type", "t")}
        try:
            return cls(t=float(data["t"]), decision=LoopDecision.from_dict(rest))
        except KeyError as exc:
            raise InputError(f"loop_decision event lacks the field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class KeyframeLearned(MapEvent):
    """The frame taken at ``t`` was learned as key frame ``frame`` of ``node``."""

    type: ClassVar[str] = "keyframe_learned"
    t: float
    frame: int
    node: int


# ------------------------------------------------------------------ the service's
@dataclass(frozen=True)
class InputRejected(MapEvent):
    """Input ``seq`` (time ``t``) broke a rule of the model the service could not check before
    storing it; the mapper skipped it (``detail`` is the model's InputError)."""

    type: ClassVar[str] = "input_rejected"
    t: float
    seq: int
    detail: str


@dataclass(frozen=True)
class InputFailed(MapEvent):
    """The mapper raised on input ``seq`` (time ``t``); it was skipped and the session went on
    (deterministically: a replay skips it the same way)."""

    type: ClassVar[str] = "input_failed"
    t: float
    seq: int
    detail: str


EVENT_TYPES: dict[str, type[MapEvent]] = {
    c.type: c
    for c in (
        NodeCreated,
        NodeMerged,
        LoopPending,
        LoopAccepted,
        LoopRejected,
        MapRelaxed,
        NodesPruned,
        FrameAssigned,
        RecognitionMade,
        LoopDecided,
        KeyframeLearned,
        InputRejected,
        InputFailed,
    )
}
"""Event classes by their ``type``."""

for _cls in EVENT_TYPES.values():  # the one time key
    if "t" not in {f.name for f in fields(_cls)}:
        raise TypeError(f"event class {_cls.__name__} has no time field 't'")
