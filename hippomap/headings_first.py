"""Headings-first initialisation of a pose graph before a whole Gauss–Newton solve (MODEL item 33).

The idea of LAGO (Carlone et al., 2014): a pose graph's objective is linear in the positions
once the headings are known, and nearly linear in the heading *changes*. So the headings are
solved alone first, then the positions, each by one sparse weighted Laplacian solve, and the
result is the starting point of :func:`~hippomap.least_squares.solve_lsq`. From the odometric
poses a closing link that carries a radian of heading error or more can leave Gauss–Newton
settled with that error spread wrongly; from these poses it converges in a few iterations.

* :func:`rotation_first_init` — the re-initialisation, in place, in three named steps: the held
  nodes (:func:`_free_nodes`), the headings with the odometry's heading bias
  (:func:`_solve_headings`), the positions (:func:`_solve_positions`);
  :func:`rotation_first_inits` the same from several branches of the wrapped heading residuals;
  :func:`rate_turns` the branches that one drift rate gives loops of different durations.
* :class:`_Laplacian` — the weighted least squares both steps are: ``min Σ_k w_k
  (u_dst − u_src + extra_k β − b_k)²``, on the fill-reducing orders and the symmetric sparse LU
  of :mod:`hippomap.least_squares`, factorised once for every branch.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .least_squares import _sqrt_information
from .lsq_layout import _spd_factor, group_order
from .relaxation import _as_graph, _wrap_inplace


class _Laplacian:
    """The weighted least squares ``min Σ_k w_k (u_dst − u_src + extra_k β − b_k)²`` over the nodes in
    ``keep`` (the others held at 0), assembled and factorised once for any number of right-hand sides
    ``b`` (:meth:`solve`). With ``extra`` (M,), one more unknown β shared by all links: the change of a
    parameter with a zero-mean prior of information ``extra_prior``. ``order``: the kept unknowns (β
    is unknown ``n``) in a fill-reducing elimination order, as :func:`~hippomap.lsq_layout.group_order`
    returns it (computed here when None).

    The branches of :func:`rotation_first_inits` differ only in their right-hand sides: one factor
    serves them all, and each solve is the one a factor of its own would give (the same matrix, the
    same factor, the same single-column solve)."""

    def __init__(
        self,
        n: int,
        src: np.ndarray,
        dst: np.ndarray,
        w: np.ndarray,
        keep: np.ndarray,
        extra: np.ndarray | None = None,
        extra_prior: float = 0.0,
        order: np.ndarray | None = None,
    ):
        m = len(src)
        rows = np.concatenate([np.arange(m)] * 2)
        cols = np.concatenate([src, dst])
        vals = np.concatenate([-np.ones(m), np.ones(m)])
        nv = n
        keep = np.asarray(keep, dtype=bool)
        if extra is not None:
            rows = np.concatenate([rows, np.arange(m)])
            cols, vals = np.append(cols, np.full(m, n)), np.append(vals, extra)
            nv = n + 1
            keep = np.append(keep, True)
        if order is None:
            ga, gb = src, dst
            if extra is not None:
                on = np.flatnonzero(extra != 0)
                ga, gb = np.concatenate([src, src[on], dst[on]]), np.concatenate([dst, np.full(2 * len(on), n)])
            order = group_order(nv, ga, gb, keep)
        col = np.full(nv, -1, dtype=np.int64)
        col[order] = np.arange(len(order))
        # the held unknowns are 0: their columns drop out; the others are placed in elimination order
        ok = col[cols] >= 0
        A = sp.csr_matrix((vals[ok], (rows[ok], col[cols[ok]])), shape=(m, len(order)))
        self._AW = AW = A.T.multiply(w[None, :]).tocsr()
        deg = np.bincount(src, minlength=nv) + np.bincount(dst, minlength=nv)
        diag = np.where(deg > 0, 0.0, 1.0)
        if extra is not None:
            diag[n] = extra_prior if extra_prior > 0 else 1e-9
        L = (AW @ A + sp.diags(diag[order])).tocsc()
        try:
            self._lu = _spd_factor(L)
        except RuntimeError:  # an exactly zero pivot without pivoting (the dense bias row): pivot, a hair damped
            reg = sp.diags(np.full(L.shape[0], 1e-9 * max(float(abs(L).max()), 1.0)))
            self._lu = spla.splu((L + reg).tocsc())
        self._n, self._nv, self._order, self._col = n, nv, order, col
        self._extra, self._extra_prior = extra is not None, extra_prior

    def solve(self, rhs_links: np.ndarray, extra_start: float = 0.0) -> tuple[np.ndarray, float]:
        """The unknowns for the right-hand sides ``rhs_links`` (M, C): (N, C), and β (0 without
        ``extra``; with it, one right-hand side only, its parameter now at ``extra_start``)."""
        n = self._n
        rhs = self._AW @ rhs_links
        if self._extra:
            rhs[self._col[n]] -= self._extra_prior * extra_start
        out = np.zeros((self._nv, rhs_links.shape[1]))
        out[self._order] = self._lu.solve(rhs)
        return out[:n], (float(out[n, 0]) if self._extra else 0.0)


def rotation_first_init(poses: np.ndarray, src, dst, transforms, heading_turns=None, **options) -> tuple[float, float]:
    """:func:`rotation_first_inits` of one branch (``heading_turns``, None for the wrapped reading), the
    poses re-initialised **in place**: returns the largest position change and the bias. ``options``:
    ``information``, ``anchor``, ``fixed``, ``bias_dt``, ``bias``, ``bias_information``, as there."""
    P, src, dst, T = _as_graph(poses, src, dst, transforms, inplace=True)
    ((Q, shift, new_bias),) = rotation_first_inits(P, src, dst, T, branches=[heading_turns], **options)
    P[:] = Q
    return shift, new_bias


def rotation_first_inits(
    poses: np.ndarray,
    src,
    dst,
    transforms,
    information=None,
    anchor: int | None = 0,
    fixed=None,
    bias_dt=None,
    bias: float = 0.0,
    bias_information: float = 0.0,
    branches=(None,),
) -> list[tuple[np.ndarray, float, float]]:
    """Re-initialise the poses of a pose graph headings first (the LAGO idea of Carlone et al., 2014),
    from the same poses for each of ``branches``: per branch ``(poses, largest position change,
    bias)``, the poses a new array (``poses`` is left as it is).

    Gauss–Newton linearises the rotations; after a long loop the closing link can carry a heading
    error of a radian or more, and from the odometric poses the solve can settle with that error
    spread wrongly (links a metre off, which a robust kernel then fades). Here the headings are
    solved alone first — linear in the heading *changes*, each link's wrapped residual taken on
    the current poses — and then the positions, which are linear once the headings are known:
    ``min Σ w |p_j − p_i − R(θ_i) t_xy|²``. Both are sparse Laplacian solves (a few ms at 10⁴
    nodes); the result is the starting point for :func:`~hippomap.least_squares.solve_lsq`. The
    anchor and ``fixed`` nodes keep their poses; nodes without links keep theirs. Weights:
    ``information`` (M, 3) diagonals (x/y mean for positions), unit when None. With ``bias_dt``
    the odometry's heading bias is solved with the headings (as in
    :func:`~hippomap.least_squares.solve_lsq`, from ``bias``).

    A branch is None (each link's heading residual wrapped into (−π, π]) or ``heading_turns`` (M,):
    whole turns added to each link's wrapped residual, another branch of the wrap (a loop that
    drifted more than π reads as the opposite drift). The branches share the graph, its weights and
    its held nodes, so each of the two Laplacians (headings, positions) is assembled and factorised
    once for all of them (:class:`_Laplacian`); every branch's poses are those a call of
    :func:`rotation_first_init` of its own gives.
    """
    P0, src, dst, T = _as_graph(poses, src, dst, transforms)
    n, m = len(P0), len(src)
    if m == 0:
        return [(P0.copy(), 0.0, float(bias)) for _ in branches]
    info = np.ones((m, 3)) if information is None else np.asarray(information, dtype=float)
    _sqrt_information(info, m)  # checked
    keep = _free_nodes(n, src, anchor, fixed)
    bdt = None if bias_dt is None else np.asarray(bias_dt, dtype=float).reshape(m)
    order = group_order(n, src, dst, keep)  # the node graph's order, for both solves
    # the bias couples every odometric link, so the headings' order is then computed with it
    headings = _Laplacian(n, src, dst, info[:, 2], keep, bdt, bias_information, None if bdt is not None else order)
    positions = _Laplacian(n, src, dst, 0.5 * (info[:, 0] + info[:, 1]), keep, order=order)
    out = []
    for heading_turns in branches:
        P = P0.copy()
        turns = None if heading_turns is None else np.asarray(heading_turns, dtype=float).reshape(m)
        th, new_bias = _solve_headings(P, src, dst, T, headings, bdt, float(bias), turns)
        dxy = _solve_positions(P, src, dst, T, th, positions)
        P[:, :2] += dxy
        P[:, 2] = th
        _wrap_inplace(P[:, 2])
        out.append((P, float(np.sqrt(np.max(np.sum(dxy * dxy, axis=1)))), new_bias))
    return out


def _free_nodes(n: int, src: np.ndarray, anchor: int | None, fixed) -> np.ndarray:
    """(N,) True for the nodes the initialisation moves: all but the anchor and the ``fixed``
    nodes; when none is held, all but the first linked node (the gauge: a pose graph says where
    its nodes are relative to each other only)."""
    keep = np.ones(n, dtype=bool)
    if anchor is not None:
        keep[anchor] = False
    if fixed is not None:
        keep[np.asarray(fixed, dtype=np.int64).reshape(-1)] = False
    if keep.all():
        keep[int(src[0])] = False
    return keep


def _solve_headings(
    P: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    T: np.ndarray,
    lap: _Laplacian,
    bdt: np.ndarray | None,
    bias: float,
    turns: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """The headings alone: the heading changes that make every link's wrapped heading residual,
    taken on the current poses ``P``, agree in the least squares of ``lap`` (the links' heading
    weights; with ``bdt`` (M,) the odometry's heading bias, now ``bias``, is solved with them).
    ``turns`` (M,): whole turns added to the wrapped residuals. Returns the new headings (N,,
    unwrapped) and the new bias."""
    T_th = T[:, 2] if bdt is None else T[:, 2] - bias * bdt
    e_th = _wrap_inplace(P[dst, 2] - P[src, 2] - T_th)
    if turns is not None:  # another branch of the wrapped residuals: whole turns added
        e_th += 2.0 * np.pi * turns
    sol, dbias = lap.solve(-e_th[:, None], extra_start=bias)
    return P[:, 2] + sol[:, 0], bias + dbias


def _solve_positions(
    P: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    T: np.ndarray,
    th: np.ndarray,
    lap: _Laplacian,
) -> np.ndarray:
    """The positions once the headings ``th`` are known, linear: the change (N, 2) of the
    positions ``P[:, :2]`` that minimises ``Σ w |p_j − p_i − R(θ_i) t_xy|²`` (the least squares of
    ``lap``) with the held nodes where they are."""
    c, s = np.cos(th[src]), np.sin(th[src])
    b = np.column_stack([c * T[:, 0] - s * T[:, 1], s * T[:, 0] + c * T[:, 1]])
    r = P[dst, :2] - P[src, :2] - b
    return lap.solve(-r)[0]


def turn_rates(residual: np.ndarray, duration: np.ndarray, turns) -> np.ndarray:
    """The change of drift rate (rad/s) that each loop link, taken each of ``turns`` whole turns round, reads
    as: ``(residual + 2π k) / duration`` (L, K), for the L links of ``residual`` and ``duration`` (M,) whose
    duration is not zero (a link between nodes of one instant reads no rate)."""
    ok = np.abs(duration) > 1e-9
    return (residual[ok, None] + 2.0 * np.pi * np.asarray(turns, dtype=float)[None, :]) / duration[ok, None]


def rate_turns(
    residual,
    duration,
    bias: float,
    max_rate: float,
    turns=(-2, -1, 1, 2),
    limit: int = 4,
    agree_rad: float = 0.5,
    exclude=(),
) -> list[np.ndarray]:
    """Branches of the wrapped heading residuals whose whole turns differ from link to link: the turns one
    drift rate asks of each link.

    A heading bias changed by ``db`` (rad/s) turns the headings along the odometry between a loop link's
    two nodes by ``db`` times the time between them, ``duration`` (s, signed: target's time minus
    source's), so a link's turned residual ``residual + 2π k`` agrees with that change when it equals
    ``db · duration``. Loops of different lengths then need different ``k`` for one rate, which taking
    every link the same number of turns round cannot give: a short loop closed first whose drift read
    right and a long one closed later whose drift passed half a turn. Each link and each of ``turns``
    proposes the rate change that would explain it; rates whose total ``bias + db`` lies beyond
    ``max_rate`` are dropped; every link then takes the turns nearest to what a proposed rate asks
    (``round((db · duration − residual) / 2π)``). Returns up to ``limit`` distinct turn vectors (each
    (M,) floats, the wrapped reading, all zeros, left out), those under which the most links agree with
    their rate within ``agree_rad`` first, then the smaller total rate, none equal to one of ``exclude``
    (turn vectors (M,) already tried). ``residual`` (M,): each link's heading residual wrapped into
    [−π, π), as :func:`rotation_first_inits` reads it."""
    e = np.asarray(residual, dtype=float).ravel()
    dt = np.asarray(duration, dtype=float).ravel()
    if e.shape != dt.shape:
        raise ValueError(f"rate_turns: {e.size} residuals and {dt.size} durations")
    two_pi = 2.0 * np.pi
    rates = turn_rates(e, dt, turns).ravel()
    rates = rates[np.abs(bias + rates) <= max_rate]
    if not rates.size:
        return []
    K = np.round((rates[:, None] * dt[None, :] - e[None, :]) / two_pi)  # (R, M): each rate's turns per link
    left = np.abs(e[None, :] + two_pi * K - rates[:, None] * dt[None, :])
    support = np.count_nonzero(left < agree_rad, axis=1)
    seen = {np.zeros(e.size).tobytes()} | {(np.asarray(x, dtype=float).ravel() + 0.0).tobytes() for x in exclude}
    out: list[np.ndarray] = []
    for r in np.lexsort((np.abs(bias + rates), -support)):  # the most links explained first
        k = K[r] + 0.0  # + 0.0: -0.0 and 0.0 are one turn count
        key = k.tobytes()
        if key in seen:
            continue
        seen.add(key)
        out.append(k)
        if len(out) == limit:
            break
    return out
