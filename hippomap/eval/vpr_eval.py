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
too, for context, and so is a conventional SIFT + RANSAC recogniser (:mod:`~hippomap.eval.vpr_reference`,
under ``references``). Ours runs at its fixed operating point (accept above the 0.9 decision
threshold after the verification saccades); its PR curve sweeps the recognition's
``confidence`` over the accepted queries. Ours is stochastic: the headline is the run with
``config.seed``, ``seeds`` runs in all are summarised under ``ours_over_seeds``.

Writes ``metrics.json`` (its figures computed in :mod:`~hippomap.eval.vpr_scores`), ``pr_curve.png``
and ``traces/*.png`` (saccade traces on the query beside the accepted reference with its learned
fixation points; :mod:`~hippomap.eval.vpr_figures`).
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
from .vpr_reference import sift_reference
from .vpr_scores import n_positives, ours_metrics, over_seeds, query_rows, ranking_figures, seed_runs, stats_ms, targets

__all__ = ["VPRDataset", "load_vpr_dataset", "evaluate_vpr", "read_visual_config", "add_parser", "load_baseline_module"]

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
    references = sift_reference(cfg, ds, ref_images, query_images)
    main = _run_ours(cfg, ds, ref_images, query_images, progress)
    runs = [main] + [
        _run_ours(cfg.model_copy(update={"seed": cfg.seed + k}), ds, ref_images, query_images, progress)
        for k in range(1, seeds)
    ]
    metrics, ours_pr = _metrics(data_dir, ds, cfg, runs, base_results)
    metrics["references"] = references
    plot_pr(
        out / "pr_curve.png",
        ds.name,
        ours_pr,
        (main["precision"], main["recall"]),
        base_results["column"],
        base_results.get("grid_60x10"),
        references["sift_inliers"],
    )
    recs = [(qi, query_images[qi], rec) for qi, rec in enumerate(main["recs"])]
    metrics["examples"] = write_examples(
        out / "traces", recs, metrics["queries"], main["memory"], main["frame_to_ref"], ref_images, n_examples, cfg
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def _metrics(
    data_dir: str | Path,
    ds: VPRDataset,
    cfg: VisualConfig,
    runs: list[dict[str, Any]],
    base_results: dict[str, dict[str, Any]],
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The figures of ``metrics.json`` (all but the drawn examples) from ours' runs (the headline run first) and
    the baseline variants' results; with ours' PR curve sweeping confidence, for the plot."""
    main, base_main = runs[0], base_results["column"]
    per_seed = seed_runs(cfg, runs)
    ours, ours_pr = ours_metrics(cfg, main, n_positives(ds))
    metrics: dict[str, Any] = {
        "dataset": ds.name,
        "data_dir": str(Path(data_dir).resolve()),
        "protocol": ds.protocol,
        "n_references": len(ds.references),
        "n_queries": len(ds.queries),
        "n_queries_with_match": n_positives(ds),
        "config": cfg.model_dump(mode="json"),
        "ours": ours,
        "ours_over_seeds": over_seeds(per_seed),
        "baseline": {k: v for k, v in base_main.items() if not k.startswith("_")},
        "baseline_variants": {
            n: {k: v for k, v in b.items() if not k.startswith("_") and k != "pr_curve"}
            for n, b in base_results.items()
        },
        "queries": query_rows(ds, main["rows"], base_main),
    }
    metrics["target"] = targets(main, per_seed, base_main)
    return metrics, ours_pr


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
    b_ok = np.array([b in ds.positives[i] for i, b in enumerate(best)])
    figures = ranking_figures(np.array(errs), b_ok, ds, higher_better=False)
    curve = figures.pop("pr_curve")
    return {
        "name": "RatSLAM view templates (OpenRatSLAM local_view_match: SAD with shift)"
        + (", column intensity profile" if bcfg.template_y == 1 else f", {bcfg.template_x}x{bcfg.template_y} template"),
        "config": {k: getattr(bcfg, k) for k in bcfg.__dataclass_fields__},
        **figures,
        "learn_ms": stats_ms(t_bl),
        "compare_ms": stats_ms(t_bc),
        "pr_curve": curve,
        "_best": best,
        "_errors": errs,
        "_ok": b_ok.tolist(),
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


def read_visual_config(config: str | Path | None, sets: list[str] | None) -> VisualConfig:
    """eval-vpr's visual config: the JSON file ``config`` (VisualConfig fields, or a full config with
    ``visual``) with the ``--set KEY=VALUE`` overrides ``sets``; the defaults without either."""
    overrides: dict[str, Any] = {}
    if config:
        try:
            data = json.loads(Path(config).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read config {config}: {exc}") from exc
        overrides.update(data.get("visual", data) if isinstance(data, dict) else {})
    overrides.update(_parse_overrides(sets))
    return _as_visual(overrides or None)


def _run(args: argparse.Namespace) -> int:
    check("eval", "hippomap eval-vpr (precision-recall plot)")
    m = evaluate_vpr(
        args.data_dir,
        args.out,
        read_visual_config(args.config, args.set),
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
    r1, r2 = m["references"]["sift_inliers"], m["references"]["sift_inlier_ratio"]
    print(
        f"  (SIFT + RANSAC: recall at 100% precision {r1['recall_at_100_precision']:.3f} by inliers, "
        f"{r2['recall_at_100_precision']:.3f} by inliers over the runner-up's; recall@1 {r1['recall_at_1']:.3f})"
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
