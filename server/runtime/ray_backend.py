"""The Ray session backend: each session's mapper in its own Ray actor (``hippomap serve --backend ray``).

Why Ray: when a fleet of robots outgrows one machine, the mappers must run on a cluster an
operator already knows how to run, not on a home-made one. The split of work:

* the **server** (this process) keeps everything about durability: it stores each input
  before acknowledging it, hands the durable inputs to the session's actor in order
  (batches of up to ``ray_max_batch`` per call, so the call overhead is shared), and writes
  the derived records and snapshot bytes the actor sends back into the shared store
  (:mod:`server.runtime.worker`). The actors need no database access and can run on any Ray node.
* an **actor** (:class:`MapperActor`) wraps an :class:`~server.runtime.mapper_host.InProcessHost`,
  so the mapper logic is the same code as the in-process backend.

An actor that dies (its process killed, its node lost) surfaces as ``RayActorError`` on the
next call; :class:`RayHost` turns it into :class:`~server.runtime.mapper_host.HostDied` and the
worker restores a new actor from the store's latest snapshot plus a replay of the stored
inputs (``restarts`` in the session's stats). Actors belong to the server that created
them: if the server dies, Ray ends them too.

``ray_address`` unset: a private local Ray is started inside the server, on loopback
(127.0.0.1), no dashboard, no usage statistics. Set: the server joins that cluster; every
node needs hippomap installed (the same image). Ray is an optional dependency (``pip install
"hippomap[ray]"``); nothing imports this module unless the Ray backend is chosen.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Iterator, TypeVar

from hippomap.config import HippomapConfig
from hippomap.grid_cells import use_table_cache
from hippomap.inputs import Frame, Odometry

from ..settings import ServerSettings
from . import model
from .mapper_host import HostDied, InProcessHost, MapperHost, RemoteHost, StepResult

T = TypeVar("T")

log = logging.getLogger("hippomap.server")

RAY_MISSING = 'the Ray backend needs Ray, which is not installed: pip install "hippomap[ray]"'
ACTOR_CONCURRENCY = 4  # a query may run while the actor processes a batch (between two inputs)


def _token_unset() -> bool:
    """A Ray token is at hand (``RAY_AUTH_TOKEN``, or the file of ``RAY_AUTH_TOKEN_PATH`` or Ray's
    default path) but ``RAY_AUTH_MODE`` does not say to use it."""
    return "RAY_AUTH_MODE" not in os.environ and bool(
        os.environ.get("RAY_AUTH_TOKEN")
        or Path(os.environ.get("RAY_AUTH_TOKEN_PATH") or "~/.ray/auth_token").expanduser().is_file()
    )


def _ray_env() -> None:
    """Environment Ray reads when it is first imported: no usage statistics; token authentication
    when a token is at hand (Ray does so by itself only for a Ray it starts, not for one it joins)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if _token_unset():
        os.environ["RAY_AUTH_MODE"] = "token"


def require_ray() -> Any:
    """The ``ray`` module, or a RuntimeError that says how to install it.

    Ray reads its authentication mode once, when it is first imported. When something else in this
    process imported Ray before the backend could set token authentication for a token at hand, Ray
    will join a cluster without it, and a cluster that requires its token refuses the connection
    with an error about an invalid token: the warning logged here names the cause."""
    if "ray" not in sys.modules:
        _ray_env()
    elif _token_unset():
        log.warning(
            "Ray was imported before the Ray backend could set RAY_AUTH_MODE=token for the Ray token at hand: "
            "a cluster that requires its token will refuse this process. Set RAY_AUTH_MODE=token before "
            "anything imports Ray."
        )
    try:
        import ray
    except ImportError as exc:
        raise RuntimeError(RAY_MISSING) from exc
    return ray


class MapperActor:
    """The Ray actor of one session: an in-process host, remotely. Its methods mirror
    :class:`~server.runtime.mapper_host.MapperHost` (called in order by the session's worker; queries
    from any thread of the server, run under the host's lock)."""

    def __init__(self, table_cache: str | None = None) -> None:
        use_table_cache(table_cache)  # the grid-cell tables of this node's earlier actors, if any
        self.host = InProcessHost()

    def restore(self, snapshot: bytes | None, config: HippomapConfig) -> dict[str, Any]:
        return self.host.restore(snapshot, config)

    def process(self, batch: list[tuple[int, Odometry | Frame]]) -> list[StepResult]:
        return self.host.process(batch)

    def snapshot(self) -> bytes:
        return self.host.snapshot()

    def query(self, query: model.queries.Query[T]) -> T | None:
        return self.host.query(query)

    def info(self) -> dict[str, Any]:
        import ray

        return {"kind": "ray", "pid": os.getpid(), "node": ray.get_runtime_context().get_node_id()}


class RayHost(RemoteHost):
    """A :class:`~server.runtime.mapper_host.MapperHost` whose mapper lives in a :class:`MapperActor`."""

    def __init__(self, backend: "RayBackend", session_id: str) -> None:
        self._ray = backend.ray
        self.session_id = session_id
        self.max_batch = backend.settings.ray_max_batch
        self.actor = backend.actor_class.options(
            num_cpus=backend.settings.ray_actor_cpus, max_concurrency=ACTOR_CONCURRENCY, scheduling_strategy="SPREAD"
        ).remote(backend.settings.table_cache_dir)
        self._info: dict[str, Any] = {"kind": "ray"}
        self._closed = False

    def _call(self, method: str, *args: Any) -> Any:
        ray = self._ray
        if self._closed:
            raise HostDied(f"the actor of session {self.session_id} was closed")
        try:
            return ray.get(getattr(self.actor, method).remote(*args))
        except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError, ray.exceptions.ObjectLostError) as exc:
            raise HostDied(f"Ray actor of session {self.session_id} died: {type(exc).__name__}") from exc

    def restore(self, snapshot: bytes | None, config: HippomapConfig) -> dict[str, Any]:
        stats = self._call("restore", snapshot, config)
        self._info = self._call("info")
        return stats

    def info(self) -> dict[str, Any]:
        return dict(self._info)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._ray.kill(self.actor, no_restart=True)
        except Exception:  # noqa: BLE001 - already gone, or Ray is shutting down
            log.debug(
                "killing the actor of session %s failed",
                self.session_id,
                exc_info=True,
                extra={"session": self.session_id},
            )


@contextlib.contextmanager
def _keep_signal_handlers() -> Iterator[None]:
    """Keep the server's SIGTERM/SIGINT handlers across ``ray.init``.

    A driver that starts a local Ray installs its own SIGTERM handler, which exits at once
    (``sys.exit(1)``): ``docker stop`` would then skip the graceful shutdown — the last
    snapshot of every session and the release of its lease. The server's own shutdown calls
    :meth:`RayBackend.shutdown`, which stops the local Ray, and Ray's atexit hook remains."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            if handler is not None:
                signal.signal(sig, handler)


class RayBackend:
    """One per server: joins (or starts) Ray and makes one :class:`RayHost` per session."""

    def __init__(self, settings: ServerSettings) -> None:
        self.ray = require_ray()
        self.settings = settings
        self.actor_class: Any = None
        self._owns_ray = False

    def start(self) -> None:
        ray = self.ray
        common = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING, namespace="hippomap")
        if not ray.is_initialized():
            with _keep_signal_handlers():
                if self.settings.ray_address:
                    log.info("joining the Ray cluster at %s", self.settings.ray_address)
                    ray.init(address=self.settings.ray_address, **common)
                else:
                    log.info("starting a local Ray on 127.0.0.1")
                    ray.init(address="local", _node_ip_address="127.0.0.1", **common)
            self._owns_ray = True
        self.actor_class = ray.remote(MapperActor)

    def factory(self, session_id: str) -> MapperHost:
        return RayHost(self, session_id)

    def shutdown(self) -> None:
        """Leave Ray (ends this server's actors; a local Ray stops)."""
        if self._owns_ray and self.ray.is_initialized():
            self.ray.shutdown()
        self._owns_ray = False
