"""Ray for tests and benchmarks: a private Ray head on loopback that the test servers join.

:func:`local_ray_head` starts one :class:`LocalRayHead` per test run (stopped at exit). With
``HIPPOMAP_TEST_RAY_DIR`` set (``tests/conftest.py`` sets it in the process that starts the test workers),
the workers share one head: the first that needs it starts it and notes it in that folder, the others join
it, and :func:`stop_shared_head` ends it when the run ends (an idle head costs a few per cent of a core);
:func:`ray_test_env` is the environment a Ray-backed test server needs to join it, and
:func:`ray_auth_env` puts the same authentication into this process for a test that joins it in process.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from .live import ROOT, pid_alive

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
            if pid_alive(creator):
                continue  # its test run is still going (or another user's)
            try:
                os.killpg(pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            shutil.rmtree(pidfile.parent, ignore_errors=True)

    def start(self, timeout: float = 120.0, owner: int | None = None) -> "LocalRayHead":
        """Start the head; ``owner``: the process whose end makes it stale for :meth:`remove_stale` (this
        one by default, which then also stops it at exit; another one stops it itself)."""
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
        env = {
            **os.environ,
            **self.env,
            "RAY_USAGE_STATS_ENABLED": "0",
            "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p),
        }
        log = open(self.root / "head.log", "w")
        self.proc = subprocess.Popen(
            [
                str(Path(sys.executable).parent / "ray"),
                "start",
                "--head",
                "--block",
                "--node-ip-address=127.0.0.1",
                f"--port={port}",
                f"--num-cpus={self.num_cpus}",
                "--include-dashboard=false",
                "--disable-usage-stats",
                f"--object-store-memory={self.object_store_bytes}",
                f"--temp-dir={self.root}",
            ],
            cwd=ROOT,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        (self.root / "creator.pid").write_text(f"{owner or os.getpid()} {self.proc.pid}")
        if owner is None:
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

        proc, root, self.proc, self.root = self.proc, self.root, None, None
        if proc is not None:
            end_group(proc.pid, proc)
        if root is not None:
            shutil.rmtree(root, ignore_errors=True)


def end_group(pgid: int, proc: subprocess.Popen | None = None) -> None:
    """SIGTERM to process group ``pgid``, SIGKILL to what is left after a few seconds; ``proc``, the
    group's leader if this process started it, is reaped on the way."""
    import time

    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 10.0)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            break
        if proc is not None:
            try:
                proc.wait(wait_s)
            except subprocess.TimeoutExpired:
                pass
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline and ray_group_alive(pgid):
            time.sleep(0.1)
        if not ray_group_alive(pgid):
            break


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


SHARED_DIR_ENV = "HIPPOMAP_TEST_RAY_DIR"  # a folder of the test run: its workers share one head
SHARED_OWNER_ENV = "HIPPOMAP_TEST_RAY_OWNER"  # the pid of the process that stops the shared head


def local_ray_head() -> LocalRayHead:
    """The Ray head of this test run: started on first use, stopped at exit (shared by the run's workers
    when ``HIPPOMAP_TEST_RAY_DIR`` is set)."""
    global _RAY_HEAD
    with _RAY_LOCK:
        if _RAY_HEAD is None or (_RAY_HEAD.proc is None and not _RAY_HEAD.address):
            shared = os.environ.get(SHARED_DIR_ENV)
            _RAY_HEAD = _shared_head(Path(shared)) if shared else LocalRayHead().start()
        return _RAY_HEAD


def _shared_head(folder: Path) -> LocalRayHead:
    """The head noted in ``folder`` if it is alive, else a new one noted there (one process at a time)."""
    import fcntl
    import json

    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        note = folder / "head.json"
        if note.exists():
            d = json.loads(note.read_text())
            if ray_group_alive(d["pgid"]):
                head = LocalRayHead()
                head.address, head.env = d["address"], d["env"]
                return head  # joined: no process or folder of its own to stop
        owner = int(os.environ.get(SHARED_OWNER_ENV) or os.getppid())
        head = LocalRayHead().start(owner=owner)
        assert head.proc is not None and head.root is not None
        d = {"address": head.address, "env": head.env, "pgid": head.proc.pid, "root": str(head.root)}
        note.write_text(json.dumps(d))
        return head


def stop_shared_head(folder: Path) -> None:
    """End the head noted in ``folder`` (its whole process group) and remove its files."""
    import json
    import shutil

    note = folder / "head.json"
    if not note.exists():
        return
    d = json.loads(note.read_text())
    end_group(d["pgid"])
    shutil.rmtree(d["root"], ignore_errors=True)
    note.unlink(missing_ok=True)


def _reload_ray_auth() -> None:
    """Make an already imported Ray read its authentication settings from the environment again.

    Ray reads ``RAY_AUTH_MODE`` and the token once and caches them. A test process that imported Ray
    before the variables were set (another test file run earlier in the same process) would otherwise
    join the head without its token and be refused. Nothing to do when Ray is not imported yet: it
    reads the environment when it is. Ray's own tests reload it this way."""
    if "ray" in sys.modules:
        from ray._private.authentication_test_utils import reset_auth_token_state

        reset_auth_token_state()


@contextlib.contextmanager
def ray_auth_env(head: LocalRayHead) -> Iterator[None]:
    """This process's environment with the head's token authentication (``head.env``), as a server
    that joins it has: for a test that joins the head in process. The environment and Ray's
    authentication state are restored on the way out."""
    saved = {k: os.environ.get(k) for k in head.env}
    os.environ.update(head.env)
    _reload_ray_auth()
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        _reload_ray_auth()


def ray_test_env(data_dir: Path) -> dict[str, str]:
    """Environment of a Ray-backed test server: join the test run's Ray head."""
    head = local_ray_head()
    return {"HIPPOMAP_RAY_ADDRESS": head.address, **head.env}
