"""The ``hippomap`` command line.

Each subcommand lives in the module that does the work and registers itself through an
``add_parser(subparsers)`` function, declared as an entry point of the group
``hippomap.commands`` in ``pyproject.toml``. Discovery through entry points lets the
server package add ``serve`` without ``hippomap/`` ever importing web code."""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

from .errors import HippomapError

GROUP = "hippomap.commands"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hippomap", description="hippomap: bio-inspired SLAM after the rat hippocampus (grid cells, place cells, visual recognition memory, cognitive map).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for ep in sorted(entry_points(group=GROUP), key=lambda e: e.name):
        try:
            register = ep.load()
        except ImportError as exc:  # e.g. `serve` without the server extra installed
            _unavailable(sub, ep.name, exc)
            continue
        register(sub)
    return parser


def _unavailable(sub: argparse._SubParsersAction, name: str, exc: ImportError) -> None:
    """Keep a command whose dependencies are missing visible, with the way to fix it."""
    message = f"needs a missing dependency ({exc.name or exc}); install it with: pip install 'hippomap[server]'"
    p = sub.add_parser(name, help=f"(unavailable: {message})")

    def fail(args: argparse.Namespace) -> int:
        print(f"hippomap {name}: {message}", file=sys.stderr)
        return 2

    p.set_defaults(func=fail)


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
