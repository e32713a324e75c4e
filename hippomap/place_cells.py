"""Place cells: the iterative grid-cell -> place-cell model and the spatial pathway (paper §2.3-2.4; spec §3).

Three layers:

* :class:`PlaceCells` — the iterative model of §2.3.2. Each grid cell's rate matrix G_n passes the
  window comparator of Eq. 9, ``MB_n = 1[|G_n - T_n| <= Delta T / 2]`` (T_n = the cell's current
  discharge), and the position matrix is multiplied element-wise by one MB_n after another (Eq. 10),
  ``POS <- POS * MB_n``. After every product the variances S_x, S_y of the coordinates of the ones are
  tested; when both are below T_s a single place field has formed and its centroid is the local position.
  If a product would be empty, that MB_n is skipped (spec §3 decision); if the cells run out first there
  is no place field.
* :class:`PlaceCode` — what one step hands to the cognitive map: the global place code
  ``p = o + centroid`` (paper §2.4), the heading, and the field.
* :class:`SpatialPathway` — path integration of odometry, the periodic phase reset of §2.4 (re-centre the
  coding area when the robot leaves it), the current discharge ``T_n = g_n(q(r_loc))`` and the place cells.

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
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .config import SpatialConfig
from .errors import InputError
from .geometry import compose, wrap_angle
from .grid_cells import LEVELS, GridCells, RateTables

_STATE_VERSION = 1
_FP_SLACK = 1e-9  # levels; absorbs rounding of T * LEVELS / g_max (1.5e-14 g_max)


# -- shared pieces of the two implementations ---------------------------------------------------------


def window_levels(T: np.ndarray, cfg: SpatialConfig) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 9 window ``[T - Delta T/2, T + Delta T/2]`` as inclusive integer level bounds (lo, hi), int64.

    ``lo`` is clipped to [0, LEVELS + 1] and ``hi`` to [-1, LEVELS]; ``lo > hi`` means an empty window.
    """
    t = np.asarray(T, dtype=float) * (LEVELS / cfg.g_max)
    h = 0.5 * cfg.window * LEVELS
    lo = np.clip(np.ceil(t - h - _FP_SLACK), 0, LEVELS + 1).astype(np.int64)
    hi = np.clip(np.floor(t + h + _FP_SLACK), -1, LEVELS).astype(np.int64)
    return lo, hi


def iteration_order(counts: np.ndarray, mode: str) -> np.ndarray:
    """Order in which the MB_n are applied: by ascending number of ones (stable) or by cell index."""
    if mode == "cyclic":
        return np.arange(len(counts))
    return np.argsort(np.asarray(counts), kind="stable")


def _tau(cfg: SpatialConfig, resolution: float) -> float:
    """T_s in squared grid units."""
    return cfg.variance_threshold_m2 / resolution**2


def _is_single(n: int, sx: int, sxx: int, sy: int, syy: int, tau: float) -> bool:
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
        iy, ix = np.divmod(flat, size)
        n = int(flat.size)
        sx, sy = int(ix.sum()), int(iy.sum())
        sxx, syy = int((ix * ix).sum()), int((iy * iy).sum())
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


def _check_rates(T, n_cells: int) -> np.ndarray:
    t = np.asarray(T, dtype=float)
    if t.shape != (n_cells,):
        raise InputError(f"current discharges T must have shape ({n_cells},), got {t.shape}")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(f"current discharge T[{bad}] = {t[bad]} is not finite")
    return t


def _resolve_tables(source) -> RateTables:
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

    @property
    def tables(self) -> RateTables:
        return _resolve_tables(self._source)

    def localise(self, T) -> PlaceField | None:
        """Run the iteration for current discharges T (n_cells,) in rate units; None if no single field forms."""
        t = self.tables
        T = _check_rates(T, t.n_cells)
        lo, hi = window_levels(T, self.cfg)
        cells = np.arange(t.n_cells)
        counts = np.maximum(t.cum[cells, hi + 1] - t.cum[cells, lo], 0)
        tau = _tau(self.cfg, t.resolution)
        n_max = max_single_field_count(tau)
        size = t.size
        cand = None  # None: POS is still all ones
        iterations = skipped = 0
        applied: list[int] = []
        for n in iteration_order(counts, self.cfg.iteration_order).tolist():
            if counts[n] == 0:  # MB_n is all zeros: the product would be empty
                skipped += 1
                continue
            lo_n, hi_n = int(lo[n]), int(hi[n])
            if cand is None:
                new = t.order[n, t.cum[n, lo_n] : t.cum[n, hi_n + 1]]
            else:
                v = t.levels[n].take(cand)
                keep = np.subtract(v, np.uint16(lo_n), dtype=np.uint16) <= np.uint16(hi_n - lo_n)
                new = cand[keep]
                if new.size == 0:
                    skipped += 1
                    continue
            cand = new
            iterations += 1
            applied.append(n)
            if new.size <= n_max:
                iy, ix = np.divmod(new.astype(np.int64), size)
                if _is_single(int(new.size), int(ix.sum()), int((ix * ix).sum()), int(iy.sum()), int((iy * iy).sum()),
                              tau):
                    return PlaceField._from_indices(new, size, t.resolution, iterations, skipped, applied)
        return None


def localise_literal(source: GridCells | RateTables, T, cfg: SpatialConfig | None = None) -> PlaceField | None:
    """Reference: the literal iteration on full matrices (Eq. 9 on every G_n, Eq. 10 on the whole POS).

    Same window bounds, order and exact variance test as :meth:`PlaceCells.localise`; used by the tests
    (equality) and by ``bench/bench_spatial.py`` (speed-up).
    """
    cfg = cfg or source.cfg  # type: ignore[union-attr]  # a RateTables source needs cfg given (as before)
    t = _resolve_tables(source)
    T = _check_rates(T, t.n_cells)
    lo, hi = window_levels(T, cfg)
    lo, hi = lo.tolist(), hi.tolist()  # Python ints: compared to the uint16 matrices without up-casting them
    G = t.levels
    mb = None
    if cfg.iteration_order == "cyclic":
        order = iteration_order(np.zeros(t.n_cells), "cyclic")
    else:
        mb = [(G[n] >= lo[n]) & (G[n] <= hi[n]) for n in range(t.n_cells)]
        order = iteration_order(np.array([m.sum() for m in mb]), cfg.iteration_order)
    tau = _tau(cfg, t.resolution)
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
        if _is_single(int(ix.size), int(ix.sum()), int((ix * ix).sum()), int(iy.sum()), int((iy * iy).sum()), tau):
            return PlaceField._from_indices(np.flatnonzero(pos), t.size, t.resolution, iterations, skipped, applied)
    return None


# -- the spatial pathway ------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlaceCode:
    """One step's output of the spatial pathway (paper §2.4).

    ``x, y`` is the global place code p = o + centroid (metres), ``theta`` the path-integrated heading
    (radians, wrapped to [-pi, pi)), ``local`` the centroid in the coding area, ``origin`` the area's
    corner o, ``iterations`` the products of Eq. 10 used, ``reset`` whether the phases were reset this
    step, ``field`` the :class:`PlaceField`.
    """

    x: float
    y: float
    theta: float
    local: tuple[float, float]
    origin: tuple[float, float]
    iterations: int
    reset: bool
    field: PlaceField | None = None


def _finite(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} = {value!r} is not a number") from exc
    if not math.isfinite(v):
        raise InputError(f"{name} = {v} is not finite")
    return v


class SpatialPathway:
    """Odometry -> grid-cell phases (path integration + phase reset) -> place code (paper §2.3-2.4; spec §3).

    The pose is integrated in the world frame; the coding area ``[0, L]^2`` has its corner at the
    origin o, initially chosen so that the start pose is at its centre. When the local position
    ``r_loc = r - o`` leaves the area, the grid phases are reset: ``o <- r - (L/2, L/2)`` (§2.4, Fig. 6).
    The current discharges are the rate matrices read at the grid point nearest r_loc,
    ``T_n = g_n(q(r_loc))``, plus optional Gaussian noise ``rate_noise * g_max`` (seeded).
    """

    def __init__(self, cfg: SpatialConfig | None = None, pose=(0.0, 0.0, 0.0)):
        self.cfg = cfg = cfg or SpatialConfig()
        self.grid = GridCells(cfg)
        self.place_cells = PlaceCells(self.grid, cfg)
        p = [_finite(f"pose[{i}]", v) for i, v in enumerate(_triple("pose", pose))]
        self._pose = np.array([p[0], p[1], wrap_angle(p[2])])
        half = 0.5 * cfg.area_size_m
        self._origin = self._pose[:2] - half
        self._rng = np.random.default_rng([cfg.seed, 1])  # T noise; its own stream
        self._resets = 0
        self._steps = 0

    # -- state ----------------------------------------------------------------------------------
    @property
    def pose(self) -> tuple[float, float, float]:
        """Odometric pose (x, y, theta) in the world frame."""
        return (float(self._pose[0]), float(self._pose[1]), float(self._pose[2]))

    @property
    def origin(self) -> tuple[float, float]:
        """Corner o of the current coding area (world metres)."""
        return (float(self._origin[0]), float(self._origin[1]))

    @property
    def resets(self) -> int:
        """Phase resets so far."""
        return self._resets

    @property
    def steps(self) -> int:
        """Odometry steps integrated so far."""
        return self._steps

    def state_dict(self) -> dict:
        """Plain-number snapshot (JSON-serialisable) from which :meth:`from_state` rebuilds this pathway."""
        return {
            "version": _STATE_VERSION,
            "pose": list(self.pose),
            "origin": list(self.origin),
            "resets": self._resets,
            "steps": self._steps,
            "rng": self._rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, cfg: SpatialConfig, state: dict) -> "SpatialPathway":
        """Rebuild a pathway whose future outputs equal those of the one that produced ``state``."""
        try:
            if state["version"] != _STATE_VERSION:
                raise InputError(f"spatial state version {state['version']!r} is not {_STATE_VERSION}")
            out = cls(cfg, pose=state["pose"])
            o = [_finite(f"origin[{i}]", v) for i, v in enumerate(_triple("origin", state["origin"], 2))]
            out._origin = np.array(o)
            out._resets = int(state["resets"])
            out._steps = int(state["steps"])
            out._rng.bit_generator.state = state["rng"]
        except InputError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed spatial state: {exc!r}") from exc
        return out

    # -- stepping -------------------------------------------------------------------------------
    def step_increment(self, dx, dy, dtheta) -> PlaceCode | None:
        """Apply a relative pose increment given in the frame of the previous pose (g2o EDGE_SE2:
        translate by (dx, dy) in that frame, then rotate by dtheta); return the place code or None."""
        inc = (_finite("dx", dx), _finite("dy", dy), _finite("dtheta", dtheta))
        return self._step(inc)

    def step_velocity(self, v, omega, dt) -> PlaceCode | None:
        """Integrate velocities over dt in [ORS] order: theta += omega dt, then r += v dt (cos theta, sin theta).

        Expressed as the increment (v dt cos(omega dt), v dt sin(omega dt), omega dt) in the previous
        frame, so it shares :meth:`step_increment`'s code path.
        """
        v, omega, dt = _finite("v", v), _finite("omega", omega), _finite("dt", dt)
        if dt <= 0:
            raise InputError(f"dt = {dt} must be > 0")
        dth = omega * dt
        return self._step((v * dt * math.cos(dth), v * dt * math.sin(dth), dth))

    def localise(self) -> PlaceCode | None:
        """The place code at the current pose, without moving (e.g. for the first node)."""
        return self._code(reset=False)

    def record(self) -> "IterationRecord":
        """The iteration at the current pose, recorded step by step (:func:`record_iteration`), from the
        noise-free discharges: draws no noise, so the pathway's future outputs are unchanged. Without
        rate noise its field is the one the last step produced."""
        loc = self._pose[:2] - self._origin
        return record_iteration(self.place_cells.tables, noise_free_discharges(self.place_cells.tables, self.cfg, loc),
                                self.cfg)

    def _step(self, inc) -> PlaceCode | None:
        self._pose = compose(self._pose, inc)
        self._steps += 1
        L = self.cfg.area_size_m
        loc = self._pose[:2] - self._origin
        reset = not (0.0 <= loc[0] <= L and 0.0 <= loc[1] <= L)
        if reset:
            self._origin = self._pose[:2] - 0.5 * L
            self._resets += 1
        return self._code(reset)

    def discharges(self) -> np.ndarray:
        """Current discharges T_n = g_n(q(r_loc)) (+ noise), shape (n_cells,). Draws noise if enabled."""
        t = self.place_cells.tables
        loc = self._pose[:2] - self._origin
        ix, iy = np.clip(np.rint(loc / t.resolution), 0, t.size - 1).astype(np.int64)
        T = t.levels[:, iy * t.size + ix] * (self.cfg.g_max / LEVELS)
        if self.cfg.rate_noise > 0:
            T = T + self._rng.normal(0.0, self.cfg.rate_noise * self.cfg.g_max, T.shape)
        return T

    def _code(self, reset: bool) -> PlaceCode | None:
        field = self.place_cells.localise(self.discharges())
        if field is None:
            return None
        cx, cy = field.centroid
        ox, oy = self.origin
        return PlaceCode(
            x=ox + cx,
            y=oy + cy,
            theta=float(self._pose[2]),
            local=(cx, cy),
            origin=(ox, oy),
            iterations=field.iterations,
            reset=reset,
            field=field,
        )


def _triple(name: str, value, n: int = 3):
    try:
        seq = list(value)
    except TypeError as exc:
        raise InputError(f"{name} = {value!r} must be a sequence of {n} numbers") from exc
    if len(seq) != n:
        raise InputError(f"{name} = {value!r} must have {n} values")
    return seq


# -- recording the iteration (on demand; never on the hot path) ---------------------------------------


@dataclass(frozen=True, eq=False)
class IterationStep:
    """One MB_n of Eq. 10 as the iteration met it.

    ``cell`` is n, ``lo``/``hi`` its window in levels (Eq. 9), ``ones`` the number of ones of MB_n,
    ``applied`` False when the product would have been empty (the MB_n was skipped), ``position`` the
    sorted flat indices of the ones of POS after this step (unchanged by a skipped step), ``variance``
    (S_x, S_y) of those ones in m^2, and ``single`` whether the stop test passed here.
    """

    cell: int
    lo: int
    hi: int
    ones: int
    applied: bool
    position: np.ndarray
    variance: tuple[float, float]
    single: bool


@dataclass(frozen=True, eq=False)
class IterationRecord:
    """The whole iteration of one place code: discharges, every MB_n met, and the resulting field.

    Built by :func:`record_iteration`; the binarised matrices themselves are computed on demand
    (:meth:`window_matrix`, :meth:`position_matrix`) from the shared rate tables, so a record costs
    the sparse position sets only.
    """

    T: np.ndarray
    tables: RateTables
    cfg: SpatialConfig
    steps: tuple[IterationStep, ...]
    field: PlaceField | None

    @property
    def size(self) -> int:
        return self.tables.size

    @property
    def resolution(self) -> float:
        return self.tables.resolution

    @property
    def applied(self) -> tuple[IterationStep, ...]:
        """The steps whose MB_n entered the product, in order (``len`` = the field's ``iterations``)."""
        return tuple(s for s in self.steps if s.applied)

    def window_matrix(self, step: IterationStep) -> np.ndarray:
        """MB_n of ``step`` (Eq. 9) as a dense bool (N, N) matrix (rows = y, columns = x)."""
        g = self.tables.levels[step.cell]
        return ((g >= step.lo) & (g <= step.hi)).reshape(self.size, self.size)

    def position_matrix(self, step: IterationStep) -> np.ndarray:
        """POS after ``step`` (Eq. 10) as a dense bool (N, N) matrix."""
        out = np.zeros(self.size * self.size, dtype=bool)
        out[step.position] = True
        return out.reshape(self.size, self.size)

    def agreement(self) -> np.ndarray:
        """Fraction of the applied cells whose window each point passes, (N, N) float in [0, 1]:
        1 exactly on the product of the applied MB_n (the place field when one formed)."""
        steps = self.applied
        count = np.zeros(self.size * self.size, np.uint16)
        for s in steps:  # one vectorised comparator per applied cell (<= n_cells)
            g = self.tables.levels[s.cell]
            count += (g >= s.lo) & (g <= s.hi)
        return (count / float(max(len(steps), 1))).reshape(self.size, self.size)


def record_iteration(source: GridCells | RateTables, T, cfg: SpatialConfig | None = None) -> IterationRecord:
    """Run the iteration of Eq. 9-10 for discharges ``T`` and record every step (for figures, Fig. 8).

    The literal full-matrix algorithm (:func:`localise_literal`) with the same windows, order, skip rule
    and exact stop test as :meth:`PlaceCells.localise`, so ``record.field`` equals what ``localise``
    returns for the same ``T`` (tested). Costs ~10-50 ms at the defaults: call it when a figure is asked
    for, never per step.
    """
    cfg = cfg or source.cfg  # type: ignore[union-attr]  # a RateTables source needs cfg given (as before)
    t = _resolve_tables(source)
    T = _check_rates(T, t.n_cells)
    lo, hi = window_levels(T, cfg)
    cells = np.arange(t.n_cells)
    counts = np.maximum(t.cum[cells, hi + 1] - t.cum[cells, lo], 0)
    tau = _tau(cfg, t.resolution)
    d2 = t.resolution * t.resolution
    G = t.levels
    pos: np.ndarray | None = None  # flat indices of the ones of POS; None = all ones
    steps: list[IterationStep] = []
    iterations = skipped = 0
    applied: list[int] = []
    field = None
    for n in iteration_order(counts, cfg.iteration_order).tolist():
        lo_n, hi_n = int(lo[n]), int(hi[n])
        if pos is None:
            new = np.flatnonzero((G[n] >= lo_n) & (G[n] <= hi_n))
        else:
            v = G[n].take(pos)
            new = pos[(v >= lo_n) & (v <= hi_n)]
        ok = new.size > 0
        if ok:
            pos = new
            iterations += 1
            applied.append(n)
        else:
            skipped += 1
        cur = pos if pos is not None else np.arange(t.size * t.size)
        iy, ix = np.divmod(cur.astype(np.int64), t.size)
        m = int(cur.size)
        sx, sxx, sy, syy = int(ix.sum()), int((ix * ix).sum()), int(iy.sum()), int((iy * iy).sum())
        single = ok and _is_single(m, sx, sxx, sy, syy, tau)
        var = ((m * sxx - sx * sx) / (m * m) * d2, (m * syy - sy * sy) / (m * m) * d2) if m else (0.0, 0.0)
        frozen = np.array(cur, dtype=np.int64)
        frozen.flags.writeable = False
        steps.append(IterationStep(cell=int(n), lo=lo_n, hi=hi_n, ones=int(counts[n]), applied=ok,
                                   position=frozen, variance=(float(var[0]), float(var[1])), single=single))
        if single:
            field = PlaceField._from_indices(pos, t.size, t.resolution, iterations, skipped, applied)
            break
    return IterationRecord(T=T.copy(), tables=t, cfg=cfg, steps=tuple(steps), field=field)


def noise_free_discharges(source: GridCells | RateTables, cfg: SpatialConfig, local) -> np.ndarray:
    """``T_n = g_n(q(r_loc))`` without noise at the local position ``local`` (metres in the coding area)."""
    t = _resolve_tables(source)
    loc = np.asarray(local, dtype=float)
    if loc.shape != (2,) or not np.all(np.isfinite(loc)):
        raise InputError(f"local position must be 2 finite numbers, got {local!r}")
    ix, iy = np.clip(np.rint(loc / t.resolution), 0, t.size - 1).astype(np.int64)
    return t.levels[:, iy * t.size + ix] * (cfg.g_max / LEVELS)


def record_stored_field(source: GridCells | RateTables, cfg: SpatialConfig, indices,
                        max_tries: int = 512) -> IterationRecord:
    """Re-run, with recording, the iteration that produced a stored field given by its flat ``indices``.

    A stored field keeps no discharges. Without rate noise, the robot's grid point ``q(r_loc)`` passes
    every window, so it lies in the field and its noise-free discharges reproduce the field exactly:
    the field's points are tried, nearest to its centroid first, with the fast iteration, and the
    first one that reproduces the stored indices is recorded. If none does (rate noise moved the
    windows), the record is that of the centroid's grid point: the field the model finds there.
    """
    t = _resolve_tables(source)
    idx = np.unique(np.asarray(indices, dtype=np.int64))
    if idx.size == 0 or idx[0] < 0 or idx[-1] >= t.size * t.size:
        raise InputError(f"field indices must be a non-empty subset of 0..{t.size * t.size - 1}")
    iy, ix = np.divmod(idx, t.size)
    c = np.array([ix.mean(), iy.mean()])
    near = np.argsort((ix - c[0]) ** 2 + (iy - c[1]) ** 2, kind="stable")[:max_tries]
    pc = PlaceCells(t, cfg)
    for k in near.tolist():
        T = noise_free_discharges(t, cfg, (ix[k] * t.resolution, iy[k] * t.resolution))
        f = pc.localise(T)
        if f is not None and np.array_equal(f.indices, idx):
            return record_iteration(t, T, cfg)
    return record_iteration(t, noise_free_discharges(t, cfg, c * t.resolution), cfg)
