"""The PostgreSQL storage backend: several service replicas sharing one database.

Same contract as the embedded store (:mod:`server.storage.sqlite`), chosen by a
``postgresql://`` (or ``postgres://``) URL in ``HIPPOMAP_DATABASE``:

* **One writer thread, group commit.** Every write is queued to a single thread that takes
  everything waiting (up to ``MAX_BATCH`` operations) and commits them in one transaction,
  so one commit (one WAL flush on the server) acknowledges all concurrent sessions' inputs.
  One failing write must not spoil the others: the batch first runs straight through, with
  consecutive input appends merged into one ``INSERT ... SELECT FROM unnest(arrays)`` (a batch
  of inputs only is that one statement: one round trip, its own transaction); if anything
  fails, the transaction is rolled back and the batch re-run with each operation in its own
  SAVEPOINT, so only the bad one fails. (Failures are rare — a duplicate key — so the common
  batch pays neither savepoint nor per-write round trips.) Futures complete after the commit, in
  submission order; ``on_durable`` callbacks run in that order before their future completes.
* **Reads from a small pool** of autocommit connections (thread-safe; each read sees the last
  committed state, like SQLite's WAL readers). A read on a connection the server dropped is
  retried once on a fresh one.
* **A connection lost mid-write fails that batch** (its futures raise
  :class:`StoreConnectionError`: not durable, not acknowledged — never a hang); a connection
  the server closed while idle (restart, terminated backend) is noticed before use and
  replaced, so a restarted database server is picked up without failing any write.
* **Session leases** (:meth:`PostgresStore.claim_session`): replicas sharing the database agree
  on which one runs a session's mapper — one atomic upsert on the server's clock.

``durability="full"`` commits with ``synchronous_commit=on`` (an acknowledged input survives a
database crash); ``"normal"`` sets it off (survives a hippomap crash, may lose the last
commits if PostgreSQL itself crashes) — the same trade as SQLite's ``synchronous`` modes.
"""

from __future__ import annotations

import queue
import select
import threading
from concurrent.futures import Future
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

import psycopg
from psycopg.conninfo import conninfo_to_dict
from psycopg.pq import TransactionStatus

from .sql import KINDS, SCHEMA_VERSION, SQLStore
from .store import InputRecord, WriterState, fail_batch, settle_batch

POOL_SIZE = 8
_SCHEMA_LOCK = 0x68697070  # advisory lock id ("hipp"): replicas starting together create the schema once

# Free-text fields (session name, token label) are bytea: PostgreSQL text cannot hold NUL,
# SQLite can, and both stores must accept the same inputs.
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tokens (
    hash TEXT PRIMARY KEY, id TEXT NOT NULL UNIQUE, role TEXT NOT NULL, owner TEXT, session TEXT,
    label BYTEA NOT NULL, created DOUBLE PRECISION NOT NULL);
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, name BYTEA NOT NULL, config TEXT NOT NULL,
    created DOUBLE PRECISION NOT NULL);
CREATE TABLE IF NOT EXISTS inputs (
    session TEXT NOT NULL, seq BIGINT NOT NULL, kind SMALLINT NOT NULL, t DOUBLE PRECISION NOT NULL,
    data BYTEA NOT NULL, PRIMARY KEY (session, seq));
CREATE INDEX IF NOT EXISTS inputs_frame_t ON inputs (session, t) WHERE kind = 1;
CREATE TABLE IF NOT EXISTS snapshots (
    session TEXT NOT NULL, seq BIGINT NOT NULL, created DOUBLE PRECISION NOT NULL, data BYTEA NOT NULL,
    PRIMARY KEY (session, seq));
CREATE TABLE IF NOT EXISTS events (
    session TEXT NOT NULL, id BIGINT NOT NULL, seq BIGINT NOT NULL, type TEXT NOT NULL, t DOUBLE PRECISION,
    ref BIGINT, data TEXT NOT NULL, PRIMARY KEY (session, id));
CREATE INDEX IF NOT EXISTS events_seq ON events (session, seq);
CREATE INDEX IF NOT EXISTS events_type ON events (session, type, ref);
CREATE TABLE IF NOT EXISTS place_fields (
    session TEXT NOT NULL, step BIGINT NOT NULL, seq BIGINT NOT NULL, t DOUBLE PRECISION NOT NULL,
    data BYTEA NOT NULL, PRIMARY KEY (session, step));
CREATE INDEX IF NOT EXISTS place_fields_seq ON place_fields (session, seq);
CREATE TABLE IF NOT EXISTS leases (
    session TEXT PRIMARY KEY, owner TEXT, expires TIMESTAMPTZ NOT NULL);
"""

_CONNECT_OPTIONS: dict[str, Any] = {  # defaults; a URL's own ?connect_timeout=... etc. win
    "connect_timeout": 10,
    "application_name": "hippomap",
    # a database host that vanishes (no RST) is noticed in ~25 s instead of hanging on TCP
    "keepalives": 1,
    "keepalives_idle": 10,
    "keepalives_interval": 5,
    "keepalives_count": 3,
}


def _insert_inputs(conn: psycopg.Connection, rows: list[tuple]) -> None:
    """Insert input rows with one statement (one round trip, however many rows): the columns
    travel as arrays in binary."""
    if not rows:
        return
    cols = list(zip(*rows))
    conn.execute(
        "INSERT INTO inputs (session, seq, kind, t, data) SELECT * FROM "
        "unnest(%b::text[], %b::int8[], %b::int2[], %b::float8[], %b::bytea[])",
        [list(c) for c in cols],
        prepare=True,
    )


def _stale(conn: psycopg.Connection) -> bool:
    """Whether an idle connection is known dead. An idle connection is sent nothing (we never
    LISTEN), so a readable socket means the server said goodbye (restart, terminated backend)."""
    if conn.closed or conn.broken:
        return True
    try:
        readable, _, _ = select.select([conn.fileno()], [], [], 0)
    except (OSError, ValueError):
        return True
    return bool(readable)


class StoreConnectionError(RuntimeError):
    """PostgreSQL could not be reached (or the connection was lost). The message names host,
    port, database and user — never the password."""


def describe_url(url: str) -> str:
    """``user@host:port/dbname`` of a libpq URL, without the password (for messages and logs)."""
    try:
        info: dict[str, Any] = conninfo_to_dict(url)
    except psycopg.ProgrammingError:
        return "<unparsable PostgreSQL URL>"
    host = info.get("host") or info.get("hostaddr") or "localhost (unix socket)"
    port = info.get("port") or "5432"
    user = info.get("user")
    db = info.get("dbname") or user or "?"
    return f"{user + '@' if user else ''}{host}:{port}/{db}"


def _scrub(message: str, url: str) -> str:
    try:
        password: Any = conninfo_to_dict(url).get("password")
    except psycopg.ProgrammingError:
        password = None
    return message.replace(password, "***") if password else message


class PostgresStore(SQLStore):
    """:class:`~server.storage.store.Store` on a PostgreSQL database (tables created if missing); the
    SQL it shares with the SQLite store is in :class:`~server.storage.sql.SQLStore`.

    ``url``: a libpq URL, ``postgresql://user:password@host:port/dbname[?options]``."""

    EMPTY_BLOB = "''::bytea"

    def __init__(self, url: str, durability: str = "full", pool_size: int = POOL_SIZE) -> None:
        if not url.startswith(("postgresql://", "postgres://")):
            raise ValueError("PostgresStore needs a postgresql://user@host:port/dbname URL")
        self._url = url
        self.location = describe_url(url)
        try:  # our connection defaults, unless the URL sets them
            given = conninfo_to_dict(url)
        except psycopg.ProgrammingError as exc:
            raise ValueError(f"bad PostgreSQL URL: {_scrub(str(exc), url)}") from None
        self._options = {k: v for k, v in _CONNECT_OPTIONS.items() if k not in given}
        self._sync = "on" if durability == "full" else "off"
        self._queue: queue.Queue = queue.Queue()
        self.writer = WriterState("postgres-writer")
        self._closed = False
        self._pool_size = pool_size
        self._idle: list[psycopg.Connection] = []
        self._pool_lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(pool_size)
        self._writer_conn: psycopg.Connection | None = self._connect(writer=True)
        self._create_schema(self._writer_conn)
        self._thread = threading.Thread(target=self._write_loop, name="postgres-writer", daemon=True)
        self._thread.start()

    def __repr__(self) -> str:
        return f"PostgresStore({self.location!r})"

    @property
    def url(self) -> str:
        """The URL this store was opened with (contains the password if it had one: do not log it)."""
        return self._url

    # ------------------------------------------------------------ plumbing
    def _connect(self, writer: bool = False) -> psycopg.Connection:
        """An autocommit connection (the writer opens its transactions explicitly)."""
        try:
            conn = psycopg.connect(self._url, autocommit=True, **self._options)
        except psycopg.Error as exc:
            reason = _scrub(str(exc).strip(), self._url)
            raise StoreConnectionError(f"cannot connect to PostgreSQL database {self.location}: {reason}") from None
        if writer:
            conn.execute(f"SET synchronous_commit = {self._sync}")
        return conn

    def _create_schema(self, conn: psycopg.Connection) -> None:
        """Tables, once per database (replicas starting together serialise on an advisory lock),
        then the schema version check."""
        try:
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (_SCHEMA_LOCK,))
                row = None
                meta = conn.execute("SELECT to_regclass('meta')").fetchone()
                assert meta is not None  # a SELECT without FROM returns one row
                if meta[0] is not None:
                    row = conn.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
                if row is None:  # a new database
                    # (no DDL on a live one: even CREATE INDEX IF NOT EXISTS would lock out writers)
                    conn.execute(_SCHEMA)
                    # frames are JPEGs: storing them uncompressed saves a futile compression attempt
                    conn.execute("ALTER TABLE inputs ALTER COLUMN data SET STORAGE EXTERNAL")
                    conn.execute("INSERT INTO meta VALUES ('schema', %s)", (str(SCHEMA_VERSION),))
                elif int(row[0]) != SCHEMA_VERSION:
                    raise RuntimeError(f"{self.location}: database schema {row[0]}, this server needs {SCHEMA_VERSION}")
        except BaseException:
            conn.close()
            raise

    @contextmanager
    def _read(self) -> Iterator[psycopg.Connection]:
        """A pooled autocommit connection for reads (at most ``pool_size`` at once)."""
        self._slots.acquire()
        conn: psycopg.Connection | None = None
        try:
            with self._pool_lock:
                conn = self._idle.pop() if self._idle else None
            if conn is not None and _stale(conn):
                conn.close()
            if conn is None or conn.closed:
                conn = self._connect()
            yield conn
        finally:
            if conn is not None:
                if conn.closed or conn.broken or self._closed:
                    conn.close()
                else:
                    with self._pool_lock:
                        self._idle.append(conn)
            self._slots.release()

    def _fetch(self, sql: str, args: Any = (), one: bool = False) -> Any:
        """Run a read; a connection found dead (database restarted) is replaced once."""
        for attempt in (0, 1):
            with self._read() as conn:
                try:
                    cur = conn.cursor(binary=True)
                    cur.execute(sql, args)
                    return cur.fetchone() if one else cur.fetchall()
                except psycopg.OperationalError as exc:
                    if attempt == 0 and conn.broken:
                        continue
                    raise StoreConnectionError(
                        f"PostgreSQL database {self.location}: {_scrub(str(exc).strip(), self._url)}"
                    ) from None
        raise AssertionError("unreachable")  # pragma: no cover

    def _execute(self, conn: psycopg.Connection, sql: str, args: Sequence[Any] = ()) -> psycopg.Cursor:
        return conn.execute(sql, args)

    def _executemany(self, conn: psycopg.Connection, sql: str, rows: list[tuple]) -> None:
        with conn.cursor() as cur:
            cur.executemany(sql, rows)

    def _text_in(self, text: str) -> bytes:
        return text.encode()

    def _text_out(self, value: Any) -> str:
        return bytes(value).decode()

    def _write_batch(self, batch: list) -> None:
        try:
            self._run_batch(batch)
        except Exception:  # left half-way: no transaction may stay open for the next batch
            if self._writer_conn is not None:
                self._rollback(self._writer_conn)
            raise

    def _writer(self) -> psycopg.Connection:
        conn = self._writer_conn
        if conn is None or _stale(conn):
            if conn is not None:
                conn.close()
            self._writer_conn = None
            self._writer_conn = conn = self._connect(writer=True)
        return conn

    @staticmethod
    def _attempt(conn: psycopg.Connection, batch: list, savepoints: bool) -> list[tuple[Any, BaseException | None]]:
        """Run the batch as one transaction. Without savepoints the first failing operation
        raises (the caller rolls back); with them each failure is recorded and undone."""
        if not savepoints and all(getattr(fn, "input_rows", None) is not None for fn, _, _ in batch):
            # the common batch, inputs only: one statement is one round trip and its own transaction
            _insert_inputs(conn, [row for fn, _, _ in batch for row in fn.input_rows])
            return [(None, None)] * len(batch)
        outcomes: list[tuple[Any, BaseException | None]] = []
        conn.execute("BEGIN")
        i = 0
        while i < len(batch):
            fn = batch[i][0]
            if not savepoints:
                if getattr(fn, "input_rows", None) is None:
                    outcomes.append((fn(conn), None))
                    i += 1
                    continue
                # consecutive input appends (many sessions' streams) go in as one statement
                j, rows = i, []
                while j < len(batch) and getattr(batch[j][0], "input_rows", None) is not None:
                    rows += batch[j][0].input_rows
                    j += 1
                _insert_inputs(conn, rows)
                outcomes += [(None, None)] * (j - i)
                i = j
                continue
            conn.execute("SAVEPOINT op")
            try:
                res = fn(conn)
            except Exception as exc:  # one bad write must not spoil the batch
                if conn.broken:
                    raise
                conn.execute("ROLLBACK TO SAVEPOINT op")
                outcomes.append((None, exc))
            else:
                outcomes.append((res, None))
            conn.execute("RELEASE SAVEPOINT op")
            i += 1
        conn.execute("COMMIT")
        return outcomes

    @staticmethod
    def _rollback(conn: psycopg.Connection) -> None:
        if not conn.closed and not conn.broken and conn.info.transaction_status != TransactionStatus.IDLE:
            try:
                conn.execute("ROLLBACK")
            except psycopg.Error:
                conn.close()

    def _run_batch(self, batch: list) -> None:
        outcomes: list[tuple[Any, BaseException | None]] | None = None
        try:
            conn = self._writer()
            try:
                outcomes = self._attempt(conn, batch, savepoints=False)
            except Exception as exc:
                if conn.broken or conn.closed:
                    raise
                self._rollback(conn)
                if len(batch) == 1:  # the one operation failed: that is its outcome
                    outcomes = [(None, exc)]
                else:
                    outcomes = self._attempt(conn, batch, savepoints=True)
        except Exception as exc:  # connection lost or the commit failed: nothing of the batch is durable
            if self._writer_conn is not None:
                self._rollback(self._writer_conn)
            err: BaseException = exc
            if isinstance(exc, psycopg.OperationalError):
                err = StoreConnectionError(
                    f"PostgreSQL database {self.location}: {_scrub(str(exc).strip(), self._url)}"
                )
            fail_batch(batch, err)
            return
        settle_batch(batch, outcomes)

    def close(self) -> None:
        if self._closed:
            return
        self._queue.put(None)
        self._thread.join()
        self._closed = True
        if self._writer_conn is not None:
            self._writer_conn.close()
        with self._pool_lock:
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()

    # -------------------------------------------------------------- inputs
    def append_inputs(
        self, session_id: str, inputs: list[InputRecord], on_durable: Callable[[], None] | None = None
    ) -> Future:
        rows = [(session_id, r.seq, KINDS.index(r.kind), float(r.t), r.data) for r in inputs]

        def op(c: psycopg.Connection) -> None:
            _insert_inputs(c, rows)

        op.input_rows = rows  # type: ignore[attr-defined]  # lets a batch merge consecutive appends
        return self._submit(op, on_durable)

    def last_times(self, session_id: str) -> dict[str, float]:
        # the newest inputs hold both kinds in practice; one index scan per kind finds each
        rows = self._fetch(
            "SELECT k.kind, (SELECT t FROM inputs WHERE session=%s AND kind=k.kind "
            "ORDER BY seq DESC LIMIT 1) FROM (VALUES (0::smallint), (1::smallint)) AS k(kind)",
            (session_id,),
        )
        return {KINDS[kind]: float(t) for kind, t in rows if t is not None}

    # -------------------------------------------------------------- leases
    def claim_session(self, session_id: str, replica: str, ttl_s: float) -> str:
        """Take the lease on running ``session_id``'s mapper for ``ttl_s`` seconds if it is free,
        expired or already ``replica``'s (then it is renewed); returns the replica holding it
        after the call. One atomic upsert, timed by the database server's clock, so replicas
        with skewed clocks still agree."""
        if not ttl_s > 0:
            raise ValueError(f"ttl_s must be > 0, got {ttl_s!r}")
        for _ in range(10):
            row = self._fetch(
                "INSERT INTO leases AS l VALUES (%s, %s, now() + make_interval(secs => %s)) "
                "ON CONFLICT (session) DO UPDATE SET owner=EXCLUDED.owner, expires=EXCLUDED.expires "
                "WHERE l.owner IS NULL OR l.owner=EXCLUDED.owner OR l.expires < now() RETURNING owner",
                (session_id, replica, float(ttl_s)),
                one=True,
            )
            if row is not None:
                return str(row[0])
            holder = self.session_owner(session_id)
            if holder is not None:
                return holder
            # released or expired between the two statements: claim again
        raise RuntimeError(f"could not settle the lease of session {session_id}")  # pragma: no cover

    def release_session(self, session_id: str, replica: str) -> bool:
        """Give up ``replica``'s lease on ``session_id``; False if it did not hold it."""
        row = self._fetch(
            "UPDATE leases SET owner=NULL WHERE session=%s AND owner=%s RETURNING session",
            (session_id, replica),
            one=True,
        )
        return row is not None

    def session_owner(self, session_id: str) -> str | None:
        """The replica holding an unexpired lease on ``session_id``, or None."""
        row = self._fetch(
            "SELECT owner FROM leases WHERE session=%s AND owner IS NOT NULL AND expires >= now()",
            (session_id,),
            one=True,
        )
        return None if row is None else str(row[0])
