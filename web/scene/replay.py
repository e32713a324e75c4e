"""The time slider's replay: the map as it was at an earlier time of the run, in one browser.

:func:`replay_at` cuts the current map back to time ``t``: the trajectory samples up to ``t``, the
nodes created by then (node ids are appended in creation order, so they are the nodes up to the
highest id the robot had reached by ``t``, and all of a saved map the run started in), the links
among those nodes, the loop closures accepted among them for hypotheses made by ``t``, and the
ground truth up to ``t``. Nodes keep their current (relaxed) positions and loop closures their
current robust weights (as the live layers, only the ones the map uses are drawn): the replay shows
how the map grew, not how relaxation moved it. The trajectories, the robot and the loop closures follow
the live layers' placement rule for a run in a saved map (:mod:`web.scene.placement`): nothing of the
run's path before its placement, its raw odometry re-anchored there; so the replay at a time
after the placement draws what the live layers drew then (up to relaxation since).

:class:`ReplayLayer` draws that in one browser's client-scoped scene under ``/replay`` (while the
shared live layers are shadowed for that browser), each layer only if the browser shows it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hippomap.cognitive_map import LOOP
from hippomap.robust_kernel import USED_WEIGHT, used_flags

from ..settings import ViewerSettings
from ..snapshot import TRAJ_NODE, MapSnapshot
from .ground_truth import GROUND_TRUTH_Z
from .loops import loop_segments
from .map import LINK_Z, NODE_Z, node_points
from .placement import drawn_trajectories, placement
from .trajectories import MAP_Z, ODOMETRY_Z, polyline_segments


@dataclass(frozen=True)
class ReplayFrame:
    """What the map looked like at time ``t`` (see module doc)."""

    t: float
    t_start: float
    t_end: float
    n_nodes: int
    nodes: np.ndarray  # (n, 3) points
    keyframe: np.ndarray  # (n,) bool
    links: np.ndarray  # (m, 2, 3) segments
    loop_links: np.ndarray
    accepted: np.ndarray  # (k, 2, 3) the loop closures among the nodes that the map uses
    corrected: np.ndarray  # (s, 2, 3) map trajectory up to t
    odometry: np.ndarray
    ground_truth: np.ndarray
    robot: np.ndarray | None  # (3,) the robot's map pose at t (None: not on the map yet)


def time_span(samples: np.ndarray) -> tuple[float, float] | None:
    """First and last time of the trajectory samples, or None."""
    if not len(samples):
        return None
    return float(samples[0, 0]), float(samples[-1, 0])


def replay_at(
    snap: MapSnapshot, samples: np.ndarray, gt_samples: np.ndarray | None, t: float, max_nodes: int = 100000
) -> ReplayFrame:
    """The map cut back to time ``t`` (see module doc). ``samples`` are the sampled trajectory rows
    (t, raw x y theta, node, offset x y theta); ``gt_samples`` the ground truth in the map frame.
    The run's placement is the one ``snap``'s stats and decisions give (:func:`web.scene.placement.placement`)."""
    span = time_span(samples)
    t0, t1 = span if span is not None else (0.0, 0.0)
    rows = samples[samples[:, 0] <= t] if len(samples) else samples
    placed = placement(snap.stats, snap.decisions)
    n_all = len(snap.node_poses)
    reached = int(rows[:, TRAJ_NODE].max() + 1) if len(rows) else 0
    base = int(snap.stats.get("base_nodes") or 0) if placed.based else 0
    k = min(max(reached, base), n_all)
    idx = np.arange(k)
    if k > max_nodes:
        idx = idx[:: -(-k // max_nodes)]
    nodes = node_points(snap.node_poses[idx], NODE_Z)
    keyframe = snap.node_frames[idx] >= 0
    pts = node_points(snap.node_poses[:k], NODE_Z)
    inside = (snap.link_source < k) & (snap.link_target < k) & (snap.link_source >= 0) & (snap.link_target >= 0)
    seg = (
        np.stack([pts[snap.link_source[inside]], pts[snap.link_target[inside]]], axis=1)
        if k
        else np.empty((0, 2, 3), np.float32)
    )
    seg[:, :, 2] = LINK_Z
    loop = snap.link_kind[inside] == LOOP
    faded = snap.link_weight[inside] < USED_WEIGHT
    made = [i for i, d in enumerate(snap.decisions) if float(d.hypothesis.time) <= t]
    decided = [snap.decisions[i] for i in made]
    used = used_flags(decided, snap.loop_weights[made])
    acc = loop_segments(decided, snap.node_poses[:k], "accepted", placed.hides_lost_decisions, used)
    raw, on_map = drawn_trajectories(rows, snap.node_poses, placed)
    corrected = polyline_segments(on_map[:, :2], MAP_Z)
    odometry = polyline_segments(raw[:, :2], ODOMETRY_Z)
    robot = on_map[-1] if len(on_map) else None
    if gt_samples is not None and len(gt_samples):
        g = gt_samples[gt_samples[:, 0] <= t]
        ground_truth = polyline_segments(g[:, 1:3], GROUND_TRUTH_Z)
    else:
        ground_truth = np.empty((0, 2, 3), np.float32)
    return ReplayFrame(
        t=float(t),
        t_start=t0,
        t_end=t1,
        n_nodes=k,
        nodes=nodes,
        keyframe=keyframe,
        links=seg[~loop],
        loop_links=seg[loop & ~faded],
        accepted=acc,
        corrected=corrected,
        odometry=odometry,
        ground_truth=ground_truth,
        robot=robot,
    )


class ReplayLayer:
    """One browser's replay under ``/replay`` (client-scoped scene nodes)."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        self.scene, self.settings = scene, settings
        self._handles: list[Any] = []
        self._root: Any = None
        self.frame: ReplayFrame | None = None

    def clear(self) -> None:
        """Remove the replay (its root frame; viser removes the children with it)."""
        if self._root is not None:
            self._root.remove()
        self._root = None
        self._handles = []
        self.frame = None

    def _lines(self, name: str, seg: np.ndarray, color) -> None:
        if not len(seg):
            return
        flat = np.ascontiguousarray(np.asarray(seg, np.float32).reshape(-1, 3))
        i = np.arange(len(seg), dtype=np.uint32)
        faces = np.column_stack([2 * i, 2 * i + 1, 2 * i + 1])
        self._handles.append(
            self.scene.add_mesh_simple(
                name,
                flat,
                faces,
                color=tuple(int(c) for c in color),
                wireframe=True,
                cast_shadow=False,
                receive_shadow=False,
            )
        )

    def draw(self, frame: ReplayFrame, shown: dict[str, bool]) -> None:
        """Replace the replay by ``frame``, drawing the layers ``shown`` maps to True."""
        s = self.settings
        old, self._handles = self._handles, []
        on = lambda key: shown.get(key, True)  # noqa: E731
        if self._root is None:
            self._root = self.scene.add_frame("/replay", show_axes=False)
        if on("nodes") and len(frame.nodes):
            colors = np.where(
                frame.keyframe[:, None], np.array(s.color_keyframe_node, np.uint8), np.array(s.color_node, np.uint8)
            )
            self._handles.append(
                self.scene.add_point_cloud(
                    "/replay/nodes",
                    frame.nodes,
                    np.ascontiguousarray(colors.astype(np.uint8)),
                    point_size=s.node_size_m,
                    point_shape="circle",
                    precision="float32",
                    point_shading="flat",
                )
            )
        if on("links"):
            self._lines("/replay/links", frame.links, s.color_link)
            self._lines("/replay/loop_links", frame.loop_links, s.color_loop_link)
        if on("accepted"):
            self._lines("/replay/accepted", frame.accepted, s.color_loop_accepted)
        if on("odometry"):
            self._lines("/replay/odometry", frame.odometry, s.color_odometry)
        if on("corrected"):
            self._lines("/replay/map", frame.corrected, s.color_corrected)
        if on("ground_truth"):
            self._lines("/replay/ground_truth", frame.ground_truth, s.color_ground_truth)
        if on("robot") and frame.robot is not None:
            r = frame.robot
            self._handles.append(
                self.scene.add_point_cloud(
                    "/replay/robot",
                    np.array([[r[0], r[1], 0.1]], np.float32),
                    np.array([s.color_robot], np.uint8),
                    point_size=1.5 * s.node_size_m,
                    point_shape="circle",
                    precision="float32",
                    point_shading="flat",
                )
            )
        for h in old:  # after the new nodes are queued: replaced names are not removed twice
            if h.name not in {x.name for x in self._handles}:
                h.remove()
        self.frame = frame
