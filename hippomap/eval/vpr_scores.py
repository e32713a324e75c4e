"""The scores of ``hippomap eval-vpr``: precision-recall sweeps, the headline run's figures, the summary over
seeds, the per-query table and the evaluation's targets.

:mod:`~hippomap.eval.vpr_eval` runs ours and the RatSLAM baseline; this module turns their per-query results into
the figures of ``metrics.json``. Precision = TP / accepted (1 when nothing is accepted), recall = TP / queries with at
least one positive.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..config import VisualConfig
from .vpr_datasets import VPRDataset

__all__ = [
    "pr_points",
    "ranking_figures",
    "stats_ms",
    "n_positives",
    "ours_metrics",
    "seed_runs",
    "over_seeds",
    "query_rows",
    "targets",
]


def pr_points(scores: np.ndarray, correct: np.ndarray, n_pos: int, higher_better: bool) -> dict[str, Any]:
    """Precision/recall when accepting every query whose score passes a threshold."""
    if scores.size == 0 or n_pos == 0:
        return {
            "precision": [],
            "recall": [],
            "thresholds": [],
            "recall_at_100_precision": 0.0,
            "threshold_at_100_precision": None,
            "average_precision": 0.0,
        }
    order = np.argsort(-scores if higher_better else scores, kind="stable")
    s, c = scores[order], correct[order].astype(float)
    tp, fp = np.cumsum(c), np.cumsum(1.0 - c)
    # a threshold accepts all tied scores at once: keep only the last index of each tie group
    last = np.r_[s[1:] != s[:-1], True]
    tp, fp, s = tp[last], fp[last], s[last]
    precision = tp / (tp + fp)
    recall = tp / n_pos
    ok = precision >= 1.0 - 1e-12
    r100 = float(recall[ok].max()) if ok.any() else 0.0
    t100 = float(s[ok][np.argmax(recall[ok])]) if ok.any() else None
    # average precision: step integration of precision over recall
    prev_r = np.r_[0.0, recall[:-1]]
    ap = float(np.sum((recall - prev_r) * precision))
    f1 = 2 * precision * recall / np.maximum(precision + recall, 1e-12)
    b = int(np.argmax(f1))
    return {
        "precision": precision.round(4).tolist(),
        "recall": recall.round(4).tolist(),
        "thresholds": s.round(6).tolist(),
        "recall_at_100_precision": r100,
        "threshold_at_100_precision": t100,
        "average_precision": ap,
        "best_f1": {
            "f1": float(f1[b]),
            "precision": float(precision[b]),
            "recall": float(recall[b]),
            "threshold": float(s[b]),
        },
    }


def ranking_figures(scores: np.ndarray, ok: np.ndarray, ds: VPRDataset, higher_better: bool) -> dict[str, Any]:
    """The figures of a recogniser that names every query's best reference (right or not: ``ok``) with a score:
    recall@1 over the queries with a positive, and the threshold sweep of :func:`pr_points` (recall at 100 %
    precision and its threshold, average precision, best F1, the curve under ``pr_curve``)."""
    n_pos = n_positives(ds)
    has_pos = np.array([bool(p) for p in ds.positives])
    pr = pr_points(scores, ok, n_pos, higher_better=higher_better)
    return {
        "recall_at_1": float(ok[has_pos].mean()) if n_pos else 0.0,
        "recall_at_100_precision": pr["recall_at_100_precision"],
        "threshold_at_100_precision": pr["threshold_at_100_precision"],
        "average_precision": pr["average_precision"],
        "best_f1": pr.get("best_f1"),
        "pr_curve": {k: pr[k] for k in ("precision", "recall", "thresholds")},
    }


def stats_ms(t: list[float]) -> dict[str, float]:
    a = np.asarray(t) * 1000.0
    if a.size == 0:
        return {"median": 0.0, "p95": 0.0, "mean": 0.0}
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "mean": float(a.mean())}


def n_positives(ds: VPRDataset) -> int:
    """The number of queries with at least one matching reference (recall's denominator)."""
    return sum(1 for p in ds.positives if p)


def ours_metrics(cfg: VisualConfig, main: dict[str, Any], n_pos: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """The headline run's figures (``metrics["ours"]``) and its PR curve sweeping confidence over the accepted
    queries."""
    rows = main["rows"]
    acc = np.array([r["reference"] is not None for r in rows])
    ok = np.array([r["correct"] for r in rows])
    conf = np.array([r["confidence"] for r in rows])
    ours_pr = pr_points(conf[acc], ok[acc], n_pos, higher_better=True)
    fixations = np.array([r["fixations"] for r in rows])
    mem = main["memory"]
    ours = {
        "seed": cfg.seed,
        "precision": main["precision"],
        "recall": main["recall"],
        "accepted": main["accepted"],
        "true_positives": main["tp"],
        "false_positives": main["accepted"] - main["tp"],
        "rejected": int((~acc).sum()),
        "recall_at_100_precision_sweeping_confidence": ours_pr["recall_at_100_precision"],
        "fixations": {"mean": float(fixations.mean()), "median": float(np.median(fixations))},
        "fixations_accepted_median": float(np.median(fixations[acc])) if acc.any() else None,
        "resets_mean": float(np.mean([r["resets"] for r in rows])),
        "skipped_references": main["skipped"],
        "learn_ms": stats_ms(main["t_learn"]),
        "recognise_ms": stats_ms(main["t_rec"]),
        "memory_bytes_per_frame": mem.memory_bytes() / max(1, mem.n_frames),
        "pr_curve": {k: ours_pr[k] for k in ("precision", "recall", "thresholds")},
    }
    return ours, ours_pr


def seed_runs(cfg: VisualConfig, runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each run of ours (run ``k`` with seed ``cfg.seed + k``): its seed, precision, recall, true and false
    positives."""
    return [
        {
            "seed": cfg.seed + k,
            "precision": e["precision"],
            "recall": e["recall"],
            "true_positives": e["tp"],
            "false_positives": e["accepted"] - e["tp"],
        }
        for k, e in enumerate(runs)
    ]


def over_seeds(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Ours over all seeds: every run's figures, the mean and worst precision and recall, the false positives."""
    return {
        "runs": per_seed,
        "precision_mean": float(np.mean([p["precision"] for p in per_seed])),
        "precision_min": float(np.min([p["precision"] for p in per_seed])),
        "recall_mean": float(np.mean([p["recall"] for p in per_seed])),
        "recall_min": float(np.min([p["recall"] for p in per_seed])),
        "false_positives_total": int(sum(p["false_positives"] for p in per_seed)),
    }


def query_rows(ds: VPRDataset, rows_o: list[dict[str, Any]], base_main: dict[str, Any]) -> list[dict[str, Any]]:
    """Per query: its positives, what ours accepted (or not) and what the baseline's best template was."""
    rows = []
    for qi, path in enumerate(ds.queries):
        r = rows_o[qi]
        rows.append(
            {
                "query": qi,
                "file": path.name,
                "positives": sorted(ds.positives[qi]),
                "ours_reference": r["reference"],
                "ours_correct": r["correct"],
                "confidence": r["confidence"],
                "fixations": r["fixations"],
                "resets": r["resets"],
                "baseline_reference": base_main["_best"][qi],
                "baseline_error": base_main["_errors"][qi],
                "baseline_correct": bool(base_main["_ok"][qi]),
            }
        )
    return rows


def targets(main: dict[str, Any], per_seed: list[dict[str, Any]], base_main: dict[str, Any]) -> dict[str, bool]:
    """The evaluation's targets: ours without a false positive, at a recall no lower than the baseline's at
    100 % precision, for the headline seed and for every seed."""
    r100 = base_main["recall_at_100_precision"]
    return {
        "ours_precision_is_100": bool(main["accepted"] == main["tp"]),
        "ours_recall_ge_baseline_recall_at_100_precision": bool(main["recall"] >= r100 - 1e-12),
        "all_seeds_precision_100": bool(all(p["false_positives"] == 0 for p in per_seed)),
        "all_seeds_recall_ge_baseline": bool(all(p["recall"] >= r100 - 1e-12 for p in per_seed)),
    }
