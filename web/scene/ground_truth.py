"""Ground truth, when the session has it: the true path drawn in the map frame.

A simulated or recorded run may send a ground-truth pose with its odometry (see
:meth:`web.source.SessionSource` ``ground_truth``). Ground truth lives in its own world frame; it is
carried into the map frame by the rigid transform that puts its first pose on the robot's first
odometric pose (the pose the map starts from, at the same time stamp) — the ``--align_origin``
convention of trajectory evaluation tools. A run in a saved map starts at an unknown pose of the
base's frame: its ground truth is put on the first trajectory row that is on the map, at that
row's map pose, once the run is placed (:mod:`web.scene.placement`). Nothing else is fitted, so the
gap between the ground truth and the map trajectory is the map's real error (drift before loop
closures, residual after).

Sampled like the other trajectories (one pose per ``trajectory_spacing_m`` of path, coarser past
``trajectory_budget``) and drawn as a thin append-only polyline.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hippomap.geometry import between, compose

from ..settings import ViewerSettings
from .chunks import ChunkedSegments, ChunkUpdate
from .trajectories import TrajectorySampler, polyline_segments

GROUND_TRUTH_Z = 0.035


def origin_alignment(gt: np.ndarray, first_row: np.ndarray) -> np.ndarray | None:
    """The pose ``A`` with ``A (+) gt_0 = raw_0``: ``gt`` rows (t, x, y, theta), ``first_row`` the first
    trajectory row (t, raw x, y, theta, ...). The ground-truth pose used is the one nearest in time to
    the row; None when none is within 0.5 s of it (the two streams do not overlap yet)."""
    if not len(gt):
        return None
    t0 = float(first_row[0])
    k = int(np.argmin(np.abs(gt[:, 0] - t0)))
    if abs(float(gt[k, 0]) - t0) > 0.5:
        return None
    raw0 = np.asarray(first_row[1:4], float)
    g0 = gt[k, 1:4]
    # A = raw0 (+) g0^-1, so A (+) g = raw0 (+) between(g0, g)
    return compose(raw0, between(g0, np.zeros(3)))


class GroundTruthLayer:
    """Scene node ``/ground_truth/<k>``: the ground truth as a thin polyline in the map frame."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        s = settings
        self.settings = s
        self.sampler = TrajectorySampler(s.trajectory_spacing_m, s.trajectory_budget)
        self.segments = ChunkedSegments(
            scene,
            "/ground_truth",
            s.chunk_size,
            s.move_tolerance_m,
            s.trajectory_thickness_m,
            style="thin",
            color=s.color_ground_truth,
            tail_size=s.tail_size,
        )
        self.alignment: np.ndarray | None = None
        self._pending = np.empty((0, 4))
        self._seen = 0

    @property
    def present(self) -> bool:
        """Whether any ground truth has been drawn."""
        return self.alignment is not None and len(self.sampler.samples) > 0

    @property
    def seen(self) -> int:
        """Ground-truth rows consumed so far (the next call reads from here)."""
        return self._seen

    def update(self, rows: np.ndarray | None, first_trajectory_row: np.ndarray | None) -> ChunkUpdate | None:
        """Consume new ground-truth rows (t, x, y, theta), ``rows`` continuing from :attr:`seen`;
        ``first_trajectory_row`` is the map's first trajectory row (None if there is none yet)."""
        if rows is not None and len(rows):
            rows = np.asarray(rows, float).reshape(-1, 4)
            self._pending = np.vstack([self._pending, rows]) if len(self._pending) else rows
            self._seen += len(rows)
        if self.alignment is None:
            if first_trajectory_row is None or not len(self._pending):
                return None
            self.alignment = origin_alignment(self._pending, first_trajectory_row)
            if self.alignment is None:
                return None
        if not len(self._pending):
            return None
        mapped = np.empty((len(self._pending), 8))
        mapped[:, 0] = self._pending[:, 0]
        mapped[:, 1:4] = compose(self.alignment, self._pending[:, 1:4])
        mapped[:, 4:] = 0.0
        self.sampler.add(self._seen - len(self._pending), mapped)
        self._pending = np.empty((0, 4))
        return self.segments.update(polyline_segments(self.sampler.samples[:, 1:3], GROUND_TRUTH_Z))

    @property
    def samples(self) -> np.ndarray:
        """The sampled ground truth in the map frame, rows (t, x, y, theta, 0, 0, 0, 0)."""
        return self.sampler.samples
