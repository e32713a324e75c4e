"""Exact pose-graph solve: Gauss–Newton least squares on the SE(2) graph (``MapConfig.solver = 'lsq'``).

The alternative to the [ORS] relaxation of :mod:`hippomap.relaxation` (same link convention:
link k from node i to node j stores the pose of j in the frame of i). Relaxation is a diffusion
and needs O(N²) sweeps to spread a loop-closure error around an N-node loop; :func:`solve_lsq`
solves it in a few iterations with ``scipy.sparse``. Its optimum differs slightly from the
relaxation's fixed point because relaxation (like [ORS]) has no heading–position coupling term.

* :func:`solve_lsq` — weighted Gauss–Newton (Levenberg–Marquardt on failure), optionally with
  the odometry's heading bias estimated with the poses.
* The headings-first re-initialisation (LAGO) before the solve is :mod:`hippomap.headings_first`.
* :func:`graph_cost` — the objective :func:`solve_lsq` minimises.
* :func:`bias_sigma` — the estimated heading bias's posterior standard deviation.
* The sparse linear algebra (one fill-reducing order per solve, symmetric-mode LU, normal equations
  on a fixed pattern, remembered for the last few graph structures) is :mod:`hippomap.lsq_layout`.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .lsq_layout import _lsq_layout, _spd_factor
from .relaxation import RelaxResult, _as_graph, _wrap_inplace


def _sqrt_information(information, m: int) -> np.ndarray:
    """(M, 3) square roots of the links' diagonal information (ones when None); checked."""
    if information is None:
        return np.ones((m, 3))
    w = np.asarray(information, dtype=float)
    if w.shape != (m, 3):
        raise InputError(f"link information must have shape ({m}, 3), got {w.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(w) & (w > 0), axis=1))
    if len(bad):
        raise InputError(f"link {int(bad[0])} has information {w[bad[0]].tolist()}: every value must be finite and > 0")
    return np.sqrt(w)


def couple(e: np.ndarray, coupling: np.ndarray) -> np.ndarray:
    """Link residuals ``e`` (K, 3: x, y, heading in the source frame) with each heading residual
    replaced by what a coupled visual link measures, ``heading + coupling · y`` (``coupling`` (K,),
    m⁻¹; :attr:`~hippomap.loop_closure.LoopHypothesis.coupling`), in place; the same array. A link without coupling
    keeps its heading residual (adding 0 changes no value but the sign of a zero)."""
    e[:, 2] += coupling * e[:, 1]
    return e


def link_errors(P: np.ndarray, src: np.ndarray, dst: np.ndarray, T: np.ndarray, coupling=None) -> np.ndarray:
    """Each link's residual (K, 3) in its source frame, the frame of its per-axis information, with
    coupled heading residuals (:func:`couple`) when ``coupling`` is given: what the solver
    whitens and what the robust kernel must see. ``P``, ``src``, ``dst``, ``T`` are the map's own
    checked arrays (float64 poses and transforms, int64 link ends)."""
    return _lsq_errors(P, src, dst, T, coupling=coupling)[0]


def _lsq_errors(P, src, dst, T, sw=None, coupling=None):
    """Each link's error (M, 3) in its source frame, weighted by ``sw`` (the square roots of the
    information), with the heading error of a coupled link replaced by heading + ``coupling`` · y
    (:func:`couple`); and the cosines, sines and position differences the
    Jacobian needs."""
    ti = P[src, 2]
    dx = P[dst, 0] - P[src, 0]
    dy = P[dst, 1] - P[src, 1]
    c, s = np.cos(ti), np.sin(ti)
    e = np.empty((len(src), 3))
    e[:, 0] = c * dx + s * dy - T[:, 0]
    e[:, 1] = -s * dx + c * dy - T[:, 1]
    e[:, 2] = _wrap_inplace(P[dst, 2] - ti - T[:, 2])
    if coupling is not None:
        couple(e, coupling)
    if sw is not None:
        e *= sw
    return e, c, s, dx, dy


def graph_cost(
    poses,
    src,
    dst,
    transforms,
    information=None,
    bias_dt=None,
    bias: float = 0.0,
    bias_information: float = 0.0,
    coupling=None,
) -> float:
    """Sum of squared link errors in the links' own frames, weighted by ``information`` (M, 3)
    when given, heading errors coupled by ``coupling`` (M,) when given: the objective of
    :func:`solve_lsq`. With ``bias_dt``, each link's heading change
    is corrected by ``bias · bias_dt`` and the bias's prior ``bias_information · bias²`` is added,
    as :func:`solve_lsq` does."""
    P, src, dst, T = _as_graph(poses, src, dst, transforms)
    prior = 0.0
    if bias_dt is not None:
        T = T.copy()
        T[:, 2] -= bias * np.asarray(bias_dt, dtype=float)
        prior = bias_information * bias * bias
    e = _lsq_errors(P, src, dst, T, _sqrt_information(information, len(src)), coupling)[0]
    return float(np.sum(e * e)) + prior


def _lsq_jacobian(c, s, dx, dy, sw: np.ndarray, bdt: np.ndarray | None, coupling=None) -> np.ndarray:
    """Each link's weighted Jacobian (M, 3, q) at the poses :func:`_lsq_errors` returned ``c, s, dx,
    dy`` for: rows ex, ey, et; columns xi, yi, ti, xj, yj, tj, and the bias when ``bdt`` is given
    (the bias is estimated)."""
    Jk = np.zeros((len(sw), 3, 7 if bdt is not None else 6))
    Jk[:, 0, :5] = np.column_stack([-c, -s, -s * dx + c * dy, c, s]) * sw[:, :1]
    y_row = np.column_stack([s, -c, -c * dx - s * dy, -s, c])  # d ey, unweighted
    Jk[:, 1, :5] = y_row * sw[:, 1:2]
    Jk[:, 2, 2] = -sw[:, 2]
    Jk[:, 2, 5] = sw[:, 2]
    if coupling is not None:  # d(heading + coupling · y): the y row, unweighted, times the coupling
        Jk[:, 2, :5] += y_row * (coupling * sw[:, 2])[:, None]
    if bdt is not None:
        Jk[:, 2, 6] = bdt * sw[:, 2]  # d et / d bias
    return Jk


def solve_lsq(
    poses: np.ndarray,
    src,
    dst,
    transforms,
    iterations: int = 10,
    anchor: int | None = 0,
    tol: float = 1e-6,
    cost_rtol: float = 1e-9,
    information=None,
    fixed=None,
    bias_dt=None,
    bias: float = 0.0,
    bias_information: float = 0.0,
    estimate_bias: bool = True,
    coupling=None,
) -> RelaxResult:
    """Gauss–Newton on the SE(2) pose graph, **in place**.

    Stops after ``iterations`` linear solves, when the largest step is below ``tol``, or when
    the cost fell by less than ``cost_rtol`` of itself (GN converges only linearly on an
    inconsistent graph; the cost settles long before the steps vanish). A step that would
    raise the cost is retried with Levenberg–Marquardt damping; the poses are never left worse.

    Error of link i→j: ``e = (R_iᵀ(t_j − t_i) − t_xy, wrap(θ_j − θ_i − t_θ))``, weighted by
    ``information`` (M, 3): the diagonal of each link's information matrix (x, y, θ in the
    link's frame); None = unit information. The normal equations ``JᵀJ δ = −Jᵀe`` are assembled
    per link block on a sparsity pattern fixed for the solve (:func:`_normal_pattern`) and solved
    by sparse LU in the nodes' minimum-degree order (:func:`group_order`), with the ``anchor``
    node held fixed (``None``: a tiny damping fixes the gauge). A first undamped step that
    raises the cost by less than ``cost_rtol`` ends the solve: the poses are at the optimum up to
    rounding. ``fixed``: ids of further nodes held at their poses (the boundary of a
    local solve). Nodes without links keep their pose.

    ``coupling`` (M,), m⁻¹: a link with a coupling measures ``heading + coupling · y`` where the
    others measure the heading (a visual link's image shift: :attr:`LoopHypothesis.coupling`); its
    heading information weighs that combination. All zeros or None: the plain errors.

    ``bias_dt`` (M,): a heading bias of the odometry, estimated with the poses (odometry
    calibration, as in Kümmerle et al., *Simultaneous calibration, localization, and mapping*,
    IROS 2011): link k's measured heading change is taken to include ``bias · bias_dt[k]`` (a
    gyro's constant drift per second when ``bias_dt`` holds the links' durations; 0 for links
    that are not odometry). ``bias`` is the starting value, ``bias_information`` a zero-mean
    prior on it (needed while no loop determines it); ``estimate_bias=False`` holds it fixed.
    The result's ``bias`` is the final value.

    One function on purpose: the damped step-and-retry loop shares the iterate, its
    cost, the damping and the factorisation; split, each step would pass all of them around.
    """
    P, src, dst, T = _as_graph(poses, src, dst, transforms, inplace=True)
    n, m = len(P), len(src)
    if m == 0 or iterations <= 0:
        return RelaxResult("lsq", 0, 0.0, float(bias))
    sw = _sqrt_information(information, m)
    bdt = None
    if bias_dt is not None:
        bdt = np.asarray(bias_dt, dtype=float)
        if bdt.shape != (m,) or not np.all(np.isfinite(bdt)):
            raise InputError(f"bias_dt must be {m} finite values, one per link, got shape {bdt.shape}")
        if not np.isfinite(bias) or not (np.isfinite(bias_information) and bias_information >= 0):
            raise InputError(f"bias {bias!r} and bias_information {bias_information!r} must be finite, the latter >= 0")
        T = T.copy()
        T_raw = T[:, 2].copy()
        T[:, 2] = T_raw - bias * bdt
    est = bdt is not None and estimate_bias and bool(np.any(bdt != 0))
    nv, idx, col, H_of = _lsq_layout(n, src, dst, anchor, fixed, bdt if est else None, bias_information)
    shift = 0.0
    done = 0
    work = 0
    lam = 0.0  # Levenberg-Marquardt damping, raised only when a Gauss-Newton step fails
    b = float(bias)
    prior = bias_information if est else 0.0

    def total(e_: np.ndarray, b_: float) -> float:
        return float(np.sum(e_ * e_)) + prior * b_ * b_

    if coupling is not None:
        coupling = np.asarray(coupling, dtype=float)
        if coupling.shape != (m,) or not np.all(np.isfinite(coupling)):
            raise InputError(f"coupling must be {m} finite values, one per link, got shape {coupling.shape}")
        if not np.any(coupling):
            coupling = None  # the plain errors, bit for bit
    e, c, s, dx, dy = _lsq_errors(P, src, dst, T, sw, coupling)
    cost = total(e, b)
    while done < iterations and cost > 0:
        H, damped, g = H_of(_lsq_jacobian(c, s, dx, dy, sw, bdt if est else None, coupling), e)
        if est:
            g[col[3 * n]] -= prior * b  # the prior's gradient (its Hessian is in damp)
        while True:
            # symmetric positive definite: symmetric-mode LU without pivoting, in the nodes'
            # minimum-degree order computed above (several times faster than the default COLAMD spsolve)
            lu = _spd_factor(H if lam == 0 else damped(lam))
            work += lu.nnz
            full = np.zeros(nv)
            full[idx] = lu.solve(g)
            step = full[: 3 * n].reshape(n, 3)
            trial = P + step
            _wrap_inplace(trial[:, 2])
            b_t = b + (float(full[3 * n]) if est else 0.0)
            if est:
                assert bdt is not None  # est implies bias_dt was given
                T[:, 2] = T_raw - b_t * bdt
            e_t, c_t, s_t, dx_t, dy_t = _lsq_errors(trial, src, dst, T, sw, coupling)
            cost_t = total(e_t, b_t)
            done += 1
            if np.isfinite(cost_t) and cost_t <= cost:
                lam = 0.0 if lam <= 1e-6 else lam / 10
                break
            lam = 1e-4 if lam == 0 else lam * 10
            if est:
                assert bdt is not None  # est implies bias_dt was given
                T[:, 2] = T_raw - b * bdt
            # a step that raises the cost by less than cost_rtol: the optimum, up to rounding
            at_optimum = lam == 1e-4 and np.isfinite(cost_t) and cost_t - cost <= cost_rtol * cost
            if at_optimum or lam > 1e6 or done >= iterations:
                return RelaxResult("lsq", done, shift, b, work)  # no step lowers the cost: keep the poses
        P[:] = trial
        b = b_t
        shift = float(np.sqrt(np.max(step[:, 0] ** 2 + step[:, 1] ** 2)))
        converged = np.max(np.abs(full)) < tol or cost - cost_t <= cost_rtol * cost
        e, c, s, dx, dy, cost = e_t, c_t, s_t, dx_t, dy_t, cost_t
        if converged:
            break
    return RelaxResult("lsq", done, shift, b, work)


def bias_sigma(
    poses,
    src,
    dst,
    transforms,
    bias_dt,
    bias: float = 0.0,
    bias_information: float = 0.0,
    information=None,
    anchor: int | None = 0,
) -> float:
    """Posterior standard deviation of the odometry's heading bias of :func:`solve_lsq` at ``poses``
    (rad/s when ``bias_dt`` holds durations): ``sqrt([H⁻¹]_bb)`` of the weighted Gauss–Newton
    normal matrix ``H = JᵀJ`` (with the bias's prior) linearised there, i.e. the bias's marginal
    uncertainty once every pose is solved with it. It says how well the graph's loops observe the
    bias: the map applies an estimated bias only when it stands out of this noise (Wald test,
    :meth:`~hippomap.map_correction.MapCorrection._solve_lsq`). ``inf`` when no odometric link
    carries a duration (nothing observes it)."""
    P, src, dst, T = _as_graph(poses, src, dst, transforms)
    n, m = len(P), len(src)
    bdt = np.asarray(bias_dt, dtype=float)
    if bdt.shape != (m,) or not np.all(np.isfinite(bdt)):
        raise InputError(f"bias_dt must be {m} finite values, one per link, got shape {bdt.shape}")
    if m == 0 or not np.any(bdt != 0):
        return float("inf")
    sw = _sqrt_information(information, m)
    T = T.copy()
    T[:, 2] -= bias * bdt
    _, idx, col, H_of = _lsq_layout(n, src, dst, anchor, None, bdt, bias_information)
    e, c, s, dx, dy = _lsq_errors(P, src, dst, T, sw)
    H = H_of(_lsq_jacobian(c, s, dx, dy, sw, bdt), e)[0]
    unit = np.zeros(len(idx))
    unit[col[3 * n]] = 1.0
    try:
        var = float(_spd_factor(H).solve(unit)[col[3 * n]])
    except RuntimeError:  # singular: some unknown is not determined by the graph
        return float("inf")
    return float(np.sqrt(var)) if var > 0 and np.isfinite(var) else float("inf")
