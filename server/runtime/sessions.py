"""Live sessions: ordering, durability before acknowledgement, backpressure, restore.

The path of an input (HTTP or websocket alike), all on the event loop except the commit:

1. validated by :mod:`server.formats.ingest` (nothing stored yet);
2. :meth:`LiveSession.submit` (:mod:`server.runtime.live_session`) — under the session's ingest lock: the
   timestamp must exceed the last accepted one of the same kind (409 otherwise; the mapper's rule), room must
   exist in the mapper queue (``max_pending``; HTTP waits up to ``backpressure_wait_s`` then gets 429, the
   websocket waits), then sequence numbers are assigned and the write is queued to the store;
3. the store commits (group commit) and, in commit order, hands the inputs to the
   session's worker; only then is the future the caller awaits complete — the
   acknowledgement always follows durability.

:class:`SessionManager` creates, lists, finds (with the token rules of :mod:`server.security.auth`),
deletes and, at start-up, restores every stored session.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
import socket
import threading
import time
from typing import Any

from pydantic import ValidationError

from hippomap.config import HippomapConfig
from hippomap.errors import InputError

from ..formats.ingest import IngestError, pydantic_message
from ..metrics import ServiceMetrics
from ..security.auth import can_read, can_write
from ..security.quotas import MAX_OVERRIDES_CHARS, ConfigRejected, check_config, check_token_quota
from ..settings import ServerSettings
from ..storage.store import InputRecord, SessionRecord, Store, TokenRecord
from . import model
from .live_session import LiveSession, NotFound, release_memory
from .loop_calls import LoopCalls
from .mapper_host import HostFactory, MapperGate, gated_factory

log = logging.getLogger("hippomap.server")

# LiveSession, NotFound and release_memory live in .live_session; their callers import them from here
__all__ = [
    "EXIT_STORE_DEAD",
    "Forbidden",
    "LiveSession",
    "NotFound",
    "ServedElsewhere",
    "SessionManager",
    "exit_process",
    "release_memory",
]


#: exit status of a server whose store's writer died (EX_SOFTWARE)
EXIT_STORE_DEAD = 70


def exit_process(code: int) -> None:
    """End the process at once (no graceful shutdown: it would wait for writes that cannot happen)."""
    logging.shutdown()
    os._exit(code)


class Forbidden(Exception):
    """The token may see the session but not change it (a viewer token)."""


class ServedElsewhere(Exception):
    """The session exists, but another replica sharing the database runs it (holds its lease)."""

    def __init__(self, session_id: str, replica: str) -> None:
        super().__init__(f"session {session_id} is run by replica {replica!r}; send its requests there")
        self.session_id = session_id
        self.replica = replica


def _effective_config(overrides: dict[str, Any]) -> Any:
    """The model config of a session with ``overrides``, or a 422 naming what is wrong."""
    try:
        return model.effective_config(overrides)
    except ValidationError as exc:
        raise IngestError(422, f"invalid config: {pydantic_message(exc)}") from None
    except (ValueError, TypeError) as exc:
        raise IngestError(422, f"invalid config: {exc}") from None


class SessionManager:
    """All live sessions of the server.

    **Replicas.** Several servers may share one database (PostgreSQL). A session's mapper must
    run in one of them only, so a server runs a session only while it holds the session's
    *lease* in the store (:meth:`Store.claim_session`), renewed every ``lease_ttl_s / 3`` by a
    background thread. At start a server opens the stored sessions it can lease; a request
    for a session leased by another live replica gets :class:`ServedElsewhere` (HTTP 421,
    naming the replica); a session whose lease expired (its replica died) is taken over —
    restored from its snapshot plus replay — on the next request for it or by the renewal
    thread's scan. A server that finds its lease taken (it stalled past the TTL) stops that
    session's worker without writing anything more. With one server (the SQLite default) the
    lease is always its own: the replica id defaults to the host name, so a restarted server
    takes its sessions back at once.
    """

    def __init__(self, store: Store, settings: ServerSettings, metrics: ServiceMetrics | None = None) -> None:
        self.store = store
        self.settings = settings
        self.metrics = metrics if metrics is not None else ServiceMetrics()
        self.sessions: dict[str, LiveSession] = {}
        self.loop: asyncio.AbstractEventLoop | None = None
        self.calls: LoopCalls | None = None  # shared by the sessions: one wake-up of the loop per burst
        self.backend: Any = None  # the RayBackend or ProcessBackend when settings.backend is "ray" or "process"
        self.host_factory: HostFactory = gated_factory(MapperGate(settings.mapper_slots))
        self.replica = settings.replica_id or socket.gethostname()
        self._stopping = threading.Event()
        self._lease_thread: threading.Thread | None = None
        self._open_lock = threading.Lock()  # _open / _drop from the loop and the lease thread
        self._deleting: set[str] = set()  # sessions being deleted here: never adopted meanwhile

    @property
    def fatal(self) -> str | None:
        """Why this server can no longer store anything (its store's writer died), else None.
        ``/health`` and ``/ready`` answer 503 and the process exits (see :func:`exit_process`)."""
        return self.store.fatal

    def _on_store_fatal(self, reason: str) -> None:
        """The store's writer died (called from its thread): exit after ``fatal_exit_s`` so a
        supervisor restarts the server; every acknowledged input is durable, nothing is lost."""
        log.critical(
            "the store's writer died (%s): exiting in %.1f s so a supervisor restarts the server",
            reason,
            self.settings.fatal_exit_s,
        )
        timer = threading.Timer(self.settings.fatal_exit_s, exit_process, args=(EXIT_STORE_DEAD,))
        timer.daemon = True
        timer.start()

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start the session backend, then restore every stored session (each worker replays in its own thread)."""
        self.loop = loop
        self.store.on_fatal(self._on_store_fatal)
        if self.settings.backend == "ray":
            from .ray_backend import RayBackend  # Ray is imported only on this path

            self.backend = RayBackend(self.settings)
            self.backend.start()
            self.host_factory = self.backend.factory
        elif self.settings.backend == "process":
            from .process_host import ProcessBackend

            self.backend = ProcessBackend(self.settings.process_workers, table_cache=self.settings.table_cache_dir)
            self.backend.start()
            self.host_factory = self.backend.factory
        for rec in self.store.list_sessions():
            owner = self.store.claim_session(rec.id, self.replica, self.settings.lease_ttl_s)
            if owner == self.replica:
                self._open(rec, self._config_of(rec))
            else:
                log.info("session %s is run by replica %s", rec.id, owner, extra={"session": rec.id})
        self._lease_thread = threading.Thread(target=self._lease_loop, name="session-leases", daemon=True)
        self._lease_thread.start()

    @staticmethod
    def _config_of(rec: SessionRecord) -> HippomapConfig:
        try:
            return model.effective_config(rec.config)
        except ValueError:
            return HippomapConfig()

    # ------------------------------------------------------------- leases
    def _lease_loop(self) -> None:
        """Renew the leases of the sessions run here; drop those lost; adopt orphans."""
        period = self.settings.lease_ttl_s / 3
        while not self._stopping.wait(period):
            try:
                self._renew_and_adopt()
            except Exception:  # the database may be briefly unreachable: try again next period
                log.exception("renewing session leases failed")

    def _renew_and_adopt(self) -> None:
        ttl = self.settings.lease_ttl_s
        for sid, live in list(self.sessions.items()):
            if self._stopping.is_set() or live.closed:
                continue
            owner = self.store.claim_session(sid, self.replica, ttl)
            if owner != self.replica:
                log.warning(
                    "session %s: lease lost to replica %s; stopping it here", sid, owner, extra={"session": sid}
                )
                self._drop(live)
        now = time.time()
        for rec in self.store.list_sessions():
            # sessions younger than a TTL may still be being opened by the replica that created them
            if (
                self._stopping.is_set()
                or rec.id in self.sessions
                or rec.id in self._deleting
                or now - rec.created < ttl
            ):
                continue
            if (
                self.store.session_owner(rec.id) is None
                and self.store.claim_session(rec.id, self.replica, ttl) == self.replica
            ):
                log.warning(
                    "session %s: its replica stopped renewing; taking it over", rec.id, extra={"session": rec.id}
                )
                self._adopt(rec)

    def _adopt(self, rec: SessionRecord) -> LiveSession:
        """Open a session whose lease this server has just taken (restore: snapshot + replay)."""
        assert self.loop is not None
        with self._open_lock:
            live = self.sessions.get(rec.id)
            if live is None:
                live = self._open(rec, self._config_of(rec))
        return live

    def _drop(self, live: LiveSession) -> None:
        """Stop running a session here without writing anything more (another replica has it)."""
        with self._open_lock:
            live.closed = True
            if self.sessions.get(live.id) is live:
                self.sessions.pop(live.id, None)
        if self.loop is not None:
            try:
                self.loop.call_soon_threadsafe(live._room.set)
            except RuntimeError:
                pass
        live.worker.stop(snapshot=False)

    def restoring(self) -> list[str]:
        """Ids of the sessions still being restored (snapshot + replay): the server is not ready until none is."""
        return [sid for sid, live in list(self.sessions.items()) if not live.worker.ready.is_set()]

    def queue_depths(self) -> dict[str, int]:
        """Inputs acknowledged but not yet processed, per live session."""
        return {sid: live.queue_depth for sid, live in list(self.sessions.items())}

    def _open(self, rec: SessionRecord, config: HippomapConfig) -> LiveSession:
        assert self.loop is not None
        if self.calls is None or self.calls.loop is not self.loop:
            self.calls = LoopCalls(self.loop)
        live = LiveSession(
            rec, config, self.store, self.settings, self.loop, self.host_factory, self.metrics, self.calls
        )
        live.replica = self.replica
        self.sessions[rec.id] = live
        live.worker.start()
        return live

    def stop(self) -> None:
        self._stopping.set()
        if self._lease_thread is not None:
            self._lease_thread.join(30)
        for live in list(self.sessions.values()):
            live.closed = True
            live.worker.stop(snapshot=True)
        for sid in list(self.sessions):  # snapshots are written: another replica may take them now
            try:
                self.store.release_session(sid, self.replica)
            except Exception:
                log.exception("releasing the lease of session %s failed", sid, extra={"session": sid})
        self.sessions.clear()
        if self.backend is not None:
            self.backend.shutdown()
            self.backend = None

    # ------------------------------------------------------------ commands
    async def create(
        self, token: TokenRecord, name: str, overrides: dict[str, Any], base_session: str | None = None
    ) -> LiveSession:
        """A new session: a fresh mapper of ``overrides``, or (``base_session``) a new run in a copy of
        that session's map, its config the base's changed by ``overrides`` (see :meth:`_based`)."""
        if token.role == "viewer":
            raise Forbidden()
        if base_session is None:
            return await self._create(token, name, overrides)
        base = self._base(token, base_session, "base_session")
        merged, snapshot = await self._based(base, overrides)
        return await self._create(token, name, merged, snapshot)

    async def merge(self, token: TokenRecord, into: LiveSession, source_id: str, name: str) -> LiveSession:
        """A new session that holds ``source``'s run merged into ``into``'s map: a new run in a copy of
        ``into``'s map (as a based session) fed ``source``'s stored inputs, which the new session stores
        as its own and replays. ``source``'s recognitions of ``into``'s key frames are loop hypotheses
        like any other; neither session changes. Answers before the replay ends (stats: ``replaying``)."""
        if token.role == "viewer":
            raise Forbidden()
        source = self._base(token, source_id, "from")
        if source.id == into.id:
            raise IngestError(422, "a session cannot be merged into itself: 'from' names the session of the path")
        merged, snapshot = await self._based(into, {})
        return await self._create(token, name, merged, snapshot, inputs_of=source, wait_ready=False)

    def _base(self, token: TokenRecord, session_id: Any, what: str) -> LiveSession:
        """A session named in a request body, which the token must be able to read (404 otherwise)."""
        if not isinstance(session_id, str):
            raise IngestError(422, f"{what} must be a session id (a string), got {session_id!r}")
        try:
            return self.get(token, session_id)
        except NotFound:
            raise IngestError(404, f"{what} session {session_id!r} not found") from None

    async def _based(self, base: LiveSession, overrides: dict[str, Any]) -> tuple[dict[str, Any], bytes]:
        """``(config overrides, initial snapshot)`` of a new run in a copy of ``base``'s map: the base's
        overrides changed by ``overrides``, and the mapper state ``Mapper.from_base`` makes of the base's
        mapper as processed so far (built in the base's mapper host, which is only read)."""
        merged = {section: dict(values) for section, values in base.record.config.items()}
        for section, values in overrides.items():
            if not isinstance(values, dict):
                raise IngestError(422, f"invalid config: section {section!r} must be a mapping")
            merged.setdefault(section, {}).update(values)
        config = _effective_config(merged)
        if config.visual != base.config.visual:
            raise IngestError(
                422,
                "a session started from a base map must keep the base's visual config "
                "(its key frames were learned with it)",
            )
        if base.error:
            raise IngestError(409, f"base session {base.id} has failed: {base.error}")
        try:
            data = await asyncio.to_thread(base.worker.query, model.queries.BaseSnapshot(overrides))
        except InputError as exc:  # the model's refusal, e.g. a base whose own run was never placed on its map
            raise IngestError(409, f"session {base.id} cannot be a base map: {exc}") from None
        if data is None:
            raise IngestError(503, f"base session {base.id} is being restored; retry shortly", retry_after=1)
        return merged, data

    async def _create(
        self,
        token: TokenRecord,
        name: str,
        overrides: dict[str, Any],
        snapshot: bytes | None = None,
        inputs_of: LiveSession | None = None,
        wait_ready: bool = True,
    ) -> LiveSession:
        config = _effective_config(overrides)
        if len(json.dumps(overrides)) > MAX_OVERRIDES_CHARS:
            raise IngestError(422, f"config overrides longer than {MAX_OVERRIDES_CHARS} characters")
        owned = [s for s in self.sessions.values() if s.record.owner == token.id and not s.closed]
        if len(owned) >= self.settings.max_sessions_per_token:
            raise IngestError(
                429,
                f"token {token.id} already owns {len(owned)} sessions "
                f"(limit {self.settings.max_sessions_per_token}); delete one first",
            )
        try:
            check_config(config, self.settings)
            check_token_quota(config, [s.config for s in owned], self.settings)
        except ConfigRejected as exc:
            raise IngestError(exc.status, exc.detail) from None
        rec = SessionRecord(
            id="s_" + secrets.token_hex(8), owner=token.id, name=name, config=overrides, created=time.time()
        )
        await asyncio.to_thread(self.store.claim_session, rec.id, self.replica, self.settings.lease_ttl_s)
        await asyncio.wrap_future(self.store.create_session(rec))
        if snapshot is not None:  # the new run in the base's map: the state its worker restores (before seq 0)
            await asyncio.wrap_future(self.store.put_snapshot(rec.id, -1, snapshot, self.settings.keep_snapshots))
        if inputs_of is not None:
            await asyncio.to_thread(self._copy_inputs, inputs_of.id, rec.id, inputs_of.stored_seq)
        with self._open_lock:
            live = self._open(rec, config)
        log.info("session %s created by token %s", rec.id, token.id, extra={"session": rec.id})
        if wait_ready:
            # answer once the mapper exists: building it (grid-cell tables...) must not delay the first inputs
            await asyncio.to_thread(live.worker.ready.wait, 120)
        return live

    def _copy_inputs(self, source: str, target: str, until: int) -> None:
        """Store ``source``'s inputs up to seq ``until`` as ``target``'s, same order and sequence numbers
        (blocking; before ``target`` opens, so its worker replays them)."""
        after = -1
        while after < until:
            chunk = self.store.read_inputs(source, after, min(256, until - after))
            if not chunk:
                break
            self.store.append_inputs(
                target, [InputRecord(seq=r.seq, kind=r.kind, t=r.t, data=r.data) for r in chunk]
            ).result()
            after = chunk[-1].seq

    def visible(self, token: TokenRecord) -> list[LiveSession]:
        return [s for s in self.sessions.values() if can_read(token, s.record)]

    def visible_elsewhere(self, token: TokenRecord) -> list[tuple[SessionRecord, str]]:
        """``(record, replica)`` of the sessions the token may see that another replica runs
        (blocking: reads the store)."""
        out = []
        for rec in self.store.list_sessions():
            if rec.id in self.sessions or not can_read(token, rec):
                continue
            owner = self.store.session_owner(rec.id)
            if owner is not None and owner != self.replica:
                out.append((rec, owner))
        return out

    def get(self, token: TokenRecord, session_id: str, write: bool = False) -> LiveSession:
        live = self.sessions.get(session_id)
        if live is None:
            live = self._elsewhere(token, session_id)
        if live.closed or not can_read(token, live.record):
            raise NotFound()
        if write and not can_write(token, live.record):
            raise Forbidden()
        return live

    def _elsewhere(self, token: TokenRecord, session_id: str) -> LiveSession:
        """A session not run here: stored and visible to the token? Then it is either run by
        another replica (:class:`ServedElsewhere`) or orphaned, and this server takes it over."""
        if self._stopping.is_set() or not session_id.startswith("s_") or session_id in self._deleting:
            raise NotFound()
        rec = next((r for r in self.store.list_sessions() if r.id == session_id), None)
        if rec is None or not can_read(token, rec):
            raise NotFound()
        owner = self.store.claim_session(session_id, self.replica, self.settings.lease_ttl_s)
        if owner != self.replica:
            raise ServedElsewhere(session_id, owner)
        log.warning("session %s: no replica runs it; taking it over", session_id, extra={"session": session_id})
        return self._adopt(rec)

    async def delete(self, token: TokenRecord, session_id: str) -> None:
        live = self.get(token, session_id, write=True)
        self._deleting.add(session_id)  # the lease scan must not adopt it while it goes away
        try:
            await self._delete(live)
        finally:
            self._deleting.discard(session_id)

    async def _delete(self, live: LiveSession) -> None:
        session_id = live.id
        live.closed = True
        live._room.set()  # wakes an ingest waiting for room; it sees `closed` and gives up
        async with live._lock:  # no submit is half-way through after this
            pass
        self.sessions.pop(session_id, None)
        await asyncio.to_thread(live.worker.stop, False)
        await asyncio.wrap_future(self.store.delete_session(session_id))
        self.metrics.forget(session_id)
        await asyncio.to_thread(release_memory)
        log.info("session %s deleted", session_id, extra={"session": session_id})
