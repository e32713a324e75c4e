"""SE(2) helpers shared by the pathways: angle wrapping, pose composition, vectorised; and the same
for a single pose in plain floats (:func:`se2_compose`, :func:`se2_inverse`, :func:`se2_between`),
cheaper than numpy where the map handles one pose at a time."""

from __future__ import annotations

import math

import numpy as np


def wrap_angle(a):
    """Wrap angle(s) to [-pi, pi). Works on scalars and arrays."""
    w = (np.asarray(a, dtype=float) + np.pi) % (2 * np.pi) - np.pi
    return float(w) if w.ndim == 0 else w


def compose(a, b):
    """Pose a (+) b: b given in the frame of a. Arrays of shape (..., 3) -> (..., 3)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def between(a, b):
    """Pose of b in the frame of a: a^-1 (+) b. Arrays of shape (..., 3)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def integrate(increments, start=(0.0, 0.0, 0.0)):
    """Chain relative increments (N, 3) from ``start``: returns (N + 1, 3) absolute poses.

    Sequential by nature (each step rotates by the heading so far), but vectorised:
    headings are a cumulative sum, then translations are rotated and summed at once.
    """
    inc = np.asarray(increments, dtype=float).reshape(-1, 3)
    start = np.asarray(start, dtype=float)
    th = start[2] + np.concatenate([[0.0], np.cumsum(inc[:, 2])])
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    dx = c * inc[:, 0] - s * inc[:, 1]
    dy = s * inc[:, 0] + c * inc[:, 1]
    out = np.empty((len(inc) + 1, 3))
    out[:, 0] = start[0] + np.concatenate([[0.0], np.cumsum(dx)])
    out[:, 1] = start[1] + np.concatenate([[0.0], np.cumsum(dy)])
    out[:, 2] = wrap_angle(th)
    return out


def path_lengths(xy):
    """The path length (m) at each of the positions ``xy`` (N, 2), from 0."""
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))


def _wrap(a: float) -> float:
    """One angle wrapped to [-pi, pi), plain float."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def se2_compose(a, b) -> tuple[float, float, float]:
    """a (+) b for single poses (plain floats: cheaper than numpy for one pose)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], _wrap(a[2] + b[2]))


def se2_inverse(a) -> tuple[float, float, float]:
    """The inverse of a single pose: a (+) se2_inverse(a) is the identity."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], _wrap(-a[2]))


def se2_between(a, b) -> tuple[float, float, float]:
    """Pose of b in the frame of a."""
    return se2_compose(se2_inverse(a), b)
