"""Camera simulator: grey camera frames, wheel odometry and ground truth along 2-D paths
in worlds of textured walls (a vectorised 2.5-D ray caster).

No public data set has camera images, odometry and ground truth together (see the data
README), so the whole pipeline is measured on frames rendered here::

    from hippomap import sim
    world = sim.loop_world(seed=1)
    run = sim.simulate(world, rate_hz=5, frame_every=2,
                       odometry_noise=sim.OdometryNoise(sigma_omega=0.02, omega_bias=0.005), seed=1)
    img = run.frame(0)            # rendered on demand
    run.write("results/sim-loop")  # frames/, frames.csv, odometry.csv, groundtruth.csv

These are simulator parameters, not model parameters: they live in
:mod:`hippomap.sim.params`, not in ``hippomap/config.py``.
"""

from .motion import (
    DrivePlan,
    RoutePlan,
    Trajectory,
    arc_increments,
    measure_odometry,
    velocities_from_increments,
    with_stops,
)
from .params import Camera, OdometryNoise, Shading, SimConfig, TextureParams
from .render import Hits, raycast, render
from .run import SimRun, simulate
from .textures import MipAtlas, photo_strip, procedural_strip
from .world import SegmentGrid, World, point_segment_distance, walls_around_path
from .worlds import (
    bicocca_trajectory,
    bicocca_world,
    corridor_world,
    figure8_world,
    grid_walk,
    grid_world,
    hall_world,
    interpolate_poses,
    loop_world,
    office_world,
    path_world,
)

__all__ = [
    "Camera",
    "DrivePlan",
    "Hits",
    "MipAtlas",
    "OdometryNoise",
    "RoutePlan",
    "SegmentGrid",
    "Shading",
    "SimConfig",
    "SimRun",
    "TextureParams",
    "Trajectory",
    "World",
    "arc_increments",
    "bicocca_trajectory",
    "bicocca_world",
    "corridor_world",
    "figure8_world",
    "grid_walk",
    "grid_world",
    "hall_world",
    "office_world",
    "interpolate_poses",
    "loop_world",
    "measure_odometry",
    "path_world",
    "photo_strip",
    "point_segment_distance",
    "procedural_strip",
    "raycast",
    "render",
    "simulate",
    "velocities_from_increments",
    "walls_around_path",
    "with_stops",
]
