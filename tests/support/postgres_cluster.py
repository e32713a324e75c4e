"""PostgreSQL for tests and benchmarks: a throwaway cluster, and a database of its own per server.

:func:`postgres_test_url` is ``$HIPPOMAP_TEST_POSTGRES_URL`` when set, else the URL of a private
:class:`PostgresCluster` started on first use; :func:`postgres_url_for` maps a server's data folder
to a database of its own on it (the same folder, the same database: a restarted server finds its data).
"""

from __future__ import annotations

import os
import re
import subprocess
import threading
from pathlib import Path

from .live import free_port, pid_alive

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
    raise RuntimeError(
        "PostgreSQL server programs (initdb, pg_ctl) not found: install Debian's PostgreSQL "
        "(`apt-get install -y postgresql`) or point " + POSTGRES_URL_ENV + " at a server "
        '(`eval "$(bash .ci/postgres)"` does both)'
    )


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
            if pid_alive(pid):
                continue
            root = pidfile.parent
            try:
                bindir = postgres_bin_dir()
                prefix = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
                subprocess.run(
                    [*prefix, str(bindir / "pg_ctl"), "-D", str(root / "data"), "-m", "immediate", "stop"],
                    capture_output=True,
                    timeout=60,
                )
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
        self._run(
            str(self.bin_dir / "initdb"),
            "-D",
            str(root / "data"),
            "-U",
            "postgres",
            "-E",
            "UTF8",
            "--auth-local=trust",
            "--auth-host=scram-sha-256",
            f"--pwfile={pwfile}",
            "--no-sync",
        )
        pwfile.unlink()
        conf = [
            "listen_addresses = '127.0.0.1'",
            f"unix_socket_directories = '{root}'",
            "max_connections = 300",
            f"fsync = {'on' if self.fsync else 'off'}",
            f"full_page_writes = {'on' if self.fsync else 'off'}",
        ]
        with open(root / "data" / "postgresql.conf", "a") as f:
            f.write("\n".join(conf) + "\n")
        for attempt in range(5):
            self.port = free_port()
            try:
                self._run(
                    str(self.bin_dir / "pg_ctl"),
                    "-D",
                    str(root / "data"),
                    "-l",
                    str(root / "server.log"),
                    "-o",
                    f"-p {self.port}",
                    "-w",
                    "-t",
                    "60",
                    "start",
                )
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
