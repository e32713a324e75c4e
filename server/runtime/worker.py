"""One thread per session that feeds its mapper, strictly in sequence order.

Why a thread: the mapper is CPU work (numpy/OpenCV, which release the GIL in their kernels)
and must never block the event loop; one thread per session keeps each session's inputs
in order while sessions run side by side. Where the mapper itself runs is the business of a
:class:`~server.runtime.mapper_host.MapperHost`: in this process (the default) or in a Ray actor
(:mod:`server.runtime.ray_backend`). This thread stays the only writer of the session's derived
records and snapshots, whatever the host, so a remote mapper needs no database access.

Lifecycle of a worker:

1. **Restore** — load the newest snapshot into a new host (or start a fresh mapper), drop
   derived records newer than it, then replay every stored input after it up to
   ``replay_until`` (the last input stored before this server started). The mapper is
   deterministic and its snapshot restores it exactly (``Mapper.to_bytes``/``from_bytes``),
   so the restored session is in exactly the state it had before the restart.
2. **Live** — take inputs from the inbox (filled by the store right after each commit, so
   only durable inputs reach the mapper), hand them to the host (up to ``host.max_batch`` per
   call), write the events and place fields they produced, and snapshot every
   ``snapshot_every_inputs`` inputs or ``snapshot_every_s`` seconds.
3. **Host death** — if the host loses its mapper (:class:`~server.runtime.mapper_host.HostDied`: the
   actor's process died), a new host is restored as in 1, replaying the stored inputs up to
   the last one handed to the dead host (the failed batch included: every input reached the
   mapper only after it was durable, so the store has them all). ``restarts`` counts this;
   after ``backend_max_restarts`` deaths without progress the session stops with an error.

Queries (:meth:`SessionWorker.query`) are typed values (:mod:`hippomap.mapper_queries`) the host
answers between two inputs; while a dead host is being replaced they wait, so they never see a
mapper older than ``processed_seq``.

Events: an input's events are the ones the mapper's call on it returned (the map's events
included, e.g. a loop closed while a frame was observed), so each is stored under the sequence
number of the input that caused it, with its one time key ``t``.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

from hippomap.config import HippomapConfig
from hippomap.inputs import Frame, Odometry

from ..formats.ingest import frame_from_bytes, odometry_from_bytes
from ..settings import ServerSettings
from ..storage.store import EventRecord, PlaceFieldRecord, Store
from . import model
from .mapper_host import INPUT_FAILED, HostDied, HostFactory, MapperHost, StepResult, inprocess_factory

log = logging.getLogger("hippomap.server")

REPLAY_CHUNK = 256
DERIVED_FLUSH = 256
BATCH_BYTES = 16 << 20  # most image bytes handed to a host in one call
QUERY_WAIT_S = 120.0  # longest a query waits for a dead host to be replaced

T = TypeVar("T")


@dataclass(frozen=True)
class WorkItem:
    seq: int
    value: Odometry | Frame


@dataclass(frozen=True)
class _Recover:
    """Inbox message from a query that found host generation ``gen`` dead."""

    gen: int


def _nbytes(value: Odometry | Frame) -> int:
    return int(getattr(getattr(value, "image", None), "nbytes", 0))


class SessionWorker:
    """Runs one session's mapper (through its host) from its own thread."""

    def __init__(
        self,
        session_id: str,
        config: HippomapConfig,
        store: Store,
        settings: ServerSettings,
        replay_until: int,
        on_processed: Callable[[int], None] | None = None,
        host_factory: HostFactory | None = None,
        metrics: Any = None,
    ) -> None:
        self.session_id = session_id
        self.config = config
        self.store = store
        self.settings = settings
        self.replay_until = replay_until
        self.on_processed = on_processed
        self.metrics = metrics
        self.host_factory = host_factory or inprocess_factory
        self.processed_seq = -1  # newest input whose results are stored or queued (never goes back)
        self.snapshot_seq = -1
        self.replaying = True
        self.ready = threading.Event()  # set once the restore (snapshot + replay) is done
        self.error: str | None = None
        self.restarts = 0  # hosts replaced after they died
        self.input_errors = 0  # inputs the mapper raised on (skipped, recorded as input_failed events)
        self.last_input_error: str | None = None
        self.host_info: dict[str, Any] = {}
        self._host: MapperHost | None = None
        self._gen = 0  # bumped each time a host is installed
        self._cond = threading.Condition()
        self._serving = threading.Event()  # cleared while a dead host is being replaced
        self._serving.set()
        self._host_seq = -1  # newest input the current host has processed
        self._given = replay_until  # newest input handed to a host (replayed after a death)
        self._reported = replay_until  # newest input reported (on_processed, metrics)
        self._failures = 0  # host deaths since the last successful batch
        self._inbox: queue.Queue = queue.Queue()
        self._held: Any = None
        self._restoring = False
        self._stop = False
        self._next_event = 0
        self._next_step = 0
        self._events: list[EventRecord] = []
        self._fields: list[PlaceFieldRecord] = []
        self._snapshot_t = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"session-{session_id}", daemon=True)

    @property
    def _log_extra(self) -> dict[str, Any]:
        return {"session": self.session_id}

    # --------------------------------------------------------------- control
    def start(self) -> None:
        self._thread.start()

    def put(self, items: list[WorkItem]) -> None:
        """Queue durable inputs (called by the store's writer thread, in seq order)."""
        for it in items:
            self._inbox.put(it)

    def stop(self, snapshot: bool = True, timeout: float = 30.0) -> None:
        """Finish the inputs already queued, take a last snapshot, and end the thread
        (``snapshot=False``: drop the queue, no snapshot — the session is being deleted)."""
        self._stop = not snapshot
        if not snapshot:  # the session is being deleted: free the queued inputs (decoded frames) now
            while True:
                try:
                    self._inbox.get_nowait()
                except queue.Empty:
                    break
        self._inbox.put(None)
        self._thread.join(timeout)
        if not self._thread.is_alive():
            self._close_host()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    # ------------------------------------------------------------------ loop
    def _next(self, block: bool = True) -> Any:
        if self._held is not None:
            item, self._held = self._held, None
            return item
        return self._inbox.get() if block else self._inbox.get_nowait()

    def _batch(self, first: WorkItem, limit: int) -> list[WorkItem]:
        """``first`` and the inputs queued behind it, up to ``limit`` items / BATCH_BYTES."""
        batch, size = [first], _nbytes(first.value)
        while len(batch) < limit and size < BATCH_BYTES:
            try:
                item = self._next(block=False)
            except queue.Empty:
                break
            if not isinstance(item, WorkItem):
                self._held = item  # a stop or recover message: handled after this batch
                break
            batch.append(item)
            size += _nbytes(item.value)
        return batch

    def _run(self) -> None:
        try:
            self._restore_host(self.replay_until, recovering=False)
            self.replaying = False
            self.ready.set()
            while True:
                item = self._next()
                if item is None:
                    break
                if isinstance(item, _Recover):
                    if item.gen == self._gen and not self._stop:
                        self._restore_host(self._given, recovering=True, cause="a query found it dead")
                    continue
                if self._stop:
                    continue
                assert self._host is not None
                self._feed(self._batch(item, max(1, self._host.max_batch)))
                if self._held is None and self._inbox.empty():
                    self._flush_derived()
                self._maybe_snapshot()
            if not self._stop:
                self._flush_derived()
                self._snapshot()
        except Exception as exc:  # a bug in the model, or a host that keeps dying: stop this session, keep its inputs
            log.exception("session %s worker stopped", self.session_id, extra=self._log_extra)
            self.error = f"{type(exc).__name__}: {exc}"
            self.ready.set()
            return  # the mapper stays queryable (its state when the error happened) until stop()
        finally:
            self._serving.set()
        self._close_host()

    def _close_host(self) -> None:
        with self._cond:
            host, self._host = self._host, None
            self._gen += 1
            self._cond.notify_all()
        if host is not None:
            try:
                host.close()
            except Exception:  # noqa: BLE001 - closing a dead host
                log.debug(
                    "closing the host of session %s failed", self.session_id, exc_info=True, extra=self._log_extra
                )

    def _feed(self, batch: list[WorkItem]) -> None:
        """Hand ``batch`` to the host and take its results; replace the host if it died."""
        assert self._host is not None
        self._given = max(self._given, batch[-1].seq)
        try:
            results = self._host.process([(it.seq, it.value) for it in batch])
        except HostDied as exc:
            self._restore_host(self._given, recovering=True, cause=str(exc))
            return
        self._failures = 0
        self._absorb(results)

    # --------------------------------------------------------------- restore
    def _restore_host(self, until: int, recovering: bool, cause: str = "") -> None:
        """Install a new host: latest stored snapshot + replay of the stored inputs up to ``until``.

        ``recovering``: the previous host died (counted in ``restarts``; queries wait meanwhile)."""
        if recovering:
            self._serving.clear()
        try:
            while True:
                if recovering:
                    self.restarts += 1
                    self._failures += 1
                    if self._failures > self.settings.backend_max_restarts:
                        raise RuntimeError(
                            f"the session's mapper died {self._failures} times in a row (last: {cause}); giving up"
                        )
                    log.warning(
                        "session %s: mapper host died (%s); restoring a new one from the last snapshot "
                        "and replaying up to seq %d (restart %d)",
                        self.session_id,
                        cause,
                        until,
                        self.restarts,
                        extra=self._log_extra,
                    )
                    old, self._host = self._host, None
                    if old is not None:
                        try:
                            old.close()
                        except Exception:  # noqa: BLE001 - it is dead already
                            pass
                try:
                    t0 = time.monotonic()
                    self._restore(until)
                    seconds = time.monotonic() - t0
                    if self.metrics is not None:
                        self.metrics.restore_observed(self.session_id, seconds)
                    log.info(
                        "session %s restored up to seq %d in %.2f s",
                        self.session_id,
                        self._host_seq,
                        seconds,
                        extra=self._log_extra,
                    )
                    return
                except HostDied as exc:
                    cause, recovering = str(exc), True
        finally:
            self._serving.set()

    def _restore(self, until: int) -> None:
        self._restoring = True
        try:
            self._restore_inner(until)
        finally:
            self._restoring = False

    def _restore_inner(self, until: int) -> None:
        self.store.flush()  # earlier writes (derived records, snapshots) first: the truncation below follows them
        snap = self.store.latest_snapshot(self.session_id)
        seq, data = snap if snap is not None else (-1, None)
        host = self.host_factory(self.session_id)
        with self._cond:  # installed first, so a failure below is handled (closed) like any dead host
            self._host = host
            self._gen += 1
            self._cond.notify_all()
        stats = host.restore(data, self.config)
        self.host_info = host.info()
        self.store.truncate_derived(self.session_id, seq).result()
        self._events, self._fields = [], []
        self._next_event, _ = self.store.derived_counts(self.session_id)
        self._next_step = int(stats.get("odometry_steps", 0))
        self._host_seq = self.snapshot_seq = seq
        self.processed_seq = max(self.processed_seq, seq)
        self._snapshot_t = time.monotonic()
        after = seq
        limit = max(1, host.max_batch)
        while after < until:
            chunk = self.store.read_inputs(self.session_id, after, min(REPLAY_CHUNK, until - after))
            if not chunk:
                break
            items = [
                WorkItem(
                    rec.seq,
                    odometry_from_bytes(rec.data) if rec.kind == "odometry" else frame_from_bytes(rec.t, rec.data),
                )
                for rec in chunk
            ]
            k = 0
            while k < len(items):
                batch, size = [items[k]], _nbytes(items[k].value)
                while k + len(batch) < len(items) and len(batch) < limit and size < BATCH_BYTES:
                    batch.append(items[k + len(batch)])
                    size += _nbytes(batch[-1].value)
                k += len(batch)
                self._absorb(host.process([(it.seq, it.value) for it in batch]))
                self._maybe_snapshot()
            after = chunk[-1].seq
            self._flush_derived()

    # ---------------------------------------------------------------- results
    def _absorb(self, results: list[StepResult]) -> None:
        """Queue the derived records of processed inputs; report the ones processed for the first time
        (accepted loop closures: one ``loop_accepted`` event each, see ``cognitive_map.LoopAccepted``)."""
        loops = 0
        for r in results:
            if r.kind == "odometry":
                if r.field is not None:
                    self._fields.append(PlaceFieldRecord(step=self._next_step, seq=r.seq, t=r.t, data=r.field))
                self._next_step += 1
            for ev in r.events:  # MapEvent.to_dict: "type", the time "t" (None if not finite), the fields
                etype = ev["type"]
                if etype == INPUT_FAILED and r.seq > self._reported:
                    self.input_errors += 1
                    self.last_input_error = f"seq {r.seq}: {ev['detail']}"
                ref = ev.get("id") if isinstance(ev.get("id"), int) else None  # recognition, loop decision
                self._events.append(
                    EventRecord(id=self._next_event, seq=r.seq, type=etype, t=ev["t"], data=ev, ref=ref)
                )
                self._next_event += 1
            self._host_seq = r.seq
            self.processed_seq = max(self.processed_seq, r.seq)
            if len(self._events) + len(self._fields) >= DERIVED_FLUSH:
                self._flush_derived()
            if r.seq > self._reported:  # a live input, processed for the first time (a replayed one was counted
                self._reported = r.seq  # then, or before this server started)
                loops += sum(1 for ev in r.events if ev["type"] == "loop_accepted")
                if self.metrics is not None:
                    self.metrics.step_observed(self.session_id, r.kind, r.seconds)
                if self.on_processed is not None:
                    self.on_processed(r.seq)
        if loops and self.metrics is not None:
            self.metrics.loop_closures(self.session_id, loops)

    def _flush_derived(self) -> None:
        if self._events or self._fields:
            self.store.append_derived(self.session_id, self._events, self._fields)
            self._events, self._fields = [], []

    def _maybe_snapshot(self) -> None:
        s = self.settings
        if self._host_seq <= self.snapshot_seq:
            return
        if (
            self._host_seq - self.snapshot_seq >= s.snapshot_every_inputs
            or time.monotonic() - self._snapshot_t >= s.snapshot_every_s
        ):
            self._snapshot()

    def _snapshot(self) -> None:
        """Store the mapper state after ``_host_seq``; derived records up to it are queued first,
        and the store commits in order, so a stored snapshot never lacks them."""
        if self._host is None or self._host_seq <= self.snapshot_seq:
            return
        self._flush_derived()
        seq = self._host_seq
        try:
            data = self._host.snapshot()
        except HostDied as exc:  # the next input (or the final restore) replays from the previous snapshot
            if self._restoring or self._stop:
                raise
            self._restore_host(self._given, recovering=True, cause=str(exc))
            return self._snapshot()
        self.store.put_snapshot(self.session_id, seq, data, self.settings.keep_snapshots)
        self.snapshot_seq = seq
        self._snapshot_t = time.monotonic()

    # --------------------------------------------------------------- queries
    def query(self, query: model.queries.Query[T]) -> T | None:
        """The answer to ``query`` (a :mod:`hippomap.mapper_queries` value) between two inputs (call
        from a thread, not the event loop); None while the session is first restored. InputError
        for anything that is not one of the model's queries, before any host sees it."""
        model.queries.check_query(query)
        for _ in range(2):
            if not self._serving.wait(QUERY_WAIT_S):
                return None
            with self._cond:
                host, gen = self._host, self._gen
            if host is None:
                return None
            try:
                return host.query(query)
            except HostDied:
                self._inbox.put(_Recover(gen))  # the worker may be idle: make it replace the host now
                with self._cond:
                    self._cond.wait_for(lambda: self._gen != gen or not self._thread.is_alive(), QUERY_WAIT_S)
        return None
