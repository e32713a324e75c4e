"""Limits that protect the server: request rate per session and request body size.

* :class:`TokenBucket` — a session's request budget. HTTP requests over budget are answered
  429 with ``Retry-After``; websocket messages over budget are simply read later (the
  robot is slowed by TCP backpressure, nothing is dropped).
* :class:`KeyedBuckets` — read budgets, one per session and token, apart from the session's ingest
  budget: a reader flooding queries gets 429 itself and never uses up the robot's budget.
* :class:`OriginCheck` — ASGI middleware refusing websockets opened by web pages of other origins.
* :class:`BodySizeLimit` — ASGI middleware answering 413 for a body over ``max_bytes``,
  from ``Content-Length`` up front or while a chunked body streams in, before any route
  reads it.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict
from typing import Any, Hashable
from urllib.parse import urlsplit

from starlette.exceptions import HTTPException

log = logging.getLogger("hippomap.server")


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up. Thread-safe."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self._tokens = float(burst)
        self._t = time.monotonic()
        self._lock = threading.Lock()

    def _refill(self) -> None:
        now = time.monotonic()
        self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate)
        self._t = now

    def take(self, n: float = 1.0) -> float:
        """Take ``n`` tokens if available: returns 0. Otherwise takes none and returns the
        seconds until they will be."""
        with self._lock:
            self._refill()
            if self._tokens >= n:
                self._tokens -= n
                return 0.0
            return (n - self._tokens) / self.rate

    def reserve(self, n: float = 1.0) -> float:
        """Take ``n`` tokens now, going into debt if needed; returns the seconds to wait
        before acting (used to pace websocket messages)."""
        with self._lock:
            self._refill()
            self._tokens -= n
            return 0.0 if self._tokens >= 0 else -self._tokens / self.rate


class KeyedBuckets:
    """One :class:`TokenBucket` per key (e.g. ``(session, token)`` for reads), created on first use;
    at most ``max_keys`` are kept (the least recently used one is dropped first). Thread-safe."""

    def __init__(self, rate: float, burst: float, max_keys: int = 10_000) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self.max_keys = int(max_keys)
        self._buckets: OrderedDict[Hashable, TokenBucket] = OrderedDict()
        self._lock = threading.Lock()

    def take(self, key: Hashable, n: float = 1.0) -> float:
        """As :meth:`TokenBucket.take` on ``key``'s bucket."""
        with self._lock:
            bucket = self._buckets.get(key)
            if bucket is None:
                bucket = self._buckets[key] = TokenBucket(self.rate, self.burst)
                while len(self._buckets) > self.max_keys:
                    self._buckets.popitem(last=False)
            else:
                self._buckets.move_to_end(key)
        return bucket.take(n)


def _host_port(netloc: str, scheme: str) -> tuple[str, int | None]:
    """``(host, port)`` of ``host[:port]`` (IPv6 in brackets), the scheme's default port if none."""
    netloc = netloc.strip().lower()
    host, sep, port = netloc.rpartition(":")
    if not sep or "]" in port:  # no port (or the colon was inside an IPv6 literal)
        host, port = netloc, ""
    default = {"http": 80, "ws": 80, "https": 443, "wss": 443}.get(scheme)
    try:
        return host, int(port) if port else default
    except ValueError:
        return host, None


class OriginCheck:
    """ASGI middleware: a websocket whose ``Origin`` is neither the server's own host (the ``Host``
    header) nor in ``allowed`` is refused before it opens (HTTP 403). A websocket without
    ``Origin`` is accepted: robots and scripts send none, browsers always do, so a web page on
    another site can never drive a browser's cookies or stored tokens into the service's sockets.
    ``"*"`` in ``allowed`` accepts any origin."""

    def __init__(self, app: Any, allowed: str | list[str] = "") -> None:
        self.app = app
        items = allowed.split(",") if isinstance(allowed, str) else list(allowed)
        self.any = any(i.strip() == "*" for i in items)
        self.allowed = {self._origin_key(i.strip()) for i in items if i.strip() and i.strip() != "*"}

    @staticmethod
    def _origin_key(origin: str) -> tuple[str, str, int | None]:
        parts = urlsplit(origin.strip())
        scheme = parts.scheme.lower()
        host, port = _host_port(parts.netloc, scheme)
        return scheme, host, port

    def allows(self, origin: str | None, host: str | None) -> bool:
        if origin is None or self.any:
            return True
        scheme, o_host, o_port = self._origin_key(origin)
        if not o_host or scheme not in ("http", "https"):
            return False  # "null" (sandboxed pages, files) or anything else not a web origin
        if (scheme, o_host, o_port) in self.allowed:
            return True
        if host:  # the page was served by this server: same host and port (the port the client used)
            h_host, h_port = _host_port(host, scheme)
            return h_host == o_host and h_port == o_port
        return False

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] == "websocket":
            headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
            origin = headers.get("origin")
            if not self.allows(origin, headers.get("host")):
                log.warning(
                    "websocket %s refused: Origin %r is not allowed (allowed_origins)",
                    scope.get("path", ""),
                    origin[:200] if origin else origin,
                )
                await receive()  # websocket.connect
                await send({"type": "websocket.close", "code": 1008, "reason": "origin not allowed"})
                return
        await self.app(scope, receive, send)


class _TooLarge(HTTPException):
    """Raised from ``receive`` mid-body; an HTTPException so FastAPI passes it through as 413."""

    def __init__(self, detail: str) -> None:
        super().__init__(status_code=413, detail=detail)


class BodySizeLimit:
    """ASGI middleware: HTTP request bodies over ``max_bytes`` get 413 naming the limit.

    The rest of an oversize body is read and discarded (up to ``drain_bytes``) before the
    answer goes out: a client still uploading would otherwise see a reset connection
    instead of the 413."""

    def __init__(self, app: Any, max_bytes: int, drain_bytes: int | None = None) -> None:
        self.app = app
        self.max_bytes = int(max_bytes)
        self.drain_bytes = int(drain_bytes if drain_bytes is not None else max(64 << 20, 4 * self.max_bytes))

    async def _drain(self, receive: Any, seen: int) -> bool:
        """Discard the body; False if it is larger than ``drain_bytes`` (then the connection is closed)."""
        while seen <= self.drain_bytes:
            message = await receive()
            if message["type"] != "http.request":
                return False
            seen += len(message.get("body", b""))
            if not message.get("more_body", False):
                return True
        return False

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    length = int(value)
                except ValueError:
                    await self._reject(send, 400, "Content-Length is not an integer", close=True)
                    return
                if length > self.max_bytes:
                    drained = length <= self.drain_bytes and await self._drain(receive, 0)
                    await self._reject(send, 413, self._message(length), close=not drained)
                    return
        seen = 0
        started = False

        async def limited_receive() -> dict:
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:
                    if message.get("more_body", False):
                        await self._drain(receive, seen)
                    raise _TooLarge(self._message(None))
            return message

        async def tracking_send(message: dict) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _TooLarge as exc:
            if not started:
                await self._reject(send, 413, str(exc.detail), close=False)

    def _message(self, length: int | None) -> str:
        got = f" ({length} bytes)" if length is not None else ""
        return f"request body too large{got}: the limit is {self.max_bytes} bytes"

    @staticmethod
    async def _reject(send: Any, status: int, detail: str, close: bool) -> None:
        body = json.dumps({"detail": detail}).encode()
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
        if close:
            headers.append((b"connection", b"close"))
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
