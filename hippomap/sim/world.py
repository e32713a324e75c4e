"""A 2.5-D world: vertical wall segments of one height on a flat floor.

Walls are given as polylines; each polyline's walls are laid end to end along the
world's texture strip (:mod:`hippomap.sim.textures`), so every metre of wall has its own
texture. Large worlds (thousands of segments, e.g. the Bicocca building) get a uniform
grid of segments (:class:`SegmentGrid`) so a frame only ray-casts against walls near the
camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import InputError
from .params import TextureParams
from .textures import MipAtlas, make_strip

#: worlds with more segments than this use a SegmentGrid
GRID_MIN_SEGMENTS = 64


class SegmentGrid:
    """Uniform grid of square cells; each cell lists the segments passing through it
    (compressed-row arrays, built once, queried vectorised)."""

    def __init__(self, segments: np.ndarray, cell_m: float = 4.0):
        seg = np.asarray(segments, dtype=float)
        self.cell = float(cell_m)
        lo = np.minimum(seg[:, :2], seg[:, 2:]).min(axis=0) - self.cell
        hi = np.maximum(seg[:, :2], seg[:, 2:]).max(axis=0) + self.cell
        self.origin = lo
        self.shape = tuple(int(v) for v in np.ceil((hi - lo) / self.cell).astype(int) + 1)  # (nx, ny)
        # sample every segment at <= half a cell: every point of a segment is then within
        # a quarter cell of a sample, i.e. in the sample's cell or a neighbour; queries
        # are widened by one cell to cover that.
        lengths = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
        n = np.maximum(2, np.ceil(lengths / (0.5 * self.cell)).astype(int) + 1)
        sid = np.repeat(np.arange(len(seg)), n)
        start = np.repeat(np.cumsum(n) - n, n)
        frac = (np.arange(n.sum()) - start) / np.repeat(n - 1, n)
        pts = seg[sid, :2] + frac[:, None] * (seg[sid, 2:] - seg[sid, :2])
        ij = np.floor((pts - self.origin) / self.cell).astype(np.int64)
        cell = ij[:, 0] * self.shape[1] + ij[:, 1]
        key = np.unique(cell * len(seg) + sid)
        cell, sid = key // len(seg), key % len(seg)
        ncell = self.shape[0] * self.shape[1]
        counts = np.bincount(cell, minlength=ncell)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.indices = sid.astype(np.int64)  # already sorted by cell

    def query(self, x: float, y: float, radius: float) -> np.ndarray:
        """Indices of every segment with a point within the square of half-side ``radius``
        around (x, y) (a superset: whole cells, widened by one)."""
        nx, ny = self.shape
        i0, j0 = np.floor((np.array([x, y]) - radius - self.origin) / self.cell).astype(int) - 1
        i1, j1 = np.floor((np.array([x, y]) + radius - self.origin) / self.cell).astype(int) + 1
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, nx - 1), min(j1, ny - 1)
        if i0 > i1 or j0 > j1:
            return np.empty(0, dtype=np.int64)
        ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
        cells = (ii * ny + jj).ravel()
        a, b = self.indptr[cells], self.indptr[cells + 1]
        cnt = b - a
        tot = int(cnt.sum())
        if tot == 0:
            return np.empty(0, dtype=np.int64)
        idx = np.repeat(a - np.cumsum(cnt) + cnt, cnt) + np.arange(tot)
        return np.unique(self.indices[idx])


@dataclass(eq=False)
class World:
    """Walls (``segments`` (S, 4): ax, ay, bx, by in metres), the texture column at each
    segment's start (``u0``, texels), the texture atlas, and optionally a default route
    (a :class:`~hippomap.sim.motion.Trajectory`, ``DrivePlan`` or ``RoutePlan``)."""

    name: str
    segments: np.ndarray
    u0: np.ndarray
    atlas: MipAtlas
    texture: TextureParams
    route: object = None
    seed: int = 0
    floor_seed: int = 0
    grid: SegmentGrid | None = field(default=None, repr=False)

    def __post_init__(self):
        seg = np.asarray(self.segments, dtype=float)
        if seg.ndim != 2 or seg.shape[1] != 4 or len(seg) == 0:
            raise InputError(f"world segments must be (S, 4) with S >= 1, got shape {seg.shape}")
        if not np.isfinite(seg).all():
            raise InputError(
                f"world segment {int(np.flatnonzero(~np.isfinite(seg).all(1))[0])} has a non-finite coordinate"
            )
        self.segments = seg
        self.u0 = np.asarray(self.u0, dtype=float).reshape(-1)
        if self.u0.shape != (len(seg),):
            raise InputError(f"u0 has {self.u0.size} entries for {len(seg)} segments")
        d = seg[:, 2:] - seg[:, :2]
        self.lengths = np.hypot(d[:, 0], d[:, 1])
        # unit normals (either side; the renderer flips them to face the camera)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.normals = np.stack([-d[:, 1], d[:, 0]], axis=1) / self.lengths[:, None]
        self.normals[~np.isfinite(self.normals)] = 0.0
        if self.grid is None and len(seg) > GRID_MIN_SEGMENTS:
            self.grid = SegmentGrid(seg)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.segments
        return np.minimum(s[:, :2], s[:, 2:]).min(0), np.maximum(s[:, :2], s[:, 2:]).max(0)

    @classmethod
    def from_polylines(
        cls,
        polylines,
        *,
        name: str = "world",
        texture: TextureParams | None = None,
        seed: int = 0,
        route=None,
        strip: np.ndarray | None = None,
    ) -> "World":
        """Build a world from wall polylines ((K, 2) arrays; repeat the first point at the
        end to close one). Texture: a seeded strip as long as all walls together
        (``strip`` overrides it, e.g. a flat texture in tests)."""
        texture = texture or TextureParams()
        segs, u0 = [], []
        u = 1.0  # texel column where the next polyline starts
        gap = 8.0  # texels between polylines so mips do not bleed across
        for k, pl in enumerate(polylines):
            pl = np.asarray(pl, dtype=float)
            if pl.ndim != 2 or pl.shape[1] != 2 or len(pl) < 2:
                raise InputError(f"wall polyline {k} must be (K >= 2, 2), got shape {pl.shape}")
            if not np.isfinite(pl).all():
                raise InputError(f"wall polyline {k} has a non-finite vertex")
            d = np.hypot(*np.diff(pl, axis=0).T)
            keep = d > 1e-9
            a, b, d = pl[:-1][keep], pl[1:][keep], d[keep]
            if not len(d):
                continue
            segs.append(np.hstack([a, b]))
            u0.append(u + np.concatenate([[0.0], np.cumsum(d)[:-1]]) * texture.texels_per_m)
            u += d.sum() * texture.texels_per_m + gap
        if not segs:
            raise InputError("world has no wall of non-zero length")
        segments = np.vstack(segs)
        u0_all = np.concatenate(u0)
        if strip is None:
            strip = make_strip((u + 1.0) / texture.texels_per_m, texture, seed)
        atlas = MipAtlas(strip)
        return cls(name, segments, u0_all, atlas, texture, route=route, seed=seed, floor_seed=seed)


def walls_around_path(
    path_xy,
    half_width_m: float = 1.2,
    resolution_m: float = 0.1,
    simplify_m: float = 0.15,
    min_perimeter_m: float = 0.6,
) -> list[np.ndarray]:
    """Closed wall polylines around a 2-D path: the boundary of the free space made of
    every point within ``half_width_m`` of the path.

    The free space is rasterised on a grid of ``resolution_m`` (the path drawn as a
    polyline, then a Euclidean distance transform), its boundary traced
    (``cv2.findContours``) and simplified (Douglas–Peucker, ``simplify_m``). Where the
    path crosses or re-runs itself the free areas merge into one junction or corridor,
    so no wall is ever built across the path. Every path point is at least
    ``half_width_m - resolution_m - simplify_m`` from every wall.
    """
    p = np.asarray(path_xy, dtype=float)
    if p.ndim != 2 or p.shape[1] < 2 or len(p) < 1:
        raise InputError(f"path must be (N, 2) or (N, 3), got shape {p.shape}")
    p = p[:, :2]
    if not np.isfinite(p).all():
        raise InputError(f"path point {int(np.flatnonzero(~np.isfinite(p).all(1))[0])} is not finite")
    for name, v in (("half_width_m", half_width_m), ("resolution_m", resolution_m)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"{name} = {v!r} must be finite and > 0")
    if not half_width_m > 2 * resolution_m + simplify_m:
        raise InputError(
            f"half_width_m = {half_width_m} must exceed 2 * resolution_m + simplify_m = {2 * resolution_m + simplify_m}"
        )
    margin = half_width_m + 4 * resolution_m
    origin = p.min(axis=0) - margin
    size = np.ceil((p.max(axis=0) + margin - origin) / resolution_m).astype(int) + 1
    if size.prod() > 60_000_000:
        raise InputError(f"wall grid {size[0]}x{size[1]} too large: raise resolution_m (now {resolution_m})")
    shift = 4  # sub-pixel bits for cv2 drawing
    pix = np.round((p - origin) / resolution_m * (1 << shift) - 0.5 * (1 << shift)).astype(np.int32)
    path_img = np.full((size[1], size[0]), 255, np.uint8)
    if len(pix) == 1:
        cv2.circle(path_img, tuple(int(v) for v in pix[0]), 0, 0, -1, shift=shift)
    else:
        cv2.polylines(path_img, [pix.reshape(-1, 1, 2)], False, 0, 1, cv2.LINE_8, shift)
    dist = cv2.distanceTransform(path_img, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    free = (dist * resolution_m <= half_width_m).astype(np.uint8)
    contours, _ = cv2.findContours(free, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    out = []
    for c in contours:
        if len(c) < 3:
            continue
        poly = cv2.approxPolyDP(c, simplify_m / resolution_m, True).reshape(-1, 2).astype(float)
        poly = origin + (poly + 0.5) * resolution_m
        poly = np.vstack([poly, poly[:1]])
        if np.hypot(*np.diff(poly, axis=0).T).sum() < min_perimeter_m:
            continue
        out.append(poly)
    return out


def point_segment_distance(points, segments, chunk: int = 2_000_000) -> np.ndarray:
    """Distance from each point (N, 2) to the nearest segment (S, 4): (N,).
    Vectorised over points x segments, in blocks of about ``chunk`` pairs."""
    q = np.asarray(points, dtype=float)[:, :2]
    s = np.asarray(segments, dtype=float)
    a, b = s[None, :, :2], s[None, :, 2:]
    ab = b - a
    den = np.maximum((ab * ab).sum(-1), 1e-18)
    out = np.empty(len(q))
    step = max(1, chunk // max(1, len(s)))
    for k in range(0, len(q), step):
        qq = q[k : k + step, None, :]
        t = np.clip(((qq - a) * ab).sum(-1) / den, 0.0, 1.0)
        d = qq - (a + t[..., None] * ab)
        out[k : k + step] = np.sqrt((d * d).sum(-1)).min(axis=1)
    return out
