"""Helpers for tests and benchmarks: a real server in a subprocess, and synthetic robot data.

:class:`LiveServer` runs ``python -m server`` (uvicorn on loopback, port chosen by the OS)
so tests exercise exactly what a robot talks to, including being killed with SIGKILL.
:func:`synthetic_inputs` drives a robot round a circle facing a textured panorama: laps
repeat the same views, so the visual memory recognises places and closes loops.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hippomap.inputs import Odometry

ROOT = Path(__file__).resolve().parents[1]
_BANNER = re.compile(r"hippomap server on (http://\S+)")


class LiveServer:
    """``python -m server`` on 127.0.0.1 with its own data folder and admin token."""

    def __init__(self, data_dir: str | Path, token: str = "hm_test_admin_token", env: dict[str, str] | None = None,
                 args: list[str] | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.token = token
        pythonpath = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
        self.env = {**os.environ, "HIPPOMAP_ADMIN_TOKEN": token, "PYTHONPATH": pythonpath, **(env or {})}
        self.args = args or []
        self.proc: subprocess.Popen | None = None
        self.url = ""
        self.output: list[str] = []

    def start(self, timeout: float = 60.0) -> "LiveServer":
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "server", "--host", "127.0.0.1", "--port", "0", "--data-dir", str(self.data_dir),
             *self.args],
            cwd=ROOT, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        found = threading.Event()

        def pump() -> None:
            assert self.proc is not None and self.proc.stdout is not None
            for line in self.proc.stdout:
                self.output.append(line)
                m = _BANNER.search(line)
                if m and not found.is_set():
                    self.url = m.group(1)
                    found.set()
            found.set()

        threading.Thread(target=pump, daemon=True).start()
        if not found.wait(timeout) or not self.url:
            self.kill()
            raise RuntimeError("server did not start:\n" + "".join(self.output))
        return self

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs (a crash)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(30)

    def stop(self, timeout: float = 60.0) -> None:
        """SIGTERM: a graceful shutdown."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()

    def client(self, token: str | None = None) -> Any:
        from hippomap.client import Client

        return Client(self.url, token or self.token)

    def __enter__(self) -> "LiveServer":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()


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

    def server(self, data_dir: str | Path, env: dict[str, str] | None = None,
               args: list[str] | None = None) -> LiveServer:
        """A (not yet started) :class:`LiveServer` of this variant on ``data_dir``."""
        return LiveServer(data_dir, env={**self.env(data_dir), **(env or {})}, args=[*self.args, *(args or [])])

    def open_store(self, data_dir: str | Path) -> Any:
        """The store a server of this variant on ``data_dir`` uses (to inspect it directly)."""
        from .app import open_store
        from .settings import ServerSettings

        return open_store(ServerSettings(data_dir=Path(data_dir), database=self.env(data_dir).get("HIPPOMAP_DATABASE")))


# ------------------------------------------------------------------ PostgreSQL for tests
#: set to a URL of a role allowed to CREATE DATABASE (``.ci/postgres`` prints one) to use that server;
#: unset, the tests start a private cluster of their own
POSTGRES_URL_ENV = "HIPPOMAP_TEST_POSTGRES_URL"
POSTGRES_LIB = Path("/usr/lib/postgresql")  # Debian's versioned server programs: <version>/bin
_PG_LOCK = threading.Lock()
_PG_BASE_URL: str | None = None
_PG_CREATED: set[str] = set()


def postgres_bin_dir() -> Path:
    """The folder of PostgreSQL's server programs (initdb, pg_ctl): Debian's newest
    ``/usr/lib/postgresql/<version>/bin``, else wherever ``initdb`` is on the PATH."""
    import shutil

    found = [p.parent for p in POSTGRES_LIB.glob("*/bin/initdb")]
    found.sort(key=lambda b: int(b.parent.name) if b.parent.name.isdigit() else 0)
    if found:
        return found[-1]
    initdb = shutil.which("initdb")
    if initdb:
        return Path(initdb).parent
    raise RuntimeError("PostgreSQL server programs (initdb, pg_ctl) not found: install Debian's PostgreSQL "
                       "(`apt-get install -y postgresql`) or point " + POSTGRES_URL_ENV + " at a server "
                       "(`eval \"$(bash .ci/postgres)\"` does both)")


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class PostgresCluster:
    """A throwaway PostgreSQL server for tests and benchmarks: ``initdb`` in a temporary folder
    (its unix socket there too), listening on 127.0.0.1 at a free port, password login for TCP.
    Run as the ``postgres`` user when we are root (initdb refuses root). ``fsync=False`` trades
    crash safety *of the database server* for speed (tests kill hippomap, not PostgreSQL)."""

    PREFIX = "hippomap-pg-"

    def __init__(self, fsync: bool = False, bin_dir: Path | None = None) -> None:
        import secrets

        self.bin_dir = bin_dir or postgres_bin_dir()
        self.fsync = fsync
        self.password = secrets.token_hex(16)
        self.root: Path | None = None
        self.port = 0

    def _as_owner(self) -> list[str]:
        return ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []

    def _run(self, *cmd: str, timeout: float = 120) -> None:
        res = subprocess.run([*self._as_owner(), *cmd], capture_output=True, text=True, timeout=timeout)
        if res.returncode != 0:
            raise RuntimeError(f"{Path(cmd[0]).name} failed ({res.returncode}):\n{res.stdout}{res.stderr}")

    @classmethod
    def remove_stale(cls) -> None:
        """Stop and delete private clusters whose creating process is gone (killed test runs)."""
        import shutil
        import tempfile

        for pidfile in Path(tempfile.gettempdir()).glob(cls.PREFIX + "*/creator.pid"):
            try:
                pid = int(pidfile.read_text())
            except (OSError, ValueError):
                continue
            if _pid_alive(pid):
                continue
            root = pidfile.parent
            try:
                bindir = postgres_bin_dir()
                prefix = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
                subprocess.run([*prefix, str(bindir / "pg_ctl"), "-D", str(root / "data"), "-m", "immediate", "stop"],
                               capture_output=True, timeout=60)
            except (RuntimeError, OSError, subprocess.TimeoutExpired):
                pass
            shutil.rmtree(root, ignore_errors=True)

    def start(self) -> "PostgresCluster":
        import atexit
        import shutil
        import tempfile

        self.remove_stale()
        root = self.root = Path(tempfile.mkdtemp(prefix=self.PREFIX))
        (root / "creator.pid").write_text(str(os.getpid()))
        pwfile = root / "pw"
        pwfile.write_text(self.password + "\n")
        if os.geteuid() == 0:
            shutil.chown(root, "postgres", "postgres")
            shutil.chown(pwfile, "postgres", "postgres")
        pwfile.chmod(0o600)
        atexit.register(self.stop)
        self._run(str(self.bin_dir / "initdb"), "-D", str(root / "data"), "-U", "postgres", "-E", "UTF8",
                  "--auth-local=trust", "--auth-host=scram-sha-256", f"--pwfile={pwfile}", "--no-sync")
        pwfile.unlink()
        conf = ["listen_addresses = '127.0.0.1'", f"unix_socket_directories = '{root}'", "max_connections = 300",
                f"fsync = {'on' if self.fsync else 'off'}", f"full_page_writes = {'on' if self.fsync else 'off'}"]
        with open(root / "data" / "postgresql.conf", "a") as f:
            f.write("\n".join(conf) + "\n")
        for attempt in range(5):
            self.port = _free_port()
            try:
                self._run(str(self.bin_dir / "pg_ctl"), "-D", str(root / "data"), "-l", str(root / "server.log"),
                          "-o", f"-p {self.port}", "-w", "-t", "60", "start")
                return self
            except RuntimeError:  # the port was taken in between: try another
                if attempt == 4:
                    log = (root / "server.log").read_text() if (root / "server.log").exists() else ""
                    raise RuntimeError(f"PostgreSQL did not start in {root}:\n{log[-3000:]}") from None
        return self  # pragma: no cover

    def stop(self) -> None:
        import shutil

        if self.root is None:
            return
        root, self.root = self.root, None
        try:
            self._run(str(self.bin_dir / "pg_ctl"), "-D", str(root / "data"), "-m", "fast", "-w", "stop", timeout=60)
        except (RuntimeError, subprocess.TimeoutExpired):
            pass
        shutil.rmtree(root, ignore_errors=True)

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://postgres:{self.password}@127.0.0.1:{self.port}/{dbname}"


def _with_dbname(url: str, dbname: str) -> str:
    from urllib.parse import urlsplit, urlunsplit

    parts = urlsplit(url)
    return urlunsplit(parts._replace(path="/" + dbname))


def _drop_created() -> None:
    import psycopg

    if _PG_BASE_URL is None or not _PG_CREATED:
        return
    try:
        with psycopg.connect(_PG_BASE_URL, autocommit=True, connect_timeout=10) as conn:
            for name in sorted(_PG_CREATED):
                conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
    except psycopg.Error:
        pass


def postgres_test_url() -> str:
    """A PostgreSQL URL for tests whose role may create databases: ``$HIPPOMAP_TEST_POSTGRES_URL``
    if set, otherwise a private :class:`PostgresCluster` started on first use (stopped at exit)."""
    global _PG_BASE_URL
    with _PG_LOCK:
        if _PG_BASE_URL is None:
            import atexit

            env = os.environ.get(POSTGRES_URL_ENV)
            if env:
                if not env.startswith(("postgresql://", "postgres://")):
                    raise RuntimeError(f"{POSTGRES_URL_ENV} must be a postgresql:// URL")
                _PG_BASE_URL = env
                atexit.register(_drop_created)
            else:
                _PG_BASE_URL = PostgresCluster().start().url()
        return _PG_BASE_URL


def postgres_database(name: str, fresh: bool = False) -> str:
    """The URL of database ``name`` on the test server, created if missing (emptied first if
    ``fresh``). Names: lower-case letters, digits and underscores."""
    import psycopg

    if not re.fullmatch(r"[a-z_][a-z0-9_]{0,62}", name):
        raise ValueError(f"bad database name {name!r}")
    base = postgres_test_url()
    with psycopg.connect(base, autocommit=True, connect_timeout=10) as conn:
        if fresh:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        if conn.execute("SELECT 1 FROM pg_database WHERE datname=%s", (name,)).fetchone() is None:
            try:
                conn.execute(f'CREATE DATABASE "{name}"')
            except psycopg.errors.DuplicateDatabase:  # created concurrently: fine
                pass
            except psycopg.errors.UniqueViolation:
                pass
    _PG_CREATED.add(name)
    return _with_dbname(base, name)


def postgres_url_for(data_dir: str | Path, fresh: bool = False) -> str:
    """A database of its own for the server on ``data_dir``: the same folder always maps to the
    same database, so a restarted server finds its data (``fresh``: emptied first)."""
    import hashlib

    digest = hashlib.sha1(str(Path(data_dir).resolve()).encode()).hexdigest()[:24]
    return postgres_database(f"hm_{digest}", fresh=fresh)


# ------------------------------------------------------------------ Ray for tests
_RAY_LOCK = threading.Lock()
_RAY_HEAD: "LocalRayHead | None" = None


class LocalRayHead:
    """A private Ray head for tests and benchmarks: ``ray start --head --block`` on 127.0.0.1 at a free
    port, in its own process group and temporary folder, no dashboard, no usage statistics.
    :meth:`stop` ends the whole group (head services and every worker/actor process they started);
    heads left by a killed test run are stopped by the next one (:meth:`remove_stale`)."""

    PREFIX = "hippomap-ray-"

    def __init__(self, num_cpus: int = 2, object_store_bytes: int = 200_000_000) -> None:
        self.num_cpus = num_cpus
        self.object_store_bytes = object_store_bytes
        self.root: Path | None = None
        self.proc: subprocess.Popen | None = None
        self.address = ""
        self.env: dict[str, str] = {}  # what a process needs to join: token authentication

    @classmethod
    def remove_stale(cls) -> None:
        import shutil
        import tempfile

        for pidfile in Path(tempfile.gettempdir()).glob(cls.PREFIX + "*/creator.pid"):
            try:
                creator, pgid = (int(v) for v in pidfile.read_text().split())
            except (OSError, ValueError):
                continue
            try:
                os.kill(creator, 0)
                continue  # its test run is still going
            except ProcessLookupError:
                pass
            except PermissionError:
                continue
            try:
                os.killpg(pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            shutil.rmtree(pidfile.parent, ignore_errors=True)

    def start(self, timeout: float = 120.0) -> "LocalRayHead":
        import atexit
        import socket
        import tempfile
        import time

        self.remove_stale()
        # short path: Ray's unix sockets live under it (107-byte limit)
        self.root = Path(tempfile.mkdtemp(prefix=self.PREFIX))
        with socket.socket() as sk:
            sk.bind(("127.0.0.1", 0))
            port = int(sk.getsockname()[1])
        import secrets

        token = self.root / "auth_token"  # a private token: only this run's servers may join
        token.write_text(secrets.token_hex(32))
        token.chmod(0o600)
        self.env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token)}
        env = {**os.environ, **self.env, "RAY_USAGE_STATS_ENABLED": "0",
               "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
        log = open(self.root / "head.log", "w")
        self.proc = subprocess.Popen(
            [str(Path(sys.executable).parent / "ray"), "start", "--head", "--block", "--node-ip-address=127.0.0.1",
             f"--port={port}", f"--num-cpus={self.num_cpus}", "--include-dashboard=false", "--disable-usage-stats",
             f"--object-store-memory={self.object_store_bytes}", f"--temp-dir={self.root}"],
            cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        (self.root / "creator.pid").write_text(f"{os.getpid()} {self.proc.pid}")
        atexit.register(self.stop)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            text = (self.root / "head.log").read_text()
            if "Ray runtime started" in text:
                self.address = f"127.0.0.1:{port}"
                return self
            if self.proc.poll() is not None:
                break
            time.sleep(0.2)
        out = (self.root / "head.log").read_text()
        self.stop()
        raise RuntimeError("Ray head did not start:\n" + out[-3000:])

    def stop(self) -> None:
        """SIGTERM to the head's process group, SIGKILL to what is left after a few seconds."""
        import shutil
        import time

        proc, root, self.proc, self.root = self.proc, self.root, None, None
        if proc is not None:
            for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 10.0)):
                try:
                    os.killpg(proc.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    proc.wait(wait_s)
                except subprocess.TimeoutExpired:
                    pass
                deadline = time.monotonic() + wait_s
                while time.monotonic() < deadline and ray_group_alive(proc.pid):
                    time.sleep(0.1)
                if not ray_group_alive(proc.pid):
                    break
        if root is not None:
            shutil.rmtree(root, ignore_errors=True)


def ray_group_pids(pgid: int) -> list[int]:
    """Live (not zombie) processes of process group ``pgid``."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def ray_group_alive(pgid: int) -> bool:
    return bool(ray_group_pids(pgid))


def local_ray_head() -> LocalRayHead:
    """The Ray head of this test run: started on first use, stopped at exit."""
    global _RAY_HEAD
    with _RAY_LOCK:
        if _RAY_HEAD is None or _RAY_HEAD.proc is None:
            _RAY_HEAD = LocalRayHead().start()
        return _RAY_HEAD


def ray_test_env(data_dir: Path) -> dict[str, str]:
    """Environment of a Ray-backed test server: join the test run's Ray head."""
    head = local_ray_head()
    return {"HIPPOMAP_RAY_ADDRESS": head.address, **head.env}


#: every backend x store combination the service suite runs against
SERVICE_VARIANTS: list[ServiceVariant] = [
    ServiceVariant("inprocess-sqlite"),
    ServiceVariant("ray-sqlite", args=("--backend", "ray"), env_for=ray_test_env),
    ServiceVariant("inprocess-postgres", env_for=lambda d: {"HIPPOMAP_DATABASE": postgres_url_for(d)}),
    # the scale-out deployment (docker/compose.yml, profile "scale"): Ray actors + the shared store
    ServiceVariant("ray-postgres", args=("--backend", "ray"),
                   env_for=lambda d: {**ray_test_env(d), "HIPPOMAP_DATABASE": postgres_url_for(d)}),
]


@lru_cache(maxsize=4)
def panorama(seed: int = 0, width: int = 2400, height: int = 240) -> np.ndarray:
    """A 360-degree gray panorama with smooth shading and many high-contrast shapes (corners)."""
    import cv2

    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.random((6, width // 40)).astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
    img = np.clip(60 + 120 * base, 0, 255).astype(np.uint8)
    for _ in range(width // 12):
        x, y = int(rng.integers(0, width - 30)), int(rng.integers(0, height - 30))
        w, h = int(rng.integers(8, 40)), int(rng.integers(8, 40))
        g = int(rng.integers(0, 256))
        if rng.random() < 0.6:
            cv2.rectangle(img, (x, y), (x + w, y + h), g, -1)
        else:
            cv2.circle(img, (x + w // 2, y + h // 2), max(w, h) // 2, g, -1)
    return img


def view(heading: float, seed: int = 0, width: int = 320) -> np.ndarray:
    """The camera image facing ``heading`` (radians): a window of the panorama."""
    pano = panorama(seed)
    W = pano.shape[1]
    x0 = int(round((heading % (2 * np.pi)) / (2 * np.pi) * W))
    return np.take(pano, np.arange(x0, x0 + width), axis=1, mode="wrap")


@lru_cache(maxsize=8)
def synthetic_inputs(n_odometry: int = 400, rate_hz: float = 20.0, frame_every: int = 4, speed: float = 0.5,
                     radius: float = 1.0, seed: int = 0, quality: int = 85) -> tuple[tuple, ...]:
    """Inputs of a robot circling (``speed`` m/s, ``radius`` m): ``("odometry", Odometry)`` and
    ``("frame", t, jpeg)`` items in strictly increasing time order; a frame follows every
    ``frame_every``-th reading by half a period."""
    import cv2

    dt = 1.0 / rate_hz
    omega = speed / radius
    out: list[tuple] = []
    for k in range(n_odometry):
        t = round((k + 1) * dt, 6)
        out.append(("odometry", Odometry(t, v=speed, omega=omega)))
        if k % frame_every == 0:
            tf = round(t + dt / 2, 6)
            ok, buf = cv2.imencode(".jpg", view(omega * tf, seed), [cv2.IMWRITE_JPEG_QUALITY, quality])
            out.append(("frame", tf, buf.tobytes()))
    return tuple(out)


def decoded(items: tuple) -> list:
    """The inputs as the mapper takes them (frames decoded like the server does)."""
    from hippomap.inputs import Frame, decode_jpeg

    return [it[1] if it[0] == "odometry" else Frame(it[1], decode_jpeg(it[2])) for it in items]


def offline_reference(items: tuple, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a session fed ``items`` must report: the same mapper run in-process, through the
    server's own query functions and a JSON round trip (as a client sees it)."""
    import json

    from hippomap.inputs import Odometry as _Odo

    from . import model

    m = model.new_mapper(model.effective_config(overrides))
    for value in decoded(items):
        (m.step if isinstance(value, _Odo) else m.observe)(value)
    out = {"map": model.graph(m), "stats": model.stats(m),
           "loop_closures": [r["decision"] for r in model.loop_closures(m)],
           "recognitions": model.recognitions(m, -1, 10**9)}
    return json.loads(json.dumps(model.json_safe(out)))


def session_state(client: Any, session_id: str) -> dict[str, Any]:
    """The same four things, as the server reports them (after it has processed everything)."""
    client.wait_processed(session_id)
    return {"map": client.map(session_id), "stats": client.stats(session_id)["mapper"],
            "loop_closures": [r["decision"] for r in client.loop_closures(session_id, limit=10_000)],
            "recognitions": [client.saccades(session_id, r["id"])
                             for r in client.recognitions(session_id, limit=10_000)]}


async def stream_items(url: str, token: str, session_id: str, items: tuple, window: int = 64) -> list[dict]:
    """Send ``items`` over one websocket (pipelined); returns the acks in order."""
    import asyncio

    from hippomap.client import AsyncStream

    futs = []
    async with AsyncStream(url, token, session_id, max_in_flight=window) as st:
        for it in items:
            futs.append(await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2])))
        return list(await asyncio.gather(*futs))
