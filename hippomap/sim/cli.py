"""``hippomap simulate``: write a simulated run (frames, odometry, ground truth) in the
dataset folder format that ``hippomap run`` and ``hippomap replay`` read. Also runnable as
``python -m hippomap.sim``.

Odometry is noisy by default, as a real robot's: in the loop and corridor worlds the true
motion gets ``--sigma-v 0.02 --sigma-omega 0.01 --omega-bias 0.01`` (in Python
``sim.OdometryNoise.realistic()``), so the odometry drifts and the map has loops to
close. The bicocca world's odometry is the real robot's recorded wheel odometry, so no
noise is added there by default. ``--no-noise`` writes exact odometry (the ground-truth
motion); any noise option given explicitly applies on top of either.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import fields, replace

from ..cli import add_progress_argument, clean_help, progress_enabled
from ..errors import InputError
from .params import Camera, OdometryNoise, Shading, SimConfig, TextureParams


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate",
        help="render a simulated camera run into a dataset folder",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _arguments(p)
    p.set_defaults(func=run_command)
    return p


def _arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``hippomap simulate``, group by group in the order ``--help`` lists them."""
    _world_arguments(p)
    _camera_arguments(p)
    _noise_arguments(p)
    _texture_arguments(p)
    p.add_argument("--format", choices=["png", "jpg"], default="png", help="frame file format (default png)")
    add_progress_argument(p)


#: the worlds ``hippomap simulate`` renders (bench/bench_maps.py reports them in this order)
WORLDS = ("loop", "corridor", "figure8", "grid", "hall", "office", "bicocca")


def _world_arguments(p: argparse.ArgumentParser) -> None:
    """The world and the route: which world, where it goes, its seed, how long and how fast it is driven."""
    p.add_argument(
        "world",
        choices=WORLDS,
        help="loop: a 16 m x 10 m corridor loop; corridor: a straight corridor driven out and back; "
        "figure8: corridors round two 10 m x 7 m blocks driven as a figure of eight; "
        "grid: corridors round a 2 x 2 grid of 8 m x 6 m blocks driven as a random walk of the seed; "
        "hall: an open 18 m x 13 m hall with six pillars, driven as a random walk of the seed between them; "
        "office: a 28 m corridor with five rooms off it, driven end to end, visiting rooms as the seed chooses; "
        "bicocca: walls along the real Bicocca run, driven as recorded",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--data",
        default="../shared/data/bicocca25b",
        help="Bicocca data folder for the bicocca world (default ../shared/data/bicocca25b, "
        "relative to the current directory)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the world (textures, route jitter) and of the noise")
    p.add_argument(
        "--laps",
        type=int,
        default=3,
        help="loop and figure8: laps, corridor and office: passes, grid and hall: the walk's length in lengths of "
        "the grid's corridors or the hall's lanes "
        "(default 3; the bicocca world drives the recorded run once)",
    )
    p.add_argument(
        "--blocks",
        type=int,
        default=None,
        help="grid: blocks along each side of the grid (default 2); the walk's length grows with its corridors",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=5.0,
        help="odometry rate in Hz (default 5; the bicocca world keeps the recorded times)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=None,
        help="loop, corridor, figure8, grid, hall and office: the route's mean speed in m/s (default 0.4); the "
        "bicocca world drives the recorded run at its recorded speed",
    )
    p.add_argument(
        "--stop-every",
        type=float,
        default=0.0,
        help="the robot stands still each time it has driven this many more metres (default 0: it never stops)",
    )
    p.add_argument(
        "--stop-seconds", type=float, default=30.0, help="how long each stop of --stop-every lasts (default 30 s)"
    )


def _camera_arguments(p: argparse.ArgumentParser) -> None:
    """The camera: how often it renders, its image size, field of view, sensor noise and the light."""
    p.add_argument("--frame-every", type=int, default=1, help="render a frame every N odometry steps (default 1)")
    p.add_argument("--width", type=int, default=320, help="frame width in pixels (default 320)")
    p.add_argument("--height", type=int, default=240, help="frame height in pixels (default 240)")
    p.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view, degrees (default 60)")
    p.add_argument("--pixel-noise", type=float, default=0.0, help="sensor noise std, grey levels (default 0)")
    p.add_argument(
        "--exposure-change",
        type=float,
        default=0.0,
        help="the light changes slowly: grey levels scaled by 1 + A sin(2 pi t / period) (default 0)",
    )
    p.add_argument("--exposure-period", type=float, default=97.0, help="seconds of one light cycle (default 97)")
    p.add_argument(
        "--light-swing",
        type=float,
        default=0.0,
        help="the light's direction swings by up to this many degrees (default 0: a fixed light)",
    )
    p.add_argument("--light-period", type=float, default=131.0, help="seconds of one swing of the light (default 131)")
    p.add_argument(
        "--directional",
        type=float,
        default=0.25,
        help="how much darker a wall facing away from the light is than one facing it, a fraction (default 0.25)",
    )


def _texture_arguments(p: argparse.ArgumentParser) -> None:
    """The walls' appearance (:class:`TextureParams`): procedural, or photos, and how often the photos repeat."""
    p.add_argument("--texture", default="procedural", help="'procedural' or a folder of photos (jpg/png)")
    p.add_argument(
        "--photos",
        type=int,
        default=None,
        metavar="N",
        help="photo walls: use only the first N photos of the --texture folder, sorted by name (default all); "
        "fewer photos repeat more often along the walls",
    )
    p.add_argument(
        "--photo-overlay",
        type=int,
        choices=(0, 1),
        default=1,
        help="photo walls: 1 draws procedural posters over the photos so that repeated photos still make distinct "
        "places (default); 0 leaves the photos bare, so that places far apart can look alike",
    )


def texture_params(args: argparse.Namespace) -> TextureParams:
    """The walls of a command line; the photo options need photo walls."""
    photo_options = args.photos is not None or args.photo_overlay != 1
    if args.texture == "procedural" and photo_options:
        raise InputError("--photos and --photo-overlay apply to photo walls: give --texture a folder of photos")
    return TextureParams(source=args.texture, photo_overlay=bool(args.photo_overlay), photo_count=args.photos)


def _noise_arguments(p: argparse.ArgumentParser) -> None:
    """The odometry noise (:class:`OdometryNoise`): each option defaults to the realistic noise, or none with
    ``--no-noise`` (see :func:`odometry_noise`)."""
    realistic = OdometryNoise.realistic()
    p.add_argument(
        "--sigma-v",
        type=float,
        default=None,
        help=f"odometry speed noise std, m/s (default {realistic.sigma_v}; bicocca 0)",
    )
    p.add_argument(
        "--sigma-omega",
        type=float,
        default=None,
        help=f"odometry turn-rate noise std, rad/s (default {realistic.sigma_omega}; bicocca 0)",
    )
    p.add_argument(
        "--omega-bias",
        type=float,
        default=None,
        help=f"constant turn-rate bias, rad/s: the heading drifts by this much per second "
        f"(default {realistic.omega_bias}; bicocca 0)",
    )
    p.add_argument(
        "--scale-error",
        type=float,
        default=None,
        help=f"odometry distance scale error, a fraction (default {realistic.scale_error})",
    )
    p.add_argument(
        "--omega-bias-walk",
        type=float,
        default=None,
        help="the turn-rate bias wanders as a random walk of this many (rad/s)/sqrt(s), a gyro's rate random "
        f"walk: after T seconds it has moved by about this times sqrt(T) (default {realistic.omega_bias_walk}: "
        "a constant bias)",
    )
    p.add_argument(
        "--no-noise", action="store_true", help="exact odometry: every noise option 0 unless given explicitly"
    )


def odometry_noise(args: argparse.Namespace) -> OdometryNoise:
    """The noise of a command line: the world's default (realistic; none for bicocca, whose
    odometry is already real) or none with ``--no-noise``, then the options given."""
    base = OdometryNoise() if args.no_noise or args.world == "bicocca" else OdometryNoise.realistic()
    given = {f.name: getattr(args, f.name) for f in fields(OdometryNoise) if getattr(args, f.name, None) is not None}
    return replace(base, **given)


def run_command(args) -> int:
    from . import worlds
    from .run import simulate

    if args.blocks is not None and args.world != "grid":
        raise InputError(f"--blocks: only the grid world has blocks, not the {args.world} world")
    tex = texture_params(args)
    speed = {} if args.speed is None else {"speed_mps": args.speed}
    if args.world == "loop":
        world = worlds.loop_world(seed=args.seed, laps=args.laps, texture=tex, **speed)
    elif args.world == "corridor":
        world = worlds.corridor_world(seed=args.seed, passes=args.laps, texture=tex, **speed)
    elif args.world == "figure8":
        world = worlds.figure8_world(seed=args.seed, laps=args.laps, texture=tex, **speed)
    elif args.world == "grid":
        n = 2 if args.blocks is None else args.blocks
        world = worlds.grid_world(seed=args.seed, laps=args.laps, blocks=(n, n), texture=tex, **speed)
    elif args.world == "hall":
        world = worlds.hall_world(seed=args.seed, laps=args.laps, texture=tex, **speed)
    elif args.world == "office":
        world = worlds.office_world(seed=args.seed, passes=args.laps, texture=tex, **speed)
    elif speed:
        raise InputError("--speed: the bicocca world drives the recorded run at its recorded speed")
    else:
        world = worlds.bicocca_world(args.data, seed=args.seed, texture=tex)
    config = SimConfig(
        camera=Camera(
            width=args.width,
            height=args.height,
            hfov_deg=args.hfov,
            pixel_noise=args.pixel_noise,
            exposure_change=args.exposure_change,
            exposure_period_s=args.exposure_period,
        ),
        shading=Shading(
            directional=args.directional, light_swing_deg=args.light_swing, light_period_s=args.light_period
        ),
        odometry_noise=odometry_noise(args),
        rate_hz=args.rate,
        frame_every=args.frame_every,
        seed=args.seed,
        image_format=args.format,
        stop_every_m=args.stop_every,
        stop_s=args.stop_seconds,
    )
    run = simulate(world, config=config)
    out = run.write(args.out, progress=progress_enabled(args))
    n = config.odometry_noise
    print(
        f"{out}: {len(run)} odometry steps, {run.n_frames} frames ({world.name} world); odometry noise: "
        + (
            "none"
            if n.is_zero
            else f"sigma_v {n.sigma_v} m/s, sigma_omega {n.sigma_omega} rad/s, "
            f"omega_bias {n.omega_bias} rad/s, scale_error {n.scale_error}"
            + (f", omega_bias_walk {n.omega_bias_walk} (rad/s)/sqrt(s)" if n.omega_bias_walk else "")
        )
    )
    return 0


def main(argv=None) -> int:
    from ..errors import HippomapError

    p = argparse.ArgumentParser(
        prog="python -m hippomap.sim", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    _arguments(p)
    clean_help(p)
    args = p.parse_args(argv)
    try:
        return run_command(args)
    except HippomapError as exc:
        print(f"hippomap simulate: error: {exc}", file=sys.stderr)
        return 2
