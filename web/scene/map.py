"""The cognitive map in 3D: nodes as points, links as line segments, on the floor (z up).

Nodes are drawn at their map poses ``l_i`` (after relaxation); nodes that hold a key frame
(``V_i >= 0``) are coloured differently. Links are drawn thin (native GL lines, cheap for 50k
links), loop links in their own colour (:data:`hippomap.cognitive_map.LINK_KINDS`), and only those the
map uses: a loop link the robust kernel has faded (weight below ``USED_WEIGHT``) shapes no part of the
map, so it is not drawn as one (:mod:`web.scene.loops` shows its closure on demand). All layers
are chunked (:mod:`web.scene.chunks`): appended nodes and links cost only their own chunk; a relaxation
resends just the chunks it moved.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hippomap.cognitive_map import LOOP
from hippomap.robust_kernel import USED_WEIGHT

from ..settings import ViewerSettings
from ..snapshot import MapSnapshot
from .chunks import ChunkedPoints, ChunkedSegments, ChunkUpdate

NODE_Z = 0.02
LINK_Z = 0.01


def node_points(poses: np.ndarray, z: float = NODE_Z) -> np.ndarray:
    """(N, 3) map poses -> (N, 3) float32 points on the floor at height ``z``."""
    out = np.empty((len(poses), 3), np.float32)
    out[:, :2] = poses[:, :2]
    out[:, 2] = z
    return out


@dataclass(frozen=True)
class MapUpdate:
    nodes: ChunkUpdate
    links: ChunkUpdate
    loop_links: ChunkUpdate


class MapGraphLayer:
    """Scene nodes ``/map/nodes/<k>``, ``/map/links/<k>`` (odometry and prune links, thin grey) and
    ``/map/loop_links/<k>`` (the loop links the map uses, thin green)."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        s = settings
        self.settings = s
        self.nodes = ChunkedPoints(
            scene, "/map/nodes", s.chunk_size, s.move_tolerance_m, s.node_size_m, tail_size=s.tail_size
        )
        self.links = ChunkedSegments(
            scene,
            "/map/links",
            s.chunk_size,
            s.move_tolerance_m,
            s.link_thickness_m,
            style="thin",
            color=s.color_link,
            tail_size=s.tail_size,
        )
        self.loop_links = ChunkedSegments(
            scene,
            "/map/loop_links",
            s.chunk_size,
            s.move_tolerance_m,
            s.link_thickness_m,
            style="thin",
            color=s.color_loop_link,
            tail_size=s.tail_size,
        )

    def update(self, snap: MapSnapshot) -> MapUpdate:
        s = self.settings
        pts = node_points(snap.node_poses)
        colors = np.where(
            (snap.node_frames >= 0)[:, None],
            np.array(s.color_keyframe_node, np.uint8),
            np.array(s.color_node, np.uint8),
        ).astype(np.uint8)
        nodes = self.nodes.update(pts, colors)
        n = len(pts)
        if n:
            src = np.clip(snap.link_source, 0, n - 1)
            dst = np.clip(snap.link_target, 0, n - 1)
            seg = np.stack([pts[src], pts[dst]], axis=1)
            seg[:, :, 2] = LINK_Z
        else:
            seg = np.empty((0, 2, 3), np.float32)
        loop = snap.link_kind == LOOP
        links = self.links.update(seg[~loop])
        loops = self.loop_links.update(seg[loop & (snap.link_weight >= USED_WEIGHT)])
        return MapUpdate(nodes, links, loops)

    def set_visible(self, nodes: bool | None = None, links: bool | None = None) -> None:
        if nodes is not None:
            self.nodes.visible = nodes
        if links is not None:
            self.links.visible = links
            self.loop_links.visible = links
