"""The place-cell iteration recorded step by step, for figures (the paper's Fig. 8).

:func:`record_iteration` runs Eq. 9-10 for given discharges and keeps every MB_n met, so that the
formation of a place field can be drawn (:mod:`hippomap.viz.place_field_figure`);
:func:`record_stored_field` does so for a field stored without its discharges. The record holds the
sparse position sets only; the binarised matrices are computed from the shared rate tables on demand.
Costs tens of milliseconds: built when a figure is asked for, never on the mapping path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import SpatialConfig
from .errors import InputError
from .grid_cells import GridCells, RateTables
from .place_cells import (
    PlaceCells,
    PlaceField,
    check_rates,
    is_single_field,
    iteration_order,
    noise_free_discharges,
    resolve_tables,
    stop_threshold,
    window_levels,
)


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
    t = resolve_tables(source)
    T = check_rates(T, t.n_cells)
    lo, hi = window_levels(T, cfg)
    cells = np.arange(t.n_cells)
    counts = np.maximum(t.cum[cells, hi + 1] - t.cum[cells, lo], 0)
    tau = stop_threshold(cfg, t.resolution)
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
        single = ok and is_single_field(m, sx, sxx, sy, syy, tau)
        var = ((m * sxx - sx * sx) / (m * m) * d2, (m * syy - sy * sy) / (m * m) * d2) if m else (0.0, 0.0)
        frozen = np.array(cur, dtype=np.int64)
        frozen.flags.writeable = False
        steps.append(
            IterationStep(
                cell=int(n),
                lo=lo_n,
                hi=hi_n,
                ones=int(counts[n]),
                applied=ok,
                position=frozen,
                variance=(float(var[0]), float(var[1])),
                single=single,
            )
        )
        if single:
            field = PlaceField._from_indices(pos, t.size, t.resolution, iterations, skipped, applied)
            break
    return IterationRecord(T=T.copy(), tables=t, cfg=cfg, steps=tuple(steps), field=field)


def record_stored_field(
    source: GridCells | RateTables, cfg: SpatialConfig, indices, max_tries: int = 512
) -> IterationRecord:
    """Re-run, with recording, the iteration that produced a stored field given by its flat ``indices``.

    A stored field keeps no discharges. Without rate noise, the robot's grid point ``q(r_loc)`` passes
    every window, so it lies in the field and its noise-free discharges reproduce the field exactly:
    the field's points are tried, nearest to its centroid first, with the fast iteration, and the
    first one that reproduces the stored indices is recorded. If none does (rate noise moved the
    windows), the record is that of the centroid's grid point: the field the model finds there.
    """
    t = resolve_tables(source)
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
