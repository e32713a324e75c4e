"""The place cells made visible: the recorded iteration (Eq. 9-10) and its Fig. 8 figure."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.config import SpatialConfig
from hippomap.errors import InputError
from hippomap.grid_cells import GridCells
from hippomap.iteration_record import record_iteration, record_stored_field
from hippomap.place_cells import PlaceCells, noise_free_discharges
from hippomap.spatial_pathway import SpatialPathway
from hippomap.viz.place_field_figure import place_field_figure, place_field_png

# a small coding area (121 x 121) keeps the tables quick to build; the algebra is the same
SMALL = dict(area_size_m=0.06, resolution_m=0.0005, n_modules=4, cells_per_module=3)


@pytest.fixture(scope="module", params=["narrowest_first", "cyclic"])
def small(request):
    cfg = SpatialConfig(**SMALL, iteration_order=request.param)
    grid = GridCells(cfg)
    return cfg, grid.tables


@settings(max_examples=40, deadline=None)
@given(x=st.floats(0.0, 0.06), y=st.floats(0.0, 0.06), noise=st.lists(st.floats(-0.04, 0.04), min_size=12, max_size=12))
def test_recorded_iteration_finds_the_field_localise_finds(small, x, y, noise):
    cfg, tables = small
    T = noise_free_discharges(tables, cfg, (x, y)) + np.array(noise)
    fast = PlaceCells(tables, cfg).localise(T)
    rec = record_iteration(tables, T, cfg)
    if fast is None:
        assert rec.field is None
        return
    f = rec.field
    assert f is not None
    assert np.array_equal(f.indices, fast.indices)
    assert (f.iterations, f.skipped, f.cells, f.centroid) == (fast.iterations, fast.skipped, fast.cells, fast.centroid)
    # the steps: applied ones shrink POS to the product of their windows, skipped ones leave it alone
    N = tables.size
    pos = np.ones((N, N), bool)
    for s in rec.steps:
        mb = rec.window_matrix(s)
        assert int(mb.sum()) == s.ones
        if s.applied:
            assert (pos & mb).any()
            pos &= mb
        else:
            assert not (pos & mb).any()
        assert np.array_equal(rec.position_matrix(s), pos)
    assert rec.steps[-1].single and not any(s.single for s in rec.steps[:-1])
    assert np.array_equal(np.flatnonzero(pos), f.indices)
    assert len(rec.applied) == f.iterations
    # agreement is 1 exactly on the product of the applied windows
    assert np.array_equal(rec.agreement() == 1.0, pos)


def test_recording_draws_no_noise_and_reproduces_the_step():
    cfg = SpatialConfig(**SMALL, rate_noise=0.01)
    a, b = SpatialPathway(cfg), SpatialPathway(cfg)
    for _ in range(25):
        ca = a.step_increment(0.003, 0.001, 0.05)
        a.record()  # must not touch the noise stream
        cb = b.step_increment(0.003, 0.001, 0.05)
        assert (ca is None) == (cb is None)
        if ca is not None:
            assert np.array_equal(ca.field.indices, cb.field.indices)
    # without noise the recorded field is exactly the step's field
    p = SpatialPathway(SpatialConfig(**SMALL))
    for _ in range(10):
        code = p.step_increment(0.004, -0.002, 0.1)
        rec = p.record()
        assert code is not None and rec.field is not None
        assert np.array_equal(rec.field.indices, code.field.indices)
        # ... and a stored field (indices only) is recovered with its iteration
        again = record_stored_field(p.place_cells.tables, p.cfg, code.field.indices)
        assert np.array_equal(again.field.indices, code.field.indices)
        assert [s.cell for s in again.applied] == list(code.field.cells)


def test_record_rejects_bad_input(small):
    cfg, tables = small
    with pytest.raises(InputError):
        record_iteration(tables, np.zeros(3), cfg)
    with pytest.raises(InputError):
        record_stored_field(tables, cfg, [])
    with pytest.raises(InputError):
        record_stored_field(tables, cfg, [tables.size**2])
    with pytest.raises(InputError):
        noise_free_discharges(tables, cfg, (np.nan, 0.0))


def _dark_panels(img: np.ndarray) -> int:
    """Square panels of the binarised matrices: large components of the figure's 'zero' colour."""
    off = np.array([0x14, 0x14, 0x28])
    mask = (np.abs(img.astype(int) - off).max(axis=2) <= 6).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8))
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask)
    big = [
        s
        for s in stats[1:]
        if s[cv2.CC_STAT_WIDTH] > 80
        and s[cv2.CC_STAT_HEIGHT] > 80
        and 0.8 < s[cv2.CC_STAT_WIDTH] / s[cv2.CC_STAT_HEIGHT] < 1.25
    ]
    return len(big)


def test_figure_shows_windows_products_and_a_colour_scale():
    cfg = SpatialConfig()  # the paper's 40 cm area and 8 modules
    p = SpatialPathway(cfg)
    code = p.step_increment(0.05, 0.02, 0.3)
    rec = p.record()
    assert rec.field is not None and np.array_equal(rec.field.indices, code.field.indices)
    k = len(rec.applied)
    img = place_field_figure(rec)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    # one MB panel and one POS panel per product (k <= 8 here), all on the dark 'zero' colour
    assert 2 <= k <= 8
    assert _dark_panels(img) == 2 * k
    c = img.reshape(-1, 3).astype(int)
    yellow = ((c[:, 0] > 230) & (c[:, 1] > 190) & (c[:, 2] < 90)).sum()  # MB = 1
    cyan = ((c[:, 0] < 90) & (c[:, 1] > 200) & (c[:, 2] > 230)).sum()  # POS = 1
    assert yellow > 2000 and cyan > 200
    # the inferno colour bar: a tall strip whose colour runs from black through red to pale yellow
    inferno = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_INFERNO)[:, 0, ::-1]
    found = [np.abs(c[:, None, :] - inferno[None, [40, 128, 220], :]).max(axis=2).min(axis=0) < 25]
    assert np.all(found)
    # more products -> more panels: the figure grows with the iteration (whole area, capped at max_steps)
    wide = place_field_figure(rec, view_m=None, max_steps=8)
    assert _dark_panels(wide) == 2 * k
    narrow = place_field_figure(rec, max_steps=2)
    assert narrow.shape[1] < img.shape[1] or k <= 2
    png = place_field_png(rec)
    dec = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert dec.shape == img.shape and np.array_equal(dec[:, :, ::-1], img)
    with pytest.raises(InputError):
        place_field_figure(rec, max_steps=1)
