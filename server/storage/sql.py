"""The SQL both store backends share: one set of tables, read and written by the same statements.

SQLite (:mod:`server.storage.sqlite`) and PostgreSQL (:mod:`server.storage.postgres`) hold the same
tables (``tokens``, ``sessions``, ``inputs``, ``snapshots``, ``events``, ``place_fields``, ``leases``)
and queue every write to one writer thread. :class:`SQLStore` writes what is the same logic once: the
write queue (``_submit``, ``flush``), the row decoders and every read, delete and upsert whose SQL both
databases accept. Statements use psycopg's placeholders (``%s``; ``%b`` for a parameter sent in
binary); the SQLite backend turns them into its ``?`` (:func:`qmark`).

What differs stays in the backends: connections and the schema's column types (free text is
``BYTEA`` in PostgreSQL, which cannot hold NUL in ``TEXT``: :meth:`SQLStore._text_in` and
:meth:`SQLStore._text_out` convert), the group-commit transaction, input appends (PostgreSQL merges
consecutive appends into one statement), the newest input times and the session leases (each
database's own atomic claim and clock).
"""

from __future__ import annotations

import abc
import functools
import json
import queue
import time
from concurrent.futures import Future
from typing import Any, Callable, Sequence

from .store import (
    EventRecord,
    InputKind,
    InputRecord,
    PlaceFieldRecord,
    SessionRecord,
    Store,
    TokenRecord,
    WriterState,
)

SCHEMA_VERSION = 1
MAX_BATCH = 1024  # writes per group commit at most
KINDS: tuple[InputKind, ...] = ("odometry", "frame")  # an input's kind as stored: its index here

_TOKEN_COLUMNS = "id, role, owner, session, label, created"
_EVENT_COLUMNS = "id, seq, type, t, ref, data"


@functools.lru_cache(maxsize=256)
def qmark(sql: str) -> str:
    """``sql`` with psycopg's placeholders (``%s``, ``%b``) as SQLite's ``?``."""
    return sql.replace("%s", "?").replace("%b", "?")


def _input(r: Sequence[Any]) -> InputRecord:
    return InputRecord(seq=r[0], kind=KINDS[r[1]], t=r[2], data=bytes(r[3]))


def _place_field(r: Sequence[Any]) -> PlaceFieldRecord:
    return PlaceFieldRecord(step=r[0], seq=r[1], t=r[2], data=bytes(r[3]))


def _event(r: Sequence[Any]) -> EventRecord:
    return EventRecord(id=r[0], seq=r[1], type=r[2], t=r[3], ref=r[4], data=json.loads(r[5]))


class SQLStore(Store):
    """A :class:`~server.storage.store.Store` on an SQL database with one writer thread.

    A backend sets ``writer``, ``_queue`` (drained by :meth:`_write_loop` on its writer thread) and
    ``_closed``, and provides reads (:meth:`_fetch`), statements on the writer's connection
    (:meth:`_execute`, :meth:`_executemany`), the batch itself (:meth:`_write_batch`) and the
    methods whose SQL differs."""

    writer: WriterState  # set by the backend's __init__ (the base class allows None)
    _queue: queue.Queue
    _closed: bool
    #: an empty blob in the database's SQL (inputs and place fields read without their data)
    EMPTY_BLOB: str

    # --------------------------------------------------- what a backend provides
    @abc.abstractmethod
    def _fetch(self, sql: str, args: Sequence[Any] = (), one: bool = False) -> Any:
        """Run a read on the last committed state: the first row (None if none) if ``one``, else all."""

    @abc.abstractmethod
    def _execute(self, conn: Any, sql: str, args: Sequence[Any] = ()) -> Any:
        """Run one statement on the writer's connection ``conn`` (inside its batch); returns the cursor."""

    @abc.abstractmethod
    def _executemany(self, conn: Any, sql: str, rows: list[tuple]) -> None:
        """Run one statement per row of ``rows`` on the writer's connection."""

    @abc.abstractmethod
    def _write_batch(self, batch: list) -> None:
        """Commit one group-commit batch of ``(op, future, on_durable)`` (the writer thread)."""

    def _text_in(self, text: str) -> Any:
        """A free-text field (token label, session name) as stored."""
        return text

    def _text_out(self, value: Any) -> str:
        """A stored free-text field as text."""
        return value

    # ------------------------------------------------------------ write queue
    def _submit(self, fn: Callable[[Any], Any], on_durable: Callable[[], None] | None = None) -> Future:
        """Queue ``fn(conn)`` for the writer thread; the future completes once it is committed."""
        if self._closed:
            raise RuntimeError("store is closed")
        return self._enqueue(self._queue, (fn, Future(), on_durable))

    def _write_loop(self) -> None:
        self.writer.run(self._queue, MAX_BATCH, self._write_batch)

    def flush(self) -> None:
        self._submit(lambda conn: None).result()

    # ---------------------------------------------------------------- tokens
    def add_token(self, secret_hash: str, token: TokenRecord) -> Future:
        row = (secret_hash, token.id, token.role, token.owner, token.session, self._text_in(token.label), token.created)

        def op(c: Any) -> None:
            self._execute(c, "INSERT INTO tokens VALUES (%s,%s,%s,%s,%s,%s,%s)", row)

        return self._submit(op)

    def _token(self, row: Sequence[Any]) -> TokenRecord:
        return TokenRecord(
            id=row[0], role=row[1], owner=row[2], session=row[3], label=self._text_out(row[4]), created=row[5]
        )

    def token_by_hash(self, secret_hash: str) -> TokenRecord | None:
        row = self._fetch(f"SELECT {_TOKEN_COLUMNS} FROM tokens WHERE hash=%s", (secret_hash,), one=True)
        return None if row is None else self._token(row)

    def list_tokens(self, owner: str) -> list[TokenRecord]:
        rows = self._fetch(
            f"SELECT {_TOKEN_COLUMNS} FROM tokens WHERE owner=%s OR id=%s ORDER BY created", (owner, owner)
        )
        return [self._token(r) for r in rows]

    def delete_token(self, token_id: str) -> Future:
        return self._submit(lambda c: self._execute(c, "DELETE FROM tokens WHERE id=%s", (token_id,)).rowcount)

    def revoke_token(self, token_id: str, heir: str) -> Future:
        def op(c: Any) -> list[str]:
            sessions = [
                r[0] for r in self._execute(c, "SELECT id FROM sessions WHERE owner=%s", (token_id,)).fetchall()
            ]
            self._execute(c, "UPDATE sessions SET owner=%s WHERE owner=%s", (heir, token_id))
            self._execute(c, "DELETE FROM tokens WHERE id=%s OR owner=%s", (token_id, token_id))
            return sessions

        return self._submit(op)

    # -------------------------------------------------------------- sessions
    def create_session(self, session: SessionRecord) -> Future:
        row = (session.id, session.owner, self._text_in(session.name), json.dumps(session.config), session.created)

        def op(c: Any) -> None:
            self._execute(c, "INSERT INTO sessions VALUES (%s,%s,%s,%s,%s)", row)

        return self._submit(op)

    def list_sessions(self) -> list[SessionRecord]:
        rows = self._fetch("SELECT id, owner, name, config, created FROM sessions ORDER BY created")
        return [
            SessionRecord(id=r[0], owner=r[1], name=self._text_out(r[2]), config=json.loads(r[3]), created=r[4])
            for r in rows
        ]

    def delete_session(self, session_id: str) -> Future:
        def op(c: Any) -> None:
            for table in ("inputs", "snapshots", "events", "place_fields", "leases"):
                self._execute(c, f"DELETE FROM {table} WHERE session=%s", (session_id,))
            self._execute(c, "DELETE FROM sessions WHERE id=%s", (session_id,))
            self._execute(c, "DELETE FROM tokens WHERE session=%s", (session_id,))

        return self._submit(op)

    # ---------------------------------------------------------------- inputs
    def last_input(self, session_id: str) -> tuple[int, float] | None:
        row = self._fetch(
            "SELECT seq, t FROM inputs WHERE session=%s ORDER BY seq DESC LIMIT 1", (session_id,), one=True
        )
        return None if row is None else (int(row[0]), float(row[1]))

    def read_inputs(self, session_id: str, after_seq: int, limit: int, with_data: bool = True) -> list[InputRecord]:
        data = "data" if with_data else f"CASE kind WHEN 0 THEN data ELSE {self.EMPTY_BLOB} END"
        rows = self._fetch(
            f"SELECT seq, kind, t, {data} FROM inputs WHERE session=%s AND seq>%s ORDER BY seq LIMIT %s",
            (session_id, after_seq, limit),
        )
        return [_input(r) for r in rows]

    def input_by_seq(self, session_id: str, seq: int) -> InputRecord | None:
        r = self._fetch(
            "SELECT seq, kind, t, data FROM inputs WHERE session=%s AND seq=%s", (session_id, seq), one=True
        )
        return None if r is None else _input(r)

    def frame_at(self, session_id: str, t: float) -> InputRecord | None:
        r = self._fetch(
            "SELECT seq, kind, t, data FROM inputs WHERE session=%s AND kind=1 AND t=%s ORDER BY seq LIMIT 1",
            (session_id, float(t)),
            one=True,
        )
        return None if r is None else _input(r)

    # ------------------------------------------------------------- snapshots
    def put_snapshot(self, session_id: str, seq: int, data: bytes, keep: int) -> Future:
        def op(c: Any) -> None:
            self._execute(
                c,
                "INSERT INTO snapshots VALUES (%s,%s,%s,%b) ON CONFLICT (session, seq) DO UPDATE "
                "SET created=EXCLUDED.created, data=EXCLUDED.data",
                (session_id, seq, time.time(), data),
            )
            self._execute(
                c,
                "DELETE FROM snapshots WHERE session=%s AND seq NOT IN "
                "(SELECT seq FROM snapshots WHERE session=%s ORDER BY seq DESC LIMIT %s)",
                (session_id, session_id, keep),
            )

        return self._submit(op)

    def latest_snapshot(self, session_id: str) -> tuple[int, bytes] | None:
        r = self._fetch(
            "SELECT seq, data FROM snapshots WHERE session=%s ORDER BY seq DESC LIMIT 1", (session_id,), one=True
        )
        return None if r is None else (int(r[0]), bytes(r[1]))

    # ------------------------------------------------------- derived records
    def append_derived(self, session_id: str, events: list[EventRecord], fields: list[PlaceFieldRecord]) -> Future:
        ev = [(session_id, e.id, e.seq, e.type, e.t, e.ref, json.dumps(e.data, allow_nan=True)) for e in events]
        pf = [(session_id, f.step, f.seq, f.t, f.data) for f in fields]

        def op(c: Any) -> None:
            if ev:  # a replay regenerates records already stored: the new ones replace them
                self._executemany(
                    c,
                    "INSERT INTO events VALUES (%s,%s,%s,%s,%s,%s,%s) ON CONFLICT (session, id) "
                    "DO UPDATE SET seq=EXCLUDED.seq, type=EXCLUDED.type, t=EXCLUDED.t, "
                    "ref=EXCLUDED.ref, data=EXCLUDED.data",
                    ev,
                )
            if pf:
                self._executemany(
                    c,
                    "INSERT INTO place_fields VALUES (%s,%s,%s,%s,%b) ON CONFLICT (session, step) "
                    "DO UPDATE SET seq=EXCLUDED.seq, t=EXCLUDED.t, data=EXCLUDED.data",
                    pf,
                )

        return self._submit(op)

    def truncate_derived(self, session_id: str, after_seq: int) -> Future:
        def op(c: Any) -> None:
            self._execute(c, "DELETE FROM events WHERE session=%s AND seq>%s", (session_id, after_seq))
            self._execute(c, "DELETE FROM place_fields WHERE session=%s AND seq>%s", (session_id, after_seq))

        return self._submit(op)

    def derived_counts(self, session_id: str) -> tuple[int, int]:
        r = self._fetch(
            "SELECT (SELECT COALESCE(MAX(id) + 1, 0) FROM events WHERE session=%s), "
            "(SELECT COALESCE(MAX(step) + 1, 0) FROM place_fields WHERE session=%s)",
            (session_id, session_id),
            one=True,
        )
        return int(r[0]), int(r[1])

    def query_events(
        self,
        session_id: str,
        types: list[str] | None = None,
        since_id: int = -1,
        t_min: float | None = None,
        t_max: float | None = None,
        limit: int = 1000,
    ) -> list[EventRecord]:
        sql = f"SELECT {_EVENT_COLUMNS} FROM events WHERE session=%s AND id>%s"
        args: list[Any] = [session_id, since_id]
        if types:
            sql += f" AND type IN ({','.join(['%s'] * len(types))})"
            args += list(types)
        if t_min is not None:
            sql += " AND t>=%s"
            args.append(float(t_min))
        if t_max is not None:
            sql += " AND t<=%s"
            args.append(float(t_max))
        sql += " ORDER BY id LIMIT %s"
        args.append(limit)
        return [_event(r) for r in self._fetch(sql, args)]

    def event_by_ref(self, session_id: str, type: str, ref: int) -> EventRecord | None:
        r = self._fetch(
            f"SELECT {_EVENT_COLUMNS} FROM events WHERE session=%s AND type=%s AND ref=%s ORDER BY id LIMIT 1",
            (session_id, type, ref),
            one=True,
        )
        return None if r is None else _event(r)

    def place_fields(
        self, session_id: str, since_step: int = -1, limit: int = 1000, with_data: bool = False
    ) -> list[PlaceFieldRecord]:
        col = "data" if with_data else self.EMPTY_BLOB
        rows = self._fetch(
            f"SELECT step, seq, t, {col} FROM place_fields WHERE session=%s AND step>%s ORDER BY step LIMIT %s",
            (session_id, since_step, limit),
        )
        return [_place_field(r) for r in rows]

    def place_field(self, session_id: str, step: int) -> PlaceFieldRecord | None:
        r = self._fetch(
            "SELECT step, seq, t, data FROM place_fields WHERE session=%s AND step=%s", (session_id, step), one=True
        )
        return None if r is None else _place_field(r)
