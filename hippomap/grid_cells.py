"""Grid cells: hexagonal firing-rate maps over the local coding area (paper §2.3.1, Eq. 6-8; spec §3).

A grid cell fires on a triangular lattice of fields. The paper (Eq. 6) writes its rate as a sum
of three plane waves 60 degrees apart::

    g_n(r) = 2/3 g_max [ 1/3 sum_i cos(k_i . (r - r0_n)) + 1/2 ]        in [0, g_max]
    k_i    = |k| (cos(theta + (i-1) pi/3), sin(theta + (i-1) pi/3)),     i = 1, 2, 3

**Deviation from the paper (spec §3, §6.5).** Eq. 7-8 use ``|k_i|/sqrt(2)`` with ``|k_i| = 2 pi/lambda``;
the resulting lattice has spacing ``4 lambda / sqrt(6) = 1.63 lambda``, so lambda would not be the grid
spacing the paper says it is. We use ``|k| = 4 pi / (sqrt(3) lambda)``, for which the distance between
neighbouring firing fields is exactly lambda (lattice vectors of length lambda at theta + 30 deg + m 60 deg;
tested in ``tests/test_grid_cells.py``).

Cells: ``n_modules`` modules, each with its own orientation theta ~ U[0, 2 pi) and spacing
lambda ~ U[spacing_min, spacing_max]; ``cells_per_module`` cells per module, each with its own phase
r0 ~ U([0, L] x [0, L]). Cell ``n`` belongs to module ``n % n_modules``, so iterating over cells in
index order cycles through the modules (spec §3, "cycling through the modules").

Rate matrices (the "discharge rate matrix" M(X, Y) of §2.3.1) are sampled on the (N x N) grid of
points ``(i delta, j delta)``, ``N = L/delta + 1`` (801 x 801 at the defaults). They are stored
**quantised to uint16 levels** (``level = rint(65535 g / g_max)``, step 1.5e-5 g_max, far below the
comparator window of 0.1 g_max) together with the two indexes the fast place-cell iteration needs:
per cell the argsort of its levels (int32) and the cumulative level histogram (int32). The tables
are built lazily, read-only, and shared by every ``GridCells`` with the same geometry and seed
(a server's sessions share one copy). Memory at the defaults (32 cells, 801^2):
levels 41 MB + argsort 82 MB + histogram 8.4 MB = 132 MB (``RateTables.nbytes``).

**Across processes** (a Ray actor or a mapper process per session, a command per run), each process would
build its own copy: about 1.4 s of CPU and 132 MB at the defaults. When the environment variable
``HIPPOMAP_TABLE_CACHE`` names a folder, tables of at least :data:`DISK_CACHE_MIN_ENTRIES` are kept there as
``.npy`` files (written once, atomically) and read back memory-mapped and read-only: the processes of one
machine then share one copy in the page cache, and a new one has its tables in milliseconds. The files are
named after everything the tables depend on (geometry, seed, :data:`LEVELS`, numpy's version); the
:data:`DISK_CACHE_KEEP` most recently used sets are kept. A file that cannot be read or written is
rebuilt in memory, as without the cache (with a warning).
"""

from __future__ import annotations

import hashlib
import os
import threading
import warnings
import weakref
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import SpatialConfig

#: number of quantisation steps of a rate matrix: levels 0 ... LEVELS map to 0 ... g_max
LEVELS = 65535
#: the environment variable naming the folder of the tables' disk cache (unset, empty or "off": none)
TABLE_CACHE_ENV = "HIPPOMAP_TABLE_CACHE"
#: tables of fewer rate-matrix entries (cells x grid points) than this are built in memory, never written:
#: they cost less to build than to write (the defaults have 32 x 801^2 = 20.5 million, 1.4 s to build)
DISK_CACHE_MIN_ENTRIES = 2_000_000
#: table sets kept in the disk cache (the least recently used beyond this are deleted)
DISK_CACHE_KEEP = 4
_DISK_FORMAT = 1  # bump when the files' layout or the tables' computation changes


def wave_number(spacing):
    """|k| for a grid of spacing lambda: 4 pi / (sqrt(3) lambda) (deviation from Eq. 8, see module doc)."""
    return 4.0 * np.pi / (np.sqrt(3.0) * np.asarray(spacing, dtype=float))


@dataclass(frozen=True, eq=False)
class RateTables:
    """Quantised rate matrices of all cells plus the indexes of the fast iteration (read-only, shared).

    ``levels[n]`` is cell n's rate matrix as a flat (N*N,) uint16 array in row-major order
    (flat index ``iy * N + ix``, position ``(ix delta, iy delta)``); ``order[n]`` is its argsort
    (int32, ascending level); ``cum[n, v]`` counts the entries of ``levels[n]`` below level ``v``
    (shape (n_cells, LEVELS + 2)), so the entries with level in [lo, hi] are exactly
    ``order[n, cum[n, lo]:cum[n, hi + 1]]``.
    """

    levels: np.ndarray
    order: np.ndarray
    cum: np.ndarray
    size: int
    resolution: float

    @property
    def n_cells(self) -> int:
        return self.levels.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        return (self.size, self.size)

    @property
    def nbytes(self) -> int:
        return self.levels.nbytes + self.order.nbytes + self.cum.nbytes

    @classmethod
    def from_levels(cls, levels: np.ndarray, resolution: float) -> "RateTables":
        """Build the tables from quantised level matrices (n_cells, N, N) (also used by tests)."""
        levels = np.asarray(levels)
        if levels.ndim != 3 or levels.shape[1] != levels.shape[2]:
            raise ValueError(f"levels must have shape (n_cells, N, N), got {levels.shape}")
        n_cells, size = levels.shape[0], levels.shape[1]
        flat = np.ascontiguousarray(levels.reshape(n_cells, size * size), dtype=np.uint16)
        order = np.empty(flat.shape, dtype=np.int32)
        cum = np.zeros((n_cells, LEVELS + 2), dtype=np.int32)
        for n in range(n_cells):  # one-time setup; radix sort on uint16
            order[n] = np.argsort(flat[n], kind="stable")
            np.cumsum(np.bincount(flat[n], minlength=LEVELS + 1), out=cum[n, 1:])
        for a in (flat, order, cum):
            a.flags.writeable = False
        return cls(levels=flat, order=order, cum=cum, size=size, resolution=float(resolution))


_CACHE_LOCK = threading.Lock()
_CACHE: "weakref.WeakValueDictionary[tuple, RateTables]" = weakref.WeakValueDictionary()
_RECENT: deque = deque(maxlen=1)  # keeps the latest tables alive while no instance holds them


def table_key(cfg: SpatialConfig) -> tuple:
    """Everything the rate tables depend on: two configs with the same key share one copy (in memory, in
    the disk cache, and in a token's memory quota)."""
    return (
        cfg.area_size_m,
        cfg.resolution_m,
        cfg.n_modules,
        cfg.cells_per_module,
        cfg.spacing_min_m,
        cfg.spacing_max_m,
        cfg.seed,
    )


def matrix_size(cfg: SpatialConfig) -> int:
    """N, points per side of the rate matrices: L / delta + 1 (801 at the defaults)."""
    return int(round(cfg.area_size_m / cfg.resolution_m)) + 1


class GridCells:
    """The grid-cell population of the spatial pathway, drawn reproducibly from ``SpatialConfig``."""

    def __init__(self, cfg: SpatialConfig | None = None):
        self.cfg = cfg = cfg or SpatialConfig()
        rng = np.random.default_rng(cfg.seed)
        m, c = cfg.n_modules, cfg.cells_per_module
        self.module_orientation = rng.uniform(0.0, 2.0 * np.pi, m)
        self.module_spacing = rng.uniform(cfg.spacing_min_m, cfg.spacing_max_m, m)
        self._phase = rng.uniform(0.0, cfg.area_size_m, (m * c, 2))
        self.module = np.arange(m * c) % m
        ang = self.orientation[:, None] + np.arange(3)[None, :] * (np.pi / 3.0)
        k = wave_number(self.spacing)[:, None]
        self.wave_vectors = np.stack([k * np.cos(ang), k * np.sin(ang)], axis=-1)  # (n_cells, 3, 2)
        for a in (self.module_orientation, self.module_spacing, self._phase, self.module, self.wave_vectors):
            a.flags.writeable = False
        self._tables: RateTables | None = None

    # -- parameters ---------------------------------------------------------------------------
    @property
    def n_cells(self) -> int:
        return self.module.size

    @property
    def spacing(self) -> np.ndarray:
        """lambda of every cell (metres), shape (n_cells,)."""
        return self.module_spacing[self.module]

    @property
    def orientation(self) -> np.ndarray:
        """theta of every cell (radians), shape (n_cells,)."""
        return self.module_orientation[self.module]

    @property
    def phase(self) -> np.ndarray:
        """r0 of every cell (local metres), shape (n_cells, 2)."""
        return self._phase

    @property
    def size(self) -> int:
        return matrix_size(self.cfg)

    @property
    def resolution(self) -> float:
        return self.cfg.resolution_m

    # -- rates -----------------------------------------------------------------------------------
    def rates(self, points) -> np.ndarray:
        """Eq. 6 at arbitrary local positions (..., 2) in metres -> rates (..., n_cells), float64."""
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (2,):
            raise ValueError(f"points must have shape (..., 2), got {p.shape}")
        d = p[..., None, :] - self._phase  # (..., n_cells, 2)
        arg = np.einsum("...nd,nid->...ni", d, self.wave_vectors)
        return (2.0 / 3.0) * self.cfg.g_max * (np.cos(arg).sum(-1) / 3.0 + 0.5)

    @property
    def tables(self) -> RateTables:
        """The quantised rate matrices and their indexes, built on first use and shared (see module doc)."""
        if self._tables is None:
            key = table_key(self.cfg)
            with _CACHE_LOCK:
                tables = _CACHE.get(key)
                if tables is None:
                    tables = self._disk_or_build(key)
                    _CACHE[key] = tables
                _RECENT.append(tables)
            self._tables = tables
        return self._tables

    def _build(self) -> RateTables:
        return RateTables.from_levels(self._compute_levels(), self.cfg.resolution_m)

    def _disk_or_build(self, key: tuple) -> RateTables:
        """The tables from the disk cache of :data:`TABLE_CACHE_ENV` (written there first if missing), or
        built in memory when no cache is set, the tables are small, or the folder cannot be used."""
        folder = os.environ.get(TABLE_CACHE_ENV)
        n = self.n_cells
        if not folder or folder == "off" or n * self.size * self.size < DISK_CACHE_MIN_ENTRIES:
            return self._build()
        stem = Path(folder) / f"grid-tables-{_disk_key(key)}"
        try:
            tables = _read_tables(stem, n, self.size, self.resolution)
        except (OSError, ValueError) as exc:
            if not isinstance(exc, (FileNotFoundError, NotADirectoryError)):  # not there: written below
                warnings.warn(f"grid-cell table cache {stem}: unreadable ({exc}); rebuilding it", stacklevel=3)
            tables = self._build()
            try:
                _write_tables(stem, tables)
            except OSError as werr:
                warnings.warn(f"grid-cell table cache {stem}: cannot write ({werr}); kept in memory", stacklevel=3)
        return tables

    def _compute_levels(self) -> np.ndarray:
        """Quantised Eq. 6 on the matrix grid, (n_cells, N, N) uint16.

        Separable: cos(a(x) + b(y)) = cos a cos b - sin a sin b, so each cell is one (N x 6) @ (6 x N)
        product instead of 3 N^2 cosines.
        """
        size, delta = self.size, self.resolution
        axis = np.arange(size) * delta
        out = np.empty((self.n_cells, size, size), dtype=np.uint16)
        for n in range(self.n_cells):  # one-time setup
            kx, ky = self.wave_vectors[n, :, 0], self.wave_vectors[n, :, 1]
            a = kx[:, None] * (axis[None, :] - self._phase[n, 0])  # (3, N) over x
            b = ky[:, None] * (axis[None, :] - self._phase[n, 1])  # (3, N) over y
            left = np.concatenate([np.cos(b), -np.sin(b)]).T  # (N_y, 6)
            right = np.concatenate([np.cos(a), np.sin(a)])  # (6, N_x)
            g = left @ right  # then (2/3) (g / 3 + 0.5) = rate / g_max, [iy, ix], in place (same operations)
            g /= 3.0
            g += 0.5
            g *= 2.0 / 3.0
            np.clip(g, 0.0, 1.0, out=g)
            g *= LEVELS
            np.rint(g, out=g)
            out[n] = g
        return out

    def rate_matrix(self, n: int) -> np.ndarray:
        """Cell n's discharge rate matrix M(X, Y) (rows = y, columns = x), float32 in rate units (a copy)."""
        t = self.tables
        return (t.levels[n].reshape(t.shape).astype(np.float32)) * np.float32(self.cfg.g_max / LEVELS)


# -- the disk cache (see the module doc) ------------------------------------------------------------------


def use_table_cache(folder: str | os.PathLike | None) -> None:
    """Keep this process's grid-cell tables in ``folder`` (see the module doc), and those of the processes it
    starts afterwards (the setting is the environment variable :data:`TABLE_CACHE_ENV`); None leaves the
    setting as it is. For a process that runs mappers, e.g. a server's mapper process or Ray actor."""
    if folder is not None:
        os.environ[TABLE_CACHE_ENV] = os.fspath(folder)


_PARTS = ("levels", "order", "cum")


def _disk_key(key: tuple) -> str:
    """A file-name-safe digest of everything the tables depend on."""
    text = repr((_DISK_FORMAT, LEVELS, np.__version__, tuple(float(v) for v in key)))
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _read_tables(stem: Path, n_cells: int, size: int, resolution: float) -> RateTables:
    """The tables of the files ``stem.<part>.npy``, memory-mapped read-only; ValueError if one does not hold
    what the tables must (shape, dtype), FileNotFoundError if one is missing."""
    want = {
        "levels": ((n_cells, size * size), np.uint16),
        "order": ((n_cells, size * size), np.int32),
        "cum": ((n_cells, LEVELS + 2), np.int32),
    }
    arrays = {}
    for part in _PARTS:
        a = np.load(stem.with_name(f"{stem.name}.{part}.npy"), mmap_mode="r", allow_pickle=False)
        shape, dtype = want[part]
        if a.shape != shape or a.dtype != dtype:
            raise ValueError(f"{part} holds {a.dtype} {a.shape}, not {np.dtype(dtype)} {shape}")
        arrays[part] = np.asarray(a)  # a plain read-only array on the mapped file (no copy)
    os.utime(stem.with_name(f"{stem.name}.levels.npy"))  # used now: the eviction keeps it
    return RateTables(size=size, resolution=float(resolution), **arrays)


def _write_tables(stem: Path, tables: RateTables) -> None:
    """Write the tables as ``stem.<part>.npy``, each to a temporary file first and then renamed (a reader
    never sees a partial file); then delete the least recently used sets beyond :data:`DISK_CACHE_KEEP`."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    for part in _PARTS:
        final = stem.with_name(f"{stem.name}.{part}.npy")
        tmp = final.with_name(f"{final.name}.tmp{os.getpid()}")
        try:
            with open(tmp, "wb") as f:
                np.save(f, getattr(tables, part), allow_pickle=False)
            os.replace(tmp, final)
        finally:
            tmp.unlink(missing_ok=True)
    mine = stem.with_name(f"{stem.name}.levels.npy")
    others = [p for p in stem.parent.glob("grid-tables-*.levels.npy") if p != mine]
    others.sort(key=_mtime, reverse=True)
    for old in others[DISK_CACHE_KEEP - 1 :]:  # the set just written stays, whatever the clock's resolution
        base = old.name[: -len(".levels.npy")]
        for part in _PARTS:
            old.with_name(f"{base}.{part}.npy").unlink(missing_ok=True)


def _mtime(path: Path) -> float:
    """When ``path`` was last written or read from the cache; 0 for a file another process just deleted."""
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0
