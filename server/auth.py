"""Bearer tokens: who may do what to which session.

Three roles:

* ``admin`` — one per server (id ``admin``); a writer that may also mint writer tokens. Its
  secret comes from ``HIPPOMAP_ADMIN_TOKEN`` or is generated on the first start and saved in
  ``<data_dir>/admin.token`` (mode 0600), so a local first run needs no setup.
* ``writer`` — creates sessions and streams into them; sees only the sessions it created.
* ``viewer`` — read-only; minted by a writer, it sees that writer's sessions (or one of them).

Any session a token may not see is answered exactly like a missing one (404), so session ids
cannot be probed. Only SHA-256 hashes of secrets are stored.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import threading
import time
from pathlib import Path

from .store import SessionRecord, Store, TokenRecord

ADMIN_ID = "admin"
TOKEN_PREFIX = "hm_"


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
    """Resolves secrets to token records, with a small cache (tokens are few and rarely change)."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self._cache: dict[str, TokenRecord | None] = {}
        self._lock = threading.Lock()

    def authenticate(self, secret: str | None) -> TokenRecord | None:
        if not secret or len(secret) > 512:
            return None
        h = hash_secret(secret)
        with self._lock:
            if h in self._cache:
                return self._cache[h]
        token = self.store.token_by_hash(h)
        with self._lock:
            if token is not None:
                self._cache[h] = token
        return token

    def forget(self) -> None:
        """Drop the cache (after a token was deleted)."""
        with self._lock:
            self._cache.clear()

    def mint(self, role: str, owner: str | None, session: str | None, label: str = "") -> tuple[str, TokenRecord]:
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
        token_file.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(secret + "\n")
    return secret, created
