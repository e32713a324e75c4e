"""Could a coarse view of the whole frame tell, before any saccade, that a recognition will find nothing?

On the Bicocca world most recognitions name no key frame, and most of those are *futile*: none of their
candidate key frames was learned within ``FUTILE_M`` of where the robot truly stands, so there was nothing
to find. A fast familiarity signal (the perirhinal cortex's, in dual-process accounts of recognition memory)
could skip them: compare a coarse "gist" of the query with the gists of the candidate key frames and run the
saccades only when the best match is familiar enough. This bench measures whether any such threshold
exists. One default mapper runs over each recorded run (its behaviour is not changed); every learned key
frame and every recognition's query are summarised by

* ``area WxH``: the ganglion image (the retina's output the sensory cells see) area-averaged to W x H;
* ``area WxH +-2``: the same, the best of the horizontal shifts by up to 2 cells (a turn of the head);
* ``gradient 8x6``: horizontal and vertical gradient energy of the ganglion image, pooled 8 x 6;

and a recognition's familiarity is its query's best Pearson correlation with a candidate's gist. Printed
per run and gist: the threshold that keeps every recognition that named a right key frame (learned within
``FUTILE_M`` of the robot) and what it would skip: the share of the futile recognitions, of all fixations,
and of the recognitions that named none although a candidate was near.

    python bench/bench_familiarity.py SIM [SIM ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_mapper_parts import FUTILE_M, nearest_learned_m  # noqa: E402
from hippomap.cli.run import dataset_config, open_dataset  # noqa: E402
from hippomap.config import HippomapConfig  # noqa: E402
from hippomap.eval.evaluation import groundtruth_at  # noqa: E402
from hippomap.inputs import Odometry  # noqa: E402
from hippomap.mapper import Mapper  # noqa: E402

#: the gists compared: name -> (pooled size, horizontal shifts tried)
AREAS = {"area 8x6": ((8, 6), 0), "area 16x12": ((16, 12), 0), "area 32x24": ((32, 24), 0)}
AREAS |= {f"{k} +-2": (size, 2) for k, (size, _) in AREAS.items()}
GRADIENT = "gradient 8x6"


def gists(mapper: Mapper, image: Any) -> dict[str, np.ndarray]:
    """Every gist of one frame, from the visual memory's own views of it (the retina runs once per frame)."""
    work, _, _ = mapper.memory._views(image)
    g = (work[..., 0] if work.ndim == 3 else work).astype(np.float32)
    out = {k: cv2.resize(g, size, interpolation=cv2.INTER_AREA) for k, (size, _) in AREAS.items()}
    gx = np.abs(cv2.Sobel(g, cv2.CV_32F, 1, 0))
    gy = np.abs(cv2.Sobel(g, cv2.CV_32F, 0, 1))
    out[GRADIENT] = np.concatenate([cv2.resize(a, (8, 6), interpolation=cv2.INTER_AREA) for a in (gx, gy)], axis=1)
    return out


def correlation(a: np.ndarray, b: np.ndarray, shifts: int) -> float:
    """Best Pearson correlation of two gists over horizontal shifts of up to ``shifts`` cells (overlap only)."""
    best, w = -1.0, a.shape[1]
    for s in range(-shifts, shifts + 1):
        x, y = (a[:, s:], b[:, : w - s]) if s >= 0 else (a[:, : w + s], b[:, -s:])
        x = x.ravel() - x.mean()
        y = y.ravel() - y.mean()
        best = max(best, float(x @ y / (np.linalg.norm(x) * np.linalg.norm(y) + 1e-9)))
    return best


def record(folder: Path) -> tuple[list[dict[str, Any]], Mapper]:
    """One default mapper over the run, and per recognition: its kind (``right``: named a key frame learned
    within ``FUTILE_M`` of the robot; ``wrong``: named another; ``futile``: named none and no candidate was
    learned within ``FUTILE_M``; ``missed``: named none although one was), fixations and familiarity per gist."""
    dataset = open_dataset(folder)
    if dataset.groundtruth is None:
        raise SystemExit(f"{folder}: no ground truth")
    m = Mapper(dataset_config(dataset, HippomapConfig()))
    learned: dict[int, tuple[float, dict[str, np.ndarray]]] = {}
    asked: list[tuple[float, dict[str, np.ndarray], list[int], int | None, int]] = []
    learn, recognise = m.memory.learn, m.memory.recognise

    def noted_learn(image: Any) -> Any:
        g = gists(m, image)
        fid = learn(image)
        if fid is not None:
            learned[int(fid)] = (m.last_frame_t, g)
        return fid

    def noted_recognise(image: Any, candidates: Any = None, **kw: Any) -> Any:
        g = gists(m, image)
        r = recognise(image, candidates=candidates, **kw)
        cands = [] if candidates is None else [int(c) for c in candidates]
        asked.append((m.last_frame_t, g, cands, r.frame, r.n_fixations))
        return r

    m.memory.learn = noted_learn  # type: ignore[method-assign]
    m.memory.recognise = noted_recognise  # type: ignore[method-assign]
    for e in dataset.events():
        if isinstance(e, Odometry):
            m.step(e)
        else:
            m.observe(e.load())
    gt = dataset.groundtruth
    where = {f: groundtruth_at(gt, t) for f, (t, _) in learned.items()}
    rows = []
    for t, g, candidates, named, fixations in asked:
        now = groundtruth_at(gt, t)
        cands = [c for c in candidates if c in learned]
        near = nearest_learned_m(where, cands, now)
        fam = {
            k: max(correlation(g[k], learned[c][1][k], AREAS[k][1] if k in AREAS else 0) for c in cands)
            for k in g
            if cands
        }
        kind = "futile" if not near < FUTILE_M else "missed"
        if named is not None:
            kind = "right" if nearest_learned_m(where, [named], now) < FUTILE_M else "wrong"
        rows.append({"kind": kind, "fixations": fixations, "familiarity": fam})
    return rows, m


def report(name: str, rows: list[dict[str, Any]]) -> None:
    kinds = {k: [r for r in rows if r["kind"] == k] for k in ("right", "wrong", "futile", "missed")}
    fix = sum(r["fixations"] for r in rows)
    print(f"\n{name}: {len(rows)} recognitions: " + ", ".join(f"{k} {len(v)}" for k, v in kinds.items()))
    futile_fix = sum(r["fixations"] for r in kinds["futile"]) / max(fix, 1)
    print(f"  futile recognitions hold {futile_fix:.2f} of the fixations")
    right = [r for r in kinds["right"] if r["familiarity"]]
    if not right:
        return
    heads = ("threshold", 9), ("futile skipped", 15), ("fixations skipped", 18), ("missed skipped", 15)
    print(f"  {'gist':16s} " + " ".join(f"{h:>{w}s}" for h, w in heads))
    fut, mis = kinds["futile"], kinds["missed"]
    for k in right[0]["familiarity"]:
        thr = min(r["familiarity"][k] for r in right)

        def below(rs: list[dict[str, Any]], k: str = k, thr: float = thr) -> list[dict[str, Any]]:
            return [r for r in rs if r["familiarity"] and r["familiarity"][k] < thr]

        skipped_fix = sum(r["fixations"] for r in below(fut)) / max(fix, 1)
        print(
            f"  {k:16s} {thr:9.3f} {len(below(fut)) / max(len(fut), 1):15.2f} {skipped_fix:18.2f}"
            f" {len(below(mis)) / max(len(mis), 1):15.2f}"
        )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="recorded runs with ground truth (hippomap simulate)")
    args = ap.parse_args()
    for folder in args.runs:
        report(folder.name, record(folder)[0])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
