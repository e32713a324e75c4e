"""The saccade decoder's cost per pair: the one-pair path against the batched expressions, in one run.

A recognition decodes one saccade vector at a time (``VisualGridCells._decode_one``, reached through
``decode_phase_difference`` with an (M, 3) phase difference); the batched expressions of the same
decoder (an (N, M, 3) batch) are the reference. Both decode the same pairs of whole-pixel points of a
320 x 240 view, one pair per call, alternating, and must agree on every vector. Also timed: a point's
module phasors through the public ``encode`` and ``_project`` against ``_phase_code_one``.

    python bench/bench_decode.py [--pairs 2000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.visual_grid_cells import VisualGridCells  # noqa: E402
from timing import timings  # noqa: E402


def best_us(fn: Callable[[], object], n: int, repeats: int) -> float:
    """Best of ``repeats`` timings of ``fn`` (which does ``n`` items), in microseconds per item."""
    return float(timings(fn, repeats).min()) / n * 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    grid = VisualGridCells()
    rng = np.random.default_rng(0)
    a = np.column_stack([rng.integers(15, 305, args.pairs), rng.integers(15, 225, args.pairs)]).astype(float)
    b = np.column_stack([rng.integers(15, 305, args.pairs), rng.integers(15, 225, args.pairs)]).astype(float)
    deltas = np.angle(grid._project(grid.encode(b)) * np.conj(grid._project(grid.encode(a))))
    one = [grid.decode_phase_difference(d) for d in deltas]
    batched = [grid.decode_phase_difference(d[None])[0] for d in deltas]
    if not all(np.array_equal(x, y) for x, y in zip(one, batched)):
        raise SystemExit("the one-pair decoder and the batched expressions disagree")
    n = len(deltas)
    t_batched = best_us(lambda: [grid.decode_phase_difference(d[None]) for d in deltas], n, args.repeats)
    t_one = best_us(lambda: [grid._decode_one(d) for d in deltas], n, args.repeats)
    t_public = best_us(lambda: [grid._project(grid.encode(p)) for p in a], n, args.repeats)
    t_phasors = best_us(lambda: [grid._phase_code_one(p) for p in a], n, args.repeats)
    exact = sum(np.array_equal(v, q - p) for v, p, q in zip(one, a, b))
    print(f"{n} pairs of a 320x240 view, best of {args.repeats}; decoded exactly: {exact} of {n}")
    print(f"{'us per pair':36s} {'reference':>10s} {'fast':>8s} {'fast/ref':>9s}")
    print(f"{'decode (batched of one / one-pair)':36s} {t_batched:10.1f} {t_one:8.1f} {t_one / t_batched:9.2f}")
    print(f"{'phasors (encode+project / one)':36s} {t_public:10.1f} {t_phasors:8.1f} {t_phasors / t_public:9.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
