"""The benchmarks' timing loop: one function run several times, each run timed on its own.

A shared machine makes the same work read slower from run to run, so a benchmark times a function
several times and reports the best run (the least disturbed) or the spread of the runs. The
benchmarks that time small functions in a loop import this one loop rather than keep a copy each.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

__all__ = ["timings"]


def timings(fn: Callable[[], object], repeats: int) -> np.ndarray:
    """Wall seconds of each of ``repeats`` calls of ``fn`` (``time.perf_counter``), in call order."""
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out
