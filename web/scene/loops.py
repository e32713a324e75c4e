"""Loop closures in 3D: the ones the map uses highlighted, faded and rejected ones on demand, the
selected one marked.

A loop decision joins the node that was current when the hypothesis was made
(``LoopDecision.from_node``) and the recognised node (``hypothesis.node``); it is drawn between
their map poses, above the map so it stays visible. Both are thin native lines (one pixel, in the
layer's colour) so that ten laps of closures do not bury the map, and a used closure's two
ends are marked by dots no larger than a node (a closed loop pulls its nodes together, so its
segment may be very short). An accepted closure is *used* while its link's robust weight is at least
``USED_WEIGHT`` and *faded* below it (:func:`hippomap.robust_kernel.is_used`): the kernel revises the
weights as the map converges, so a closure can move between the two layers. Used closures are shown;
faded and rejected ones are hidden by default in each browser (:mod:`web.panels.layers`); pending ones
are not drawn. The loop chosen in the panel's list gets a thick marker and labels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hippomap.cognitive_map import LoopDecision
from hippomap.robust_kernel import is_used, used_flags

from ..settings import RGB, ViewerSettings
from ..snapshot import MapSnapshot
from .chunks import ChunkedPoints, ChunkedSegments, ChunkUpdate
from .placement import decided_while_lost

LOOP_Z = 0.08


def loop_segments(
    decisions: tuple[LoopDecision, ...] | list[LoopDecision],
    poses: np.ndarray,
    status: str,
    skip_lost: bool = False,
    keep: list[bool] | None = None,
) -> np.ndarray:
    """(K, 2, 3) segments of the decisions with ``status`` (and, with ``keep``, only those whose entry
    is true), in decision order; ``skip_lost`` leaves out the accepted ones made while the robot had
    no pose on the map (a localising run in a saved map: their ``from_node`` is not a node the robot
    was near, see :mod:`web.scene.placement`)."""
    n = len(poses)
    sel = keep if keep is not None else [True] * len(decisions)
    pairs = np.array(
        [
            (d.from_node, d.hypothesis.node)
            for d, k in zip(decisions, sel)
            if k and d.status == status and not (skip_lost and decided_while_lost(d))
        ],
        dtype=np.int64,
    ).reshape(-1, 2)
    pairs = pairs[(pairs >= 0).all(axis=1) & (pairs < n).all(axis=1)]
    seg = np.empty((len(pairs), 2, 3), np.float32)
    seg[:, :, :2] = poses[pairs][:, :, :2]
    seg[:, :, 2] = LOOP_Z
    return seg


@dataclass(frozen=True)
class LoopUpdate:
    accepted: ChunkUpdate  # the used closures
    faded: ChunkUpdate
    rejected: ChunkUpdate


class LoopLayer:
    """Scene nodes ``/loops/accepted/<k>`` (the used closures, with ``/loops/accepted/ends/<k>``),
    ``/loops/faded/<k>``, ``/loops/rejected/<k>`` and ``/loops/selected``."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        s = settings
        self.scene, self.settings = scene, s

        def thin(name: str, color: RGB) -> ChunkedSegments:
            return ChunkedSegments(
                scene,
                name,
                s.chunk_size,
                s.move_tolerance_m,
                s.loop_thickness_m,
                style="thin",
                color=color,
                tail_size=s.tail_size,
            )

        self.accepted = thin("/loops/accepted", s.color_loop_accepted)
        # a closed loop pulls its two nodes together, so its segment is short: mark its ends too,
        # with dots smaller than a node (the node stays visible around its loop mark)
        self.accepted_ends = ChunkedPoints(
            scene, "/loops/accepted/ends", s.chunk_size, s.move_tolerance_m, 0.6 * s.node_size_m, tail_size=s.tail_size
        )
        self.faded = thin("/loops/faded", s.color_loop_faded)
        self.rejected = thin("/loops/rejected", s.color_loop_rejected)
        self._selected: list[Any] = []
        self._selected_key: tuple | None = None

    def update(self, snap: MapSnapshot, skip_lost: bool = False) -> LoopUpdate:
        """Push the decisions of ``snap`` (``skip_lost``: see :func:`loop_segments`)."""
        s = self.settings
        used = used_flags(snap.decisions, snap.loop_weights)
        acc = loop_segments(snap.decisions, snap.node_poses, "accepted", skip_lost, used)
        fad = loop_segments(snap.decisions, snap.node_poses, "accepted", skip_lost, [not u for u in used])
        rej = loop_segments(snap.decisions, snap.node_poses, "rejected")

        def colours(n: int, color: RGB) -> np.ndarray:
            return np.broadcast_to(np.array(color, np.uint8), (n, 3))

        a = self.accepted.update(acc, colours(len(acc), s.color_loop_accepted))
        ends = acc.reshape(-1, 3)
        self.accepted_ends.update(ends, colours(len(ends), s.color_loop_accepted))
        f = self.faded.update(fad, colours(len(fad), s.color_loop_faded))
        r = self.rejected.update(rej, colours(len(rej), s.color_loop_rejected))
        return LoopUpdate(a, f, r)

    def select(self, decision: LoopDecision | None, poses: np.ndarray, weight: float = float("nan")) -> None:
        """Mark one loop closure (or none) with a thick segment, in its layer's colour (``weight``: its
        link's robust weight, NaN without a link), and its two node labels."""
        n = len(poses)
        key = None
        if decision is not None and 0 <= decision.from_node < n and 0 <= decision.hypothesis.node < n:
            a, b = poses[decision.from_node, :2], poses[decision.hypothesis.node, :2]
            ab: np.ndarray = np.r_[a, b]
            key = (decision.id, decision.status, is_used(decision.status, weight), *np.round(ab, 2))
        if key == self._selected_key:
            return
        for h in self._selected:
            h.remove()
        self._selected = []
        self._selected_key = key
        if key is None:
            return
        assert decision is not None  # key is set only for a decision
        s = self.settings
        if decision.status != "accepted":
            color = s.color_loop_rejected
        else:
            color = s.color_loop_accepted if is_used(decision.status, weight) else s.color_loop_faded
        seg = np.array([[[a[0], a[1], LOOP_Z + 0.02], [b[0], b[1], LOOP_Z + 0.02]]], np.float32)
        self._selected = [
            self.scene.add_line_segments(
                "/loops/selected/segment", seg, np.array(color, np.uint8), thickness=3 * s.loop_thickness_m
            ),
            self.scene.add_label(
                "/loops/selected/now",
                f"loop {decision.id}: node {decision.from_node}",
                position=(float(a[0]), float(a[1]), 0.3),
            ),
            self.scene.add_label(
                "/loops/selected/then", f"node {decision.hypothesis.node}", position=(float(b[0]), float(b[1]), 0.3)
            ),
        ]

    def set_visible(
        self, accepted: bool | None = None, rejected: bool | None = None, faded: bool | None = None
    ) -> None:
        if accepted is not None:
            self.accepted.visible = accepted
        if faded is not None:
            self.faded.visible = faded
        if rejected is not None:
            self.rejected.visible = rejected
