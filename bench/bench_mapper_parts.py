"""Where the mapper's time per frame goes, part by part and third by third of a recorded run.

The speed targets compare the whole mapper's mean cost per frame with OpenRatSLAM's, and the last
third of a run with the first. This bench says which part of the mapper makes each figure, so that a
speed-up is aimed where the time is. One mapper (the default config, or ``--config``) runs over a
recorded run's frames, decoded before timing, ``--repeats`` times (the figures are the medians: the
same work reads up to a third apart between runs on a shared machine); every part is timed with
``time.process_time`` (CPU of this process) by wrapping the mapper's own objects:

* ``spatial pathway``: odometry to place code (grid cells, place cells; ``SpatialPathway.step_increment``);
* ``map update``: the cognitive map's per-step update (new nodes, and the corrections it runs:
  ``CognitiveMap.update``);
* ``candidates``: which key frames the gate offers (``loop_candidates``);
* ``recognition``: ``VisualMemory.recognise``, split into the recognitions that named a key frame and
  those that did not;
* ``loop decision``: ``propose_loop`` (verification, fit, and the correction it starts);
* ``learning``: ``VisualMemory.learn``;
* ``rest``: everything else of ``step`` and ``observe``;
* ``whole solves``: the whole-map solves (``MapCorrection._whole_solve``), timed inside the map update and the loop
  decision that start them and printed apart (not added again to the total).

Printed: each part's CPU ms per frame over the whole run, its first and last third, and the change
between them; then the recognitions per outcome with their mean and p95 ms, and the local solves of the
map's corrections (``map.lsq_window_hops``) with the nodes their windows hold. Then the recognitions per
search (``sequence``: the old path's sequence, ``mapper.sequence_window_m``; ``gated``: the key frames the gate
offers, or the rest of them; ``gated, primed``: all of them with that sequence primed, ``mapper.sequence_prior``;
``global``: the global search, ``mapper.global_search_*``) and outcome, with their fixations (median, p95) and CPU
ms per fixation: a recognition's cost is its fixations times a cost per fixation, and this says which of the two
sets a p95. When the run has ground truth, a recognition that named none is also
counted as *futile* when none of its candidate key frames was learned within ``FUTILE_M`` of where the robot truly
stands (there was nothing there to recognise), and as *facing away* when some were but none of those faced within
``FUTILE_RAD`` of the robot's true heading (they stood near but saw another view).

    python -m hippomap simulate loop --out SIM --seed 3 --omega-bias 0.01 --sigma-omega 0.01 --sigma-v 0.02
    python bench/bench_mapper_parts.py SIM [SIM ...] [--config FILE] [--repeats 3] [--slices 6]

``--slices N`` also prints every part per N equal slices of the run: where a long run's cost starts to grow.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_maps import TimedMapper, warm_up  # noqa: E402
from hippomap.cli.run import dataset_config, open_dataset  # noqa: E402
from hippomap.config import HippomapConfig  # noqa: E402
from hippomap.eval.evaluation import groundtruth_at  # noqa: E402
from hippomap.geometry import wrap_angle  # noqa: E402
from hippomap.inputs import Frame, Odometry  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402

#: the timed parts, in the order they are printed (``rest`` and ``total`` are derived)
PARTS = ("spatial pathway", "map update", "candidates", "recognition", "loop decision", "learning")
#: timed within the parts above, printed apart and left out of ``rest``: the whole-map solves, which the map update
#: and the loop decision both start (``MapCorrection._whole_solve``)
SUBPARTS = ("whole solves",)
#: a recognition that names none is futile when no candidate key frame was learned within this of the robot (m)
FUTILE_M = 2.0
#: ... and faces away when none of the candidates learned within FUTILE_M faced within this of the robot (rad, 45 deg)
FUTILE_RAD = math.pi / 4


@dataclass
class Recognised:
    """One recognition as the bench saw it."""

    frame: int  # index of the camera frame it ran on
    seconds: float  # CPU
    named: bool  # named a key frame
    fixations: int
    search: str  # "sequence", "gated", "gated, primed" or "global"
    truth_m: float  # how far the nearest candidate key frame was learned from the robot's true position (nan: unknown)
    #: the smallest true heading difference (rad) between the robot and the candidates learned within FUTILE_M of it
    #: (nan: none, or unknown)
    truth_rad: float = math.nan


class PartTimer:
    """CPU seconds per part, accumulated while the mapper runs; :meth:`mark` closes a frame."""

    def __init__(self) -> None:
        self.acc = dict.fromkeys(PARTS + SUBPARTS, 0.0)
        self.rows: list[dict[str, float]] = []  # per frame: cumulative seconds per part and in total
        self.total = 0.0
        self.recognitions: list[Recognised] = []
        self.windows: list[tuple[int, int]] = []  # (frame index, nodes) of each local solve's window
        self.search = "gated"  # the search of the recognition under way (set by :meth:`wrap_search`)
        # with ground truth (:meth:`wrap_truth`): the mapper's clock, when each key frame was learned, and each
        # recognition that named none with its time and candidates, dated after the run (:meth:`date_truth`)
        self.clock: Callable[[], float] | None = None
        self._learned_t: dict[int, float] = {}
        self._asked: list[tuple[int, float, tuple[int, ...]]] = []

    def wrap(self, obj: Any, name: str, part: str) -> None:
        """Time every call of ``obj.name`` as ``part`` (an instance attribute shadows the method)."""
        f: Callable[..., Any] = getattr(obj, name)
        acc = self.acc

        def timed(*a: Any, **k: Any) -> Any:
            c = time.process_time()
            try:
                return f(*a, **k)
            finally:
                acc[part] += time.process_time() - c

        setattr(obj, name, timed)

    def wrap_recognise(self, memory: Any) -> None:
        """Time ``memory.recognise`` as ``recognition`` and keep each call's outcome."""
        f = memory.recognise

        def timed(image: Any, candidates: Any = None, **kw: Any) -> Any:
            c = time.process_time()
            r = f(image, candidates=candidates, **kw)
            dt = time.process_time() - c
            self.acc["recognition"] += dt
            named = r.frame is not None
            if not named and candidates is not None and self.clock is not None:
                self._asked.append((len(self.recognitions), self.clock(), tuple(int(c) for c in candidates)))
            self.recognitions.append(Recognised(len(self.rows), dt, named, r.n_fixations, self.search, math.nan))
            return r

        memory.recognise = timed

    def wrap_search(self, mapper: Mapper) -> None:
        """Tell the recognitions of ``mapper``'s sequence, gated and global searches apart."""
        f = mapper._recognise

        def tagged(*a: Any, search: str = "gated", **k: Any) -> Any:
            self.search = f"{search}, primed" if k.get("prior") else search
            return f(*a, search=search, **k)

        mapper._recognise = tagged  # type: ignore[method-assign]

    def wrap_truth(self, mapper: Mapper) -> None:
        """Note when each key frame was learned and when each recognition that named none was made, so that
        :meth:`date_truth` can say, after the run, how far its nearest candidate key frame was learned from where
        the robot truly stood. Only times are noted during the run: the frames' CPU times (``TimedMapper``) hold
        the mapper's work, not the ground-truth look-ups."""
        learn = mapper.memory.learn

        def noted(image: Any) -> Any:
            fid = learn(image)
            if fid is not None:
                self._learned_t[int(fid)] = mapper.last_frame_t
            return fid

        mapper.memory.learn = noted
        self.clock = lambda: mapper.last_frame_t

    def date_truth(self, gt: tuple[np.ndarray, np.ndarray]) -> None:
        """Set ``truth_m`` and ``truth_rad`` of the recognitions noted by :meth:`wrap_truth` from the ground truth
        ``gt``."""
        learned = {f: groundtruth_at(gt, t) for f, t in self._learned_t.items()}
        for i, t, candidates in self._asked:
            now = groundtruth_at(gt, t)
            self.recognitions[i].truth_m = nearest_learned_m(learned, candidates, now)
            self.recognitions[i].truth_rad = nearest_facing_rad(learned, candidates, now)

    def wrap_windows(self, cmap: Any) -> None:
        """Keep the size of every local solve's window (``CognitiveMap._local_window``: None for a whole solve)."""
        f = cmap._local_window

        def seen(*a: Any, **k: Any) -> Any:
            w = f(*a, **k)
            if w is not None:
                self.windows.append((len(self.rows), len(w[0])))
            return w

        cmap._local_window = seen

    def mark(self, seconds: float) -> None:
        self.total += seconds
        self.rows.append({**self.acc, "total": self.total})


def _learned_poses(learned_at: dict[int, np.ndarray | None], frames: Any) -> np.ndarray:
    """(k, 3) the true poses ``learned_at`` (frame -> x, y, heading; None where the ground truth has a gap) of the
    key frames ``frames`` that have one."""
    return np.asarray([learned_at[c] for c in frames if learned_at.get(c) is not None], float).reshape(-1, 3)


def nearest_learned_m(learned_at: dict[int, np.ndarray | None], frames: Any, now: np.ndarray | None) -> float:
    """How far from the true pose ``now`` the nearest of the key frames ``frames`` was learned, by their true
    poses ``learned_at`` (:func:`_learned_poses`); nan when nothing is known."""
    poses = _learned_poses(learned_at, frames)
    if now is None or not len(poses):
        return math.nan
    return float(np.min(np.hypot(poses[:, 0] - now[0], poses[:, 1] - now[1])))


def nearest_facing_rad(learned_at: dict[int, np.ndarray | None], frames: Any, now: np.ndarray | None) -> float:
    """Of the key frames ``frames`` learned within ``FUTILE_M`` of the true pose ``now`` (by their true poses
    ``learned_at``, :func:`_learned_poses`), the smallest difference between the heading each was learned at and
    ``now``'s (rad, in [0, pi]); nan when none was, or nothing is known."""
    if now is None:
        return math.nan
    poses = _learned_poses(learned_at, frames)
    near = poses[np.hypot(poses[:, 0] - now[0], poses[:, 1] - now[1]) <= FUTILE_M]
    if not len(near):
        return math.nan
    return float(np.min(np.abs(wrap_angle(near[:, 2] - now[2]))))


def run(folder: Path, config: HippomapConfig | None) -> tuple[PartTimer, Mapper]:
    """The part times of one default (or ``config``) mapper over the run in ``folder``, and the mapper."""
    dataset = open_dataset(folder)
    cfg = dataset_config(dataset, config)
    events = [e if isinstance(e, Odometry) else e.load() for e in dataset.events()]
    frames = [e for e in events if isinstance(e, Frame)]
    if not frames:
        raise SystemExit(f"{folder}: no camera frames")
    warm_up(cfg, frames[0].image)
    m = TimedMapper(cfg)  # a frame's CPU time with the odometry steps before it
    timer = PartTimer()
    timer.wrap(m.pathway, "step_increment", "spatial pathway")
    timer.wrap(m.cmap, "update", "map update")
    timer.wrap(m.cmap, "loop_candidates", "candidates")
    timer.wrap(m.cmap, "propose_loop", "loop decision")
    timer.wrap(m.memory, "learn", "learning")
    timer.wrap(m.cmap, "_whole_solve", "whole solves")
    timer.wrap_recognise(m.memory)
    timer.wrap_search(m)
    if dataset.groundtruth is not None:
        timer.wrap_truth(m)
    timer.wrap_windows(m.cmap)
    for e in events:
        if isinstance(e, Odometry):
            m.step(e)
        else:
            m.observe(e)
            timer.mark(m.frame_cpu_seconds[-1])
    if dataset.groundtruth is not None:
        timer.date_truth(dataset.groundtruth)
    return timer, m


def per_frame(rows: list[dict[str, float]], lo: int, hi: int) -> dict[str, float]:
    """ms per frame of each part over frames ``lo`` to ``hi`` (exclusive), from the cumulative rows."""
    end = rows[hi - 1]
    start = rows[lo - 1] if lo > 0 else dict.fromkeys(end, 0.0)
    out = {k: (end[k] - start[k]) * 1e3 / (hi - lo) for k in end}
    out["rest"] = out["total"] - sum(out[p] for p in PARTS)  # the SUBPARTS are inside PARTS
    return out


def spans(n: int) -> tuple[tuple[str, int, int], ...]:
    """The named frame spans of a run of ``n`` frames: its first third, middle and last third."""
    a = max(1, n // 3)
    return (("first third", 0, a), ("middle", a, n - a), ("last third", n - a, n))


def thirds(rows: list[dict[str, float]]) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """:func:`per_frame` over the whole run, its first third and its last third (:func:`spans`)."""
    n = len(rows)
    (_, lo1, hi1), _, (_, lo3, hi3) = spans(n)
    return per_frame(rows, 0, n), per_frame(rows, lo1, hi1), per_frame(rows, lo3, hi3)


def report(name: str, timers: list[PartTimer], slices: int = 0) -> None:
    """Print the parts of one run measured ``len(timers)`` times: the median of each figure over the
    repeats, and the recognitions' times of all repeats together (the same recognitions each time); with
    ``slices`` > 1 also each part per slice of the run (where a cost starts to grow on a long run)."""
    t = timers[0]
    n = len(t.rows)
    each = [thirds(x.rows) for x in timers]
    whole, first, last = ({k: float(np.median([e[i][k] for e in each])) for k in each[0][i]} for i in range(3))
    print(f"\n{name}: {n} frames, {len(t.recognitions)} recognitions; CPU ms per frame, median of {len(timers)} runs")
    print(f"{'part':18s} {'run':>7s} {'1st 3rd':>8s} {'last 3rd':>9s} {'last-1st':>9s}")
    labels = (*PARTS, "rest", "total", *SUBPARTS)
    for p in labels:
        print(f"{p:18s} {whole[p]:7.3f} {first[p]:8.3f} {last[p]:9.3f} {last[p] - first[p]:+9.3f}")
    print(f"last third / first third: {last['total'] / first['total']:.2f}")
    slices = min(slices, n)  # no empty slice
    if slices > 1:
        bounds = np.linspace(0, n, slices + 1).astype(int)
        cols = [
            {k: float(np.median([per_frame(x.rows, lo, hi)[k] for x in timers])) for k in whole}
            for lo, hi in zip(bounds[:-1], bounds[1:])
        ]
        print(f"CPU ms per frame by {slices} equal slices of the run (median of the repeats):")
        for p in labels:
            print(f"{p:18s} " + " ".join(f"{c[p]:7.3f}" for c in cols))
    r = np.array([(x.frame, x.seconds, x.named) for t_ in timers for x in t_.recognitions], dtype=float).reshape(-1, 3)
    for label, lo, hi in (*spans(n), ("run", 0, n)):
        sel = r[(r[:, 0] >= lo) & (r[:, 0] < hi)]
        parts = []
        for outcome, keep in (("named a key frame", 1.0), ("named none", 0.0)):
            s = sel[sel[:, 2] == keep, 1] * 1e3
            if len(s):
                count = len(s) // len(timers)
                parts.append(f"{outcome} {count} (mean {s.mean():.1f}, p95 {np.percentile(s, 95):.1f} ms)")
        p95 = f"p95 of all {np.percentile(sel[:, 1] * 1e3, 95):.1f} ms; " if len(sel) else ""
        print(f"recognitions, {label}: {p95}{'; '.join(parts) or 'none'}")
    searches(t.recognitions, timers, n)
    w = np.array(t.windows, dtype=float).reshape(-1, 2)
    for label, lo, hi in spans(n):
        sel = w[(w[:, 0] >= lo) & (w[:, 0] < hi), 1]
        print(f"local solves, {label}: {len(sel)}" + (f", {sel.mean():.0f} nodes each (mean)" if len(sel) else ""))


def searches(recognitions: list[Recognised], timers: list[PartTimer], n: int) -> None:
    """Print the recognitions per third, search and outcome: count, fixations (median, p95), CPU ms per fixation
    (over all repeats), and of those that named none, the futile ones and those facing away (ground truth only)."""
    for label, lo, hi in spans(n):
        parts = []
        for search in ("sequence", "gated", "gated, primed", "global"):
            for named in (True, False):
                sel = [x for x in recognitions if lo <= x.frame < hi and x.search == search and x.named == named]
                if not sel:
                    continue
                fix = np.array([x.fixations for x in sel], float)
                per = [
                    y.seconds * 1e3 / y.fixations
                    for t_ in timers
                    for y in t_.recognitions
                    if lo <= y.frame < hi and y.search == search and y.named == named and y.fixations
                ]
                text = (
                    f"{search} {'named' if named else 'none'} {len(sel)}: fixations {np.median(fix):.0f} / "
                    f"p95 {np.percentile(fix, 95):.0f}, {np.median(per) if per else math.nan:.2f} ms each"
                )
                truth = np.array([x.truth_m for x in sel])
                if not named and np.isfinite(truth).any():
                    away = np.array([x.truth_rad for x in sel])
                    text += f", futile {int((truth > FUTILE_M).sum())}, facing away {int((away > FUTILE_RAD).sum())}"
                parts.append(text)
        print(f"recognitions by search, {label}: {'; '.join(parts) or 'none'}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="+", type=Path, help="recorded runs (hippomap data folders)")
    ap.add_argument("--config", help="hippomap JSON config overrides (default: the default config)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each recorded run; the median is printed")
    ap.add_argument("--slices", type=int, default=0, help="also print each part per this many equal slices of the run")
    args = ap.parse_args(argv)
    config = HippomapConfig.from_file(args.config) if args.config else None
    for folder in args.data:
        report(folder.name, [run(folder, config)[0] for _ in range(max(1, args.repeats))], args.slices)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
