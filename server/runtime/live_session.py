"""A live session: one stored session in memory, with its worker and ingest state.

:meth:`LiveSession.submit` is where an input gets its order and its durability before the acknowledgement
(the path is described in :mod:`server.runtime.sessions`, whose :class:`~server.runtime.sessions.SessionManager`
creates, restores and drops these); kept apart from the manager so each module reads on its own.
"""

from __future__ import annotations

import asyncio
import ctypes
import gc
import logging
from collections import Counter
from typing import Any, Awaitable, Callable, cast

from hippomap.config import HippomapConfig
from hippomap.inputs import Frame

from ..formats.ingest import Accepted, IngestError, check_frame, check_time_jump
from ..metrics import ServiceMetrics
from ..security.limits import TokenBucket
from ..settings import ServerSettings
from ..storage.store import InputRecord, SessionRecord, Store, StoreDead
from . import model
from .loop_calls import LoopCalls
from .mapper_host import HostFactory
from .worker import SessionWorker, WorkItem

log = logging.getLogger("hippomap.server")


class NotFound(Exception):
    """No such session — or one the token may not see (indistinguishable on purpose)."""


def release_memory() -> None:
    """Give freed memory back to the operating system (after a session is deleted): collect
    cycles, then ask glibc to return its free heap pages (a no-op elsewhere)."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def input_bytes(a: Accepted) -> int:
    """Memory an accepted input holds until the mapper has it: the decoded image of a frame."""
    image = getattr(a.value, "image", None)
    return 0 if image is None else int(image.nbytes)


class LiveSession:
    """A session in memory: its record, config, worker and ingest state."""

    replica: str = ""  #: the replica (server) running it: SessionManager.replica

    def __init__(
        self,
        record: SessionRecord,
        config: HippomapConfig,
        store: Store,
        settings: ServerSettings,
        loop: asyncio.AbstractEventLoop,
        host_factory: HostFactory | None = None,
        metrics: ServiceMetrics | None = None,
        calls: LoopCalls | None = None,
    ) -> None:
        self.record = record
        self.config = config
        self.store = store
        self.settings = settings
        self.loop = loop
        #: completions from the store's writer and the worker reach the loop through here (batched wake-ups)
        self.calls = calls if calls is not None else LoopCalls(loop)
        self.metrics = metrics
        last = store.last_input(record.id)
        self.next_seq = 0 if last is None else last[0] + 1
        #: timestamp of the last accepted input of each kind: the next one of that kind must exceed it
        self.last_times: dict[str, float] = store.last_times(record.id)
        self.stored_seq = self.next_seq - 1  # last durable input
        self.pending = 0
        self.pending_bytes = 0  # decoded image bytes of the pending inputs (frames)
        self._pending_sizes: dict[int, int] = {}  # seq -> bytes, for the frames among them
        self.closed = False
        self.store_error: str | None = None
        self.rejected: Counter[int] = Counter()
        self._frame_shapes_ok: set[tuple[Any, ...]] = set()  # see _validate_frame
        self.bucket = TokenBucket(settings.rate_per_s, settings.rate_burst)
        self._lock = asyncio.Lock()
        self._room = asyncio.Event()
        self.worker = SessionWorker(
            record.id,
            config,
            store,
            settings,
            replay_until=self.next_seq - 1,
            on_processed=self._processed_threadsafe,
            host_factory=host_factory,
            metrics=metrics,
        )

    @property
    def id(self) -> str:
        return self.record.id

    @property
    def error(self) -> str | None:
        return self.store_error or self.worker.error

    @property
    def queue_depth(self) -> int:
        """Inputs acknowledged (durable) but not yet processed by the mapper."""
        return max(0, self.stored_seq - self.worker.processed_seq)

    @property
    def last_t(self) -> float | None:
        """Timestamp of the newest accepted input of either kind."""
        return max(self.last_times.values()) if self.last_times else None

    # --------------------------------------------------------------- ingest
    def _processed_threadsafe(self, seq: int) -> None:
        self.calls.call(self._processed, seq)

    def _processed(self, seq: int | None = None) -> None:
        self.pending = max(0, self.pending - 1)
        if seq is not None:
            self.pending_bytes = max(0, self.pending_bytes - self._pending_sizes.pop(seq, 0))
        self._room.set()

    def _has_room(self, n: int, nbytes: int = 0) -> bool:
        """Room in the mapper queue for ``n`` more inputs of ``nbytes``: both the count
        (``max_pending``) and the bytes (``max_pending_bytes``) must fit; an empty queue always
        takes one message, however large (it was validated against the frame limits)."""
        if self.pending == 0:
            return True
        return (
            self.pending + n <= self.settings.max_pending
            and self.pending_bytes + nbytes <= self.settings.max_pending_bytes
        )

    async def submit(
        self, items: list[Accepted], wait_s: float | None, on_busy: Callable[[], Awaitable[None]] | None = None
    ) -> tuple[int, int, asyncio.Future]:
        """Accept validated inputs; returns ``(first seq, last seq, durability future)``.

        ``wait_s``: how long to wait for room in the mapper queue before 429 (None: forever,
        calling ``on_busy`` once first — the websocket's "busy" notice).

        One function on purpose: the checks, the wait for room and the sequence numbers form a single
        critical section under the ingest lock, read best top to bottom."""
        async with self._lock:
            if self.closed:
                raise NotFound()
            if self.error:
                raise IngestError(503, f"session {self.id} cannot take inputs: {self.error}")
            first = items[0]
            last_t = self.last_times.get(first.kind)
            if not model.follows(last_t, first.t):
                raise IngestError(
                    409,
                    f"{first.kind} timestamp {first.t!r} does not follow the session's previous "
                    f"{first.kind} at {last_t!r}",
                )
            check_time_jump(first.kind, first.t, self.last_t, self.settings)
            sizes = [input_bytes(a) for a in items]
            nbytes = sum(sizes)
            if not self._has_room(len(items), nbytes):
                if wait_s is None and on_busy is not None:
                    await on_busy()
                deadline = None if wait_s is None else self.loop.time() + wait_s
                while not self._has_room(len(items), nbytes):
                    if self.closed:
                        raise NotFound()
                    self._room.clear()
                    remaining = None if deadline is None else deadline - self.loop.time()
                    if remaining is not None and remaining <= 0:
                        raise IngestError(
                            429,
                            f"session {self.id} is busy: {self.pending} inputs "
                            f"({self.pending_bytes / 1e6:.1f} MB of images) wait for the mapper "
                            f"(limits {self.settings.max_pending} inputs, "
                            f"{self.settings.max_pending_bytes / 1e6:.0f} MB); retry later",
                            retry_after=1,
                        )
                    try:
                        await asyncio.wait_for(self._room.wait(), remaining)
                    except asyncio.TimeoutError:
                        pass
            seq0 = self.next_seq
            records = [InputRecord(seq=seq0 + k, kind=a.kind, t=a.t, data=a.data) for k, a in enumerate(items)]
            work = [WorkItem(seq0 + k, a.value) for k, a in enumerate(items)]
            worker = self.worker
            try:
                cfut = self.store.append_inputs(self.id, records, on_durable=lambda: worker.put(work))
            except StoreDead as exc:
                raise IngestError(503, f"inputs cannot be stored: {exc}") from None
            self.next_seq += len(items)
            for a in items:
                self.last_times[a.kind] = a.t
            self.pending += len(items)
            self.pending_bytes += nbytes
            for k, size in enumerate(sizes):
                if size:
                    self._pending_sizes[seq0 + k] = size
        last = seq0 + len(items) - 1
        kinds = Counter(a.kind for a in items)
        # the commit completes `cfut` in the writer thread; the bookkeeping and `done` follow on the loop
        # (batched with the other completions of the same commit). A caller that stops waiting (a websocket
        # closed mid-ack) cancels only `done`: the write, its bookkeeping and the store's writer go on
        done = self.loop.create_future()
        cfut.add_done_callback(lambda f: self.calls.call(self._stored, f, last, kinds, done))
        return seq0, last, done

    def _stored(
        self, fut: Any, last: int, kinds: Counter[str] | None = None, done: asyncio.Future | None = None
    ) -> None:
        """On the loop, once the store has settled a write (``fut``, a concurrent future): record it and
        settle ``done``, the future the caller awaits, with the same outcome."""
        error = RuntimeError("the write was cancelled") if fut.cancelled() else fut.exception()
        if error is not None:
            # sequence numbers were promised but not stored: refuse further inputs rather than leave a gap
            self.store_error = f"storage failed: {error}"
            log.error("session %s: %s", self.id, self.store_error, extra={"session": self.id})
        else:
            self.stored_seq = max(self.stored_seq, last)
            if self.metrics is not None and kinds:
                for kind, n in kinds.items():  # durable now: the acknowledgement follows
                    self.metrics.inputs_accepted(self.id, kind, n)
        if done is not None and not done.done():
            if error is None:
                done.set_result(fut.result())
            else:
                done.set_exception(error)

    def _validate_frame(self, data: bytes, t: Any) -> Accepted:
        """The server's checks (:func:`~server.formats.ingest.check_frame`: decoded fully and strictly), then the
        model's own rules (:func:`server.runtime.model.check_frame`: e.g. large enough for the fovea).

        The model's rules look at the decoded image's shape and type only, but checking them runs the
        visual front end (resize and retina: about three quarters of the validation's CPU time, and the
        mapper does the same work again). So a shape and type the model accepted once in this session
        is not checked again; a refused one is checked every time (the refusal names the problem)."""
        accepted = check_frame(data, t, self.settings)
        image = accepted.value.image  # type: ignore[union-attr]
        key = (image.shape, image.dtype.str)
        if key not in self._frame_shapes_ok:
            try:
                model.check_frame(self.config, cast(Frame, accepted.value))
            except ValueError as exc:
                raise IngestError(422, str(exc)) from None
            self._frame_shapes_ok.add(key)
        return accepted

    async def validate_frame(self, data: bytes, t: Any) -> Accepted:
        """Validate an encoded frame off the event loop (decoding is CPU work): IngestError if bad."""
        return await asyncio.to_thread(self._validate_frame, data, t)

    # ---------------------------------------------------------------- state
    def stats(self) -> dict[str, Any]:
        w = self.worker
        # read before the mapper is asked: queries are answered between inputs, so the mapper's figures are at
        # least as new as this; read after, an input processed meanwhile would be counted but not in the figures
        processed_seq = w.processed_seq
        mapper_stats = model.json_safe(w.query(model.queries.Stats()) or {})
        return {
            "session": self.id,
            "inputs_stored": self.stored_seq + 1,
            "last_seq": self.stored_seq,
            "last_t": self.last_t,
            "last_odometry_t": self.last_times.get("odometry"),
            "last_frame_t": self.last_times.get("frame"),
            "processed_seq": processed_seq,
            "pending": self.queue_depth,
            "snapshot_seq": w.snapshot_seq,
            "replaying": w.replaying,
            "backend": {**w.host_info, "restarts": w.restarts},
            "backend_restarts": w.restarts,
            "error": self.error,
            "input_errors": w.input_errors,
            "last_input_error": w.last_input_error,
            "rejected": {str(k): v for k, v in sorted(self.rejected.items())},
            "mapper": mapper_stats,
        }
