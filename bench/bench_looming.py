"""How well a recognition's looming tells where the robot stands along the matched key frame's view,
against ground truth, on recorded runs.

Every recognition that names a key frame moves the robot along that key frame's view by the looming
of its saccade correspondences (``hippomap.loop_pose.looming_offset``, docs/MODEL.md item 37):
``d = D (1 - 1 / s)`` with ``s`` the scale change of the scene and ``D`` one typical view distance
(``mapper.view_distance_m``). Nothing in a recognition measures how far beside the key frame the
robot stands. This bench runs one mapper (the default config, or ``--config``) over each run and
records, for every recognition that named a key frame, the scale ``s`` (read between the image
positions of the correspondences, and on the viewing sphere as the mapper reads it when the camera's
field of view is known, ``mapper.looming_on_sphere``) and the robot's true pose in the frame of the key
frame's true pose (ground truth at the time the key frame was learned and at the time of the
recognition): ``along`` (m, ahead along the key frame's view), ``beside`` (m, to its left) and ``turn``
(rad). Recognitions whose true offset exceeds ``--plausible-m`` on either axis name a key frame of
another place (the map's verification is there to reject them) and are counted apart.

Printed per run and over all runs: the correlation of the estimate with the true along offset, the
median error of the along estimate for each view distance of ``--view-distances`` (and for none,
the robot put on the key frame), the median error of both readings per band of true turn, the
estimate and the distance beside the track per band of true along offset, and the true offset per
band of estimate.

    python bench/bench_looming.py RUN [RUN ...] [--config FILE] [--view-distances 2 3 4 5]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hippomap.cli.run import dataset_config, open_dataset  # noqa: E402
from hippomap.config import HippomapConfig  # noqa: E402
from hippomap.eval.evaluation import groundtruth_at  # noqa: E402
from hippomap.geometry import between  # noqa: E402
from hippomap.inputs import Odometry  # noqa: E402
from hippomap.loop_pose import looming_distance, looming_scale  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402

#: bands of true along offset (m) and of estimated along offset (m) the tables are split into
TURN_BANDS = ((0.0, 0.15), (0.15, 0.3), (0.3, 0.5), (0.5, 3.2))
TRUE_BANDS = ((-3.0, -1.0), (-1.0, -0.5), (-0.5, -0.2), (-0.2, 0.2), (0.2, 0.5), (0.5, 1.0), (1.0, 3.0))
ESTIMATE_BANDS = ((-1.6, -0.6), (-0.6, -0.3), (-0.3, 0.3), (0.3, 0.6), (0.6, 1.6))


def record(folder: Path, config: HippomapConfig | None) -> np.ndarray:
    """(N, 5) per recognition that named a key frame and has a scale: the scale as the mapper reads it (on the
    viewing sphere when its config says so), true along, true beside, true turn, and the scale between the image
    positions."""
    dataset = open_dataset(folder)
    if dataset.groundtruth is None:
        raise SystemExit(f"{folder}: no ground truth")
    gt = dataset.groundtruth
    m = Mapper(dataset_config(dataset, config))
    learned_at: dict[int, float] = {}
    now = {"t": 0.0}
    learn, recognise = m.memory.learn, m.memory.recognise
    rows: list[tuple[float, ...]] = []
    hfov = m.config.mapper.looming_hfov_deg

    def dated_learn(image: Any) -> Any:
        fid = learn(image)
        if fid is not None:
            learned_at[int(fid)] = now["t"]
        return fid

    def scored_recognise(image: Any, candidates: Any = None, **kw: Any) -> Any:
        rec = recognise(image, candidates=candidates, **kw)
        pairs = rec.correspondences or []
        if rec.frame is None or not pairs:
            return rec
        q, mem = [c["query"] for c in pairs], [c["memory"] for c in pairs]
        flat = looming_scale(q, mem)
        s = flat if hfov is None else looming_scale(q, mem, camera=(image.shape[1], image.shape[0], hfov))
        a, b = groundtruth_at(gt, learned_at[int(rec.frame)]), groundtruth_at(gt, now["t"])
        if s is not None and flat is not None and a is not None and b is not None:
            rel = between(a, b)
            rows.append((s, float(rel[0]), float(rel[1]), float(rel[2]), flat))
        return rec

    m.memory.learn = dated_learn
    m.memory.recognise = scored_recognise
    for e in dataset.events():
        if isinstance(e, Odometry):
            m.step(e)
        else:
            frame = e.load()
            now["t"] = frame.t
            m.observe(frame)
    return np.array(rows, dtype=float).reshape(-1, 5)


def report(name: str, rows: np.ndarray, view_distances: list[float], default_d: float, plausible_m: float) -> None:
    ok = (np.abs(rows[:, 1]) <= plausible_m) & (np.abs(rows[:, 2]) <= plausible_m)
    r = rows[ok]
    print(f"\n{name}: {len(rows)} recognitions named a key frame, {len(r)} within {plausible_m:g} m of it")
    if len(r) < 3:
        return
    along, beside = r[:, 1], np.abs(r[:, 2])
    est = looming_distance(r[:, 0], default_d)
    errs = ", ".join(f"D {d:g}: {np.median(np.abs(looming_distance(r[:, 0], d) - along)):.3f}" for d in view_distances)
    corr = np.corrcoef(est, along)[0, 1]
    print(f"correlation of the estimate (D {default_d:g} m) with the true along offset: {corr:.2f}")
    print(f"median |along error| (m): none (on the key frame): {np.median(np.abs(along)):.3f}, {errs}")
    flat = looming_distance(r[:, 4], default_d)
    print(f"{'|true turn| (rad)':>17s} {'n':>5s} {'|along error| as read':>22s} {'in the image plane':>19s}")
    for lo, hi in TURN_BANDS:
        s = (np.abs(r[:, 3]) >= lo) & (np.abs(r[:, 3]) < hi)
        if s.any():
            e_read, e_flat = np.median(np.abs(est[s] - along[s])), np.median(np.abs(flat[s] - along[s]))
            print(f"{f'[{lo:g}, {hi:g})':>17s} {int(s.sum()):5d} {e_read:22.3f} {e_flat:19.3f}")
    print(f"{'true along (m)':>16s} {'n':>5s} {'estimate median':>16s} {'|beside| median':>16s}")
    for lo, hi in TRUE_BANDS:
        s = (along >= lo) & (along < hi)
        if s.any():
            print(
                f"{f'[{lo:g}, {hi:g})':>16s} {int(s.sum()):5d} {np.median(est[s]):16.2f} {np.median(beside[s]):16.2f}"
            )
    print(f"{'estimate (m)':>16s} {'n':>5s} {'true along median':>18s} {'p10 / p90':>12s} {'|beside| median':>16s}")
    for lo, hi in ESTIMATE_BANDS:
        s = (est >= lo) & (est < hi)
        if s.any():
            p10, p90 = np.percentile(along[s], [10, 90])
            print(
                f"{f'[{lo:g}, {hi:g})':>16s} {int(s.sum()):5d} {np.median(along[s]):18.2f} "
                f"{f'{p10:.2f} / {p90:.2f}':>12s} {np.median(beside[s]):16.2f}"
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="+", type=Path, help="recorded runs with ground truth (hippomap data folders)")
    ap.add_argument("--config", help="hippomap JSON config overrides (default: the default config)")
    ap.add_argument("--view-distances", nargs="+", type=float, default=[2.0, 3.0, 4.0, 5.0])
    ap.add_argument("--plausible-m", type=float, default=3.0, help="largest true offset counted (m, each axis)")
    args = ap.parse_args(argv)
    config = HippomapConfig.from_file(args.config) if args.config else HippomapConfig()
    default_d = config.mapper.view_distance_m or 3.0
    every = []
    for folder in args.data:
        rows = record(folder, config)
        every.append(rows)
        report(folder.name, rows, args.view_distances, default_d, args.plausible_m)
    if len(every) > 1:
        report("all runs", np.concatenate(every), args.view_distances, default_d, args.plausible_m)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
