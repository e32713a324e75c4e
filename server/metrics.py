"""Prometheus metrics of one server process (``GET /metrics``), via ``prometheus-client``.

Why a registry per :class:`ServiceMetrics` and not the library's global one: tests and
benchmarks build several apps in one process, and a metric may be registered only once per
registry. What is measured, all labelled by session id:

* ``hippomap_inputs_total{session,kind}`` — inputs accepted (stored and acknowledged); the
  per-session input rate is ``rate(hippomap_inputs_total[1m])``;
* ``hippomap_queue_depth{session}`` — inputs acknowledged but not yet processed by the mapper;
* ``hippomap_step_seconds{session,kind}`` — histogram of the mapper's time per input;
* ``hippomap_loop_closures_total{session}`` — loop closures the map accepted;
* ``hippomap_restore_seconds{session}`` — time the last restore (snapshot + replay) took;
* ``hippomap_sessions`` and ``hippomap_ready`` (1 once no session is restoring).
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Iterable

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

#: step latency buckets (seconds): a few hundred microseconds (odometry) to a second (a large frame on a busy core)
STEP_BUCKETS = (0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)


class _LiveGauges(Collector):
    """Gauges read at scrape time from the running sessions (nothing to keep in step)."""

    def __init__(self, depths: Callable[[], dict[str, int]], ready: Callable[[], bool]) -> None:
        self._depths = depths
        self._ready = ready

    def collect(self) -> Iterable[GaugeMetricFamily]:
        depths = self._depths()
        q = GaugeMetricFamily(
            "hippomap_queue_depth", "inputs acknowledged but not yet processed by the mapper", labels=["session"]
        )
        for sid, depth in sorted(depths.items()):
            q.add_metric([sid], depth)
        yield q
        yield GaugeMetricFamily("hippomap_sessions", "live sessions", value=len(depths))
        yield GaugeMetricFamily(
            "hippomap_ready", "1 when every session is restored and serving", value=float(self._ready())
        )


class ServiceMetrics:
    """The metrics of one server; every method is thread-safe (prometheus-client's own locks)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self._inputs = Counter(
            "hippomap_inputs", "inputs accepted (stored and acknowledged)", ["session", "kind"], registry=self.registry
        )
        self._steps = Histogram(
            "hippomap_step_seconds",
            "mapper time per input",
            ["session", "kind"],
            buckets=STEP_BUCKETS,
            registry=self.registry,
        )
        self._loops = Counter(
            "hippomap_loop_closures", "loop closures accepted by the map", ["session"], registry=self.registry
        )
        self._restore = Gauge(
            "hippomap_restore_seconds",
            "duration of the session's last restore (snapshot + replay)",
            ["session"],
            registry=self.registry,
        )
        self._live: _LiveGauges | None = None
        self._lock = threading.Lock()
        # the labelled children of the per-input metrics, looked up once per (session, kind): ``labels()``
        # takes the metric's lock and builds its key on every call, and these run once per input
        self._children: dict[tuple[str, str, str], Any] = {}

    def _child(self, metric: Any, name: str, session_id: str, kind: str) -> Any:
        key = (name, session_id, kind)
        child = self._children.get(key)
        if child is None:
            child = self._children[key] = metric.labels(session_id, kind)
        return child

    # ---------------------------------------------------------------- events
    def inputs_accepted(self, session_id: str, kind: str, n: int = 1) -> None:
        self._child(self._inputs, "inputs", session_id, kind).inc(n)

    def step_observed(self, session_id: str, kind: str, seconds: float) -> None:
        self._child(self._steps, "steps", session_id, kind).observe(seconds)

    def loop_closures(self, session_id: str, n: int = 1) -> None:
        self._loops.labels(session_id).inc(n)

    def restore_observed(self, session_id: str, seconds: float) -> None:
        self._restore.labels(session_id).set(seconds)

    def forget(self, session_id: str) -> None:
        """Drop a deleted session's series (they would otherwise be exported forever)."""
        for key in [k for k in list(self._children) if k[1] == session_id]:
            self._children.pop(key, None)
        for metric, kinds in ((self._inputs, ("odometry", "frame")), (self._steps, ("odometry", "frame"))):
            for kind in kinds:
                try:
                    metric.remove(session_id, kind)
                except KeyError:
                    pass
        for series in (self._loops, self._restore):
            try:
                series.remove(session_id)
            except KeyError:
                pass

    # ---------------------------------------------------------------- export
    def track(self, depths: Callable[[], dict[str, int]], ready: Callable[[], bool]) -> None:
        """Export the live gauges: ``depths()`` → queue depth per session, ``ready()`` → readiness."""
        with self._lock:
            if self._live is not None:
                self.registry.unregister(self._live)
            self._live = _LiveGauges(depths, ready)
            self.registry.register(self._live)

    def render(self) -> tuple[bytes, str]:
        """The text exposition format and its content type."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST
