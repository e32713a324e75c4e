"""Exports a SLAM user takes away: g2o with each link's information, ground truth as TUM, and a
session's recorded inputs as a data folder and as a ROS 2 bag that the offline mapper re-runs.

The end-to-end tests stream a small simulated run into a real server session, download the
exports with the Python client, run the offline mapper on them and compare with the session."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.cli.run import link_error, open_dataset, run_dataset, write_run
from hippomap.cognitive_map import CognitiveMap, LoopHypothesis
from hippomap.config import HippomapConfig, MapConfig
from hippomap.errors import InputError
from hippomap.geometry import compose, integrate, wrap_angle
from hippomap.inputs import Odometry, decode_jpeg
from hippomap.io.datasets import UNIT_INFORMATION, read_folder_dataset, read_g2o
from hippomap.io.exports import link_information, read_tum, write_g2o
from hippomap.io.rosbag import read_rosbag
from hippomap.io.session_export import (
    GROUNDTRUTH_TOPIC,
    IMAGE_TOPIC,
    ODOM_TOPIC,
    EncodedFrame,
    increments,
    write_data_dir,
    write_rosbag2,
)
from hippomap.mapper import Mapper
from tests.test_cognitive_map import drive, square_increments, true_loops

ROOT = Path(__file__).resolve().parents[1]

CONFIG = {"mapper": {"keyframe_interval": 5}}


# ------------------------------------------------------------------ g2o information
def _map_with_weak_and_strong_loops() -> CognitiveMap:
    """Two laps of a square with true loop closures, and one false closure (0.6 m off) that
    the robust kernel fades: loop links of weight ~1 and of weight << 1."""
    inc = square_increments()
    gt = integrate(inc)
    first = len(inc) // 2
    truth = true_loops(gt, first, every=10)

    def hyps(k, cmap, node_at, off):
        out = truth(k, cmap, node_at, off)
        if k == first + 200:
            out += [
                LoopHypothesis(
                    node=h.node,
                    transform=tuple(compose(h.transform, (0.6, 0.3, 0.1))),
                    source="false",
                    time=h.time + 0.5,
                )
                for h in out
            ]
        return out

    # relocalising on the closures: the next node hangs off an old one, so the map is no chain
    cmap = CognitiveMap(MapConfig(prune_online=False, loop_min_support=1, loop_relocalise=True))
    drive(cmap, inc, hypotheses=hyps)
    cmap.finish()
    return cmap


def _rows(src, dst, info):
    """Edges as rows sorted by (source, target, information): comparable whatever order they were
    read in (parallel links between two nodes included)."""
    rows = np.column_stack([src, dst, info]).astype(float)
    return rows[np.lexsort(rows.T[::-1])]


def test_g2o_carries_each_links_information_and_reads_back(tmp_path):
    cmap = _map_with_weak_and_strong_loops()
    cfg = cmap.cfg
    links = cmap.links
    kinds = links["kind"]
    info = link_information(cmap)
    w = cmap.link_weights()
    loop = np.flatnonzero(kinds == "loop")
    odo = np.flatnonzero(kinds == "odometry")
    assert w[loop].max() > 0.99 and w[loop].min() < 0.1, w[loop]  # a strong and a faded loop link

    # odometric links: odometry_information_per_m over the length (heading: plus the turn's variance)
    length = np.maximum(np.hypot(links["transform"][odo, 0], links["transform"][odo, 1]), 0.05)
    xy, th = cfg.odometry_information_per_m
    np.testing.assert_allclose(info[odo, 0], xy / length)
    np.testing.assert_allclose(
        info[odo, 2], 1 / (length / th + cfg.odometry_turn_variance * np.abs(links["transform"][odo, 2]))
    )
    # loop links: their information times their robust weight
    strong, weak = loop[np.argmax(w[loop])], loop[np.argmin(w[loop])]
    lx, lth = cfg.loop_information
    np.testing.assert_allclose(info[strong], np.array([lx, lx, lth]) * w[strong])
    np.testing.assert_allclose(info[weak], np.array([lx, lx, lth]) * w[weak])
    assert info[weak, 0] < 0.1 * info[strong, 0]

    path = write_g2o(tmp_path / "map.g2o", cmap.poses, links["source"], links["target"], links["transform"], info)
    edge_lines = [ln.split() for ln in path.read_text().splitlines() if ln.startswith("EDGE_SE2")]
    assert len({tuple(ln[6:]) for ln in edge_lines}) > 3  # not one matrix for every edge
    with pytest.raises(InputError, match="no odometry edge"):  # after a loop the map is no chain
        read_g2o(path)
    g = read_g2o(path, chain=False)
    np.testing.assert_allclose(g.vertices, cmap.poses, atol=1e-8)
    src, dst, tr, full = g.edges()
    assert len(src) == cmap.link_count
    assert np.all(full[:, [1, 2, 4]] == 0)  # diagonal information
    written = _rows(links["source"], links["target"], info)
    read = _rows(src, dst, full[:, [0, 3, 5]])
    np.testing.assert_array_equal(read[:, :2], written[:, :2])
    np.testing.assert_allclose(read[:, 2:], written[:, 2:], rtol=1e-15)  # repr: exact
    parallel = [e.information for e in g.loops if (e.i, e.j) == (links["source"][weak], links["target"][weak])]
    assert (info[weak, 0], 0.0, 0.0, info[weak, 1], 0.0, info[weak, 2]) in parallel


def test_g2o_information_defaults_and_is_checked(tmp_path):
    poses = integrate([[1, 0, 0.2], [1, 0, 0.2], [1, 0.1, 0]])
    tr = [[1, 0, 0.2], [1, 0, 0.2], [1, 0.1, 0], [0.5, 0.5, 0.1]]
    g = read_g2o(write_g2o(tmp_path / "u.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], tr))
    assert np.all(g.odometry_information == UNIT_INFORMATION) and g.loops[0].information == UNIT_INFORMATION
    info = [[10, 10, 100], [20, 20, 200], [30, 30, 300], [0.5, 0.5, 5]]
    g = read_g2o(write_g2o(tmp_path / "i.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], tr, info))
    np.testing.assert_array_equal(g.odometry_information[:, [0, 3, 5]], info[:3])
    assert g.loops[0].information == (0.5, 0.0, 0.0, 0.5, 0.0, 5.0)
    with pytest.raises(InputError, match=r"link 3 has information \[0.5, -1.0, 5.0\]"):
        write_g2o(tmp_path / "bad.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], tr, [*info[:3], [0.5, -1, 5]])
    with pytest.raises(InputError, match=r"information must have shape \(4, 3\)"):
        write_g2o(tmp_path / "bad.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], tr, info[:2])
    # a coupled loop link (heading + c · y measured): its matrix has the y-heading term, J^T diag J
    g = read_g2o(write_g2o(tmp_path / "c.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], tr, info, [0, 0, 0, 0.25]))
    np.testing.assert_array_equal(g.odometry_information[:, [0, 3, 5]], info[:3])  # uncoupled: as before
    J = np.array([[1, 0, 0], [0, 1, 0], [0, 0.25, 1]])  # residual rows x, y, heading + c · y
    full = J.T @ np.diag(info[3]) @ J
    np.testing.assert_allclose(g.loops[0].information, full[np.triu_indices(3)])
    with pytest.raises(InputError, match="coupling must be 4 finite values"):
        write_g2o(tmp_path / "bad.g2o", poses, [0, 1, 2, 3], [1, 2, 3, 0], tr, info, [0, 0, -1, 0])


# ------------------------------------------------------------- recorded inputs
def _circle_gt(t: float, speed: float = 0.5, radius: float = 1.0) -> tuple[float, float, float]:
    a = speed / radius * t
    return (radius * math.sin(a), radius * (1 - math.cos(a)), float(wrap_angle(a)))


def recorded_items(n_odometry: int = 300, frame_every: int = 3, seed: int = 3, with_gt: bool = True):
    """The synthetic circling run of tests.support.synthetic, readings carrying ground truth (300 readings:
    over a lap, so the map closes loops)."""
    from tests.support.synthetic import synthetic_inputs

    out = []
    for it in synthetic_inputs(n_odometry=n_odometry, frame_every=frame_every, seed=seed):
        if it[0] == "odometry" and with_gt:
            o = it[1]
            out.append(("odometry", Odometry(o.t, v=o.v, omega=o.omega, gt=_circle_gt(o.t))))
        else:
            out.append(it)
    return tuple(out)


def _inputs(items):
    return [it[1] if it[0] == "odometry" else EncodedFrame(it[1], it[2]) for it in items]


def _mapper_on(dataset, config=None) -> Mapper:
    return run_dataset(dataset, HippomapConfig.with_overrides(config or {}))[0]


def test_data_folder_round_trip_and_run_writes_groundtruth_tum(tmp_path):
    items = recorded_items(n_odometry=60)
    inputs = _inputs(items)
    folder = write_data_dir(tmp_path / "data", inputs, config=CONFIG)
    ds = read_folder_dataset(folder)
    readings = [x for x in inputs if isinstance(x, Odometry)]
    frames = [x for x in inputs if isinstance(x, EncodedFrame)]
    assert (folder / "odometry.csv").read_text().startswith("t,v,omega\n")
    assert [(o.t, o.v, o.omega) for o in ds.odometry] == [(o.t, o.v, o.omega) for o in readings]
    assert [f.t for f in ds.frames] == [f.t for f in frames]
    assert [f.path.read_bytes() for f in ds.frames] == [f.data for f in frames]  # the bytes as recorded
    np.testing.assert_array_equal(ds.groundtruth[1], [o.gt for o in readings])
    assert json.loads((folder / "config.json").read_text()) == CONFIG
    with pytest.raises(InputError, match="already holds a data set"):
        write_data_dir(folder, inputs)

    m, timing = run_dataset(ds, HippomapConfig.with_overrides(CONFIG))
    write_run(m, ds, tmp_path / "out", timing)
    t, poses = read_tum(tmp_path / "out" / "groundtruth.tum")
    np.testing.assert_allclose(t, [o.t for o in readings])
    np.testing.assert_allclose(poses, [o.gt for o in readings], atol=1e-9)
    # no ground truth in the data set: no groundtruth.tum
    (folder / "groundtruth.csv").unlink()
    write_run(m, read_folder_dataset(folder), tmp_path / "out2", timing)
    assert (tmp_path / "out2" / "map.tum").is_file() and not (tmp_path / "out2" / "groundtruth.tum").exists()


def test_increment_readings_export_as_increments_the_mapper_integrates_alike(tmp_path):
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.05, 0.1, 40)) + 10
    readings = [
        Odometry(float(t[k]), v=0.4, omega=0.2)
        if k % 3
        else Odometry(float(t[k]), increment=tuple(map(float, rng.normal(0, 0.05, 3))))
        for k in range(40)
    ]
    folder = write_data_dir(tmp_path / "inc", readings)
    assert (folder / "odometry.csv").read_text().startswith("t,dx,dy,dtheta\n")
    ds = read_folder_dataset(folder)
    assert all(o.increment is not None for o in ds.odometry)
    a, b = Mapper(HippomapConfig()), Mapper(HippomapConfig())
    for o in readings:
        a.step(o)
    for o in ds.odometry:
        b.step(o)
    np.testing.assert_array_equal(a.odometry_trajectory(), b.odometry_trajectory())
    with pytest.raises(InputError, match="no odometry to export"):
        write_data_dir(tmp_path / "empty", [EncodedFrame(1.0, b"\xff\xd8\xff")])


def test_rosbag2_round_trip_gives_the_same_inputs(tmp_path):
    items = recorded_items(n_odometry=40)
    inputs = _inputs(items)
    counts = write_rosbag2(tmp_path / "bag", inputs)
    readings = [x for x in inputs if isinstance(x, Odometry)]
    frames = [x for x in inputs if isinstance(x, EncodedFrame)]
    assert counts == {"odometry": len(readings), "frames": len(frames), "groundtruth": len(readings)}
    ds = read_rosbag(tmp_path / "bag", IMAGE_TOPIC, ODOM_TOPIC, groundtruth_topic=GROUNDTRUTH_TOPIC)
    np.testing.assert_allclose([o.t for o in ds.odometry], [o.t for o in readings], rtol=0, atol=1e-9)
    np.testing.assert_allclose([o.increment for o in ds.odometry], increments(readings), rtol=0, atol=1e-12)
    np.testing.assert_allclose([f.t for f in ds.frames], [f.t for f in frames], rtol=0, atol=1e-9)
    for got, sent in zip(ds.frames, frames):
        np.testing.assert_array_equal(got.load().image, decode_jpeg(sent.data))
    np.testing.assert_allclose(ds.groundtruth[1], [o.gt for o in readings], atol=1e-12)
    with pytest.raises(InputError, match="exists already"):
        write_rosbag2(tmp_path / "bag", inputs)
    with pytest.raises(InputError, match="positive times only"):
        write_rosbag2(tmp_path / "neg", [Odometry(-1.0, v=0.0, omega=0.0)])


# ----------------------------------------------------------- through the service
@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from tests.support.live import LiveServer

    srv = LiveServer(tmp_path_factory.mktemp("exports")).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def recorded(server):
    """A session fed the simulated run (with ground truth) over the websocket, fully processed."""
    import asyncio

    from tests.support.live import stream_items

    items = recorded_items()
    with server.client() as c:
        sid = c.create_session("exports", CONFIG)["id"]
        asyncio.run(stream_items(server.url, server.token, sid, items))
        c.wait_processed(sid)
    return sid, items


def _unzip(path: Path, into: Path, sid: str) -> Path:
    with zipfile.ZipFile(path) as zf:
        assert all(n.startswith(f"{sid}/") for n in zf.namelist())
        zf.extractall(into)
    return into / sid


def _assert_same_map(map_json: dict, session_map: dict, atol: float) -> None:
    assert len(map_json["nodes"]) == len(session_map["nodes"]) > 3
    assert any(ln["kind"] == "loop" for ln in session_map["links"])  # the run closed loops
    np.testing.assert_allclose(
        [n["pose"] for n in map_json["nodes"]], [n["pose"] for n in session_map["nodes"]], atol=atol
    )
    assert [(ln["source"], ln["target"], ln["kind"]) for ln in map_json["links"]] == [
        (ln["source"], ln["target"], ln["kind"]) for ln in session_map["links"]
    ]


def test_session_groundtruth_and_g2o_downloads(server, recorded):
    from hippomap.client import ServerError
    from tests.support.synthetic import decoded

    sid, items = recorded
    readings = [it[1] for it in items if it[0] == "odometry"]
    with server.client() as c:
        path = Path(server.data_dir) / "gt.tum"
        path.write_text(c.groundtruth_tum(sid))
        t, poses = read_tum(path)
        np.testing.assert_allclose(t, [o.t for o in readings])
        np.testing.assert_allclose(poses, [o.gt for o in readings], atol=1e-9)
        plain = c.create_session("no-gt", CONFIG)["id"]
        c.send_odometry(plain, [Odometry(1.0, v=0.1, omega=0.0), Odometry(1.1, v=0.1, omega=0.0)])
        with pytest.raises(ServerError) as e:
            c.groundtruth_tum(plain)
        assert e.value.status == 404 and "has no ground truth" in str(e.value.detail)
        with pytest.raises(ServerError) as e:
            c.trajectory_tum(sid, "bogus")
        assert e.value.status == 422

        # map.g2o: each link with the information the session's map gives it
        (Path(server.data_dir) / "map.g2o").write_text(c.map_g2o(sid))
    g = read_g2o(Path(server.data_dir) / "map.g2o", chain=False)
    m = Mapper(HippomapConfig.with_overrides(CONFIG))
    for x in decoded(items):
        (m.step if isinstance(x, Odometry) else m.observe)(x)
    links = m.cmap.links
    src, dst, _, info = g.edges()
    np.testing.assert_allclose(
        _rows(src, dst, info[:, [0, 3, 5]]),
        _rows(links["source"], links["target"], link_information(m.cmap)),
        rtol=1e-12,
    )
    assert not np.all(info[:, [0, 3, 5]] == 1.0)


def test_data_zip_re_runs_offline_to_the_sessions_map(server, recorded, tmp_path):
    sid, items = recorded
    with server.client() as c:
        session_map = c.map(sid)
        path = c.export_data_zip(sid, tmp_path / "data.zip")
    folder = _unzip(path, tmp_path, sid)
    assert json.loads((folder / "config.json").read_text()) == CONFIG
    ds = read_folder_dataset(folder)
    assert [e.t for e in ds.events()] == [it[1].t if it[0] == "odometry" else it[1] for it in items]
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "hippomap",
            "run",
            str(folder),
            "--out",
            str(out),
            "--config",
            str(folder / "config.json"),
            "--quiet",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    _assert_same_map(json.loads((out / "map.json").read_text()), session_map, atol=1e-9)
    t, _ = read_tum(out / "groundtruth.tum")
    assert len(t) == sum(it[0] == "odometry" for it in items)


def test_rosbag2_zip_reads_back_as_the_sessions_inputs(server, recorded, tmp_path):
    sid, items = recorded
    with server.client() as c:
        session_map = c.map(sid)
        path = c.export_rosbag2_zip(sid, tmp_path / "bag.zip")
    bag = _unzip(path, tmp_path, sid)
    assert (bag / "metadata.yaml").is_file()
    ds = open_dataset(bag, IMAGE_TOPIC, ODOM_TOPIC, GROUNDTRUTH_TOPIC)
    readings = [it[1] for it in items if it[0] == "odometry"]
    frames = [it for it in items if it[0] == "frame"]
    np.testing.assert_allclose([o.t for o in ds.odometry], [o.t for o in readings], rtol=0, atol=1e-9)
    np.testing.assert_allclose([o.increment for o in ds.odometry], increments(readings), rtol=0, atol=1e-12)
    assert len(ds.frames) == len(frames)
    for got, sent in zip(ds.frames, frames):
        assert got.t == pytest.approx(sent[1], abs=1e-9)
        np.testing.assert_array_equal(got.image, decode_jpeg(sent[2]))
    np.testing.assert_allclose(ds.groundtruth[1], [o.gt for o in readings], atol=1e-12)
    from server.runtime import model

    m = _mapper_on(ds, CONFIG)
    graph = model.graph(m.answer(model.queries.GraphArrays()))
    _assert_same_map(json.loads(json.dumps(model.json_safe(graph))), session_map, atol=1e-6)


def test_exports_refuse_what_they_cannot_write(server):
    from hippomap.client import ServerError

    with server.client() as c:
        empty = c.create_session("empty", CONFIG)["id"]
        for fn in (c.export_data_zip, c.export_rosbag2_zip):
            with pytest.raises(ServerError) as e:
                fn(empty, Path(server.data_dir) / "never.zip")
            assert e.value.status == 409 and "no odometry to export" in str(e.value.detail)
            assert not (Path(server.data_dir) / "never.zip").exists()
            with pytest.raises(ServerError) as e:
                fn("s_0000000000000000", Path(server.data_dir) / "never.zip")
            assert e.value.status == 404


def test_a_link_error_is_split_along_and_beside_the_view_of_the_node_it_names():
    """Ground truth puts node ``to`` 1 m further ahead and 0.5 m further left, in the frame the link gives it,
    and turned 0.1 rad further: ``link_error_along_m`` +1, ``link_error_beside_m`` +0.5, 0.1 rad; the same
    pair seen in any frame of the world (both true poses moved by one rigid motion) gives the same parts."""
    claim = (2.0, 1.0, 0.0)  # where the link says node ``to`` lies in the frame of node ``from``
    t = np.array([0.0, 1.0])

    def errors(world):
        gt = compose(np.asarray(world, dtype=float), np.array([[0.0, 0.0, 0.0], [3.0, 1.5, 0.1]]))
        return link_error((t, gt), 0.0, 1.0, claim)

    e = errors((0.0, 0.0, 0.0))
    assert e["link_error_along_m"] == pytest.approx(1.0) and e["link_error_beside_m"] == pytest.approx(0.5)
    assert e["link_error_m"] == pytest.approx(math.hypot(1.0, 0.5)) and e["link_error_rad"] == pytest.approx(0.1)
    assert errors((-4.0, 7.0, 2.5)) == pytest.approx(e)
    assert link_error((t, np.zeros((2, 3))), 0.0, 5.0, claim) == {}  # ground truth has no pose at t = 5


@settings(max_examples=40, deadline=None)
@given(
    st.tuples(*(st.floats(-5, 5),) * 2, st.floats(-3, 3)),
    st.tuples(*(st.floats(-5, 5),) * 2, st.floats(-3, 3)),
)
def test_a_link_error_has_its_position_error_as_the_length_of_its_two_parts(claim, truth):
    """Whatever the claim and the truth, the along and beside parts are the position error's two components:
    their length is ``link_error_m``, and a claim equal to the truth has no error."""
    t = np.array([0.0, 1.0])
    gt = np.array([[0.0, 0.0, 0.0], truth])
    e = link_error((t, gt), 0.0, 1.0, claim)
    assert math.hypot(e["link_error_along_m"], e["link_error_beside_m"]) == pytest.approx(e["link_error_m"], abs=1e-9)
    exact = link_error((t, gt), 0.0, 1.0, truth)
    assert max(abs(exact["link_error_along_m"]), abs(exact["link_error_beside_m"]), exact["link_error_rad"]) < 1e-9
