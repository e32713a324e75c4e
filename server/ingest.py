"""Validation of incoming odometry and frames: every problem becomes a 4xx naming it.

Nothing here touches storage or a mapper: an input that fails is simply never accepted.
Checks run cheapest first (sizes and magic bytes before decoding). Status codes:

* 413 — too large (body, encoded frame, image dimensions, batch length);
* 415 — a frame that is not a JPEG or PNG;
* 422 — malformed or non-finite numbers, corrupt images, images the model cannot use;
* 409 — timestamps that do not increase (checked against the session in :mod:`server.sessions`).

The per-reading checks themselves are :class:`hippomap.inputs.Odometry`, :class:`~hippomap.inputs.Frame`
and :func:`hippomap.inputs.decode_jpeg`, so the server rejects exactly what the library rejects.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from hippomap.errors import InputError
from hippomap.inputs import Frame, Odometry, decode_jpeg

from .images import image_dimensions, image_kind, is_truncated
from .schemas import OdometryReading
from .settings import ServerSettings


class IngestError(Exception):
    """A rejected input: HTTP status and a message naming the problem."""

    def __init__(self, status: int, detail: str, retry_after: float | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.retry_after = retry_after


@dataclass(frozen=True)
class Accepted:
    """A validated input ready to store: its record bytes and, for the mapper, the parsed value."""

    kind: str  # "odometry" | "frame"
    t: float
    data: bytes
    value: Odometry | Frame


def pydantic_message(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(x) for x in err.get("loc", ()))
        parts.append(f"{loc}: {err.get('msg')}" if loc else str(err.get("msg")))
    return "; ".join(parts)


# ------------------------------------------------------------------ odometry
def odometry_bytes(o: Odometry) -> bytes:
    """The stored form of a reading (compact JSON; floats round-trip exactly)."""
    if o.increment is not None:
        return json.dumps({"t": o.t, "increment": list(o.increment)}, separators=(",", ":")).encode()
    return json.dumps({"t": o.t, "v": o.v, "omega": o.omega}, separators=(",", ":")).encode()


def odometry_from_bytes(data: bytes) -> Odometry:
    d = json.loads(data)
    inc = d.get("increment")
    return Odometry(d["t"], v=d.get("v"), omega=d.get("omega"), increment=None if inc is None else tuple(inc))


def check_odometry(readings: list[OdometryReading], max_batch: int) -> list[Accepted]:
    """Validate a batch: each reading finite and well-formed, timestamps increasing within it."""
    if len(readings) > max_batch:
        raise IngestError(413, f"odometry batch of {len(readings)} readings exceeds the limit of {max_batch}")
    if not readings:
        raise IngestError(422, "odometry batch is empty")
    out: list[Accepted] = []
    prefix = (lambda i: f"readings[{i}]: ") if len(readings) > 1 else (lambda i: "")
    for i, r in enumerate(readings):
        try:
            o = Odometry(r.t, v=r.v, omega=r.omega, increment=r.increment)
        except InputError as exc:
            raise IngestError(422, f"{prefix(i)}{exc}") from None
        if out and not o.t > out[-1].t:
            raise IngestError(409, f"{prefix(i)}odometry timestamp {o.t!r} does not follow the previous reading "
                                   f"at {out[-1].t!r}")
        out.append(Accepted("odometry", o.t, odometry_bytes(o), o))
    return out


def parse_odometry_message(msg: dict[str, Any], max_batch: int) -> list[Accepted]:
    """The odometry of a websocket text message: inline fields or ``readings``."""
    body = {k: v for k, v in msg.items() if k not in ("type", "id")}
    try:
        if "readings" in body:
            if set(body) != {"readings"}:
                raise IngestError(422, f"unexpected fields next to readings: {sorted(set(body) - {'readings'})}")
            if not isinstance(body["readings"], list):
                raise IngestError(422, "readings must be a list")
            if len(body["readings"]) > max_batch:
                raise IngestError(413, f"odometry batch of {len(body['readings'])} readings exceeds the limit of {max_batch}")
            readings = [OdometryReading.model_validate(r) for r in body["readings"]]
        else:
            readings = [OdometryReading.model_validate(body)]
    except ValidationError as exc:
        raise IngestError(422, f"bad odometry message: {pydantic_message(exc)}") from None
    return check_odometry(readings, max_batch)


# -------------------------------------------------------------------- frames
def check_frame(data: bytes, t: Any, settings: ServerSettings) -> Accepted:
    """Validate an encoded frame: timestamp, byte size, type, dimensions, then decode it."""
    try:
        tf = float(t)
    except (TypeError, ValueError):
        raise IngestError(422, f"frame t must be a number, got {t!r}") from None
    if not math.isfinite(tf):
        raise IngestError(422, f"frame t must be finite, got {tf}")
    if not data:
        raise IngestError(422, "empty image payload")
    if len(data) > settings.max_frame_bytes:
        raise IngestError(413, f"frame of {len(data)} bytes exceeds the limit of {settings.max_frame_bytes} bytes")
    if image_kind(data) is None:
        raise IngestError(415, "frame is not a JPEG or PNG image (bad magic bytes)")
    try:
        w, h = image_dimensions(data)
    except InputError as exc:
        raise IngestError(422, str(exc)) from None
    if w <= 0 or h <= 0:
        raise IngestError(422, f"image header gives an empty image ({w}x{h})")
    if is_truncated(data):
        raise IngestError(422, "corrupt image: truncated (no end-of-image marker)")
    if max(w, h) > settings.max_image_side or w * h > settings.max_image_pixels:
        raise IngestError(413, f"image of {w}x{h} px exceeds the limit ({settings.max_image_side} px a side, "
                               f"{settings.max_image_pixels} px in all)")
    try:
        gray = decode_jpeg(data)
        frame = Frame(tf, gray)
    except InputError as exc:
        raise IngestError(422, str(exc)) from None
    if gray.shape != (h, w):
        raise IngestError(422, f"corrupt image: header says {w}x{h}, decoded {gray.shape[1]}x{gray.shape[0]}")
    return Accepted("frame", tf, bytes(data), frame)


def frame_from_bytes(t: float, data: bytes) -> Frame:
    """Decode a stored frame (already validated when it was accepted)."""
    return Frame(t, decode_jpeg(data))
