"""Cost of the per-frame image check: the checks only (now) against the full preparation with the
retina (before), in the same process on the same frames.

    python bench/bench_frame_check.py DATA_DIR      # a hippomap data folder, e.g. from `hippomap simulate`

Every frame is checked before the mapper's state changes; only key frames need the retina. Prints
the mapper's CPU time per frame (``observe``, decode excluded) both ways, twice, interleaved, and
the ratio; the loop closures accepted must be the same both ways.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap import visual_memory as vm  # noqa: E402
from hippomap.cli.run import open_dataset  # noqa: E402
from hippomap.inputs import Odometry  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", help="a hippomap data folder, e.g. from `hippomap simulate`")
    ds = open_dataset(ap.parse_args().data_dir)
    items = list(ds.events())
    frames = {id(i): i.load() for i in items if not isinstance(i, Odometry)}
    checks_only = vm.VisualMemory.check_image

    def with_retina(self, image, name="image"):
        vm.prepare_image(image, self.config, name)

    res: dict[str, list[float]] = {}
    try:
        for label, fn in (("full preparation", with_retina), ("checks only", checks_only)) * 2:
            vm.VisualMemory.check_image = fn
            m = Mapper()
            cpu = 0.0
            for it in items:
                if isinstance(it, Odometry):
                    m.step(it)
                else:
                    t0 = time.process_time()
                    m.observe(frames[id(it)])
                    cpu += time.process_time() - t0
            ms = cpu / len(frames) * 1e3
            res.setdefault(label, []).append(ms)
            accepted = m.stats()["loop_closures_accepted"]
            print(f"{label:17s} {ms:6.2f} ms CPU per frame; loop closures accepted {accepted}")
    finally:
        vm.VisualMemory.check_image = checks_only
    ratios = [n / o for n, o in zip(res["checks only"], res["full preparation"])]
    print("ratio checks only / full preparation:", ", ".join(f"{r:.2f}" for r in ratios))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
