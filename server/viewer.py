"""The service's one wiring to the viewer: live sessions as :class:`web.source.SessionSource`.

Package ``web`` knows nothing of the service: it draws any :class:`~web.source.SessionSource` and
asks a :class:`web.routes.ViewerAccess` which sessions a browser's token may see. This module is the
only place in ``server`` that imports ``web`` (an import-linter contract in ``pyproject.toml``), so
the dependency runs one way, from the service to the viewer.

The service keeps one :class:`server.runtime.live_session.LiveSession` per session, whose worker
thread feeds a Mapper under ``worker.lock`` and answers ``worker.query(query)`` (a typed read of
:mod:`hippomap.mapper_queries`) between inputs; every
input it acknowledged is in its store (frames as received). This module adapts that to the
viewer's two interfaces, reading ``app.state`` lazily (it is filled by the app's lifespan):

* :class:`ServiceAccess` — :class:`web.routes.ViewerAccess` over the service's tokens: a token sees
  exactly the sessions ``GET /sessions`` shows it (viewer tokens included), others are 404.
* :class:`ServiceSession` — :class:`web.source.SessionSource` over one live session: the mapper via
  ``worker.query``; the latest processed frame, recognition query frames and learned key frames
  decoded from the store (key frames are found through the session's ``keyframe_learned`` events).

Integration (the one call in ``server/app.py``): ``mount_viewer(app)``.
"""

from __future__ import annotations

import json
import threading
from typing import Any, TypeVar

import numpy as np
from fastapi import APIRouter, FastAPI

from hippomap.mapper_queries import LastInputTime, Query
from web.landing import router as landing_router
from web.routes import SessionEntry, make_router
from web.session_viewer import ViewerHub
from web.settings import ViewerSettings
from web.source import CameraImage

from .formats.ingest import frame_from_bytes
from .runtime.sessions import LiveSession, NotFound, ServedElsewhere
from .storage.store import Store

T = TypeVar("T")

LOOKBACK = 32  # inputs searched backwards for the newest processed frame
GT_BATCH = 2000  # stored inputs scanned for ground-truth poses per viewer update


def _decode(t: float, data: bytes) -> np.ndarray | None:
    try:
        return frame_from_bytes(t, data).image
    except Exception:  # a stored frame that no longer decodes is shown as missing, not fatal
        return None


class ServiceSession:
    """One live service session as a :class:`~web.source.SessionSource`."""

    def __init__(self, live: LiveSession, store: Store) -> None:
        self.live = live
        self.store = store
        self._lock = threading.Lock()
        self._latest: CameraImage | None = None
        self._latest_seq = -1
        self._keyframe_t: dict[int, float] = {}
        self._events_seen = -1
        self._gt: list[tuple[float, float, float, float]] = []  # (t, x, y, theta) of odometry readings with gt
        self._gt_seq = -1  # inputs scanned for ground truth so far

    @property
    def session_id(self) -> str:
        return self.live.id

    @property
    def title(self) -> str:
        return self.live.record.name or self.live.id

    @property
    def closed(self) -> bool:
        return bool(self.live.closed)

    def read(self, query: Query[T]) -> T | None:
        """The answer to ``query`` between two inputs of the worker (None while the session restores)."""
        return self.live.worker.query(query)

    def latest_frame(self) -> CameraImage | None:
        seq = int(self.live.worker.processed_seq)
        with self._lock:
            if seq <= self._latest_seq:
                return self._latest
            recs = self.store.read_inputs(self.session_id, max(-1, seq - LOOKBACK), LOOKBACK + 1, with_data=False)
            frames = [r for r in recs if r.kind == "frame" and r.seq <= seq]
            if frames and frames[-1].seq > self._latest_seq:
                rec = self.store.input_by_seq(self.session_id, frames[-1].seq)
                image = None if rec is None else _decode(rec.t, rec.data)
                if rec is not None and image is not None:
                    self._latest = CameraImage(rec.t, image)
                    self._latest_seq = rec.seq
            return self._latest

    def frame_at(self, t: float) -> np.ndarray | None:
        rec = self.store.frame_at(self.session_id, float(t))
        return None if rec is None else _decode(rec.t, rec.data)

    def keyframe_image(self, frame_id: int) -> np.ndarray | None:
        with self._lock:
            if int(frame_id) not in self._keyframe_t:
                while True:
                    evs = self.store.query_events(
                        self.session_id, types=["keyframe_learned"], since_id=self._events_seen, limit=1000
                    )
                    for e in evs:
                        self._keyframe_t[int(e.data["frame"])] = float(e.data["t"])  # KeyframeLearned
                    if not evs:
                        break
                    self._events_seen = evs[-1].id
            t = self._keyframe_t.get(int(frame_id))
        return None if t is None else self.frame_at(t)

    def ground_truth(self, start: int = 0) -> np.ndarray | None:
        """Ground-truth rows ``start:`` (t, x, y, theta) from the stored odometry readings that carry a
        ``gt`` pose (read incrementally, at most GT_BATCH inputs per call), or None if none has."""
        with self._lock:
            recs = self.store.read_inputs(self.session_id, self._gt_seq, GT_BATCH, with_data=True)
            for r in recs:
                if r.kind == "odometry" and b'"gt"' in r.data:
                    d = json.loads(r.data)
                    g = d.get("gt")
                    if g is not None and len(g) == 3:
                        self._gt.append((float(d["t"]), float(g[0]), float(g[1]), float(g[2])))
            if recs:
                self._gt_seq = recs[-1].seq
            if not self._gt:
                return None
            return np.array(self._gt[max(0, int(start)) :], dtype=float).reshape(-1, 4)

    def lag_s(self) -> float | None:
        """Stream seconds between the newest input received and the newest the mapper processed."""
        received = self.live.last_t
        processed = self.read(LastInputTime())
        if received is None or processed is None:
            return None
        return max(0.0, float(received) - float(processed))


class ServiceAccess:
    """:class:`web.routes.ViewerAccess` over a service app's tokens and live sessions."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self._sources: dict[str, ServiceSession] = {}
        self._lock = threading.Lock()

    def _token(self, secret: str | None) -> Any:
        auth = getattr(self.app.state, "auth", None)
        return None if auth is None else auth.authenticate(secret)

    def list_sessions(self, token: str | None) -> list[SessionEntry] | None:
        tok = self._token(token)
        if tok is None:
            return None
        lives = sorted(self.app.state.manager.visible(tok), key=lambda s: -s.record.created)
        return [SessionEntry(s.id, s.record.name or s.id, "error: " + s.error if s.error else "") for s in lives]

    def open_session(self, token: str | None, session_id: str) -> ServiceSession | None:
        tok = self._token(token)
        if tok is None:
            return None
        try:
            live = self.app.state.manager.get(tok, session_id)
        except (NotFound, ServedElsewhere):  # another replica's viewer shows it
            return None
        with self._lock:
            src = self._sources.get(session_id)
            if src is None or src.live is not live:
                src = self._sources[session_id] = ServiceSession(live, self.app.state.store)
            return src


def viewer_router(app: Any, settings: ViewerSettings | None = None) -> APIRouter:
    """The viewer's routes for a service app (include it with ``app.include_router``)."""
    hub = ViewerHub(settings)
    app.state.viewer_hub = hub
    return make_router(ServiceAccess(app), hub)


def mount_viewer(app: FastAPI, settings: ViewerSettings | None = None) -> None:
    """Mount the viewer on a service app: ``/viewer/`` (:mod:`web.routes`) and the landing page ``/``."""
    app.include_router(viewer_router(app, settings))
    app.include_router(landing_router)
