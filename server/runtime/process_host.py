"""The process session backend: every session's mapper in a child process of the server.

Why: a mapper step is mostly Python, so in-process mappers (:class:`~server.runtime.mapper_host.InProcessHost`,
threads) share the server's GIL with the event loop that reads, stores and acknowledges every
input; past about a dozen robots on two cores the loop queues for the GIL behind the mappers.
Here the mappers run in ``workers`` child processes (each with its own GIL; its sessions share its
grid-cell tables, mapped from the ``table_cache`` folder that all children share); the server keeps
everything about durability, as
with Ray (:mod:`server.runtime.ray_backend`), and hands each session's durable inputs to its child in
batches (``host.max_batch``) over a pipe.

A child runs :class:`~server.runtime.mapper_host.InProcessHost` objects, one per session, so the mapper
logic is the same code as the in-process backend. Requests to one child are served one at a
time (a query waits for the batch being processed: between two batches, never inside one).
Queries are typed values (:mod:`hippomap.mapper_queries`), checked before they are sent and
pickled by the standard library like every request. A child that dies (killed,
out of memory) surfaces as :class:`~server.runtime.mapper_host.HostDied` on its sessions' next call; the
next host made for one of them starts a new child, and the worker restores the session from the
store (snapshot + replay), as for a dead Ray actor.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import pickle
import threading
from typing import Any, TypeVar

from hippomap.config import HippomapConfig
from hippomap.grid_cells import use_table_cache

from .mapper_host import HostDied, InProcessHost, MapperHost, RemoteHost

T = TypeVar("T")

log = logging.getLogger("hippomap.server")


def _child_main(conn: Any, table_cache: str | None = None) -> None:
    """A child's loop: ``(op, session, args)`` requests in, ``("ok", result)`` / ``("err", exc)`` out.
    ``table_cache``: the folder of the grid-cell tables shared with the other mapper processes."""
    import signal

    use_table_cache(table_cache)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the server ends its children (Ctrl-C reaches the whole group)
    hosts: dict[str, InProcessHost] = {}
    host: InProcessHost | None
    while True:
        try:
            op, sid, args = pickle.loads(conn.recv_bytes())
        except (EOFError, OSError):  # the server is gone
            return
        try:
            if op == "restore":
                old = hosts.pop(sid, None)
                if old is not None:
                    old.close()
                host = hosts[sid] = InProcessHost()
                res: Any = host.restore(*args)
            elif op == "process":
                res = hosts[sid].process(args)
            elif op == "snapshot":
                res = hosts[sid].snapshot()
            elif op == "query":
                host = hosts.get(sid)
                res = None if host is None else host.query(args)
            elif op == "close":
                host = hosts.pop(sid, None)
                if host is not None:
                    host.close()
                res = None
            elif op == "pid":
                res = os.getpid()
            else:
                raise ValueError(f"unknown request {op!r}")
            reply = ("ok", res)
        except Exception as exc:  # noqa: BLE001 - the server re-raises it for the caller
            reply = ("err", exc)
        try:
            data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # noqa: BLE001 - an unpicklable result or exception
            data = pickle.dumps(("err", RuntimeError(f"{op} result cannot be sent back: {type(exc).__name__}: {exc}")))
        conn.send_bytes(data)


class _Child:
    """One child process and the pipe to it; one request at a time."""

    def __init__(self, ctx: Any, table_cache: str | None = None) -> None:
        parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=_child_main, args=(child, table_cache), name="hippomap-mappers", daemon=True)
        self.proc.start()
        child.close()
        self.conn = parent
        self.lock = threading.Lock()
        self.dead = False

    def call(self, op: str, sid: str, args: Any) -> Any:
        with self.lock:
            if self.dead:
                raise HostDied(f"the mapper process {self.proc.pid} has stopped")
            try:
                self.conn.send_bytes(pickle.dumps((op, sid, args), protocol=pickle.HIGHEST_PROTOCOL))
                status, res = pickle.loads(self.conn.recv_bytes())
            except (EOFError, OSError) as exc:
                self.dead = True
                raise HostDied(f"the mapper process {self.proc.pid} died ({type(exc).__name__})") from exc
        if status == "err":
            raise res
        return res

    def stop(self) -> None:
        with self.lock:
            self.dead = True
            try:
                self.conn.close()
            except OSError:
                pass
        self.proc.join(10)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(10)


class ProcessHost(RemoteHost):
    """A :class:`~server.runtime.mapper_host.MapperHost` whose mapper lives in a child process."""

    def __init__(self, session_id: str, child: _Child, max_batch: int) -> None:
        self.session_id = session_id
        self.child = child
        self.max_batch = max_batch
        self._closed = False

    def _call(self, op: str, *args: Any) -> Any:
        if self._closed:
            raise HostDied(f"the host of session {self.session_id} was closed")
        return self.child.call(op, self.session_id, args[0] if len(args) == 1 else (args or None))

    def restore(self, snapshot: bytes | None, config: HippomapConfig) -> dict[str, Any]:
        return self._call("restore", (snapshot, config))

    def info(self) -> dict[str, Any]:
        return {"kind": "process", "pid": self.child.proc.pid}

    def close(self) -> None:
        if self._closed:
            return
        try:
            self._call("close")
        except Exception:  # noqa: BLE001 - the child is gone already
            pass
        self._closed = True


class ProcessBackend:
    """One per server: ``workers`` child processes; sessions are spread over them in turn."""

    def __init__(self, workers: int = 1, max_batch: int = 32, table_cache: str | None = None) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self.max_batch = max_batch
        self.table_cache = table_cache
        self._ctx = mp.get_context("spawn")  # never fork a threaded server
        self._children: list[_Child | None] = [None] * workers
        self._lock = threading.Lock()
        self._next = 0

    def start(self) -> None:
        with self._lock:
            for i in range(self.workers):
                self._children[i] = _Child(self._ctx, self.table_cache)

    def _child(self) -> _Child:
        with self._lock:
            i = self._next % self.workers
            self._next += 1
            child = self._children[i]
            if child is None or child.dead or not child.proc.is_alive():
                if child is not None:
                    log.warning("mapper process %s stopped; starting a new one", child.proc.pid)
                    child.dead = True
                child = self._children[i] = _Child(self._ctx, self.table_cache)
            return child

    def factory(self, session_id: str) -> MapperHost:
        return ProcessHost(session_id, self._child(), self.max_batch)

    def shutdown(self) -> None:
        with self._lock:
            children, self._children = self._children, [None] * self.workers
        for child in children:
            if child is not None:
                child.stop()
