"""A text stream that says whether it is a terminal, for tests of what commands print where."""

from __future__ import annotations

import io


class FakeTTY(io.StringIO):
    """A ``StringIO`` whose ``isatty()`` answers ``tty``: stands in for ``sys.stderr`` when a test
    checks behaviour that depends on a terminal (progress bars, colours)."""

    def __init__(self, tty: bool) -> None:
        super().__init__()
        self._tty = tty

    def isatty(self) -> bool:
        return self._tty
