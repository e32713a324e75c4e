"""``hippomap eval-vpr`` on small synthetic datasets in both supported layouts."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from hippomap.config import VisualConfig
from hippomap.errors import HippomapError, InputError
from hippomap.eval import vpr_eval
from hippomap.eval.vpr_datasets import VPRDataset, load_vpr_dataset
from hippomap.eval.vpr_eval import add_parser, evaluate_vpr
from hippomap.eval.vpr_reference import sift_reference
from hippomap.eval.vpr_scores import pr_points
from tests.test_visual_memory import perturb, scene  # the same synthetic scenes


def _write(path: Path, gray: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])


@pytest.fixture(scope="module")
def vpr_bench_dir(tmp_path_factory) -> Path:
    """ref/ + query/ + ground_truth_new.npy: queries 0-3 revisit refs 0-3, queries 4-5 are new places."""
    root = tmp_path_factory.mktemp("vprbench")
    refs = [scene(500 + i) for i in range(6)]
    for i, img in enumerate(refs):
        _write(root / "ref" / f"{i:07d}.jpg", img)
    for q in range(4):
        _write(root / "query" / f"{q:07d}.jpg", perturb(refs[q], seed=q))
    for q in (4, 5):
        _write(root / "query" / f"{q:07d}.jpg", scene(900 + q))
    gt = np.empty((6, 2), dtype=object)
    for q in range(6):
        gt[q, 0] = q
        gt[q, 1] = [q] if q < 4 else []
    np.save(root / "ground_truth_new.npy", gt, allow_pickle=True)
    return root


@pytest.fixture(scope="module")
def rtabmap_dir(tmp_path_factory) -> Path:
    """data/samples/1..10.jpg + data/samples_GT.bmp: frames 6-10 revisit frames 1-5."""
    root = tmp_path_factory.mktemp("rtab")
    first = [scene(700 + i) for i in range(5)]
    for i, img in enumerate(first):
        _write(root / "data" / "samples" / f"{i + 1}.jpg", img)
        _write(root / "data" / "samples" / f"{i + 6}.jpg", perturb(img, seed=i))
    gt = np.zeros((10, 10), np.uint8)
    for i in range(5):
        gt[5 + i, i] = 255
    cv2.imwrite(str(root / "data" / "samples_GT.bmp"), gt)
    return root


def test_layouts_are_read_with_their_ground_truth(vpr_bench_dir, rtabmap_dir):
    ds = load_vpr_dataset(vpr_bench_dir)
    assert len(ds.references) == 6 and len(ds.queries) == 6
    assert ds.positives == [{0}, {1}, {2}, {3}, set(), set()]
    ds = load_vpr_dataset(rtabmap_dir)
    assert [p.name for p in ds.references] == [f"{i}.jpg" for i in range(1, 6)]  # before the first loop closure
    assert [p.name for p in ds.queries] == [f"{i}.jpg" for i in range(6, 11)]
    assert ds.positives == [{0}, {1}, {2}, {3}, {4}]


def test_unknown_layout_and_missing_dir_raise(tmp_path):
    with pytest.raises(InputError):
        load_vpr_dataset(tmp_path / "nope")
    with pytest.raises(InputError):
        load_vpr_dataset(tmp_path)


def test_eval_scores_ours_and_the_baseline_and_writes_outputs(vpr_bench_dir, tmp_path):
    out = tmp_path / "out"
    m = evaluate_vpr(vpr_bench_dir, out, n_examples=2, seeds=2)
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["ours"]["precision"] == m["ours"]["precision"]
    assert m["n_queries"] == 6 and m["n_queries_with_match"] == 4
    o = m["ours"]
    assert o["true_positives"] + o["false_positives"] == o["accepted"]
    assert o["accepted"] + o["rejected"] == 6
    # the revisits are mild (noise, gain, 3 x 5 px shift): every one is found, the new places rejected
    assert o["precision"] == 1.0 and o["recall"] == 1.0
    assert [q["ours_reference"] for q in m["queries"]] == [0, 1, 2, 3, None, None]
    assert len(m["ours_over_seeds"]["runs"]) == 2
    b = m["baseline"]
    assert 0.0 <= b["recall_at_100_precision"] <= 1.0 and 0.0 <= b["recall_at_1"] <= 1.0
    assert set(m["baseline_variants"]) == {"column", "grid_60x10"}
    # the SIFT + RANSAC reference finds the mild revisits too, and the new places score below them
    assert set(m["references"]) == {"sift_inliers", "sift_inlier_ratio"}
    assert m["references"]["sift_inliers"]["recall_at_1"] == 1.0
    assert m["references"]["sift_inliers"]["recall_at_100_precision"] == 1.0
    png = cv2.imread(str(out / "pr_curve.png"))
    assert png is not None and png.shape[0] > 100
    assert m["examples"] and all((out / e).is_file() for e in m["examples"])
    assert all(cv2.imread(str(out / e)) is not None for e in m["examples"])


def _texture(seed: int) -> np.ndarray:
    """Smooth random texture at three scales: the blobs and corners SIFT is built for (the shape scenes of the
    other tests repeat the same few shapes, which a similarity fit matches across scenes)."""
    rng = np.random.default_rng(seed)
    img = sum(cv2.GaussianBlur(rng.normal(0.0, 1.0, (240, 320)), (0, 0), s) * s for s in (2, 5, 12))
    return ((img - img.min()) / np.ptp(img) * 255.0).astype(np.uint8)


def test_sift_reference_fits_a_similarity_and_ranks_unseen_places_below_revisits():
    """The reference's two scores on a revisit seen 1.15 x larger and turned 4 degrees (a similarity, which
    its RANSAC fit follows), a revisit with noise, a change of light and a shift, and two unseen places."""
    refs = [_texture(300 + i) for i in range(4)]
    h, w = refs[0].shape
    zoom = cv2.warpAffine(refs[1], cv2.getRotationMatrix2D((w / 2, h / 2), 4.0, 1.15), (w, h))
    queries = [zoom, perturb(refs[2], seed=1), _texture(950), _texture(951)]
    paths = [Path(f"{i}.png") for i in range(4)]
    ds = VPRDataset("synthetic", paths, paths, [{1}, {2}, set(), set()], "synthetic")
    out = sift_reference(VisualConfig(), ds, refs, queries)
    inl, ratio = out["sift_inliers"], out["sift_inlier_ratio"]
    assert inl["recall_at_1"] == 1.0  # both revisits name their reference
    # a threshold on either score separates the revisits from the unseen places: recall 1 without a false one
    assert inl["recall_at_100_precision"] == 1.0 and ratio["recall_at_100_precision"] == 1.0
    assert inl["threshold_at_100_precision"] >= 50  # a fit of many matches, not a handful of chance ones
    assert max(inl["pr_curve"]["thresholds"][2:]) < 10  # the unseen places: chance matches only
    # the same reference again: the same figures (RANSAC's generator is seeded)
    assert sift_reference(VisualConfig(), ds, refs, queries)["sift_inliers"]["pr_curve"] == inl["pr_curve"]


def test_eval_rtabmap_layout(rtabmap_dir, tmp_path):
    m = evaluate_vpr(rtabmap_dir, tmp_path / "o", seeds=1, n_examples=1)
    assert m["n_references"] == 5 and m["n_queries"] == 5 and m["n_queries_with_match"] == 5
    assert m["ours"]["precision"] == 1.0 and m["ours"]["recall"] >= 0.8
    assert "before the first ground-truth loop closure" in m["protocol"]


def test_pr_points_by_hand():
    # errors (lower is better) with the 3rd-best match wrong: 2 of 4 positives are found
    # before the first false positive -> recall at 100 % precision = 0.5
    pr = pr_points(np.array([0.1, 0.2, 0.3, 0.4]), np.array([True, True, False, True]), 4, higher_better=False)
    assert pr["recall_at_100_precision"] == 0.5
    assert pr["threshold_at_100_precision"] == 0.2
    assert pr["precision"] == [1.0, 1.0, round(2 / 3, 4), 0.75]
    # ties are accepted together: a tie between a true and a false match gives no 100 % point
    pr = pr_points(np.array([0.1, 0.1]), np.array([False, True]), 2, higher_better=False)
    assert pr["recall_at_100_precision"] == 0.0
    pr = pr_points(np.array([0.9, 0.5]), np.array([True, True]), 3, higher_better=True)
    assert pr["recall_at_100_precision"] == pytest.approx(2 / 3)


def test_command_line(vpr_bench_dir, tmp_path, capsys):
    parser = argparse.ArgumentParser(prog="hippomap")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    out = tmp_path / "cli"
    args = parser.parse_args(
        [
            "eval-vpr",
            str(vpr_bench_dir),
            "--out",
            str(out),
            "--seeds",
            "1",
            "--examples",
            "1",
            "--set",
            "n_std=3.0",
            "--set",
            "visual.tolerance_px=6",
        ]
    )
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "precision" in text and "baseline" in text
    cfg = json.loads((out / "metrics.json").read_text())["config"]
    assert cfg["n_std"] == 3.0 and cfg["tolerance_px"] == 6
    bad = parser.parse_args(["eval-vpr", str(vpr_bench_dir), "--out", str(out), "--set", "no_such_field=1"])
    with pytest.raises(InputError, match="no_such_field"):
        bad.func(bad)
    bad = parser.parse_args(["eval-vpr", str(vpr_bench_dir), "--out", str(out), "--set", "n_std=-1"])
    with pytest.raises(InputError):
        bad.func(bad)


def test_missing_baseline_is_a_clear_error(vpr_bench_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(vpr_eval, "BASELINE_PATH", tmp_path / "bench" / "ratslam_baseline.py")
    with pytest.raises(HippomapError, match="ratslam_baseline.py"):
        evaluate_vpr(vpr_bench_dir, tmp_path / "x", seeds=1)
