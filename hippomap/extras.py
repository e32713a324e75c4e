"""The optional dependencies: which extra of ``pyproject.toml`` installs which package, and the error that
names the extra to install when code that needs one runs without it.

The core install (``pip install hippomap``) is the model and the offline commands: numpy, SciPy, OpenCV,
pydantic, tqdm. Evaluation, figures, ROS bags and the client of the service need more. Their imports are
made inside the functions that use them, under :func:`requires`, so the model never needs them and a missing
one fails with the command that installs it instead of a bare ``ModuleNotFoundError``::

    with requires("eval", "a TUM file"):
        from evo.tools import file_interface
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from contextlib import contextmanager

from .errors import HippomapError

#: the top-level modules each extra installs (``[project.optional-dependencies]`` in ``pyproject.toml``;
#: tests/test_packaging.py checks the built wheel's metadata against this table), smallest extra first
EXTRAS: dict[str, tuple[str, ...]] = {
    "viz": ("matplotlib",),
    "rosbag": ("rosbags",),
    "client": ("httpx", "websockets"),
    "eval": ("evo", "matplotlib"),
}


class MissingExtraError(HippomapError, ImportError):
    """An optional dependency is not installed. ``extra`` is the extra that installs it and ``name`` (as for
    any ``ImportError``) the missing module; the message says what needed it and the ``pip`` command."""

    def __init__(self, extra: str, module: str, needed_for: str) -> None:
        super().__init__(f"{needed_for} needs {module}, which is not installed: pip install 'hippomap[{extra}]'")
        self.extra = extra
        self.name = module


def extra_for(module: str) -> str | None:
    """The smallest extra that installs the top-level package of ``module`` (``"evo.core"`` -> ``"eval"``),
    or None when no extra of this table does (e.g. the server's packages: the ``server`` extra)."""
    top = module.partition(".")[0]
    return next((extra for extra, modules in EXTRAS.items() if top in modules), None)


@contextmanager
def requires(extra: str, needed_for: str) -> Iterator[None]:
    """Run the imports of the ``with`` block; a module of ``extra`` that is missing raises
    :class:`MissingExtraError` naming ``needed_for`` (what the caller was doing) and the extra. Other
    import errors (a broken install of some other package) pass through unchanged."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; the extras are {sorted(EXTRAS)}")
    try:
        yield
    except ModuleNotFoundError as exc:
        top = (exc.name or "").partition(".")[0]
        if top not in EXTRAS[extra]:
            raise
        raise MissingExtraError(extra, top, needed_for) from exc


def check(extra: str, needed_for: str) -> None:
    """Raise :class:`MissingExtraError` now when a package of ``extra`` is not installed, without importing
    it: for a command that would otherwise find out only after its long run, when it writes its results."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; the extras are {sorted(EXTRAS)}")
    for module in EXTRAS[extra]:
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            raise MissingExtraError(extra, module, needed_for)
