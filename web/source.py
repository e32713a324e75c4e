"""What a session viewer reads: the :class:`SessionSource` interface, and an in-process session.

A session's :class:`~hippomap.mapper.Mapper` is mutated by the session's worker thread. The viewer
never holds it longer than a copy takes: :meth:`SessionSource.read` answers a typed read
(:mod:`hippomap.mapper_queries`) between two inputs, and every such read only copies (see
:mod:`web.snapshot`); everything heavier (geometry, colour maps, JPEG) happens afterwards in the
viewer's thread. A read is a value, not a function, so it reaches a mapper in another process too.

The mapper keeps no camera images (the visual memory stores fovea patches only), so images come
from the source too: the service reads them from its store (every frame it received is kept);
:class:`LocalSession` keeps the latest frame, the key frames and the recognised frames itself.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Iterable, Protocol, TypeVar, runtime_checkable

import numpy as np

from hippomap.config import HippomapConfig
from hippomap.inputs import Frame, Odometry
from hippomap.map_events import KeyframeLearned, MapEvent, RecognitionMade
from hippomap.mapper import Mapper
from hippomap.mapper_queries import Query

T = TypeVar("T")


@dataclass(frozen=True)
class CameraImage:
    """A camera frame as received: time stamp and uint8 image (gray or BGR). Not to be mutated."""

    t: float
    image: np.ndarray


@runtime_checkable
class SessionSource(Protocol):
    """A mapping session as the viewer sees it (read-only)."""

    @property
    def session_id(self) -> str: ...

    @property
    def title(self) -> str:
        """A human name for the page title and the landing page."""

    @property
    def closed(self) -> bool:
        """True once the session is gone (its viewer is then closed)."""

    def read(self, query: Query[T]) -> T | None:
        """The answer to ``query`` between two inputs of the session (queries only copy).
        None if the session has no mapper yet (e.g. while it is restored)."""

    def latest_frame(self) -> CameraImage | None:
        """The newest camera frame the session received, or None."""

    def frame_at(self, t: float) -> np.ndarray | None:
        """The camera frame with time stamp ``t`` (a recognition's query frame), or None."""

    def keyframe_image(self, frame_id: int) -> np.ndarray | None:
        """The image learned as key frame ``frame_id`` (the visual memory keeps only patches), or None."""

    def lag_s(self) -> float | None:
        """Seconds between receiving the newest input and the mapper having processed it (None: unknown)."""

    # Optional (looked up with getattr, so older sources still satisfy the protocol):
    #   def ground_truth(self, start: int = 0) -> np.ndarray | None
    # ground-truth poses rows ``start:`` as (K, 4) float (t, x, y, theta) in the ground truth's own
    # world frame (append-only), or None when the session has no ground truth.


def ground_truth_rows(source: "SessionSource", start: int) -> np.ndarray | None:
    """``source.ground_truth(start)`` if the source offers ground truth, else None."""
    fn = getattr(source, "ground_truth", None)
    if fn is None:
        return None
    rows = fn(start)
    return None if rows is None else np.asarray(rows, float).reshape(-1, 4)


class GrowingRows:
    """An append-only float table (thread-safe appends and reads of a suffix)."""

    def __init__(self, width: int) -> None:
        self._a = np.empty((256, width))
        self._n = 0
        self._lock = threading.Lock()

    def append(self, row) -> None:
        with self._lock:
            if self._n == len(self._a):
                grown = np.empty((2 * len(self._a), self._a.shape[1]))
                grown[: self._n] = self._a[: self._n]
                self._a = grown
            self._a[self._n] = row
            self._n += 1

    def since(self, start: int) -> np.ndarray:
        with self._lock:
            return self._a[max(0, int(start)) : self._n].copy()

    def __len__(self) -> int:
        return self._n


class _ImageCache:
    """A bounded, thread-safe map of images (oldest evicted first)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._d: OrderedDict[Any, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, key: Any, image: np.ndarray) -> None:
        with self._lock:
            self._d[key] = image
            self._d.move_to_end(key)
            while len(self._d) > self.capacity:
                self._d.popitem(last=False)

    def get(self, key: Any) -> np.ndarray | None:
        with self._lock:
            return self._d.get(key)


class LocalSession:
    """A mapper fed in-process (tests, benchmarks, the demo): a :class:`SessionSource` that owns its data.

    :meth:`step` and :meth:`observe` feed the mapper under the session lock and keep the images
    the viewer needs (the latest frame, each learned key frame, each recognition's query frame;
    at most ``image_capacity`` of the last two kinds).
    """

    def __init__(
        self,
        session_id: str = "local",
        mapper: Mapper | None = None,
        config: HippomapConfig | None = None,
        title: str = "",
        image_capacity: int = 2000,
    ) -> None:
        self._id = session_id
        self._title = title or session_id
        self.mapper = mapper if mapper is not None else Mapper(config)
        self.lock = threading.RLock()
        self._latest: CameraImage | None = None
        self._keyframes = _ImageCache(image_capacity)
        self._queries = _ImageCache(image_capacity)
        self._ground_truth = GrowingRows(4)
        self._received = 0.0  # wall time of the newest input handed to step/observe
        self._processed = 0.0
        self._closed = False

    @property
    def session_id(self) -> str:
        return self._id

    @property
    def title(self) -> str:
        return self._title

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        self._closed = True

    def read(self, query: Query[T]) -> T:
        with self.lock:
            return self.mapper.answer(query)

    def step(self, odometry: Odometry, gt: tuple[float, float, float] | None = None) -> list[MapEvent]:
        """Feed one odometry reading; ``gt`` (or the reading's own ``gt``, if it has one) is the true
        pose at its time, kept for the viewer (the mapper never sees it)."""
        self._received = time.monotonic()
        with self.lock:
            events = self.mapper.step(odometry)
        self._processed = time.monotonic()
        gt = gt if gt is not None else getattr(odometry, "gt", None)
        if gt is not None:
            self.add_ground_truth(odometry.t, gt)
        return events

    def add_ground_truth(self, t: float, pose: tuple[float, float, float]) -> None:
        """Record the true pose at time ``t`` (x, y, theta in the ground truth's frame)."""
        row = np.array([t, *pose], float)
        if row.shape != (4,) or not np.all(np.isfinite(row)):
            raise ValueError(f"ground truth must be a finite time and pose (x, y, theta), got {t!r}, {pose!r}")
        self._ground_truth.append(row)

    def ground_truth(self, start: int = 0) -> np.ndarray | None:
        """Ground-truth rows ``start:`` (t, x, y, theta), or None if the session has none."""
        return self._ground_truth.since(start) if len(self._ground_truth) else None

    def observe(self, frame: Frame) -> list[MapEvent]:
        self._received = time.monotonic()
        with self.lock:
            events = self.mapper.observe(frame)
        self._processed = time.monotonic()
        self._latest = CameraImage(frame.t, frame.image)
        for e in events:
            if isinstance(e, KeyframeLearned):
                self._keyframes.put(int(e.frame), frame.image)
            elif isinstance(e, RecognitionMade):
                self._queries.put(float(frame.t), frame.image)
        return events

    def feed(self, items: Iterable[Odometry | Frame]) -> int:
        """Feed inputs in order; returns how many were fed."""
        n = 0
        for item in items:
            self.step(item) if isinstance(item, Odometry) else self.observe(item)
            n += 1
        return n

    def latest_frame(self) -> CameraImage | None:
        return self._latest

    def frame_at(self, t: float) -> np.ndarray | None:
        return self._queries.get(float(t))

    def keyframe_image(self, frame_id: int) -> np.ndarray | None:
        return self._keyframes.get(int(frame_id))

    def lag_s(self) -> float | None:
        """Seconds the input being processed has waited (0 when the mapper is idle)."""
        if self._received == 0.0:
            return None
        return max(0.0, time.monotonic() - self._received) if self._received > self._processed else 0.0
