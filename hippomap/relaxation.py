"""Map relaxation: move node poses so that they agree with their links (paper Eq. 14; spec §4).

Every link k from node i to node j stores the pose of j measured in the frame of i,
``t_k = (dx, dy, dθ)`` (the [ORS] ``d, heading, facing`` triple in Cartesian form:
``dx = d cos(heading)``, ``dy = d sin(heading)``, ``dθ = facing``). Node i "thinks" node j
is at ``l_i ⊕ t_k``; the residual of the link is

    r_k = ( x_j − x_i − R(θ_i) t_xy ,  wrap(θ_j − θ_i − t_θ) )        (map frame, as [ORS])

and Eq. 14 — with its sign fixed so that the incoming term reads ``(l_k − l_i + Δl_ki)``,
i.e. ``−r`` for incoming links (spec §4, §6.9) — moves node i by

    Δl_i = α [ Σ_{k: i→·} r_k  −  Σ_{k: ·→i} r_k ]                        (Eq. 14, sign fixed)

Solvers (pure numpy / scipy on plain arrays; node 0 is the map's anchor by default):

* :func:`relax` — **default** (``MapConfig.solver = 'relax'``). The [ORS]
  ``ExperienceMap::iterate()`` per-link update, vectorised: the links are split by a greedy
  *edge colouring* into matchings (no two links of a class share a node); the links of one
  class are updated all at once with the exact [ORS] arithmetic, which equals running
  them one after the other. One sweep visits every link once: O(M) work in
  ``n_colours`` numpy passes (2–5 for a trajectory graph). The only difference from
  [ORS] is the *order* in which links are visited inside a sweep; measured on loops, the
  order does not change the convergence rate (see tests and ``bench/bench_relaxation.py``).
* :func:`relax_jacobi` — Eq. 14 applied to all nodes simultaneously with ``np.bincount``
  (``MapConfig.solver = 'jacobi'``). The literal simultaneous update with α = 0.5 is unstable
  once a node has more than a few links (eigenvalues of ``I − αL`` reach ``1 − 2α·d_max``);
  each node's correction is therefore divided by its degree (``I − αD⁻¹L``, eigenvalues
  in ``[1 − 2α, 1]``: stable for α ≤ 1, any degree). Stable but, being a lazy diffusion,
  4–10× slower to converge per sweep than :func:`relax`.
* :func:`relax_ors_reference` — the literal [ORS] loop in Python. Reference only.
* :func:`~hippomap.least_squares.solve_lsq` (module :mod:`hippomap.least_squares`) — exact
  alternative (``MapConfig.solver = 'lsq'``): Gauss–Newton on the SE(2) pose graph with
  ``scipy.sparse``. Relaxation is a diffusion and needs O(N²) sweeps to spread a loop-closure
  error around an N-node loop; this solves it in a few iterations. Its optimum differs slightly from
  the relaxation's fixed point because relaxation (like [ORS]) has no heading–position coupling term.

All three iterative solvers are equivariant under a rigid motion of the whole map, so the
anchor is applied as a gauge fix after the sweeps (the whole map is moved back rigidly so
that the anchor keeps its pose): the result is [ORS]'s un-anchored relaxation, seen from
the anchor, and convergence is not slowed down by a pinned node.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .geometry import between, compose

_TWO_PI = 2.0 * np.pi
#: colours available to the incremental edge colouring (bits of an int64 mask); a link whose
#: two ends already use all of them gets colour -1 and is relaxed by a Jacobi step instead.
MAX_COLOURS = 63


def _wrap_inplace(a: np.ndarray) -> np.ndarray:
    a += np.pi
    np.mod(a, _TWO_PI, out=a)
    a -= np.pi
    return a


def _as_graph(poses, src, dst, transforms, inplace: bool = False):
    if inplace and (not isinstance(poses, np.ndarray) or poses.dtype != np.float64):
        raise InputError("this solver works in place: poses must be a float64 numpy array")
    P = poses if inplace else np.asarray(poses, dtype=float)
    src = np.asarray(src, dtype=np.int64)
    dst = np.asarray(dst, dtype=np.int64)
    T = np.asarray(transforms, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"poses must have shape (N, 3), got {P.shape}")
    if src.ndim != 1 or src.shape != dst.shape:
        raise InputError(f"link sources {src.shape} and targets {dst.shape} must be 1-D and of equal length")
    if T.shape != (len(src), 3):
        raise InputError(f"link transforms must have shape ({len(src)}, 3), got {T.shape}")
    n = len(P)
    if len(src):
        bad = np.flatnonzero((src < 0) | (src >= n) | (dst < 0) | (dst >= n))
        if len(bad):
            k = int(bad[0])
            raise InputError(f"link {k} ({int(src[k])} -> {int(dst[k])}) names a node outside [0, {n})")
        loops = np.flatnonzero(src == dst)
        if len(loops):
            raise InputError(f"link {int(loops[0])} is a self-link of node {int(src[loops[0]])}")
    return P, src, dst, T


def _gauge_fix(poses: np.ndarray, anchor: int | None, before: np.ndarray | None) -> None:
    """Move the whole map rigidly so that ``anchor`` is back at pose ``before``."""
    if anchor is None or before is None:
        return
    after = poses[anchor].copy()
    if np.array_equal(after, before):
        return
    poses[:] = compose(before, between(after, poses))


def link_residuals(poses, src, dst, transforms) -> np.ndarray:
    """Residual ``r_k`` (M, 3) of every link: where the target is minus where the link puts it.

    xy in the map frame ([ORS] ``e1 − (lx, ly)``), heading wrapped to [-π, π).
    """
    return _link_residuals(*_as_graph(poses, src, dst, transforms))


def _link_residuals(P: np.ndarray, src: np.ndarray, dst: np.ndarray, T: np.ndarray) -> np.ndarray:
    """:func:`link_residuals` of arrays already checked (float64 poses and transforms, int64 link
    ends within the map, no self-link: the map's own arrays), without the checks: the map asks
    for a few links' residuals at every step (a new link's, the changed links' of the deferred
    correction), where the checks cost more than the arithmetic. The same operations, the same
    numbers."""
    ts = P[src, 2]
    c, s = np.cos(ts), np.sin(ts)
    out = np.empty((len(src), 3))
    out[:, 0] = P[dst, 0] - P[src, 0] - (c * T[:, 0] - s * T[:, 1])
    out[:, 1] = P[dst, 1] - P[src, 1] - (s * T[:, 0] + c * T[:, 1])
    out[:, 2] = _wrap_inplace(P[dst, 2] - ts - T[:, 2])
    return out


def colour_link(masks: np.ndarray, i: int, j: int) -> int:
    """Greedy colour of a new link i–j given per-node int64 masks of used colours (updated in place).

    Returns the smallest colour used by neither end, or -1 when all :data:`MAX_COLOURS` are taken.
    """
    used = int(masks[i]) | int(masks[j])
    free = ~used & (used + 1)  # lowest zero bit
    c = free.bit_length() - 1
    if c >= MAX_COLOURS:
        return -1
    masks[i] = int(masks[i]) | free
    masks[j] = int(masks[j]) | free
    return c


def edge_colouring(src, dst, n: int) -> np.ndarray:
    """Greedy edge colouring of the links in index order (the same colours the map assigns
    incrementally). Links of one colour share no node. A Python loop over links: build-time
    only (O(M)), never called per sweep."""
    src = np.asarray(src, dtype=np.int64)
    dst = np.asarray(dst, dtype=np.int64)
    masks = [0] * int(n)
    out = np.empty(len(src), dtype=np.int64)
    limit = 1 << MAX_COLOURS
    for k, (i, j) in enumerate(zip(src.tolist(), dst.tolist())):
        used = masks[i] | masks[j]
        free = ~used & (used + 1)
        if free >= limit:
            out[k] = -1
            continue
        out[k] = free.bit_length() - 1
        masks[i] |= free
        masks[j] |= free
    return out


@dataclass(frozen=True)
class RelaxResult:
    """What a solver did: iterations (sweeps) run and the largest node displacement of the last one."""

    solver: str
    iterations: int
    max_shift: float
    #: :func:`solve_lsq` with ``bias_dt``: the heading bias rate it ends with (rad per unit of ``bias_dt``)
    bias: float = 0.0
    #: :func:`solve_lsq`: the nonzeros of its factorisations' L and U factors, summed (a solve's work)
    work: int = 0


class ColourGroups:
    """Links grouped by colour, ready for :func:`relax` (build once, reuse while links are unchanged)."""

    def __init__(
        self,
        src: np.ndarray,
        dst: np.ndarray,
        transforms: np.ndarray,
        colours: np.ndarray,
        n: int,
        check: bool = True,
        weights: np.ndarray | None = None,
    ):
        """``weights`` (M,) in (0, 1] scale each link's correction (robust loop weights); None = 1."""
        colours = np.asarray(colours, dtype=np.int64)
        if weights is not None:
            weights = np.asarray(weights, dtype=float)
            if weights.shape != src.shape or not np.all((weights > 0) & (weights <= 1)):
                raise InputError("link weights must be (M,) values in (0, 1]")
            if np.all(weights == 1.0):
                weights = None
        if colours.shape != src.shape:
            raise InputError(f"colours {colours.shape} must match links {src.shape}")
        small = len(colours) == 0 or (colours.min() >= -128 and colours.max() < 128)
        # the map's colours fit int8, for which numpy's stable sort is a radix sort: O(M)
        order = np.argsort(colours.astype(np.int8) if small else colours, kind="stable")
        cs = colours[order]
        cuts = np.flatnonzero(np.diff(cs)) + 1
        self.groups = []
        self.overflow = None
        for g in np.split(order, cuts):
            if not len(g):
                continue
            s, d = src[g], dst[g]
            item = (
                s,
                d,
                np.ascontiguousarray(transforms[g, 0]),
                np.ascontiguousarray(transforms[g, 1]),
                np.ascontiguousarray(transforms[g, 2]),
                1.0 if weights is None else weights[g],
            )
            if colours[g[0]] < 0:
                self.overflow = item
            else:
                if check and len(np.unique(np.concatenate([s, d]))) != 2 * len(g):
                    raise InputError(f"colour {int(colours[g[0]])} is not a matching: two of its links share a node")
                self.groups.append(item)
        self.n = n
        if self.overflow is not None:
            s, d = self.overflow[0], self.overflow[1]
            deg = np.bincount(s, minlength=n) + np.bincount(d, minlength=n)
            self.overflow_gain = 1.0 / np.maximum(deg, 1)


def relax(
    poses: np.ndarray,
    src,
    dst,
    transforms,
    sweeps: int,
    alpha: float = 0.5,
    anchor: int | None = 0,
    colours=None,
    groups: ColourGroups | None = None,
) -> RelaxResult:
    """``sweeps`` [ORS] relaxation sweeps on ``poses`` (N, 3), **in place**, vectorised by edge colour.

    ``colours`` (M,) from :func:`edge_colouring` (computed when omitted) or a prebuilt
    ``groups``. ``anchor`` keeps that node's pose (gauge fix, see module doc); ``None``
    leaves the map free as [ORS] does.
    """
    P, src, dst, T = _as_graph(poses, src, dst, transforms, inplace=True)
    if not 0 < alpha <= 1:
        raise InputError(f"alpha must be in (0, 1], got {alpha}")
    n = len(P)
    if len(src) == 0 or sweeps <= 0:
        return RelaxResult("relax", 0, 0.0)
    if groups is None:
        groups = ColourGroups(src, dst, T, edge_colouring(src, dst, n) if colours is None else colours, n)
    before = P[anchor].copy() if anchor is not None else None
    x, y, th = P[:, 0], P[:, 1], P[:, 2]
    start = P[:, :2].copy()
    for sweep in range(sweeps):
        if sweep == sweeps - 1:
            start[:] = P[:, :2]
        for s_, d_, tx, ty, tt, w in groups.groups:
            ts = th[s_]
            c = np.cos(ts)
            s = np.sin(ts)
            a = alpha * w
            ex = (x[d_] - x[s_] - (c * tx - s * ty)) * a
            ey = (y[d_] - y[s_] - (s * tx + c * ty)) * a
            et = _wrap_inplace(th[d_] - ts - tt) * a
            x[s_] += ex
            y[s_] += ey
            th[s_] += et
            x[d_] -= ex
            y[d_] -= ey
            th[d_] -= et
        if groups.overflow is not None:
            s_, d_, tx, ty, tt, w = groups.overflow
            _jacobi_step(x, y, th, s_, d_, tx, ty, tt, alpha * groups.overflow_gain, n, w)
        _wrap_inplace(th)
    shift = float(np.sqrt(np.max(np.sum((P[:, :2] - start) ** 2, axis=1))))
    _gauge_fix(P, anchor, before)
    return RelaxResult("relax", int(sweeps), shift)


def _jacobi_step(x, y, th, src, dst, tx, ty, tt, gain, n, w=1.0):
    ts = th[src]
    c = np.cos(ts)
    s = np.sin(ts)
    rx = (x[dst] - x[src] - (c * tx - s * ty)) * w
    ry = (y[dst] - y[src] - (s * tx + c * ty)) * w
    rt = _wrap_inplace(th[dst] - ts - tt) * w
    cx = (np.bincount(src, rx, n) - np.bincount(dst, rx, n)) * gain
    cy = (np.bincount(src, ry, n) - np.bincount(dst, ry, n)) * gain
    ct = (np.bincount(src, rt, n) - np.bincount(dst, rt, n)) * gain
    x += cx
    y += cy
    th += ct
    return cx, cy


def relax_jacobi(
    poses: np.ndarray,
    src,
    dst,
    transforms,
    sweeps: int,
    alpha: float = 0.5,
    anchor: int | None = 0,
    normalise: bool = True,
) -> RelaxResult:
    """``sweeps`` simultaneous Eq. 14 updates on ``poses`` (N, 3), **in place** (``np.bincount``, O(M + N)).

    ``normalise`` divides each node's correction by its degree (stable for any degree);
    ``normalise=False`` is the literal Eq. 14, kept to show its instability at hubs.
    """
    P, src, dst, T = _as_graph(poses, src, dst, transforms, inplace=True)
    if not 0 < alpha <= 1:
        raise InputError(f"alpha must be in (0, 1], got {alpha}")
    n = len(P)
    if len(src) == 0 or sweeps <= 0:
        return RelaxResult("jacobi", 0, 0.0)
    if normalise:
        deg = np.bincount(src, minlength=n) + np.bincount(dst, minlength=n)
        gain = alpha / np.maximum(deg, 1)
    else:
        gain = np.full(n, float(alpha))
    before = P[anchor].copy() if anchor is not None else None
    tx, ty, tt = (np.ascontiguousarray(T[:, i]) for i in range(3))
    x, y, th = P[:, 0], P[:, 1], P[:, 2]
    cx = cy = np.zeros(1)
    for _ in range(sweeps):
        cx, cy = _jacobi_step(x, y, th, src, dst, tx, ty, tt, gain, n)
        _wrap_inplace(th)
    shift = float(np.sqrt(np.max(cx * cx + cy * cy)))
    _gauge_fix(P, anchor, before)
    return RelaxResult("jacobi", int(sweeps), shift)


def relax_ors_reference(poses: np.ndarray, src, dst, transforms, sweeps: int, alpha: float = 0.5) -> None:
    """The literal [ORS] ``ExperienceMap::iterate()`` (Gauss–Seidel), **in place**. Slow: reference only.

    Each sweep: nodes in id order, each node's outgoing links in creation order; every link
    moves both ends by ``α`` × its residual immediately (spec §4 pseudocode). No anchor.
    """
    P, src, dst, T = _as_graph(poses, src, dst, transforms, inplace=True)
    order = np.argsort(src, kind="stable")
    links = [(int(src[k]), int(dst[k]), float(T[k, 0]), float(T[k, 1]), float(T[k, 2])) for k in order]
    nodes = P.tolist()
    cos, sin = np.cos, np.sin
    for _ in range(sweeps):
        for i, j, dx, dy, dt in links:
            e0, e1 = nodes[i], nodes[j]
            c, s = cos(e0[2]), sin(e0[2])
            ex = (e1[0] - (e0[0] + c * dx - s * dy)) * alpha
            ey = (e1[1] - (e0[1] + s * dx + c * dy)) * alpha
            e0[0] += ex
            e0[1] += ey
            e1[0] -= ex
            e1[1] -= ey
            df = (e1[2] - (e0[2] + dt) + np.pi) % _TWO_PI - np.pi
            e0[2] = (e0[2] + alpha * df + np.pi) % _TWO_PI - np.pi
            e1[2] = (e1[2] - alpha * df + np.pi) % _TWO_PI - np.pi
    P[:] = np.asarray(nodes, dtype=float).reshape(P.shape)
