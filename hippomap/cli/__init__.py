"""The ``hippomap`` command line.

Each subcommand lives in the module that does the work and registers itself through an
``add_parser(subparsers)`` function, declared as an entry point of the group
``hippomap.commands`` in ``pyproject.toml``. Discovery through entry points lets the
server package add ``serve`` without ``hippomap/`` ever importing web code."""

from __future__ import annotations

import argparse
import re
import sys
from importlib.metadata import PackageNotFoundError, entry_points, version

from ..errors import HippomapError
from ..extras import extra_for

GROUP = "hippomap.commands"


def package_version() -> str:
    """The installed distribution's version (``pyproject.toml``), or ``"unknown"`` when
    the package runs from a source tree that was never installed."""
    try:
        return version("hippomap")
    except PackageNotFoundError:
        return "unknown"


def add_progress_argument(parser: argparse.ArgumentParser) -> None:
    """The one progress switch of every long command: ``--progress`` / ``--no-progress``,
    by default on when stderr is a terminal (see :func:`progress_enabled`).

    ``--quiet`` is kept, hidden from the help, as an old spelling of ``--no-progress`` so
    that scripts written for earlier versions keep working."""
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="show progress on stderr (default: on when stderr is a terminal)",
    )
    parser.add_argument("--quiet", dest="progress", action="store_false", help=argparse.SUPPRESS)


def progress_enabled(args: argparse.Namespace) -> bool:
    """Whether to show progress: the flag if given, else whether stderr is a terminal
    (a pipe or a log file would fill up with progress bars)."""
    flag = getattr(args, "progress", None)
    if flag is not None:
        return bool(flag)
    isatty = getattr(sys.stderr, "isatty", None)
    return bool(isatty and isatty())


_ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|obj|exc):`~?([^`]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def plain_text(text: str | None) -> str | None:
    """``text`` without reStructuredText / Sphinx markup, for terminal help: inline literals
    lose their double backticks, cross-references (class, func, meth, mod, ...) become their
    target (the last part only when the target starts with a tilde), and a literal-block
    ``::`` at a line end becomes ``:``.

    Module docstrings double as command descriptions; they keep their markup for the API
    docs and are cleaned here, once, for every command."""
    if not text:
        return text

    def role(m: re.Match) -> str:
        target = m.group(1)
        return target.rsplit(".", 1)[-1] if m.group(0).split("`", 1)[1].startswith("~") else target

    text = _ROLE.sub(role, text)
    text = _LITERAL.sub(r"\1", text)
    return re.sub(r"::$", ":", text, flags=re.M)


def clean_help(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Strip markup (:func:`plain_text`) from a parser's description, epilog and argument
    help, and from every sub-command's, recursively."""
    parser.description = plain_text(parser.description)
    parser.epilog = plain_text(parser.epilog)
    for action in parser._actions:
        if action.help not in (None, argparse.SUPPRESS):
            action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = plain_text(choice.help)
            for sub in set(action.choices.values()):
                clean_help(sub)
    return parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hippomap",
        description="hippomap: bio-inspired SLAM after the rat hippocampus (grid cells, place cells, "
        "visual recognition memory, cognitive map).",
    )
    parser.add_argument("--version", action="version", version=f"hippomap {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for ep in sorted(entry_points(group=GROUP), key=lambda e: e.name):
        try:
            register = ep.load()
        except ImportError as exc:  # e.g. `serve` without the server extra installed
            _unavailable(sub, ep.name, exc, own=ep.value.startswith("hippomap."))
            continue
        register(sub)
    return clean_help(parser)


def _unavailable(sub: argparse._SubParsersAction, name: str, exc: ImportError, own: bool = False) -> None:
    """Keep a command whose dependencies are missing visible, with the way to fix it: for a command of
    this package (``own``), the extra that installs the missing module (:func:`~hippomap.extras.extra_for`);
    for the others (``serve``, registered by the server package), the ``server`` extra."""
    extra = extra_for(exc.name) if own and exc.name else None
    message = (
        f"needs a missing dependency ({exc.name or exc}); install it with: pip install 'hippomap[{extra or 'server'}]'"
    )
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
