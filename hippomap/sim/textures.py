"""Wall textures for the camera simulator: one long "wallpaper" strip per world.

Every metre of wall in a world gets its own stretch of the strip (walls are laid out
end to end along it), so no two places share a texture. The strip is either procedural
(seeded: panels, skirting, posters, notices with text lines, doors, checker boards,
clocks, triangles — many rectangle corners, since the visual memory fixates on
Shi–Tomasi corners, spec §2) or built from a folder of real photos.

:class:`MipAtlas` keeps the strip with a mip pyramid (each level a 2x ``pyrDown`` of the
previous) flattened into one array, so a frame samples every pixel with a single
vectorised gather and far walls are pre-filtered instead of aliasing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")


class MipAtlas:
    """A grey-level strip (rows = wall height, columns = metres of wall) and its mips."""

    def __init__(self, strip: np.ndarray, max_levels: int = 7):
        strip = np.asarray(strip)
        if strip.ndim != 2 or strip.shape[0] < 2 or strip.shape[1] < 2:
            raise InputError(f"texture strip must be a 2-D image, got shape {strip.shape}")
        levels: list[np.ndarray] = [np.ascontiguousarray(strip, dtype=np.uint8)]
        while len(levels) < max_levels and min(levels[-1].shape) >= 8:
            levels.append(cv2.pyrDown(levels[-1]))
        self.levels = levels
        self.rows = np.array([lv.shape[0] for lv in levels], dtype=np.int64)
        self.cols = np.array([lv.shape[1] for lv in levels], dtype=np.int64)
        sizes = self.rows * self.cols
        self.offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.flat = np.concatenate([lv.ravel() for lv in levels])
        if self.flat.size >= 2**31:
            raise InputError(f"texture atlas of {self.flat.size} texels too large: lower texels_per_m")
        self.scales = 2.0 ** -np.arange(len(levels))

    @property
    def shape(self) -> tuple[int, int]:
        return self.levels[0].shape

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    def sample(self, level: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Nearest-texel lookup; ``row``, ``col`` in level-0 texels, ``level`` integer.
        All three broadcast together (e.g. (H, W), (H, W), (W,))."""
        level = np.asarray(level, dtype=np.int64)
        sc = self.scales[level]
        nr = self.rows[level]
        nc = self.cols[level]
        r = np.clip((row * sc).astype(np.int64), 0, nr - 1)
        c = np.clip((col * sc).astype(np.int64), 0, nc - 1)
        return self.flat[self.offsets[level] + r * nc + c]


# --------------------------------------------------------------------------- procedural


def _smooth_noise(rng: np.random.Generator, n: int, correlation: float) -> np.ndarray:
    """1-D smooth noise, unit std, correlation length ``correlation`` samples."""
    k = max(1, int(correlation))
    raw = rng.standard_normal(n + 4 * k)
    kernel = np.hanning(4 * k + 1)
    sm = np.convolve(raw, kernel / kernel.sum(), mode="same")[2 * k : 2 * k + n]
    sd = sm.std()
    return sm / sd if sd > 0 else sm


def _contrasting(rng: np.random.Generator, base: float) -> int:
    """A grey level at least 50 levels away from ``base``."""
    lo = np.arange(10, 246)
    ok = lo[np.abs(lo - base) >= 50]
    return int(rng.choice(ok))


def _draw_poster(img, rng, x0, y0, x1, y1, bg_level):
    """A framed rectangle with structured content; every kind has sharp corners."""
    fill = _contrasting(rng, bg_level)
    frame = _contrasting(rng, fill)
    cv2.rectangle(img, (x0, y0), (x1, y1), frame, -1)
    b = max(1, int(rng.integers(1, 4)))
    cv2.rectangle(img, (x0 + b, y0 + b), (x1 - b, y1 - b), fill, -1)
    w, h = x1 - x0 - 2 * b, y1 - y0 - 2 * b
    if w < 6 or h < 6:
        return
    ix0, iy0 = x0 + b, y0 + b
    kind = rng.integers(0, 6)
    ink = _contrasting(rng, fill)
    if kind == 0:  # notice: title block and lines of "text"
        th = max(2, h // 6)
        cv2.rectangle(img, (ix0 + 2, iy0 + 2), (ix0 + int(w * rng.uniform(0.4, 0.9)), iy0 + 2 + th), ink, -1)
        y = iy0 + th + 6
        step = int(rng.integers(4, 7))
        while y + 2 < iy0 + h - 2:
            ln = int(w * rng.uniform(0.3, 0.95))
            cv2.rectangle(img, (ix0 + 3, y), (ix0 + 3 + ln - 6, y + 1), ink, -1)
            y += step
    elif kind == 1:  # checker board / calendar grid
        nx, ny = int(rng.integers(2, 7)), int(rng.integers(2, 6))
        xs = np.linspace(ix0, ix0 + w, nx + 1).astype(int)
        ys = np.linspace(iy0, iy0 + h, ny + 1).astype(int)
        other = _contrasting(rng, ink)
        for i in range(nx):
            for j in range(ny):
                if (i + j) % 2 == 0 or rng.random() < 0.3:
                    cv2.rectangle(
                        img, (xs[i], ys[j]), (xs[i + 1] - 1, ys[j + 1] - 1), ink if (i + j) % 2 else other, -1
                    )
    elif kind == 2:  # picture: a few overlapping rectangles
        for _ in range(int(rng.integers(2, 6))):
            ax, bx = sorted(rng.integers(ix0, ix0 + w, 2))
            ay, by = sorted(rng.integers(iy0, iy0 + h, 2))
            if bx - ax > 2 and by - ay > 2:
                cv2.rectangle(img, (int(ax), int(ay)), (int(bx), int(by)), int(rng.integers(0, 256)), -1)
    elif kind == 3:  # triangles / arrows (corners at odd angles)
        for _ in range(int(rng.integers(1, 4))):
            pts = np.stack([rng.integers(ix0, ix0 + w, 3), rng.integers(iy0, iy0 + h, 3)], axis=1).astype(np.int32)
            cv2.fillPoly(img, [pts], int(rng.integers(0, 256)))
    elif kind == 4:  # clock / sign: a disc with a square in it
        r = max(2, min(w, h) // 2 - 1)
        c = (ix0 + w // 2, iy0 + h // 2)
        cv2.circle(img, c, r, ink, -1)
        s = max(1, int(r * 0.55))
        cv2.rectangle(img, (c[0] - s, c[1] - s // 2), (c[0] + s, c[1] + s // 2), fill, -1)
    else:  # barcode-like vertical stripes of random widths
        x = ix0
        while x < ix0 + w - 1:
            bw = int(rng.integers(1, 6))
            if rng.random() < 0.5:
                cv2.rectangle(img, (x, iy0 + h // 5), (min(x + bw, ix0 + w - 1), iy0 + h - 1 - h // 5), ink, -1)
            x += bw + int(rng.integers(1, 5))


def procedural_strip(length_m: float, params, seed: int = 0) -> np.ndarray:
    """A seeded, non-repeating wallpaper strip ``length_m`` long.

    ``params`` is a :class:`~hippomap.sim.params.TextureParams`. Returns uint8
    (rows, columns) with row 0 at the top of the wall. Drawn in layers from one random stream:
    the panels, their seams, the skirting and dado rail, the doors, cabinets and posters, and
    the small fittings between them.
    """
    if not np.isfinite(length_m) or length_m <= 0:
        raise InputError(f"texture strip length {length_m!r} m must be finite and > 0")
    rng = np.random.default_rng(seed)
    wall = _Wall(
        rows=params.rows,
        width=max(4, int(np.ceil(length_m * params.texels_per_m)) + 2),
        tpm=params.texels_per_m,
        height_m=params.wall_height_m,
    )
    img, edges, panel, levels = _panels(rng, wall, length_m)
    _panel_seams(img, rng, wall, edges, panel, levels)
    _skirting_and_rail(img, rng, wall)
    _features(img, rng, wall, params.feature_spacing_m)
    _fittings(img, rng, wall)
    return img


@dataclass(frozen=True)
class _Wall:
    """The strip's size: ``rows`` texels of wall height (``height_m`` metres) by ``width`` texels of wall
    length, ``tpm`` texels per metre."""

    rows: int
    width: int
    tpm: float
    height_m: float

    def row(self, h_m: float) -> int:
        """The texture row at wall height ``h_m`` metres (row 0 at the top of the wall)."""
        return int(np.clip(round((self.height_m - h_m) * self.tpm), 0, self.rows - 1))


def _panels(rng: np.random.Generator, wall: _Wall, length_m: float):
    """The base layer: panels 1.2-4.5 m wide of piecewise-constant grey with a slow modulation along the wall, a
    vertical gradient and pixel noise. Returns the image, the panel edges (texels), each column's panel and the
    panels' grey levels."""
    W, R, tpm = wall.width, wall.rows, wall.tpm
    gaps = rng.uniform(1.2, 4.5, size=int(length_m / 1.2) + 2) * tpm
    edges = np.concatenate([[0], np.cumsum(gaps)]).astype(np.int64)
    panel = np.searchsorted(edges, np.arange(W), side="right") - 1
    levels = rng.uniform(70, 200, size=panel.max() + 1)
    base = levels[panel] + 12 * _smooth_noise(rng, W, 2 * tpm)
    vert = np.linspace(-8, 8, R)[:, None] * rng.choice([-1, 1])
    img = base[None, :] + vert + rng.normal(0, 3.0, size=(R, W))
    return np.clip(img, 0, 255).astype(np.uint8), edges, panel, levels


def _panel_seams(
    img: np.ndarray, rng: np.random.Generator, wall: _Wall, edges: np.ndarray, panel: np.ndarray, levels: np.ndarray
) -> None:
    """Thin dark or bright vertical lines at most panel edges."""
    for e in edges[1:-1]:
        if e < wall.width - 2 and rng.random() < 0.7:
            cv2.rectangle(
                img,
                (int(e), 0),
                (int(e) + 1, wall.rows - 1),
                _contrasting(rng, levels[min(len(levels) - 1, panel[e])]),
                -1,
            )


def _skirting_and_rail(img: np.ndarray, rng: np.random.Generator, wall: _Wall) -> None:
    """A dark or bright skirting board along the floor and a dado rail at 1 m, with breaks."""
    skirt = wall.row(0.10)
    sk_level = int(rng.uniform(20, 60)) if rng.random() < 0.5 else int(rng.uniform(200, 240))
    img[skirt:, :] = sk_level
    rail = wall.row(1.0)
    x = 0
    while x < wall.width:
        run = int(rng.uniform(2, 8) * wall.tpm)
        if rng.random() < 0.4:
            cv2.rectangle(
                img,
                (x, rail),
                (min(wall.width - 1, x + run), rail + max(1, int(0.03 * wall.tpm))),
                _contrasting(rng, 128),
                -1,
            )
        x += run


def _features(img: np.ndarray, rng: np.random.Generator, wall: _Wall, spacing_m: float) -> None:
    """Doors from the floor, cabinets on it and posters or notices on the wall, about ``spacing_m`` apart."""
    tpm = wall.tpm
    pos = 0.3 * tpm
    while True:
        pos += rng.exponential(spacing_m * tpm) + 0.1 * tpm
        if pos >= wall.width - 4:
            break
        x0 = int(pos)
        bg = float(img[wall.row(1.2), x0])
        if rng.random() < 0.15:
            pos = _draw_door(img, rng, wall, x0, bg) + 0.2 * tpm
        elif rng.random() < 0.25:
            pos = _draw_cabinet(img, rng, wall, x0, bg) + 0.1 * tpm
        else:  # poster / notice / picture anywhere on the wall
            w = int(rng.uniform(0.2, 1.1) * tpm)
            h_m = rng.uniform(0.2, 0.9)
            bottom = rng.uniform(0.15, max(0.2, wall.height_m - 0.1 - h_m))
            x1 = min(wall.width - 2, x0 + w)
            y0, y1 = wall.row(bottom + h_m), wall.row(bottom)
            if x1 - x0 >= 4 and y1 - y0 >= 4:
                _draw_poster(img, rng, x0, y0, x1, y1, bg)
            pos = x0 + w * rng.uniform(0.3, 1.0)


def _draw_door(img: np.ndarray, rng: np.random.Generator, wall: _Wall, x0: int, bg: float) -> int:
    """A door from the floor at column ``x0``, with its frame, often a window, and a handle. Returns its right
    edge."""
    R = wall.rows
    dw = int(rng.uniform(0.8, 1.0) * wall.tpm)
    x1 = min(wall.width - 2, x0 + dw)
    top = wall.row(rng.uniform(1.95, 2.2))
    door = _contrasting(rng, bg)
    cv2.rectangle(img, (x0 - 2, top - 2), (x1 + 2, R - 1), _contrasting(rng, door), -1)
    cv2.rectangle(img, (x0, top), (x1, R - 1), door, -1)
    if rng.random() < 0.5:  # window in the door
        cv2.rectangle(img, (x0 + dw // 4, top + dw // 5), (x1 - dw // 4, top + dw), _contrasting(rng, door), -1)
    hx = x1 - max(2, dw // 8) if rng.random() < 0.5 else x0 + max(2, dw // 8)
    hy = wall.row(1.0)
    cv2.rectangle(img, (hx - 2, hy - 1), (hx + 2, hy + 2), _contrasting(rng, door), -1)
    return x1


def _draw_cabinet(img: np.ndarray, rng: np.random.Generator, wall: _Wall, x0: int, bg: float) -> int:
    """A cabinet or radiator standing on the floor at column ``x0``: drawers or doors with handles. Returns its
    right edge."""
    R = wall.rows
    w = int(rng.uniform(0.4, 1.2) * wall.tpm)
    x1 = min(wall.width - 2, x0 + w)
    top = wall.row(rng.uniform(0.35, 1.0))
    body = _contrasting(rng, bg)
    line = _contrasting(rng, body)
    cv2.rectangle(img, (x0, top), (x1, R - 1), line, -1)
    cv2.rectangle(img, (x0 + 1, top + 1), (x1 - 1, R - 2), body, -1)
    n = int(rng.integers(1, 5))
    ys = np.linspace(top, R - 1, n + 1).astype(int)
    split = rng.random() < 0.5
    for k in range(n):
        cv2.rectangle(img, (x0, ys[k]), (x1, ys[k] + 1), line, -1)
        hy = (ys[k] + ys[k + 1]) // 2
        hxs = [(x0 + x1) // 2] if not split else [(3 * x0 + x1) // 4, (x0 + 3 * x1) // 4]
        for hx in hxs:
            cv2.rectangle(img, (hx - 3, hy - 1), (hx + 3, hy + 1), line, -1)
    if split:
        cv2.rectangle(img, ((x0 + x1) // 2, top), ((x0 + x1) // 2 + 1, R - 1), line, -1)
    return x1


def _fittings(img: np.ndarray, rng: np.random.Generator, wall: _Wall) -> None:
    """Small fittings (sockets, switches, signs) between the larger features."""
    tpm = wall.tpm
    pos = rng.exponential(0.8 * tpm)
    while pos < wall.width - 8:
        x0 = int(pos)
        sz = int(rng.uniform(0.05, 0.12) * tpm) + 2
        y1 = wall.row(rng.choice([rng.uniform(0.2, 0.45), rng.uniform(0.9, 1.3)]))
        lv = _contrasting(rng, float(img[max(0, y1 - 1), x0]))
        cv2.rectangle(img, (x0, y1 - sz), (min(wall.width - 1, x0 + sz), y1), lv, -1)
        pos += rng.exponential(0.8 * tpm) + sz


# --------------------------------------------------------------------------- photos


def load_photos(folder: str | Path) -> list[np.ndarray]:
    """All images of a folder as grey uint8 arrays, sorted by file name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"texture folder {folder} does not exist")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if not files:
        raise InputError(f"texture folder {folder} holds no {'/'.join(PHOTO_SUFFIXES)} images")
    out = []
    for p in files:
        im = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if im is None or im.shape[0] < 4 or im.shape[1] < 4:
            raise InputError(f"texture image {p} cannot be read as an image")
        out.append(im)
    return out


def photo_strip(length_m: float, params, seed: int = 0) -> np.ndarray:
    """A strip made of the photos in ``params.source``, laid side by side in a seeded
    order, each randomly cropped, flipped, rescaled and re-exposed. If the walls are
    longer than the photo set the photos repeat (with different crops); with
    ``params.photo_overlay`` procedural posters are drawn over them so places stay
    distinguishable. ``params.photo_count`` keeps only the first photos of the folder."""
    if not np.isfinite(length_m) or length_m <= 0:
        raise InputError(f"texture strip length {length_m!r} m must be finite and > 0")
    photos = load_photos(params.source)[: params.photo_count]
    rng = np.random.default_rng(seed)
    R = params.rows
    W = max(4, int(np.ceil(length_m * params.texels_per_m)) + 2)
    pieces, total = [], 0
    order = rng.permutation(len(photos))
    k = 0
    while total < W:
        if k == len(order):
            order, k = rng.permutation(len(photos)), 0
        im = photos[order[k]]
        k += 1
        h, w = im.shape
        cw = max(4, int(w * rng.uniform(0.6, 1.0)))
        ch = max(4, int(h * rng.uniform(0.75, 1.0)))
        cx = int(rng.integers(0, w - cw + 1))
        cy = int(rng.integers(0, h - ch + 1))
        crop = im[cy : cy + ch, cx : cx + cw]
        if rng.random() < 0.5:
            crop = crop[:, ::-1]
        new_w = max(4, int(round(cw * R / ch * rng.uniform(0.8, 1.25))))
        crop = cv2.resize(np.ascontiguousarray(crop), (new_w, R), interpolation=cv2.INTER_AREA)
        crop = np.clip(crop.astype(np.float32) * rng.uniform(0.8, 1.2) + rng.uniform(-20, 20), 0, 255)
        pieces.append(crop.astype(np.uint8))
        total += new_w
    img = np.ascontiguousarray(np.concatenate(pieces, axis=1)[:, :W])
    if params.photo_overlay:
        tpm = params.texels_per_m
        pos = 0.3 * tpm
        while True:
            pos += rng.exponential(2.0 * params.feature_spacing_m * tpm) + 0.3 * tpm
            if pos >= W - 4:
                break
            x0 = int(pos)
            w = int(rng.uniform(0.2, 0.8) * tpm)
            y0 = int(rng.uniform(0.1, 0.6) * R)
            y1 = min(R - 2, y0 + int(rng.uniform(0.15, 0.4) * R))
            x1 = min(W - 2, x0 + w)
            if x1 - x0 >= 4 and y1 - y0 >= 4:
                _draw_poster(img, rng, x0, y0, x1, y1, float(img[(y0 + y1) // 2, x0]))
            pos = x1
    return img


def make_strip(length_m: float, params, seed: int = 0) -> np.ndarray:
    """Procedural or photo strip, as ``params.source`` says."""
    if params.source == "procedural":
        return procedural_strip(length_m, params, seed)
    return photo_strip(length_m, params, seed)
