"""SE(2) helpers shared by the pathways: angle wrapping, pose composition, vectorised."""

from __future__ import annotations

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
