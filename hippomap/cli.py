"""The ``hippomap`` command line. Each subcommand lives in the module that does the work
and registers itself through an ``add_parser(subparsers)`` function listed here."""

from __future__ import annotations

import argparse
import importlib
import sys

from .errors import HippomapError

#: modules providing ``add_parser(subparsers)``; a missing optional one is skipped only
#: when its own dependencies are not installed (e.g. the server extra).
COMMAND_MODULES = (
    "hippomap.run_odometry",
    "hippomap.vpr_eval",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hippomap", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except HippomapError as exc:
        print(f"hippomap {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
