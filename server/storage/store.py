"""The storage interface: what the server keeps, independent of the database behind it.

Everything the server must not lose goes through a :class:`Store`:

* **tokens** (only a hash of each secret is kept) and **sessions** (owner, name, config overrides);
* **inputs**: every accepted odometry reading and camera frame (the JPEG as received), numbered by a
  per-session sequence number ``seq`` — written *before* the input is acknowledged;
* **snapshots** of each session's mapper (``Mapper.to_bytes``) tagged with the last ``seq`` they contain;
* **derived records** the mapper produced (events, place fields), tagged with the ``seq`` of the input
  that produced them, so a restore can drop those after the snapshot and regenerate them by replay.

Writes return a :class:`concurrent.futures.Future` that completes once the write is durable; the
embedded backend (:mod:`server.storage.sqlite`) commits many writes per transaction (group commit).
Writes of one store complete in submission order. Reads are synchronous and thread-safe.
Implementations: :mod:`server.storage.sqlite` (embedded default) and :mod:`server.storage.postgres`,
whose shared SQL is in :mod:`server.storage.sql`.
"""

from __future__ import annotations

import abc
import logging
import queue
import threading
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field
from typing import Any, Callable, Literal

Role = Literal["admin", "writer", "viewer"]
InputKind = Literal["odometry", "frame"]

log = logging.getLogger("hippomap.server")


@dataclass(frozen=True)
class TokenRecord:
    """A bearer token (never the secret itself). ``owner``: for viewer tokens, the writer
    token whose sessions it may read; ``session``: optionally limits a viewer to one session."""

    id: str
    role: Role
    owner: str | None = None
    session: str | None = None
    label: str = ""
    created: float = 0.0


@dataclass(frozen=True)
class SessionRecord:
    """A mapping session: who owns it and the config overrides it was created with."""

    id: str
    owner: str
    name: str = ""
    config: dict[str, Any] = field(default_factory=dict)
    created: float = 0.0


@dataclass(frozen=True)
class InputRecord:
    """One stored input: odometry (``data`` = JSON bytes) or a frame (``data`` = the encoded image)."""

    seq: int
    kind: InputKind
    t: float
    data: bytes


@dataclass(frozen=True)
class EventRecord:
    """One mapper event (``data`` is the event dict); ``id`` numbers a session's events from 0."""

    id: int
    seq: int
    type: str
    t: float | None
    data: dict[str, Any]
    ref: int | None = None  # the event's own id in the mapper (e.g. a recognition id), for lookup


@dataclass(frozen=True)
class PlaceFieldRecord:
    """The place field of one odometry step (``step`` counts odometry inputs from 0)."""

    step: int
    seq: int
    t: float
    data: bytes


class Store(abc.ABC):
    """Durable storage of one server. All methods are thread-safe."""

    # ---------------------------------------------------------------- tokens
    @abc.abstractmethod
    def add_token(self, secret_hash: str, token: TokenRecord) -> Future: ...

    @abc.abstractmethod
    def token_by_hash(self, secret_hash: str) -> TokenRecord | None: ...

    @abc.abstractmethod
    def list_tokens(self, owner: str) -> list[TokenRecord]:
        """Tokens created by ``owner`` (and the owner itself)."""

    @abc.abstractmethod
    def delete_token(self, token_id: str) -> Future: ...

    @abc.abstractmethod
    def revoke_token(self, token_id: str, heir: str) -> Future:
        """In one transaction: delete the token and every token it minted (its viewer tokens), and
        give the sessions it owns to ``heir`` (the token that minted it). Result: the ids of those
        sessions."""

    # -------------------------------------------------------------- sessions
    @abc.abstractmethod
    def create_session(self, session: SessionRecord) -> Future: ...

    @abc.abstractmethod
    def list_sessions(self) -> list[SessionRecord]:
        """Every stored session (the server filters by owner)."""

    @abc.abstractmethod
    def delete_session(self, session_id: str) -> Future:
        """Drop a session with all its inputs, snapshots, derived records and its lease."""

    # ---------------------------------------------------------------- leases
    # Several server replicas may share one database (PostgreSQL): a session's mapper must run
    # in one of them only. The replica that runs it holds a lease and renews it.
    @abc.abstractmethod
    def claim_session(self, session_id: str, replica: str, ttl_s: float) -> str:
        """Take (if free or expired) or renew (if ``replica``'s) the lease on running
        ``session_id``'s mapper for ``ttl_s`` > 0 seconds; returns the replica holding it after
        the call. Atomic across processes sharing the database."""

    @abc.abstractmethod
    def release_session(self, session_id: str, replica: str) -> bool:
        """Give up ``replica``'s lease; False if it did not hold it."""

    @abc.abstractmethod
    def session_owner(self, session_id: str) -> str | None:
        """The replica holding an unexpired lease, or None."""

    # ---------------------------------------------------------------- inputs
    @abc.abstractmethod
    def append_inputs(
        self, session_id: str, inputs: list[InputRecord], on_durable: Callable[[], None] | None = None
    ) -> Future:
        """Store inputs (consecutive ``seq``). ``on_durable`` runs, in submission order, right
        after the commit and before the future completes."""

    @abc.abstractmethod
    def last_input(self, session_id: str) -> tuple[int, float] | None:
        """``(seq, t)`` of the session's last stored input, or None."""

    @abc.abstractmethod
    def last_times(self, session_id: str) -> dict[str, float]:
        """The timestamp of the last stored input of each kind (kinds never stored are absent)."""

    @abc.abstractmethod
    def read_inputs(self, session_id: str, after_seq: int, limit: int, with_data: bool = True) -> list[InputRecord]:
        """Inputs with ``seq > after_seq`` in order, at most ``limit``."""

    @abc.abstractmethod
    def input_by_seq(self, session_id: str, seq: int) -> InputRecord | None: ...

    @abc.abstractmethod
    def frame_at(self, session_id: str, t: float) -> InputRecord | None:
        """The frame input with timestamp ``t`` exactly, or None."""

    # -------------------------------------------------------------- snapshots
    @abc.abstractmethod
    def put_snapshot(self, session_id: str, seq: int, data: bytes, keep: int) -> Future:
        """Store a mapper snapshot covering inputs up to ``seq``; keep only the ``keep`` newest."""

    @abc.abstractmethod
    def latest_snapshot(self, session_id: str) -> tuple[int, bytes] | None: ...

    # ------------------------------------------------------- derived records
    @abc.abstractmethod
    def append_derived(self, session_id: str, events: list[EventRecord], fields: list[PlaceFieldRecord]) -> Future: ...

    @abc.abstractmethod
    def truncate_derived(self, session_id: str, after_seq: int) -> Future:
        """Delete derived records of inputs with ``seq > after_seq`` (before a replay)."""

    @abc.abstractmethod
    def derived_counts(self, session_id: str) -> tuple[int, int]:
        """``(number of events, number of place fields)`` stored for the session."""

    @abc.abstractmethod
    def query_events(
        self,
        session_id: str,
        types: list[str] | None = None,
        since_id: int = -1,
        t_min: float | None = None,
        t_max: float | None = None,
        limit: int = 1000,
    ) -> list[EventRecord]: ...

    @abc.abstractmethod
    def event_by_ref(self, session_id: str, type: str, ref: int) -> EventRecord | None:
        """The event of ``type`` whose ``ref`` is ``ref`` (e.g. recognition number ``ref``)."""

    @abc.abstractmethod
    def place_fields(
        self, session_id: str, since_step: int = -1, limit: int = 1000, with_data: bool = False
    ) -> list[PlaceFieldRecord]: ...

    @abc.abstractmethod
    def place_field(self, session_id: str, step: int) -> PlaceFieldRecord | None: ...

    # ------------------------------------------------------------- lifecycle
    #: the writer thread's state (backends with a writer thread set it)
    writer: "WriterState | None" = None

    @property
    def fatal(self) -> str | None:
        """Why the store's writer thread died (None while it runs): nothing more can be stored."""
        return None if self.writer is None else self.writer.fatal

    def on_fatal(self, callback: Callable[[str], None]) -> None:
        """Call ``callback(reason)`` if the writer thread dies."""
        if self.writer is not None:
            self.writer.on_fatal(callback)

    def _enqueue(self, q: "queue.Queue", item: tuple[Any, Future, Any]) -> Future:
        """Queue a write for the writer thread (:class:`StoreDead` if it has died)."""
        if self.writer is not None:
            self.writer.check()
        q.put(item)
        if self.writer is not None and self.writer.fatal is not None:  # died meanwhile: it may not see this one
            _complete(item[1], error=StoreDead(f"the store's writer stopped ({self.writer.fatal})"))
        return item[1]

    @abc.abstractmethod
    def flush(self) -> None:
        """Wait until every submitted write is durable."""

    @abc.abstractmethod
    def close(self) -> None: ...


class StoreDead(RuntimeError):
    """The store's writer thread has stopped: nothing more can be made durable in this process."""


def _complete(fut: Future, result: Any = None, error: BaseException | None = None) -> None:
    """Complete ``fut`` unless it is already done (a waiter may have cancelled it: the write
    itself still happened, or failed, and that must never stop the writer)."""
    if fut.done():
        return
    try:
        if error is not None:
            fut.set_exception(error)
        else:
            fut.set_result(result)
    except InvalidStateError:  # cancelled between the check and the call
        pass


def fail_batch(batch: list[tuple[Any, Future, Callable[[], None] | None]], error: BaseException) -> None:
    """Fail every not-yet-done future of ``batch`` with ``error`` (nothing of it is durable)."""
    for _, fut, _ in batch:
        _complete(fut, error=error)


def settle_batch(
    batch: list[tuple[Any, Future, Callable[[], None] | None]], outcomes: list[tuple[Any, BaseException | None]]
) -> None:
    """Complete the futures of a committed group-commit ``batch`` (``(op, future, on_durable)``
    triples) in submission order: each with its operation's ``(result, error)``; a successful
    operation's ``on_durable`` runs first (shared by the store backends). A future a waiter
    cancelled is skipped, but its ``on_durable`` still runs: the write is durable whether or
    not anyone still waits for it (the session's mapper must get the input)."""
    for (_, fut, cb), (res, err) in zip(batch, outcomes):
        if err is not None:
            _complete(fut, error=err)
            continue
        if cb is not None:
            try:
                cb()
            except Exception as exc:  # the server's own callbacks; never let one stop the writer
                log.exception("an on_durable callback failed")
                _complete(fut, error=exc)
                continue
        _complete(fut, res)


def next_batch(q: "queue.Queue", max_batch: int) -> tuple[list, bool] | None:
    """The next group-commit batch of a store's writer thread: the first queued write (waiting
    for it) and whatever else is queued, up to ``max_batch``; ``None`` queued means stop.
    Returns ``(batch, stop_after)`` or None when the stop comes first."""
    item = q.get()
    if item is None:
        return None
    batch = [item]
    while len(batch) < max_batch:
        try:
            nxt = q.get_nowait()
        except queue.Empty:
            break
        if nxt is None:
            return batch, True
        batch.append(nxt)
    return batch, False


class WriterState:
    """The life of a store's writer thread, shared by the backends.

    :meth:`run` drives the loop: each batch runs through ``run_batch``; an exception out of a
    batch (a bug, or anything a request could provoke) fails that batch's futures and the
    loop goes on. Only if the loop itself dies (an error outside any batch, or a
    non-``Exception`` such as ``MemoryError``... ``BaseException``) is the writer *dead*:
    :attr:`fatal` names why, every queued write fails at once, every later submit raises
    :class:`StoreDead`, and ``on_fatal`` callbacks run (the server turns ``/health`` and
    ``/ready`` to 503 and exits so a supervisor restarts it: acknowledged inputs are durable)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.fatal: str | None = None
        self._callbacks: list[Callable[[str], None]] = []
        self._lock = threading.Lock()

    def on_fatal(self, callback: Callable[[str], None]) -> None:
        """Call ``callback(reason)`` when the writer dies (at once if it already has)."""
        with self._lock:
            if self.fatal is None:
                self._callbacks.append(callback)
                return
            reason = self.fatal
        callback(reason)

    def check(self) -> None:
        """Raise :class:`StoreDead` if the writer has died."""
        if self.fatal is not None:
            raise StoreDead(f"the store's writer stopped ({self.fatal}); the server must restart")

    def run(self, q: "queue.Queue", max_batch: int, run_batch: Callable[[list], None]) -> None:
        """The writer thread's body: batches from ``q`` through ``run_batch`` until a stop."""
        batch: list = []
        try:
            while (taken := next_batch(q, max_batch)) is not None:
                batch, stop = taken
                try:
                    run_batch(batch)
                except Exception as exc:  # one batch's trouble must not stop every later write
                    log.exception("%s: a write batch failed", self.name)
                    fail_batch(batch, exc)
                batch = []
                if stop:
                    return
        except BaseException as exc:  # noqa: BLE001 - the thread ends here whatever it was
            self._die(q, batch, f"{type(exc).__name__}: {exc}")

    def _die(self, q: "queue.Queue", batch: list, reason: str) -> None:
        log.critical("%s thread died: %s", self.name, reason)
        with self._lock:
            self.fatal = reason
            callbacks, self._callbacks = self._callbacks, []
        error = StoreDead(f"the store's writer stopped ({reason})")
        fail_batch(batch, error)  # its outcome is unknown: not acknowledged (a restart replays what was committed)
        while True:  # nothing queued will ever be written: fail it now rather than let callers hang
            try:
                item = q.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                _complete(item[1], error=error)
        for cb in callbacks:
            try:
                cb(reason)
            except Exception:
                log.exception("%s: an on_fatal callback failed", self.name)
