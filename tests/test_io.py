"""Dataset readers, exports and evo-based metrics: round trips and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.errors import InputError
from hippomap.eval.evaluation import trajectory_metrics
from hippomap.geometry import between, compose, integrate, wrap_angle
from hippomap.io.datasets import load_odometry_dataset, read_g2o, read_groundtruth_csv, read_timestamps
from hippomap.io.exports import graph_dict, link_transforms, plot_map, read_tum, write_g2o, write_tum

poses_st = st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-3.1, 3.1)), min_size=1, max_size=20)


@given(poses_st, poses_st)
def test_compose_between_inverse(a, b):
    n = min(len(a), len(b))
    a, b = np.array(a[:n]), np.array(b[:n])
    np.testing.assert_allclose(between(a, compose(a, b)), np.column_stack([b[:, :2], wrap_angle(b[:, 2])]), atol=1e-9)


@given(st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-0.5, 0.5)), min_size=1, max_size=30))
def test_integrate_matches_sequential_compose(incs):
    incs = np.array(incs)
    out = integrate(incs)
    pose = np.zeros(3)
    for k, inc in enumerate(incs):
        pose = compose(pose, inc)
        np.testing.assert_allclose(out[k + 1, :2], pose[:2], atol=1e-9)
        assert abs(wrap_angle(out[k + 1, 2] - pose[2])) < 1e-9


def _write_graph(path, n=6, loop=(5, 1)):
    rng = np.random.default_rng(0)
    incs = np.column_stack([rng.uniform(0.1, 0.3, n - 1), rng.normal(0, 0.01, n - 1), rng.normal(0, 0.05, n - 1)])
    verts = integrate(incs)
    lines = [f"VERTEX_SE2 {i} {x} {y} {t}" for i, (x, y, t) in enumerate(verts)]
    lines += [f"EDGE_SE2 {i} {i + 1} {dx} {dy} {dt} 1 0 0 1 0 1" for i, (dx, dy, dt) in enumerate(incs)]
    i, j = loop
    rel = between(verts[i], verts[j])
    lines.append(f"EDGE_SE2 {i} {j} {rel[0]} {rel[1]} {rel[2]} 1 0 0 1 0 1")
    path.write_text("\n".join(lines) + "\n")
    return verts, incs


def test_read_g2o_round_trip(tmp_path):
    verts, incs = _write_graph(tmp_path / "g.g2o")
    g = read_g2o(tmp_path / "g.g2o")
    np.testing.assert_allclose(g.vertices, verts)
    np.testing.assert_allclose(g.odometry, incs)
    assert [(e.i, e.j) for e in g.loops] == [(5, 1)]
    np.testing.assert_allclose(compose(verts[5], g.loops[0].transform), verts[1], atol=1e-9)


@pytest.mark.parametrize(
    "bad, needle",
    [
        ("VERTEX_SE2 0 0 0\n", ":1: VERTEX_SE2 needs"),
        ("VERTEX_SE2 0 0 0 abc\n", "malformed number"),
        ("VERTEX_SE2 0 0 nan 0\n", "non-finite value nan"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", ":3: EDGE_SE2 needs"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 2 0 0 0\n", "missing [1]"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\n", "no odometry edge 0 -> 1"),
        ("BOGUS 1 2\n", "unknown g2o tag 'BOGUS'"),
        ("", "no VERTEX_SE2"),
    ],
)
def test_read_g2o_errors_name_the_line(tmp_path, bad, needle):
    p = tmp_path / "bad.g2o"
    p.write_text(bad)
    with pytest.raises(InputError, match=None) as err:
        read_g2o(p)
    assert needle in str(err.value)


def test_timestamps_and_groundtruth(tmp_path):
    (tmp_path / "t.txt").write_text("1.0\n1.5\n2.0\n")
    np.testing.assert_allclose(read_timestamps(tmp_path / "t.txt"), [1.0, 1.5, 2.0])
    (tmp_path / "bad.txt").write_text("1.0\n2.0\n2.0\n")
    with pytest.raises(InputError, match=r"bad.txt:3: timestamps must increase"):
        read_timestamps(tmp_path / "bad.txt")
    (tmp_path / "gt.csv").write_text("t,x,y,theta\n1.0, 0, 0, 0\n2.0, 1, 0.5, 0.1\n")
    t, p = read_groundtruth_csv(tmp_path / "gt.csv")
    np.testing.assert_allclose(p[1], [1, 0.5, 0.1])
    (tmp_path / "gt2.csv").write_text("1.0, 0, 0\n")
    with pytest.raises(InputError, match="expected 't,x,y,theta'"):
        read_groundtruth_csv(tmp_path / "gt2.csv")


def test_load_dataset_checks_counts(tmp_path):
    _write_graph(tmp_path / "g.g2o")
    (tmp_path / "x_timestamps.txt").write_text("1\n2\n3\n")
    with pytest.raises(InputError, match="3 timestamps but g.g2o has 6 poses"):
        load_odometry_dataset(tmp_path, "g.g2o")
    with pytest.raises(InputError, match="not found"):
        load_odometry_dataset(tmp_path, "missing.g2o")


@settings(max_examples=20, deadline=None)
@given(st.integers(2, 40), st.integers(0, 10_000))
def test_tum_round_trip_through_evo(tmp_path_factory, n, seed):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.05, 1.0, n)) + 1e9
    poses = np.column_stack([rng.normal(0, 20, n), rng.normal(0, 20, n), rng.uniform(-np.pi, np.pi, n)])
    path = write_tum(tmp_path_factory.mktemp("tum") / "x.tum", t, poses)
    t2, p2 = read_tum(path)
    np.testing.assert_allclose(t2, t, rtol=0, atol=1e-6)
    np.testing.assert_allclose(p2[:, :2], poses[:, :2], atol=1e-6)
    assert np.all(np.abs(wrap_angle(p2[:, 2] - poses[:, 2])) < 1e-6)


def test_g2o_export_reads_back(tmp_path):
    poses = integrate([[1, 0, 0.2], [1, 0, 0.2], [1, 0.1, 0]])
    tr = link_transforms([1.0, 1.0], [0.0, 0.1], [0.2, -0.3])
    write_g2o(tmp_path / "m.g2o", poses, [0, 1], [1, 2], tr)
    with pytest.raises(InputError):  # link 2->3 missing: our writer's file is still strict g2o
        read_g2o(tmp_path / "m.g2o")
    write_g2o(tmp_path / "m.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], np.vstack([tr, tr]))
    g = read_g2o(tmp_path / "m.g2o")
    np.testing.assert_allclose(g.vertices, poses, atol=1e-9)
    np.testing.assert_allclose(g.odometry[:2], tr, atol=1e-9)
    assert [(e.i, e.j) for e in g.loops] == [(3, 0)]


def test_graph_dict_and_plot(tmp_path):
    poses = integrate([[1, 0, 0.2], [1, 0, 0.2]])
    d = graph_dict(poses, poses, [3, -1, -1], [0.0, 1.0, 2.0], [0, 1], [1, 2], np.zeros((2, 3)), ["odometry", "loop"])
    assert d["nodes"][0]["frame"] == 3 and d["nodes"][1]["frame"] is None
    assert d["links"][1] == {"source": 1, "target": 2, "transform": [0.0, 0.0, 0.0], "kind": "loop"}
    png = plot_map(tmp_path / "m.png", poses, poses + 0.1, poses, loops=[[[0, 0], [1, 1]]])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_metrics_measure_known_error():
    rng = np.random.default_rng(1)
    t = np.arange(300) * 0.2
    gt = integrate(np.column_stack([np.full(299, 0.1), np.zeros(299), rng.normal(0, 0.02, 299)]))
    exact = trajectory_metrics(t, gt, t, gt)
    assert exact["ate"]["rmse"] < 1e-6
    # a rigid transform is removed by the alignment
    moved = compose(np.array([5.0, -3.0, 0.7]), gt)
    assert trajectory_metrics(t, moved, t, gt)["ate"]["rmse"] < 1e-6
    # a known lateral wobble of +-0.5 m gives an ATE of about 0.5 / sqrt(2) or less after alignment
    wobble = gt.copy()
    wobble[:, 1] += 0.5 * np.sign(np.sin(np.arange(300)))
    ate = trajectory_metrics(t, wobble, t, gt)["ate"]["rmse"]
    assert 0.3 < ate <= 0.5 + 1e-9
    with pytest.raises(InputError, match="timestamp"):
        trajectory_metrics(t + 1000, gt, t, gt)
    line = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    with pytest.raises(InputError, match="cannot align"):
        trajectory_metrics(t[:10], line, t[:10], line)


def test_scaled_ate_tells_a_scaled_copy_from_a_wrong_shape():
    """``scaled``: a map drawn with every distance 5 % long (a scaled copy, moved and turned) has a
    rigid ATE of about 5 % of the path's spread but none once the scale is corrected too, at the
    scale that undoes it; a wrong shape keeps its error either way."""
    rng = np.random.default_rng(2)
    t = np.arange(400) * 0.2
    gt = integrate(np.column_stack([np.full(399, 0.1), np.zeros(399), rng.normal(0, 0.05, 399)]))
    big = compose(np.array([2.0, 1.0, 0.3]), np.column_stack([1.05 * gt[:, :2], gt[:, 2]]))
    m = trajectory_metrics(t, big, t, gt, scaled=True)
    spread = float(np.sqrt(((gt[:, :2] - gt[:, :2].mean(0)) ** 2).sum(1).mean()))
    assert m["ate_scaled"]["rmse"] < 1e-6 and m["ate_scaled"]["scale"] == pytest.approx(1 / 1.05, rel=1e-9)
    assert m["ate"]["rmse"] == pytest.approx(0.05 / 1.05 * spread, rel=0.1)  # the scale error alone, rigidly
    assert "ate_scaled" not in trajectory_metrics(t, big, t, gt)  # only when asked
    wobble = gt.copy()
    wobble[:, 1] += 0.5 * np.sign(np.sin(np.arange(400)))
    w = trajectory_metrics(t, wobble, t, gt, scaled=True)
    assert 0.3 < w["ate_scaled"]["rmse"] <= w["ate"]["rmse"] + 1e-9  # a similarity cannot undo a wrong shape


def test_the_camera_field_of_view_comes_from_the_data_folder(tmp_path):
    """camera.json (hfov_deg or intrinsics) or the simulator's sim.json give the field of view that
    `hippomap run` fills in where the config leaves it unset; a broken file is named, never guessed."""
    import json

    from hippomap.cli.run import dataset_config
    from hippomap.config import HippomapConfig
    from hippomap.io.datasets import SensorDataset, read_camera_hfov

    assert read_camera_hfov(tmp_path) is None
    (tmp_path / "sim.json").write_text(json.dumps({"intrinsics": {"fx": 160.0, "width": 320}}))
    assert read_camera_hfov(tmp_path) == pytest.approx(90.0)
    (tmp_path / "camera.json").write_text(json.dumps({"hfov_deg": 60}))  # camera.json comes first
    assert read_camera_hfov(tmp_path) == 60.0
    for bad, text in (("{", "cannot read"), ("[1]", "JSON object"), ('{"hfov_deg": 200}', r"\(0, 180\)")):
        (tmp_path / "camera.json").write_text(bad)
        with pytest.raises(InputError, match=text):
            read_camera_hfov(tmp_path)
    (tmp_path / "camera.json").write_text(json.dumps({"intrinsics": {"width": 320}}))
    with pytest.raises(InputError, match="camera.json.*fx"):
        read_camera_hfov(tmp_path)
    ds = SensorDataset([], [], None, tmp_path, camera_hfov_deg=70.0)
    assert dataset_config(ds).mapper.camera_hfov_deg == 70.0
    own = HippomapConfig.model_validate({"mapper": {"camera_hfov_deg": 50.0}})
    assert dataset_config(ds, own).mapper.camera_hfov_deg == 50.0  # the config's own value wins
    assert dataset_config(SensorDataset([], [], None, tmp_path)).mapper.camera_hfov_deg is None
