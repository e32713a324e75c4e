"""Server settings: where data lives, and every limit the server enforces.

These are service parameters, not model parameters (those live in
``hippomap/config.py``). Every field can be set from the environment as
``HIPPOMAP_<FIELD>`` (upper case), e.g. ``HIPPOMAP_DATA_DIR=/var/lib/hippomap``; the
``serve`` command's flags override the environment.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class ServerSettings(BaseModel):
    """All settings of one server process."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    data_dir: Path = Field(
        Path("hippomap-data"), description="folder of the embedded database and the admin token file"
    )
    database: str | None = Field(
        None,
        description="database location: a SQLite file path (default <data_dir>/hippomap.sqlite3), "
        "sqlite:///path, or a PostgreSQL URL postgresql://user:password@host:port/db (several replicas may share it)",
    )
    durability: Literal["full", "normal"] = Field(
        "full",
        description="SQLite synchronous mode: 'full' fsyncs every commit (survives power loss); "
        "'normal' survives a process crash only",
    )
    # ---- limits (security) ----
    max_body_bytes: int = Field(8 << 20, ge=1024, description="largest HTTP request body or websocket message")
    max_frame_bytes: int = Field(4 << 20, ge=1024, description="largest encoded camera frame")
    max_image_side: int = Field(4096, ge=32, description="largest frame width or height, pixels")
    max_image_pixels: int = Field(8_000_000, ge=1024, description="largest frame area, pixels")
    max_odometry_batch: int = Field(10_000, ge=1, description="most readings in one odometry batch")
    rate_per_s: float = Field(500.0, gt=0, description="requests (HTTP) or messages (websocket) per second per session")
    rate_burst: float = Field(1000.0, ge=1, description="burst allowance of the per-session rate limit")
    max_pending: int = Field(
        256, ge=1, description="inputs accepted but not yet processed by the mapper before backpressure starts"
    )
    backpressure_wait_s: float = Field(
        2.0, ge=0, description="how long an HTTP ingest waits for queue room before answering 429"
    )
    max_sessions_per_token: int = Field(100, ge=1, description="live sessions one token may own")
    max_text_message_bytes: int = Field(
        2 << 20,
        ge=1024,
        description="longest websocket text message, characters (an odometry batch of 10,000 readings is about 0.7 MB)",
    )
    max_json_depth: int = Field(
        16,
        ge=4,
        description="deepest nesting of a websocket JSON message (an odometry "
        "batch needs 4); checked by a linear scan before parsing",
    )
    max_pending_bytes: int = Field(
        256 << 20,
        ge=1 << 20,
        description="decoded image bytes accepted but not yet processed by the mapper, per "
        "session, before backpressure starts (as max_pending, which counts inputs)",
    )
    # ---- physical bounds on inputs (any real robot fits; a reading outside is refused with 422) ----
    max_speed_mps: float = Field(100.0, gt=0, description="largest |v| of an odometry reading, m/s (360 km/h)")
    max_turn_rate_rad_s: float = Field(
        100.0, gt=0, description="largest |omega| of an odometry reading, rad/s (16 turns a second)"
    )
    max_increment_m: float = Field(100.0, gt=0, description="largest |dx|, |dy| of an odometry increment, metres")
    max_increment_rad: float = Field(
        6.2832, gt=0, description="largest |dtheta| of an odometry increment, rad (one full turn)"
    )
    max_time_jump_s: float = Field(
        2_592_000.0,
        gt=0,
        description="largest step of an input's timestamp ahead of the session's newest input "
        "(either kind), seconds: 30 days (a robot parked for a month resumes its session; a clock error "
        "of years is refused instead of wedging the session with 409s)",
    )
    max_abs_t: float = Field(
        1e10, gt=0, description="largest |t| of any timestamp, seconds (Unix time fits until the year 2286)"
    )
    # ---- session config overrides (see server/security/quotas.py for the safe ranges and the memory cost) ----
    max_session_grid_bytes: int = Field(
        512 << 20,
        ge=1 << 20,
        description="largest grid-cell rate tables one session's config may need, bytes "
        "(132 MB at the defaults; sessions with the same spatial geometry and seed share one copy)",
    )
    max_token_grid_bytes: int = Field(
        1 << 30,
        ge=1 << 20,
        description="grid-cell tables all the live sessions of one token may need together, "
        "bytes (each distinct spatial geometry/seed counted once)",
    )
    switch_interval_s: float = Field(
        0.0005,
        gt=0,
        le=0.1,
        description="Python's GIL switch interval in the server process: short, so the event loop (acks) is not "
        "held up for long behind a mapper thread (Python's default is 5 ms)",
    )
    fatal_exit_s: float = Field(
        1.0,
        ge=0,
        description="if the store's writer thread dies, /health and /ready answer 503 and the process "
        "exits (status 70) this many seconds later, so a supervisor restarts it (acknowledged inputs are durable)",
    )
    # ---- persistence ----
    snapshot_every_inputs: int = Field(2000, ge=1, description="snapshot the mapper after this many inputs...")
    snapshot_every_s: float = Field(60.0, gt=0, description="...or this many seconds, whichever comes first")
    keep_snapshots: int = Field(2, ge=1, description="snapshots kept per session (older ones are deleted)")
    # ---- replicas sharing one database (PostgreSQL): each session runs in the replica holding its lease ----
    replica_id: str | None = Field(
        None,
        description="this server's name in session leases; unset: the host name (stable across restarts, so a "
        "restarted server takes its sessions back at once; give replicas on one host distinct ids)",
    )
    lease_ttl_s: float = Field(
        15.0,
        gt=0,
        description="a session lease lasts this long and is renewed every third of it; a replica that "
        "stops renewing (crashed) loses its sessions to the others after at most this long",
    )
    # ---- session backend (where each session's mapper runs: server/runtime/mapper_host.py, ray_backend.py) ----
    backend: Literal["inprocess", "process", "ray"] = Field(
        "inprocess",
        description="'inprocess': every session's mapper in this process (a thread each); "
        "'process': the mappers in process_workers child processes of this server (the event loop does not share "
        "its GIL with them: more robots per server, see server/runtime/process_host.py); "
        "'ray': one Ray actor per session (needs the 'ray' extra: pip install \"hippomap[ray]\")",
    )
    mapper_slots: int = Field(
        1,
        ge=1,
        le=64,
        description="in-process backend: how many session mappers step at the same time; the others "
        "wait their turn without holding the GIL, so the event loop (which acknowledges inputs) is not starved by "
        "mapper threads (server/runtime/mapper_host.py, MapperGate)",
    )
    process_workers: int = Field(
        1,
        ge=1,
        le=256,
        description="process backend: child processes running the sessions' mappers (sessions are "
        "spread over them in turn; they share the grid-cell tables through table_cache)",
    )
    ray_address: str | None = Field(
        None,
        description="Ray cluster to join (e.g. 127.0.0.1:6379 or ray://host:10001); unset: start a local "
        "Ray on loopback inside this server",
    )
    ray_max_batch: int = Field(
        32,
        ge=1,
        description="most inputs sent to a session's actor in one call (amortises "
        "the call overhead; a query waits at most one batch)",
    )
    ray_actor_cpus: float = Field(
        0.0,
        ge=0,
        description="CPUs each session's actor reserves in Ray's scheduler (0: no reservation, actors are "
        "spread over the nodes; 1: at most one session per CPU, further sessions wait for room)",
    )
    table_cache: str | None = Field(
        None,
        description="process and Ray backends: folder where a mapper process keeps the grid-cell tables (the "
        "defaults' 132 MB, 1.4 s of CPU to build) as files it maps read-only, so the processes of a machine share "
        "one copy and a new session's actor starts without building them; unset: <data_dir>/grid-tables; 'off': "
        "each process builds its own (hippomap/grid_cells.py)",
    )
    backend_max_restarts: int = Field(
        5,
        ge=0,
        description="a session whose mapper host (actor) dies this many times in a row without "
        "progress stops with an error instead of being restored again",
    )
    # ---- auth ----
    admin_token: str | None = Field(
        None,
        description="the admin token; if unset one is generated on first start and saved in <data_dir>/admin.token",
    )
    metrics_token: str | None = Field(
        None, description="the bearer token GET /metrics requires; unset: the admin token (see metrics_public)"
    )
    metrics_public: bool = Field(
        False,
        description="serve GET /metrics without a token (it names every session: only where the network is trusted)",
    )
    allowed_origins: str = Field(
        "",
        description="comma-separated origins (scheme://host[:port]) whose web pages may open the websockets, "
        "besides the server's own host; clients that send no Origin (robots, scripts) are always allowed; '*': any",
    )
    read_rate_per_s: float = Field(
        500.0,
        gt=0,
        description="read requests (queries) per second per session and token, a budget apart from "
        "rate_per_s (ingest): a reader flooding queries cannot use up the robot's ingest budget",
    )
    read_rate_burst: float = Field(1000.0, ge=1, description="burst allowance of the read rate limit")

    @property
    def database_path(self) -> Path:
        return Path(self.database) if self.database else Path(self.data_dir) / "hippomap.sqlite3"

    @property
    def table_cache_dir(self) -> str:
        """The grid-cell table cache folder the mapper processes use (absolute), or ``"off"``: handed to them
        as it is, so that "off" also overrides a folder their own environment may name."""
        if self.table_cache == "off":
            return "off"
        return str(Path(self.table_cache or Path(self.data_dir) / "grid-tables").resolve())

    @property
    def token_file(self) -> Path:
        return Path(self.data_dir) / "admin.token"

    @classmethod
    def from_env(cls, **overrides: Any) -> "ServerSettings":
        """Defaults, then ``HIPPOMAP_*`` environment variables, then ``overrides`` (None = unset)."""
        values: dict[str, Any] = {}
        for name in cls.model_fields:
            env = os.environ.get(f"HIPPOMAP_{name.upper()}")
            if env is not None and env != "":
                values[name] = env
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls.model_validate(values)
