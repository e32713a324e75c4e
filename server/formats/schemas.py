"""Request and response bodies of the HTTP API (they make the OpenAPI document)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictFloat

from hippomap.config import HippomapConfig


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ------------------------------------------------------------------ inputs
class OdometryReading(_In):
    """One odometry reading: velocities held since the previous reading, or a pose increment."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "oneOf": [
                {
                    "required": ["t", "v", "omega"],
                    "properties": {"v": {"type": "number"}, "omega": {"type": "number"}, "increment": {"type": "null"}},
                },
                {
                    "required": ["t", "increment"],
                    "properties": {"increment": {"type": "array"}, "v": {"type": "null"}, "omega": {"type": "null"}},
                },
            ],
            "examples": [
                {"t": 12.5, "v": 0.4, "omega": 0.05},
                {"t": 12.55, "increment": [0.02, 0.0, 0.0025]},
                {"t": 12.6, "v": 0.4, "omega": 0.0, "gt": [3.1, -0.4, 1.57]},
            ],
        },
    )

    # strict numbers: a JSON string ("0.1") or boolean (true) is refused, not coerced
    t: StrictFloat = Field(
        description="timestamp, seconds; must exceed the session's previous input and lie "
        "at most max_time_jump_s (30 days) after the session's newest input"
    )
    v: StrictFloat | None = Field(None, description="forward velocity, m/s (|v| <= max_speed_mps, 100)")
    omega: StrictFloat | None = Field(None, description="turn rate, rad/s (|omega| <= max_turn_rate_rad_s, 100)")
    increment: tuple[StrictFloat, StrictFloat, StrictFloat] | None = Field(
        None,
        description="relative pose (dx, dy, dtheta) in the previous pose's frame, instead of v/omega "
        "(|dx|, |dy| <= max_increment_m, 100; |dtheta| <= max_increment_rad, 2 pi)",
    )
    gt: tuple[StrictFloat, StrictFloat, StrictFloat] | None = Field(
        None,
        description="optional ground-truth pose (x, y, theta) at t in the ground truth's own frame (simulated "
        "runs, data sets): stored with the reading and drawn by the viewer; the mapper never uses it",
    )


class OdometryBatch(_In):
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [{"readings": [{"t": 12.5, "v": 0.4, "omega": 0.05}, {"t": 12.55, "v": 0.4, "omega": 0.04}]}]
        },
    )

    readings: list[OdometryReading] = Field(min_length=1, description="readings in increasing time order")


class IngestAck(BaseModel):
    """Inputs stored durably under sequence numbers ``seq``..``last_seq``."""

    session: str
    seq: int
    last_seq: int
    count: int


# ---------------------------------------------------------------- sessions
class SessionCreate(_In):
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"name": "warehouse, lap 3", "config": {"mapper": {"keyframe_interval": 10}}},
                {"name": "defaults"},
            ]
        },
    )

    name: str = Field("", max_length=200, description="free label")
    base_session: str | None = Field(
        None,
        max_length=100,
        description="start in a copy of this session's map (one the token can read; it is "
        "never changed): the new run's odometry starts from an unknown pose and is placed on the map when its "
        "recognitions of the base's key frames are verified; `config` then changes the base's config (it must "
        'keep the visual section), e.g. {"mapper": {"mode": "localise"}} to localise without changing the map',
    )
    config: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description='overrides of the model config by section, e.g. {"mapper": {"keyframe_interval": 10}}; the '
        "fields of each section, their ranges and defaults: GET /sessions/{id} shows a session's full config",
        json_schema_extra={
            "properties": {
                name: {"type": "object", "description": f"overrides of the {name!r} section"}
                for name in HippomapConfig.model_fields
            },
            "additionalProperties": False,
        },
    )


class SessionInfo(BaseModel):
    id: str
    name: str
    created: float
    config_overrides: dict[str, Any]
    stats: dict[str, Any] | None = Field(
        description="see GET /sessions/{id}/stats; null for a session another replica runs"
    )
    replica: str = Field(description="the server replica that runs the session (holds its lease)")


class SessionDetail(SessionInfo):
    config: dict[str, Any] = Field(description="the effective model config")
    links: dict[str, str] = Field(description="URLs of the session's resources")


class Stats(BaseModel):
    """Server-side progress of a session and the mapper's own statistics."""

    session: str
    inputs_stored: int = Field(description="inputs accepted and durable")
    last_seq: int = Field(description="sequence number of the last stored input (-1: none)")
    last_t: float | None = Field(description="timestamp of the newest input of either kind")
    last_odometry_t: float | None = Field(description="the next odometry reading must be later than this")
    last_frame_t: float | None = Field(description="the next frame must be later than this")
    processed_seq: int = Field(description="last input the mapper has consumed (-1: none)")
    pending: int = Field(description="inputs stored but not yet consumed by the mapper")
    snapshot_seq: int = Field(description="last input covered by the newest snapshot (-1: none)")
    replaying: bool = Field(description="the session is restoring after a restart")
    backend: dict[str, Any] = Field(
        default_factory=dict,
        description="where the session's mapper runs: 'kind' "
        "(inprocess, ray), for Ray the actor's 'pid' and 'node', and 'restarts'",
    )
    backend_restarts: int = Field(
        0, description="times the session's mapper (Ray actor) died and was restored from its last snapshot plus replay"
    )
    error: str | None = Field(description="why the session's worker stopped, if it did")
    input_errors: int = Field(
        0,
        description="stored inputs the mapper could not process since this server started "
        "(skipped; each is an 'input_failed' event)",
    )
    last_input_error: str | None = Field(None, description="the latest of them: its seq and the error")
    rejected: dict[str, int] = Field(description="rejected inputs by HTTP status")
    mapper: dict[str, Any] = Field(description="Mapper.stats()")


# ----------------------------------------------------------------- queries
class Node(BaseModel):
    id: int
    pose: list[float] = Field(description="map pose (x, y, theta) after relaxation")
    place_code: list[float] | None = Field(
        description="global place code p (x, y, theta), Eq. 11; null before the first odometry step"
    )
    frame: int | None = Field(description="key frame learned at the node")
    t: float | None


class Link(BaseModel):
    source: int
    target: int
    transform: list[float] = Field(description="(dx, dy, dtheta) of target in source's frame")
    kind: str


class MapGraph(BaseModel):
    nodes: list[Node]
    links: list[Link]


class Event(BaseModel):
    """One event of the session (``hippomap.map_events``), stored under the input that caused it."""

    id: int = Field(description="event number in the session, from 0")
    seq: int = Field(description="the input that caused it")
    type: str = Field(description="what happened: node_created, loop_accepted, recognition, keyframe_learned, ...")
    t: float | None = Field(description="the event's time, s (its data's 't'; null if not finite)")
    data: dict[str, Any] = Field(
        description="the event's fields, the same for every event type: 'type', the time 't', then its own fields"
    )


class LoopClosure(BaseModel):
    """One loop-closure decision of the cognitive map, accepted or rejected."""

    id: int = Field(description="event id (use since_id to page)")
    t: float | None = Field(description="time of the hypothesis")
    status: str = Field(description="'accepted', 'rejected' or 'pending'")
    weight: float | None = Field(
        description="the robust weight of its loop link now (0-1; None without a link): the kernel revises it "
        "whenever the map is solved, so a closure the map no longer agrees with fades"
    )
    used: bool = Field(description="accepted and its weight at least 0.5: the map applies it (else it has faded)")
    nodes: list[int | None] = Field(description="[current node, matched node]")
    evidence: float | None
    source: str | None = Field(description="what proposed it, e.g. 'visual'")
    recognition: int | None = Field(description="id of the recognition (saccade trace) behind it")
    saccades: str | None = Field(description="URL of the saccade trace")
    decision: dict[str, Any] = Field(description="the decision as the cognitive map reported it")


class RecognitionInfo(BaseModel):
    id: int
    t: float | None
    node: int | None
    accepted: bool | None
    frame_id: int | None
    evidence: float | None
    n_fixations: int | None
    search: str | None = Field(
        None,
        description="which key frames competed: 'sequence' (of the gate's, those learned near the key frame the "
        "last recognition named, searched first), 'gated' (those the loop gate admits near the robot's map pose, or "
        "the rest of them after a sequence search) or 'global' (every other one, after a long run without a "
        "verified closure); None in older sessions",
    )
    candidates: int | None = Field(None, description="how many key frames competed; None in older sessions")
    primed: int | None = Field(
        None,
        description="how many of them started primed as the old path's sequence, those learned near the key frame "
        "the last recognition named (mapper.sequence_prior: a head start, not a decision); None when none did",
    )
    saccades: str
    image: str


class PlaceFieldInfo(BaseModel):
    step: int = Field(description="odometry step (counts odometry inputs from 0)")
    seq: int
    t: float


class PlaceField(PlaceFieldInfo):
    size: int = Field(description="the position matrix is size x size")
    resolution: float = Field(description="metres per cell")
    origin: list[float] = Field(description="corner o of the coding area, metres")
    centroid: list[float] = Field(description="field centroid in the coding area, metres")
    place_code: list[float] = Field(description="global place code p = o + centroid, with heading")
    iterations: int
    indices: list[int] = Field(description="flat indices iy * size + ix of the field's cells")


# ------------------------------------------------------------------ tokens
class TokenCreate(_In):
    # a writer token is never limited to one session
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "anyOf": [
                {"properties": {"role": {"const": "viewer"}}},
                {"required": ["role"], "properties": {"role": {"const": "writer"}, "session": {"type": "null"}}},
            ],
            "examples": [{"role": "viewer", "label": "control-room dashboard"}, {"role": "writer", "label": "robot 7"}],
        },
    )

    role: Literal["viewer", "writer"] = "viewer"
    session: str | None = Field(None, description="viewer only: limit the token to this session")
    label: str = Field("", max_length=200)


class TokenInfo(BaseModel):
    id: str
    role: str
    owner: str | None
    session: str | None
    label: str
    created: float


class TokenCreated(TokenInfo):
    token: str = Field(description="the secret; shown only once")


class Problem(BaseModel):
    detail: Any


# ------------------------------------------------------- websocket messages
# The stream /sessions/{id}/stream (server/formats/protocol.py) is not an HTTP operation: OpenAPI cannot list
# it. These models document its JSON messages in the OpenAPI document's ``x-websockets`` extension
# (server/api/wsdoc.py); the stream itself validates odometry with OdometryReading, as HTTP does.
MessageId = int | float | str | None


class WsOdometry(OdometryReading):
    """Client → server: one odometry reading (the fields of OdometryReading inline)."""

    model_config = ConfigDict(
        extra="forbid",
        title="odometry",
        json_schema_extra={
            "examples": [
                {"type": "odometry", "id": 7, "t": 12.5, "v": 0.4, "omega": 0.05},
                {"type": "odometry", "id": 8, "t": 12.55, "increment": [0.02, 0.0, 0.0025]},
            ]
        },
    )

    type: Literal["odometry"]
    id: MessageId = Field(
        None, description="echoed in the ack or error (a number, or a string of at most 128 characters)"
    )


class WsOdometryBatch(_In):
    """Client → server: a batch of odometry readings, acknowledged together."""

    model_config = ConfigDict(
        extra="forbid",
        title="odometry batch",
        json_schema_extra={
            "examples": [
                {
                    "type": "odometry",
                    "id": 9,
                    "readings": [{"t": 12.6, "v": 0.4, "omega": 0.0}, {"t": 12.65, "v": 0.4, "omega": 0.0}],
                }
            ]
        },
    )

    type: Literal["odometry"]
    id: MessageId = None
    readings: list[OdometryReading] = Field(min_length=1, description="readings in increasing time order")


class WsPing(_In):
    """Client → server: answered by a pong with the same id."""

    model_config = ConfigDict(
        extra="forbid", title="ping", json_schema_extra={"examples": [{"type": "ping", "id": 10}]}
    )

    type: Literal["ping"]
    id: MessageId = None


class WsHello(BaseModel):
    """Server → client, first message: where the session stands (lets a robot resume)."""

    model_config = ConfigDict(
        title="hello",
        json_schema_extra={
            "examples": [
                {
                    "type": "hello",
                    "session": "s_3f9a1c2b7d4e",
                    "last_seq": 41,
                    "last_t": 12.5,
                    "last_odometry_t": 12.5,
                    "last_frame_t": 12.4,
                    "max_pending": 256,
                }
            ]
        },
    )

    type: Literal["hello"]
    session: str
    last_seq: int = Field(description="sequence number of the last stored input (-1: none)")
    last_t: float | None
    last_odometry_t: float | None = Field(description="the next odometry reading must be later than this")
    last_frame_t: float | None = Field(description="the next frame must be later than this")
    max_pending: int = Field(description="inputs the session queues before the server stops reading (busy)")


class WsAck(BaseModel):
    """Server → client: the message's inputs are durable as ``seq``..``last_seq``; acks come in message order."""

    model_config = ConfigDict(
        title="ack", json_schema_extra={"examples": [{"type": "ack", "id": 7, "seq": 42, "last_seq": 42, "count": 1}]}
    )

    type: Literal["ack"]
    id: MessageId
    seq: int
    last_seq: int
    count: int


class WsError(BaseModel):
    """Server → client: the message was refused (HTTP status codes); nothing of it was stored, the stream
    stays open."""

    model_config = ConfigDict(
        title="error",
        json_schema_extra={
            "examples": [{"type": "error", "id": 7, "status": 422, "detail": "odometry v must be finite, got nan"}]
        },
    )

    type: Literal["error"]
    id: MessageId
    status: int
    detail: str


class WsBusy(BaseModel):
    """Server → client: the mapper's queue is full; the server reads nothing more until there is room."""

    model_config = ConfigDict(
        title="busy", json_schema_extra={"examples": [{"type": "busy", "pending": 256, "max_pending": 256}]}
    )

    type: Literal["busy"]
    pending: int
    max_pending: int


class WsPong(BaseModel):
    """Server → client: the answer to a ping."""

    model_config = ConfigDict(title="pong", json_schema_extra={"examples": [{"type": "pong", "id": 10}]})

    type: Literal["pong"]
    id: MessageId
