"""Exceptions raised by hippomap. Every message names the offending value or line."""


class HippomapError(Exception):
    """Base class of hippomap's own errors."""


class InputError(HippomapError, ValueError):
    """Bad input: NaN/infinite odometry, non-increasing timestamps, malformed files, bad images."""


def finite(name: str, value: object) -> float:
    """``value`` as a float, or an InputError naming ``name`` when it is not a finite number."""
    import math

    try:
        f = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(f):
        raise InputError(f"{name} must be finite, got {f}")
    return f
