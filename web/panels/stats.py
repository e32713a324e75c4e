"""Panel: session statistics — nodes, links, loop closures, frames per second, lag.

Counts come from :meth:`hippomap.mapper.Mapper.stats`; rates are measured by the viewer between
its updates (frames and odometry steps processed per wall-clock second, smoothed); the lag is
what the session reports (:meth:`web.source.SessionSource.lag_s`).
"""

from __future__ import annotations

import time
from typing import Any, Mapping


class RateMeter:
    """Events per second of a growing counter, exponentially smoothed over ``tau`` seconds."""

    def __init__(self, tau: float = 2.0) -> None:
        self.tau = tau
        self.rate = 0.0
        self._last: tuple[float, float] | None = None

    def update(self, count: float, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        if self._last is not None:
            c0, t0 = self._last
            dt = now - t0
            if dt > 0:
                inst = max(0.0, count - c0) / dt
                w = min(1.0, dt / self.tau)
                self.rate += w * (inst - self.rate)
        self._last = (count, now)
        return self.rate


def stats_markdown(stats: Mapping[str, Any], fps: float, odometry_hz: float, lag_s: float | None) -> str:
    """The stats table as markdown."""
    lag = "–" if lag_s is None else f"{lag_s:.2f} s"
    rows = [
        ("nodes", stats.get("nodes", 0)),
        ("links", stats.get("links", 0)),
        (
            "loop closures",
            f"{stats.get('loop_closures_used', 0)} used of {stats.get('loop_closures_accepted', 0)} accepted"
            f" / {stats.get('loop_closures_rejected', 0)} rejected",
        ),
        ("key frames", stats.get("keyframes", 0)),
        ("recognitions", stats.get("recognitions", 0)),
        ("frames", f"{stats.get('frames', 0)} ({fps:.1f} /s)"),
        ("odometry steps", f"{stats.get('odometry_steps', 0)} ({odometry_hz:.1f} /s)"),
        ("distance", f"{float(stats.get('distance_m', 0.0)):.1f} m"),
        ("lag", lag),
    ]
    return "| | |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)


class StatsPanel:
    """GUI markdown ``stats``."""

    def __init__(self, gui: Any) -> None:
        self.markdown = gui.add_markdown(stats_markdown({}, 0.0, 0.0, None))
        self.fps = RateMeter()
        self.odometry_hz = RateMeter()
        self._text = ""

    def update(self, stats: Mapping[str, Any], lag_s: float | None, now: float | None = None) -> bool:
        fps = self.fps.update(float(stats.get("frames", 0)), now)
        hz = self.odometry_hz.update(float(stats.get("odometry_steps", 0)), now)
        text = stats_markdown(stats, fps, hz, lag_s)
        if text == self._text:
            return False
        self._text = text
        self.markdown.content = text
        return True
