"""2.5-D ray caster: one ray per image column against every nearby wall at once.

For a camera at pose (x, y, θ), column ``c`` looks along ``R(θ)·(1, k_c)`` with
``k_c = -(c + 0.5 - cx) / f`` (image right = robot's right). Intersecting that ray with
all candidate segments is one (W, S) broadcast; the nearest hit gives the column's
forward depth ``z`` (perpendicular, so no fish-eye), the wall and the texture column.
A pixel row ``r`` then sees height ``h = h_cam + (cy - r - 0.5) z / f`` on that wall;
heights in [0, wall height] are wall texture, below is the floor, above the ceiling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import InputError
from .params import Camera, Shading
from .world import World


@dataclass(frozen=True)
class Hits:
    """Per-column ray-cast result: forward ``depth`` (inf where no wall is in range),
    ``segment`` index (-1 for none), texture column ``u`` (texels) and the column's
    ray direction in the world (``dx``, ``dy``; forward component 1)."""

    depth: np.ndarray
    segment: np.ndarray
    u: np.ndarray
    dx: np.ndarray
    dy: np.ndarray


@lru_cache(maxsize=16)
def _columns(camera: Camera) -> np.ndarray:
    c = np.arange(camera.width) + 0.5
    return -(c - camera.cx) / camera.focal_px


@lru_cache(maxsize=16)
def _rows(camera: Camera) -> np.ndarray:
    r = np.arange(camera.height) + 0.5
    return ((camera.cy - r) / camera.focal_px).astype(np.float32)


def _check_pose(pose) -> np.ndarray:
    p = np.asarray(pose, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise InputError(f"camera pose must be 3 finite numbers (x, y, theta), got {pose!r}")
    return p


def _cast(px, py, dx, dy, seg):
    """Nearest hit of rays (px, py) + t (dx, dy) on segments (S, 4): t (W,), index (W,), s (W,)."""
    ax, ay = seg[:, 0], seg[:, 1]
    ex, ey = seg[:, 2] - ax, seg[:, 3] - ay
    wx, wy = ax - px, ay - py
    denom = dx[:, None] * ey - dy[:, None] * ex  # (W, S)
    num_t = wx * ey - wy * ex  # (S,)
    num_s = wx * dy[:, None] - wy * dx[:, None]  # (W, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / denom
        t = num_t * inv
        s = num_s * inv
    ok = (t > 1e-6) & (s >= 0.0) & (s <= 1.0)
    t = np.where(ok, t, np.inf)
    j = np.argmin(t, axis=1)
    rows = np.arange(len(dx))
    return t[rows, j], j, s[rows, j]


def _frustum(world: World, idx: np.ndarray, px, py, c, s, half_slope) -> np.ndarray:
    """Drop candidate segments entirely behind the camera or outside the field of view."""
    seg = world.segments[idx]
    ax, ay = seg[:, 0] - px, seg[:, 1] - py
    bx, by = seg[:, 2] - px, seg[:, 3] - py
    fa, la = c * ax + s * ay, -s * ax + c * ay
    fb, lb = c * bx + s * by, -s * bx + c * by
    behind = (fa <= 0) & (fb <= 0)
    left = (la > half_slope * fa) & (lb > half_slope * fb)
    right = (-la > half_slope * fa) & (-lb > half_slope * fb)
    return idx[~(behind | left | right)]


def raycast(world: World, pose, camera: Camera = Camera()) -> Hits:
    """Cast one ray per image column; vectorised over columns and segments."""
    px, py, th = _check_pose(pose)
    k = _columns(camera)
    c, s = np.cos(th), np.sin(th)
    dx, dy = c - k * s, s + k * c
    W = camera.width
    depth = np.full(W, np.inf)
    segid = np.full(W, -1, dtype=np.int64)
    spar = np.zeros(W)
    half_slope = abs(k[0]) * 1.01 + 1e-9
    norm = np.hypot(dx, dy)  # Euclidean distance = depth * norm
    if world.grid is None:
        t, j, sp = _cast(px, py, dx, dy, world.segments)
        hit = np.isfinite(t) & (t * norm <= camera.max_range_m)
        depth[hit], segid[hit], spar[hit] = t[hit], j[hit], sp[hit]
    else:
        todo = np.arange(W)
        radii = [r for r in (camera.near_range_m,) if r < camera.max_range_m] + [camera.max_range_m]
        for radius in radii:
            idx = world.grid.query(px, py, radius)
            if idx.size:
                idx = _frustum(world, idx, px, py, c, s, half_slope)
            if idx.size == 0:
                continue
            t, j, sp = _cast(px, py, dx[todo], dy[todo], world.segments[idx])
            # a hit no farther than the query radius is the nearest wall: every closer
            # wall lies inside the query square and was a candidate
            hit = np.isfinite(t) & (t * norm[todo] <= radius)
            cols = todo[hit]
            depth[cols], segid[cols], spar[cols] = t[hit], idx[j[hit]], sp[hit]
            todo = todo[~hit]
            if todo.size == 0:
                break
    u = np.zeros(W)
    ok = segid >= 0
    u[ok] = world.u0[segid[ok]] + spar[ok] * world.lengths[segid[ok]] * world.texture.texels_per_m
    return Hits(depth, segid, u, dx, dy)


def _hash01(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic per-tile value in [-1, 1] (32-bit integer hash, vectorised)."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.uint32) * np.uint32(0x9E3779B1)) ^ (iy.astype(np.uint32) * np.uint32(0x85EBCA77))
        h ^= np.uint32((seed * 0xC2B2AE3D) & 0xFFFFFFFF)
        h ^= h >> np.uint32(15)
        h *= np.uint32(0x2C1B3C6D)
        h ^= h >> np.uint32(12)
        h *= np.uint32(0x297A2D39)
        h ^= h >> np.uint32(15)
    return (h & np.uint32(0xFFFF)).astype(np.float32) * np.float32(1 / 32767.5) - np.float32(1.0)


def render(
    world: World,
    pose,
    camera: Camera = Camera(),
    shading: Shading = Shading(),
    rng: np.random.Generator | None = None,
    gain: float = 1.0,
) -> np.ndarray:
    """Grey uint8 image (height, width) seen from ``pose`` = (x, y, θ).

    Walls: texture (mip level from the texel footprint of each column) times a
    directional light term and a depth fog. Floor: world-anchored tiles with a seeded
    shade each, fading with distance. Ceiling: brightness falling with distance.
    The scene's light scales every grey level by ``gain`` (``Camera.exposure_gain`` of the frame's
    time); sensor noise (``camera.pixel_noise``) is added after it, only when ``rng`` is given.
    """
    pose = _check_pose(pose)
    if not (math.isfinite(gain) and gain >= 0):
        raise InputError(f"gain = {gain!r} must be a finite factor >= 0")
    hits = raycast(world, pose, camera)
    yv = _rows(camera)[:, None]  # (H, 1) upward slope of each row
    dz = np.where(np.isfinite(hits.depth), hits.depth, 0.0)
    img = np.empty((camera.height, camera.width), np.float32)
    _ceiling(img, yv, world, camera, shading)
    _floor(img, yv, pose, hits, world, camera, shading)
    _walls(img, yv, hits, dz, world, camera, shading)
    if gain != 1.0:
        img *= np.float32(gain)
    if rng is not None and camera.pixel_noise > 0:
        img += rng.normal(0.0, camera.pixel_noise, img.shape).astype(np.float32)
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def _ceiling(img: np.ndarray, yv: np.ndarray, world: World, camera: Camera, shading: Shading) -> None:
    """The rows above the horizon: the ceiling's brightness, fogged with its distance."""
    above = np.flatnonzero(yv[:, 0] > 0)
    if above.size:
        zc = (world.texture.wall_height_m - camera.mount_height_m) / yv[above]
        img[above] = shading.ceiling_level * (shading.fog_floor + (1 - shading.fog_floor) / (1 + zc / shading.fog_m))


def _floor(
    img: np.ndarray, yv: np.ndarray, pose: np.ndarray, hits: Hits, world: World, camera: Camera, shading: Shading
) -> None:
    """The rows below the horizon: world-anchored floor tiles, each with a seeded shade, fading with distance."""
    below = np.flatnonzero(yv[:, 0] <= 0)
    if not below.size:
        return
    with np.errstate(divide="ignore"):
        zf = camera.mount_height_m / -yv[below]  # (B, 1) forward depth of the floor (inf at the horizon)
    zf = np.minimum(zf, np.float32(1e6))
    X = np.float32(pose[0]) + zf * hits.dx.astype(np.float32)[None, :]
    Y = np.float32(pose[1]) + zf * hits.dy.astype(np.float32)[None, :]
    tile = np.float32(1.0 / shading.floor_tile_m)
    val = _hash01(np.floor(X * tile).astype(np.int32), np.floor(Y * tile).astype(np.int32), world.floor_seed)
    fog = shading.fog_floor + (1 - shading.fog_floor) / (1 + zf / shading.fog_m)
    img[below] = shading.floor_level * fog + (shading.floor_contrast * np.exp(-zf / shading.floor_fade_m)) * val


def _mip_levels(hits: Hits, dz: np.ndarray, world: World, camera: Camera) -> np.ndarray:
    """The mip level of each column: from its texels per pixel, vertically (z / f) and along the wall (the
    texture column's change between neighbours on the same wall)."""
    seg = hits.segment
    fv = dz / camera.focal_px * world.texture.texels_per_m
    du = np.abs(np.gradient(hits.u)) if len(hits.u) > 1 else np.zeros(1)
    same = np.ones(len(seg), bool)
    same[1:-1] = (seg[2:] == seg[:-2]) & (seg[1:-1] >= 0)
    fu = np.where(same, du, fv)
    foot = np.maximum(fv, np.sqrt(fu * fv))
    return np.clip(np.floor(np.log2(np.maximum(foot, 1e-9))), 0, world.atlas.n_levels - 1).astype(np.int64)


def _wall_gain(hits: Hits, dz: np.ndarray, world: World, shading: Shading) -> np.ndarray:
    """The shading of each column's wall: light from a fixed direction on the face seen, and depth fog."""
    nrm = world.normals[np.maximum(hits.segment, 0)]
    facing = -np.sign(nrm[:, 0] * hits.dx + nrm[:, 1] * hits.dy)
    la = np.radians(shading.light_deg)
    lam = 0.5 + 0.5 * facing * (nrm[:, 0] * np.cos(la) + nrm[:, 1] * np.sin(la))
    fog_w = shading.fog_floor + (1 - shading.fog_floor) / (1 + dz / shading.fog_m)
    return (((1 - shading.directional) + shading.directional * lam) * fog_w).astype(np.float32)


def _walls(
    img: np.ndarray, yv: np.ndarray, hits: Hits, dz: np.ndarray, world: World, camera: Camera, shading: Shading
) -> None:
    """The walls over the background: in each column that hits one, the texture row of every pixel is affine in
    the row index; pixels between floor and wall top take the texel (at the column's mip level) times its gain."""
    hit = np.isfinite(hits.depth)
    if not hit.any():
        return
    atlas = world.atlas
    tpm = world.texture.texels_per_m
    level = _mip_levels(hits, dz, world, camera)
    gain = _wall_gain(hits, dz, world, shading)
    cols = np.flatnonzero(hit)
    trow = (
        np.float32((world.texture.wall_height_m - camera.mount_height_m) * tpm)
        - yv * (dz[cols] * tpm).astype(np.float32)[None, :]
    )  # (H, C)
    wall = (trow >= 0) & (trow <= atlas.rows[0])
    lv = level[cols]
    sc = atlas.scales[lv].astype(np.float32)
    nr, nc = atlas.rows[lv].astype(np.int32), atlas.cols[lv].astype(np.int32)
    r = (trow * sc).astype(np.int32)
    np.minimum(r, nr - 1, out=r)
    np.maximum(r, 0, out=r)
    r *= nc
    r += (atlas.offsets[lv] + np.minimum((hits.u[cols] * sc).astype(np.int64), nc - 1)).astype(np.int32)
    tex = atlas.flat[r]
    sub = img[:, cols]
    img[:, cols] = np.where(wall, tex * gain[cols], sub)
