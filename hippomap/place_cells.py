"""Place cells: the iterative grid-cell -> place-cell model of the paper's §2.3.2 (spec §3).

:class:`PlaceCells` — each grid cell's rate matrix G_n passes the window comparator of Eq. 9,
``MB_n = 1[|G_n - T_n| <= Delta T / 2]`` (T_n = the cell's current discharge), and the position matrix
is multiplied element-wise by one MB_n after another (Eq. 10), ``POS <- POS * MB_n``. After every product
the variances S_x, S_y of the coordinates of the ones are tested; when both are below T_s a single place
field (:class:`PlaceField`) has formed and its centroid is the local position. If a product would be
empty, that MB_n is skipped (spec §3 decision); if the cells run out first there is no place field.
The pathway that drives the cells (path integration, phase reset, the discharges T_n) is
:mod:`hippomap.spatial_pathway`; the step-by-step record of one iteration, for figures, is
:mod:`hippomap.iteration_record`.

**Fast, exact iteration.** The literal algorithm multiplies whole N x N matrices (801^2 at the defaults)
at every iteration. :meth:`PlaceCells.localise` computes only where the field can still be: the ones of
the first MB_n are a contiguous slice of that cell's argsort (bounds from the cumulative level histogram,
no matrix scan), and every further MB_n is evaluated only at the surviving candidate indices (gather +
compare). The variance test is skipped while the candidate set is provably too large to pass it
(:func:`max_single_field_count`, a lattice-packing bound), and it is done in exact integer arithmetic, so
the result — field, centroid, iteration count — is identical to the literal full-matrix product
(:func:`localise_literal`, kept as the reference; equality is tested).

**Iteration order** (``SpatialConfig.iteration_order``). The paper iterates n = 1, 2, ... (``"cyclic"``;
our cell index cycles through the modules). The default ``"narrowest_first"`` applies the MB_n in
ascending order of their number of ones (ties by cell index): the product is the same set algebra, but
it needs fewer iterations and the first candidate set is ~3x smaller. Because the stop test runs after
every product, the order changes the outcome slightly (the field at which the test first passes), so
both the fast and the literal implementations honour the same order.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .config import SpatialConfig
from .errors import InputError
from .grid_cells import LEVELS, GridCells, RateTables

_FP_SLACK = 1e-9  # levels; absorbs rounding of T * LEVELS / g_max (1.5e-14 g_max)
_RECENT_RESULTS = 16  # results of PlaceCells.localise remembered per instance (see localise)
_BOUND_MIN = np.array([[0.0], [-1.0]])  # clip bounds of [lo; hi] (see _window_bounds)
_BOUND_MAX = np.array([[LEVELS + 1.0], [float(LEVELS)]])


# -- shared pieces of the two implementations ---------------------------------------------------------


def window_levels(T: np.ndarray, cfg: SpatialConfig) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 9 window ``[T - Delta T/2, T + Delta T/2]`` as inclusive integer level bounds (lo, hi), int64.

    ``lo`` is clipped to [0, LEVELS + 1] and ``hi`` to [-1, LEVELS]; ``lo > hi`` means an empty window.
    """
    b = _window_bounds(np.asarray(T, dtype=float), cfg, _signed_scale(cfg))
    return b[0], b[1]


def _signed_scale(cfg: SpatialConfig) -> np.ndarray:
    """``[[-LEVELS / g_max], [LEVELS / g_max]]``, the factor of :func:`_window_bounds`."""
    scale = LEVELS / cfg.g_max
    return np.array([[-scale], [scale]])


def _window_bounds(t: np.ndarray, cfg: SpatialConfig, signed_scale: np.ndarray) -> np.ndarray:
    """(2, n) int64 array ``[lo; hi]`` of :func:`window_levels`, in a few ufunc calls on one array.

    Per call this is the fixed cost of every localisation, so both bounds are computed together. It
    is exact: with x = T LEVELS / g_max, ``lo = clip(ceil((x - h) - s), 0, LEVELS + 1)`` is computed as
    ``-floor((-x + h) + s)`` because ceil(a) = -floor(-a) and IEEE rounding is symmetric (fl(-a) = -fl(a),
    so ``(-x + h) + s`` is bit for bit ``-((x - h) - s)``); ``hi = clip(floor((x + h) + s), -1, LEVELS)``
    as written. Clipping before the cast keeps huge |T| in range.
    """
    y = t * signed_scale  # [-x; x]: fl(-a b) = -fl(a b)
    y += 0.5 * cfg.window * LEVELS
    y += _FP_SLACK
    np.floor(y, out=y)
    np.negative(y[0], out=y[0])
    np.maximum(y, _BOUND_MIN, out=y)
    np.minimum(y, _BOUND_MAX, out=y)
    return y.astype(np.int64)


def iteration_order(counts: np.ndarray, mode: str) -> np.ndarray:
    """Order in which the MB_n are applied: by ascending number of ones (stable) or by cell index."""
    if mode == "cyclic":
        return np.arange(len(counts))
    return np.argsort(np.asarray(counts), kind="stable")


def stop_threshold(cfg: SpatialConfig, resolution: float) -> float:
    """T_s in squared grid units."""
    return cfg.variance_threshold_m2 / resolution**2


def is_single_field(n: int, sx: int, sxx: int, sy: int, syy: int, tau: float) -> bool:
    """S_x < T_s and S_y < T_s (population variances), exactly: n Sxx - Sx^2 < tau n^2 on Python ints."""
    n2 = tau * n * n
    return (n * sxx - sx * sx) < n2 and (n * syy - sy * sy) < n2


@lru_cache(maxsize=32)
def max_single_field_count(tau: float) -> int:
    """Largest number of ones for which S_x < tau and S_y < tau (grid units) is still possible.

    For n distinct lattice points, the k-th closest to any centre lies at least sqrt(k/pi) - sqrt(2)/2 away
    (at most pi (R + sqrt(2)/2)^2 lattice points lie within R: their unit squares fit in that disc), so
    n (S_x + S_y) >= sum_k max(0, sqrt(k/pi) - sqrt(2)/2)^2 =: B(n). B(n)/n is non-decreasing; passing the
    test needs S_x + S_y < 2 tau, so any n with B(n)/n >= 2 tau fails it and need not be tested.
    """
    limit = 2.0 * tau * (1.0 + 1e-6)  # conservative: never skip a set that could pass
    size = 1024
    while True:
        k = np.arange(1, size + 1, dtype=float)
        b = np.cumsum(np.maximum(0.0, np.sqrt(k / np.pi) - math.sqrt(0.5)) ** 2) / k
        over = np.flatnonzero(b >= limit)
        if over.size:
            return int(over[0])  # counts 1 ... over[0] may pass (index over[0] is count over[0] + 1)
        size *= 4


@dataclass(frozen=True, eq=False)
class PlaceField:
    """A single place field on the position matrix, stored sparsely.

    ``indices`` are the sorted flat indices ``iy * N + ix`` of the ones of POS (position ``(ix, iy) delta``
    in local metres). ``iterations`` counts the products of Eq. 10 applied, ``skipped`` the MB_n skipped
    because the product would have been empty; ``cells`` lists the cells applied, in order.
    """

    indices: np.ndarray
    size: int
    resolution: float
    centroid: tuple[float, float]
    variance: tuple[float, float]
    iterations: int
    skipped: int
    cells: tuple[int, ...]

    def __len__(self) -> int:
        return int(self.indices.size)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.size, self.size)

    def coordinates(self) -> np.ndarray:
        """Local positions (metres) of the field's points, (n, 2) as (x, y)."""
        iy, ix = np.divmod(self.indices, self.size)
        return np.column_stack([ix, iy]) * self.resolution

    def dense(self) -> np.ndarray:
        """The position matrix POS as a dense bool (N, N) array (rows = y, columns = x)."""
        out = np.zeros(self.size * self.size, dtype=bool)
        out[self.indices] = True
        return out.reshape(self.shape)

    @classmethod
    def _from_indices(cls, flat, size, resolution, iterations, skipped, cells) -> "PlaceField":
        flat = np.sort(np.asarray(flat, dtype=np.int64))
        return cls._from_moments(flat, *_moments(flat, size), size, resolution, iterations, skipped, cells)

    @classmethod
    def _from_moments(
        cls, flat: np.ndarray, sx: int, sxx: int, sy: int, syy: int, size, resolution, iterations, skipped, cells
    ) -> "PlaceField":
        """The field of the sorted int64 flat indices ``flat`` (owned: frozen here) whose coordinate sums
        (:func:`_moments`) are already known, e.g. from the stop test (integer sums do not depend on the
        order of the points, so the unsorted candidate set gives the same values)."""
        n = int(flat.size)
        d2 = resolution * resolution
        flat.flags.writeable = False
        return cls(
            indices=flat,
            size=size,
            resolution=resolution,
            centroid=(sx / n * resolution, sy / n * resolution),
            variance=((n * sxx - sx * sx) / (n * n) * d2, (n * syy - sy * sy) / (n * n) * d2),
            iterations=iterations,
            skipped=skipped,
            cells=tuple(cells),
        )


def _moments(flat: np.ndarray, size: int) -> tuple[int, int, int, int]:
    """Exact coordinate sums (Sx, Sxx, Sy, Syy) of the flat indices ``iy * size + ix``, as Python ints.

    int64 throughout (|ix|, |iy| < 46341 since flat indices fit int32, so no product or sum overflows);
    integer addition is associative, so the order of the points and of the reduction does not matter.
    """
    iy, ix = np.divmod(flat, np.int64(size))
    return int(np.add.reduce(ix)), int(ix.dot(ix)), int(np.add.reduce(iy)), int(iy.dot(iy))


def check_rates(T, n_cells: int) -> np.ndarray:
    """The current discharges T as a float (n_cells,) array; an InputError names a wrong shape or a non-finite value."""
    t = np.asarray(T, dtype=float)
    if t.shape != (n_cells,):
        raise InputError(f"current discharges T must have shape ({n_cells},), got {t.shape}")
    if not np.logical_and.reduce(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"current discharge T[{bad}] = {t[bad]} is not finite")
    return t


def resolve_tables(source) -> RateTables:
    """The rate tables of a :class:`GridCells` (built on first use) or the given :class:`RateTables`."""
    return source.tables if isinstance(source, GridCells) else source


# -- the iterative model ----------------------------------------------------------------------------------


class PlaceCells:
    """The iterative grid-cell -> place-cell model (Eq. 9-10 with the variance stop test of §2.3.2).

    ``source`` is a :class:`GridCells` (its rate tables are built on first use) or ready
    :class:`RateTables`; ``cfg`` defaults to the grid cells' config.
    """

    def __init__(self, source: GridCells | RateTables, cfg: SpatialConfig | None = None):
        if cfg is None:
            if not isinstance(source, GridCells):
                raise ValueError("cfg is required when PlaceCells is built from RateTables")
            cfg = source.cfg
        self.cfg = cfg
        self._source = source
        self._prepared: _Prepared | None = None
        self._recent: OrderedDict[bytes, PlaceField | None] = OrderedDict()  # T bytes -> result, LRU

    @property
    def tables(self) -> RateTables:
        return resolve_tables(self._source)

    def _prepare(self, t: RateTables) -> "_Prepared":
        """The per-call constants of :meth:`localise` for tables ``t``, computed once (tables never change)."""
        p = self._prepared
        if p is None or p.tables is not t:
            p = self._prepared = _Prepared(t, self.cfg)
        return p

    def localise(self, T) -> PlaceField | None:
        """Run the iteration for current discharges T (n_cells,) in rate units; None if no single field forms.

        The result is a pure function of T (tables and config are fixed), and fields are immutable, so the
        last :data:`_RECENT_RESULTS` distinct T are remembered by their bytes and a repeated T returns the
        same result without iterating. T repeats whenever the robot comes back to the same grid point;
        without rate noise every phase reset does (it puts the robot at the centre of the coding area:
        about a third of the steps on a typical run).
        """
        p = self._prepare(self.tables)
        t = check_rates(T, p.n_cells)
        key = t.tobytes()
        recent = self._recent
        if key in recent:  # (one instance serves one pathway: no concurrent use)
            recent.move_to_end(key)
            return recent[key]
        field = self._iterate(p, t)
        recent[key] = field
        if len(recent) > _RECENT_RESULTS:
            recent.popitem(last=False)
        return field

    def _iterate(self, p: "_Prepared", T: np.ndarray) -> PlaceField | None:
        """The iteration proper, for checked discharges T.

        Per call: the window bounds of all cells and their histogram counts are a handful of vectorised
        operations on (2, n_cells) arrays; the loop then reads Python lists. The first applied MB_n is a
        slice of its cell's argsort, every later one a gather at the surviving candidates (``take`` with
        ``mode="wrap"``: the indices are in range, so it only skips the bounds check). The candidate
        order is irrelevant to the result (the field is sorted, the moments are exact integer sums).
        """
        b = _window_bounds(T, self.cfg, p.signed_scale)  # [lo; hi]
        at = p.cum_flat.take(b + p.cum_offsets)  # [cum[n, lo_n]; cum[n, hi_n + 1]]
        counts = at[1] - at[0]  # >= 0: lo <= hi + 1 always (ceil(a) - 1 <= floor(b) for a <= b), cum rises
        lo_l, hi_l = b.tolist()
        start_l, stop_l = at.tolist()
        counts_l = counts.tolist()
        tau, n_max, size = p.tau, p.n_max, p.size
        cand = None  # None: POS is still all ones
        iterations = skipped = 0
        applied: list[int] = []
        for n in iteration_order(counts, self.cfg.iteration_order).tolist():
            if counts_l[n] == 0:  # MB_n is all zeros: the product would be empty
                skipped += 1
                continue
            if cand is None:
                new = p.order[n, start_l[n] : stop_l[n]]
            else:
                lo_n = lo_l[n]
                v = p.levels[n].take(cand, mode="wrap")
                keep = np.subtract(v, lo_n, dtype=np.uint16) <= hi_l[n] - lo_n  # 0 <= lo_n <= hi_n <= LEVELS
                new = cand[keep.nonzero()[0]]
                if new.size == 0:
                    skipped += 1
                    continue
            cand = new
            iterations += 1
            applied.append(n)
            m = new.size
            if m > n_max:
                continue
            if m == 1:  # one point: zero variances, the test is 0 < tau
                iy, ix = divmod(int(new[0]), size)
                if not 0.0 < tau:
                    continue
                flat = np.array([iy * size + ix], dtype=np.int64)
                return PlaceField._from_moments(
                    flat, ix, ix * ix, iy, iy * iy, size, p.resolution, iterations, skipped, applied
                )
            if _spread_fails(new, m, size, tau):
                continue
            mom = _moments(new, size)
            if is_single_field(m, mom[0], mom[1], mom[2], mom[3], tau):
                flat = new.astype(np.int64)
                flat.sort()
                return PlaceField._from_moments(flat, *mom, size, p.resolution, iterations, skipped, applied)
        return None


class _Prepared:
    """Constants of :meth:`PlaceCells.localise` for one set of tables and one config."""

    def __init__(self, t: RateTables, cfg: SpatialConfig):
        self.tables = t
        self.n_cells = t.n_cells
        self.levels, self.order, self.size, self.resolution = t.levels, t.order, t.size, t.resolution
        self.cum_flat = t.cum.reshape(-1)
        row = np.arange(t.n_cells, dtype=np.int64) * t.cum.shape[1]
        self.cum_offsets = np.stack([row, row + 1])  # [lo; hi] + cum_offsets = flat [n, lo_n]; [n, hi_n + 1]
        self.signed_scale = _signed_scale(cfg)
        self.tau = stop_threshold(cfg, t.resolution)
        self.n_max = max_single_field_count(self.tau)


def _spread_fails(flat: np.ndarray, m: int, size: int, tau: float) -> bool:
    """True if the m >= 2 points of ``flat`` certainly fail the stop test, from their y range alone.

    Two points R apart on y give ``n Syy - Sy^2 = n^2 S_y >= n R^2 / 2``, so R^2 >= 2 tau m (1 + 1e-6)
    makes the exact test's y part fail (its right side ``tau n n`` is within 2 ulp of tau n^2); the margin
    covers the rounding of this float bound. iy is monotone in the flat index, so R comes from min and max.
    """
    r = int(np.maximum.reduce(flat)) // size - int(np.minimum.reduce(flat)) // size
    return r * r >= 2.0 * tau * m * (1.0 + 1e-6)


def localise_literal(source: GridCells | RateTables, T, cfg: SpatialConfig | None = None) -> PlaceField | None:
    """Reference: the literal iteration on full matrices (Eq. 9 on every G_n, Eq. 10 on the whole POS).

    Same window bounds, order and exact variance test as :meth:`PlaceCells.localise`; used by the tests
    (equality) and by ``bench/bench_spatial.py`` (speed-up).
    """
    cfg = cfg or source.cfg  # type: ignore[union-attr]  # a RateTables source needs cfg given (as before)
    t = resolve_tables(source)
    T = check_rates(T, t.n_cells)
    lo, hi = window_levels(T, cfg)
    lo, hi = lo.tolist(), hi.tolist()  # Python ints: compared to the uint16 matrices without up-casting them
    G = t.levels
    mb = None
    if cfg.iteration_order == "cyclic":
        order = iteration_order(np.zeros(t.n_cells), "cyclic")
    else:
        mb = [(G[n] >= lo[n]) & (G[n] <= hi[n]) for n in range(t.n_cells)]
        order = iteration_order(np.array([m.sum() for m in mb]), cfg.iteration_order)
    tau = stop_threshold(cfg, t.resolution)
    pos = np.ones(G.shape[1], dtype=bool)
    iterations = skipped = 0
    applied = []
    for n in order:
        mb_n = mb[n] if mb is not None else (G[n] >= lo[n]) & (G[n] <= hi[n])
        prod = pos & mb_n
        if not prod.any():
            skipped += 1
            continue
        pos = prod
        iterations += 1
        applied.append(int(n))
        iy, ix = np.divmod(np.flatnonzero(pos), t.size)
        if is_single_field(int(ix.size), int(ix.sum()), int((ix * ix).sum()), int(iy.sum()), int((iy * iy).sum()), tau):
            return PlaceField._from_indices(np.flatnonzero(pos), t.size, t.resolution, iterations, skipped, applied)
    return None


def noise_free_discharges(source: GridCells | RateTables, cfg: SpatialConfig, local) -> np.ndarray:
    """``T_n = g_n(q(r_loc))`` without noise at the local position ``local`` (metres in the coding area)."""
    t = resolve_tables(source)
    loc = np.asarray(local, dtype=float)
    if loc.shape != (2,):
        raise InputError(f"local position must be 2 finite numbers, got {local!r}")
    x, y = loc.tolist()
    if not (math.isfinite(x) and math.isfinite(y)):
        raise InputError(f"local position must be 2 finite numbers, got {local!r}")
    # Python floats: the same IEEE division, and round() is round-half-even like np.rint; clipping the
    # integers equals clipping the integral floats.
    top = t.size - 1
    ix = min(max(round(x / t.resolution), 0), top)
    iy = min(max(round(y / t.resolution), 0), top)
    return t.levels[:, iy * t.size + ix] * (cfg.g_max / LEVELS)
