"""Simulated runs: ground truth, noisy wheel odometry, and camera frames rendered on
demand, written in the project's dataset folder format:

- ``frames/NNNNNN.png`` (or ``.jpg``) grey images,
- ``frames.csv``: ``t,file`` (file relative to the folder),
- ``odometry.csv``: ``t,v,omega`` (m/s, rad/s),
- ``groundtruth.csv``: ``t,x,y,theta`` (m, rad).

Odometry rows are *causal*: row ``i`` (time ``t_i``) holds the constant velocities of
the motion from ``t_{i-1}`` to ``t_i`` (row 0 is zero), so integrating rows ``1..i`` as
arcs gives the pose at ``t_i``, and odometry and ground truth share their time column.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Iterator, cast

import cv2
import numpy as np

from ..errors import InputError
from .motion import Trajectory, measure_odometry, with_stops
from .params import SimConfig
from .render import render
from .world import World


@dataclass(eq=False)
class SimRun:
    """A simulated run. ``times`` (N,), ``groundtruth`` (N, 3), ``odometry`` (N, 3) rows
    ``t, v, omega`` (causal, see module doc), ``increments`` (N-1, 3) relative poses
    i -> i+1 in the frame of i (as ``hippomap.io.datasets.G2OGraph.odometry``), and camera
    frames at the odometry steps ``frame_steps``, rendered only when asked for."""

    world: World
    config: SimConfig
    times: np.ndarray
    groundtruth: np.ndarray
    odometry: np.ndarray
    increments: np.ndarray
    frame_steps: np.ndarray

    def __len__(self) -> int:
        return len(self.times)

    @property
    def n_frames(self) -> int:
        return len(self.frame_steps)

    @property
    def frame_times(self) -> np.ndarray:
        return self.times[self.frame_steps]

    @property
    def frame_poses(self) -> np.ndarray:
        return self.groundtruth[self.frame_steps]

    def frame(self, i: int) -> np.ndarray:
        """Camera frame ``i`` (uint8, height x width), rendered now."""
        if not (-self.n_frames <= i < self.n_frames):
            raise InputError(f"frame index {i} out of range 0..{self.n_frames - 1}")
        i %= self.n_frames
        cam = self.config.camera
        rng = np.random.default_rng([self.config.seed, 7, i]) if cam.pixel_noise > 0 else None
        t = float(self.frame_times[i])
        shading = self.config.shading.at(t)
        return render(self.world, self.groundtruth[self.frame_steps[i]], cam, shading, rng, cam.exposure_gain(t))

    def frames(self) -> Iterator[tuple[float, np.ndarray]]:
        """Iterate (t, frame) over all frames, one rendered at a time."""
        for i in range(self.n_frames):
            yield float(self.frame_times[i]), self.frame(i)

    def write(self, folder: str | Path, progress: bool = False) -> Path:
        """Write the run in the dataset folder format (see module doc) plus ``sim.json``
        (world, seed, camera intrinsics, noise) and return the folder."""
        folder = Path(folder)
        (folder / "frames").mkdir(parents=True, exist_ok=True)
        ext = self.config.image_format
        names = []
        it = range(self.n_frames)
        if progress:
            from tqdm import tqdm

            it = tqdm(it, desc="frames", unit="frame")
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if ext == "jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
        for i in it:
            name = f"frames/{i:06d}.{ext}"
            if not cv2.imwrite(str(folder / name), self.frame(i), params):
                raise InputError(f"cannot write {folder / name}")
            names.append(name)
        with (folder / "frames.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "file"])
            w.writerows([f"{t:.6f}", n] for t, n in zip(self.frame_times, names))
        with (folder / "odometry.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "v", "omega"])
            w.writerows([f"{t:.6f}", repr(float(v)), repr(float(o))] for t, v, o in self.odometry)
        with (folder / "groundtruth.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "x", "y", "theta"])
            w.writerows([f"{t:.6f}", *(repr(float(x)) for x in p)] for t, p in zip(self.times, self.groundtruth))
        cam = self.config.camera
        meta = {
            "world": self.world.name,
            "world_seed": self.world.seed,
            "texture": asdict(self.world.texture),
            "config": asdict(self.config),
            "intrinsics": {
                "fx": cam.focal_px,
                "fy": cam.focal_px,
                "cx": cam.cx,
                "cy": cam.cy,
                "width": cam.width,
                "height": cam.height,
            },
            "odometry_convention": "row i: constant v, omega from t[i-1] to t[i]; row 0 is zero",
        }
        (folder / "sim.json").write_text(json.dumps(meta, indent=2))
        return folder


def simulate(world: World, trajectory=None, config: SimConfig | None = None, **overrides) -> SimRun:
    """Simulate a run in ``world`` along ``trajectory`` (a ``Trajectory``, ``DrivePlan``
    or ``RoutePlan``; default: the world's own route). Keyword overrides replace fields
    of ``config`` (``rate_hz``, ``frame_every``, ``odometry_noise``, ``camera``,
    ``shading``, ``seed``, ``image_format``, ``stop_every_m``, ``stop_s``). Deterministic for a given seed."""
    config = config or SimConfig()
    if overrides:
        names = {f.name for f in fields(SimConfig)}
        bad = sorted(set(overrides) - names)
        if bad:
            raise InputError(f"simulate() got unknown option(s) {bad}; known: {sorted(names)}")
        config = replace(config, **overrides)
    plan = trajectory if trajectory is not None else world.route
    if plan is None:
        raise InputError(f"world {world.name!r} has no default route: pass a trajectory or drive plan")
    if not hasattr(plan, "sample"):
        raise InputError(f"trajectory must be a Trajectory, DrivePlan or RoutePlan, got {type(plan).__name__}")
    traj: Trajectory = cast(Any, plan).sample(config.rate_hz)  # any plan with .sample (checked above)
    if config.stop_every_m > 0:
        traj = with_stops(traj, config.stop_every_m, config.stop_s)
    rng = np.random.default_rng([config.seed, 3])
    v, w, inc = measure_odometry(traj, config.odometry_noise, rng)
    odo = np.zeros((len(traj), 3))
    odo[:, 0] = traj.times
    odo[1:, 1] = v
    odo[1:, 2] = w
    steps = np.arange(0, len(traj), config.frame_every)
    return SimRun(world, config, traj.times.copy(), traj.poses.copy(), odo, np.asarray(inc, float), steps)
