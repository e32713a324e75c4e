"""The sparse linear algebra of :func:`~hippomap.least_squares.solve_lsq` (and of the headings-first
init, :mod:`hippomap.headings_first`): one fill-reducing order per graph structure
(:func:`group_order`), the symmetric-mode LU in that order (:func:`_spd_factor`), and the normal
equations assembled on a fixed sparsity pattern (:func:`_normal_pattern`, laid out per solve by
:func:`_lsq_layout`). The orders and layouts of the last few graph structures are remembered: the
same numbers as computing them again.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["group_order"]


def _structure_key(*arrays: np.ndarray) -> tuple[bytes, ...]:
    """The bytes of a graph's index arrays (int64) or masks (bool): a memo key that tells two
    structures apart exactly."""
    return tuple(
        np.ascontiguousarray(x, dtype=bool if np.asarray(x).dtype == bool else np.int64).tobytes() for x in arrays
    )


def group_order(n_groups: int, a: np.ndarray, b: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Fill-reducing elimination order of the kept groups (:func:`_group_order`), remembered for
    the last few structures: the robust reweighting and a closure applied over several steps solve
    an unchanged graph again, and with the bias estimated the headings-first init and the
    Gauss–Newton solve order the same graph. Same numbers as computing it (read-only array)."""
    return _group_order_memo(int(n_groups), *_structure_key(a, b, np.asarray(keep, dtype=bool)))


@functools.lru_cache(maxsize=8)
def _group_order_memo(n_groups: int, a: bytes, b: bytes, keep: bytes) -> np.ndarray:
    out = _group_order(n_groups, np.frombuffer(a, np.int64), np.frombuffer(b, np.int64), np.frombuffer(keep, bool))
    out.flags.writeable = False
    return out


def _group_order(n_groups: int, a: np.ndarray, b: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Fill-reducing elimination order of the kept groups of unknowns of a sparse symmetric system
    in which group ``a[k]`` is coupled to group ``b[k]`` (a pose graph's nodes, and its bias).

    Minimum degree (SuperLU's MMD on A + Aᵀ) on the graph of the groups, not of the unknowns: the
    three unknowns of a node always share their couplings, so the node graph (a third of the
    unknowns, a ninth of the entries) orders them with about the fill of an order of the unknowns
    (measured: the same on a 407-node simulated loop map). The order is computed once per solve and
    reused by every factorisation of the solve (the Gauss–Newton iterations and their damped
    retries, the two Laplacian solves of :func:`~hippomap.headings_first.rotation_first_inits`) instead of once per
    factorisation, where SuperLU's ordering cost more than the factorisation itself.
    Returns the ids of the kept groups in elimination order."""
    kept = np.flatnonzero(keep)
    if len(kept) <= 2:
        return kept
    pos = np.full(n_groups, -1, dtype=np.int64)
    pos[kept] = np.arange(len(kept))
    pa, pb = pos[a], pos[b]
    ok = (pa >= 0) & (pb >= 0) & (pa != pb)
    pa, pb = pa[ok], pb[ok]
    nk = len(kept)
    deg = np.bincount(pa, minlength=nk) + np.bincount(pb, minlength=nk)
    # a diagonally dominant matrix with the groups' coupling pattern: factorable without pivoting
    rows = np.concatenate([pa, pb, np.arange(nk)])
    cols = np.concatenate([pb, pa, np.arange(nk)])
    vals = np.concatenate([-np.ones(2 * len(pa)), deg + 1.0])
    C = sp.csc_matrix((vals, (rows, cols)), shape=(nk, nk))
    lu = spla.splu(
        C, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, relax=1, panel_size=1, options={"SymmetricMode": True}
    )
    return kept[np.argsort(lu.perm_c, kind="stable")]


def _spd_factor(A: sp.spmatrix):
    """Sparse LU of a symmetric positive definite matrix whose rows and columns are already in a
    fill-reducing order (:func:`group_order`): symmetric mode, no pivoting, no re-ordering, and
    no relaxed supernodes or panels (``relax=1, panel_size=1``): a pose graph's factor has only
    small supernodes, and SuperLU's defaults made the factorisation of a 400-node map 1.7 × slower
    (0.73 vs 0.44 ms CPU, same fill)."""
    return spla.splu(
        sp.csc_matrix(A),
        permc_spec="NATURAL",
        diag_pivot_thresh=0.0,
        relax=1,
        panel_size=1,
        options={"SymmetricMode": True},
    )


def _normal_pattern(col: np.ndarray, src: np.ndarray, dst: np.ndarray, bias_col: int, damp: np.ndarray):
    """The normal equations of a pose graph assembled on a fixed sparsity pattern, computed once per
    solve: link k touches unknowns (3 i, 3 i + 1, 3 i + 2, 3 j, 3 j + 1, 3 j + 2[, ``bias_col``]),
    placed at ``col`` (-1: held fixed, dropped); ``damp``: the diagonal added (kept unknowns' order).

    Returns ``H_of(Jk, e)``, which turns the links' weighted Jacobian blocks ``Jk`` (M, 3, q) and
    errors ``e`` (M, 3) into ``(H, damped, g)``: ``H = JᵀJ + diag(damp)`` (CSC), ``damped(λ)`` =
    ``H + λ diag(H)`` and ``g = −Jᵀe``. Each entry of H is one ``bincount`` over the links'
    6×6 (7×7) blocks into the fixed pattern, instead of a sparse JᵀJ product per iteration.

    The pattern (each block entry's place in the CSC data) is found per node block when every
    kept node's three unknowns sit in consecutive columns, as :func:`_lsq_layout_of` places them
    (:func:`_block_pattern`), else entry by entry (:func:`_entry_pattern`): the same integers."""
    nk = len(damp)
    loc = np.column_stack([3 * src, 3 * src + 1, 3 * src + 2, 3 * dst, 3 * dst + 1, 3 * dst + 2])
    if bias_col >= 0:
        loc = np.column_stack([loc, np.full(len(src), bias_col)])
    gk = col[loc]  # (M, q)
    c3 = col[: 3 * (len(col) // 3)].reshape(-1, 3)
    c3 = c3[c3[:, 0] >= 0]
    if nk > 0 and np.all(c3[:, 1:] == c3[:, :1] + np.array([1, 2])):
        ok, slot, indices, indptr = _block_pattern(col, gk, bias_col, nk)
    else:
        ok, slot, indices, indptr = _entry_pattern(gk, nk)
    nnz = len(indices)
    n_ok = int(ok.sum())
    s_link, s_diag = slot[:n_ok], slot[n_ok:]
    g_ok = gk >= 0

    def H_of(Jk: np.ndarray, e: np.ndarray):
        blocks = np.einsum("kri,krj->kij", Jk, Jk).ravel()[ok]
        data = np.asarray(np.bincount(s_link, weights=blocks, minlength=nnz), dtype=np.float64)
        data[s_diag] += damp
        H = sp.csc_matrix((data, indices, indptr), shape=(nk, nk))
        hd = data[s_diag].copy()

        def damped(lam: float) -> sp.csc_matrix:
            d = data.copy()
            d[s_diag] += lam * hd
            return sp.csc_matrix((d, indices, indptr), shape=(nk, nk))

        jte = np.einsum("kri,kr->ki", Jk, e)
        g = -np.bincount(gk[g_ok], weights=jte[g_ok], minlength=nk)
        return H, damped, g

    return H_of


def _entry_pattern(gk: np.ndarray, nk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The CSC pattern of the normal equations, one entry at a time: ``(ok, slot, indices,
    indptr)``: which of the links' (M, q, q) block entries are kept (both unknowns kept), the
    place in the CSC data of each kept entry (in block order) and then of each unknown's diagonal,
    and the pattern's row indices and column pointers (rows sorted within each column)."""
    m, q = gk.shape
    rr = np.broadcast_to(gk[:, :, None], (m, q, q)).ravel()
    cc = np.broadcast_to(gk[:, None, :], (m, q, q)).ravel()
    ok = (rr >= 0) & (cc >= 0)
    diag = np.arange(nk)
    keys = np.concatenate([cc[ok] * nk + rr[ok], diag * nk + diag])  # column-major: CSC order
    uniq, slot = np.unique(keys, return_inverse=True)
    indices = (uniq % nk).astype(np.int32)
    indptr = np.zeros(nk + 1, dtype=np.int32)
    indptr[1:] = np.cumsum(np.bincount(uniq // nk, minlength=nk))
    return ok, slot.reshape(-1), indices, indptr


def _block_pattern(
    col: np.ndarray, gk: np.ndarray, bias_col: int, nk: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_entry_pattern` (the same four arrays, the same integers) when every kept node's
    unknowns are three consecutive columns: the entries are deduplicated per block of two groups
    of unknowns (a node's three, the bias's one) instead of per entry, a ninth of the sort.

    A block (rows of group R, columns of group C) covers the rows ``r0 … r0 + |R| − 1`` of the
    columns ``c0 … c0 + |C| − 1``; blocks of distinct group pairs share no entry. A kept group that
    no kept link touches has only its diagonal (``diag(damp)``). In CSC order the entries of the
    columns of group C are its blocks in the order of their first row, each contributing its
    rows (one, the diagonal's, for a diagonal-only block) to every column of C; an entry's place
    is therefore ``indptr[column] + (entries of C's earlier blocks) + (its row within the block)``."""
    m, q = gk.shape
    pos_off = np.array([0, 1, 2, 0, 1, 2, 0])[:q]  # loc position -> unknown within its group
    gstart = gk[:, [0, 3, 6][: (q + 2) // 3]]  # (M, G) first column of each group, -1 held
    ng = gstart.shape[1]
    size_at = np.zeros(nk + 1, dtype=np.int64)  # group size by first column (index nk: held)
    nodes = col[: 3 * (len(col) // 3) : 3]
    size_at[nodes[nodes >= 0]] = 3
    if bias_col >= 0 and col[bias_col] >= 0:
        size_at[col[bias_col]] = 1
    first = np.flatnonzero(size_at[:nk])  # every kept group, by first column
    r0 = np.broadcast_to(gstart[:, :, None], (m, ng, ng))
    c0 = np.broadcast_to(gstart[:, None, :], (m, ng, ng))
    bok = (r0 >= 0) & (c0 >= 0)
    keys = np.concatenate([(c0 * nk + r0)[bok], first * nk + first])  # column-major, as the entries
    n_full = len(keys) - len(first)
    ukey, inv = np.unique(keys, return_inverse=True)
    inv = inv.reshape(-1)
    full = np.zeros(len(ukey), dtype=bool)
    full[inv[:n_full]] = True
    ur, uc = ukey % nk, ukey // nk
    cnt = np.where(full, size_at[ur], 1)  # rows the block gives each of its columns
    seg = np.flatnonzero(np.concatenate(([True], uc[1:] != uc[:-1])))  # first block of each column group
    before = np.cumsum(cnt) - cnt
    seg_of = np.repeat(np.arange(len(seg)), np.diff(np.append(seg, len(ukey))))
    off = before - before[seg[seg_of]]  # entries of the column group's earlier blocks
    seg_cnt = np.add.reduceat(cnt, seg)
    colcnt = np.repeat(seg_cnt, size_at[uc[seg]])  # the groups tile the columns in order
    indptr = np.zeros(nk + 1, dtype=np.int32)
    indptr[1:] = np.cumsum(colcnt)
    # the kept links' block entries, in (link, row position, column position) order: each block of
    # (M, G, G) repeated over its group's positions (3, 3[, 1])
    reps = np.array([3, 3, 1])[:ng]
    ub = np.zeros((m, ng, ng), dtype=np.int64)
    ub[bok] = off[inv[:n_full]]
    ok = np.repeat(np.repeat(bok, reps, axis=1), reps, axis=2).ravel()
    base = indptr[np.where(gk >= 0, gk, 0)]  # (M, q) first entry of each position's column
    link_slot = np.repeat(np.repeat(ub, reps, axis=1), reps, axis=2) + base[:, None, :] + pos_off[None, :, None]
    # each unknown's diagonal: in its group's diagonal block
    u = np.arange(nk)
    g0 = np.repeat(first, size_at[first])  # the groups tile the columns in order
    dblock = np.repeat(inv[n_full:], size_at[first])
    diag_slot = indptr[u] + off[dblock] + np.where(full[dblock], u - g0, 0)
    slot = np.concatenate([link_slot.ravel()[ok], diag_slot])
    # the row of every entry of the pattern (written once per link block it appears in: same value)
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    indices[slot] = np.concatenate([np.broadcast_to(gk[:, :, None], (m, q, q)).ravel()[ok], u])
    return ok, slot, indices, indptr


def _lsq_layout(
    n: int, src: np.ndarray, dst: np.ndarray, anchor: int | None, fixed, bdt: np.ndarray | None, bias_information: float
):
    """:func:`_lsq_layout_of`, remembered for the last eight structures (the layout depends on
    ``bdt`` only through which links carry the bias): consecutive solves of an unchanged graph
    (the robust reweighting's, a closure being applied over several steps) reuse its order and
    normal-equation pattern. Returns the same numbers as computing it (read-only arrays). Eight, not
    two: a whole solve with the bias, its test and the solve without it, and the local solves between,
    interleave: on an 8354-frame run, with two, 55 of the 296 layouts computed had been computed before;
    with eight, 16 of 257 (a layout of a 2700-node map holds about 1.5 MB)."""
    fx = np.zeros(0, np.int64) if fixed is None else np.asarray(fixed, dtype=np.int64).reshape(-1)
    odo = np.zeros(0, bool) if bdt is None else np.asarray(bdt) != 0
    return _lsq_layout_memo(
        int(n),
        *_structure_key(src, dst, fx, odo),
        None if anchor is None else int(anchor),
        fixed is None,
        bdt is None,
        float(bias_information),
    )


@functools.lru_cache(maxsize=8)
def _lsq_layout_memo(
    n: int,
    src: bytes,
    dst: bytes,
    fixed: bytes,
    odo: bytes,
    anchor: int | None,
    no_fixed: bool,
    no_bias: bool,
    bias_information: float,
):
    bdt = None if no_bias else np.frombuffer(odo, bool).astype(float)
    fx = None if no_fixed else np.frombuffer(fixed, np.int64)
    nv, idx, col, H_of = _lsq_layout_of(
        n, np.frombuffer(src, np.int64), np.frombuffer(dst, np.int64), anchor, fx, bdt, bias_information
    )
    idx.flags.writeable = col.flags.writeable = False
    return nv, idx, col, H_of


def _lsq_layout_of(
    n: int, src: np.ndarray, dst: np.ndarray, anchor: int | None, fixed, bdt: np.ndarray | None, bias_information: float
):
    """The unknowns of one :func:`solve_lsq` and their normal equations' pattern, computed once per
    solve: the three pose unknowns of every node, then the bias when ``bdt`` (the links' bias
    factors, only when the bias is estimated) is given. The anchor's and ``fixed`` nodes' unknowns
    are held (dropped); the kept ones are placed in the fill-reducing order of their nodes
    (:func:`group_order`, the bias being group ``n``). Returns ``(nv, idx, col, H_of)``: the number
    of unknowns, the kept ones in elimination order, each unknown's column (-1: held) and the
    assembler of :func:`_normal_pattern`."""
    est = bdt is not None
    deg = np.bincount(src, minlength=n) + np.bincount(dst, minlength=n)
    damp = np.repeat(np.where(deg > 0, 0.0, 1.0), 3) + (1e-9 if anchor is None else 0.0)
    nv = 3 * n + (1 if est else 0)  # unknowns: the poses, then the bias
    if est:
        damp = np.append(damp, bias_information if bias_information > 0 else 1e-9)
    keep = np.ones(nv, dtype=bool)
    if anchor is not None:
        keep[3 * anchor : 3 * anchor + 3] = False
    if fixed is not None:
        f3 = 3 * np.asarray(fixed, dtype=np.int64).reshape(-1)
        keep[np.concatenate([f3, f3 + 1, f3 + 2])] = False
        if anchor is None and len(f3):
            damp = damp - 1e-9  # the fixed nodes fix the gauge
    groups = np.arange(nv) // 3
    ga, gb = src, dst
    if bdt is not None:
        odo = np.flatnonzero(bdt != 0)
        ga, gb = np.concatenate([src, src[odo], dst[odo]]), np.concatenate([dst, np.full(2 * len(odo), n)])
    gkeep = np.zeros(n + 1, dtype=bool)
    np.logical_or.at(gkeep, groups, keep)
    gorder = group_order(n + 1, ga, gb, gkeep)
    grank = np.empty(n + 1, dtype=np.int64)
    grank[gorder] = np.arange(len(gorder))
    kv = np.flatnonzero(keep)
    idx = kv[np.argsort(grank[groups[kv]], kind="stable")]  # the kept unknowns, in elimination order
    col = np.full(nv, -1, dtype=np.int64)
    col[idx] = np.arange(len(idx))
    return nv, idx, col, _normal_pattern(col, src, dst, 3 * n if est else -1, damp[idx])
