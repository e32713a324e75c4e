"""The figures of ``hippomap eval-vpr``: the precision-recall plot and the saccade-trace examples.

``pr_curve.png`` sets ours (its operating point and its curve sweeping confidence) beside the RatSLAM
baselines' curves; ``traces/*.png`` draw a query's saccade trace beside the accepted reference with its
learned fixation points, with the recognition beside it as JSON.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..config import VisualConfig
from ..extras import requires
from ..visual_memory import VisualMemory, draw_frame_features, draw_trace

__all__ = ["plot_pr", "write_examples"]


def _side_by_side(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` and ``b`` beside each other at the taller one's height, with a white gap."""
    h = max(a.shape[0], b.shape[0])

    def fit(x: np.ndarray) -> np.ndarray:
        if x.shape[0] == h:
            return x
        return cv2.resize(x, (int(round(x.shape[1] * h / x.shape[0])), h), interpolation=cv2.INTER_LINEAR)

    gap = np.full((h, 6, 3), 255, np.uint8)
    return np.hstack([fit(a), gap, fit(b)])


def plot_pr(
    path: Path,
    name: str,
    ours: dict[str, Any],
    op: tuple[float, float],
    base: dict[str, Any],
    base2: dict[str, Any] | None = None,
    reference: dict[str, Any] | None = None,
) -> None:
    """Write the precision-recall figure: the baselines' curves, the SIFT + RANSAC reference's
    (:mod:`~hippomap.eval.vpr_reference`), ours sweeping confidence, ours at its operating point ``op`` =
    (precision, recall)."""
    with requires("eval", "the precision-recall plot"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4.5), dpi=120)
    curves = (
        (base, "-", "tab:gray", "RatSLAM column profile, baseline"),
        (base2, ":", "tab:gray", "RatSLAM 60x10 templates"),
        (reference, "--", "tab:green", "SIFT + RANSAC inliers, reference"),
    )
    for result, style, colour, text in curves:
        if result is not None and result["pr_curve"]["recall"]:
            ax.plot(
                [0.0] + result["pr_curve"]["recall"],
                [1.0] + result["pr_curve"]["precision"],
                style,
                color=colour,
                label=f"{text} (R@P100 = {result['recall_at_100_precision']:.2f})",
            )
    if ours["recall"]:
        ax.plot(
            [0.0] + ours["recall"], [1.0] + ours["precision"], "-", color="tab:blue", label="ours, sweeping confidence"
        )
    ax.plot([op[1]], [op[0]], "o", color="tab:red", ms=8, label=f"ours at theta_dec (P = {op[0]:.2f}, R = {op[1]:.2f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3)
    ax.set_title(f"{name}: visual place recognition")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_examples(
    folder: Path,
    recs: list,
    rows: list[dict[str, Any]],
    mem: VisualMemory,
    frame_to_ref: dict[int, int],
    ref_images: list[np.ndarray],
    n: int,
    cfg: VisualConfig,
) -> list[str]:
    """Draw ``n`` true matches spread over the queries, one false match and one rejection (when there are any):
    the saccade trace on the query beside the accepted reference's learned fixation points, as PNG, and the
    recognition as JSON. Returns the images' paths relative to the output folder."""
    if n <= 0:
        return []
    tp = [i for i, r in enumerate(rows) if r["ours_correct"]]
    fp = [i for i, r in enumerate(rows) if r["ours_reference"] is not None and not r["ours_correct"]]
    rej = [i for i, r in enumerate(rows) if r["ours_reference"] is None]
    picks: list[tuple[int, str]] = []
    # n true positives spread over the sequence, then one false positive and one rejection
    for i in np.linspace(0, len(tp) - 1, min(n, len(tp))).round().astype(int) if tp else []:
        picks.append((tp[i], "match"))
    if fp:
        picks.append((fp[0], "false_match"))
    if rej:
        picks.append((rej[len(rej) // 2], "rejected"))
    written = []
    for qi, kind in picks:
        _, img, rec = recs[qi]
        scale = img.shape[1] / cfg.working_width
        enlarge = max(1.0, 480.0 / img.shape[1])  # small frames (corridor: 160 px) are drawn larger
        left = draw_trace(img, rec, fovea=int(round(cfg.fovea * scale)), scale=enlarge)
        if rec.accepted:
            last = rec.steps[-1].attempt
            steps = [s for s in rec.steps if s.attempt == last]
            # the reference's features found in the last attempt, labelled with their fixation number
            hl = {
                s.found_feature: str(i)
                for i, s in enumerate(steps, 1)
                if s.found_feature is not None and s.found_frame == rec.frame_id
            }
            ref_img = ref_images[frame_to_ref[rec.frame_id]]
            right = draw_frame_features(ref_img, mem, rec.frame_id, hl, scale=max(1.0, 480.0 / ref_img.shape[1]))
        else:
            right = np.full_like(left, 40)
        name = f"q{qi:03d}_{kind}.png"
        cv2.imwrite(str(folder / name), _side_by_side(left, right))
        (folder / f"q{qi:03d}_{kind}.json").write_text(json.dumps(rec.to_dict(), indent=1))
        written.append(f"traces/{name}")
    return written
