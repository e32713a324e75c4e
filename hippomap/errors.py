"""Exceptions raised by hippomap, and the checks of input values that raise them. Every message names the
offending value or line."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


class HippomapError(Exception):
    """Base class of hippomap's own errors."""


class InputError(HippomapError, ValueError):
    """Bad input: NaN/infinite odometry, non-increasing timestamps, malformed files, bad images."""


def finite(name: str, value: object) -> float:
    """``value`` as a float, or an InputError naming ``name`` when it is not a finite number."""
    try:
        f = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(f):
        raise InputError(f"{name} must be finite, got {f}")
    return f


def vec3(value: Any, name: str) -> tuple[float, float, float]:
    """A finite (x, y, θ) triple from a sequence (or an object with x, y, theta), else InputError. A tuple
    of three finite Python floats (the mapper's, every step) is returned as it is: the floats the array
    route gives, without its round trip (7 us, more than the rest of a step's map bookkeeping)."""
    if type(value) is tuple and len(value) == 3 and all(type(v) is float and math.isfinite(v) for v in value):
        return value
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


def node_id(value: Any, name: str) -> int:
    """``value`` as a node id (an integer, not a bool), else InputError naming ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an integer node id, got {value!r}")
    return int(value)
