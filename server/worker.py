"""One thread per session that feeds its mapper, strictly in sequence order.

Why a thread: the mapper is CPU work (numpy/OpenCV, which release the GIL in their kernels)
and must never block the event loop; one thread per session keeps each session's inputs
in order while sessions run side by side.

Lifecycle of a worker:

1. **Restore** — load the newest snapshot (or start a fresh mapper), drop derived records
   newer than it, then replay every stored input after it up to ``replay_until`` (the last
   input stored before this server started). The mapper is deterministic and its snapshot
   restores it exactly (``Mapper.to_bytes``/``from_bytes``), so the restored session is in
   exactly the state it had before the restart.
2. **Live** — take inputs from the inbox (filled by the store right after each commit, so
   only durable inputs reach the mapper), process them, write the events and place fields
   they produced, and snapshot every ``snapshot_every_inputs`` inputs or
   ``snapshot_every_s`` seconds.

Queries read the mapper under :attr:`SessionWorker.lock`, which the worker holds only
while processing one input.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from hippomap.config import HippomapConfig
from hippomap.errors import InputError
from hippomap.inputs import Frame, Odometry

from . import model
from .ingest import frame_from_bytes, odometry_from_bytes
from .settings import ServerSettings
from .store import EventRecord, PlaceFieldRecord, Store

log = logging.getLogger("hippomap.server")

REPLAY_CHUNK = 256
DERIVED_FLUSH = 256


@dataclass(frozen=True)
class WorkItem:
    seq: int
    value: Odometry | Frame


class SessionWorker:
    """Runs one session's mapper in its own thread."""

    def __init__(self, session_id: str, config: HippomapConfig, store: Store, settings: ServerSettings,
                 replay_until: int, on_processed: Callable[[int], None] | None = None) -> None:
        self.session_id = session_id
        self.config = config
        self.store = store
        self.settings = settings
        self.replay_until = replay_until
        self.on_processed = on_processed
        self.lock = threading.Lock()
        self.mapper: model.MapperPort | None = None
        self.processed_seq = -1
        self.snapshot_seq = -1
        self.replaying = True
        self.ready = threading.Event()  # set once the restore (snapshot + replay) is done
        self.error: str | None = None
        self._inbox: queue.Queue = queue.Queue()
        self._stop = False
        self._next_event = 0
        self._next_step = 0
        self._last_field: Any = None
        self._events: list[EventRecord] = []
        self._fields: list[PlaceFieldRecord] = []
        self._snapshot_t = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"session-{session_id}", daemon=True)

    # --------------------------------------------------------------- control
    def start(self) -> None:
        self._thread.start()

    def put(self, items: list[WorkItem]) -> None:
        """Queue durable inputs (called by the store's writer thread, in seq order)."""
        for it in items:
            self._inbox.put(it)

    def stop(self, snapshot: bool = True, timeout: float = 30.0) -> None:
        """Finish the inputs already queued, take a last snapshot, and end the thread."""
        self._stop = not snapshot
        self._inbox.put(None)
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        try:
            self._restore()
            self.replaying = False
            self.ready.set()
            while True:
                item = self._inbox.get()
                if item is None:
                    break
                if self._stop:
                    continue
                self._process(item)
                if self._inbox.empty():
                    self._flush_derived()
                self._maybe_snapshot()
            if not self._stop:
                self._flush_derived()
                self._snapshot()
        except Exception as exc:  # a bug in the model: stop this session, keep its inputs
            log.exception("session %s worker stopped", self.session_id)
            self.error = f"{type(exc).__name__}: {exc}"
            self.ready.set()

    def _restore(self) -> None:
        snap = self.store.latest_snapshot(self.session_id)
        if snap is not None:
            seq, data = snap
            mapper = model.load_mapper(data)
        else:
            seq, mapper = -1, model.new_mapper(self.config)
        self.store.truncate_derived(self.session_id, seq).result()
        self._next_event, _ = self.store.derived_counts(self.session_id)
        self._next_step = int(mapper.stats().get("odometry_steps", 0))
        with self.lock:
            self.mapper = mapper
            self.processed_seq = self.snapshot_seq = seq
        after = seq
        while after < self.replay_until:
            chunk = self.store.read_inputs(self.session_id, after, min(REPLAY_CHUNK, self.replay_until - after))
            if not chunk:
                break
            for rec in chunk:
                value = odometry_from_bytes(rec.data) if rec.kind == "odometry" else frame_from_bytes(rec.t, rec.data)
                self._process(WorkItem(rec.seq, value))
                self._maybe_snapshot()
            after = chunk[-1].seq
            self._flush_derived()

    def _process(self, item: WorkItem) -> None:
        assert self.mapper is not None
        value = item.value
        with self.lock:
            try:
                if isinstance(value, Odometry):
                    events = self.mapper.step(value)
                else:
                    events = self.mapper.observe(value)
            except InputError as exc:  # validated at ingest, so only a model-side rule can get here
                events = [{"type": "input_rejected", "t": value.t, "seq": item.seq, "detail": str(exc)}]
            field = self.mapper.place_field if isinstance(value, Odometry) else None
            self.processed_seq = item.seq
        if isinstance(value, Odometry):
            if field is not None and field is not self._last_field and getattr(field, "field", None) is not None:
                self._fields.append(PlaceFieldRecord(step=self._next_step, seq=item.seq, t=value.t,
                                                     data=model.place_field_blob(field)))
            self._last_field = field
            self._next_step += 1
        for ev in events:
            ev = model.json_safe(ev)
            t = ev.get("t", ev.get("time"))
            ref = ev.get("id") if isinstance(ev.get("id"), int) else None
            self._events.append(EventRecord(id=self._next_event, seq=item.seq, type=str(ev.get("type", "event")),
                                            t=t if isinstance(t, (int, float)) else None, data=ev, ref=ref))
            self._next_event += 1
        if len(self._events) + len(self._fields) >= DERIVED_FLUSH:
            self._flush_derived()
        if self.on_processed is not None and not self.replaying:
            self.on_processed(item.seq)

    def _flush_derived(self) -> None:
        if self._events or self._fields:
            self.store.append_derived(self.session_id, self._events, self._fields)
            self._events, self._fields = [], []

    def _maybe_snapshot(self) -> None:
        s = self.settings
        if self.processed_seq <= self.snapshot_seq:
            return
        if (self.processed_seq - self.snapshot_seq >= s.snapshot_every_inputs
                or time.monotonic() - self._snapshot_t >= s.snapshot_every_s):
            self._snapshot()

    def _snapshot(self) -> None:
        """Write the mapper state after ``processed_seq``; derived records up to it are queued
        first, and the store commits in order, so a stored snapshot never lacks them."""
        if self.mapper is None or self.processed_seq <= self.snapshot_seq:
            return
        self._flush_derived()
        with self.lock:
            seq = self.processed_seq
            data = self.mapper.to_bytes()
        self.store.put_snapshot(self.session_id, seq, data, self.settings.keep_snapshots)
        self.snapshot_seq = seq
        self._snapshot_t = time.monotonic()

    # --------------------------------------------------------------- queries
    def query(self, fn: Callable[[Any], Any]) -> Any:
        """Run ``fn(mapper)`` while the worker is between inputs (call from a thread, not the loop)."""
        with self.lock:
            if self.mapper is None:
                return None
            return fn(self.mapper)
