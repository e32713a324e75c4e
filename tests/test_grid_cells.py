"""Grid cells (Eq. 6 with |k| = 4 pi / (sqrt 3 lambda)): the lattice spacing really is lambda, rate
matrices agree with Eq. 6, parameters follow SpatialConfig, tables are shared and consistent, in one
process and, through the files of ``HIPPOMAP_TABLE_CACHE``, between processes."""

from __future__ import annotations

import mmap
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap import grid_cells
from hippomap.config import SpatialConfig
from hippomap.grid_cells import LEVELS, GridCells, RateTables

SMALL = dict(area_size_m=0.03, resolution_m=0.0005)


def _single_cell(spacing: float, seed: int) -> GridCells:
    cfg = SpatialConfig(n_modules=1, cells_per_module=1, spacing_min_m=spacing, spacing_max_m=spacing, seed=seed)
    return GridCells(cfg)


def _lattice_dirs(theta: float) -> np.ndarray:
    """The 6 unit vectors from a firing field to its neighbours: theta + 30 deg + m 60 deg."""
    a = theta + np.pi / 6 + np.arange(6) * np.pi / 3
    return np.column_stack([np.cos(a), np.sin(a)])


@settings(max_examples=60, deadline=None)
@given(
    spacing=st.floats(0.003, 0.05),
    seed=st.integers(0, 2**31),
    r=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)),
)
def test_rate_is_periodic_with_period_lambda_along_the_six_lattice_vectors(spacing, seed, r):
    g = _single_cell(spacing, seed)
    lam, theta = g.spacing[0], g.orientation[0]
    assert lam == pytest.approx(spacing)
    r = np.asarray(r)
    shifted = r + lam * _lattice_dirs(theta)  # (6, 2)
    np.testing.assert_allclose(g.rates(shifted)[:, 0], g.rates(r)[0], atol=1e-9)
    # sums of lattice vectors too (a lattice, not 6 isolated coincidences)
    two = r + lam * (_lattice_dirs(theta)[0] + _lattice_dirs(theta)[1])
    np.testing.assert_allclose(g.rates(two)[0], g.rates(r)[0], atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(spacing=st.floats(0.003, 0.05), seed=st.integers(0, 2**31))
def test_no_firing_field_closer_than_lambda_and_range_is_0_to_gmax(spacing, seed):
    g = _single_cell(spacing, seed)
    lam, r0 = g.spacing[0], g.phase[0]
    gmax = g.cfg.g_max
    assert g.rates(r0)[0] == pytest.approx(gmax, abs=1e-12)  # a field peak at the phase r0
    # every point of the punctured disc 0.05 lambda < |d| < 0.95 lambda is clearly below the peak:
    # the nearest other peak is at distance lambda, so the spacing is not shorter than lambda
    t = np.linspace(0.05, 0.95, 60) * lam
    phi = np.linspace(0, 2 * np.pi, 181)
    pts = r0 + t[:, None, None] * np.stack([np.cos(phi), np.sin(phi)], -1)[None]
    assert g.rates(pts).max() < gmax * (1 - 1e-3)
    # and the peaks at distance exactly lambda exist in the 6 lattice directions
    np.testing.assert_allclose(g.rates(r0 + lam * _lattice_dirs(g.orientation[0]))[:, 0], gmax, atol=1e-9)
    # range [0, g_max] over random points, with the minimum 0 reached at the triangle centres
    rng = np.random.default_rng(seed % 1000)
    vals = g.rates(rng.uniform(-1, 1, (500, 2)))
    assert vals.min() >= -1e-12 and vals.max() <= gmax + 1e-12
    centre = r0 + lam / np.sqrt(3) * _lattice_dirs(g.orientation[0])[0] @ np.array(
        [[np.cos(np.pi / 6), np.sin(np.pi / 6)], [-np.sin(np.pi / 6), np.cos(np.pi / 6)]]
    )
    assert g.rates(centre)[0] == pytest.approx(0.0, abs=1e-9)


def test_paper_wave_vector_would_give_spacing_1_63_lambda():
    """Why we deviate: with Eq. 7-8 (|k| = 2 pi / lambda, divided by sqrt 2) the peak-to-peak distance is
    4 lambda / sqrt 6; ours puts the neighbouring peak at exactly lambda."""
    lam = 0.01
    k_paper = 2 * np.pi / lam / np.sqrt(2)
    ang = np.arange(3) * np.pi / 3
    kv = k_paper * np.column_stack([np.cos(ang), np.sin(ang)])
    d = np.linspace(0.5, 2.0, 150001) * lam  # along the 30-degree lattice direction
    pts = d[:, None] * np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    s = np.cos(pts @ kv.T).sum(1)
    assert d[np.argmax(s)] / lam == pytest.approx(4 / np.sqrt(6), abs=1e-4)


def test_parameters_follow_config_and_seed():
    cfg = SpatialConfig(n_modules=5, cells_per_module=3, seed=7)
    g = GridCells(cfg)
    assert g.n_cells == 15
    np.testing.assert_array_equal(g.module, np.arange(15) % 5)  # index order cycles through the modules
    assert np.all((g.module_spacing >= cfg.spacing_min_m) & (g.module_spacing <= cfg.spacing_max_m))
    assert np.all((g.module_orientation >= 0) & (g.module_orientation < 2 * np.pi))
    assert np.all((g.phase >= 0) & (g.phase <= cfg.area_size_m))
    # cells of a module share lambda and theta but have their own phases
    for m in range(5):
        cells = np.flatnonzero(g.module == m)
        assert np.unique(g.spacing[cells]).size == 1 and np.unique(g.orientation[cells]).size == 1
        assert np.unique(g.phase[cells], axis=0).shape[0] == 3
    again, other = GridCells(cfg), GridCells(cfg.model_copy(update={"seed": 8}))
    np.testing.assert_array_equal(again.phase, g.phase)
    np.testing.assert_array_equal(again.spacing, g.spacing)
    assert not np.allclose(other.phase, g.phase)


def test_rates_accepts_any_leading_shape_and_rejects_bad_points():
    g = GridCells(SpatialConfig(**SMALL))
    pts = np.random.default_rng(0).uniform(0, 0.03, (4, 5, 2))
    out = g.rates(pts)
    assert out.shape == (4, 5, g.n_cells)
    np.testing.assert_allclose(out[2, 3], g.rates(pts[2, 3]))
    with pytest.raises(ValueError):
        g.rates(np.zeros((3, 3)))


def test_rate_matrices_sample_eq6_on_the_grid():
    cfg = SpatialConfig(**SMALL, seed=3)
    g = GridCells(cfg)
    n = g.size
    assert n == 61 and g.tables.shape == (61, 61)
    iy, ix = np.mgrid[0:n, 0:n]
    pts = np.stack([ix, iy], -1) * cfg.resolution_m  # rows = y, columns = x
    expected = g.rates(pts)  # (n, n, cells)
    for c in (0, 5, g.n_cells - 1):
        np.testing.assert_allclose(g.rate_matrix(c), expected[..., c], atol=1.0 / LEVELS)


def test_tables_are_consistent_and_shared_between_identical_configs():
    cfg = SpatialConfig(**SMALL, seed=11)
    a, b = GridCells(cfg), GridCells(cfg.model_copy(update={"window": 0.2, "rate_noise": 0.01}))
    ta = a.tables
    assert b.tables is ta  # window/noise do not change the matrices: one shared copy
    assert GridCells(cfg.model_copy(update={"seed": 12})).tables is not ta
    assert not ta.levels.flags.writeable and not ta.order.flags.writeable
    for c in range(ta.n_cells):
        srt = ta.levels[c][ta.order[c]]
        assert np.all(np.diff(srt.astype(int)) >= 0)  # order is an argsort
        for v in (0, int(srt[len(srt) // 2]), LEVELS):
            assert ta.cum[c, v] == np.count_nonzero(ta.levels[c] < v)
    assert ta.nbytes == ta.levels.nbytes + ta.order.nbytes + ta.cum.nbytes


def test_tables_from_levels_validates_shape():
    with pytest.raises(ValueError):
        RateTables.from_levels(np.zeros((2, 3, 4), np.uint16), 0.001)


# -- the disk cache of HIPPOMAP_TABLE_CACHE -------------------------------------------------------------


def _forget() -> None:
    """Drop this process's shared copies of the tables."""
    grid_cells._CACHE.clear()
    grid_cells._RECENT.clear()


def _fresh(cfg: SpatialConfig) -> RateTables:
    """The tables of ``cfg`` read as a new process would: not from this process's shared copy."""
    _forget()
    return GridCells(cfg).tables


def _mapped(a: np.ndarray) -> bool:
    """Whether ``a``'s memory is a mapped file (a view's base chain ends in an mmap)."""
    while isinstance(a, np.ndarray):
        a = a.base
    return isinstance(a, mmap.mmap)


def _same(a: RateTables, b: RateTables) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("levels", "order", "cum"))


@pytest.fixture()
def forget_tables():
    """This process's shared copies are dropped after the test (they may be read from a removed folder)."""
    yield
    _forget()


@pytest.fixture()
def disk_cache(tmp_path, monkeypatch, forget_tables):
    """A table cache folder in force, with every table big enough to be written to it."""
    folder = tmp_path / "tables"
    monkeypatch.setenv(grid_cells.TABLE_CACHE_ENV, str(folder))
    monkeypatch.setattr(grid_cells, "DISK_CACHE_MIN_ENTRIES", 0)
    return folder


def test_tables_are_written_once_and_read_back_mapped_and_equal(disk_cache, monkeypatch):
    cfg = SpatialConfig(**SMALL, seed=21)
    monkeypatch.delenv(grid_cells.TABLE_CACHE_ENV)
    built = _fresh(cfg)  # no cache: built in memory, nothing written
    assert not _mapped(built.levels) and not disk_cache.exists()
    monkeypatch.setenv(grid_cells.TABLE_CACHE_ENV, str(disk_cache))
    first = _fresh(cfg)  # built and written
    assert sorted(p.name.split(".", 1)[1] for p in disk_cache.iterdir()) == ["cum.npy", "levels.npy", "order.npy"]
    with monkeypatch.context() as m:
        m.setattr(GridCells, "_compute_levels", lambda self: pytest.fail("built again, not read"))
        again = _fresh(cfg)  # read back
    assert _same(built, first) and _same(built, again)
    assert all(_mapped(getattr(again, k)) and not getattr(again, k).flags.writeable for k in ("levels", "order", "cum"))
    # another seed is another set of files
    assert not _same(_fresh(cfg.model_copy(update={"seed": 22})), built)
    assert len(list(disk_cache.glob("*.levels.npy"))) == 2


def test_off_means_no_cache(tmp_path, monkeypatch, forget_tables):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(grid_cells.TABLE_CACHE_ENV, "off")  # the server setting's word for none
    monkeypatch.setattr(grid_cells, "DISK_CACHE_MIN_ENTRIES", 0)
    assert not _mapped(_fresh(SpatialConfig(**SMALL, seed=27)).levels) and not list(tmp_path.iterdir())


def test_small_tables_are_not_written(tmp_path, monkeypatch, forget_tables):
    monkeypatch.setenv(grid_cells.TABLE_CACHE_ENV, str(tmp_path / "tables"))
    cfg = SpatialConfig(**SMALL, n_modules=1, cells_per_module=3, seed=23)
    t = _fresh(cfg)
    assert t.levels.size < grid_cells.DISK_CACHE_MIN_ENTRIES
    assert not (tmp_path / "tables").exists()


def test_a_damaged_file_is_rebuilt_with_a_warning(disk_cache):
    cfg = SpatialConfig(**SMALL, seed=24)
    good = _fresh(cfg)
    (order,) = disk_cache.glob("*.order.npy")
    np.save(order, np.zeros((3, 4), np.int32))  # a readable file with the wrong shape
    with pytest.warns(UserWarning, match="unreadable"):
        again = _fresh(cfg)
    assert _same(good, again)
    assert _same(good, _fresh(cfg))  # the file was written again: read back without a warning
    order.write_bytes(b"not a numpy file")
    with pytest.warns(UserWarning, match="unreadable"):
        assert _same(good, _fresh(cfg))


def test_an_unusable_folder_keeps_the_tables_in_memory(tmp_path, monkeypatch, forget_tables):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv(grid_cells.TABLE_CACHE_ENV, str(blocker / "tables"))  # below a file: cannot exist
    monkeypatch.setattr(grid_cells, "DISK_CACHE_MIN_ENTRIES", 0)
    cfg = SpatialConfig(**SMALL, seed=25)
    with pytest.warns(UserWarning, match="cannot write"):
        t = _fresh(cfg)
    monkeypatch.delenv(grid_cells.TABLE_CACHE_ENV)
    assert _same(t, _fresh(cfg)) and not _mapped(t.levels)


def test_the_least_recently_used_sets_are_deleted(disk_cache):
    keep = grid_cells.DISK_CACHE_KEEP
    seeds = list(range(30, 30 + keep + 2))
    for i, seed in enumerate(seeds):
        _fresh(SpatialConfig(**SMALL, seed=seed))
        for p in disk_cache.glob("*.npy"):  # distinct ages whatever the file system's clock resolution
            if p.stat().st_mtime_ns > 10**9 * (1000 + i):
                os.utime(p, (1000 + i, 1000 + i))
    names = {p.name.split(".")[0] for p in disk_cache.glob("*.npy")}
    assert len(names) == keep and len(list(disk_cache.glob("*.npy"))) == 3 * keep
    assert not list(disk_cache.glob("*.tmp*"))
    written = {grid_cells._disk_key(grid_cells.table_key(SpatialConfig(**SMALL, seed=s))) for s in seeds[-keep:]}
    assert names == {f"grid-tables-{k}" for k in written}  # the newest ones


def test_another_process_reads_the_tables_without_building_them(disk_cache):
    cfg = SpatialConfig(**SMALL, seed=26)
    here = _fresh(cfg)
    code = (
        "import sys, numpy as np\n"
        "from hippomap import grid_cells\n"
        "from hippomap.config import SpatialConfig\n"
        "grid_cells.DISK_CACHE_MIN_ENTRIES = 0\n"
        "grid_cells.GridCells._compute_levels = lambda self: sys.exit('built, not read')\n"
        f"t = grid_cells.GridCells(SpatialConfig(**{SMALL!r}, seed=26)).tables\n"
        "sys.stdout.write(str(int(t.levels.astype(np.int64).sum())))\n"
    )
    env = {**os.environ, grid_cells.TABLE_CACHE_ENV: str(disk_cache)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout) == int(here.levels.astype(np.int64).sum())
