"""A consistent copy of what the viewer draws, taken from a session's mapper between two inputs.

:func:`take_snapshot` asks the session for one typed read, :class:`~hippomap.mapper_queries.ViewerState`,
which copies arrays and nothing else (a few hundred microseconds for a 50k-node map), so the worker
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
from hippomap.grid_cells import GridCells, RateTables
from hippomap.mapper_queries import MapView, ViewerState
from hippomap.spatial_pathway import PlaceCode

from .source import SessionSource

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
    link_weight: np.ndarray  # (M,) robust weight: 1 for odometric links, the kernel's for loop links
    trajectory_start: int  # index of the first row of ``trajectory``
    trajectory: np.ndarray  # (K, 8) new rows: t, raw x y theta, node, offset x y theta
    trajectory_total: int
    current_node: int
    robot_pose: np.ndarray  # (3,) the robot in the map: l_current (+) offset
    decisions: tuple[LoopDecision, ...]
    loop_weights: np.ndarray  # (len(decisions),) robust weight of each decision's link, NaN without one
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
        node poses, key frames, links and robust weights identical. Lets an idle session cost ~nothing."""
        if prev is None or len(self.trajectory) or self.recognition_count != prev.recognition_count:
            return False
        if len(self.decisions) != len(prev.decisions):
            return False
        if any(a is not b for a, b in zip(self.decisions, prev.decisions)):
            return False
        code = None if self.place_field is None else self.place_field.code
        prev_code = None if prev.place_field is None else prev.place_field.code
        return (
            code is prev_code
            and np.array_equal(self.robot_pose, prev.robot_pose)
            and np.array_equal(self.node_poses, prev.node_poses)
            and np.array_equal(self.node_frames, prev.node_frames)
            and np.array_equal(self.link_source, prev.link_source)
            and np.array_equal(self.link_target, prev.link_target)
            and np.array_equal(self.link_weight, prev.link_weight)
            and np.array_equal(self.loop_weights, prev.loop_weights, equal_nan=True)
        )


def from_view(view: MapView) -> MapSnapshot:
    """The viewer's snapshot of a :class:`~hippomap.mapper_queries.MapView` (the ``ViewerState``
    answer). The grid cells' tables come from the model's shared cache for the view's spatial
    config, not across the query: they are the same for every step, and large."""
    place = None
    if view.place_code is not None:
        place = PlaceFieldView(
            code=view.place_code,
            tables=GridCells(view.spatial).tables,
            spatial=view.spatial,
            odometric_pose=view.odometric_pose,
            map_pose=view.robot_pose,
        )
    return MapSnapshot(
        node_poses=view.node_poses,
        node_frames=view.node_frames,
        link_source=view.link_source,
        link_target=view.link_target,
        link_kind=view.link_kind,
        link_weight=view.link_weight,
        trajectory_start=view.trajectory_start,
        trajectory=view.trajectory,
        trajectory_total=view.trajectory_start + len(view.trajectory),
        current_node=view.current_node,
        robot_pose=view.robot_pose,
        decisions=view.decisions,
        loop_weights=view.loop_weights,
        recognition_count=view.recognition_count,
        last_recognition=view.last_recognition,
        place_field=place,
        stats=view.stats,
    )


def take_snapshot(source: SessionSource, cursor: Cursor = Cursor()) -> MapSnapshot | None:
    """Copy what the viewer needs from ``source``'s mapper (one ``ViewerState`` query, answered
    between two inputs); None while the session has no mapper."""
    view = source.read(ViewerState(cursor.trajectory))
    return None if view is None else from_view(view)
