"""Where a session's mapper runs: the :class:`MapperHost` interface and its in-process implementation.

The session worker (:mod:`server.runtime.worker`) owns everything about a session's durability —
which inputs to feed, in which order, the derived records and snapshots it writes to the
store, restore and replay — and talks to the mapper only through a host:

* :meth:`MapperHost.restore` — load a snapshot (or start a fresh mapper from the config);
* :meth:`MapperHost.process` — feed a batch of inputs in order; per input, the events it caused
  (``MapEvent.to_dict``, JSON-ready: one schema, one time key ``t``), the place-field blob of an
  odometry step whose field changed, and the seconds the mapper spent (measured where the mapper
  runs);
* :meth:`MapperHost.snapshot` — the mapper state as bytes (``Mapper.to_bytes``);
* :meth:`MapperHost.query` — the answer to a typed read (a :mod:`hippomap.mapper_queries` value,
  picklable by the standard library) between two inputs (None before a restore);
* :meth:`MapperHost.close`.

Two implementations: :class:`InProcessHost` (the mapper in the server process; the default)
and :class:`server.runtime.ray_backend.RayHost` (the mapper in a Ray actor that wraps an
:class:`InProcessHost`, so the mapper logic exists once). A host whose mapper is gone (the
actor's process died) raises :class:`HostDied`; the worker then builds a new host and
restores it from the store. Nothing here imports Ray.
"""

from __future__ import annotations

import abc
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

from hippomap.config import HippomapConfig
from hippomap.errors import InputError
from hippomap.inputs import Frame, Odometry
from hippomap.map_events import InputFailed, InputRejected, MapEvent

from . import model

log = logging.getLogger("hippomap.server")

#: event type of an input the mapper raised on (recorded, skipped; the session goes on)
INPUT_FAILED = InputFailed.type

T = TypeVar("T")


class HostDied(RuntimeError):
    """The host lost its mapper (e.g. the Ray actor's process died): restore it from the store."""


@dataclass(frozen=True)
class StepResult:
    """What one input produced: ``events`` (``MapEvent.to_dict``, JSON-ready), ``field`` (place-field blob of an
    odometry step whose place field changed, else None) and ``seconds`` of mapper time."""

    seq: int
    kind: str
    t: float
    events: list[dict[str, Any]]
    field: bytes | None
    seconds: float


class MapperHost(abc.ABC):
    """One session's mapper, wherever it runs. Calls come from the session's worker thread,
    one at a time and in order; :meth:`query` may come from any thread at any time."""

    #: most inputs the worker hands over in one :meth:`process` call (1 in-process: no call overhead
    #: to amortise, and acks follow every input; larger for a remote host)
    max_batch: int = 1

    @abc.abstractmethod
    def restore(self, snapshot: bytes | None, config: HippomapConfig) -> dict[str, Any]:
        """Load ``snapshot`` (None: a fresh mapper of ``config``); returns the mapper's stats."""

    @abc.abstractmethod
    def process(self, batch: list[tuple[int, Odometry | Frame]]) -> list[StepResult]:
        """Feed ``(seq, input)`` pairs in order; one result per input."""

    @abc.abstractmethod
    def snapshot(self) -> bytes: ...

    @abc.abstractmethod
    def query(self, query: model.queries.Query[T]) -> T | None:
        """The answer to ``query`` between two inputs (None before a restore); InputError for a
        value that is not one of the model's queries."""

    def info(self) -> dict[str, Any]:
        """Where the mapper runs (shown in the session's stats)."""
        return {"kind": "inprocess"}

    def close(self) -> None:  # noqa: B027 (an optional hook: hosts holding nothing keep the no-op)
        """Release the mapper (idempotent)."""


class MapperGate:
    """How many in-process mappers may step at once (one per server by default), and the way they
    leave the event loop its turn.

    Why: the mappers run in threads beside the event loop, and a mapper step is mostly Python, so
    it holds the GIL. With one thread per session stepping at once, the loop — which reads every
    message, hands it to the store and sends its acknowledgement — queues for the GIL behind all
    of them, several switch intervals per message: acknowledgements waited for mapping work that
    they do not depend on. Through the gate only ``slots`` mappers contend for the GIL; the
    others wait on a lock, which costs no GIL. Mapping throughput is unchanged (GIL-bound work
    does not run faster in more threads), each session still processes its inputs in order, and
    the sessions take turns input by input. After each
    step the GIL is offered to the other threads (``time.sleep(0)``), so the loop does not wait
    for a switch interval to expire."""

    def __init__(self, slots: int = 1) -> None:
        if slots < 1:
            raise ValueError(f"slots must be >= 1, got {slots}")
        self.slots = slots
        self._sem = threading.Semaphore(slots)

    def __enter__(self) -> "MapperGate":
        self._sem.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._sem.release()
        time.sleep(0)  # release the GIL now: a waiting event loop runs before the next step


class RemoteHost(MapperHost):
    """A host whose mapper lives elsewhere (a child process, a Ray actor): every call is one
    request through :meth:`_call`; a query is checked here, before it is sent."""

    @abc.abstractmethod
    def _call(self, op: str, *args: Any) -> Any: ...

    def process(self, batch: list[tuple[int, Odometry | Frame]]) -> list[StepResult]:
        return self._call("process", batch)

    def snapshot(self) -> bytes:
        return self._call("snapshot")

    def query(self, query: model.queries.Query[T]) -> T | None:
        model.queries.check_query(query)  # refused here, before it is sent
        return self._call("query", query)


class InProcessHost(MapperHost):
    """The mapper in this process. :attr:`lock` is held while one input is processed, so a query
    always sees the mapper between two inputs; ``gate`` (shared by a server's hosts) bounds how
    many mappers step at once (:class:`MapperGate`)."""

    def __init__(self, gate: MapperGate | None = None) -> None:
        self.gate = gate
        self.lock = threading.Lock()
        self.mapper: model.MapperPort | None = None
        self._last_field: Any = None

    def restore(self, snapshot: bytes | None, config: HippomapConfig) -> dict[str, Any]:
        mapper = model.load_mapper(snapshot) if snapshot is not None else model.new_mapper(config)
        with self.lock:
            self.mapper = mapper
            self._last_field = None
            return mapper.stats()

    def process(self, batch: list[tuple[int, Odometry | Frame]]) -> list[StepResult]:
        if self.gate is None:
            return [self._one(seq, value) for seq, value in batch]
        out = []
        for seq, value in batch:
            with self.gate:
                out.append(self._one(seq, value))
        return out

    def _one(self, seq: int, value: Odometry | Frame) -> StepResult:
        if self.mapper is None:
            raise RuntimeError("process() before restore()")
        odometry = isinstance(value, Odometry)
        with self.lock:
            t0 = time.perf_counter()
            events: list[MapEvent]
            try:
                events = self.mapper.step(value) if isinstance(value, Odometry) else self.mapper.observe(value)
            except InputError as exc:  # validated at ingest, so only a model-side rule can get here
                events = [InputRejected(value.t, seq, str(exc))]
            except Exception as exc:  # noqa: BLE001 - an input the model cannot take must not stop the session
                # (deterministic: a replay of the same inputs fails, and is skipped, the same way)
                log.exception(
                    "input seq %d (t=%r) failed in the mapper (skipped): %s: %s", seq, value.t, type(exc).__name__, exc
                )
                events = [InputFailed(value.t, seq, f"{type(exc).__name__}: {exc}")]
            seconds = time.perf_counter() - t0
            field = self.mapper.place_field if odometry else None
        blob = None
        if odometry:
            if field is not None and field is not self._last_field and getattr(field, "field", None) is not None:
                blob = model.place_field_blob(field)
            self._last_field = field
        return StepResult(
            seq,
            "odometry" if odometry else "frame",
            float(value.t),
            [model.event_dict(ev) for ev in events],
            blob,
            seconds,
        )

    def snapshot(self) -> bytes:
        with self.lock:
            if self.mapper is None:
                raise RuntimeError("snapshot() before restore()")
            return self.mapper.to_bytes()

    def query(self, query: model.queries.Query[T]) -> T | None:
        model.queries.check_query(query)
        with self.lock:
            if self.mapper is None:
                return None
            return self.mapper.answer(query)

    def close(self) -> None:
        with self.lock:
            self.mapper = None


#: builds a fresh host for a session id (the worker calls it again after a host died)
HostFactory = Callable[[str], MapperHost]


def inprocess_factory(session_id: str) -> MapperHost:
    return InProcessHost()


def gated_factory(gate: MapperGate) -> HostFactory:
    """In-process hosts that share ``gate`` (the server's default backend)."""

    def factory(session_id: str) -> MapperHost:
        return InProcessHost(gate)

    return factory
