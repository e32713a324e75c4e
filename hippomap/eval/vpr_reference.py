"""A conventional local-feature place recogniser, scored beside ours by ``hippomap eval-vpr``.

The recognition memory's recall targets (``docs/MODEL.md``, the visual recognition memory) mean more beside
what a standard pipeline reaches on the same images: SIFT keypoints and descriptors (Lowe 2004), Lowe's ratio
test (0.8) on the two nearest references' descriptors, and a RANSAC fit of a similarity transform (rotation,
scale, translation; ``cv2.estimateAffinePartial2D``, 8 px) to the surviving matches. Every query is compared
with every reference; its best reference is the one with the most RANSAC inliers. Two scores rank the queries
for the precision-recall sweep: the best reference's inlier count, and that count over the runner-up's (how
much the best stands out, which favours places that look like nothing else).

Each image is first brought to the recognition memory's working size (``working_width``), so both read the
same pixels. *Recall at 100 % precision* is, as for the RatSLAM baseline, the best recall any threshold on
the score reaches without a false positive: an oracle choice of threshold, favourable to the reference.
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np

from ..config import VisualConfig
from ..visual_images import working_gray
from .vpr_datasets import VPRDataset
from .vpr_scores import ranking_figures, stats_ms

__all__ = ["RATIO", "RANSAC_PX", "sift_reference"]

#: Lowe's ratio test: a match is kept when its distance is below this fraction of the second nearest's
RATIO = 0.8
#: RANSAC's reprojection bar for the similarity fit (working px)
RANSAC_PX = 8.0
#: fewer matches than this cannot be fitted (a similarity needs 2; RANSAC is given a few more)
_MIN_MATCHES = 4


def _features(sift: Any, image: np.ndarray, cfg: VisualConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoint positions ``(n, 2)`` float32 and descriptors of ``image`` at the working size."""
    gray, _ = working_gray(image, cfg)
    keypoints, descriptors = sift.detectAndCompute(gray, None)
    return np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2), descriptors


def _inliers(matcher: Any, q: tuple[np.ndarray, np.ndarray | None], r: tuple[np.ndarray, np.ndarray | None]) -> int:
    """RANSAC inliers of the similarity fitted to the ratio-tested matches of query ``q`` to reference ``r``."""
    (qp, qd), (rp, rd) = q, r
    if qd is None or rd is None or len(qd) < 2 or len(rd) < 2:
        return 0
    pairs = matcher.knnMatch(qd, rd, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    if len(good) < _MIN_MATCHES:
        return 0
    src = qp[[m.queryIdx for m in good]]
    dst = rp[[m.trainIdx for m in good]]
    _, mask = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=RANSAC_PX)
    return 0 if mask is None else int(mask.sum())


def sift_reference(
    cfg: VisualConfig, ds: VPRDataset, ref_images: list[np.ndarray], query_images: list[np.ndarray]
) -> dict[str, dict[str, Any]]:
    """Score SIFT + ratio test + RANSAC on the data set: ``{"sift_inliers": ..., "sift_inlier_ratio": ...}``,
    each with its recall@1, recall at 100 % precision (and the threshold that reaches it), average precision,
    PR curve and ``learn_ms`` / ``compare_ms`` (SIFT on a reference; one query against all references)."""
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's generator: the same figures on every run
    sift = cv2.SIFT.create()
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    t_learn, refs = [], []
    for img in ref_images:
        t0 = time.perf_counter()
        refs.append(_features(sift, img, cfg))
        t_learn.append(time.perf_counter() - t0)
    best, first, second, t_cmp = [], [], [], []
    for img in query_images:
        t0 = time.perf_counter()
        q = _features(sift, img, cfg)
        counts = np.array([_inliers(matcher, q, r) for r in refs], dtype=np.float64)
        t_cmp.append(time.perf_counter() - t0)
        order = np.argsort(-counts, kind="stable")
        best.append(int(order[0]) if counts.size else -1)
        first.append(counts[order[0]] if counts.size else 0.0)
        second.append(counts[order[1]] if counts.size > 1 else 0.0)
    ok = np.array([b in ds.positives[i] for i, b in enumerate(best)], dtype=bool)
    timing = {
        "config": {"ratio": RATIO, "ransac_px": RANSAC_PX, "working_width": cfg.working_width},
        "learn_ms": stats_ms(t_learn),
        "compare_ms": stats_ms(t_cmp),
    }
    inl, runner_up = np.array(first), np.array(second)
    name = "SIFT + ratio test + RANSAC similarity: inliers"
    return {
        "sift_inliers": {"name": name, **ranking_figures(inl, ok, ds, True), **timing},
        "sift_inlier_ratio": {
            "name": name + " over the runner-up's",
            **ranking_figures(inl / np.maximum(runner_up, 1.0), ok, ds, True),
            **timing,
        },
    }
