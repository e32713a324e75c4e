"""The embedded storage backend: one SQLite database in WAL mode.

Why this shape:

* **One writer thread, group commit.** Every write is queued to a single thread that takes
  everything waiting (up to ``MAX_BATCH`` operations), runs each in its own savepoint (one
  failing write cannot spoil the others) and commits once. With ``synchronous=FULL`` a
  commit is an fsync of the WAL, so acknowledged inputs survive a power cut; batching
  amortises that fsync over all concurrent sessions. Futures complete after the commit,
  in submission order.
* **Readers never wait for the writer**: WAL lets any number of per-thread read
  connections see the last committed state.
* **Checkpoints off the commit path.** SQLite normally checkpoints (copies the WAL into the
  database file and fsyncs it) inside whichever commit crosses 1000 pages, stalling every
  acknowledgement waiting on that commit; here a background thread checkpoints (PASSIVE:
  it never blocks the writer) every ``CHECKPOINT_EVERY_S``.
"""

from __future__ import annotations

import queue
import sqlite3
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Callable, Sequence

from .sql import KINDS, SCHEMA_VERSION, SQLStore, qmark
from .store import InputRecord, WriterState, fail_batch, settle_batch

CHECKPOINT_EVERY_S = 1.0

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS tokens (
    hash TEXT PRIMARY KEY, id TEXT NOT NULL UNIQUE, role TEXT NOT NULL, owner TEXT, session TEXT,
    label TEXT NOT NULL DEFAULT '', created REAL NOT NULL);
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, name TEXT NOT NULL, config TEXT NOT NULL, created REAL NOT NULL);
CREATE TABLE IF NOT EXISTS inputs (
    session TEXT NOT NULL, seq INTEGER NOT NULL, kind INTEGER NOT NULL, t REAL NOT NULL, data BLOB NOT NULL,
    PRIMARY KEY (session, seq));
CREATE INDEX IF NOT EXISTS inputs_frame_t ON inputs (session, t) WHERE kind = 1;
CREATE TABLE IF NOT EXISTS snapshots (
    session TEXT NOT NULL, seq INTEGER NOT NULL, created REAL NOT NULL, data BLOB NOT NULL,
    PRIMARY KEY (session, seq));
CREATE TABLE IF NOT EXISTS events (
    session TEXT NOT NULL, id INTEGER NOT NULL, seq INTEGER NOT NULL, type TEXT NOT NULL, t REAL,
    ref INTEGER, data TEXT NOT NULL, PRIMARY KEY (session, id));
CREATE INDEX IF NOT EXISTS events_seq ON events (session, seq);
CREATE INDEX IF NOT EXISTS events_type ON events (session, type, ref);
CREATE TABLE IF NOT EXISTS place_fields (
    session TEXT NOT NULL, step INTEGER NOT NULL, seq INTEGER NOT NULL, t REAL NOT NULL, data BLOB NOT NULL,
    PRIMARY KEY (session, step));
CREATE INDEX IF NOT EXISTS place_fields_seq ON place_fields (session, seq);
CREATE TABLE IF NOT EXISTS leases (session TEXT PRIMARY KEY, owner TEXT, expires REAL NOT NULL);
"""


class SQLiteStore(SQLStore):
    """:class:`~server.storage.store.Store` on a SQLite file (created if missing); the SQL it shares
    with the PostgreSQL store is in :class:`~server.storage.sql.SQLStore`."""

    EMPTY_BLOB = "x''"

    def __init__(self, path: str | Path, durability: str = "full") -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._sync = "FULL" if durability == "full" else "NORMAL"
        self._local = threading.local()
        self._queue: queue.Queue = queue.Queue()
        self.writer = WriterState("sqlite-writer")
        self._closed = False
        self._writer_conn = self._connect()
        self._writer_conn.execute("PRAGMA journal_mode=WAL")
        self._writer_conn.executescript(_SCHEMA)
        row = self._writer_conn.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
        if row is None:
            self._writer_conn.execute("INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),))
        elif int(row[0]) != SCHEMA_VERSION:
            raise RuntimeError(f"{self.path}: database schema {row[0]}, this server needs {SCHEMA_VERSION}")
        self._writer_conn.execute("PRAGMA wal_autocheckpoint=0")
        self._thread = threading.Thread(target=self._write_loop, name="sqlite-writer", daemon=True)
        self._thread.start()
        self._stop_checkpoints = threading.Event()
        self._checkpointer = threading.Thread(target=self._checkpoint_loop, name="sqlite-checkpoint", daemon=True)
        self._checkpointer.start()

    # ------------------------------------------------------------ plumbing
    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=30)
        conn.execute(f"PRAGMA synchronous={self._sync}")
        conn.execute("PRAGMA busy_timeout=30000")
        return conn

    def _read(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._local.conn = self._connect()
        return conn

    def _fetch(self, sql: str, args: Sequence[Any] = (), one: bool = False) -> Any:
        cur = self._read().execute(qmark(sql), args)
        return cur.fetchone() if one else cur.fetchall()

    def _execute(self, conn: sqlite3.Connection, sql: str, args: Sequence[Any] = ()) -> sqlite3.Cursor:
        return conn.execute(qmark(sql), args)

    def _executemany(self, conn: sqlite3.Connection, sql: str, rows: list[tuple]) -> None:
        conn.executemany(qmark(sql), rows)

    def _write_batch(self, batch: list) -> None:
        conn = self._writer_conn
        try:
            self._run_batch(conn, batch)
        except Exception:  # left half-way: no transaction may stay open for the next batch
            if conn.in_transaction:
                try:
                    conn.execute("ROLLBACK")
                except sqlite3.Error:
                    pass
            raise

    @classmethod
    def _run_batch(cls, conn: sqlite3.Connection, batch: list) -> None:
        """Commit ``batch`` in one transaction, each operation isolated from the others' failures.

        Operations almost never fail, so the batch first runs without savepoints (two statements fewer
        per operation). If one raises, that transaction is rolled back — nothing of it was committed —
        and the whole batch runs again, each operation in its own savepoint (operations only touch the
        database, so running them again is safe)."""
        if len(batch) > 1:
            outcomes: list[tuple[Any, BaseException | None]] = []
            try:
                conn.execute("BEGIN IMMEDIATE")
                for fn, _, _ in batch:
                    outcomes.append((fn(conn), None))
            except Exception:  # an operation failed (or BEGIN did): redo the batch the careful way
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
            else:
                try:
                    conn.execute("COMMIT")
                except Exception as exc:  # the commit itself failed (disk full, I/O error): nothing is durable
                    cls._abort(conn, batch, exc)
                    return
                settle_batch(batch, outcomes)
                return
        cls._run_isolated(conn, batch)

    @staticmethod
    def _run_isolated(conn: sqlite3.Connection, batch: list) -> None:
        outcomes: list[tuple[Any, BaseException | None]] = []
        try:
            conn.execute("BEGIN IMMEDIATE")
            for fn, _, _ in batch:
                conn.execute("SAVEPOINT op")
                try:
                    res = fn(conn)
                    conn.execute("RELEASE op")
                    outcomes.append((res, None))
                except Exception as exc:  # one bad write must not spoil the batch
                    conn.execute("ROLLBACK TO op")
                    conn.execute("RELEASE op")
                    outcomes.append((None, exc))
            conn.execute("COMMIT")
        except Exception as exc:  # the commit itself failed (disk full, I/O error): nothing is durable
            SQLiteStore._abort(conn, batch, exc)
            return
        settle_batch(batch, outcomes)

    @staticmethod
    def _abort(conn: sqlite3.Connection, batch: list, exc: BaseException) -> None:
        """Roll back what the batch wrote and fail every write in it with ``exc``."""
        try:
            conn.execute("ROLLBACK")
        except sqlite3.Error:
            pass
        fail_batch(batch, exc)

    def _checkpoint_loop(self) -> None:
        conn = self._connect()
        try:
            while not self._stop_checkpoints.wait(CHECKPOINT_EVERY_S):
                try:
                    conn.execute("PRAGMA wal_checkpoint(PASSIVE)")
                except sqlite3.Error:  # busy or I/O trouble: the next round tries again
                    pass
        finally:
            conn.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop_checkpoints.set()
        self._checkpointer.join()
        self._queue.put(None)
        self._thread.join()
        try:
            self._writer_conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except sqlite3.Error:
            pass
        self._writer_conn.close()

    # -------------------------------------------------------------- inputs
    def append_inputs(
        self, session_id: str, inputs: list[InputRecord], on_durable: Callable[[], None] | None = None
    ) -> Future:
        rows = [(session_id, r.seq, KINDS.index(r.kind), r.t, r.data) for r in inputs]

        def op(c: sqlite3.Connection) -> None:
            c.executemany("INSERT INTO inputs VALUES (?,?,?,?,?)", rows)

        return self._submit(op, on_durable)

    def last_times(self, session_id: str) -> dict[str, float]:
        conn = self._read()
        out: dict[str, float] = {}
        # the newest inputs hold both kinds in practice; look there first, then fall back to a scan
        for kind, t in conn.execute(
            "SELECT kind, t FROM inputs WHERE session=? ORDER BY seq DESC LIMIT 1000", (session_id,)
        ):
            out.setdefault(KINDS[kind], float(t))
            if len(out) == len(KINDS):
                return out
        for kind, t in conn.execute("SELECT kind, MAX(t) FROM inputs WHERE session=? GROUP BY kind", (session_id,)):
            out.setdefault(KINDS[kind], float(t))
        return out

    # -------------------------------------------------------------- leases
    def claim_session(self, session_id: str, replica: str, ttl_s: float) -> str:
        """Take the lease on running ``session_id``'s mapper for ``ttl_s`` seconds if it is free,
        expired or already ``replica``'s (then it is renewed); returns the replica holding it
        after the call. Runs in the writer's transaction (``BEGIN IMMEDIATE``: one writer across
        every process on the file), so the read-then-write is atomic."""
        if not ttl_s > 0:
            raise ValueError(f"ttl_s must be > 0, got {ttl_s!r}")

        def op(c: sqlite3.Connection) -> str:
            now = time.time()
            row = c.execute("SELECT owner, expires FROM leases WHERE session=?", (session_id,)).fetchone()
            if row is None or row[0] is None or row[0] == replica or row[1] < now:
                c.execute("INSERT OR REPLACE INTO leases VALUES (?,?,?)", (session_id, replica, now + ttl_s))
                return replica
            return str(row[0])

        return self._submit(op).result()

    def release_session(self, session_id: str, replica: str) -> bool:
        """Give up ``replica``'s lease on ``session_id``; False if it did not hold it."""
        return bool(
            self._submit(
                lambda c: (
                    c.execute(
                        "UPDATE leases SET owner=NULL WHERE session=? AND owner=?", (session_id, replica)
                    ).rowcount
                )
            ).result()
        )

    def session_owner(self, session_id: str) -> str | None:
        """The replica holding an unexpired lease on ``session_id``, or None."""
        row = (
            self._read()
            .execute(
                "SELECT owner FROM leases WHERE session=? AND owner IS NOT NULL AND expires>=?",
                (session_id, time.time()),
            )
            .fetchone()
        )
        return None if row is None else str(row[0])
