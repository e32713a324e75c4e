"""Fitting the camera to the map: a near top-down view in which the map's bounding box fills the canvas.

The viewer's camera looks at the floor (z up) from above, tilted by ``tilt`` (a little, so orbiting
stays well-defined) and with +x to the right of the screen. The distance is the smallest at which
the box, enlarged by ``margin``, fits both the vertical field of view and the horizontal one
(``aspect`` = width / height of the canvas). Parts of the canvas are covered by floating panels
(the controls on the right, the legend on the left): ``covered`` and ``covered_left`` are those
fractions of the width; the box is fitted into the rest and centred in it.
"""

from __future__ import annotations

import math

import numpy as np


def map_bounds(*point_sets: np.ndarray | None, minimum: float = 2.0) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) corners of the (x, y) bounding box of the given (N, >=2) arrays, at least ``minimum``
    metres on each side (centred), or None if all are empty."""
    sets = [np.asarray(p, float)[:, :2] for p in point_sets if p is not None and len(p)]
    if not sets:
        return None
    xy = np.vstack(sets)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return None
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    c, half = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.5 * minimum)
    return c - half, c + half


def project(points: np.ndarray, position: np.ndarray, look_at: np.ndarray, fov: float, aspect: float) -> np.ndarray:
    """Pinhole projection (+z up) of world points (N, 3) to normalised screen coordinates (N, 2):
    x in [-1, 1] left to right, y in [-1, 1] bottom to top, for points in view."""
    f = np.asarray(look_at, float) - np.asarray(position, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = np.asarray(points, float) - position
    zc = d @ f
    t = math.tan(fov / 2)
    return np.column_stack([(d @ r) / (zc * t * aspect), (d @ u) / (zc * t)])


def fit_camera(
    lo: np.ndarray,
    hi: np.ndarray,
    fov: float,
    aspect: float,
    margin: float = 1.15,
    covered: float = 0.0,
    tilt: float = math.radians(12.0),
    covered_left: float = 0.0,
    points: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera ``(position, look_at)`` that shows the box ``lo``-``hi`` (see module doc).

    ``fov`` is the vertical field of view (radians), ``aspect`` width / height. The tilt makes the
    near edge of the box look wider than the far one, so the distance and centring are refined on
    the projected corners (a few fixed-point steps from the flat-floor estimate). With ``points``
    ((N, >=2) floor points inside the box, e.g. the nodes), those are fitted instead of the box's
    corners (a round map then fills the view rather than its bounding box); at most 4096 are used."""
    lo, hi = np.asarray(lo, float)[:2], np.asarray(hi, float)[:2]
    _check_parameters(fov, aspect, covered, covered_left, margin, lo, hi)
    centre, half, corners = _fit_targets(lo, hi, margin, points)
    t = math.tan(fov / 2)
    x_lo, x_hi = -1.0 + 2.0 * covered_left, 1.0 - 2.0 * covered
    view = np.array([0.0, -math.sin(tilt), math.cos(tilt)])
    dist = max(2 * half[1] * math.cos(tilt) / (2 * t), 2 * half[0] / (2 * t * aspect * (x_hi - x_lo) / 2))
    look = np.array([centre[0], centre[1], 0.0])
    for _ in range(60):
        uv = project(corners, look + dist * view, look, fov, aspect)
        cu, cv = 0.5 * (uv[:, 0].max() + uv[:, 0].min()), 0.5 * (uv[:, 1].max() + uv[:, 1].min())
        need = max((uv[:, 0].max() - uv[:, 0].min()) / (x_hi - x_lo), (uv[:, 1].max() - uv[:, 1].min()) / 2.0)
        # move the look-at point so the projected box centres in the free area, then rescale the distance
        look[0] += (cu - 0.5 * (x_lo + x_hi)) * t * aspect * dist
        look[1] += cv * t * dist / math.cos(tilt)
        dist *= need
        if abs(need - 1.0) < 1e-6 and abs(cu - 0.5 * (x_lo + x_hi)) < 1e-6 and abs(cv) < 1e-6:
            break
    uv = project(corners, look + dist * view, look, fov, aspect)
    over = max(
        uv[:, 0].max() / x_hi if x_hi > 0 else 1.0,
        uv[:, 0].min() / x_lo if x_lo < 0 else 1.0,
        np.abs(uv[:, 1]).max(),
        1.0,
    )
    dist *= over  # never cut the box off, even if the refinement stopped short
    return look + dist * view, look


def _check_parameters(
    fov: float, aspect: float, covered: float, covered_left: float, margin: float, lo: np.ndarray, hi: np.ndarray
) -> None:
    """:func:`fit_camera`'s parameters in range (a :class:`ValueError` naming them all otherwise): a field of view
    in (0, pi), a positive aspect, at most 90 % of the width covered, a margin of at least 1, ``lo <= hi``."""
    if (
        not (0 < fov < math.pi)
        or not aspect > 0
        or not (0 <= covered)
        or not (0 <= covered_left)
        or covered + covered_left >= 0.9
        or margin < 1.0
        or not np.all(hi >= lo)
    ):
        raise ValueError(
            f"bad camera parameters fov={fov}, aspect={aspect}, covered={covered}, "
            f"covered_left={covered_left}, margin={margin}, box={lo}-{hi}"
        )


def _fit_targets(
    lo: np.ndarray, hi: np.ndarray, margin: float, points: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The box's centre and half size (with the margin), and the floor points to fit into the view: the box's
    corners, or the finite ``points`` (at most 4096 of them) spread by the margin about the centre."""
    centre = 0.5 * (lo + hi)
    half = 0.5 * np.maximum(hi - lo, 1e-6) * margin
    corners = np.array([[centre[0] + sx * half[0], centre[1] + sy * half[1], 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    if points is not None and len(points):
        pts = np.asarray(points, float)[:, :2]
        pts = pts[np.all(np.isfinite(pts), axis=1)][:: max(1, -(-len(pts) // 4096))]
        if len(pts):
            corners = np.column_stack([centre + (pts - centre) * margin, np.zeros(len(pts))])
    return centre, half, corners
