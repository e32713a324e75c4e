"""The mapper's fast paths give the numbers of their reference paths: the remembered elimination
orders and normal-equation layouts of :mod:`hippomap.least_squares`, the array behind
``Mapper._recognisable``, and the whole solves that skip the headings-first init."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap import least_squares as ls
from hippomap import lsq_layout as lay
from hippomap.cognitive_map import CognitiveMap
from hippomap.config import MapConfig
from hippomap.geometry import integrate
from hippomap.headings_first import rotation_first_init
from hippomap.mapper import Mapper

from .test_cognitive_map import biased_square, corrected, drive, rms_xy, true_loops
from .test_mapper import CONFIG, feed, inputs  # noqa: F401  (module fixture)


def _graph(draw_seed: int, n: int, extra: int):
    rng = np.random.default_rng(draw_seed)
    src = np.concatenate([np.arange(n - 1), rng.integers(0, n, extra)])
    dst = np.concatenate([np.arange(1, n), rng.integers(0, n, extra)])
    ok = src != dst
    return src[ok], dst[ok], rng


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(2, 40), extra=st.integers(0, 30))
def test_remembered_group_order_equals_a_fresh_one(seed, n, extra):
    src, dst, rng = _graph(seed, n, extra)
    keep = rng.random(n) > 0.2
    fresh = lay._group_order(n, src, dst, keep)
    for _ in range(2):  # computed, then remembered
        got = lay.group_order(n, src, dst, keep)
        np.testing.assert_array_equal(got, fresh)
        assert not got.flags.writeable  # shared between solves: nobody may change it
    # another structure of the same size is not confused with it
    other = keep.copy()
    other[0] = not other[0]
    np.testing.assert_array_equal(lay.group_order(n, src, dst, other), lay._group_order(n, src, dst, other))


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(3, 30),
    extra=st.integers(0, 20),
    bias=st.booleans(),
    anchor=st.sampled_from([None, 0]),
    n_fixed=st.integers(0, 2),
)
def test_remembered_lsq_layout_equals_a_fresh_one(seed, n, extra, bias, anchor, n_fixed):
    src, dst, rng = _graph(seed, n, extra)
    fixed = rng.choice(np.arange(1, n), size=min(n_fixed, n - 1), replace=False) if n_fixed else None
    bdt = np.where(rng.random(len(src)) > 0.3, rng.random(len(src)), 0.0) if bias else None
    fresh = lay._lsq_layout_of(n, src, dst, anchor, fixed, bdt, 4.0)
    got = lay._lsq_layout(n, src, dst, anchor, fixed, bdt, 4.0)
    assert got[0] == fresh[0]
    np.testing.assert_array_equal(got[1], fresh[1])
    np.testing.assert_array_equal(got[2], fresh[2])
    q = 7 if bias else 6
    Jk, e = rng.normal(size=(len(src), 3, q)), rng.normal(size=(len(src), 3))
    (H1, d1, g1), (H2, d2, g2) = fresh[3](Jk, e), got[3](Jk, e)
    np.testing.assert_array_equal(H1.toarray(), H2.toarray())
    np.testing.assert_array_equal(d1(0.5).toarray(), d2(0.5).toarray())
    np.testing.assert_array_equal(g1, g2)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(2, 30),
    extra=st.integers(0, 40),
    bias=st.booleans(),
    n_held=st.integers(0, 3),
    isolated=st.integers(0, 3),
)
def test_block_pattern_equals_the_entry_pattern(seed, n, extra, bias, n_held, isolated):
    """The normal equations' pattern found per node block gives the integers of the pattern found
    entry by entry (parallel links, held nodes, nodes without links, the bias), for any order of
    the nodes with each node's unknowns consecutive (as the solver places them)."""
    src, dst, rng = _graph(seed, n, extra)
    n_all = n + isolated  # the last nodes have no link: only their diagonal
    nv = 3 * n_all + (1 if bias else 0)
    keep = np.ones(nv, dtype=bool)
    for f in rng.choice(n_all, size=min(n_held, n_all - 1), replace=False):
        keep[3 * f : 3 * f + 3] = False
    rank = rng.permutation(n_all + 1)  # any order of the groups (the bias is group n_all)
    kv = np.flatnonzero(keep)
    idx = kv[np.argsort(rank[np.arange(nv)[kv] // 3], kind="stable")]
    col = np.full(nv, -1, dtype=np.int64)
    col[idx] = np.arange(len(idx))
    bias_col = 3 * n_all if bias else -1
    loc = np.column_stack([3 * src, 3 * src + 1, 3 * src + 2, 3 * dst, 3 * dst + 1, 3 * dst + 2])
    if bias:
        loc = np.column_stack([loc, np.full(len(src), bias_col)])
    gk = col[loc]
    for want, got in zip(lay._entry_pattern(gk, len(idx)), lay._block_pattern(col, gk, bias_col, len(idx))):
        assert want.dtype == got.dtype
        np.testing.assert_array_equal(got, want)


def test_solves_give_the_same_poses_with_the_remembered_layouts():
    """Two solves of one graph (as the robust reweighting does): the second, on remembered orders
    and layouts, gives the poses the first gave, bit for bit."""
    rng = np.random.default_rng(4)
    n = 60
    src = np.concatenate([np.arange(n - 1), [0, 10, 20]])
    dst = np.concatenate([np.arange(1, n), [n - 1, 50, 40]])
    tr = np.column_stack([np.full(len(src), 0.5), np.zeros(len(src)), np.full(len(src), 2 * math.pi / n)])
    P0 = np.cumsum(rng.normal(0, 0.3, (n, 3)), axis=0)
    lay._group_order_memo.cache_clear()
    lay._lsq_layout_memo.cache_clear()
    out = []
    for _ in range(2):
        P = P0.copy()
        rotation_first_init(P, src, dst, tr)
        ls.solve_lsq(P, src, dst, tr)
        out.append(P)
    assert lay._lsq_layout_memo.cache_info().hits >= 1 and lay._group_order_memo.cache_info().hits >= 1
    np.testing.assert_array_equal(out[0], out[1])


def _recognisable_reference(m: Mapper, frames) -> list[int]:
    gap = m.config.mapper.recognition_min_path_m
    return sorted({int(f) for f in frames if m.distance - m.frame_path.get(int(f), -math.inf) >= gap})


def test_recognisable_matches_the_dict_reading(inputs):  # noqa: F811
    """The array behind ``_recognisable`` follows ``frame_path`` as frames are learned and after a
    restore, and names the same frames as reading the dict frame by frame."""
    m = Mapper(CONFIG)
    checked = 0
    for i in range(0, len(inputs), 40):
        feed(m, inputs[i : i + 40])
        frames = np.arange(-1, len(m.frame_path) + 3)  # unknown and negative ids too
        frames = frames[frames >= 0]
        assert m._recognisable(frames) == _recognisable_reference(m, frames)
        checked += len(m.frame_path) > 0
    assert checked and len(m.frame_path) > 5
    restored = Mapper.from_bytes(m.to_bytes())
    ids = np.array(sorted(m.frame_path))
    assert restored._recognisable(ids) == _recognisable_reference(m, ids)
    restored.frame_path = {}  # a replaced dict is read afresh
    assert restored._recognisable(ids) == ids.tolist()  # unknown frames: learned "infinitely" far back


def test_whole_solves_of_small_changes_skip_the_headings_first_init():
    """Corrections whose changed links all agree with the map, solved whole because their window
    held most of the map, skip the headings-first init; new loops and the final solve keep it."""
    inc, gt, noisy, first_lap = biased_square(side=6.0, laps=3)
    cmap = CognitiveMap(  # bias off: a whole solve with an insignificant bias initialises twice (item 34)
        MapConfig(prune_online=False, loop_transform_radius_m=3.0, lsq_window_hops=400, odometry_bias_sigma=0.0)
    )
    calls = []
    original_init, original_solve = cmap._rotation_init, cmap._solve_lsq

    original_small = cmap._small_change
    smalls = []
    cmap._small_change = lambda: (smalls.append(original_small()), smalls[-1])[1]

    def solve(window, rotation_init=True):
        calls.append((window is None, rotation_init, bool(smalls) and smalls[-1]))
        return original_solve(window, rotation_init)

    cmap._solve_lsq = solve
    inits = []
    cmap._rotation_init = lambda *a: (inits.append(1), original_init(*a))[1]
    drive(cmap, noisy, hypotheses=true_loops(gt, first_lap))
    cmap.finish()
    whole = [c for c in calls if c[0]]
    assert any(not init for _, init, _ in whole), "no whole solve of a small change"
    assert all(init == (not small) for _, init, small in whole[:-1])
    assert whole[-1][1]  # the final solve (finish) always re-initialises
    assert len(inits) == sum(init for _, init, _ in whole)


def test_small_corrections_wait_for_lsq_defer_m_of_path_and_new_loops_do_not():
    """A correction whose changed links all agree with the map waits until the robot has gone
    ``lsq_defer_m`` since the last solve, and is then solved with the ones after it; a change that
    disagrees with the map (a new loop) is solved at once. Far fewer solves, the same final map."""
    inc, gt, noisy, first_lap = biased_square(side=6.0, laps=3)
    out = {}
    for defer in (0.0, 1.0):
        cfg = MapConfig(prune_online=False, loop_transform_radius_m=3.0, lsq_defer_m=defer, lsq_defer_s=1e9)
        cmap = CognitiveMap(cfg)
        solves, waits = [], []
        original_deferred, original_solve = cmap._deferred, cmap._solve_lsq

        def deferred(t, cmap=cmap, original=original_deferred, waits=waits, solves=solves):
            small = cmap._small_change()
            d = original(t)
            if d:
                waits.append((cmap._path, small, solves[-1] if solves else -math.inf))
            return d

        def solve(window, rotation_init=True, cmap=cmap, original=original_solve, solves=solves):
            solves.append(cmap._path)
            return original(window, rotation_init)

        cmap._deferred, cmap._solve_lsq = deferred, solve
        node_at, off, _ = drive(cmap, noisy, hypotheses=true_loops(gt, first_lap))
        cmap.finish()
        assert not cmap._dirty
        out[defer] = (corrected(cmap, node_at, off), solves, waits)
    now, now_solves, now_waits = out[0.0]
    later, later_solves, later_waits = out[1.0]
    assert not now_waits  # 0: every change is solved at once
    assert later_waits, "no correction waited"
    # only small changes wait, and never beyond lsq_defer_m of path since the last solve
    assert all(small and path - last < 1.0 for path, small, last in later_waits)
    assert len(later_solves) < 0.5 * len(now_solves)
    assert rms_xy(later, gt) < rms_xy(now, gt) + 0.02
    assert rms_xy(later, now) < 0.05


def test_a_robot_that_stops_still_gets_its_small_corrections_solved():
    """Deferred corrections wait for ``lsq_defer_m`` of path *or* ``lsq_defer_s`` seconds: a robot
    that stops right after a small closure gets it solved once the time has passed."""
    inc, gt, noisy, first_lap = biased_square(side=6.0, laps=2)
    cmap = CognitiveMap(MapConfig(prune_online=False, loop_transform_radius_m=3.0, lsq_defer_m=1.0, lsq_defer_s=3.0))
    hyps = true_loops(gt, first_lap)
    odo = integrate(noisy)
    node_at, off = [cmap.current], [cmap.robot_offset]
    for k in range(1, len(noisy) + 1):
        t = k / 10.0  # 1 m/s: the path bound comes first while the robot moves
        cmap.update(odo[k], noisy[k - 1], t)
        for h in hyps(k, cmap, node_at, off):
            cmap.propose_loop(h)
        node_at.append(cmap.current)
        off.append(cmap.robot_offset)
        if k > first_lap + 40 and cmap._dirty and cmap._deferred(t):
            break
    else:
        raise AssertionError("no correction was deferred")
    waiting_since = cmap._solved_t
    # the robot stands still: no path, only time passes
    still = t
    while cmap._dirty:
        still += 0.1
        cmap.update(odo[k], (0.0, 0.0, 0.0), still)
        assert still - waiting_since < 3.0 + 0.15, "the deferred correction was never solved"
    assert still - waiting_since >= 3.0 - 1e-9
