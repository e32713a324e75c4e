"""The service variants the service suite runs against: each session backend x store.

A :class:`ServiceVariant` is one way to run the service under test (backend arguments, and the
environment that points a server at its store); :data:`SERVICE_VARIANTS` lists them and
``tests/conftest.py`` parametrises the ``variant`` fixture over them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from .live import LiveServer
from .postgres_cluster import postgres_url_for
from .ray_head import ray_test_env


@dataclass(frozen=True)
class ServiceVariant:
    """One way to run the service under test: a session backend and a store.

    The service suite (tests/test_server_live.py, test_server_crash.py, test_client_replay.py)
    runs once per entry of :data:`SERVICE_VARIANTS` through the ``variant`` fixture, so every
    backend and store passes the same tests. ``env_for(data_dir)`` gives the environment that
    points a server at its store (e.g. a PostgreSQL database of its own for that data folder);
    it must return the same store for the same folder, so a restarted server finds its data."""

    name: str
    args: tuple[str, ...] = ()
    env_for: Callable[[Path], dict[str, str]] | None = field(default=None, compare=False)

    def env(self, data_dir: str | Path) -> dict[str, str]:
        return self.env_for(Path(data_dir)) if self.env_for is not None else {}

    def server(
        self, data_dir: str | Path, env: dict[str, str] | None = None, args: list[str] | None = None
    ) -> LiveServer:
        """A (not yet started) :class:`LiveServer` of this variant on ``data_dir``."""
        return LiveServer(data_dir, env={**self.env(data_dir), **(env or {})}, args=[*self.args, *(args or [])])

    def open_store(self, data_dir: str | Path) -> Any:
        """The store a server of this variant on ``data_dir`` uses (to inspect it directly)."""
        from server.app import open_store
        from server.settings import ServerSettings

        return open_store(ServerSettings(data_dir=Path(data_dir), database=self.env(data_dir).get("HIPPOMAP_DATABASE")))


#: every backend x store combination the service suite runs against
SERVICE_VARIANTS: list[ServiceVariant] = [
    ServiceVariant("inprocess-sqlite"),
    ServiceVariant("ray-sqlite", args=("--backend", "ray"), env_for=ray_test_env),
    ServiceVariant("inprocess-postgres", env_for=lambda d: {"HIPPOMAP_DATABASE": postgres_url_for(d)}),
    # the scale-out deployment (docker/compose.yml, profile "scale"): Ray actors + the shared store
    ServiceVariant(
        "ray-postgres",
        args=("--backend", "ray"),
        env_for=lambda d: {**ray_test_env(d), "HIPPOMAP_DATABASE": postgres_url_for(d)},
    ),
]
