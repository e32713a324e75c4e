"""Calls from other threads onto the event loop, one wake-up per burst instead of one per call.

The store's writer thread completes a durability future per accepted message and every
session's worker reports each processed input; with ``loop.call_soon_threadsafe`` (which
``asyncio.wrap_future`` uses) each of them writes to the loop's wake-up pipe and wakes the
loop on its own — two system calls and a loop iteration per message, for thousands of
messages a second. :class:`LoopCalls` queues the calls and wakes the loop only when its queue
goes from empty to non-empty: a group commit of fifty inputs costs one wake-up, and the loop
runs the fifty calls back to back, in the order they were made.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections import deque
from typing import Any, Callable

log = logging.getLogger("hippomap.server")


class LoopCalls:
    """Run ``fn(*args)`` on ``loop`` from any thread, in call order, batched per wake-up."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._calls: deque[tuple[Callable[..., Any], tuple[Any, ...]]] = deque()
        self._lock = threading.Lock()
        self._scheduled = False

    def call(self, fn: Callable[..., Any], *args: Any) -> None:
        """Queue ``fn(*args)`` for the loop (dropped silently once the loop is closed: shutdown)."""
        with self._lock:
            self._calls.append((fn, args))
            if self._scheduled:
                return
            self._scheduled = True
        try:
            self.loop.call_soon_threadsafe(self._run)
        except RuntimeError:  # the loop is closed: the server is shutting down
            with self._lock:
                self._scheduled = False
                self._calls.clear()

    def _run(self) -> None:
        with self._lock:
            calls = list(self._calls)
            self._calls.clear()
            self._scheduled = False
        for fn, args in calls:
            try:
                fn(*args)
            except Exception:  # one failing callback must not cost the others theirs
                log.exception("a callback on the event loop failed")
