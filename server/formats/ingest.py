"""Validation of incoming odometry and frames: every problem becomes a 4xx naming it.

Nothing here touches storage or a mapper: an input that fails is simply never accepted.
Checks run cheapest first (sizes and magic bytes before decoding). Status codes:

* 413 — too large (body, encoded frame, image dimensions, batch length);
* 415 — a frame that is not a JPEG or PNG;
* 422 — malformed or non-finite numbers, numbers given as strings or booleans, readings outside the
  physical bounds of the server settings (speed, turn rate, increment, |t|, a timestamp more than
  ``max_time_jump_s`` ahead of the session's newest input), corrupt images (decoded fully and
  strictly before the acknowledgement), images the model cannot use;
* 409 — timestamps that do not increase (checked against the session in :mod:`server.runtime.sessions`).

The per-reading checks themselves are :class:`hippomap.inputs.Odometry`, :class:`~hippomap.inputs.Frame`
and :func:`hippomap.inputs.decode_jpeg`, so the server rejects exactly what the library rejects.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import ValidationError

from hippomap.errors import InputError
from hippomap.inputs import Frame, Odometry, decode_jpeg

from ..settings import ServerSettings
from .images import check_jpeg_strict, image_dimensions, image_kind, is_truncated
from .schemas import OdometryReading


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

    kind: Literal["odometry", "frame"]
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
    d: dict[str, Any] = (
        {"t": o.t, "increment": list(o.increment)}
        if o.increment is not None
        else {"t": o.t, "v": o.v, "omega": o.omega}
    )
    if o.gt is not None:
        d["gt"] = list(o.gt)
    return json.dumps(d, separators=(",", ":")).encode()


def odometry_from_bytes(data: bytes) -> Odometry:
    d = json.loads(data)
    inc = d.get("increment")
    gt = d.get("gt")
    return Odometry(
        d["t"],
        v=d.get("v"),
        omega=d.get("omega"),
        increment=None if inc is None else tuple(inc),
        gt=None if gt is None else tuple(gt),
    )


def check_bounds(o: Odometry, limits: ServerSettings) -> None:
    """The physical bounds of a reading (server settings): IngestError 422 naming the field."""
    if not abs(o.t) <= limits.max_abs_t:
        raise IngestError(422, f"odometry t={o.t!r} is out of range (|t| <= {limits.max_abs_t:g} s)")
    if o.increment is not None:
        dx, dy, dth = o.increment
        for name, x in (("dx", dx), ("dy", dy)):
            if not abs(x) <= limits.max_increment_m:
                raise IngestError(
                    422,
                    f"odometry increment {name}={x!r} exceeds the limit of "
                    f"{limits.max_increment_m:g} m (max_increment_m)",
                )
        if not abs(dth) <= limits.max_increment_rad:
            raise IngestError(
                422,
                f"odometry increment dtheta={dth!r} exceeds the limit of "
                f"{limits.max_increment_rad:g} rad (max_increment_rad)",
            )
        return
    assert o.v is not None and o.omega is not None
    if not abs(o.v) <= limits.max_speed_mps:
        raise IngestError(422, f"odometry v={o.v!r} exceeds the limit of {limits.max_speed_mps:g} m/s (max_speed_mps)")
    if not abs(o.omega) <= limits.max_turn_rate_rad_s:
        raise IngestError(
            422,
            f"odometry omega={o.omega!r} exceeds the limit of {limits.max_turn_rate_rad_s:g} "
            "rad/s (max_turn_rate_rad_s)",
        )


def check_time_jump(kind: str, t: float, previous: float | None, limits: ServerSettings, where: str = "") -> None:
    """``t`` may lie at most ``max_time_jump_s`` after ``previous`` (the session's clock): 422 otherwise."""
    if previous is not None and t - previous > limits.max_time_jump_s:
        raise IngestError(
            422,
            f"{where}{kind} t={t!r} jumps {t - previous:g} s ahead of {previous!r}, more than "
            f"the limit of {limits.max_time_jump_s:g} s (max_time_jump_s)",
        )


def check_odometry(
    readings: list[OdometryReading], max_batch: int, limits: ServerSettings | None = None
) -> list[Accepted]:
    """Validate a batch: each reading finite and well-formed (and within ``limits``' physical
    bounds if given), timestamps increasing within it."""
    if len(readings) > max_batch:
        raise IngestError(413, f"odometry batch of {len(readings)} readings exceeds the limit of {max_batch}")
    if not readings:
        raise IngestError(422, "odometry batch is empty")
    out: list[Accepted] = []
    prefix = (lambda i: f"readings[{i}]: ") if len(readings) > 1 else (lambda i: "")
    for i, r in enumerate(readings):
        try:
            o = Odometry(r.t, v=r.v, omega=r.omega, increment=r.increment, gt=r.gt)
        except InputError as exc:
            raise IngestError(422, f"{prefix(i)}{exc}") from None
        if limits is not None:
            try:
                check_bounds(o, limits)
            except IngestError as exc:
                raise IngestError(exc.status, f"{prefix(i)}{exc.detail}") from None
        if out and not o.t > out[-1].t:
            raise IngestError(
                409, f"{prefix(i)}odometry timestamp {o.t!r} does not follow the previous reading at {out[-1].t!r}"
            )
        if out and limits is not None:
            check_time_jump("odometry", o.t, out[-1].t, limits, prefix(i))
        out.append(Accepted("odometry", o.t, odometry_bytes(o), o))
    return out


def parse_odometry_message(msg: dict[str, Any], max_batch: int, limits: ServerSettings | None = None) -> list[Accepted]:
    """The odometry of a websocket text message: inline fields or ``readings``."""
    body = {k: v for k, v in msg.items() if k not in ("type", "id")}
    try:
        if "readings" in body:
            if set(body) != {"readings"}:
                raise IngestError(422, f"unexpected fields next to readings: {sorted(set(body) - {'readings'})}")
            if not isinstance(body["readings"], list):
                raise IngestError(422, "readings must be a list")
            if len(body["readings"]) > max_batch:
                raise IngestError(
                    413, f"odometry batch of {len(body['readings'])} readings exceeds the limit of {max_batch}"
                )
            readings = [OdometryReading.model_validate(r) for r in body["readings"]]
        else:
            readings = [OdometryReading.model_validate(body)]
    except ValidationError as exc:
        raise IngestError(422, f"bad odometry message: {pydantic_message(exc)}") from None
    return check_odometry(readings, max_batch, limits)


# -------------------------------------------------------------------- frames
def check_frame(data: bytes, t: Any, settings: ServerSettings) -> Accepted:
    """Validate an encoded frame: timestamp, byte size, type, dimensions, then decode it."""
    try:
        tf = float(t)
    except (TypeError, ValueError):
        raise IngestError(422, f"frame t must be a number, got {t!r}") from None
    if not math.isfinite(tf):
        raise IngestError(422, f"frame t must be finite, got {tf}")
    if not abs(tf) <= settings.max_abs_t:
        raise IngestError(422, f"frame t={tf!r} is out of range (|t| <= {settings.max_abs_t:g} s)")
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
        raise IngestError(
            413,
            f"image of {w}x{h} px exceeds the limit ({settings.max_image_side} px a side, "
            f"{settings.max_image_pixels} px in all)",
        )
    try:
        gray = check_jpeg_strict(data)  # decoded once: the strict check's image is the frame
        if gray is None:
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
