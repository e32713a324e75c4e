"""``hippomap run-odometry`` end to end on a synthetic g2o data set with known truth.

The robot drives a 20 m x 10 m rectangle twice; its odometry has a heading bias. The
loop file proposes the true revisits (with their true relative poses) and also false
loops between distant places. The map must beat raw odometry by a wide margin, accept
only true loops, and write every export.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hippomap.cli import main
from hippomap.cli.run_odometry import run_odometry
from hippomap.config import HippomapConfig
from hippomap.geometry import between, integrate
from hippomap.io.datasets import load_odometry_dataset
from hippomap.io.exports import read_tum


def _rectangle_increments(laps: int, v: float = 0.5, rate: float = 5.0) -> np.ndarray:
    step = v / rate
    inc = []
    for _ in range(laps):
        for side in (20.0, 10.0, 20.0, 10.0):
            inc += [[step, 0.0, 0.0]] * int(round(side / step))
            inc += [[0.0, 0.0, np.pi / 2 / 8]] * 8  # turn on the spot over 8 steps
    return np.array(inc)


def make_dataset(folder, false_loops: int = 12, seed: int = 0):
    rng = np.random.default_rng(seed)
    true_inc = _rectangle_increments(2)
    gt = integrate(true_inc)
    n = len(gt)
    odo_inc = true_inc.copy()
    odo_inc[:, 2] += 0.0001  # heading bias of 1 mrad per metre: 0.24 rad by the end
    odo_inc[:, 0] *= 1.01  # 1 % scale error
    odo = integrate(odo_inc)
    t = 1000.0 + np.arange(n) * 0.2
    lap = n // 2
    lines = [f"VERTEX_SE2 {i} {x:.9f} {y:.9f} {th:.9f}" for i, (x, y, th) in enumerate(odo)]
    lines += [f"EDGE_SE2 {i} {i + 1} {a:.9f} {b:.9f} {c:.9f} 1 0 0 1 0 1" for i, (a, b, c) in enumerate(odo_inc)]
    truth = {}
    for k in range(lap + 20, n - 20, 15):  # true revisits: the same place one lap earlier
        j = k - lap
        rel = between(gt[k], gt[j])
        lines.append(f"EDGE_SE2 {k} {j} {rel[0]:.9f} {rel[1]:.9f} {rel[2]:.9f} 1 0 0 1 0 1")
        truth[(k, j)] = True
    for _ in range(false_loops):  # distant places with a made-up "same place" transform
        while True:
            k = int(rng.integers(lap, n))
            j = int(rng.integers(0, lap))
            if np.linalg.norm(gt[k, :2] - gt[j, :2]) > 8:
                break
        lines.append(f"EDGE_SE2 {k} {j} {rng.normal(0, 0.3):.9f} {rng.normal(0, 0.3):.9f} 0.0 1 0 0 1 0 1")
        truth[(k, j)] = False
    (folder / "synthetic.g2o").write_text("\n".join(lines) + "\n")
    (folder / "synthetic_timestamps.txt").write_text("\n".join(f"{x:.6f}" for x in t) + "\n")
    (folder / "synthetic_GT.csv").write_text(
        "\n".join(f"{a:.6f}, {x:.6f}, {y:.6f}, {th:.6f}" for a, (x, y, th) in zip(t, gt)) + "\n"
    )
    return truth


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic")
    truth = make_dataset(folder)
    return folder, truth


def test_map_beats_odometry_and_rejects_false_loops(dataset_dir):
    folder, truth = dataset_dir
    ds = load_odometry_dataset(folder, "synthetic.g2o")
    run = run_odometry(ds)
    accepted = [tuple(d["hypothesis"]["meta"]["poses"]) for d in run.decisions if d["status"] == "accepted"]
    rejected = [tuple(d["hypothesis"]["meta"]["poses"]) for d in run.decisions if d["status"] == "rejected"]
    assert accepted, "no loop closure accepted"
    assert all(truth[p] for p in accepted), "a false loop closure was accepted"
    assert sum(not truth[p] for p in rejected) == sum(not v for v in truth.values())
    gt = integrate(_rectangle_increments(2))
    err_odo = np.linalg.norm(run.odometry[:, :2] - gt[:, :2], axis=1).mean()
    err_map = np.linalg.norm(run.corrected[:, :2] - gt[:, :2], axis=1).mean()
    assert err_map < 0.5 * err_odo, (err_map, err_odo)


def test_measured_loop_proposals_prune_online_unless_configured(dataset_dir):
    """``map.prune_online`` None (the default) means on for measured loop proposals: the second
    lap merges into the first lap's nodes; an explicit False keeps every node."""
    folder, _ = dataset_dir
    ds = load_odometry_dataset(folder, "synthetic.g2o")
    default = run_odometry(ds)
    grown = run_odometry(ds, HippomapConfig.with_overrides({"map": {"prune_online": False}}))
    assert "prune" in set(default.cmap.links["kind"])
    assert "prune" not in set(grown.cmap.links["kind"])
    assert default.cmap.node_count < grown.cmap.node_count


def test_cli_writes_exports(dataset_dir, tmp_path, capsys):
    folder, _ = dataset_dir
    out = tmp_path / "out"
    assert main(["run-odometry", str(folder), "--loops", "synthetic.g2o", "--out", str(out), "--no-progress"]) == 0
    assert "ATE rmse odometry" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["map"]["ate"]["rmse"] < metrics["odometry"]["ate"]["rmse"]
    assert metrics["loop_closures"]["accepted_false"] == 0
    lc = metrics["loop_closures"]
    assert lc["accepted"] + lc["rejected"] == lc["proposed"]
    assert lc["revisits"]["episodes"] >= 1 and lc["revisits"]["closed"] == lc["revisits"]["episodes"]  # lap 2
    t_map, p_map = read_tum(out / "map.tum")
    t_odo, _ = read_tum(out / "odometry.tum")
    ts = np.array([float(x) for x in (folder / "synthetic_timestamps.txt").read_text().split()])
    np.testing.assert_allclose(t_map, ts, atol=1e-6)
    np.testing.assert_allclose(t_odo, ts, atol=1e-6)
    graph = json.loads((out / "map.json").read_text())
    assert len(graph["nodes"]) == metrics["nodes"] and len(graph["links"]) == metrics["links"]
    assert (out / "map.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "map.g2o").read_text().startswith("VERTEX_SE2 0 ")


def test_cli_reports_bad_input(tmp_path, capsys):
    (tmp_path / "bad.g2o").write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 nan\n")
    out = str(tmp_path / "o")
    assert main(["run-odometry", str(tmp_path), "--loops", "bad.g2o", "--out", out, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "bad.g2o:2" in err and "non-finite value nan" in err
