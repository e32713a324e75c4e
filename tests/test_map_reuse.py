"""Map reuse: a second run started in a saved map, from an unknown pose, is placed by
recognition through the loop-closure path and lands in the first run's frame; localisation
mode leaves the map exactly as it was; the offline ``--base-map`` option and the service's
based sessions and merge do the same end to end.

The world is the 8 m x 5 m simulated corridor loop. Run 1 drives 400 steps (80 s, 32 m) of its
default route from (4, 0) and ends at (8, 2.5); run 2 starts at (0, 5) heading down the left-hand
side, a pose the mapper is not told. In this scenario run 2 is placed after 5 key frames with a
recognition attempt (6 when localising) and its map trajectory is 0.29 m (0.30 m) RMSE from the
ground truth in run 1's frame after placement; run 1's own is 0.12 m (``python
tests/test_map_reuse.py`` prints these). A throwaway sweep of the
same scenario over three start points x two seeds gave 3-7 key frames and 0.12-0.49 m, so the
tests bound them by 8 key frames and 0.75 m.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hippomap import sim
from hippomap.cognitive_map import CognitiveMap
from hippomap.errors import InputError
from hippomap.geometry import compose
from hippomap.inputs import Frame, Odometry
from hippomap.map_reuse import ReuseMap
from hippomap.mapper import Mapper

RELOCALISE_KEYFRAMES = 8  # key frames with a recognition attempt before the run is placed (measured 3-7)
ATE_M = 0.75  # RMSE of run 2's map trajectory after placement, in run 1's ground-truth frame (measured 0.12-0.49)
NOISE = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)
RUN1_STEPS, RUN2_STEPS = 400, 250


def sim_inputs(run: sim.SimRun, n: int) -> list[Odometry | Frame]:
    """Odometry and a frame at each of the first ``n`` steps, in time order."""
    out: list[Odometry | Frame] = []
    for i in range(min(n, len(run))):
        t, v, w = run.odometry[i]
        out.append(Odometry(float(t), v=float(v), omega=float(w)))
        out.append(Frame(float(t), run.frame(i)))
    return out


def feed(m: Mapper, items) -> list[dict]:
    events: list[dict] = []
    for item in items:
        events.extend(e.to_dict() for e in (m.step(item) if isinstance(item, Odometry) else m.observe(item)))
    return events


def align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The SE(2) pose that best maps points ``a`` (N, 2) onto ``b`` (least squares)."""
    ca, cb = a.mean(0), b.mean(0)
    A, B = a - ca, b - cb
    phi = math.atan2(float((A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]).sum()), float((A * B).sum()))
    c, s = math.cos(phi), math.sin(phi)
    t = cb - np.array([c * ca[0] - s * ca[1], s * ca[0] + c * ca[1]])
    return np.array([t[0], t[1], phi])


@pytest.fixture(scope="module")
def world():
    return sim.loop_world(seed=3, size=(8.0, 5.0))


@pytest.fixture(scope="module")
def run1(world):
    return sim.simulate(world, None, rate_hz=5.0, seed=1, odometry_noise=NOISE)


@pytest.fixture(scope="module")
def run2(world):
    plan = sim.RoutePlan(((0.0, 5.0), (0.0, 0.0), (8.0, 0.0), (8.0, 5.0)), closed=True, laps=1, seed=2)
    return sim.simulate(world, plan, rate_hz=5.0, seed=2, odometry_noise=NOISE)


@pytest.fixture(scope="module")
def run2_inputs(run2):
    return sim_inputs(run2, RUN2_STEPS)


@pytest.fixture(scope="module")
def base(run1):
    """Run 1's mapper, its snapshot, and the pose that takes its map frame to the ground truth's."""
    m = Mapper()
    feed(m, sim_inputs(run1, RUN1_STEPS))
    to_gt = align(m.corrected_trajectory()[:, :2], run1.groundtruth[:RUN1_STEPS, :2])
    return m, m.to_bytes(), to_gt


def run_second(snapshot: bytes, items, overrides=None) -> tuple[Mapper, int | None, int | None]:
    """Run 2 in the saved map: the mapper, the number of key frames with a recognition attempt
    until the run was placed, and the trajectory step from which it was placed."""
    m = Mapper.from_base(snapshot, overrides)
    assert m.lost
    keyframes, placed, step = 0, None, None
    for item in items:
        events = m.step(item) if isinstance(item, Odometry) else m.observe(item)
        keyframes += any(e.type == "recognition" for e in events)
        if placed is None and not m.lost:
            placed, step = keyframes, len(m.trajectory_times)
    return m, placed, step


def ate_in_run1_frame(m: Mapper, to_gt: np.ndarray, run2: sim.SimRun, start: int) -> float:
    traj = compose(to_gt, m.corrected_trajectory())[start:]
    gt = run2.groundtruth[start : len(m.trajectory_times)]
    return float(np.sqrt(np.mean(np.sum((traj[:, :2] - gt[:, :2]) ** 2, axis=1))))


# --------------------------------------------------------------------------- the model
def test_second_run_is_placed_in_the_first_runs_frame(base, run2, run2_inputs):
    m1, snap, to_gt = base
    m, placed, step = run_second(snap, run2_inputs)
    assert placed is not None and placed <= RELOCALISE_KEYFRAMES, placed
    assert ate_in_run1_frame(m, to_gt, run2, step) < ATE_M
    # ...the whole run, the part before the placement included: its nodes moved with it
    assert ate_in_run1_frame(m, to_gt, run2, 0) < ATE_M
    # the run's start is not the base's last pose: run 2 really began elsewhere
    assert np.hypot(*(run2.groundtruth[0, :2] - compose(to_gt, m1.corrected_trajectory()[-1])[:2])) > 3.0
    # the first acceptance needed the agreement of loop_min_support hypotheses, and no gate
    accepted = [d for d in m.cmap.loop_decisions if d.status == "accepted"]
    placing = [d for d in accepted if d.decided_step == min(a.decided_step for a in accepted)]
    assert all(math.isnan(d.gate_limit) for d in placing)
    assert any("no gate" in d.reason and len(d.support) >= m.config.map.loop_min_support - 1 for d in placing)
    # the saved map is kept and extended: its key frames, and new nodes linked to it
    s = m.stats()
    assert s["base_nodes"] == m1.stats()["nodes"] and s["nodes"] > s["base_nodes"]
    assert s["keyframes"] > m1.stats()["keyframes"]
    links = m.cmap.links
    joins = (links["kind"] == "loop") & (links["source"] >= s["base_nodes"]) & (links["target"] < s["base_nodes"])
    assert joins.any()
    # the base itself is untouched
    assert m1.to_bytes() == snap


def test_localisation_only_relocalises_and_leaves_the_map_unchanged(base, run2, run2_inputs):
    m1, snap, to_gt = base
    m, placed, step = run_second(snap, run2_inputs, {"mapper": {"mode": "localise"}})
    assert placed is not None and placed <= RELOCALISE_KEYFRAMES
    assert ate_in_run1_frame(m, to_gt, run2, step) < ATE_M
    before = m1.cmap
    assert m.cmap.node_count == before.node_count and m.cmap.link_count == before.link_count
    np.testing.assert_array_equal(m.cmap.poses, before.poses)
    np.testing.assert_array_equal(m.cmap.frames, before.frames)
    assert m.memory.frame_count == m1.memory.frame_count
    accepted = [d for d in m.cmap.loop_decisions if d.status == "accepted"]
    assert len(accepted) >= 3 and all(d.link == -1 and "localisation only" in d.reason for d in accepted)
    assert m.stats()["mode"] == "localise"


def test_snapshot_while_lost_restores_and_continues_identically(base, run2_inputs):
    _, snap, _ = base
    whole, _, _ = run_second(snap, run2_inputs[:120])
    half = Mapper.from_base(snap)
    feed(half, run2_inputs[:21])
    assert half.lost
    restored = Mapper.from_bytes(half.to_bytes())
    assert restored.lost
    feed(restored, run2_inputs[21:120])
    assert restored.to_bytes() == whole.to_bytes()


def test_a_run_in_another_world_stays_lost_and_apart(base):
    """No overlap: nothing is recognised as the saved map, the run's nodes stay unlinked to it."""
    _, snap, _ = base
    other = sim.simulate(sim.corridor_world(seed=11, length=12.0), rate_hz=5.0, seed=4, odometry_noise=NOISE)
    m, placed, _ = run_second(snap, sim_inputs(other, 150))
    assert placed is None and m.lost
    assert len(m.recognitions) > 10  # it kept trying, against every saved key frame
    links = m.cmap.links
    n0 = m.stats()["base_nodes"]
    assert not np.any((links["source"] >= n0) & (links["target"] < n0))
    assert m.stats()["nodes"] > n0 + 5  # it went on mapping its own nodes
    with pytest.raises(InputError, match="never placed"):  # floating nodes: no base for another run
        Mapper.from_base(m)


def test_from_base_refuses_bad_input(base):
    _, snap, _ = base
    with pytest.raises(InputError, match="not a hippomap mapper snapshot"):
        Mapper.from_base(b"not a snapshot")
    with pytest.raises(InputError, match="visual config"):
        Mapper.from_base(snap, {"visual": {"n_fixations": 12}})
    with pytest.raises(InputError, match="mode"):
        Mapper.from_base(snap, {"mapper": {"mode": "explore"}})
    with pytest.raises(InputError, match="unknown config section"):
        Mapper.from_base(snap, {"maps": {}})
    with pytest.raises(InputError, match="snapshot"):
        Mapper.from_base(12)  # type: ignore[arg-type]


def test_command_line_base_map(base, run2, tmp_path, capsys):
    from hippomap.cli import main

    m1, snap, _ = base
    (tmp_path / "base.npz").write_bytes(snap)
    n = 160
    sub = sim.simulate(
        run2.world, sim.Trajectory(run2.times[:n], run2.groundtruth[:n]), rate_hz=5.0, seed=2, odometry_noise=NOISE
    )
    sub.write(tmp_path / "run2")
    (tmp_path / "loc.json").write_text(json.dumps({"mapper": {"mode": "localise"}}))
    assert (
        main(
            [
                "run",
                str(tmp_path / "run2"),
                "--out",
                str(tmp_path / "out"),
                "--quiet",
                "--base-map",
                str(tmp_path / "base.npz"),
                "--config",
                str(tmp_path / "loc.json"),
            ]
        )
        == 0
    )
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["stats"]["nodes"] == m1.stats()["nodes"] and metrics["stats"]["lost"] is False
    assert metrics["stats"]["mode"] == "localise" and metrics["stats"]["loop_closures_accepted"] >= 3
    # the saved map's nodes were made in run 1: run 2's ground truth says nothing about their places
    rows = json.loads((tmp_path / "out" / "loop_closures.json").read_text())
    assert rows and not any("groundtruth_distance_m" in r for r in rows)
    assert metrics["loop_closures"].get("accepted_false", 0) == 0
    assert (
        main(
            [
                "run",
                str(tmp_path / "run2"),
                "--out",
                str(tmp_path / "o2"),
                "--quiet",
                "--base-map",
                str(tmp_path / "none"),
            ]
        )
        == 2
    )
    assert "cannot read base map" in capsys.readouterr().err


# --------------------------------------------------------------------------- the service
def jpeg_items(run: sim.SimRun, n: int) -> tuple:
    """The run's first ``n`` steps as the service takes them: odometry, and a JPEG frame at each step."""
    import cv2

    out: list[tuple] = []
    for i in range(min(n, len(run))):
        t, v, w = run.odometry[i]
        out.append(("odometry", Odometry(float(t), v=float(v), omega=float(w))))
        ok, buf = cv2.imencode(".jpg", run.frame(i), [cv2.IMWRITE_JPEG_QUALITY, 90])
        out.append(("frame", float(t), buf.tobytes()))
    return tuple(out)


def tum_xy(text: str) -> tuple[np.ndarray, np.ndarray]:
    rows = np.array(
        [
            [float(v) for v in line.split()[:3]]
            for line in text.splitlines()
            if line.strip() and not line.startswith("#")
        ]
    )
    return rows[:, 0], rows[:, 1:3]


def placed_after(client, sid: str) -> float:
    """When the run was placed: the first group of loop closures accepted together (they share the
    map step of the decision) was decided at the proposal of its newest member."""
    rows = client.loop_closures(sid, status="accepted")
    first = min(r["decision"]["decided_step"] for r in rows)
    return max(r["t"] for r in rows if r["decision"]["decided_step"] == first)


def ate_from(client, sid: str, run: sim.SimRun, to_gt: np.ndarray, t0: float) -> float:
    t, xy = tum_xy(client.trajectory_tum(sid))
    keep = t >= t0
    pts = compose(to_gt, np.column_stack([xy, np.zeros(len(xy))]))[keep, :2]
    gt = run.groundtruth[np.searchsorted(run.times, t[keep] - 1e-9)][:, :2]
    return float(np.sqrt(np.mean(np.sum((pts - gt) ** 2, axis=1))))


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    from tests.support.live import LiveServer

    srv = LiveServer(tmp_path_factory.mktemp("reuse")).start()
    yield srv
    srv.stop()


def test_service_reuse_end_to_end(service, run1, run2):
    """Base session by streaming run 1; a session from it streams run 2 and lands in run 1's frame;
    a localisation session leaves the map as it was; a plain session of run 2 merged into the
    base's map does the same through replay; the base never changes; a restart restores it all."""
    import asyncio

    from tests.support.live import stream_items

    client = service.client()
    base = client.create_session("run 1")["id"]
    asyncio.run(stream_items(service.url, service.token, base, jpeg_items(run1, RUN1_STEPS)))
    client.wait_processed(base)
    t1, xy1 = tum_xy(client.trajectory_tum(base))
    to_gt = align(xy1, run1.groundtruth[np.searchsorted(run1.times, t1 - 1e-9), :2])
    base_map = client.map(base)
    n_base = len(base_map["nodes"])

    items2 = jpeg_items(run2, RUN2_STEPS)
    reused = client._json("POST", "/sessions", {"name": "run 2", "base_session": base})
    assert reused["stats"]["mapper"]["lost"] is True and reused["stats"]["mapper"]["base_nodes"] == n_base
    localise = client._json(
        "POST",
        "/sessions",
        {"name": "run 2, localising", "base_session": base, "config": {"mapper": {"mode": "localise"}}},
    )
    assert localise["config"]["mapper"]["mode"] == "localise"
    plain = client.create_session("run 2 alone")["id"]

    async def streams():
        await asyncio.gather(
            *(stream_items(service.url, service.token, sid, items2) for sid in (reused["id"], localise["id"], plain))
        )

    asyncio.run(streams())
    for sid in (reused["id"], localise["id"], plain):
        client.wait_processed(sid)

    # started from the saved map: placed by recognition, in run 1's frame, the map grown from the base's
    st = client.stats(reused["id"])["mapper"]
    assert st["lost"] is False and st["nodes"] > n_base
    assert ate_from(client, reused["id"], run2, to_gt, placed_after(client, reused["id"])) < ATE_M
    # localisation only: placed, and the map exactly the base's
    st = client.stats(localise["id"])["mapper"]
    assert st["lost"] is False and st["mode"] == "localise"
    assert client.map(localise["id"]) == base_map
    assert ate_from(client, localise["id"], run2, to_gt, placed_after(client, localise["id"])) < ATE_M

    # merge: the plain run 2 session into the base's map, as a new session replaying run 2's inputs
    merged = client._json("POST", f"/sessions/{base}/merge", {"from": plain, "name": "run 1 + run 2"})
    client.wait_processed(merged["id"])
    assert [(r["seq"], r["kind"], r["t"]) for r in client.all_inputs(merged["id"])] == [
        (r["seq"], r["kind"], r["t"]) for r in client.all_inputs(plain)
    ]
    st = client.stats(merged["id"])["mapper"]
    assert st["lost"] is False and st["base_nodes"] == n_base and st["nodes"] > n_base
    assert ate_from(client, merged["id"], run2, to_gt, placed_after(client, merged["id"])) < ATE_M
    # the same run through the base or through a merge: the same session state
    assert client.map(merged["id"]) == client.map(reused["id"])

    # the base is copied, never changed; its snapshot is the saved map of `hippomap run --base-map`
    assert client.map(base) == base_map
    snap = client._req("GET", f"/sessions/{base}/snapshot").content
    assert Mapper.from_bytes(snap).stats()["nodes"] == n_base

    # a restart restores the based, localising and merged sessions (initial snapshot + replay)
    before = {sid: client.trajectory_tum(sid) for sid in (reused["id"], localise["id"], merged["id"])}
    service.stop()
    service.start()
    client = service.client()
    for sid, tum in before.items():
        client.wait_processed(sid)
        assert client.trajectory_tum(sid) == tum


def test_service_reuse_refuses_bad_requests(service):
    from hippomap.client import ServerError

    client = service.client()
    sid = client.create_session("small")["id"]
    client.send_odometry(sid, [Odometry(0.1, v=0.1, omega=0.0), Odometry(0.2, v=0.1, omega=0.0)])
    client.wait_processed(sid)

    def status(method: str, path: str, body: dict, c=client) -> tuple[int, str]:
        with pytest.raises(ServerError) as exc:
            c._json(method, path, body)
        return exc.value.status, str(exc.value.detail)

    assert status("POST", "/sessions", {"base_session": "s_0000000000000000"}) == (
        404,
        "base_session session 's_0000000000000000' not found",
    )
    code, detail = status("POST", "/sessions", {"base_session": sid, "config": {"visual": {"n_fixations": 12}}})
    assert code == 422 and "visual config" in detail
    code, detail = status("POST", "/sessions", {"base_session": sid, "config": {"mapper": {"mode": "explore"}}})
    assert code == 422 and "mode" in detail
    assert status("POST", f"/sessions/{sid}/merge", {"from": sid})[0] == 422
    assert status("POST", f"/sessions/{sid}/merge", {"from": "s_0000000000000000"})[0] == 404
    assert status("POST", f"/sessions/{sid}/merge", {})[0] == 422  # 'from' is required
    # another writer cannot see the session, so cannot start from it or merge it; a viewer cannot create
    writer = service.client(client.create_token("writer")["token"])
    assert status("POST", "/sessions", {"base_session": sid}, writer)[0] == 404
    other = writer.create_session("other")["id"]
    assert status("POST", f"/sessions/{other}/merge", {"from": sid}, writer)[0] == 404
    viewer = service.client(client.create_token("viewer")["token"])
    assert status("POST", "/sessions", {"base_session": sid}, viewer)[0] == 403
    # a based session whose run was never placed (nothing to recognise here) cannot be a base in turn
    lost = client._json("POST", "/sessions", {"base_session": sid})["id"]
    client.send_odometry(lost, [Odometry(0.1, v=0.1, omega=0.0), Odometry(0.2, v=0.1, omega=0.0)])
    assert client.wait_processed(lost)["mapper"]["lost"] is True
    code, detail = status("POST", "/sessions", {"base_session": lost})
    assert code == 409 and "never placed" in detail
    assert status("POST", f"/sessions/{lost}/merge", {"from": sid})[0] == 409


def test_a_runs_start_node_takes_the_time_of_its_first_valid_update():
    """The first node is made with the map, before any time is known; on a robot's clock (Unix
    seconds) it must take the first update's time, or everything measured from it (the pace of the
    drift allowance, a closure's ground truth, the exported map) would start in 1970. An update
    with a bad time changes nothing; a later run's start node takes its own first time."""
    t0 = 1_235_603_336.2
    for cls in (CognitiveMap, ReuseMap):  # hippomap run-odometry's map, and the mapper's
        cmap = cls()
        with pytest.raises(InputError):
            cmap.update((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), math.nan)
        assert cmap.times[0] == 0.0  # untouched by the rejected update
        for k in range(40):
            cmap.update((0.1 * k, 0.0, 0.0), (0.1, 0.0, 0.0), t0 + 0.2 * k)
        times = np.asarray(cmap.times)
        assert times[0] == t0 and len(times) > 3
        assert np.all(np.diff(times) > 0) and times[-1] - t0 < 8.0
        restored = cls.from_state(cmap.cfg, cmap.state_dict())
        assert restored.times[0] == t0
    n = len(times)
    cmap.start_run((0.0, 0.0, 0.0))  # a new run: its own start node
    with pytest.raises(InputError):
        cmap.update((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), math.inf)
    assert cmap.times[n] == 0.0
    cmap.update((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), t0 + 100.0)
    assert cmap.times[0] == t0 and cmap.times[n] == t0 + 100.0


if __name__ == "__main__":  # the figures of the module doc: python tests/test_map_reuse.py
    _world = sim.loop_world(seed=3, size=(8.0, 5.0))
    _run1 = sim.simulate(_world, None, rate_hz=5.0, seed=1, odometry_noise=NOISE)
    _plan = sim.RoutePlan(((0.0, 5.0), (0.0, 0.0), (8.0, 0.0), (8.0, 5.0)), closed=True, laps=1, seed=2)
    _run2 = sim.simulate(_world, _plan, rate_hz=5.0, seed=2, odometry_noise=NOISE)
    _m1 = Mapper()
    feed(_m1, sim_inputs(_run1, RUN1_STEPS))
    _to_gt = align(_m1.corrected_trajectory()[:, :2], _run1.groundtruth[:RUN1_STEPS, :2])
    print(f"run 1: {_m1.stats()['nodes']} nodes, map ATE {ate_in_run1_frame(_m1, _to_gt, _run1, 0):.2f} m")
    _items = sim_inputs(_run2, RUN2_STEPS)
    for _mode in ("map", "localise"):
        _m, _placed, _step = run_second(_m1.to_bytes(), _items, {"mapper": {"mode": _mode}})
        print(
            f"run 2 ({_mode}): placed after {_placed} key frames (t = {_m.trajectory_times[_step - 1]:.1f} s), "
            f"ATE after placement {ate_in_run1_frame(_m, _to_gt, _run2, _step):.2f} m in run 1's frame, "
            f"{_m.stats()['nodes']} nodes"
        )
