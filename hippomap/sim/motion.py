"""Robot motion for the simulator: trajectories, drive plans and wheel odometry.

A step of wheel odometry is a unicycle moving with constant forward speed ``v`` and
turn rate ``ω`` for ``dt``: an exact circular arc (:func:`arc_increments`). Drive plans
are integrated with exactly these arcs, so with zero odometry noise the odometry
integrates (``hippomap.geometry.integrate``) to the ground truth to rounding error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..geometry import between, integrate, path_lengths, wrap_angle
from .params import OdometryNoise


def arc_increments(v, omega, dt) -> np.ndarray:
    """Relative pose (dx, dy, dθ) in the start frame after moving at constant ``v``,
    ``omega`` for ``dt`` (arrays broadcast): (N, 3)."""
    v, omega, dt = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (v, omega, dt)))
    th = omega * dt
    d = v * dt
    dx = d * np.sinc(th / np.pi)  # sin(th) / th
    dy = d * np.sin(th / 2) * np.sinc(th / (2 * np.pi))  # (1 - cos th) / th
    return np.stack([dx, dy, th], axis=-1).reshape(-1, 3)


def velocities_from_increments(increments, dt) -> tuple[np.ndarray, np.ndarray]:
    """The constant (v, ω) whose arc joins each increment's end points:
    ``ω = dθ / dt`` and ``v = ±arc length / dt`` (negative when driving backwards).
    Exact inverse of :func:`arc_increments` for |dθ| < 2π; for an increment that is not
    an arc (sideways slip) the arc keeps its chord length and heading change."""
    inc = np.asarray(increments, dtype=float).reshape(-1, 3)
    dt = np.asarray(dt, dtype=float)
    th = inc[:, 2]
    chord = np.hypot(inc[:, 0], inc[:, 1])
    arc = chord / np.sinc(th / (2 * np.pi))
    sign = np.where(inc[:, 0] < 0, -1.0, 1.0)
    return sign * arc / dt, th / dt


def _check_times(times: np.ndarray, what: str) -> None:
    if times.ndim != 1 or len(times) < 2:
        raise InputError(f"{what}: need at least 2 times, got shape {times.shape}")
    if not np.isfinite(times).all():
        raise InputError(f"{what}: time {int(np.flatnonzero(~np.isfinite(times))[0])} is not finite")
    bad = np.flatnonzero(np.diff(times) <= 0)
    if bad.size:
        k = int(bad[0])
        raise InputError(f"{what}: times must increase: t[{k + 1}] = {times[k + 1]!r} follows t[{k}] = {times[k]!r}")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A camera path: ``times`` (N,), ground-truth ``poses`` (N, 3).

    Optionally the true per-step ``velocities`` (N-1, 2: v, ω held over each step, from a
    drive plan) or measured ``odometry`` increments (N-1, 3, e.g. real wheel odometry of
    a recorded run) that the simulator reports instead of deriving odometry from poses.
    """

    times: np.ndarray
    poses: np.ndarray
    velocities: np.ndarray | None = None
    odometry: np.ndarray | None = None

    def __post_init__(self):
        t = np.asarray(self.times, dtype=float).reshape(-1)
        p = np.asarray(self.poses, dtype=float)
        _check_times(t, "trajectory")
        if p.shape != (len(t), 3):
            raise InputError(f"trajectory poses must be ({len(t)}, 3) to match the times, got {p.shape}")
        if not np.isfinite(p).all():
            raise InputError(f"trajectory pose {int(np.flatnonzero(~np.isfinite(p).all(1))[0])} is not finite")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "poses", p)
        for name, cols in (("velocities", 2), ("odometry", 3)):
            a = getattr(self, name)
            if a is None:
                continue
            a = np.asarray(a, dtype=float)
            if a.shape != (len(t) - 1, cols):
                raise InputError(f"trajectory {name} must be ({len(t) - 1}, {cols}), got {a.shape}")
            if not np.isfinite(a).all():
                raise InputError(
                    f"trajectory {name} row {int(np.flatnonzero(~np.isfinite(a).all(1))[0])} is not finite"
                )
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return len(self.times)

    def sample(self, rate_hz: float | None = None) -> "Trajectory":
        """A trajectory already has its times: returned unchanged."""
        return self


@dataclass(frozen=True)
class DrivePlan:
    """Piecewise-constant commands ``(duration_s, v, omega)`` from ``start``. Each
    duration is rounded to a whole number of odometry steps (at least one)."""

    commands: tuple
    start: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        c = np.asarray(self.commands, dtype=float)
        if c.ndim != 2 or c.shape[1] != 3 or len(c) == 0:
            raise InputError(f"drive plan commands must be (duration, v, omega) rows, got shape {c.shape}")
        if not np.isfinite(c).all() or (c[:, 0] <= 0).any():
            k = int(np.flatnonzero(~np.isfinite(c).all(1) | (c[:, 0] <= 0))[0])
            raise InputError(f"drive plan command {k} = {tuple(c[k])}: durations must be > 0 and values finite")
        object.__setattr__(self, "commands", tuple(map(tuple, c)))

    def sample(self, rate_hz: float) -> Trajectory:
        c = np.asarray(self.commands)
        n = np.maximum(1, np.round(c[:, 0] * rate_hz).astype(int))
        v, w = np.repeat(c[:, 1], n), np.repeat(c[:, 2], n)
        dt = 1.0 / rate_hz
        poses = integrate(arc_increments(v, w, dt), self.start)
        times = np.arange(len(poses)) * dt
        return Trajectory(times, poses, velocities=np.stack([v, w], axis=1))


def _smooth(rng, n, corr):
    k = max(1, int(corr))
    raw = rng.standard_normal(n + 4 * k)
    ker = np.hanning(4 * k + 1)
    sm = np.convolve(raw, ker / ker.sum(), mode="same")[2 * k : 2 * k + n]
    return sm / (sm.std() or 1.0)


def _nearest_heading_our_way(q: np.ndarray, tangent: np.ndarray, lo: int, hi: int, pose: np.ndarray) -> int:
    """Index of the route point in ``q[lo:hi]`` nearest the robot at ``pose`` among those whose route
    direction (``tangent``) points the robot's way; ``lo`` when none does. Where the route turns back on
    itself (a corridor's end), a slow robot can turn round before the last point of the leg, and the nearest
    route point then stays on the leg behind it while it circles; after a whole turn without progress,
    :meth:`RoutePlan.sample` asks this for the leg the robot has turned onto instead."""
    same_way = tangent[lo:hi] @ np.array([np.cos(pose[2]), np.sin(pose[2])]) > 0
    if not same_way.any():
        return lo
    d = np.hypot(q[lo:hi, 0] - pose[0], q[lo:hi, 1] - pose[1])
    return lo + int(np.argmin(np.where(same_way, d, np.inf)))


@dataclass(frozen=True)
class RoutePlan:
    """Drive along waypoints with a pure-pursuit controller (the robot steers towards
    the point ``lookahead_m`` ahead on the route, turns on the spot when that point is
    behind it). ``closed`` routes are driven ``laps`` times round; open routes are driven
    out and back ``laps`` times in all. Each lap wanders by a seeded, smooth lateral
    offset (std ``lateral_jitter_m``) and speed change (``speed_jitter`` fraction), so
    revisits are near, not identical, poses."""

    waypoints: tuple
    closed: bool = True
    laps: int = 1
    speed_mps: float = 0.4
    lookahead_m: float = 0.8
    max_omega: float = 1.0
    lateral_jitter_m: float = 0.12
    speed_jitter: float = 0.15
    seed: int = 0

    def __post_init__(self):
        w = np.asarray(self.waypoints, dtype=float)
        if w.ndim != 2 or w.shape[1] != 2 or len(w) < 2 or not np.isfinite(w).all():
            raise InputError(f"route waypoints must be finite (K >= 2, 2), got shape {w.shape}")
        object.__setattr__(self, "waypoints", tuple(map(tuple, w)))
        for name in ("speed_mps", "lookahead_m", "max_omega"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"RoutePlan.{name} = {v!r} must be finite and > 0")
        if not (isinstance(self.laps, int) and self.laps >= 1):
            raise InputError(f"RoutePlan.laps = {self.laps!r} must be an integer >= 1")
        if not (0 <= self.speed_jitter < 1) or not self.lateral_jitter_m >= 0:
            raise InputError(
                f"RoutePlan jitters must be >= 0 (speed_jitter < 1), got {self.lateral_jitter_m}, {self.speed_jitter}"
            )

    def path(self, spacing: float = 0.05) -> np.ndarray:
        """The route as driven (all laps, jitter applied), resampled every ``spacing`` m."""
        w = np.asarray(self.waypoints)
        if self.closed:
            lap = np.vstack([w, w[:1]])
            pl = np.vstack([lap] + [lap[1:]] * (self.laps - 1))
        else:
            legs = [w if k % 2 == 0 else w[::-1] for k in range(self.laps)]
            pl = np.vstack([legs[0]] + [leg[1:] for leg in legs[1:]])
        seg = np.hypot(*np.diff(pl, axis=0).T)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        q = np.arange(0.0, s[-1], spacing)
        q = np.append(q, s[-1])
        dense = np.stack([np.interp(q, s, pl[:, 0]), np.interp(q, s, pl[:, 1])], axis=1)
        if self.lateral_jitter_m > 0:
            rng = np.random.default_rng([self.seed, 1])
            tang = np.gradient(dense, axis=0)
            tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-12)
            normal = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
            off = self.lateral_jitter_m * _smooth(rng, len(dense), 3.0 / spacing)
            off[0] = 0.0
            # no offset at the start so lap 1 begins on the route
            ramp = np.clip(np.arange(len(dense)) * spacing / 1.0, 0, 1)
            dense = dense + (off * ramp)[:, None] * normal
        return dense

    def sample(self, rate_hz: float) -> Trajectory:
        spacing = 0.05
        q = self.path(spacing)
        m = len(q)
        dt = 1.0 / rate_hz
        rng = np.random.default_rng([self.seed, 2])
        speed = self.speed_mps * (1 + self.speed_jitter * np.clip(_smooth(rng, m, 4.0 / spacing), -2, 2) / 2)
        look = max(1, int(round(self.lookahead_m / spacing)))
        window = int((self.speed_mps * 2 * dt + 0.5) / spacing) + 2
        ahead = q[min(m - 1, look)] - q[0]
        pose = np.array([q[0, 0], q[0, 1], np.arctan2(ahead[1], ahead[0])])
        i = 0
        vs: list[float] = []
        ws: list[float] = []
        max_steps = int(10 * m * spacing / (self.speed_mps * dt)) + 100
        # a whole turn's worth of steps without progress along the route: see _nearest_heading_our_way
        stuck_after = int(np.ceil(2 * np.pi / (self.max_omega * dt)))
        stuck, best_i = 0, -1
        tangent = np.gradient(q, axis=0)
        while True:
            if len(vs) >= max_steps:
                raise InputError(
                    f"the route follower did not reach the end of the route in {max_steps} steps (stuck at point {i} "
                    f"of {m}): speed_mps {self.speed_mps}, lookahead_m {self.lookahead_m}, max_omega {self.max_omega}"
                )
            lo, hi = i, min(m, i + window)
            d = np.hypot(q[lo:hi, 0] - pose[0], q[lo:hi, 1] - pose[1])
            i = lo + int(np.argmin(d))
            if stuck >= stuck_after:
                i = _nearest_heading_our_way(q, tangent, i, min(m, i + 2 * look + window), pose)
            if i >= m - 1 or (m - 1 - i) * spacing < 0.05:
                break
            stuck = stuck + 1 if i <= best_i else 0
            best_i = max(i, best_i)
            tgt = q[min(m - 1, i + look)]
            alpha = wrap_angle(np.arctan2(tgt[1] - pose[1], tgt[0] - pose[0]) - pose[2])
            sp = speed[i]
            if abs(alpha) < np.pi / 2:
                v = sp * np.cos(alpha)
                w = float(np.clip(2 * sp * np.sin(alpha) / self.lookahead_m, -self.max_omega, self.max_omega))
            else:  # target behind: turn on the spot
                v, w = 0.0, float(np.copysign(self.max_omega, alpha))
            # near the end: do not overshoot the last point
            remaining = (m - 1 - i) * spacing
            v = min(v, remaining / dt)
            inc = arc_increments(v, w, dt)[0]
            c, s_ = np.cos(pose[2]), np.sin(pose[2])
            pose = np.array(
                [pose[0] + c * inc[0] - s_ * inc[1], pose[1] + s_ * inc[0] + c * inc[1], wrap_angle(pose[2] + inc[2])]
            )
            vs.append(v)
            ws.append(w)
            if remaining < 0.05:
                break
        if not vs:
            raise InputError("route is too short to drive")
        v_arr, w_arr = np.array(vs), np.array(ws)
        start = np.array([q[0, 0], q[0, 1], np.arctan2(ahead[1], ahead[0])])
        poses = integrate(arc_increments(v_arr, w_arr, dt), start)
        return Trajectory(np.arange(len(poses)) * dt, poses, velocities=np.stack([v_arr, w_arr], axis=1))


def with_stops(traj: Trajectory, every_m: float, seconds: float) -> Trajectory:
    """``traj`` with the robot standing still for ``seconds`` each time it has driven another ``every_m``
    of path (none at the very end), as a robot waits at a door or for people to pass. The stops are
    whole odometry steps of the trajectory's own period (its median step; at least one); the times after
    a stop are shifted by its length. Standing still, the true velocities (or measured increments) are zero, so a
    gyro's bias still turns the odometry's heading (:func:`measure_odometry`)."""
    if not (np.isfinite(every_m) and every_m > 0 and np.isfinite(seconds) and seconds > 0):
        raise InputError(f"stops need every_m > 0 and seconds > 0, got {every_m!r} and {seconds!r}")
    t, p = traj.times, traj.poses
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    n = max(1, int(round(seconds / dt))) if dt > 0 else 0
    path = path_lengths(p[:, :2])
    at = np.searchsorted(path, np.arange(every_m, path[-1], every_m))  # the first step at or past each mark
    at = np.unique(at[(at > 0) & (at < len(t) - 1)])
    if n == 0 or not len(at):
        return traj
    # step i of the new run copies step src[i] of the old one; a stop repeats its step's pose n more times,
    # so i - src[i] steps of standing still come before step i: its time is shifted by that many periods
    reps = np.ones(len(t), np.int64)
    reps[at] += n
    src = np.repeat(np.arange(len(t)), reps)
    times = t[src] + dt * (np.arange(len(src)) - src)
    moving = np.ones(len(src) - 1, bool)  # a step between two copies of one pose is a standstill
    moving[src[1:] == src[:-1]] = False
    out = {}
    for name in ("velocities", "odometry"):
        a = getattr(traj, name)
        if a is not None:
            b = np.zeros((len(src) - 1, a.shape[1]))
            b[moving] = a
            out[name] = b
    return Trajectory(times, p[src], **out)


def measure_odometry(traj: Trajectory, noise: OdometryNoise, rng: np.random.Generator):
    """Wheel odometry of a trajectory: per step (v, ω) as measured and the increments
    they integrate to. Source motion: the plan's true velocities if known, else the
    trajectory's measured odometry, else the ground-truth increments; then the
    :class:`OdometryNoise` model. With zero noise the increments are the source ones
    unchanged (so ground-truth increments integrate exactly back to the poses)."""
    dt = np.diff(traj.times)
    if traj.velocities is not None:
        v, w = traj.velocities[:, 0].copy(), traj.velocities[:, 1].copy()
        inc = arc_increments(v, w, dt)
    else:
        inc = traj.odometry if traj.odometry is not None else between(traj.poses[:-1], traj.poses[1:])
        v, w = velocities_from_increments(inc, dt)
    if noise.is_zero:
        return v, w, inc
    v = (1.0 + noise.scale_error) * v + (rng.normal(0.0, noise.sigma_v, len(v)) if noise.sigma_v > 0 else 0.0)
    w = w + noise.omega_bias + (rng.normal(0.0, noise.sigma_omega, len(w)) if noise.sigma_omega > 0 else 0.0)
    if noise.omega_bias_walk > 0:  # drawn after the others, so a run without it keeps its noise
        w = w + np.cumsum(rng.normal(0.0, 1.0, len(w)) * noise.omega_bias_walk * np.sqrt(dt))
    return v, w, arc_increments(v, w, dt)
