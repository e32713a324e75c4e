"""``hippomap simulate``: write a simulated run (frames, odometry, ground truth) in the
dataset folder format. Register by adding ``"hippomap.sim.cli"`` to
``hippomap.cli.COMMAND_MODULES``; also runnable as ``python -m hippomap.sim``."""

from __future__ import annotations

import argparse
import sys

from .params import Camera, OdometryNoise, SimConfig, TextureParams


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("simulate", help="render a simulated camera run into a dataset folder",
                              description=__doc__)
    _arguments(p)
    p.set_defaults(func=run_command)
    return p


def _arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("world", choices=["loop", "corridor", "bicocca"], help="which world to drive in")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--data", default="../shared/data/bicocca25b",
                   help="Bicocca folder (bicocca world); default: the shared data beside the clone")
    p.add_argument("--seed", type=int, default=0, help="world (textures, route jitter) and noise seed")
    p.add_argument("--laps", type=int, default=3, help="loop laps / corridor passes")
    p.add_argument("--rate", type=float, default=5.0, help="odometry rate in Hz (drive plans)")
    p.add_argument("--frame-every", type=int, default=1, help="render a frame every N odometry steps")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view, degrees")
    p.add_argument("--pixel-noise", type=float, default=0.0, help="sensor noise std, grey levels")
    p.add_argument("--sigma-v", type=float, default=0.0, help="odometry speed noise std, m/s")
    p.add_argument("--sigma-omega", type=float, default=0.0, help="odometry turn-rate noise std, rad/s")
    p.add_argument("--omega-bias", type=float, default=0.0, help="constant turn-rate bias, rad/s")
    p.add_argument("--scale-error", type=float, default=0.0, help="odometry distance scale error (fraction)")
    p.add_argument("--texture", default="procedural", help="'procedural' or a folder of photos")
    p.add_argument("--format", choices=["png", "jpg"], default="png")
    p.add_argument("--progress", action="store_true", help="show a progress bar")


def run_command(args) -> int:
    from . import worlds
    from .run import simulate

    tex = TextureParams(source=args.texture)
    if args.world == "loop":
        world = worlds.loop_world(seed=args.seed, laps=args.laps, texture=tex)
    elif args.world == "corridor":
        world = worlds.corridor_world(seed=args.seed, passes=args.laps, texture=tex)
    else:
        world = worlds.bicocca_world(args.data, seed=args.seed, texture=tex)
    config = SimConfig(
        camera=Camera(width=args.width, height=args.height, hfov_deg=args.hfov, pixel_noise=args.pixel_noise),
        odometry_noise=OdometryNoise(args.sigma_v, args.sigma_omega, args.omega_bias, args.scale_error),
        rate_hz=args.rate, frame_every=args.frame_every, seed=args.seed, image_format=args.format,
    )
    run = simulate(world, config=config)
    out = run.write(args.out, progress=args.progress)
    print(f"{out}: {len(run)} odometry steps, {run.n_frames} frames ({world.name} world)")
    return 0


def main(argv=None) -> int:
    from ..errors import HippomapError

    p = argparse.ArgumentParser(prog="python -m hippomap.sim", description=__doc__)
    _arguments(p)
    args = p.parse_args(argv)
    try:
        return run_command(args)
    except HippomapError as exc:
        print(f"hippomap simulate: error: {exc}", file=sys.stderr)
        return 2
