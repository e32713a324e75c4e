"""``hippomap eval-vpr``: visual place recognition of the recognition memory on real images.

One run scores ours and the baseline on the same queries: the references are learned as key
frames and every query is recognised against all of them (``candidates=None``); the two data set
layouts, and how each gives references, queries and positives, are in :mod:`~hippomap.eval.vpr_datasets`.

A query counts as a true positive when the accepted frame is one of its positives, a false
positive when another frame is accepted; precision = TP / accepted (1 when nothing is
accepted), recall = TP / queries with at least one positive. The baseline
(``bench/ratslam_baseline.py``: OpenRatSLAM's view templates with the column intensity
profile, loaded by path so ``hippomap`` never imports ``bench``) always returns its best
template and an error; its PR curve sweeps the match threshold, and its *recall at 100 %
precision* is the best recall any threshold reaches without a false positive (an oracle
choice of threshold, favourable to it). A 60 x 10 OpenRatSLAM template variant is scored
too, for context. Ours runs at its fixed operating point (accept above the 0.9 decision
threshold after the verification saccades); its PR curve sweeps the recognition's
``confidence`` over the accepted queries. Ours is stochastic: the headline is the run with
``config.seed``, ``seeds`` runs in all are summarised under ``ours_over_seeds``.

Writes ``metrics.json``, ``pr_curve.png`` and ``traces/*.png`` (saccade traces on the query
beside the accepted reference with its learned fixation points; :mod:`~hippomap.eval.vpr_figures`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..cli import add_progress_argument, progress_enabled
from ..config import HippomapConfig, VisualConfig
from ..errors import HippomapError, InputError
from ..extras import check
from ..visual_memory import VisualMemory
from .vpr_datasets import VPRDataset, load_vpr_dataset, read_image
from .vpr_figures import plot_pr, write_examples

__all__ = ["VPRDataset", "load_vpr_dataset", "evaluate_vpr", "add_parser", "load_baseline_module"]

_REPO_ROOT = Path(__file__).resolve().parents[2]
BASELINE_PATH = _REPO_ROOT / "bench" / "ratslam_baseline.py"


def load_baseline_module():
    """Import ``bench/ratslam_baseline.py`` from the repository root (not a package import,
    so that ``hippomap`` never depends on ``bench`` at import time)."""
    if not BASELINE_PATH.is_file():
        raise HippomapError(f"the RatSLAM baseline {BASELINE_PATH} is missing: eval-vpr needs a source checkout")
    spec = importlib.util.spec_from_file_location("hippomap_bench_ratslam_baseline", BASELINE_PATH)
    assert spec is not None  # a .py file that exists (checked above)
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _pr_points(scores: np.ndarray, correct: np.ndarray, n_pos: int, higher_better: bool) -> dict[str, Any]:
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


def _stats_ms(t: list[float]) -> dict[str, float]:
    a = np.asarray(t) * 1000.0
    if a.size == 0:
        return {"median": 0.0, "p95": 0.0, "mean": 0.0}
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "mean": float(a.mean())}


def _as_visual(config: Any) -> VisualConfig:
    if config is None:
        return VisualConfig()
    if isinstance(config, VisualConfig):
        return config
    if isinstance(config, HippomapConfig):
        return config.visual
    if isinstance(config, dict):
        try:
            return VisualConfig.model_validate({**VisualConfig().model_dump(), **config})
        except Exception as exc:  # pydantic ValidationError
            raise InputError(f"bad visual config override {config!r}: {exc}") from exc
    raise InputError(f"config must be a VisualConfig, HippomapConfig or dict, got {type(config).__name__}")


def _run_ours(
    cfg: VisualConfig,
    ds: VPRDataset,
    ref_images: list[np.ndarray],
    query_images: list[np.ndarray],
    progress: bool = False,
) -> dict[str, Any]:
    """Learn every reference, recognise every query (candidates = all frames)."""
    mem = VisualMemory(cfg)
    frame_to_ref: dict[int, int] = {}
    t_learn, skipped = [], []
    for i, img in enumerate(ref_images):
        t0 = time.perf_counter()
        fid = mem.learn(img)
        t_learn.append(time.perf_counter() - t0)
        if fid is None:
            skipped.append(i)
        else:
            frame_to_ref[fid] = i
    rows: list[dict[str, Any]] = []
    recs, t_rec = [], []
    for qi, img in enumerate(query_images):
        t0 = time.perf_counter()
        rec = mem.recognise(img)
        t_rec.append(time.perf_counter() - t0)
        ref = frame_to_ref.get(rec.frame_id) if rec.accepted and rec.frame_id is not None else None
        pos = ds.positives[qi]
        rows.append(
            {
                "reference": ref,
                "correct": bool(ref is not None and ref in pos),
                "confidence": rec.confidence,
                "fixations": rec.n_fixations,
                "resets": rec.n_resets,
            }
        )
        recs.append(rec)
        if progress:
            print(
                f"seed {cfg.seed} query {qi + 1}/{len(query_images)}: -> {ref} "
                f"({'ok' if rows[-1]['correct'] else '-'})",
                file=sys.stderr,
            )
    n_pos = sum(1 for p in ds.positives if p)
    tp = sum(r["correct"] for r in rows)
    n_acc = sum(r["reference"] is not None for r in rows)
    return {
        "memory": mem,
        "frame_to_ref": frame_to_ref,
        "rows": rows,
        "recs": recs,
        "skipped": skipped,
        "t_learn": t_learn,
        "t_rec": t_rec,
        "tp": tp,
        "accepted": n_acc,
        "precision": tp / n_acc if n_acc else 1.0,
        "recall": tp / n_pos if n_pos else 0.0,
    }


#: the baseline of the issue (column intensity profile) and a 2-D OpenRatSLAM template for context
BASELINE_VARIANTS = {
    "column": {},
    "grid_60x10": {"template_y": 10, "shift": 10},
}


def evaluate_vpr(
    data_dir: str | Path,
    out_dir: str | Path,
    config: Any = None,
    n_examples: int = 4,
    progress: bool = False,
    seeds: int = 3,
) -> dict[str, Any]:
    """Learn the references, query the queries, score ours and the RatSLAM baseline; write
    ``metrics.json``, ``pr_curve.png`` and ``traces/``. Returns the metrics dict.

    Ours is stochastic (fixation order, weight jitter): the headline figures are those of
    ``config.seed``; ``seeds - 1`` further runs with seeds ``config.seed + 1, ...`` are
    summarised under ``ours_over_seeds``.
    """
    cfg = _as_visual(config)
    if seeds < 1:
        raise InputError(f"seeds must be >= 1, got {seeds}")
    ds = load_vpr_dataset(data_dir)
    baseline_mod = load_baseline_module()
    out = Path(out_dir)
    (out / "traces").mkdir(parents=True, exist_ok=True)
    ref_images = [read_image(p) for p in ds.references]
    query_images = [read_image(p) for p in ds.queries]
    base_results = {
        name: _run_baseline(baseline_mod, over, ds, ref_images, query_images)
        for name, over in BASELINE_VARIANTS.items()
    }
    base_main = base_results["column"]
    main = _run_ours(cfg, ds, ref_images, query_images, progress)
    runs = [main] + [
        _run_ours(cfg.model_copy(update={"seed": cfg.seed + k}), ds, ref_images, query_images, progress)
        for k in range(1, seeds)
    ]
    per_seed = [
        {
            "seed": cfg.seed + k,
            "precision": e["precision"],
            "recall": e["recall"],
            "true_positives": e["tp"],
            "false_positives": e["accepted"] - e["tp"],
        }
        for k, e in enumerate(runs)
    ]
    ours, ours_pr = _ours_metrics(cfg, main, _n_positives(ds))
    metrics: dict[str, Any] = {
        "dataset": ds.name,
        "data_dir": str(Path(data_dir).resolve()),
        "protocol": ds.protocol,
        "n_references": len(ds.references),
        "n_queries": len(ds.queries),
        "n_queries_with_match": _n_positives(ds),
        "config": cfg.model_dump(mode="json"),
        "ours": ours,
        "ours_over_seeds": _over_seeds(per_seed),
        "baseline": {k: v for k, v in base_main.items() if not k.startswith("_")},
        "baseline_variants": {
            n: {k: v for k, v in b.items() if not k.startswith("_") and k != "pr_curve"}
            for n, b in base_results.items()
        },
        "queries": _query_rows(ds, main["rows"], base_main),
    }
    metrics["target"] = _targets(main, per_seed, base_main)
    plot_pr(
        out / "pr_curve.png",
        ds.name,
        ours_pr,
        (main["precision"], main["recall"]),
        base_main,
        base_results.get("grid_60x10"),
    )
    recs = [(qi, query_images[qi], rec) for qi, rec in enumerate(main["recs"])]
    metrics["examples"] = write_examples(
        out / "traces", recs, metrics["queries"], main["memory"], main["frame_to_ref"], ref_images, n_examples, cfg
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def _n_positives(ds: VPRDataset) -> int:
    """The number of queries with at least one matching reference (recall's denominator)."""
    return sum(1 for p in ds.positives if p)


def _timed(fn: Any, items: list[np.ndarray]) -> tuple[list[Any], list[float]]:
    """``fn`` applied to every item in order: the results and the seconds each call took."""
    results, seconds = [], []
    for item in items:
        t0 = time.perf_counter()
        results.append(fn(item))
        seconds.append(time.perf_counter() - t0)
    return results, seconds


def _run_baseline(
    baseline_mod: Any,
    over: dict[str, int],
    ds: VPRDataset,
    ref_images: list[np.ndarray],
    query_images: list[np.ndarray],
) -> dict[str, Any]:
    """One RatSLAM view-template variant (``over``: its config overrides): learn the references, compare every
    query, score its best templates by sweeping the match threshold. Keys starting with ``_`` are per query."""
    bcfg = baseline_mod.RatSLAMViewTemplateConfig(**over)
    base = baseline_mod.RatSLAMViewTemplates(bcfg)
    _, t_bl = _timed(base.add, ref_images)
    compared, t_bc = _timed(base.compare, query_images)
    best, errs = [b_id for b_id, _ in compared], [b_err for _, b_err in compared]
    n_pos = _n_positives(ds)
    has_pos = np.array([bool(p) for p in ds.positives])
    b_ok = np.array([b in ds.positives[i] for i, b in enumerate(best)])
    pr = _pr_points(np.array(errs), b_ok, n_pos, higher_better=False)
    return {
        "name": "RatSLAM view templates (OpenRatSLAM local_view_match: SAD with shift)"
        + (", column intensity profile" if bcfg.template_y == 1 else f", {bcfg.template_x}x{bcfg.template_y} template"),
        "config": {k: getattr(bcfg, k) for k in bcfg.__dataclass_fields__},
        "recall_at_1": float(b_ok[has_pos].mean()) if n_pos else 0.0,
        "recall_at_100_precision": pr["recall_at_100_precision"],
        "threshold_at_100_precision": pr["threshold_at_100_precision"],
        "average_precision": pr["average_precision"],
        "best_f1": pr.get("best_f1"),
        "learn_ms": _stats_ms(t_bl),
        "compare_ms": _stats_ms(t_bc),
        "pr_curve": {k: pr[k] for k in ("precision", "recall", "thresholds")},
        "_best": best,
        "_errors": errs,
        "_ok": b_ok.tolist(),
    }


def _ours_metrics(cfg: VisualConfig, main: dict[str, Any], n_pos: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """The headline run's figures (``metrics["ours"]``) and its PR curve sweeping confidence over the accepted
    queries."""
    rows = main["rows"]
    acc = np.array([r["reference"] is not None for r in rows])
    ok = np.array([r["correct"] for r in rows])
    conf = np.array([r["confidence"] for r in rows])
    ours_pr = _pr_points(conf[acc], ok[acc], n_pos, higher_better=True)
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
        "learn_ms": _stats_ms(main["t_learn"]),
        "recognise_ms": _stats_ms(main["t_rec"]),
        "memory_bytes_per_frame": mem.memory_bytes() / max(1, mem.n_frames),
        "pr_curve": {k: ours_pr[k] for k in ("precision", "recall", "thresholds")},
    }
    return ours, ours_pr


def _over_seeds(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """Ours over all seeds: every run's figures, the mean and worst precision and recall, the false positives."""
    return {
        "runs": per_seed,
        "precision_mean": float(np.mean([p["precision"] for p in per_seed])),
        "precision_min": float(np.min([p["precision"] for p in per_seed])),
        "recall_mean": float(np.mean([p["recall"] for p in per_seed])),
        "recall_min": float(np.min([p["recall"] for p in per_seed])),
        "false_positives_total": int(sum(p["false_positives"] for p in per_seed)),
    }


def _query_rows(ds: VPRDataset, rows_o: list[dict[str, Any]], base_main: dict[str, Any]) -> list[dict[str, Any]]:
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


def _targets(main: dict[str, Any], per_seed: list[dict[str, Any]], base_main: dict[str, Any]) -> dict[str, bool]:
    """The evaluation's targets: ours without a false positive, at a recall no lower than the baseline's at
    100 % precision, for the headline seed and for every seed."""
    r100 = base_main["recall_at_100_precision"]
    return {
        "ours_precision_is_100": bool(main["accepted"] == main["tp"]),
        "ours_recall_ge_baseline_recall_at_100_precision": bool(main["recall"] >= r100 - 1e-12),
        "all_seeds_precision_100": bool(all(p["false_positives"] == 0 for p in per_seed)),
        "all_seeds_recall_ge_baseline": bool(all(p["recall"] >= r100 - 1e-12 for p in per_seed)),
    }


# ---------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------
def _parse_overrides(items: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise InputError(f"--set expects KEY=VALUE (a VisualConfig field), got {item!r}")
        key, value = item.split("=", 1)
        key = key.strip()
        if key.startswith("visual."):
            key = key[len("visual.") :]
        if key not in VisualConfig.model_fields:
            known = ", ".join(sorted(VisualConfig.model_fields))
            raise InputError(f"--set {key!r}: not a VisualConfig field; known: {known}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _run(args: argparse.Namespace) -> int:
    check("eval", "hippomap eval-vpr (precision-recall plot)")
    overrides: dict[str, Any] = {}
    if args.config:
        try:
            data = json.loads(Path(args.config).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read config {args.config}: {exc}") from exc
        overrides.update(data.get("visual", data) if isinstance(data, dict) else {})
    overrides.update(_parse_overrides(args.set))
    m = evaluate_vpr(
        args.data_dir,
        args.out,
        overrides or None,
        n_examples=args.examples,
        progress=progress_enabled(args),
        seeds=args.seeds,
    )
    o, b = m["ours"], m["baseline"]
    print(
        f"{m['dataset']}: {m['n_references']} references, "
        f"{m['n_queries']} queries ({m['n_queries_with_match']} with a match)"
    )
    print(
        f"  ours:     precision {o['precision']:.3f}  recall {o['recall']:.3f}  "
        f"({o['true_positives']} TP, {o['false_positives']} FP, {o['rejected']} rejected; "
        f"median {o['recognise_ms']['median']:.1f} ms/query)"
    )
    sd = m["ours_over_seeds"]
    print(
        f"  ours over {len(sd['runs'])} seeds: "
        f"precision mean {sd['precision_mean']:.3f} (min {sd['precision_min']:.3f}), "
        f"recall mean {sd['recall_mean']:.3f} (min {sd['recall_min']:.3f}), "
        f"{sd['false_positives_total']} FP in total"
    )
    print(
        f"  baseline: recall at 100% precision {b['recall_at_100_precision']:.3f}  recall@1 {b['recall_at_1']:.3f}  "
        f"AP {b['average_precision']:.3f}"
    )
    b2 = m["baseline_variants"].get("grid_60x10")
    if b2:
        print(
            f"  (RatSLAM 60x10 templates: recall at 100% precision {b2['recall_at_100_precision']:.3f}, "
            f"recall@1 {b2['recall_at_1']:.3f})"
        )
    print(f"  wrote {Path(args.out) / 'metrics.json'}, pr_curve.png, traces/")
    return 0


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``eval-vpr DATA_DIR --out OUT_DIR`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "eval-vpr",
        help="visual place recognition: ours vs the RatSLAM baseline on real images with ground truth",
        description="Visual place recognition on real images with ground-truth loop closures: learn the reference "
        "frames, query the others, score ours and the RatSLAM view-template baseline in one run.",
    )
    p.add_argument(
        "data_dir", metavar="DATA_DIR", help="dataset folder (VPR-Bench ref/query layout or RTAB-Map samples)"
    )
    p.add_argument(
        "--out", required=True, metavar="OUT_DIR", help="output folder for metrics.json, pr_curve.png, traces/"
    )
    p.add_argument(
        "--config", metavar="JSON", help="JSON file with VisualConfig overrides (or a full config with 'visual')"
    )
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override one VisualConfig field, repeatable")
    p.add_argument(
        "--examples",
        type=int,
        default=4,
        help="matches drawn as saccade-trace images (default 4), plus one false match and one rejection",
    )
    p.add_argument("--seeds", type=int, default=3, help="runs of ours with seeds seed, seed+1, ... (default 3)")
    add_progress_argument(p)  # one line per query on stderr
    p.set_defaults(func=_run)
    return p
