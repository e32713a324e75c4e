"""Append-only scene layers sent to the browser in chunks.

A map of tens of thousands of nodes cannot be resent whole five times a second: the browser
needs ~0.5 s to ingest 50k points (docs VIEWER.md). But the map is append-only (nodes, links
and trajectory samples are only ever added) and a relaxation moves positions only after an
action, mostly after a loop closure. So each layer is cut into chunks, each drawn as one viser
scene node (``<layer>/<first item>``):

* complete blocks of ``chunk_size`` items are *sealed* chunks; the items after the last complete
  block are held in small *tail* chunks of ``tail_size`` items. Appending an item resends only
  the last tail chunk (at most ``tail_size`` items); when a block fills up, its tail chunks are
  replaced by one sealed chunk (``chunk_size`` items once per ``chunk_size`` appended);
* a chunk is also resent when one of its items moved further than ``tolerance`` (or changed
  colour) since it was last sent, so what the browser holds never drifts from the map by more
  than the tolerance; a relaxation that moves only part of the map resends only its chunks.

Finding the chunks to resend is one vectorised comparison against a copy of what was sent.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class ChunkUpdate:
    """What one :meth:`ChunkTracker.plan` asks to send: chunks as ``(start, stop)`` item ranges, the
    items they hold, and the starts of chunks to delete (tail chunks merged into a sealed chunk)."""

    chunks: tuple[tuple[int, int], ...]
    items: int
    removed: tuple[int, ...] = ()


def chunk_layout(n: int, chunk_size: int, tail_size: int) -> list[tuple[int, int]]:
    """The ``(start, stop)`` ranges of ``n`` items: sealed blocks of ``chunk_size``, then tails."""
    sealed = (n // chunk_size) * chunk_size
    out = [(s, s + chunk_size) for s in range(0, sealed, chunk_size)]
    out += [(s, min(n, s + tail_size)) for s in range(sealed, n, tail_size)]
    return out


class ChunkTracker:
    """Which chunks of an append-only array of items differ from what the browser holds.

    Items are rows of ``geometry`` (float, any width: 3 for points, 6 for segments) with one
    RGB colour each. The tracker keeps a float32 copy of the rows last sent and the layout
    (``start -> stop``) of the chunks the browser holds.
    """

    def __init__(self, chunk_size: int, tolerance: float, width: int, tail_size: int | None = None) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size = {chunk_size} must be >= 1")
        tail = chunk_size if tail_size is None else int(tail_size)
        if not 1 <= tail <= chunk_size:
            raise ValueError(f"tail_size = {tail_size} must be in [1, chunk_size = {chunk_size}]")
        self.chunk_size = int(chunk_size)
        self.tail_size = tail
        self.tolerance = float(tolerance)
        self.width = int(width)
        self._geom = np.empty((0, self.width), np.float32)
        self._colors = np.empty((0, 3), np.uint8)
        self.layout: dict[int, int] = {}  # start -> stop of the chunks the browser holds
        self.n = 0  # items the browser holds

    def plan(self, geometry: np.ndarray, colors: np.ndarray) -> ChunkUpdate:
        """Chunks to send so that the browser matches ``geometry`` / ``colors``; marks them sent.

        ``geometry`` is (N, width), ``colors`` (N, 3) uint8. N may only grow (append-only);
        if it shrinks, everything is resent.
        """
        g = np.asarray(geometry, np.float32).reshape(-1, self.width)
        c = np.asarray(colors, np.uint8).reshape(-1, 3)
        if len(g) != len(c):
            raise ValueError(f"{len(g)} items but {len(c)} colours")
        n = len(g)
        old_n, old_layout = (self.n, self.layout) if n >= self.n else (0, {})
        layout = chunk_layout(n, self.chunk_size, self.tail_size)
        starts = np.array([a for a, _ in layout], dtype=np.int64)
        dirty = np.zeros(len(layout), bool)
        if old_n:
            moved = np.abs(g[:old_n] - self._geom[:old_n]).max(axis=1) > self.tolerance
            moved |= np.any(c[:old_n] != self._colors[:old_n], axis=1)
            dirty[np.unique(np.searchsorted(starts, np.flatnonzero(moved), side="right") - 1)] = True
        for i, (a, b) in enumerate(layout):
            if old_layout.get(a) != b:
                dirty[i] = True
        chunks = tuple(layout[i] for i in np.flatnonzero(dirty))
        removed = tuple(sorted(set(self.layout) - set(int(a) for a in starts)))
        self._store(g, c, chunks)
        self.layout = {a: b for a, b in layout}
        return ChunkUpdate(chunks, sum(b - a for a, b in chunks), removed)

    def _store(self, g: np.ndarray, c: np.ndarray, chunks: tuple[tuple[int, int], ...]) -> None:
        n = len(g)
        if len(self._geom) < n:
            cap = max(n, 2 * len(self._geom), self.chunk_size)
            geom = np.empty((cap, self.width), np.float32)
            cols = np.empty((cap, 3), np.uint8)
            geom[: self.n] = self._geom[: self.n]
            cols[: self.n] = self._colors[: self.n]
            self._geom, self._colors = geom, cols
        for a, b in chunks:
            self._geom[a:b] = g[a:b]
            self._colors[a:b] = c[a:b]
        self.n = n

    @property
    def n_chunks(self) -> int:
        return len(self.layout)


class _ChunkedLayer:
    """Common part of the chunked layers: a group frame, and one scene node per chunk."""

    def __init__(self, scene: Any, name: str, tracker: ChunkTracker, visible: bool = True) -> None:
        self.scene, self.name, self.tracker = scene, name, tracker
        self.group = scene.add_frame(name, show_axes=False, visible=visible)
        self._handles: dict[int, Any] = {}

    def _apply(self, plan: ChunkUpdate, add) -> ChunkUpdate:
        for a in plan.removed:
            h = self._handles.pop(a, None)
            if h is not None:
                h.remove()
        for a, b in plan.chunks:
            self._handles[a] = add(f"{self.name}/{a}", a, b)
        return plan

    @property
    def visible(self) -> bool:
        return bool(self.group.visible)

    @visible.setter
    def visible(self, value: bool) -> None:
        self.group.visible = bool(value)


class ChunkedPoints(_ChunkedLayer):
    """A growing point set (e.g. the map's nodes) as point-cloud chunks under ``name``."""

    def __init__(
        self,
        scene: Any,
        name: str,
        chunk_size: int,
        tolerance: float,
        point_size: float,
        point_shape: str = "circle",
        tail_size: int | None = None,
    ) -> None:
        super().__init__(scene, name, ChunkTracker(chunk_size, tolerance, 3, tail_size))
        self.point_size, self.point_shape = point_size, point_shape

    def update(self, points: np.ndarray, colors: np.ndarray) -> ChunkUpdate:
        """Send the chunks that changed; ``points`` (N, 3), ``colors`` (N, 3) uint8."""
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        cols = np.asarray(colors, np.uint8).reshape(-1, 3)
        plan = self.tracker.plan(pts, cols)
        return self._apply(
            plan,
            lambda name, a, b: self.scene.add_point_cloud(
                name,
                pts[a:b],
                np.ascontiguousarray(cols[a:b]),
                point_size=self.point_size,
                point_shape=self.point_shape,
                precision="float32",
                point_shading="flat",
            ),
        )


class ChunkedSegments(_ChunkedLayer):
    """A growing set of line segments (links, trajectory pieces) as chunks of one of two styles.

    ``"thin"``: a wireframe mesh per chunk (degenerate triangles ``a, b, b``), drawn with native
    1-pixel GL lines in one colour — cheap even in software WebGL, where viser's instanced "fat"
    lines cost far more per segment (see bench/bench_viewer.py). ``"fat"``: viser line segments
    with a world-space thickness and a colour per segment, for the few segments that must stand
    out (loop closures).
    """

    def __init__(
        self,
        scene: Any,
        name: str,
        chunk_size: int,
        tolerance: float,
        thickness: float,
        visible: bool = True,
        style: str = "fat",
        color: tuple[int, int, int] = (128, 128, 128),
        tail_size: int | None = None,
    ) -> None:
        if style not in ("fat", "thin"):
            raise ValueError(f"style = {style!r} must be 'fat' or 'thin'")
        super().__init__(scene, name, ChunkTracker(chunk_size, tolerance, 6, tail_size), visible)
        self.thickness = thickness
        self.style, self.color = style, tuple(int(c) for c in color)

    def update(self, segments: np.ndarray, colors: np.ndarray | None = None) -> ChunkUpdate:
        """Send the chunks that changed; ``segments`` (N, 2, 3), ``colors`` (N, 3) uint8 per segment
        (fat style; the thin style draws every segment in the layer's colour)."""
        seg = np.asarray(segments, np.float32).reshape(-1, 6)
        if colors is None or self.style == "thin":
            cols = np.broadcast_to(np.array(self.color, np.uint8), (len(seg), 3))
        else:
            cols = np.asarray(colors, np.uint8).reshape(-1, 3)
        plan = self.tracker.plan(seg, cols)

        def add(name: str, a: int, b: int) -> Any:
            if self.style == "thin":
                i = np.arange(b - a, dtype=np.uint32)
                faces = np.column_stack([2 * i, 2 * i + 1, 2 * i + 1])
                return self.scene.add_mesh_simple(
                    name,
                    np.ascontiguousarray(seg[a:b].reshape(-1, 3)),
                    faces,
                    color=self.color,
                    wireframe=True,
                    cast_shadow=False,
                    receive_shadow=False,
                )
            c = cols[a:b]
            return self.scene.add_line_segments(
                name,
                seg[a:b].reshape(-1, 2, 3),
                np.ascontiguousarray(np.repeat(c[:, None, :], 2, axis=1)),
                thickness=self.thickness,
            )

        return self._apply(plan, add)
