"""A real hippomap server in a subprocess, for tests and benchmarks, and what talks to it.

:class:`LiveServer` runs ``python -m server`` (uvicorn on loopback, port chosen by the OS) from the
repository's checkout, so tests exercise exactly what a robot talks to, including being killed with
SIGKILL. :func:`stream_items` sends synthetic inputs (:mod:`tests.support.synthetic`) to it over
one websocket. Test scaffolding: not part of the installed packages.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

#: the repository's root: the servers run from it (cwd and PYTHONPATH), so they import this checkout
ROOT = Path(__file__).resolve().parents[2]
_BANNER = re.compile(r"hippomap server on (http://\S+)")


class LiveServer:
    """``python -m server`` on 127.0.0.1 with its own data folder and admin token (``command``: another
    program that takes the serve command's arguments, e.g. a script that patches the server first)."""

    def __init__(
        self,
        data_dir: str | Path,
        token: str = "hm_test_admin_token",
        env: dict[str, str] | None = None,
        args: list[str] | None = None,
        command: list[str] | None = None,
    ) -> None:
        self.command = command or [sys.executable, "-m", "server"]
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
            [*self.command, "--host", "127.0.0.1", "--port", "0", "--data-dir", str(self.data_dir), *self.args],
            cwd=ROOT,
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
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


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (signal 0 checks without sending anything); one of another user's
    counts as alive. Used to tell the leftovers of a stopped run from those of one still going."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def anonymous_bytes(pid: int | None = None) -> int:
    """Resident anonymous memory of process ``pid`` (None: this one), bytes: its pages that no file backs,
    which every process holds for itself (decoded frames, built tables). Pages of a mapped file (the
    grid-cell table cache, a library's code) are the page cache's, one copy for all processes, and count or
    not depending on what the process touched before, so they are left out."""
    with open(f"/proc/{pid or 'self'}/smaps_rollup") as f:
        for line in f:
            if line.startswith("Anonymous:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no Anonymous line in smaps_rollup")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS's choice)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def stream_items(url: str, token: str, session_id: str, items: tuple, window: int = 64) -> list[dict]:
    """Send ``items`` over one websocket (pipelined); returns the acks in order."""
    import asyncio

    from hippomap.client import AsyncStream

    futs = []
    async with AsyncStream(url, token, session_id, max_in_flight=window) as st:
        for it in items:
            futs.append(await (st.send_odometry(it[1]) if it[0] == "odometry" else st.send_frame(it[1], it[2])))
        return list(await asyncio.gather(*futs))
