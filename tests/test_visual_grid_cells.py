"""Visual grid cells (paper Eqs. 1-5, spec §1): encoding, phase read-out, saccade decoding,
spatial view cells."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.config import VisualConfig
from hippomap.errors import InputError
from hippomap.visual_grid_cells import SpatialViewCells, VisualGridCells

GRID = VisualGridCells(VisualConfig())
W, H = 320, 240

points = st.tuples(st.integers(0, W - 1), st.integers(0, H - 1))


def test_population_shape_and_range():
    g = GRID.encode(np.array([[0, 0], [100.5, 37.25], [319, 239]]))
    assert g.shape == (3, 9 * 100)
    assert g.min() >= 0.0 and g.max() <= 1.0
    # r = 1/3 max(0, sum of three cosines) peaks at 1 where all three phases are 0 mod 2 pi
    assert np.isclose(GRID.encode(np.array([0.0, 0.0])).reshape(9, 100)[:, 0], 1.0).all()


def test_offsets_tile_the_unit_cell_exactly():
    # b_j . (u a1 + w a2) must be a multiple of 2 pi / 10 so the 100 offsets tile the rhombus (spec §1)
    k = GRID.offsets @ GRID.b.T / (2 * np.pi / 10)
    assert np.allclose(k, np.round(k), atol=1e-9)
    # and the 100 offsets are distinct phases modulo the lattice
    assert len({tuple(np.round(np.mod(r, 10)).astype(int)) for r in k}) == 100


def test_grid_spacing_matches_frequencies():
    # lambda = 4 pi / (sqrt 3 F): moving by lambda along the y axis (perpendicular to b_0)
    # returns every cell of module m to the same rate
    for m in (0, 4, 8):
        lam = GRID.spacing[m]
        x0 = np.array([13.0, 17.0])
        g0 = GRID.encode(x0).reshape(9, 100)[m]
        g1 = GRID.encode(x0 + np.array([0.0, lam])).reshape(9, 100)[m]
        assert np.allclose(g0, g1, atol=1e-9)
    assert GRID.spacing.max() == pytest.approx(4 * np.pi / (np.sqrt(3) * 2 * np.pi * 0.0014))


@given(points)
@settings(max_examples=200, deadline=None)
def test_phases_read_out(p):
    x = np.array(p, dtype=float)
    ph = GRID.phases(GRID.encode(x))
    true = GRID.F[:, None] * (GRID.b @ x)[None, :]
    err = np.angle(np.exp(1j * (ph - true)))
    assert np.abs(err).max() < 0.02  # spec §1 [T]: <= 0.011 rad


@given(points, points)
@settings(max_examples=400, deadline=None)
def test_decoded_saccade_within_one_pixel_for_any_displacement(a, b):
    """Every displacement inside a 320 x 240 frame is decoded to within 1 px (issue)."""
    xa, xb = np.array(a, float), np.array(b, float)
    d = GRID.decode(GRID.encode(xa), GRID.encode(xb))
    assert np.abs(d - (xb - xa)).max() <= 1


def test_decoding_extreme_displacements_and_batches():
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], float)
    a = np.repeat(corners, 4, axis=0)
    b = np.tile(corners, (4, 1))
    d = GRID.decode(GRID.encode(a), GRID.encode(b))
    assert d.shape == (16, 2)
    assert np.array_equal(d, (b - a).astype(int))
    # a batch decodes the same as one pair at a time
    singles = np.stack([GRID.decode(GRID.encode(p), GRID.encode(q)) for p, q in zip(a, b)])
    assert np.array_equal(singles, d)


def test_decoding_is_robust_to_rate_noise():
    rng = np.random.default_rng(7)
    a = rng.integers(0, [W, H], size=(500, 2)).astype(float)
    b = rng.integers(0, [W, H], size=(500, 2)).astype(float)
    ga = GRID.encode(a) + rng.normal(0, 0.05, (500, 900))
    gb = GRID.encode(b) + rng.normal(0, 0.05, (500, 900))
    err = np.linalg.norm(GRID.decode(ga, gb) - (b - a), axis=1)
    assert err.max() <= 2.0
    assert err.mean() < 0.5


def test_sub_pixel_positions_round_to_nearest():
    d = GRID.decode(GRID.encode(np.array([10.2, 20.0])), GRID.encode(np.array([50.0, 80.9])))
    assert np.abs(d - np.array([39.8, 60.9])).max() <= 1


@given(st.tuples(st.integers(0, 159), st.integers(0, 119)))
@settings(max_examples=60, deadline=None)
def test_spatial_view_cells_locate_the_fixation(p):
    svc = _svc()
    assert tuple(svc.locate(GRID.encode(np.array(p, float)))) == p


def test_spatial_view_cells_decode_matches_phase_decoder():
    svc = _svc()
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = rng.integers(0, [160, 120], size=(2, 2)).astype(float)
        ga, gb = GRID.encode(a), GRID.encode(b)
        assert np.array_equal(svc.decode(ga, gb), GRID.decode(ga, gb))


_SVC: list[SpatialViewCells] = []


def _svc() -> SpatialViewCells:
    if not _SVC:
        _SVC.append(SpatialViewCells(GRID, 160, 120, stride=4))
    return _SVC[0]


def test_bad_inputs_raise_input_error():
    with pytest.raises(InputError):
        GRID.encode(np.array([1.0, 2.0, 3.0]))
    with pytest.raises(InputError):
        GRID.encode(np.array([np.nan, 2.0]))
    with pytest.raises(InputError):
        GRID.decode(np.zeros(899), np.zeros(900))
    with pytest.raises(InputError):
        SpatialViewCells(GRID, 0, 10)
