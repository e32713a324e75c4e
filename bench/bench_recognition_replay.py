"""Old vs new visual recognition on a run's own queries, interleaved query by query: CPU ratios that a
loaded machine does not blur.

A whole-mapper comparison (``bench_mapper_vs.py``) times thousands of frames, of which a few hundred
recognitions are most of the cost; a burst of load on a shared machine shifts such a run by more than a
recognition change is worth. This benchmark records what the new mapper's recognitions were asked on a
data folder (the query image and its candidate key frames) and the visual memory at the end of the
run, then puts every query to the old and the new code's memories (both restored from that state),
one after the other, the order turning each time, ``--rounds`` times. It prints CPU ms per
recognition (mean, p50, p95) and per fixation for both, their ratio, and whether the two gave the same
recognitions (frame, every step of the trace).

The old code is the package at ``--against`` (default ``HEAD``), imported under another name as in
``bench_mapper_vs.py``; its memory must read the new code's state (same ``STATE_VERSION``).

    python bench/bench_recognition_replay.py SIM --against REV [--rounds 3] [--skip-first-third]
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import hippomap.cli.run  # noqa: E402
import hippomap.config  # noqa: E402
import hippomap.inputs  # noqa: E402
import hippomap.mapper  # noqa: E402
import hippomap.visual_memory  # noqa: E402
from bench_mapper_vs import load_revision  # noqa: E402

Query = tuple[np.ndarray, list[int] | None, dict[str, Any]]


def record(data: str) -> tuple[dict[str, Any], list[Query]]:
    """Run the new mapper on ``data``; return its visual memory's final state and every query it
    recognised (the gray image, the candidate key frames, and the other arguments the mapper gave:
    a global search's give-up bar)."""
    m = hippomap.mapper.Mapper()
    queries: list[Query] = []
    recognise = m.memory.recognise

    def spy(image: Any, candidates: Any = None, **kw: Any) -> Any:
        given = {k: v for k, v in kw.items() if v is not None}
        queries.append((np.array(image), None if candidates is None else list(candidates), given))
        return recognise(image, candidates=candidates, **kw)

    m.memory.recognise = spy
    for item in hippomap.cli.run.open_dataset(data).events():
        if isinstance(item, hippomap.inputs.Odometry):
            m.step(item)
        else:
            m.observe(item.load())
    return m.memory.state_dict(), queries


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="hippomap data folder (e.g. from `hippomap simulate`)")
    ap.add_argument("--against", default="HEAD", help="git revision of the old code (default HEAD)")
    ap.add_argument("--rounds", type=int, default=3, help="times every query is put to both versions")
    ap.add_argument(
        "--skip-first-third", action="store_true", help="replay only the queries after the first third of the run"
    )
    args = ap.parse_args()
    old_pkg = load_revision(args.against)
    old_vm = importlib.import_module(f"{old_pkg.__name__}.visual_memory")
    old_config = importlib.import_module(f"{old_pkg.__name__}.config")
    state, queries = record(args.data)
    if args.skip_first_third:
        queries = queries[len(queries) // 3 :]
    if not queries:
        raise SystemExit("the run made no recognition to replay")
    mems = {
        "old": old_vm.VisualMemory.from_state(old_config.HippomapConfig().visual, state),
        "new": hippomap.visual_memory.VisualMemory.from_state(hippomap.config.HippomapConfig().visual, state),
    }
    ms: dict[str, list[float]] = {"old": [], "new": []}
    fixations = {"old": 0, "new": 0}
    same = True
    labels = ["old", "new"]
    for r in range(args.rounds):
        for i, (image, candidates, kw) in enumerate(queries):
            out = {}
            for label in labels if (i + r) % 2 == 0 else labels[::-1]:
                t0 = time.process_time()
                try:
                    rec = mems[label].recognise(image, candidates=candidates, **kw)
                except TypeError as exc:  # an old revision without the argument the mapper gave
                    raise SystemExit(f"revision {old_pkg.revision} cannot replay {sorted(kw)}: {exc}") from None
                ms[label].append((time.process_time() - t0) * 1e3)
                fixations[label] += len(rec.steps)
                out[label] = rec.to_dict()
            same = same and out["old"] == out["new"]
    print(
        f"{args.data}: {len(queries)} recognitions x {args.rounds} rounds; old = revision {old_pkg.revision}, "
        "new = working tree"
    )
    print(f"{'CPU ms':34s} {'old':>8s} {'new':>8s} {'new/old':>8s}")
    a, b = np.array(ms["old"]), np.array(ms["new"])
    for text, f in (
        ("recognition mean", np.mean),
        ("recognition p50", np.median),
        ("recognition p95", lambda x: np.percentile(x, 95)),
    ):
        print(f"{text:34s} {f(a):8.3f} {f(b):8.3f} {f(b) / f(a):8.2f}")
    pa, pb = a.sum() / max(fixations["old"], 1), b.sum() / max(fixations["new"], 1)
    print(f"{'per fixation':34s} {pa:8.3f} {pb:8.3f} {pb / pa:8.2f}")
    print(f"fixations: old {fixations['old']}, new {fixations['new']}")
    print("recognitions identical" if same else "recognitions differ (a change of the model's numbers)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
