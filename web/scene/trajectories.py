"""Raw odometry vs corrected map trajectory, in two colours.

Both come from the Mapper's per-step trajectory rows (time, raw path-integrated pose, the
current node, the robot's offset from it): the raw trajectory is the path-integrated pose, the
corrected one the same step placed on the relaxed map, ``l_node (+) offset`` (as
:meth:`hippomap.mapper.Mapper.corrected_trajectory`). A step is drawn every
``trajectory_spacing_m`` metres of raw path, chosen once and for good, so both polylines are
append-only: the raw one never moves, the corrected one moves when a relaxation moves its nodes.
A run in a saved map is drawn from its placement on, its raw odometry re-anchored on the map
there (:func:`web.scene.placement.drawn_trajectories`).
A long run is drawn coarser: beyond ``trajectory_budget`` steps the spacing doubles. Both are
thin native lines (see :class:`web.scene.chunks.ChunkedSegments`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..settings import ViewerSettings
from ..snapshot import MapSnapshot
from .chunks import ChunkedSegments, ChunkUpdate
from .placement import Placement, drawn_trajectories, placement

ODOMETRY_Z = 0.03
MAP_Z = 0.04


class TrajectorySampler:
    """Selects trajectory rows one per ``spacing`` metres of path, incrementally, within a budget.

    A row is kept when the cumulative raw path length crosses a multiple of ``spacing``; the first
    row is always kept. Keeping is decided once per row, so the selection is append-only — until
    more than ``budget`` rows are kept: then the spacing doubles and the kept rows are thinned to
    those crossing a multiple of the new spacing, exactly the rows sampling from scratch at the new
    spacing would keep (every multiple of 2s is a multiple of s, and between two kept rows no row
    crossed one).
    """

    def __init__(self, spacing: float, budget: int | None = None) -> None:
        self.spacing = float(spacing)
        self.budget = budget
        self._reset()

    def _reset(self) -> None:
        self.rows = np.empty((0, 8))
        self._cums = np.empty(0)
        self._n = 0
        self._seen = 0  # rows consumed
        self._cum = 0.0
        self._last_xy: np.ndarray | None = None

    def add(self, start: int, rows: np.ndarray) -> None:
        """Consume rows ``start : start + len(rows)`` of the trajectory (restart if ``start`` is 0 again)."""
        if start < self._seen:
            if start != 0:
                rows = rows[self._seen - start :]
                start = self._seen
            else:
                self._reset()
        if not len(rows):
            return
        xy = rows[:, 1:3]
        prev = xy[0] if self._last_xy is None else self._last_xy
        d = np.hypot(*(np.diff(np.vstack([prev, xy]), axis=0).T))
        cum = self._cum + np.cumsum(d)
        keep = self._crossings(np.floor(self._cum / self.spacing), cum)
        if self._seen == 0:
            keep[0] = True
        self._append(rows[keep], cum[keep])
        self._cum = float(cum[-1])
        self._last_xy = xy[-1].copy()
        self._seen = start + len(rows)
        while self.budget is not None and self._n > self.budget:
            self._thin()

    def _crossings(self, k0: float, cum: np.ndarray) -> np.ndarray:
        k = np.floor(cum / self.spacing)
        return k > np.concatenate([[k0], k[:-1]])

    def _append(self, rows: np.ndarray, cums: np.ndarray) -> None:
        if len(self.rows) < self._n + len(rows):
            cap = max(2 * len(self.rows), self._n + len(rows), 256)
            grown, gcum = np.empty((cap, 8)), np.empty(cap)
            grown[: self._n], gcum[: self._n] = self.rows[: self._n], self._cums[: self._n]
            self.rows, self._cums = grown, gcum
        self.rows[self._n : self._n + len(rows)] = rows
        self._cums[self._n : self._n + len(rows)] = cums
        self._n += len(rows)

    def _thin(self) -> None:
        self.spacing *= 2
        cums = self._cums[: self._n]
        keep = self._crossings(-1.0, cums)  # the first sample (path 0) is always kept
        rows, cums = self.rows[: self._n][keep], cums[keep]
        self._n = 0
        self._append(rows, cums)

    @property
    def samples(self) -> np.ndarray:
        return self.rows[: self._n]


def polyline_segments(points: np.ndarray, z: float) -> np.ndarray:
    """(K, 2) points -> (K-1, 2, 3) float32 segments joining consecutive points at height z."""
    k = len(points)
    seg = np.empty((max(k - 1, 0), 2, 3), np.float32)
    if k > 1:
        seg[:, 0, :2] = points[:-1]
        seg[:, 1, :2] = points[1:]
        seg[:, :, 2] = z
    return seg


@dataclass(frozen=True)
class TrajectoryUpdate:
    odometry: ChunkUpdate
    corrected: ChunkUpdate


class TrajectoryLayer:
    """Scene nodes ``/trajectories/odometry/<k>`` and ``/trajectories/map/<k>``."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        s = settings
        self.settings = s
        self.sampler = TrajectorySampler(s.trajectory_spacing_m, s.trajectory_budget)
        self.odometry = ChunkedSegments(
            scene,
            "/trajectories/odometry",
            s.chunk_size,
            s.move_tolerance_m,
            s.trajectory_thickness_m,
            style="thin",
            color=s.color_odometry,
            tail_size=s.tail_size,
        )
        self.corrected = ChunkedSegments(
            scene,
            "/trajectories/map",
            s.chunk_size,
            s.move_tolerance_m,
            s.trajectory_thickness_m,
            style="thin",
            color=s.color_corrected,
            tail_size=s.tail_size,
        )

    def update(self, snap: MapSnapshot, placed: Placement | None = None) -> TrajectoryUpdate:
        """Push the new rows of ``snap``, drawn as :func:`web.scene.placement.drawn_trajectories` says for
        the run's placement ``placed`` (None: the one ``snap``'s stats and decisions give)."""
        self.sampler.add(snap.trajectory_start, snap.trajectory)
        if placed is None:
            placed = placement(snap.stats, snap.decisions)
        odometry, on_map = drawn_trajectories(self.sampler.samples, snap.node_poses, placed)
        odo = self.odometry.update(polyline_segments(odometry[:, :2], ODOMETRY_Z))
        cu = self.corrected.update(polyline_segments(on_map[:, :2], MAP_Z))
        return TrajectoryUpdate(odo, cu)

    def set_visible(self, odometry: bool | None = None, corrected: bool | None = None) -> None:
        if odometry is not None:
            self.odometry.visible = odometry
        if corrected is not None:
            self.corrected.visible = corrected
