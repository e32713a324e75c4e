"""Shared test setup: the project root on sys.path so tests run from a clean checkout."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


import pytest  # noqa: E402

from tests.support.variants import SERVICE_VARIANTS  # noqa: E402


@pytest.fixture(scope="module", params=SERVICE_VARIANTS, ids=lambda v: v.name)
def variant(request):
    """The service under test: each backend x store of ``tests.support.variants.SERVICE_VARIANTS``."""
    return request.param
