"""A consistent copy of what the viewer draws, taken from a Mapper under the session's lock.

:func:`take_snapshot` is the only code that touches a live :class:`~hippomap.mapper.Mapper`. It
copies arrays and nothing else (a few hundred microseconds for a 50k-node map), so the worker
thread is held as briefly as possible; the viewer then builds geometry and images from the copy
in its own thread.

The append-only trajectory is copied incrementally from a :class:`Cursor`; node poses, links and
loop decisions are copied whole, because a relaxation moves every pose, a batch prune renumbers
nodes, and a pending loop decision can change status. Of the recognitions only the newest is
taken (by reference: the Mapper never mutates a stored recognition); older ones are looked up
when the panel asks for one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hippomap.cognitive_map import LoopDecision
from hippomap.config import SpatialConfig
from hippomap.grid_cells import RateTables
from hippomap.mapper import Mapper
from hippomap.place_cells import PlaceCode

#: columns of a trajectory row: time, raw odometric pose, current node, robot offset from it
TRAJ_T, TRAJ_RAW, TRAJ_NODE, TRAJ_OFFSET = 0, slice(1, 4), 4, slice(5, 8)


@dataclass(frozen=True)
class Cursor:
    """How much of the append-only histories a viewer already holds."""

    trajectory: int = 0


@dataclass(frozen=True)
class PlaceFieldView:
    """The place code of the current step with what is needed to draw its field.

    ``code`` is the frozen :class:`PlaceCode` (its ``field`` the sparse single field of Eq. 10);
    ``tables`` the grid cells' read-only rate tables (shared, never mutated) and ``spatial`` their
    config, so the viewer can recompute the window comparators of Eq. 9 over the coding area.
    ``odometric_pose`` and ``map_pose`` are the robot's path-integrated and map poses now: the
    place code lives in the odometric frame, the heatmap is drawn in the map frame.
    """

    code: PlaceCode
    tables: RateTables
    spatial: SpatialConfig
    odometric_pose: np.ndarray
    map_pose: np.ndarray


@dataclass(frozen=True)
class MapSnapshot:
    """Everything one viewer update needs, copied at one instant."""

    node_poses: np.ndarray  # (N, 3) map poses l_i (after relaxation)
    node_frames: np.ndarray  # (N,) key frame id V_i, -1 = none
    link_source: np.ndarray  # (M,) int64
    link_target: np.ndarray  # (M,) int64
    link_kind: np.ndarray  # (M,) int8 codes of hippomap.cognitive_map.LINK_KINDS
    trajectory_start: int  # index of the first row of ``trajectory``
    trajectory: np.ndarray  # (K, 8) new rows: t, raw x y theta, node, offset x y theta
    trajectory_total: int
    current_node: int
    robot_pose: np.ndarray  # (3,) the robot in the map: l_current (+) offset
    decisions: tuple[LoopDecision, ...]
    recognition_count: int
    last_recognition: dict[str, Any] | None  # the newest recognition (Mapper.recognitions[-1])
    place_field: PlaceFieldView | None
    stats: dict[str, Any]
    taken_at: float = field(default_factory=time.monotonic)

    @property
    def cursor(self) -> Cursor:
        return Cursor(self.trajectory_total)

    def same_scene_as(self, prev: "MapSnapshot | None") -> bool:
        """True if nothing the 3D scene draws changed since ``prev`` (the snapshot before this one):
        no new trajectory rows or recognitions, the same decisions, place code and robot pose, and
        node poses, key frames and links identical. Lets an idle session cost ~nothing."""
        if prev is None or len(self.trajectory) or self.recognition_count != prev.recognition_count:
            return False
        if len(self.decisions) != len(prev.decisions):
            return False
        if any(a is not b for a, b in zip(self.decisions, prev.decisions)):
            return False
        code = None if self.place_field is None else self.place_field.code
        prev_code = None if prev.place_field is None else prev.place_field.code
        return (code is prev_code and np.array_equal(self.robot_pose, prev.robot_pose)
                and np.array_equal(self.node_poses, prev.node_poses)
                and np.array_equal(self.node_frames, prev.node_frames)
                and np.array_equal(self.link_source, prev.link_source)
                and np.array_equal(self.link_target, prev.link_target))


def _trajectory_rows(mapper: Mapper, start: int) -> np.ndarray:
    """Trajectory rows ``start:`` as a copy.

    ``Mapper`` exposes the whole trajectory (``odometry_trajectory()``, ``corrected_trajectory()``)
    but copying and re-composing every step five times a second would hold the worker; the rows
    are append-only, so only the new ones are copied. Uses ``Mapper.trajectory_rows`` when the
    Mapper offers it, else its private row store.
    """
    rows = getattr(mapper, "trajectory_rows", None)
    if rows is not None:
        return np.array(rows(start), dtype=float, copy=True)
    return np.array(mapper._traj.view[start:], dtype=float, copy=True)  # noqa: SLF001 (see docstring)


def take_snapshot(mapper: Mapper, cursor: Cursor = Cursor()) -> MapSnapshot:
    """Copy what the viewer needs from ``mapper`` (call under the session lock)."""
    cm = mapper.cmap
    links = cm.links
    start = cursor.trajectory
    rows = _trajectory_rows(mapper, start)
    total = start + len(rows)
    if total < start or rows.shape[1:] != (8,):  # history shrank (should not happen): restart
        rows = _trajectory_rows(mapper, 0)
        start, total = 0, len(rows)
    recs = mapper.recognitions
    place = None
    code = mapper.place_field
    if code is not None and code.field is not None:
        place = PlaceFieldView(code=code, tables=mapper.pathway.place_cells.tables,
                               spatial=mapper.pathway.cfg,
                               odometric_pose=np.asarray(mapper.pathway.pose, float),
                               map_pose=np.asarray(cm.robot_pose, float))
    return MapSnapshot(
        node_poses=np.array(cm.poses, dtype=float, copy=True),
        node_frames=np.array(cm.frames, dtype=np.int64, copy=True),
        link_source=np.array(links["source"], dtype=np.int64, copy=True),
        link_target=np.array(links["target"], dtype=np.int64, copy=True),
        link_kind=np.array(links["kind_code"], dtype=np.int8, copy=True),
        trajectory_start=start,
        trajectory=rows,
        trajectory_total=total,
        current_node=int(cm.current),
        robot_pose=np.asarray(cm.robot_pose, float),
        decisions=tuple(cm.loop_decisions),
        recognition_count=len(recs),
        last_recognition=recs[-1] if recs else None,
        place_field=place,
        stats=dict(mapper.stats()),
    )
