"""Sensor inputs of a mapping session: odometry and camera frames, validated.

Odometry comes either as velocities ``(v, omega)`` held over ``dt`` (m/s, rad/s) or as a
relative pose increment ``(dx, dy, dtheta)`` in the frame of the previous pose (g2o
convention). Both are checked here, once, so every consumer (offline runs, the server)
rejects the same bad input with the same message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError, finite


@dataclass(frozen=True)
class Odometry:
    """One odometry reading at time ``t``: velocities (``v``, ``omega``) or an increment.

    ``gt`` optionally carries the true pose (x, y, theta) at ``t`` in the ground truth's own frame
    (simulated runs, data sets with ground truth): stored with the input and drawn by the viewer,
    never used by the mapper."""

    t: float
    v: float | None = None
    omega: float | None = None
    increment: tuple[float, float, float] | None = None
    gt: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", finite("odometry t", self.t))
        if self.increment is not None:
            if self.v is not None or self.omega is not None:
                raise InputError("odometry carries either (v, omega) or an increment, not both")
            if len(self.increment) != 3:
                raise InputError(f"odometry increment must be (dx, dy, dtheta), got {self.increment!r}")
            inc = tuple(finite(f"odometry {k}", x) for k, x in zip(("dx", "dy", "dtheta"), self.increment))
            object.__setattr__(self, "increment", inc)
        else:
            if self.v is None or self.omega is None:
                raise InputError("odometry needs v and omega (or an increment)")
            object.__setattr__(self, "v", finite("odometry v", self.v))
            object.__setattr__(self, "omega", finite("odometry omega", self.omega))
        if self.gt is not None:
            if len(self.gt) != 3:
                raise InputError(f"odometry gt must be a pose (x, y, theta), got {self.gt!r}")
            gt = tuple(finite(f"odometry gt {k}", x) for k, x in zip(("x", "y", "theta"), self.gt))
            object.__setattr__(self, "gt", gt)

    def as_increment(self, dt: float) -> tuple[float, float, float]:
        """The relative pose increment over ``dt``: the exact arc driven at constant
        ``(v, omega)`` (chord of length 2 v/omega sin(omega dt / 2) at half the turn).
        [ORS] rotates first and then moves the whole distance, which puts every turn
        half a step early; the arc is exact for a robot holding its command (MODEL.md)."""
        if self.increment is not None:
            return self.increment
        assert self.v is not None and self.omega is not None  # __post_init__: an increment or both
        th = self.omega * dt
        d = self.v * dt
        half = th / 2
        chord = d * (math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6)
        return (chord * math.cos(half), chord * math.sin(half), th)


@dataclass(frozen=True)
class Frame:
    """A camera frame at time ``t``: a decoded uint8 image (gray or BGR)."""

    t: float
    image: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", finite("frame t", self.t))
        img = self.image
        if not isinstance(img, np.ndarray):
            raise InputError(f"frame image must be a numpy array, got {type(img).__name__}")
        if img.dtype != np.uint8:
            raise InputError(f"frame image must be uint8, got {img.dtype}")
        if img.ndim not in (2, 3) or img.size == 0 or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
            raise InputError(f"frame image must be HxW or HxWx{{1,3,4}} and non-empty, got shape {img.shape}")

    def gray(self) -> np.ndarray:
        import cv2

        img = self.image
        if img.ndim == 2:
            return img
        if img.shape[2] == 1:
            return img[:, :, 0]
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)


def decode_jpeg(data: bytes) -> np.ndarray:
    """Decode JPEG (or PNG) bytes to a grayscale uint8 image, with a clear error."""
    import cv2

    if not data:
        raise InputError("empty image payload")
    if not (data[:3] == b"\xff\xd8\xff" or data[:8] == b"\x89PNG\r\n\x1a\n"):
        raise InputError("image payload is not a JPEG or PNG (bad magic bytes)")
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise InputError("corrupt image payload: the decoder could not read it")
    return img


def follows(last_t: float | None, t: float) -> bool:
    """The time-order rule: within each input stream (odometry, frames) timestamps strictly
    increase; the streams may interleave. ``last_t`` is the previous input of the same stream."""
    return last_t is None or t > last_t


class TimeOrder:
    """Checks that timestamps strictly increase within one input stream (:func:`follows`)."""

    def __init__(self, name: str, last: float | None = None) -> None:
        self.name = name
        self.last = last

    def check(self, t: float) -> None:
        if not follows(self.last, t):
            raise InputError(f"{self.name} timestamps must increase: {t!r} follows {self.last!r}")
        self.last = t
