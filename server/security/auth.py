"""Bearer tokens: who may do what to which session.

Three roles:

* ``admin`` — one per server (id ``admin``); a writer that may also mint writer tokens. Its
  secret comes from ``HIPPOMAP_ADMIN_TOKEN`` or is generated on the first start and saved in
  ``<data_dir>/admin.token`` (mode 0600), so a local first run needs no setup.
* ``writer`` — creates sessions and streams into them; sees only the sessions it created.
* ``viewer`` — read-only; minted by a writer, it sees that writer's sessions (or one of them).

Revoking a token (``DELETE /tokens/{id}``, by the token that minted it) also revokes every token
it minted, and the sessions it owned pass to the revoker: a revoked writer's viewer tokens stop
working at once, and its sessions stay reachable (listed, readable, deletable) by the admin.
Websockets opened with a revoked token are closed (:class:`CloseOnRevoke`).

Any session a token may not see is answered exactly like a missing one (404), so session ids
cannot be probed. Only SHA-256 hashes of secrets are stored.
"""

from __future__ import annotations

import asyncio
import hashlib
import os
import secrets
import threading
import time
from http.cookies import CookieError, SimpleCookie
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

from ..storage.store import Role, SessionRecord, Store, TokenRecord

ADMIN_ID = "admin"
TOKEN_PREFIX = "hm_"
VIEWER_COOKIE = "hippomap_viewer"  #: the viewer's cookie holding a token (web/routes.py)


def new_secret() -> str:
    """A fresh token secret (256 bits, URL-safe)."""
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def new_token_id() -> str:
    return "tok_" + secrets.token_hex(6)


def can_read(token: TokenRecord, session: SessionRecord) -> bool:
    """Owners read their sessions; a viewer reads its writer's sessions (or its one session)."""
    if token.role == "viewer":
        return session.owner == token.owner and (token.session is None or token.session == session.id)
    return session.owner == token.id


def can_write(token: TokenRecord, session: SessionRecord) -> bool:
    return token.role != "viewer" and session.owner == token.id


class Authenticator:
    """Resolves secrets to token records, with a small cache (tokens are few and rarely change).

    A cached token is trusted for ``cache_ttl_s`` at most: a token revoked through another replica
    sharing the database stops working here within that time (through this one, at once)."""

    def __init__(self, store: Store, cache_ttl_s: float = 5.0, max_cached: int = 10_000) -> None:
        self.store = store
        self.cache_ttl_s = float(cache_ttl_s)
        self.max_cached = int(max_cached)
        self._cache: dict[str, tuple[TokenRecord, float]] = {}
        self._lock = threading.Lock()

    def authenticate(self, secret: str | None) -> TokenRecord | None:
        if not secret or len(secret) > 512:
            return None
        h = hash_secret(secret)
        now = time.monotonic()
        with self._lock:
            hit = self._cache.get(h)
            if hit is not None and hit[1] > now:
                return hit[0]
        token = self.store.token_by_hash(h)
        with self._lock:
            if token is None:
                self._cache.pop(h, None)
            else:
                if len(self._cache) >= self.max_cached:
                    self._cache.clear()
                self._cache[h] = (token, now + self.cache_ttl_s)
        return token

    def forget(self) -> None:
        """Drop the cache (after a token was deleted)."""
        with self._lock:
            self._cache.clear()

    def mint(self, role: Role, owner: str | None, session: str | None, label: str = "") -> tuple[str, TokenRecord]:
        """Create and store a token; returns the secret (shown once) and its record."""
        secret = new_secret()
        rec = TokenRecord(id=new_token_id(), role=role, owner=owner, session=session, label=label, created=time.time())
        self.store.add_token(hash_secret(secret), rec).result()
        return secret, rec


def ensure_admin(store: Store, token_file: Path, configured: str | None) -> tuple[str, bool]:
    """Make sure the admin token exists; returns ``(secret, newly_created)``.

    The admin keeps the id ``admin`` across secret changes, so its sessions survive a rotation:
    a configured secret (or the token file's) replaces a different stored one.
    """
    created = False
    secret = configured
    if not secret and token_file.is_file():
        secret = token_file.read_text().strip() or None
    if not secret:
        secret = new_secret()
        created = True
    h = hash_secret(secret)
    current = store.token_by_hash(h)
    if current is None or current.id != ADMIN_ID:
        store.delete_token(ADMIN_ID).result()
        store.add_token(h, TokenRecord(id=ADMIN_ID, role="admin", label="admin", created=time.time())).result()
    if not configured and (created or not token_file.is_file()):
        token_file.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(secret + "\n")
    return secret, created


def adopt_orphans(store: Store) -> dict[str, list[str]]:
    """Sessions whose owner token no longer exists (revoked before revocation handed them on) go to
    the admin, and the viewer tokens that owner minted are revoked. Returns ``{old owner: session ids}``."""
    known = {t.id for t in store.list_tokens(ADMIN_ID)} | {ADMIN_ID}
    orphaned: dict[str, list[str]] = {}
    for rec in store.list_sessions():
        if rec.owner not in known:
            orphaned.setdefault(rec.owner, []).append(rec.id)
    for owner in orphaned:
        store.revoke_token(owner, ADMIN_ID).result()
    return orphaned


def websocket_secret(scope: dict[str, Any]) -> str | None:
    """The token a websocket was opened with, looked up as the routes do: ``Authorization: Bearer``,
    then the ``token`` query parameter, then the viewer's cookie."""
    headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer ") and auth[7:].strip():
        return auth[7:].strip()
    query = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token")
    if query and query[0]:
        return query[0]
    cookies = SimpleCookie()
    try:
        cookies.load(headers.get("cookie", ""))
    except CookieError:
        return None
    morsel = cookies.get(VIEWER_COOKIE)
    return morsel.value if morsel is not None and morsel.value else None


class CloseOnRevoke:
    """ASGI middleware: a websocket opened with a valid token is closed (code 4401, "token revoked")
    once that token is revoked, at its next message either way or, on an idle socket, within
    ``check_every_s`` (checked at most every ``check_every_s``; the token cache makes a
    revocation through this replica visible at once, through another replica within the
    cache's lifetime). Without it a revoked robot could keep
    streaming, and a revoked viewer keep watching, over sockets opened before the revocation."""

    def __init__(self, app: Any, check_every_s: float = 1.0) -> None:
        self.app = app
        self.check_every_s = float(check_every_s)

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        """Wrap a websocket's ``receive`` and ``send`` with the revocation check. One function on purpose: the
        wrappers and the idle watcher share one socket's state (closed, last checked, the send lock) as
        closures, which is what keeps that state per connection."""
        if scope["type"] != "websocket":
            await self.app(scope, receive, send)
            return
        auth = getattr(getattr(scope.get("app"), "state", None), "auth", None)
        secret = websocket_secret(scope)
        if auth is None or not secret or auth.authenticate(secret) is None:
            await self.app(scope, receive, send)  # the route refuses it as usual
            return
        closed = False
        checked = time.monotonic()

        async def close_if_revoked() -> bool:
            nonlocal closed, checked
            if closed:
                return True
            now = time.monotonic()
            if now - checked < self.check_every_s:
                return False
            checked = now
            if auth.authenticate(secret) is not None:
                return False
            closed = True
            await send({"type": "websocket.close", "code": 4401, "reason": "token revoked"})
            return True

        lock = asyncio.Lock()  # one send at a time: the app's and the watcher's
        watcher: asyncio.Task[None] | None = None

        async def watch() -> None:
            # an idle socket (a viewer whose scene does not change, a robot that stopped sending)
            # carries no message to check at: look every check_every_s all the same
            while not closed:
                await asyncio.sleep(self.check_every_s)
                async with lock:
                    if await close_if_revoked():
                        return

        async def guarded_send(message: dict[str, Any]) -> None:
            nonlocal watcher
            async with lock:
                if closed or (message["type"] == "websocket.send" and await close_if_revoked()):
                    return  # the socket is closed: nothing more goes out
                await send(message)
            if message["type"] == "websocket.accept" and watcher is None:
                watcher = asyncio.create_task(watch())

        async def guarded_receive() -> dict[str, Any]:
            message = await receive()
            if message["type"] == "websocket.receive":
                async with lock:
                    revoked = await close_if_revoked()
                if revoked:
                    return {"type": "websocket.disconnect", "code": 4401}
            return message

        try:
            await self.app(scope, guarded_receive, guarded_send)
        finally:
            if watcher is not None:
                watcher.cancel()
