"""Visual grid cells and spatial view cells: the metric of the view plane (paper §2.2).

A fixation point ``x = (col, row)`` in a frame is encoded by 9 modules x 100 visual grid
cells (paper Eqs. 1-3; spec §1)::

    b_j = (cos(j pi/3 + psi), sin(j pi/3 + psi)),  j = 0, 1, 2
    z_{m,c,j}(x) = b_j . (F_m x + o_c),            F_m = 2 pi f_m
    r_{m,c}(x) = 1/3 max(0, sum_j cos z_{m,c,j})   in [0, 1]

The 100 offsets ``o_c`` of a module form a 10 x 10 lattice on the rhombic unit cell of the
phase plane (two adjacent equilateral triangles), ``o = u/10 a1 + w/10 a2`` with
``b_j . a in 2 pi Z`` — the exact lattice (spec §1 corrects [BBc]'s 3-8 % too large rhombus
of modules 5-9).

Why grid cells: the saccade vector between two fixations is read out of the difference
of the two grid-cell states (paper Eqs. 4-5), so the memory never needs absolute image
coordinates — only grid-cell population vectors, which is what the feature units store.

Decoding (spec §1 option B, "the 2-D form of Eq. 5"): each module's three phases are
read by a Fourier projection over its 100 offsets, phase differences are unwrapped from
the coarsest module to the finest, and the integer displacement is polished by a 3 x 3
search of the cost ``sum_{m,j} 1 - cos(F_m b_j . d - Delta_{m,j})``. All of it is
vectorised over batches of vector pairs. Spatial view cells (spec §2, option C) are the
table decoder: one cell per ``svc_stride`` pixels of the view plane, weights the
normalised grid code of their location, winner-take-all = fixation location.

Range: the coarsest module (825 px spacing) disambiguates displacements with
``|d| < lambda_max / 2 = 412 px``, which covers every vector inside a 320 x 240 frame
(the working resolution, <= 399 px).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .config import VisualConfig
from .errors import InputError

__all__ = ["VisualGridCells", "SpatialViewCells"]


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


class VisualGridCells:
    """The 9 x 100 visual grid cells of [S] Eqs. 1-3 with the phase decoder of spec §1 B.

    ``encode(x)`` gives the population vector (``n_cells`` rates in [0, 1]) at fixation
    points ``x`` (..., 2) in pixels (col, row); ``decode(g_from, g_to)`` the integer
    saccade vector ``x_to - x_from`` from two population vectors.
    """

    def __init__(self, config: VisualConfig | None = None):
        cfg = config or VisualConfig()
        f = np.asarray(cfg.vgc_frequencies, dtype=float)
        if f.ndim != 1 or f.size == 0 or np.any(f <= 0):
            raise InputError(f"vgc_frequencies must be positive, got {cfg.vgc_frequencies!r}")
        self.frequencies = f
        self.F = 2.0 * np.pi * f  # rad / px
        self.n_modules = f.size
        n = cfg.vgc_offsets_per_axis
        self.n_offsets = n * n
        self.n_cells = self.n_modules * self.n_offsets
        psi = float(cfg.vgc_orientation)
        ang = np.arange(3) * np.pi / 3.0 + psi
        self.b = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (3, 2)
        # unit-cell vectors of the phase lattice: b_j . a in 2 pi Z  (spec §1)
        L = 4.0 * np.pi / np.sqrt(3.0)
        a1 = L * np.array([np.cos(np.pi / 2 + psi), np.sin(np.pi / 2 + psi)])
        a2 = L * np.array([np.cos(np.pi / 6 + psi), np.sin(np.pi / 6 + psi)])
        u, w = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        self.offsets = (u.reshape(-1, 1) / n) * a1 + (w.reshape(-1, 1) / n) * a2  # (100, 2)
        self._bo = self.offsets @ self.b.T  # (100, 3): b_j . o_c
        self._cos_bo = np.cos(self._bo).T.copy()  # (3, 100)
        self._sin_bo = np.sin(self._bo).T.copy()
        # Fourier projection reading each module's phases (spec §1 B)
        self._proj = np.exp(-1j * self._bo)  # (100, 3)
        #: grid spacing lambda_m = 4 pi / (sqrt 3 F_m) in px, coarse to fine order below
        self.spacing = 4.0 * np.pi / (np.sqrt(3.0) * self.F)
        self._order = np.argsort(-self.spacing)  # coarse -> fine
        #: largest |d| decoded without aliasing
        self.max_range = float(self.spacing.max() / 2.0)
        # real-space lattice of the coarsest module: F b_j . v in 2 pi Z for all j
        c = self._order[0]
        basis = np.linalg.solve(self.b[:2], np.eye(2)) * (2.0 * np.pi / self.F[c])  # columns v1, v2
        v1, v2 = basis[:, 0], basis[:, 1]
        self._coarse = self._order[: max(1, min(4, self.n_modules))]
        # normal equations of sum_{m,j} (F_m b_j . delta - r_mj)^2: (3/2) sum_m F_m^2 I
        self._w_coarse = 1.5 * float((self.F[self._coarse] ** 2).sum())
        self._w_all = 1.5 * float((self.F**2).sum())
        # a wrap of phase 0 or 1 of the coarsest module shifts the solution by v1 or v2
        self._lattice_shifts = np.array([i * v1 + j * v2 for i in (0, -1, 1) for j in (0, -1, 1)])  # (9, 2)
        nb = np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)], dtype=float)
        self._polish = nb  # (9, 2) integer neighbourhood of the rounded estimate
        # the constant operands of one pair's decode (_decode_one), taken once: the same values the
        # batched expressions index out of F and b at every call
        self._c0 = int(self._order[0])
        self._bT = self.b.T
        self._F_co = self.F[self._coarse, None]  # (4, 1)
        self._F_col = self.F[:, None]  # (M, 1)
        co = self._coarse
        # the coarse modules' rows of a phase difference: a slice (a view, no gather) when they are the
        # first ones, as with frequencies in increasing order; the same values either way
        self._co_rows: slice | np.ndarray = slice(0, co.size) if np.array_equal(co, np.arange(co.size)) else co
        # the phase offsets F_m b_j . v of the 9 lattice alternatives over the coarse modules and of the 3 x 3
        # polish neighbourhood over all modules: a pair's costs add only its own base phase to them
        self._alt_phase = self._F_co[None] * (self._lattice_shifts @ self._bT)[:, None, :]  # (9, 4, 3)
        self._polish_phase = self._F_col[None] * (self._polish @ self._bT)[:, None, :]  # (9, M, 3)
        self._F_c0 = float(self.F[self._c0])
        self._F_list = self.F.tolist()
        self._b_rows = self.b.tolist()
        self._scalar_steps = ((co.tolist(), self._w_coarse), (list(range(self.n_modules)), self._w_all))

    # -- encoding ---------------------------------------------------------------------
    def encode(self, x: Any) -> np.ndarray:
        """Population vector(s) at fixation point(s) ``x`` (..., 2) = (col, row) -> (..., n_cells)."""
        x = np.asarray(x, dtype=float)
        if x.shape[-1:] != (2,):
            raise InputError(f"fixation points must have shape (..., 2), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise InputError("fixation points must be finite")
        return self._rates(x).reshape(x.shape[:-1] + (self.n_cells,))

    def _rates(self, x: np.ndarray) -> np.ndarray:
        """The rates of checked float points ``x`` (..., 2) per module and offset: (..., M, C)."""
        # cos(F b.x + b.o) = cos(F b.x) cos(b.o) - sin(F b.x) sin(b.o): 27 trig calls per point
        phi = self._F_col * (x @ self._bT)[..., None, :]  # (..., M, 3)
        s = np.cos(phi) @ self._cos_bo - np.sin(phi) @ self._sin_bo  # (..., M, C)
        return np.maximum(0.0, s) / 3.0

    def _phase_code_one(self, x: np.ndarray) -> np.ndarray:
        """``_project(encode(x))`` of one finite point ``x`` (2,) float: the module phasors (M, 3), from the
        rates without the checks and reshapes of the two public steps (the saccade loop calls it with
        whole-pixel points it made itself)."""
        return self._rates(x) @ self._proj

    # -- decoding ---------------------------------------------------------------------
    def phases(self, g: Any) -> np.ndarray:
        """Module phases ``b_j . F_m x`` (mod 2 pi) read from population vectors: (..., M, 3)."""
        z = self._project(g)
        return np.angle(z)

    def _project(self, g: Any) -> np.ndarray:
        g = np.asarray(g, dtype=float)
        if g.shape[-1:] != (self.n_cells,):
            raise InputError(f"grid-cell vectors must have {self.n_cells} entries, got shape {g.shape}")
        gm = g.reshape(g.shape[:-1] + (self.n_modules, self.n_offsets))
        return gm @ self._proj  # (..., M, 3) complex

    def decode(self, g_from: Any, g_to: Any) -> np.ndarray:
        """Integer saccade vector(s) ``x_to - x_from`` from two population vectors (..., 2).

        Coarse-to-fine phase unwrapping (spec §1 B): the running estimate moves by the
        least-squares solution of each module's wrapped phase residuals, then the rounded
        estimate is polished over its 3 x 3 integer neighbourhood by the cost of Eq. 5.
        """
        zf = self._project(g_from)
        zt = self._project(g_to)
        return self.decode_phase_difference(np.angle(zt * np.conj(zf)))

    def decode_phase_difference(self, delta: np.ndarray) -> np.ndarray:
        """Displacement(s) from module phase differences ``delta`` (..., M, 3).

        The coarsest module fixes ``d`` up to its lattice; its wrapped phases are only
        unambiguous while every ``|b_j . d| < 1 / (2 f)`` (357 px), so among the 9 lattice
        alternatives of one wrap of either phase the one with the lowest Eq. 5 cost over the
        four coarsest modules is refined through the finer modules (exact up to
        ``|d| < lambda_max / 2``).
        """
        delta = np.asarray(delta, dtype=float)
        if delta.ndim == 2:
            return self._decode_one(delta)
        c = self._order[0]
        z = _wrap(delta[..., c, :])
        # make the three phases consistent (b_2 = b_1 - b_0) before the least-squares solve,
        # so that the solution differs from the truth by a lattice vector n0 v1 + n1 v2 only
        z2 = z[..., 1] - z[..., 0] + _wrap(z[..., 2] - (z[..., 1] - z[..., 0]))
        z = np.stack([z[..., 0], z[..., 1], z2], axis=-1)
        d0 = (2.0 / 3.0) * (z @ self.b) / self.F[c]  # (..., 2)
        alt = d0[..., None, :] + self._lattice_shifts  # (..., 9, 2)
        # the alternatives are >= lambda_max apart: the coarse modules (spacing >= 4 x the
        # few-px error of the module-1 estimate) already tell them apart
        co = self._coarse
        proj = alt @ self.b.T  # (..., 9, 3)
        cost = (1.0 - np.cos(self.F[co, None] * proj[..., :, None, :] - delta[..., None, co, :])).sum(axis=(-1, -2))
        best = np.argmin(cost, axis=-1)
        d = np.take_along_axis(alt, best[..., None, None], axis=-2)[..., 0, :]  # (..., 2)
        # coarse-to-fine: joint least-squares steps on the wrapped residuals, first over the
        # coarse modules (unwrap safely for errors up to ~100 px), then over all modules
        for mods, wsum in ((co, self._w_coarse), (slice(None), self._w_all)):
            pred = self.F[mods, None] * (d @ self.b.T)[..., None, :]  # (..., m, 3)
            r = _wrap(delta[..., mods, :] - pred)
            d = d + ((self.F[mods, None] * r).sum(axis=-2) @ self.b) / wsum
        d0 = np.rint(d)
        cand = d0[..., None, :] + self._polish  # (..., 9, 2) integer neighbourhood
        cost = self._cost(cand, delta[..., None, :, :])
        best = np.argmin(cost, axis=-1)
        out = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
        return out.astype(np.int64)

    def _decode_one(self, delta: np.ndarray) -> np.ndarray:
        """:meth:`decode_phase_difference` of one pair (``delta`` (M, 3)): the same steps with fewer numpy
        calls, since a call costs more than its few dozen numbers. The coarsest module's three phases and
        the two least-squares steps are a handful of scalars, done on Python floats; the Eq. 5 costs of the
        9 lattice alternatives and of the 3 x 3 polish are one cosine each over the phase offsets of the
        alternatives and of the neighbourhood, taken once (:meth:`__init__`), plus this pair's base phase;
        the lowest cost is the largest sum of cosines. The integer vector is the batched expressions' (a
        property test compares them); intermediate floats may differ from them in the last bits."""
        rows = delta.tolist()
        (b00, b01), (b10, b11), (b20, b21) = self._b_rows
        pi, two_pi = math.pi, 2.0 * math.pi
        z0, z1, z2 = rows[self._c0]
        z0 = (z0 + pi) % two_pi - pi
        z1 = (z1 + pi) % two_pi - pi
        e = z1 - z0  # the third phase made consistent with the first two (b_2 = b_1 - b_0)
        z2 = e + ((((z2 + pi) % two_pi - pi) - e + pi) % two_pi - pi)
        k = (2.0 / 3.0) / self._F_c0
        d0 = np.array([(z0 * b00 + z1 * b10 + z2 * b20) * k, (z0 * b01 + z1 * b11 + z2 * b21) * k])
        base = self._F_co * (d0 @ self._bT) - delta[self._co_rows]  # (4, 3)
        i = int(np.add.reduce(np.cos(self._alt_phase + base), axis=(1, 2)).argmax())
        x, y = (d0 + self._lattice_shifts[i]).tolist()
        F = self._F_list
        for mods, wsum in self._scalar_steps:  # coarse modules, then all: least squares on wrapped residuals
            p0, p1, p2 = x * b00 + y * b01, x * b10 + y * b11, x * b20 + y * b21
            g0 = g1 = g2 = 0.0
            for m in mods:
                f = F[m]
                r0, r1, r2 = rows[m]
                g0 += f * ((r0 - f * p0 + pi) % two_pi - pi)
                g1 += f * ((r1 - f * p1 + pi) % two_pi - pi)
                g2 += f * ((r2 - f * p2 + pi) % two_pi - pi)
            x += (g0 * b00 + g1 * b10 + g2 * b20) / wsum
            y += (g0 * b01 + g1 * b11 + g2 * b21) / wsum
        d = np.array([round(x), round(y)], dtype=float)  # round half to even, as np.rint
        base = self._F_col * (d @ self._bT) - delta  # (M, 3)
        j = int(np.add.reduce(np.cos(self._polish_phase + base), axis=(1, 2)).argmax())
        return (d + self._polish[j]).astype(np.int64)

    def _cost(self, cand: np.ndarray, delta: np.ndarray) -> np.ndarray:
        """Eq. 5 mismatch sum_{m,j} 1 - cos(F_m b_j . d - Delta_{m,j}) for candidates (..., K, 2)."""
        proj = cand @ self.b.T  # (..., K, 3)
        return (1.0 - np.cos(self.F[:, None] * proj[..., :, None, :] - delta)).sum(axis=(-1, -2))


class SpatialViewCells:
    """Spatial view cells (spec §2, decoder option C): one cell per ``stride`` px of a
    ``width x height`` view plane, weights = the normalised grid code of its location,
    wired once "during development" independently of any stimulus ([S] §2.2).

    ``locate(g)`` is the winner-take-all of the cosine similarity, refined to the pixel
    by a winner-take-all over the ``stride`` neighbourhood of the winning cell.
    """

    def __init__(self, grid: VisualGridCells, width: int, height: int, stride: int = 4):
        if width < 1 or height < 1 or stride < 1:
            raise InputError(f"bad spatial-view-cell sheet {width}x{height}, stride {stride}")
        self.grid = grid
        self.width, self.height, self.stride = int(width), int(height), int(stride)
        cols = np.arange(0, self.width, self.stride)
        rows = np.arange(0, self.height, self.stride)
        cc, rr = np.meshgrid(cols, rows)
        self.positions = np.stack([cc.ravel(), rr.ravel()], axis=1)  # (n, 2) col, row
        w = grid.encode(self.positions).astype(np.float32)
        w /= np.linalg.norm(w, axis=1, keepdims=True) + 1e-12
        self.weights = w  # (n_svc, n_cells)
        s = self.stride
        off = np.arange(-s + 1, s)
        oc, orr = np.meshgrid(off, off)
        self._refine = np.stack([oc.ravel(), orr.ravel()], axis=1)

    @property
    def n_cells(self) -> int:
        return int(self.positions.shape[0])

    def activity(self, g: Any) -> np.ndarray:
        """Cosine similarity of every spatial view cell to the grid-cell state ``g``."""
        g = np.asarray(g, dtype=np.float32)
        return self.weights @ (g / (np.linalg.norm(g) + 1e-12))

    def locate(self, g: Any) -> np.ndarray:
        """Fixation location (col, row) encoded by the grid-cell state ``g``."""
        win = self.positions[int(np.argmax(self.activity(g)))]
        cand = win + self._refine
        ok = (cand[:, 0] >= 0) & (cand[:, 0] < self.width) & (cand[:, 1] >= 0) & (cand[:, 1] < self.height)
        cand = cand[ok]
        enc = self.grid.encode(cand)
        enc /= np.linalg.norm(enc, axis=1, keepdims=True) + 1e-12
        g = np.asarray(g, dtype=float)
        return cand[int(np.argmax(enc @ (g / (np.linalg.norm(g) + 1e-12))))].astype(np.int64)

    def decode(self, g_from: Any, g_to: Any) -> np.ndarray:
        """Saccade vector as the difference of the two decoded locations (option C)."""
        return self.locate(g_to) - self.locate(g_from)
