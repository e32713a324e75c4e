"""Map relaxation (Eq. 14, [ORS] iterate) and the exact pose-graph solver."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap import headings_first
from hippomap.errors import InputError
from hippomap.geometry import between, compose, integrate
from hippomap.headings_first import rate_turns, rotation_first_init, rotation_first_inits
from hippomap.least_squares import graph_cost, solve_lsq
from hippomap.relaxation import (
    MAX_COLOURS,
    colour_link,
    edge_colouring,
    link_residuals,
    relax,
    relax_jacobi,
    relax_ors_reference,
)


def square_loop(side_nodes=10, spacing=0.5, bias=0.02):
    """Square loop of nodes; odometry links corrupted by a constant heading bias per link,
    the closing link (last -> first) measured exactly. Returns gt, odo, src, dst, T."""
    inc = []
    for _ in range(4):
        inc += [(spacing, 0.0, 0.0)] * (side_nodes - 1) + [(spacing, 0.0, np.pi / 2)]
    inc = np.array(inc)
    gt = integrate(inc[:-1])
    noisy = inc.copy()
    noisy[:, 2] += bias
    odo = integrate(noisy[:-1])
    n = len(gt)
    src = np.append(np.arange(n - 1), n - 1)
    dst = np.append(np.arange(1, n), 0)
    T = np.vstack([noisy[:-1], between(gt[-1], gt[0])])
    return gt, odo, src, dst, T


def rms_xy(a, b):
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def to_anchor(P, i=0):
    """The map seen from node i (gauge fix for un-anchored solvers)."""
    return between(P[i], P)


def random_graph(rng, n=15, extra=6, noise=0.0):
    """Chain + random extra links; transforms from true poses (+ noise); returns true, src, dst, T."""
    inc = np.column_stack([rng.uniform(0.2, 1.0, n - 1), rng.normal(0, 0.1, n - 1), rng.normal(0, 0.4, n - 1)])
    true = integrate(inc)
    src = list(range(n - 1))
    dst = list(range(1, n))
    while len(src) < n - 1 + extra:
        a, b = rng.integers(0, n, 2)
        if a != b:
            src.append(int(a))
            dst.append(int(b))
    src, dst = np.array(src), np.array(dst)
    T = between(true[src], true[dst]) + rng.normal(0, noise, (len(src), 3))
    return true, src, dst, T


# ----------------------------------------------------------------------------- drift removal
@pytest.mark.parametrize("solver", ["relax", "jacobi", "lsq"])
def test_relaxation_removes_injected_heading_drift(solver):
    gt, odo, src, dst, T = square_loop(bias=0.02)
    before = rms_xy(odo, gt)
    assert before > 1.0  # 0.8 rad of accumulated heading error: the loop is badly open
    P = odo.copy()
    if solver == "relax":
        relax(P, src, dst, T, 2000)
    elif solver == "jacobi":
        relax_jacobi(P, src, dst, T, 20000)
    else:
        solve_lsq(P, src, dst, T)
    after = rms_xy(P, gt)
    assert after < before / 15, (before, after)
    np.testing.assert_allclose(P[0], gt[0], atol=1e-12)  # the anchor keeps its pose


@pytest.mark.parametrize("solver", ["relax", "jacobi", "lsq", "ors"])
def test_uncorrupted_loop_stays_put(solver):
    gt, _, src, dst, T = square_loop(bias=0.0)
    P = gt.copy()
    {
        "relax": lambda: relax(P, src, dst, T, 50),
        "jacobi": lambda: relax_jacobi(P, src, dst, T, 50),
        "lsq": lambda: solve_lsq(P, src, dst, T),
        "ors": lambda: relax_ors_reference(P, src, dst, T, 50),
    }[solver]()
    np.testing.assert_allclose(P, gt, atol=1e-9)


def test_lsq_reaches_a_lower_cost_than_relaxation():
    gt, odo, src, dst, T = square_loop(bias=0.02)
    Pr, Pl = odo.copy(), odo.copy()
    relax(Pr, src, dst, T, 3000)
    res = solve_lsq(Pl, src, dst, T)
    assert res.iterations < 10
    assert graph_cost(Pl, src, dst, T) <= graph_cost(Pr, src, dst, T) + 1e-12
    assert graph_cost(Pl, src, dst, T) < graph_cost(odo, src, dst, T) / 100


def test_weighted_lsq_trusts_links_by_their_information():
    """The closing link of a drifted square measured with an error of 0.1 rad: with unit
    information the error is spread over the loop; when the odometry links are 1000x more
    informative, the solution stays near the odometry and the weak link takes the error."""
    gt, odo, src, dst, T = square_loop(bias=0.0)
    T = T.copy()
    T[-1, 2] += 0.1  # the loop link's heading is wrong
    weak = np.ones((len(src), 3)) * 1000.0
    weak[-1] = 1.0
    P_unit, P_weak = odo.copy(), odo.copy()
    solve_lsq(P_unit, src, dst, T, iterations=50)
    solve_lsq(P_weak, src, dst, T, iterations=50, information=weak)
    assert rms_xy(P_weak, gt) < rms_xy(P_unit, gt) / 20
    r = link_residuals(P_weak, src, dst, T)
    assert abs(r[-1, 2]) > 0.09 and np.max(np.abs(r[:-1, 2])) < 1e-3
    # the optimum is the minimum of the weighted cost, not of the unit one
    assert graph_cost(P_weak, src, dst, T, weak) < graph_cost(P_unit, src, dst, T, weak)
    assert graph_cost(P_unit, src, dst, T) < graph_cost(P_weak, src, dst, T)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.01, 100.0))
def test_uniformly_scaled_information_gives_the_unit_solution(seed, scale):
    rng = np.random.default_rng(seed)
    true, src, dst, T = random_graph(rng, noise=0.05)
    start = true + rng.normal(0, 0.05, true.shape)
    A, B = start.copy(), start.copy()
    solve_lsq(A, src, dst, T, iterations=30)
    solve_lsq(B, src, dst, T, iterations=30, information=np.full((len(src), 3), scale))
    np.testing.assert_allclose(A, B, atol=1e-6)


def test_bad_information_raises_input_error():
    gt, odo, src, dst, T = square_loop()
    for info, text in (
        (np.ones((3, 3)), "shape"),
        (np.full((len(src), 3), -1.0), "finite and > 0"),
        (np.full((len(src), 3), np.nan), "finite and > 0"),
    ):
        with pytest.raises(InputError, match=text):
            solve_lsq(odo.copy(), src, dst, T, information=info)


# ----------------------------------------------------------------------------- agreement with [ORS]
def test_vectorised_relax_matches_ors_on_a_consistent_graph():
    """Perturbed poses, consistent links: both converge to the same (exact) map, up to gauge."""
    rng = np.random.default_rng(3)
    true, src, dst, T = random_graph(rng, n=14, extra=5)
    start = true + rng.normal(0, 0.3, true.shape)
    Po, Pv, Pj = start.copy(), start.copy(), start.copy()
    relax_ors_reference(Po, src, dst, T, 3000)
    relax(Pv, src, dst, T, 3000, anchor=None)
    relax_jacobi(Pj, src, dst, T, 20000, anchor=None)
    for P in (Po, Pv, Pj):
        np.testing.assert_allclose(link_residuals(P, src, dst, T), 0, atol=1e-7)
        np.testing.assert_allclose(to_anchor(P), to_anchor(true), atol=1e-6)


def test_vectorised_relax_agrees_with_ors_at_convergence_on_an_inconsistent_loop():
    """With an inconsistent loop the [ORS] loop and its vectorised form settle on (nearly) the same
    map: the differences are far below the inconsistency they distribute."""
    gt, odo, src, dst, T = square_loop(side_nodes=5, bias=0.05)
    Po, Pv, Pj = odo.copy(), odo.copy(), odo.copy()
    relax_ors_reference(Po, src, dst, T, 3000)
    relax(Pv, src, dst, T, 3000, anchor=None)
    relax_jacobi(Pj, src, dst, T, 30000, anchor=None)
    open_gap = np.hypot(*link_residuals(odo, src, dst, T)[-1, :2])
    assert open_gap > 1.0
    for P in (Pv, Pj):
        diff = np.max(np.hypot(*(to_anchor(P) - to_anchor(Po))[:, :2].T))
        assert diff < 0.01 * open_gap, diff
    # and all three removed most of the error
    for P in (Po, Pv, Pj):
        assert rms_xy(to_anchor(P), to_anchor(gt)) < rms_xy(to_anchor(odo), to_anchor(gt)) / 5


def test_link_order_inside_a_sweep_does_not_change_the_convergence_rate():
    """Why colouring is legitimate: [ORS] in id order vs the vectorised (colour) order, same sweeps."""
    gt, odo, src, dst, T = square_loop(side_nodes=15, bias=0.01)
    Po, Pv = odo.copy(), odo.copy()
    relax_ors_reference(Po, src, dst, T, 200)
    relax(Pv, src, dst, T, 200, anchor=None)
    eo = rms_xy(to_anchor(Po), to_anchor(gt))
    ev = rms_xy(to_anchor(Pv), to_anchor(gt))
    e0 = rms_xy(to_anchor(odo), to_anchor(gt))
    assert eo < 0.8 * e0 and ev < 0.8 * e0
    assert 0.7 < ev / eo < 1.3, (eo, ev)


# ----------------------------------------------------------------------------- stability
def hub_graph(rng, spokes=40):
    """A hub with many links (a much-revisited pruned node) plus a ring through the spokes."""
    ang = np.linspace(0, 2 * np.pi, spokes, endpoint=False)
    true = np.vstack([[0.0, 0.0, 0.0], np.column_stack([2 * np.cos(ang), 2 * np.sin(ang), ang])])
    src = np.concatenate([np.zeros(spokes, int), np.arange(1, spokes + 1)])
    dst = np.concatenate([np.arange(1, spokes + 1), np.roll(np.arange(1, spokes + 1), -1)])
    T = between(true[src], true[dst]) + rng.normal(0, 0.05, (len(src), 3))
    return true, src, dst, T


@pytest.mark.parametrize("solver", ["relax", "jacobi"])
def test_relaxation_is_stable_at_a_hub(solver):
    rng = np.random.default_rng(0)
    true, src, dst, T = hub_graph(rng)
    P = true + rng.normal(0, 0.2, true.shape)
    r0 = np.abs(link_residuals(P, src, dst, T)).max()
    fn = relax if solver == "relax" else relax_jacobi
    worst = 0.0
    for _ in range(50):
        fn(P, src, dst, T, 10)
        worst = max(worst, np.abs(link_residuals(P, src, dst, T)).max())
    assert np.all(np.isfinite(P))
    assert worst <= r0 * 1.5
    assert np.abs(link_residuals(P, src, dst, T)).max() < 0.5 * r0


def test_literal_simultaneous_eq14_is_unstable_at_a_hub():
    """The reason for the degree normalisation: the literal Jacobi Eq. 14, alpha = 0.5, blows up."""
    rng = np.random.default_rng(0)
    true, src, dst, T = hub_graph(rng)
    P = true + rng.normal(0, 0.2, true.shape)
    r0 = np.abs(link_residuals(P, src, dst, T)).max()
    with np.errstate(all="ignore"):
        relax_jacobi(P, src, dst, T, 30, normalise=False, anchor=None)
        r = np.abs(link_residuals(P, src, dst, T)).max()
    assert not np.isfinite(r) or r > 1e3 * r0


def test_colour_overflow_at_a_huge_hub_still_converges():
    rng = np.random.default_rng(1)
    true, src, dst, T = hub_graph(rng, spokes=MAX_COLOURS + 20)
    T = between(true[src], true[dst])  # consistent
    colours = edge_colouring(src, dst, len(true))
    assert (colours == -1).any()  # the hub has more links than colours
    P = true + rng.normal(0, 0.1, true.shape)
    relax(P, src, dst, T, 3000, colours=colours)
    np.testing.assert_allclose(link_residuals(P, src, dst, T), 0, atol=1e-6)


# ----------------------------------------------------------------------------- colouring
def test_edge_colouring_classes_are_matchings_and_incremental_equals_batch():
    rng = np.random.default_rng(5)
    _, src, dst, _ = random_graph(rng, n=60, extra=80)
    colours = edge_colouring(src, dst, 60)
    for c in np.unique(colours):
        ends = np.concatenate([src[colours == c], dst[colours == c]])
        assert len(np.unique(ends)) == len(ends)
    masks = np.zeros(60, dtype=np.int64)
    inc = [colour_link(masks, int(a), int(b)) for a, b in zip(src, dst)]
    np.testing.assert_array_equal(inc, colours)


# ----------------------------------------------------------------------------- properties
graphs = st.tuples(st.integers(0, 10_000), st.integers(3, 12), st.integers(0, 6))


@settings(max_examples=25, deadline=None)
@given(graphs)
def test_consistent_graph_is_a_fixed_point(g):
    seed, n, extra = g
    true, src, dst, T = random_graph(np.random.default_rng(seed), n=n, extra=extra)
    for fn in (
        lambda P: relax(P, src, dst, T, 20),
        lambda P: relax_jacobi(P, src, dst, T, 20),
        lambda P: solve_lsq(P, src, dst, T),
        lambda P: relax_ors_reference(P, src, dst, T, 5),
    ):
        P = true.copy()
        fn(P)
        np.testing.assert_allclose(P, true, atol=1e-8)


@settings(max_examples=20, deadline=None)
@given(graphs, st.floats(-np.pi, np.pi), st.floats(-50, 50), st.floats(-50, 50))
def test_relaxation_commutes_with_a_rigid_motion(g, th, x, y):
    seed, n, extra = g
    rng = np.random.default_rng(seed)
    true, src, dst, T = random_graph(rng, n=n, extra=extra, noise=0.1)
    P = true + rng.normal(0, 0.2, true.shape)
    motion = np.array([x, y, th])
    for fn in (
        lambda Q: relax(Q, src, dst, T, 15, anchor=None),
        lambda Q: relax_jacobi(Q, src, dst, T, 15, anchor=None),
        lambda Q: relax(Q, src, dst, T, 15),
        lambda Q: solve_lsq(Q, src, dst, T, iterations=3),
    ):
        A = P.copy()
        B = compose(motion, P)
        fn(A)
        fn(B)
        np.testing.assert_allclose(between(compose(motion, A), B)[:, :2], 0, atol=1e-6)
        np.testing.assert_allclose(np.sin(between(compose(motion, A), B)[:, 2]), 0, atol=1e-6)


# ----------------------------------------------------------------------------- bad input
def test_bad_graphs_raise_input_error():
    P = np.zeros((3, 3))
    T = np.zeros((1, 3))
    with pytest.raises(InputError, match="outside"):
        relax(P, [0], [5], T, 1)
    with pytest.raises(InputError, match="self-link"):
        relax(P, [1], [1], T, 1)
    with pytest.raises(InputError, match="poses"):
        relax(np.zeros((3, 2)), [0], [1], T, 1)
    with pytest.raises(InputError, match="transforms"):
        solve_lsq(P, [0, 1], [1, 2], T)
    with pytest.raises(InputError, match="alpha"):
        relax(P, [0], [1], T, 1, alpha=1.5)
    with pytest.raises(InputError, match="in place"):
        relax(P.tolist(), [0], [1], T, 1)


# ----------------------------------------------------------------------------- headings-first initialisation
@pytest.mark.parametrize("drift", [1.0, 3.0])
def test_rotation_first_init_lets_gauss_newton_close_a_long_drifting_loop_in_a_few_iterations(drift):
    """A loop whose odometry gained ``drift`` rad of heading: from the odometric poses
    Gauss-Newton needs many damped iterations; from the headings-first start it is at the
    optimum in a few, and both end at the same cost."""
    side = 100
    gt, _, src, dst, T = square_loop(side_nodes=side, spacing=0.2, bias=0.0)
    n = len(gt)
    T = T.copy()
    T[:-1, 2] += drift / (n - 1)
    odo = integrate(T[:-1])
    info = np.tile([1810.0, 1810.0, 1810.0], (len(src), 1))
    info[-1] = [100.0, 100.0, 1000.0]
    plain = odo.copy()
    r_plain = solve_lsq(plain, src, dst, T, iterations=100, information=info)
    init = odo.copy()
    shift, bias = rotation_first_init(init, src, dst, T, information=info)
    assert bias == 0.0
    assert shift > 1.0  # the start moved a long way
    assert np.array_equal(init[0], odo[0])  # the anchor holds
    r_init = solve_lsq(init, src, dst, T, iterations=100, information=info)
    cost_plain = graph_cost(plain, src, dst, T, info)
    cost_init = graph_cost(init, src, dst, T, info)
    assert cost_init == pytest.approx(cost_plain, rel=1e-6)
    assert r_init.iterations <= 12 and r_init.iterations < r_plain.iterations
    assert rms_xy(init, gt) < 0.2


def test_rotation_first_init_takes_a_loop_past_half_a_turn_the_way_it_is_told():
    """A loop whose odometry turned 4 rad too far at a constant rate (more than π), solved with that
    rate as the odometry's bias: the closing link's residual, wrapped, reads as the opposite drift, and
    the init unwinds it the wrong way (a bias of the wrong sign, the square bent by a whole extra turn).
    ``heading_turns`` takes that link the other way round the circle: the right rate and map. (Which
    branch to take is the map's choice, by cost: ``tests/test_cognitive_map.py``.)"""
    side = 100
    gt, _, src, dst, T = square_loop(side_nodes=side, spacing=0.2, bias=0.0)
    n = len(gt)
    T = T.copy()
    rate = 4.0 / (n - 1)
    T[:-1, 2] += rate
    odo = integrate(T[:-1])
    info = np.tile([1810.0, 1810.0, 1810.0], (len(src), 1))
    bias = {"bias_dt": np.append(np.ones(n - 1), 0.0), "bias_information": 1.0 / 0.02**2}
    r = link_residuals(odo, src[-1:], dst[-1:], T[-1:])[0, 2]
    assert abs(r) < np.pi and abs(r - 4.0) > 1.0  # wrapped: not the drift
    wrapped, turned = odo.copy(), odo.copy()
    _, b_wrapped = rotation_first_init(wrapped, src, dst, T, information=info, **bias)
    turns = np.zeros(len(src))
    turns[-1] = -np.sign(r)
    _, b_turned = rotation_first_init(turned, src, dst, T, information=info, heading_turns=turns, **bias)
    assert b_turned == pytest.approx(rate, rel=0.01) and b_wrapped < 0
    assert rms_xy(turned, gt) < 0.05 < 2.0 < rms_xy(wrapped, gt)
    same = odo.copy()
    rotation_first_init(same, src, dst, T, information=info, heading_turns=np.zeros(len(src)), **bias)
    np.testing.assert_array_equal(same, wrapped)  # no turns: the wrapped reading


@pytest.mark.parametrize("with_bias", [False, True])
def test_branches_share_one_factor_and_give_each_call_s_own_poses(with_bias, monkeypatch):
    """``rotation_first_inits`` factorises the two Laplacians once for every branch: each branch's
    poses, shift and bias are bit for bit those of a ``rotation_first_init`` call of its own, and the
    poses it starts from are left alone."""
    side = 60
    gt, _, src, dst, T = square_loop(side_nodes=side, spacing=0.2, bias=0.0)
    n = len(gt)
    T = T.copy()
    T[:-1, 2] += 4.0 / (n - 1)
    odo = integrate(T[:-1])
    info = np.tile([1810.0, 1810.0, 900.0], (len(src), 1))
    bias = {"bias_dt": np.append(np.ones(n - 1), 0.0), "bias_information": 1.0 / 0.02**2} if with_bias else {}
    branches = [None]
    for k in (-2, -1, 1, 2):
        turns = np.zeros(len(src))
        turns[-1] = k
        branches.append(turns)
    factored = []
    factor = headings_first._spd_factor
    monkeypatch.setattr(headings_first, "_spd_factor", lambda L: factored.append(L.shape) or factor(L))
    start = odo.copy()
    inits = rotation_first_inits(start, src, dst, T, info, anchor=0, branches=branches, **bias)
    np.testing.assert_array_equal(start, odo)
    assert len(factored) == 2  # headings and positions, once for the five branches
    monkeypatch.undo()
    assert len(inits) == len(branches)
    for turns, (Q, shift, b) in zip(branches, inits):
        one = odo.copy()
        shift1, b1 = rotation_first_init(one, src, dst, T, information=info, heading_turns=turns, **bias)
        np.testing.assert_array_equal(Q, one)
        assert (shift, b) == (shift1, b1)
    # the branches differ: a whole turn more on the closing link is another map
    assert not np.array_equal(inits[0][0], inits[1][0])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_rotation_first_init_is_exact_on_a_consistent_graph(seed):
    """Links that all agree with one set of poses: the init recovers those poses (from a
    corrupted start, anchor held) without any Gauss-Newton step."""
    rng = np.random.default_rng(seed)
    true, src, dst, T = random_graph(rng)
    start = true + np.column_stack([rng.normal(0, 0.5, (len(true), 2)), rng.normal(0, 0.5, len(true))])
    start[0] = true[0]
    rotation_first_init(start, src, dst, T)
    assert np.allclose(start[:, :2], true[:, :2], atol=1e-8)
    assert np.allclose(np.angle(np.exp(1j * (start[:, 2] - true[:, 2]))), 0.0, atol=1e-8)


def test_rotation_first_init_rejects_bad_information():
    true, src, dst, T = random_graph(np.random.default_rng(0))
    with pytest.raises(InputError, match="information"):
        rotation_first_init(true.copy(), src, dst, T, information=np.zeros((len(src), 3)))


def _gyro_bias_loop(beta: float):
    """A 2-lap-length square loop whose odometric links all gain ``beta`` rad per second of heading
    (one second per link), closed by one exact link; returns gt, odo, src, dst, T, bias_dt, info."""
    gt, _, src, dst, T = square_loop(side_nodes=100, spacing=0.2, bias=0.0)
    T = T.copy()
    dt = np.ones(len(src))
    dt[-1] = 0.0  # the closing link is not odometry
    T[:-1, 2] += beta * dt[:-1]
    info = np.tile([1810.0, 1810.0, 1810.0], (len(src), 1))
    info[-1] = [100.0, 100.0, 1000.0]
    return gt, integrate(T[:-1]), src, dst, T, dt, info


@pytest.mark.parametrize("beta", [0.002, -0.005])
def test_the_odometry_heading_bias_is_estimated_with_the_poses(beta):
    """A constant turn-rate error (a gyro's drift) bends the whole loop: the solver that estimates
    it with the poses recovers it and the true loop; without it the error is spread as noise."""
    gt, odo, src, dst, T, dt, info = _gyro_bias_loop(beta)
    plain = odo.copy()
    solve_lsq(plain, src, dst, T, iterations=50, information=info)
    est = odo.copy()
    _, b0 = rotation_first_init(est, src, dst, T, information=info, bias_dt=dt, bias_information=1.0)
    res = solve_lsq(est, src, dst, T, iterations=50, information=info, bias_dt=dt, bias=b0, bias_information=1.0)
    assert res.bias == pytest.approx(beta, rel=1e-3)
    assert rms_xy(est, gt) < 1e-4 < 0.01 < rms_xy(plain, gt)
    # Gauss-Newton alone (from zero) finds it too
    gn = odo.copy()
    assert solve_lsq(
        gn, src, dst, T, iterations=50, information=info, bias_dt=dt, bias_information=1.0
    ).bias == pytest.approx(beta, rel=1e-3)
    # held fixed, it is only applied
    fixed = odo.copy()
    assert (
        solve_lsq(fixed, src, dst, T, iterations=50, information=info, bias_dt=dt, bias=beta, estimate_bias=False).bias
        == beta
    )
    assert rms_xy(fixed, gt) < 1e-4


def test_a_strong_bias_prior_holds_the_bias_at_zero():
    gt, odo, src, dst, T, dt, info = _gyro_bias_loop(0.003)
    P = odo.copy()
    res = solve_lsq(P, src, dst, T, iterations=50, information=info, bias_dt=dt, bias_information=1e12)
    assert abs(res.bias) < 1e-6


def _dense_bias_sigma(P, src, dst, T, dt, bias, prior, info, h=1e-6):
    """[(JᵀJ + prior)⁻¹]_bb by a finite-difference Jacobian of the weighted link errors (node 0 held)."""
    from hippomap.least_squares import _lsq_errors

    sw = np.sqrt(info)

    def errors(x):
        Q = P.copy()
        Q[1:] = x[:-1].reshape(-1, 3)
        Tb = T.copy()
        Tb[:, 2] -= x[-1] * dt
        return _lsq_errors(Q, src, dst, Tb, sw)[0].ravel()

    x0 = np.append(P[1:].ravel(), bias)
    e0 = errors(x0)
    J = np.empty((len(e0), len(x0)))
    for i in range(len(x0)):
        x = x0.copy()
        x[i] += h
        J[:, i] = (errors(x) - e0) / h
    H = J.T @ J
    H[-1, -1] += prior
    return float(np.sqrt(np.linalg.inv(H)[-1, -1]))


@pytest.mark.parametrize("closed", [False, True])
def test_bias_sigma_is_the_marginal_uncertainty_of_the_bias(closed):
    """Without a loop nothing but the prior observes the bias: its posterior sigma is the prior's.
    Closed by one link, the loop observes it: the sigma equals the dense inverse of the normal
    matrix and is far below the prior; it does not depend on the poses' gauge."""
    from hippomap.least_squares import bias_sigma

    gt, odo, src, dst, T, dt, info = _gyro_bias_loop(0.002)
    if not closed:
        src, dst, T, dt, info = src[:-1], dst[:-1], T[:-1], dt[:-1], info[:-1]
    P = odo.copy()
    solve_lsq(P, src, dst, T, iterations=50, information=info, bias_dt=dt, bias_information=1.0 / 0.02**2)
    sigma = bias_sigma(P, src, dst, T, dt, 0.002, 1.0 / 0.02**2, information=info)
    if not closed:
        assert sigma == pytest.approx(0.02, rel=1e-6)
        return
    assert sigma < 0.02 / 10
    assert sigma == pytest.approx(_dense_bias_sigma(P, src, dst, T, dt, 0.002, 1.0 / 0.02**2, info), rel=1e-3)
    moved = compose(np.tile([3.0, -2.0, 1.0], (len(P), 1)), P)  # the same map, rigidly moved
    prior = 1.0 / 0.02**2
    assert bias_sigma(moved, src, dst, T, dt, 0.002, prior, information=info) == pytest.approx(sigma, rel=1e-6)
    assert bias_sigma(P, src, dst, T, np.zeros(len(src)), information=info) == float("inf")  # nothing to observe
    with pytest.raises(InputError, match="bias_dt"):
        bias_sigma(P, src, dst, T, dt[:-1], information=info)


def test_bad_bias_arguments_raise_input_error():
    gt, odo, src, dst, T, dt, info = _gyro_bias_loop(0.0)
    with pytest.raises(InputError, match="bias_dt"):
        solve_lsq(odo.copy(), src, dst, T, information=info, bias_dt=dt[:-1])
    with pytest.raises(InputError, match="bias"):
        solve_lsq(odo.copy(), src, dst, T, information=info, bias_dt=dt, bias=float("nan"))


# ----------------------------------------------------------------------------- the solver's linear algebra
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.booleans(), st.booleans())
def test_normal_equations_on_the_fixed_pattern_equal_the_dense_jacobian_product(seed, with_bias, with_fixed):
    """``_normal_pattern`` assembles JᵀJ + damping and −Jᵀe per link block into a pattern in the
    nodes' elimination order; it must equal the dense product of the full Jacobian (held
    unknowns dropped), including parallel links and the bias column."""
    from hippomap.lsq_layout import _normal_pattern

    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 12))
    _, src, dst, _ = random_graph(rng, n=n, extra=int(rng.integers(0, 8)))
    m = len(src)
    nv = 3 * n + (1 if with_bias else 0)
    keep = np.ones(nv, dtype=bool)
    keep[:3] = False  # the anchor
    if with_fixed:
        f = int(rng.integers(1, n))
        keep[3 * f : 3 * f + 3] = False
    idx = rng.permutation(np.flatnonzero(keep))  # any order of the kept unknowns
    col = np.full(nv, -1, dtype=np.int64)
    col[idx] = np.arange(len(idx))
    q = 7 if with_bias else 6
    Jk = rng.normal(size=(m, 3, q))
    e = rng.normal(size=(m, 3))
    damp = rng.uniform(0.0, 2.0, len(idx))
    H, damped, g = _normal_pattern(col, src, dst, 3 * n if with_bias else -1, damp)(Jk, e)
    J = np.zeros((3 * m, nv))
    for k, (i, j) in enumerate(zip(src, dst)):
        cols = [3 * i, 3 * i + 1, 3 * i + 2, 3 * j, 3 * j + 1, 3 * j + 2] + ([3 * n] if with_bias else [])
        for c_local, c in enumerate(cols):
            J[3 * k : 3 * k + 3, c] += Jk[k, :, c_local]
    Jr = J[:, idx]
    ref = Jr.T @ Jr + np.diag(damp)
    np.testing.assert_allclose(H.toarray(), ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(g, -(Jr.T @ e.ravel()), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(damped(0.5).toarray(), ref + 0.5 * np.diag(np.diag(ref)), rtol=1e-12, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_solves_in_the_node_order_equal_a_dense_solve(seed):
    """The factorisation in :func:`group_order`'s order (no re-ordering, no pivoting) solves an
    SPD system with a pose graph's block pattern as a dense solve does; the order holds every
    kept group once and each group's unknowns together."""
    import scipy.sparse as sp

    from hippomap.lsq_layout import _spd_factor, group_order

    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 30))
    _, src, dst, _ = random_graph(rng, n=n, extra=int(rng.integers(0, 12)))
    keep = rng.random(n) > 0.2
    keep[0] = False
    order = group_order(n, src, dst, keep)
    assert sorted(order.tolist()) == np.flatnonzero(keep).tolist()
    # a block matrix with the graph's pattern, SPD: a weighted block Laplacian plus a diagonal
    A = np.zeros((3 * n, 3 * n))
    for i, j in zip(src, dst):
        B = rng.normal(size=(3, 3))
        W = B @ B.T + np.eye(3)
        A[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] += W
        A[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += W
        A[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] -= W
        A[3 * j : 3 * j + 3, 3 * i : 3 * i + 3] -= W
    A += np.eye(3 * n)
    idx = (3 * order[:, None] + np.arange(3)).ravel()
    b = rng.normal(size=len(idx))
    x = _spd_factor(sp.csc_matrix(A[np.ix_(idx, idx)])).solve(b)
    np.testing.assert_allclose(x, np.linalg.solve(A[np.ix_(idx, idx)], b), rtol=1e-8, atol=1e-10)


def test_a_step_that_only_rounding_makes_worse_ends_the_solve():
    """At the optimum a Gauss-Newton step can raise the cost by a few units in the last place (it
    does on this loop from the headings-first start); that ends the solve, poses kept, instead of a
    run of ever more damped retries until ``iterations`` (11 here without the rule)."""
    gt, _, src, dst, T = square_loop(side_nodes=100, spacing=0.2, bias=0.0)
    n = len(gt)
    T = T.copy()
    T[:-1, 2] += 1.0 / (n - 1)
    P = integrate(T[:-1])
    info = np.tile([1810.0, 1810.0, 1810.0], (len(src), 1))
    info[-1] = [100.0, 100.0, 1000.0]
    rotation_first_init(P, src, dst, T, information=info)
    r = solve_lsq(P, src, dst, T, iterations=100, information=info)
    assert r.iterations <= 4
    Q = P.copy()
    again = solve_lsq(Q, src, dst, T, iterations=100, information=info)
    assert again.iterations <= 2  # already at the optimum: at most a step and a refused one
    assert graph_cost(Q, src, dst, T, info) <= graph_cost(P, src, dst, T, info)


# ----------------------------------------------------------------------------- coupled visual links
@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_the_coupled_jacobian_is_the_derivative_of_the_coupled_errors(seed):
    """A coupled link's heading row is d(heading + coupling · y): checked against central differences."""
    from hippomap.least_squares import _lsq_errors, _lsq_jacobian

    rng = np.random.default_rng(seed)
    true, src, dst, T = random_graph(rng, noise=0.05)
    P = true + rng.normal(0, 0.05, true.shape)
    sw = np.sqrt(rng.uniform(0.5, 50.0, (len(src), 3)))
    coupling = np.where(rng.random(len(src)) < 0.5, rng.uniform(0.1, 1.0, len(src)), 0.0)
    e, c, s, dx, dy = _lsq_errors(P, src, dst, T, sw, coupling)
    J = _lsq_jacobian(c, s, dx, dy, sw, None, coupling)
    h = 1e-6
    for k in range(len(src)):
        for col, (node, axis) in enumerate(
            [(src[k], 0), (src[k], 1), (src[k], 2), (dst[k], 0), (dst[k], 1), (dst[k], 2)]
        ):
            Pp, Pm = P.copy(), P.copy()
            Pp[node, axis] += h
            Pm[node, axis] -= h
            num = (
                _lsq_errors(Pp, src, dst, T, sw, coupling)[0][k] - _lsq_errors(Pm, src, dst, T, sw, coupling)[0][k]
            ) / (2 * h)
            np.testing.assert_allclose(J[k, :, col], num, atol=1e-5)


def test_coupled_links_tell_a_sideways_step_from_a_turn():
    """A second pass 0.3 m beside the first, parallel to it, its shape fixed by odometry. Each of its
    nodes sees the first pass's node beside it, and what it measures is heading + lateral / 4 m (an
    image shift), the lateral offset itself only weakly (0 with 10 m⁻²). Read as a heading alone, the
    shift turns the second pass across the first; coupled, the map keeps it nearly parallel and
    beside it (the weak lateral prior still pulls it part of the way in)."""
    n, Z = 20, 4.0
    first = np.column_stack([np.arange(n) * 0.5, np.zeros(n), np.zeros(n)])
    second = first + [0.0, 0.3, 0.0]
    true = np.vstack([first, second])
    src = list(range(n - 1)) + list(range(n, 2 * n - 1))
    dst = list(range(1, n)) + list(range(n + 1, 2 * n))
    T = [between(true[a], true[b]) for a, b in zip(src, dst)]
    info = [(1e8, 1e8, 1e8)] * len(src)  # odometry: the passes' shapes
    for i in range(n):  # visual links second -> first: the first node seen from the second
        rel = between(true[n + i], true[i])  # (0, -0.3, 0)
        robot = between(true[i], true[n + i])  # the robot beside the node: (0, 0.3, 0)
        measured = robot[2] + robot[1] / Z  # what the image shift gives
        src.append(n + i)
        dst.append(i)
        T.append((rel[0], 0.0, -measured))  # heading read off the shift, lateral taken as 0
        info.append((100.0, 10.0, 1000.0))
    src, dst, T, info = np.array(src), np.array(dst), np.array(T), np.array(info)
    coupling = np.r_[np.zeros(2 * (n - 1)), np.full(n, 1 / Z)]
    start = np.vstack([first, first])  # the second pass starts on the first
    plain, coupled = start.copy(), start.copy()
    solve_lsq(plain, src, dst, T, iterations=50, information=info)
    solve_lsq(coupled, src, dst, T, iterations=50, information=info, coupling=coupling)
    # the truth has no coupled residual; the coupled solve is far nearer to it than the plain one
    from hippomap.least_squares import _lsq_errors

    assert np.max(np.abs(_lsq_errors(true, src, dst, T, None, coupling)[0][-n:, 2])) < 1e-12
    heading_err = [float(np.max(np.abs(P[n:, 2]))) for P in (plain, coupled)]
    lateral_err = [float(np.sqrt(np.mean((P[n:, 1] - 0.3) ** 2))) for P in (plain, coupled)]
    assert heading_err[0] > 0.06 and heading_err[1] < heading_err[0] / 4
    assert lateral_err[1] < lateral_err[0] / 2
    # all-zero coupling is the plain solve, bit for bit; a wrong shape is refused by name
    zero = start.copy()
    solve_lsq(zero, src, dst, T, iterations=50, information=info, coupling=np.zeros(len(src)))
    assert np.array_equal(zero, plain)
    with pytest.raises(InputError, match="coupling"):
        solve_lsq(start.copy(), src, dst, T, information=info, coupling=np.zeros(3))


@settings(max_examples=80, deadline=None)
@given(
    rate=st.floats(-0.06, 0.06),
    bias=st.floats(-0.02, 0.02),
    durations=st.lists(st.floats(20.0, 400.0), min_size=2, max_size=8),
    signs=st.lists(st.booleans(), min_size=8, max_size=8),
)
def test_rate_turns_offers_the_turns_one_drift_rate_asks_of_every_link(rate, bias, durations, signs):
    """``rate_turns``: loop links whose nodes lie ``duration`` s apart along the odometry, each reading the
    drift ``rate · duration`` wrapped into [−π, π): among the branches offered is the one that unwinds every
    link by its own whole turns, the wrapped reading itself is never offered, and every branch is whole
    turns, one per link, within ``turns``' reach."""
    dt = np.array([d if s else -d for d, s in zip(durations, signs)])
    truth = rate * dt
    residual = (truth + np.pi) % (2.0 * np.pi) - np.pi
    want = np.round((truth - residual) / (2.0 * np.pi))
    got = rate_turns(residual, dt, bias, max_rate=0.1, limit=1000)
    assert all(k.shape == dt.shape and np.array_equal(k, np.round(k)) for k in got)
    assert not any(np.array_equal(k, np.zeros_like(k)) for k in got)
    if np.any(want != 0) and np.all(np.abs(want) <= 2):
        assert any(np.array_equal(k, want) for k in got)
    assert len({k.tobytes() for k in got}) == len(got)


def test_rate_turns_unwinds_a_short_and_a_long_loop_apart():
    """A drift of 0.02 rad/s over a short loop (120 s: 2.4 rad, read right) and a long one (240 s: 4.8 rad,
    read −1.5 rad): one turn on the long loop's links and none on the short one's is the first branch (every
    link agrees with it); a rate beyond ``max_rate`` is not offered; residuals and durations must pair up."""
    dt = np.array([120.0, 121.0, 240.0, 241.0])
    residual = (0.02 * dt + np.pi) % (2.0 * np.pi) - np.pi
    got = rate_turns(residual, dt, 0.0, max_rate=0.06)
    np.testing.assert_array_equal(got[0], [0.0, 0.0, 1.0, 1.0])
    assert len(got) <= 4
    assert not any(np.array_equal(k, got[0]) for k in rate_turns(residual, dt, 0.0, max_rate=0.01))
    rest = rate_turns(residual, dt, 0.0, max_rate=0.06, exclude=[got[0]])  # branches already tried are skipped
    assert not any(np.array_equal(k, got[0]) for k in rest) and [k.tobytes() for k in rest[:2]] == [
        k.tobytes() for k in got[1:3]
    ]
    assert rate_turns(residual, np.zeros(4), 0.0, max_rate=0.06) == []
    with pytest.raises(ValueError):
        rate_turns(residual, dt[:3], 0.0, max_rate=0.06)


def test_a_solve_s_work_is_its_factors_nonzeros():
    """RelaxResult.work of solve_lsq: the nonzeros of the L and U factors of every factorisation it made, summed.
    A chain's factor has fewer nonzeros than the same chain closed by loop links across it, and a solve that
    makes no factorisation (no link) has done none."""
    rng = np.random.default_rng(3)
    n = 30
    src = np.arange(n - 1)
    dst = src + 1
    tr = np.column_stack([np.full(n - 1, 0.5), np.zeros(n - 1), np.full(n - 1, 0.2)])
    P = np.zeros((n, 3))
    for i in range(1, n):
        P[i] = compose(P[i - 1], tr[i - 1])
    P += rng.normal(0, 0.05, P.shape)
    chain = solve_lsq(P.copy(), src, dst, tr, iterations=1)
    a = np.arange(0, n - 10, 3)
    b = a + 10
    ls = np.concatenate([src, a])
    ld = np.concatenate([dst, b])
    ltr = np.vstack([tr, np.array([between(P[i], P[j]) for i, j in zip(a, b)])])
    closed = solve_lsq(P.copy(), ls, ld, ltr, iterations=1)
    assert chain.iterations == closed.iterations == 1
    assert 0 < chain.work < closed.work
    assert solve_lsq(P.copy(), src[:0], dst[:0], tr[:0]).work == 0
