"""The server's only window on the model: create, restore and query a session's mapper.

Everything the server needs from :class:`hippomap.mapper.Mapper` goes through this module,
so the sessions, the worker and the routes see a small interface (:class:`MapperPort`) and a
change in the model touches one file. Reads are typed query values
(:mod:`hippomap.mapper_queries`, re-exported here as ``model.queries``) that the worker hands
to the session's host, wherever the mapper runs; the functions below turn their answers into
plain, JSON-ready data. No model logic lives here.
"""

from __future__ import annotations

import json
import math
import struct
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import numpy as np

from hippomap import inputs
from hippomap import mapper_queries as queries
from hippomap.config import HippomapConfig
from hippomap.inputs import Frame, Odometry
from hippomap.map_events import MapEvent

if TYPE_CHECKING:
    from hippomap.spatial_pathway import PlaceCode

__all__ = [
    "MapperPort",
    "queries",
    "effective_config",
    "new_mapper",
    "load_mapper",
    "follows",
    "check_frame",
    "graph",
    "loop_closures",
    "draw_saccades",
    "place_field_blob",
    "place_field_from_blob",
    "place_field_dense",
    "json_safe",
    "event_dict",
]

T = TypeVar("T")


class MapperPort(Protocol):
    """What the session's host uses of a mapper: inputs in, typed events out, typed reads, bytes."""

    place_field: "PlaceCode | None"  # the latest place code (with its field), or None

    def step(self, odometry: Odometry) -> list[MapEvent]: ...

    def observe(self, frame: Frame) -> list[MapEvent]: ...

    def answer(self, query: queries.Query[T]) -> T: ...

    def to_bytes(self) -> bytes: ...

    def stats(self) -> dict[str, Any]: ...


# ---------------------------------------------------------------- lifecycle
def effective_config(overrides: dict[str, Any] | None) -> HippomapConfig:
    """The validated model config of a session (ValueError naming the bad field)."""
    return HippomapConfig.with_overrides(overrides or {})


def new_mapper(config: HippomapConfig) -> MapperPort:
    from hippomap.mapper import Mapper

    return Mapper(config)


def load_mapper(data: bytes) -> MapperPort:
    from hippomap.mapper import Mapper

    return Mapper.from_bytes(data)


# the mapper's time rule (hippomap.inputs.follows), checked at ingest so that an input the mapper would
# refuse is never stored
follows = inputs.follows


def check_frame(config: HippomapConfig, frame: Frame) -> None:
    """Raise InputError if the visual memory could not use this frame (e.g. too small for the fovea)."""
    from hippomap.visual_memory import prepare_image

    prepare_image(frame.image, config.visual, name=f"frame at t={frame.t}")


# ------------------------------------------------------------- query answers
def graph(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """Nodes and links as JSON (``hippomap.io.exports.graph_dict``) from a ``GraphArrays`` answer."""
    from hippomap.io.exports import graph_dict

    codes = np.asarray(arrays["place_codes"], dtype=float).reshape(-1, 3)
    known = np.isfinite(codes).all(axis=1)  # a node made before the first odometry step has no place code yet
    g = graph_dict(
        arrays["poses"],
        np.where(known[:, None], codes, 0.0),
        arrays["frames"],
        arrays["times"],
        arrays["source"],
        arrays["target"],
        arrays["transform"],
        arrays["kind"],
    )
    for i in np.flatnonzero(~known):
        g["nodes"][i]["place_code"] = None
    return g


def loop_closures(report: queries.LoopReport) -> list[dict[str, Any]]:
    """Every loop decision of a ``LoopDecisions`` answer, JSON-ready, with the recognition behind it and
    its link's robust ``weight`` now (None without a link) and whether the map ``used`` it: an accepted
    closure the robust kernel has faded stays accepted but is not used."""
    out = []
    for d, w, used in zip(report.decisions, report.weights.tolist(), report.used()):
        row = _finite(d.to_dict())
        h = row["hypothesis"]
        meta = h.get("meta") or {}
        out.append(
            {
                "id": row["id"],
                "t": h.get("time"),
                "status": row["status"],
                "weight": None if math.isnan(w) else w,
                "used": used,
                "nodes": [row.get("from_node"), h.get("node")],
                "evidence": h.get("evidence"),
                "source": h.get("source"),
                "recognition": meta.get("recognition"),
                "decision": row,
            }
        )
    return out


def draw_saccades(image: np.ndarray, rec: dict[str, Any], attempt: Any = "last") -> np.ndarray:
    """The query frame with the recognition's saccade trace drawn (BGR), by the model's drawing code."""
    from hippomap.visual_memory import Recognition, SaccadeStep, draw_trace

    fields = {f for f in SaccadeStep.__dataclass_fields__}
    steps = []
    for s in rec.get("steps", []):
        kw = {k: v for k, v in s.items() if k in fields}
        kw["fixation"] = tuple(kw["fixation"]) if kw.get("fixation") is not None else None
        kw["target"] = tuple(kw["target"]) if kw.get("target") is not None else None
        kw["evidence"] = [tuple(e) for e in kw.get("evidence", [])]
        steps.append(SaccadeStep(**kw))
    r = Recognition(
        frame_id=rec.get("frame_id"),
        evidence=float(rec.get("evidence") or 0.0),
        steps=steps,
        n_resets=int(rec.get("n_resets", 0)),
        confidence=float(rec.get("confidence") or 0.0),
        image_size=tuple(rec.get("image_size", (0, 0))),
        reason=rec.get("reason", ""),
    )
    return draw_trace(image, r, attempt=attempt)


# ------------------------------------------------------------- place fields
_PF_HEADER = struct.Struct("<I")


def place_field_blob(code: Any) -> bytes:
    """A PlaceCode's field as bytes: JSON metadata + the sparse field's flat indices (int32)."""
    f = code.field
    meta = {
        "size": int(f.size),
        "resolution": float(f.resolution),
        "origin": [float(v) for v in code.origin],
        "centroid": [float(v) for v in f.centroid],
        "place_code": [float(code.x), float(code.y), float(code.theta)],
        "iterations": int(f.iterations),
    }
    js = json.dumps(meta).encode()
    return _PF_HEADER.pack(len(js)) + js + np.asarray(f.indices, dtype=np.int32).tobytes()


def place_field_from_blob(data: bytes) -> tuple[dict[str, Any], np.ndarray]:
    (n,) = _PF_HEADER.unpack_from(data)
    meta = json.loads(data[_PF_HEADER.size : _PF_HEADER.size + n])
    idx = np.frombuffer(data[_PF_HEADER.size + n :], dtype=np.int32).astype(np.int64)
    return meta, idx


def place_field_dense(meta: dict[str, Any], indices: np.ndarray) -> np.ndarray:
    """The position matrix POS (rows = y, columns = x) as uint8 0/1."""
    size = int(meta["size"])
    out = np.zeros(size * size, dtype=np.uint8)
    out[indices] = 1
    return out.reshape(size, size)


# -------------------------------------------------------------------- utils
def _finite(obj: Any) -> Any:
    """JSON cannot carry NaN or infinity: replace them by None, recursively."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


json_safe = _finite


def event_dict(event: MapEvent) -> dict[str, Any]:
    """An event as the store and the REST API keep it: ``MapEvent.to_dict``, JSON-safe."""
    return _finite(event.to_dict())
