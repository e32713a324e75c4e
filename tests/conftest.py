"""Shared test setup: the project root on sys.path so tests run from a clean checkout; one grid-cell table
cache and one Ray head for the whole run."""

import os
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


import pytest  # noqa: E402

from hippomap.grid_cells import TABLE_CACHE_ENV  # noqa: E402
from tests.support.ray_head import SHARED_DIR_ENV, SHARED_OWNER_ENV, stop_shared_head  # noqa: E402
from tests.support.variants import SERVICE_VARIANTS  # noqa: E402


@pytest.fixture(scope="module", params=SERVICE_VARIANTS, ids=lambda v: v.name)
def variant(request):
    """The service under test: each backend x store of ``tests.support.variants.SERVICE_VARIANTS``."""
    return request.param


def pytest_configure(config):
    """Set in the process that starts the test workers, so that they and everything they start inherit it:

    * one grid-cell table cache folder for the run (``hippomap.grid_cells``): the servers, mapper processes,
      Ray actors and commands the tests start read the default tables from it instead of each building
      its own (1.4 s of CPU each); a folder set from outside is used as it is;
    * one Ray head for the run's workers (``tests.support.ray_head``), started by the first that needs it
      and stopped here at the end."""
    if hasattr(config, "workerinput"):
        return
    if TABLE_CACHE_ENV not in os.environ:
        config._hippomap_table_cache = tempfile.mkdtemp(prefix="hippomap-tables-")
        os.environ[TABLE_CACHE_ENV] = config._hippomap_table_cache
    if SHARED_DIR_ENV not in os.environ:
        config._hippomap_ray_dir = tempfile.mkdtemp(prefix="hippomap-test-ray-")
        os.environ[SHARED_DIR_ENV] = config._hippomap_ray_dir
        os.environ[SHARED_OWNER_ENV] = str(os.getpid())


def pytest_unconfigure(config):
    folder = getattr(config, "_hippomap_ray_dir", None)
    if folder is not None:
        stop_shared_head(Path(folder))
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(SHARED_DIR_ENV, None)
        os.environ.pop(SHARED_OWNER_ENV, None)
    folder = getattr(config, "_hippomap_table_cache", None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(TABLE_CACHE_ENV, None)
