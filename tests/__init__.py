"""The test suite, a package so that its helpers import by their full name (``tests.support``,
``tests.worker_harness``) from tests and from benchmarks run at the repository root. Never installed:
the wheel holds only hippomap, server and web (``[tool.setuptools.packages.find]``)."""
