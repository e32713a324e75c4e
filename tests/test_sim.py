"""Camera simulator (hippomap.sim): rendering geometry, texture distinctiveness,
odometry noise model, dataset-folder output and wall building around a path."""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap import sim
from hippomap.errors import InputError
from hippomap.geometry import integrate, wrap_angle
from hippomap.sim.world import World


@pytest.fixture(scope="module")
def loop():
    return sim.loop_world(seed=3)


@pytest.fixture(scope="module")
def loop_run(loop):
    return sim.simulate(loop, rate_hz=5.0, odometry_noise=sim.OdometryNoise())


def ncc(a, b, size=(64, 48)):
    a = cv2.resize(a, size, interpolation=cv2.INTER_AREA).astype(float).ravel()
    b = cv2.resize(b, size, interpolation=cv2.INTER_AREA).astype(float).ravel()
    a -= a.mean()
    b -= b.mean()
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


def flat_wall_world(d: float, wall_height: float = 2.5) -> World:
    """One long wall across the x axis at x = d, textured plain white."""
    tex = sim.TextureParams(wall_height_m=wall_height, texels_per_m=20)
    wall = np.array([[d, -60.0], [d, 60.0]])
    strip = np.full((tex.rows, 130 * 20), 255, np.uint8)
    return World.from_polylines([wall], texture=tex, strip=strip)


# --------------------------------------------------------------------------- rendering


@pytest.mark.parametrize("w,h", [(320, 240), (640, 480)])
def test_frame_shape_dtype_and_content(loop, loop_run, w, h):
    cam = sim.Camera(width=w, height=h)
    img = sim.render(loop, loop_run.groundtruth[10], cam)
    assert img.shape == (h, w) and img.dtype == np.uint8
    assert img.std() > 20  # not blank


def test_frames_offer_shi_tomasi_corners(loop, loop_run):
    """The visual memory fixates on Shi–Tomasi corners (spec §2): every frame along the
    route, even facing a wall at a corner, must offer at least N_f = 9 of them."""
    counts = []
    for p in loop_run.groundtruth[:: max(1, len(loop_run) // 40)]:
        c = cv2.goodFeaturesToTrack(sim.render(loop, p), 50, 0.01, 5)
        counts.append(0 if c is None else len(c))
    assert min(counts) >= 9, counts


@pytest.mark.parametrize("d", [5.0, 7.0, 10.0, 15.0])
def test_wall_ahead_projects_to_f_H_over_d(d):
    cam = sim.Camera()
    shade = sim.Shading(fog_floor=1.0, directional=0.0, floor_contrast=0.0)
    img = sim.render(flat_wall_world(d), (0.0, 0.0, 0.0), cam, shade)
    col = img[:, cam.width // 2].astype(int)
    wall_rows = np.flatnonzero(col == 255)
    expected = cam.focal_px * 2.5 / d
    assert abs(len(wall_rows) - expected) <= 1.5
    assert np.all(np.diff(wall_rows) == 1)  # one contiguous band
    # the bottom edge sits mount height below the horizon: cy + f h / d
    assert wall_rows[-1] + 1 == pytest.approx(cam.cy + cam.focal_px * cam.mount_height_m / d, abs=1.0)
    # same at 640x480 with a different field of view: scales with f
    cam2 = sim.Camera(width=640, height=480, hfov_deg=75)
    col2 = sim.render(flat_wall_world(d), (0.0, 0.0, 0.0), cam2, shade)[:, 320]
    assert abs((col2 == 255).sum() - cam2.focal_px * 2.5 / d) <= 1.5


def test_a_swinging_light_brightens_walls_facing_it_and_darkens_the_others():
    """``Shading.light_swing_deg``: at time t the light comes from light_deg + swing sin(2 pi t / period), and a
    wall's brightness is (1 - directional) + directional (1 + cos(angle to the light)) / 2: a white wall seen
    head-on (normal along -x) is as bright as that formula says at each time, on a run's frames too; a wall
    facing the other way changes the other way; no swing is the fixed light, bit for bit."""
    d, cam = 6.0, sim.Camera()
    shade = sim.Shading(fog_floor=1.0, directional=0.6, floor_contrast=0.0, light_deg=0.0, light_swing_deg=90.0)
    assert sim.Shading(light_swing_deg=0.0).at(12.3) == sim.Shading()
    period = shade.light_period_s

    def wall_level(pose, t):
        img = sim.render(flat_wall_world(d), pose, cam, shade.at(t))
        return float(np.median(img[int(cam.cy) - 5, 100:220]))

    times = ((0.0, 0.0), (period / 4, 90.0), (period / 2, 0.0), (3 * period / 4, -90.0), (period / 8, 90 * 0.5**0.5))
    for t, light in times:
        assert shade.at(t).light_deg == pytest.approx(light)
        facing = 0.4 + 0.6 * (0.5 + 0.5 * -np.cos(np.radians(light)))  # normal (-1, 0) seen from x < d
        assert wall_level((0.0, 0.0, 0.0), t) == pytest.approx(255 * facing, abs=1.0)
    # seen from behind (the camera at 2 d looking back), the same wall darkens as the light turns away from it
    back = [wall_level((2 * d, 0.0, np.pi), t) for t in (0.0, period / 8, period / 4)]
    front = [wall_level((0.0, 0.0, 0.0), t) for t in (0.0, period / 8, period / 4)]
    assert back[0] > back[1] > back[2] and front[0] < front[1] < front[2]
    # a run renders each frame under the light of its time
    traj = sim.Trajectory(np.array([0.0, period / 4]), np.zeros((2, 3)))
    run = sim.simulate(flat_wall_world(d), traj, shading=shade, odometry_noise=sim.OdometryNoise())
    assert [float(np.median(run.frame(i)[int(cam.cy) - 5, 100:220])) for i in (0, 1)] == pytest.approx(
        [wall_level((0.0, 0.0, 0.0), 0.0), wall_level((0.0, 0.0, 0.0), period / 4)]
    )
    with pytest.raises(InputError, match="light_swing_deg"):
        sim.Shading(light_swing_deg=-5.0)
    with pytest.raises(InputError, match="light_period_s"):
        sim.Shading(light_swing_deg=10.0, light_period_s=0.0)


def test_wall_seen_at_an_angle_has_perpendicular_depth():
    """Camera turned 20° from a wall at x = d: each column's ray (forward component 1 in
    the camera frame) meets the wall at the analytic parameter t = d / dx."""
    d, yaw = 6.0, np.radians(20.0)
    cam = sim.Camera()
    hits = sim.raycast(flat_wall_world(d), (0.0, 0.0, yaw), cam)
    # column ray direction (forward component 1 in the camera frame) -> wall x = d
    k = -(np.arange(cam.width) + 0.5 - cam.cx) / cam.focal_px
    dx = np.cos(yaw) - k * np.sin(yaw)
    np.testing.assert_allclose(hits.depth, d / dx, rtol=1e-9)


def test_same_pose_same_image_and_seeded_worlds(loop, loop_run):
    p = loop_run.groundtruth[77]
    a = sim.render(loop, p)
    assert np.array_equal(a, sim.render(loop, p))
    assert np.array_equal(a, sim.render(sim.loop_world(seed=3), p))
    assert not np.array_equal(a, sim.render(sim.loop_world(seed=4), p))


def test_exposure_change_scales_frames_by_the_light_of_their_time(loop, loop_run):
    """``Camera.exposure_change``: each frame is the constant-light frame of the same pose with its grey
    levels scaled by 1 + A sin(2 pi t / period) (rounded, clipped at white), so the same place looks
    brighter or darker at other times; A = 0 renders the constant-light frames bit for bit; an
    amplitude of 1 or more (black or negative light) and a period that is not positive are named."""
    traj = sim.Trajectory(np.array([0.0, 24.25, 72.75]), np.tile(loop_run.groundtruth[77], (3, 1)))  # one pose
    still = sim.simulate(loop, traj, odometry_noise=sim.OdometryNoise())
    cam = sim.Camera(exposure_change=0.3, exposure_period_s=97.0)
    lit = sim.simulate(loop, traj, camera=cam, odometry_noise=sim.OdometryNoise())
    base = still.frame(0)
    assert all(np.array_equal(base, still.frame(i)) for i in (1, 2))
    assert np.array_equal(base, sim.simulate(loop, traj, camera=sim.Camera(exposure_change=0.0)).frame(0))
    gains = [1.0, 1.3, 0.7]  # sin(0), sin(pi / 2), sin(3 pi / 2)
    for i, g in enumerate(gains):
        assert cam.exposure_gain(float(traj.times[i])) == pytest.approx(g)
        img = lit.frame(i).astype(float)
        expect = np.clip(base.astype(float) * g, 0, 255)  # base is already rounded: within a grey level
        assert np.abs(img - expect).max() <= 1.0 + 0.5 * g
    assert lit.frame(1).mean() > base.mean() * 1.2 and lit.frame(2).mean() < base.mean() * 0.75
    with pytest.raises(InputError, match="exposure_change"):
        sim.Camera(exposure_change=1.0)
    with pytest.raises(InputError, match="exposure_change"):
        sim.Camera(exposure_change=-0.1)
    with pytest.raises(InputError, match="exposure_period_s"):
        sim.Camera(exposure_change=0.2, exposure_period_s=0.0)
    with pytest.raises(InputError, match="gain"):
        sim.render(loop, loop_run.groundtruth[77], gain=float("nan"))


def test_revisits_look_alike_distant_places_differ(loop, loop_run):
    gt = loop_run.groundtruth
    lap = len(gt) // 3
    rng = np.random.default_rng(1)
    rev, far = [], []
    for i in rng.integers(0, lap - 50, 24):
        later = gt[lap + 50 :]
        cost = np.hypot(*(later[:, :2] - gt[i, :2]).T) + 2 * np.abs(wrap_angle(later[:, 2] - gt[i, 2]))
        j = lap + 50 + int(np.argmin(cost))
        assert np.hypot(*(gt[j, :2] - gt[i, :2])) < 0.4  # the route really revisits
        distant = np.flatnonzero(np.hypot(*(gt[:, :2] - gt[i, :2]).T) > 6.0)
        k = int(distant[rng.integers(len(distant))])
        a = sim.render(loop, gt[i])
        rev.append(ncc(a, sim.render(loop, gt[j])))
        far.append(ncc(a, sim.render(loop, gt[k])))
    rev, far = np.array(rev), np.array(far)
    assert np.median(rev) > 0.6
    assert np.median(far) < 0.3
    assert (rev > far).mean() >= 0.85


def test_procedural_textures_do_not_repeat():
    tex = sim.TextureParams()
    strip = sim.procedural_strip(60.0, tex, seed=5).astype(float)
    w = int(2.0 * tex.texels_per_m)  # 2 m windows
    wins = [strip[:, s : s + w] for s in range(0, strip.shape[1] - w, w)]
    cors = []
    for i in range(len(wins)):
        for j in range(i + 1, len(wins)):
            a, b = wins[i] - wins[i].mean(), wins[j] - wins[j].mean()
            cors.append((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))
    assert max(cors) < 0.6
    assert np.array_equal(strip, sim.procedural_strip(60.0, tex, seed=5))
    assert not np.array_equal(strip, sim.procedural_strip(60.0, tex, seed=6))


def test_photo_textures_from_a_folder(tmp_path):
    rng = np.random.default_rng(0)
    for k in range(3):
        im = (rng.random((60, 80)) * 255).astype(np.uint8)
        cv2.imwrite(str(tmp_path / f"p{k}.png"), cv2.GaussianBlur(im, (5, 5), 0))
    world = sim.loop_world(seed=0, texture=sim.TextureParams(source=str(tmp_path)))
    run = sim.simulate(world, rate_hz=2.0, odometry_noise=sim.OdometryNoise())
    img = run.frame(5)
    assert img.shape == (240, 320) and img.std() > 10
    with pytest.raises(InputError, match="does not exist"):
        sim.loop_world(texture=sim.TextureParams(source=str(tmp_path / "missing")))


def test_photo_walls_can_use_fewer_photos_and_leave_them_bare(tmp_path):
    """``photo_count`` keeps the first photos of the folder (sorted by name) and ``photo_overlay=False`` draws
    no posters over them: a strip of a dark and a bright photo, cut to the dark one, holds only its grey levels
    (each crop re-exposed by at most x1.2 + 20), while the posters of the overlay and the second photo do not."""
    cv2.imwrite(str(tmp_path / "a.png"), np.full((60, 80), 40, np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.full((60, 80), 210, np.uint8))
    bare_one = sim.photo_strip(30.0, sim.TextureParams(source=str(tmp_path), photo_count=1, photo_overlay=False))
    assert bare_one.max() <= 40 * 1.2 + 20 + 1
    bare_both = sim.photo_strip(30.0, sim.TextureParams(source=str(tmp_path), photo_overlay=False))
    assert bare_both.max() >= 210 * 0.8 - 20 - 1 and bare_both.min() <= 40 * 1.2 + 20 + 1
    posters = sim.photo_strip(30.0, sim.TextureParams(source=str(tmp_path), photo_count=1))
    assert bare_one.shape == posters.shape and (posters > 40 * 1.2 + 20 + 1).mean() > 0.02
    with pytest.raises(InputError, match="photo_count"):
        sim.TextureParams(source=str(tmp_path), photo_count=0)


def test_command_line_photo_options_need_photo_walls(tmp_path, capsys):
    """``--photos N --photo-overlay 0`` render with the photo walls asked for and record them in ``sim.json``;
    on procedural walls either option is named as needing photos."""
    import json

    from hippomap.sim.cli import main

    cv2.imwrite(str(tmp_path / "a.png"), (np.random.default_rng(0).random((60, 80)) * 255).astype(np.uint8))
    out = tmp_path / "bare"
    args = ["loop", "--out", str(out), "--laps", "1", "--frame-every", "100", "--no-progress", "--texture"]
    assert main(args + [str(tmp_path), "--photos", "1", "--photo-overlay", "0"]) == 0
    texture = json.loads((out / "sim.json").read_text())["texture"]
    assert texture["photo_count"] == 1 and texture["photo_overlay"] is False and texture["source"] == str(tmp_path)
    capsys.readouterr()
    assert main(["loop", "--out", str(tmp_path / "p"), "--photos", "2"]) == 2
    assert "photo walls" in capsys.readouterr().err
    assert main(["loop", "--out", str(tmp_path / "p"), "--photo-overlay", "0"]) == 2
    assert "photo walls" in capsys.readouterr().err


def test_grid_raycast_equals_brute_force():
    rng = np.random.default_rng(2)
    a = rng.uniform(-40, 40, (300, 2))
    b = a + rng.normal(0, 3, (300, 2))
    world = World.from_polylines([np.stack([p, q]) for p, q in zip(a, b)], seed=1)
    assert world.grid is not None
    brute = World(world.name, world.segments, world.u0, world.atlas, world.texture)
    brute.grid = None
    cam = sim.Camera(near_range_m=5.0, max_range_m=60.0)
    for pose in np.column_stack([rng.uniform(-30, 30, (25, 2)), rng.uniform(-np.pi, np.pi, 25)]):
        g, f = sim.raycast(world, pose, cam), sim.raycast(brute, pose, cam)
        np.testing.assert_array_equal(g.segment, f.segment)
        np.testing.assert_allclose(g.depth, f.depth)


# --------------------------------------------------------------------------- odometry


def test_zero_noise_odometry_integrates_to_ground_truth(loop_run):
    run = loop_run
    np.testing.assert_allclose(integrate(run.increments, run.groundtruth[0]), run.groundtruth, atol=1e-9)
    # the (t, v, omega) rows, integrated as arcs, give the same path
    dt = np.diff(run.odometry[:, 0])
    inc = sim.arc_increments(run.odometry[1:, 1], run.odometry[1:, 2], dt)
    np.testing.assert_allclose(integrate(inc, run.groundtruth[0]), run.groundtruth, atol=1e-9)
    assert np.all(run.odometry[0, 1:] == 0)


def test_zero_noise_on_a_given_trajectory_is_exact():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.1, 0.3, 200))
    poses = integrate(np.column_stack([rng.uniform(0, 0.1, 199), rng.normal(0, 0.01, 199), rng.normal(0, 0.1, 199)]))
    run = sim.simulate(sim.loop_world(), sim.Trajectory(t, poses), odometry_noise=sim.OdometryNoise())
    np.testing.assert_allclose(integrate(run.increments, poses[0]), poses, atol=1e-9)
    np.testing.assert_array_equal(run.times, t)


def test_omega_bias_shows_up_as_heading_drift(loop):
    bias = 0.01
    clean = sim.simulate(loop, rate_hz=5.0, odometry_noise=sim.OdometryNoise())
    run = sim.simulate(loop, rate_hz=5.0, odometry_noise=sim.OdometryNoise(omega_bias=bias))
    est = integrate(run.increments, run.groundtruth[0])
    drift = np.unwrap(est[:, 2]) - np.unwrap(clean.groundtruth[:, 2])
    np.testing.assert_allclose(drift, bias * (run.times - run.times[0]), atol=1e-9)
    # and the position drifts too, more the longer the run
    err = np.hypot(*(est[:, :2] - clean.groundtruth[:, :2]).T)
    assert err[-1] > 1.0 > err[50]


@settings(max_examples=40, deadline=None)
@given(every=st.floats(0.3, 3.0), seconds=st.floats(0.2, 5.0), rate=st.sampled_from([2.0, 5.0, 10.0]))
def test_stops_hold_the_pose_for_their_seconds_at_each_mark_of_path(every, seconds, rate):
    """A run with stops is the same path, with the robot standing still (zero true velocities) for
    ``seconds`` (whole steps) each time another ``every`` metres have been driven; the clock keeps its step."""
    plan = sim.DrivePlan(((6.0, 0.5, 0.2), (4.0, 0.3, -0.4)))
    tr = plan.sample(rate)
    s = sim.with_stops(tr, every, seconds)
    n = max(1, int(round(seconds / float(np.median(np.diff(tr.times))))))  # whole steps, at least one
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(tr.poses[:, :2], axis=0).T))])
    marks = np.unique(np.searchsorted(path, np.arange(every, path[-1], every)))
    marks = marks[(marks > 0) & (marks < len(tr) - 1)]
    assert len(s) == len(tr) + n * len(marks)
    np.testing.assert_allclose(np.diff(s.times), 1.0 / rate, atol=1e-9)
    still = s.velocities[:, 0] == 0
    assert still.sum() == n * len(marks)
    # each stop is n steps at the pose of the first step at or past its mark; the path itself is unchanged
    starts = np.flatnonzero(np.diff(np.r_[False, still].astype(int)) == 1)
    assert [int(np.flatnonzero((s.poses == tr.poses[m]).all(axis=1))[0]) for m in marks] == starts.tolist()
    np.testing.assert_array_equal(s.poses[np.r_[True, ~still]], tr.poses)
    np.testing.assert_array_equal(s.velocities[~still], tr.velocities)


def test_a_gyro_bias_turns_the_odometry_while_the_robot_stands_still(loop):
    """Stops through :func:`simulate` (``stop_every_m``, ``stop_s``): the ground truth stands still and the
    odometry's heading drifts by the bias over each stop, as a real gyro's does."""
    bias = 0.01
    run = sim.simulate(
        loop, rate_hz=5.0, odometry_noise=sim.OdometryNoise(omega_bias=bias), stop_every_m=10.0, stop_s=20.0
    )
    still = (run.odometry[1:, 1] == 0) & (np.diff(run.groundtruth, axis=0) == 0).all(axis=1)
    assert still.sum() >= 100 * 3  # at least three stops of 100 steps on the loop's laps
    est = integrate(run.increments, run.groundtruth[0])
    turn = np.diff(np.unwrap(est[:, 2]))
    np.testing.assert_allclose(turn[still], bias * 0.2, atol=1e-12)
    with pytest.raises(InputError, match="stop_s"):
        sim.simulate(loop, stop_every_m=10.0)
    with pytest.raises(InputError, match="stop_every_m"):
        sim.simulate(loop, stop_every_m=-1.0, stop_s=5.0)


def test_odometry_noise_statistics_match_config(loop):
    noise = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.05, omega_bias=0.01, scale_error=0.1)
    clean = sim.simulate(loop, rate_hz=10.0, odometry_noise=sim.OdometryNoise())
    run = sim.simulate(loop, rate_hz=10.0, odometry_noise=noise, seed=4)
    v0, w0 = clean.odometry[1:, 1], clean.odometry[1:, 2]
    v, w = run.odometry[1:, 1], run.odometry[1:, 2]
    n = len(v)
    dw = w - w0
    assert abs(dw.mean() - 0.01) < 4 * 0.05 / np.sqrt(n)
    assert dw.std() == pytest.approx(0.05, rel=0.1)
    dv = v - 1.1 * v0
    assert abs(dv.mean()) < 4 * 0.02 / np.sqrt(n)
    assert dv.std() == pytest.approx(0.02, rel=0.1)
    # scale error: the noisy distance is 10 % longer
    assert np.sum(v) / np.sum(v0) == pytest.approx(1.1, rel=0.01)
    # deterministic per seed
    again = sim.simulate(loop, rate_hz=10.0, odometry_noise=noise, seed=4)
    np.testing.assert_array_equal(again.odometry, run.odometry)
    other = sim.simulate(loop, rate_hz=10.0, odometry_noise=noise, seed=5)
    assert not np.array_equal(other.odometry, run.odometry)


def test_omega_bias_walk_wanders_at_its_rate_and_leaves_the_other_noise_as_it_was(loop):
    base = sim.OdometryNoise(sigma_v=0.02, sigma_omega=0.01, omega_bias=0.01)
    walk = 0.002
    steady = sim.simulate(loop, rate_hz=10.0, odometry_noise=base, seed=4)
    wander = sim.simulate(loop, rate_hz=10.0, odometry_noise=replace(base, omega_bias_walk=walk), seed=4)
    # the same draws for speed and turn-rate noise: only the bias differs
    np.testing.assert_array_equal(wander.odometry[:, 1], steady.odometry[:, 1])
    b = wander.odometry[1:, 2] - steady.odometry[1:, 2]
    dt = np.diff(wander.times)
    steps = np.diff(b) / np.sqrt(dt[1:])
    assert abs(steps.mean()) < 4 * walk / np.sqrt(len(steps))
    assert steps.std() == pytest.approx(walk, rel=0.1)
    # a random walk, not white noise: the bias at the end is far from the start on the scale of one step
    assert np.abs(b).max() > 5 * walk * np.sqrt(dt.mean())
    with pytest.raises(InputError, match="omega_bias_walk"):
        sim.OdometryNoise(omega_bias_walk=-0.001)
    assert not sim.OdometryNoise(omega_bias_walk=0.001).is_zero


@settings(max_examples=200, deadline=None)
@given(
    v=st.floats(-2, 2),
    w=st.floats(-3, 3),
    dt=st.floats(0.01, 0.5),
)
def test_arc_velocity_round_trip(v, w, dt):
    inc = sim.arc_increments(v, w, dt)
    v2, w2 = sim.velocities_from_increments(inc, dt)
    np.testing.assert_allclose(sim.arc_increments(v2, w2, dt), inc, atol=1e-12)
    # the arc's chord length never exceeds the distance driven
    assert np.hypot(inc[0, 0], inc[0, 1]) <= abs(v) * dt + 1e-12


def test_drive_plan_circle_closes():
    w = 2 * np.pi / 20.0  # one turn in 20 s = 400 steps at 20 Hz
    plan = sim.DrivePlan([(20.0, 0.5, w)], start=(1.0, 2.0, 0.3))
    traj = plan.sample(20.0)
    assert len(traj) == 401
    np.testing.assert_allclose(traj.poses[-1], [1.0, 2.0, 0.3], atol=1e-9)
    radius = np.hypot(*(traj.poses[:, :2] - traj.poses[:-1, :2].mean(0)).T)
    np.testing.assert_allclose(radius, 0.5 / w, atol=1e-9)


def assert_walls_clear(world, poses, margin_m: float) -> None:
    """No wall of ``world`` within ``margin_m`` either side of the camera at ``poses`` (a thin ray-cast fan
    to the left and to the right)."""
    cam = sim.Camera(width=9, hfov_deg=2)
    for p in poses:
        for side in (np.pi / 2, -np.pi / 2):
            assert sim.raycast(world, (p[0], p[1], p[2] + side), cam).depth.min() > margin_m


def test_figure8_world_drives_round_both_blocks_and_through_its_junctions():
    """The figure8 world: ``laps`` figures of eight round two blocks; the shared middle corridor is driven
    twice a lap, northwards both times; the junction at its foot is left eastwards, northwards and westwards
    (three directions); walls never come within half a metre of the route's camera, either side."""
    bx, by = 10.0, 7.0
    world = sim.figure8_world(seed=2, block=(bx, by), laps=2)
    run = sim.simulate(world, rate_hz=2.0, odometry_noise=sim.OdometryNoise())
    gt = run.groundtruth
    assert gt[:, 0].min() == pytest.approx(0.0, abs=0.5) and gt[:, 0].max() == pytest.approx(2 * bx, abs=0.5)
    assert gt[:, 1].min() == pytest.approx(0.0, abs=0.5) and gt[:, 1].max() == pytest.approx(by, abs=0.5)
    length = float(np.hypot(*np.diff(gt[:, :2], axis=0).T).sum())
    assert length == pytest.approx(2 * (5 * bx + 4 * by), rel=0.05)  # a lap: the bottom of the left block 1.5 x
    middle = (np.abs(gt[:, 0] - bx) < 0.5) & (gt[:, 1] > 1.5) & (gt[:, 1] < by - 1.5)
    assert np.all(np.abs(wrap_angle(gt[middle, 2] - np.pi / 2)) < 0.5)  # northwards only
    passes = np.flatnonzero(np.diff(middle.astype(int)) == 1).size + int(middle[0])
    assert passes == 4  # twice a lap
    foot = np.hypot(gt[:, 0] - bx, gt[:, 1]) < 2.0
    leaving = gt[foot & (np.hypot(gt[:, 0] - bx, gt[:, 1]) > 1.5), 2]
    directions = {int(np.rint(wrap_angle(a) / (np.pi / 2))) % 4 for a in leaving}
    assert {0, 1, 2} <= directions
    assert_walls_clear(world, gt[::4], 0.5)
    frame = run.frame(run.n_frames // 3)
    assert frame.shape == (240, 320) and frame.std() > 10
    with pytest.raises(InputError, match="block"):
        sim.figure8_world(block=(2.0, 7.0))


def test_grid_world_is_a_random_walk_of_its_seed_along_the_grid_lines():
    """The grid world: a random walk over the junctions of a grid of blocks, its own for each seed; every leg
    runs along one grid line between neighbouring junctions, never straight back the way it came; the walk is
    ``laps`` times the grid's corridors long; the route driven keeps to the corridors (walls never within
    half a metre either side) and passes a four-way junction in more than two directions."""
    bx, by = 8.0, 6.0
    ways = [sim.grid_walk(seed, (2, 2), (bx, by), 84.0) for seed in range(6)]
    assert len({tuple(w) for w in ways}) == 6
    for way in ways:
        w = np.asarray(way)
        assert tuple(w[0]) == (bx / 2, 0.0) and tuple(w[1]) == (bx, 0.0)
        assert np.all(np.isin(w[1:, 0], [0.0, bx, 2 * bx])) and np.all(np.isin(w[1:, 1], [0.0, by, 2 * by]))
        leg = np.diff(w, axis=0)
        assert np.all((leg == 0).sum(axis=1) == 1)  # along x or along y
        assert np.all(np.isin(np.abs(leg).max(axis=1), [bx / 2, bx, by]))  # to a neighbouring junction
        assert np.all(np.any(w[2:] != w[:-2], axis=1))  # never straight back
        length = np.abs(leg).sum()
        assert 84.0 <= length < 84.0 + max(bx, by)
    world = sim.grid_world(seed=4, blocks=(2, 2), block=(bx, by), laps=1)
    run = sim.simulate(world, rate_hz=2.0, odometry_noise=sim.OdometryNoise())
    gt = run.groundtruth
    assert float(np.hypot(*np.diff(gt[:, :2], axis=0).T).sum()) == pytest.approx(84.0, rel=0.1)
    assert_walls_clear(world, gt[::4], 0.5)
    walk = sim.simulate(sim.grid_world(seed=4, block=(bx, by)), rate_hz=2.0, odometry_noise=sim.OdometryNoise())
    long = walk.groundtruth
    centre = np.hypot(long[:, 0] - bx, long[:, 1] - by)
    leaving = long[(centre > 1.5) & (centre < 2.0), 2]
    assert len({int(np.rint(wrap_angle(a) / (np.pi / 2))) % 4 for a in leaving}) >= 3
    for bad, match in (({"blocks": (0, 2)}, "blocks"), ({"block": (2.0, 6.0)}, "block"), ({"laps": 0}, "laps")):
        with pytest.raises(InputError, match=match):
            sim.grid_world(**bad)


def test_hall_world_is_an_open_room_of_pillars_driven_as_a_random_walk_of_its_seed():
    """The hall world: walls only round the hall and round one pillar per square of lanes; the route is
    the seed's random walk along the lanes, ``laps`` times the lanes long; it keeps a metre from every
    pillar and wall; and the view is open: looking along a lane the camera sees further than the
    corridor worlds' walls allow, and looking across it, the pillar beside the lane."""
    world = sim.hall_world(seed=3, laps=1)
    assert world.name == "hall"
    assert len(world.segments) == 4 * (1 + 3 * 2)  # the hall's four walls and four faces of each of six pillars
    run = sim.simulate(world, rate_hz=2.0, odometry_noise=sim.OdometryNoise())
    gt = run.groundtruth
    assert float(np.hypot(*np.diff(gt[:, :2], axis=0).T).sum()) == pytest.approx(85.0, rel=0.1)
    assert_walls_clear(world, gt[::4], 1.0)
    others = {tuple(np.round(sim.hall_world(seed=s, laps=1).route.path(1.0)[:12].ravel(), 3)) for s in range(4)}
    assert len(others) == 4  # each seed walks its own route
    cam = sim.Camera(width=9, hfov_deg=2)
    assert sim.raycast(world, (2.5, 0.0, 0.0), cam).depth.min() > 12.0  # along the bottom lane: the far wall
    beside = sim.raycast(world, (2.5, 0.0, np.pi / 2), cam).depth  # across it: the first pillar's face
    assert np.all(np.abs(beside - 1.75) < 0.05)
    for bad, match in (
        ({"lanes": (0, 2)}, "lanes"),
        ({"pillar": 4.5}, "pillar"),
        ({"margin": 0.2}, "margin"),
        ({"laps": 0}, "laps"),
    ):
        with pytest.raises(InputError, match=match):
            sim.hall_world(**bad)


def test_office_world_is_a_corridor_whose_route_visits_rooms_through_their_doors():
    """The office world: five rooms off a corridor, each with a desk; the route drives the corridor end to end
    ``passes`` times and on each pass goes round the desk of at least one room it passes, entering and leaving
    through the door; the seed picks the rooms; walls keep their distance from the camera; the rooms' sizes and
    the passes are checked."""
    world = sim.office_world(seed=4, passes=3)
    assert world.name == "office"
    run = sim.simulate(world, rate_hz=2.0, odometry_noise=sim.OdometryNoise())
    gt = run.groundtruth
    assert_walls_clear(world, gt[::3], 0.5)
    x, y = gt[:, 0], gt[:, 1]
    assert x.min() > -0.5 and x.max() > 27.0  # end to end along the corridor
    inside = np.abs(y) > 2.4  # beyond the doorways: in a room, past its desk's near side
    assert inside.any()
    # every stretch in a room goes round its desk: it reaches the far wall's side of the desk
    rooms = {(xc, side) for xc, side in sim.worlds.OFFICE_ROOMS}
    seen = {(xc, side) for xc, side in rooms if np.any((np.abs(x - xc) < 2.5) & (side * y > 5.0))}
    assert len(seen) >= 2  # seed 4 goes round the desks of several rooms over its three passes
    # into and out of a room only through its door: where the route crosses the corridor's wall line
    cross = np.flatnonzero(np.diff(np.sign(np.abs(y) - 1.2)) != 0)
    doors = np.array([xc for xc, _ in sim.worlds.OFFICE_ROOMS])
    assert np.all(np.min(np.abs(x[cross][:, None] - doors[None, :]), axis=1) < 0.7)
    routes = {tuple(np.round(sim.office_world(seed=s).route.path(1.0)[:60].ravel(), 3)) for s in range(5)}
    assert len(routes) > 1  # the seed chooses the rooms
    for bad, match in (
        ({"length": 20.0}, "length"),
        ({"room": (3.0, 5.0)}, "rooms"),
        ({"room": (11.0, 5.0)}, "rooms"),
        ({"door": 0.8}, "door"),
        ({"desk": (2.5, 1.0)}, "desk"),
        ({"passes": 0}, "passes"),
    ):
        with pytest.raises(InputError, match=match):
            sim.office_world(**bad)


# --------------------------------------------------------------------------- output


def test_write_produces_the_dataset_folder_format(tmp_path, loop):
    plan = sim.DrivePlan([(3.0, 0.4, 0.0), (2.0, 0.3, 0.4)], start=(8.0, 0.0, 0.0))
    run = sim.simulate(
        loop, plan, rate_hz=10.0, frame_every=3, odometry_noise=sim.OdometryNoise(sigma_omega=0.01), seed=2
    )
    out = run.write(tmp_path / "run")
    files = sorted((out / "frames").iterdir())
    assert len(files) == run.n_frames == len(range(0, len(run), 3))
    with (out / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["t", "file"]
    assert [Path(r["file"]).name for r in rows] == [f.name for f in files]
    np.testing.assert_allclose([float(r["t"]) for r in rows], run.frame_times, atol=1e-6)
    img = cv2.imread(str(out / rows[4]["file"]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320) and img.dtype == np.uint8
    assert np.array_equal(img, run.frame(4))
    with (out / "odometry.csv").open() as fh:
        odo = list(csv.DictReader(fh))
    assert list(odo[0]) == ["t", "v", "omega"] and len(odo) == len(run)
    np.testing.assert_allclose([[float(r[k]) for k in ("t", "v", "omega")] for r in odo], run.odometry, atol=1e-6)
    with (out / "groundtruth.csv").open() as fh:
        gt = list(csv.DictReader(fh))
    assert list(gt[0]) == ["t", "x", "y", "theta"] and len(gt) == len(run)
    np.testing.assert_allclose([[float(r[k]) for k in ("x", "y", "theta")] for r in gt], run.groundtruth, atol=1e-9)


def test_frames_iterator_is_lazy_and_matches_frame(loop_run):
    it = loop_run.frames()
    t0, f0 = next(it)
    t1, f1 = next(it)
    assert t0 == loop_run.frame_times[0] and t1 == loop_run.frame_times[1]
    assert np.array_equal(f1, loop_run.frame(1))
    with pytest.raises(InputError, match="out of range"):
        loop_run.frame(loop_run.n_frames)


# --------------------------------------------------------------------------- path worlds


def figure_eight(n=600):
    s = np.linspace(0, 2 * np.pi, n)
    xy = np.column_stack([12 * np.sin(s), 6 * np.sin(2 * s)])
    th = np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0]))
    return np.column_stack([xy, th])


def test_walls_around_a_self_crossing_path():
    path = figure_eight()
    # driven twice, the second time 0.3 m to the side (re-runs merge into one corridor)
    path2 = path.copy()
    path2[:, 1] += 0.3
    both = np.vstack([path, path2])
    hw, res, simp = 1.2, 0.1, 0.15
    polys = sim.walls_around_path(both[:, :2], half_width_m=hw, resolution_m=res, simplify_m=simp)
    world = World.from_polylines(polys)
    # the camera is never inside (or against) a wall anywhere on the path, the crossing included
    d = sim.point_segment_distance(both[:, :2], world.segments)
    assert d.min() >= hw - res - simp
    assert np.hypot(*both[np.argmin(np.hypot(*both[:, :2].T)), :2]) < 0.5  # the path does cross at the origin
    # ... and enclosed: every ray from the start pose meets a wall, none too close
    for yaw in np.linspace(-np.pi, np.pi, 8, endpoint=False):
        hits = sim.raycast(world, (both[0, 0], both[0, 1], yaw), sim.Camera())
        assert np.isfinite(hits.depth).all()
        assert (hits.depth * np.hypot(hits.dx, hits.dy)).min() >= hw - res - simp
    # walls hug the path: on a straight stretch the corridor is about 2 * hw + offset wide
    i = 75  # top of the right lobe (s = pi/4), heading along +x
    ray_up = sim.raycast(world, (path[i, 0], path[i, 1], np.pi / 2), sim.Camera(width=9, hfov_deg=2))
    ray_dn = sim.raycast(world, (path[i, 0], path[i, 1], -np.pi / 2), sim.Camera(width=9, hfov_deg=2))
    width = ray_up.depth[4] + ray_dn.depth[4]
    assert 2 * hw + 0.3 - 0.5 <= width <= 2 * hw + 0.3 + 0.5


def test_path_world_renders_along_the_path():
    path = figure_eight(300)
    world = sim.path_world(path[:, :2], seed=2, route=sim.Trajectory(np.arange(len(path)) * 0.2, path))
    run = sim.simulate(world, frame_every=50, odometry_noise=sim.OdometryNoise())
    assert run.n_frames == 6
    for _, img in run.frames():
        assert img.std() > 15


def test_bicocca_trajectory_matches_ground_truth_by_timestamp(tmp_path):
    """Synthetic files in the Bicocca layout: odometry at 5 Hz, ground truth at other
    times starting later; poses before the ground truth are dropped, the rest are
    interpolated at the odometry times."""
    rng = np.random.default_rng(0)
    n = 60
    t = 1000.0 + 0.2 * np.arange(n)
    inc = np.column_stack([np.full(n - 1, 0.1), np.zeros(n - 1), rng.normal(0, 0.05, n - 1)])
    true = integrate(inc)
    lines = [f"VERTEX_SE2 {i} {x} {y} {th}" for i, (x, y, th) in enumerate(true)]
    info = " ".join(["1", "0", "0", "1", "0", "1"])
    lines += [f"EDGE_SE2 {i} {i + 1} {dx} {dy} {dth} {info}" for i, (dx, dy, dth) in enumerate(inc)]
    (tmp_path / "run.g2o").write_text("\n".join(lines) + "\n")
    (tmp_path / "run_timestamps.txt").write_text("\n".join(f"{x:.6f}" for x in t) + "\n")
    gt_t = np.arange(t[3] - 0.05, t[-1] + 0.3, 0.23)
    # ground truth of a pure straight motion x = 0.5 (t - 1000), heading 0.1 t
    gt = np.column_stack([0.5 * (gt_t - 1000), np.zeros_like(gt_t), wrap_angle(0.1 * (gt_t - 1000))])
    (tmp_path / "run_GT.csv").write_text("".join(f"{a:.6f}, {b}, {c}, {d}\n" for a, b, c, d in zip(gt_t, *gt.T)))
    traj = sim.bicocca_trajectory(tmp_path, "run.g2o")
    assert traj.times[0] == t[3] and traj.times[-1] == t[-1]
    np.testing.assert_allclose(traj.poses[:, 0], 0.5 * (traj.times - 1000), atol=1e-6)
    np.testing.assert_allclose(traj.poses[:, 2], wrap_angle(0.1 * (traj.times - 1000)), atol=1e-6)
    np.testing.assert_array_equal(traj.odometry, inc[3:])
    run = sim.simulate(
        World.from_polylines(sim.walls_around_path(traj.poses[:, :2])), traj, odometry_noise=sim.OdometryNoise()
    )
    np.testing.assert_allclose(run.increments, inc[3:])  # real odometry passed through


# --------------------------------------------------------------------------- bad input


def test_bad_input_raises_input_error(loop):
    with pytest.raises(InputError, match="width"):
        sim.Camera(width=2)
    with pytest.raises(InputError, match="sigma_omega"):
        sim.OdometryNoise(sigma_omega=-1)
    with pytest.raises(InputError, match="pose"):
        sim.render(loop, (0.0, np.nan, 0.0))
    with pytest.raises(InputError, match="unknown option"):
        sim.simulate(loop, rate=3)
    with pytest.raises(InputError, match="increase"):
        sim.Trajectory([0.0, 1.0, 1.0], np.zeros((3, 3)))
    with pytest.raises(InputError, match="not finite"):
        sim.walls_around_path(np.array([[0.0, 0.0], [np.inf, 1.0]]))


def test_command_line_writes_a_run(tmp_path, capsys):
    from hippomap.sim.cli import main

    rc = main(
        [
            "corridor",
            "--out",
            str(tmp_path / "c"),
            "--laps",
            "1",
            "--frame-every",
            "40",
            "--sigma-omega",
            "0.01",
            "--format",
            "jpg",
            "--exposure-change",
            "0.2",
            "--light-swing",
            "60",
            "--directional",
            "0.5",
        ]
    )
    assert rc == 0
    import json

    config = json.loads((tmp_path / "c" / "sim.json").read_text())["config"]
    assert config["camera"]["exposure_change"] == 0.2 and config["camera"]["exposure_period_s"] == 97.0
    assert config["shading"]["light_swing_deg"] == 60.0 and config["shading"]["directional"] == 0.5
    assert (
        len(list((tmp_path / "c" / "frames").glob("*.jpg")))
        == len((tmp_path / "c" / "frames.csv").read_text().splitlines()) - 1
        > 0
    )
    assert main(["loop", "--out", str(tmp_path / "x"), "--width", "4"]) == 2
    assert "width" in capsys.readouterr().err
    assert main(["figure8", "--out", str(tmp_path / "f"), "--laps", "1", "--frame-every", "100", "--no-progress"]) == 0
    assert json.loads((tmp_path / "f" / "sim.json").read_text())["world"] == "figure8"
    assert main(["grid", "--out", str(tmp_path / "g"), "--laps", "1", "--frame-every", "100", "--no-progress"]) == 0
    assert json.loads((tmp_path / "g" / "sim.json").read_text())["world"] == "grid"
    assert main(["hall", "--out", str(tmp_path / "h"), "--laps", "1", "--frame-every", "100", "--no-progress"]) == 0
    assert json.loads((tmp_path / "h" / "sim.json").read_text())["world"] == "hall"
    assert main(["office", "--out", str(tmp_path / "o"), "--laps", "1", "--frame-every", "100", "--no-progress"]) == 0
    assert json.loads((tmp_path / "o" / "sim.json").read_text())["world"] == "office"
    assert main(["grid", "--out", str(tmp_path / "g3"), "--blocks", "3", "--laps", "1", "--frame-every", "100"]) == 0
    gt = np.loadtxt(tmp_path / "g3" / "groundtruth.csv", delimiter=",", skiprows=1)
    assert float(np.hypot(*np.diff(gt[:, 1:3], axis=0).T).sum()) > 150  # a 3 x 3 grid: 168 m of corridors (2 x 2: 84)
    capsys.readouterr()
    assert main(["loop", "--out", str(tmp_path / "b"), "--blocks", "3"]) == 2
    assert "--blocks" in capsys.readouterr().err
    assert main(["grid", "--out", str(tmp_path / "b"), "--blocks", "0"]) == 2
    assert "blocks" in capsys.readouterr().err


def test_command_line_drives_the_route_at_the_speed_asked(tmp_path, capsys):
    """``--speed`` (loop and corridor): the route is driven at that mean speed, in proportionally
    fewer odometry steps; the Bicocca world keeps its recorded speed and says so; a speed that is not
    positive is named."""
    from hippomap.sim.cli import main

    def run(speed: str | None) -> np.ndarray:
        out = tmp_path / f"c{speed}"
        args = ["corridor", "--out", str(out), "--laps", "1", "--frame-every", "50", "--no-noise", "--no-progress"]
        assert main(args + (["--speed", speed] if speed else [])) == 0
        rows = list(csv.DictReader((out / "odometry.csv").open()))
        return np.array([float(r["v"]) for r in rows])

    slow, fast = run(None), run("0.8")
    assert np.median(slow) == pytest.approx(0.4, rel=0.2) and np.median(fast) == pytest.approx(0.8, rel=0.2)
    assert len(fast) == pytest.approx(len(slow) / 2, rel=0.15)
    assert main(["bicocca", "--out", str(tmp_path / "b"), "--speed", "1.0"]) == 2
    assert "--speed" in capsys.readouterr().err
    assert main(["loop", "--out", str(tmp_path / "z"), "--speed", "0"]) == 2
    assert "speed_mps" in capsys.readouterr().err
    # --stop-every / --stop-seconds: the robot stands still (its true speed 0) for that long each time
    out = tmp_path / "stops"
    args = ["corridor", "--out", str(out), "--laps", "1", "--frame-every", "50", "--no-noise", "--no-progress"]
    assert main(args + ["--stop-every", "5", "--stop-seconds", "4"]) == 0
    v = np.array([float(r["v"]) for r in csv.DictReader((out / "odometry.csv").open())])
    assert len(v) == len(slow) + 20 * np.count_nonzero(np.diff((v[1:] == 0).astype(int)) == 1)
    assert 4 <= np.count_nonzero(np.diff((v[1:] == 0).astype(int)) == 1) and np.count_nonzero(v[1:] == 0) % 20 == 0
    assert main(["loop", "--out", str(tmp_path / "y"), "--stop-every", "5", "--stop-seconds", "0"]) == 2
    assert "stop_s" in capsys.readouterr().err


def test_a_slow_robot_turns_round_at_a_corridor_end_and_drives_on():
    """At 0.2 m/s the pursuit of a point a lookahead along the route, where the route turns back on
    itself, used to circle on the spot beside the corridor's end for the rest of the step budget (about
    500 turns). The route is now driven to its end, with at most one turn on the spot at the turn-round."""
    from hippomap.sim import worlds
    from hippomap.sim.motion import RoutePlan

    traj = worlds.corridor_world(seed=11, speed_mps=0.2).route.sample(5.0)
    v, w = traj.velocities[:, 0], traj.velocities[:, 1]
    # out and back: one turn-round of pi, at most one turn on the spot before the follower looks further on
    assert np.abs(w).sum() * 0.2 < 4 * np.pi
    assert np.hypot(*traj.poses[-1, :2]) < 0.5  # back at the start
    assert v.mean() == pytest.approx(0.2, rel=0.15)
    # a robot that cannot turn round never reaches the end: a clear error, not a run of spinning
    plan = RoutePlan(((0.0, 0.0), (10.0, 0.0)), closed=False, laps=2, speed_mps=0.4, max_omega=1e-3)
    with pytest.raises(InputError, match="did not reach the end of the route"):
        plan.sample(5.0)
