"""One live viewer per mapping session, and the hub that creates them on demand and closes idle ones.

A :class:`SessionViewer` owns a ``viser.ViserServer`` bound to 127.0.0.1 on a free port (never
exposed: the browser reaches it only through the FastAPI proxy of :mod:`web.routes`), the scene
layers and panels, and one update thread. The thread pushes, inside ``server.atomic()``:

* the camera image at ``camera_hz``;
* the map graph, trajectories, loop closures, place field, recognition and stats at ``graph_hz``,
  from a :class:`~web.snapshot.MapSnapshot` copied under the session lock.

While no browser is connected the thread idles (viser replays the latest scene state to a new
client, and the next tick brings it up to date). :class:`ViewerHub` creates a viewer on first
view and closes it after ``idle_timeout_s`` without a connection.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import viser

from hippomap.cognitive_map import LoopDecision

from .chunks import ChunkUpdate
from .images import pair_panel, placeholder
from .panel_camera import CameraPanel
from .panel_evidence import EvidencePanel
from .panel_layers import Layer, LayersPanel
from .panel_loops import LoopsPanel
from .panel_stats import StatsPanel
from .scene_loops import LoopLayer, LoopUpdate
from .scene_map import MapGraphLayer, MapUpdate
from .scene_place_field import PlaceFieldLayer
from .scene_pose import RobotMarker
from .scene_trajectories import TrajectoryLayer, TrajectoryUpdate
from .settings import ViewerSettings
from .snapshot import Cursor, MapSnapshot, take_snapshot
from .source import SessionSource

log = logging.getLogger(__name__)
_QUIET_LOCK = threading.Lock()


@contextlib.contextmanager
def _quiet_viser() -> Iterator[None]:
    """Swallow viser's console banners (its loopback URLs, "Server stopped"): the browser must use the
    service's URL, so printing viser's own would mislead. viser prints through rich's console."""
    import rich

    console = rich.get_console()
    with _QUIET_LOCK:  # console-wide (viser also prints from its own thread): one block at a time
        quiet, console.quiet = console.quiet, True
        try:
            yield
        finally:
            console.quiet = quiet


_NOTHING = ChunkUpdate((), 0)
_NO_MAP = MapUpdate(_NOTHING, _NOTHING, _NOTHING)
_NO_TRAJECTORY = TrajectoryUpdate(_NOTHING, _NOTHING)
_NO_LOOPS = LoopUpdate(_NOTHING, _NOTHING)


@dataclass(frozen=True)
class GraphUpdate:
    """What one graph update sent, and how long it took (seconds)."""

    map: MapUpdate
    trajectories: TrajectoryUpdate
    loops: LoopUpdate
    place_field: bool
    copy_s: float  # under the session lock
    build_s: float  # geometry, images and queueing, outside the lock

    @property
    def items_sent(self) -> int:
        parts = (self.map.nodes, self.map.links, self.map.loop_links, self.trajectories.odometry,
                 self.trajectories.corrected, self.loops.accepted, self.loops.rejected)
        return sum(p.items for p in parts)


class SessionViewer:
    """The live 3D view of one session (see module doc)."""

    def __init__(self, source: SessionSource, settings: ViewerSettings | None = None, start: bool = True) -> None:
        self.source = source
        self.settings = s = settings or ViewerSettings()
        with _quiet_viser():
            self.server = viser.ViserServer(host="127.0.0.1", port=0, label=f"hippomap · {source.title}",
                                            verbose=False)
        self.server.scene.set_up_direction("+z")
        # Lighting, measured in headless Chromium (software WebGL): viser's default environment map
        # costs two thirds of the frame time of a 10k-node map, shadows buy nothing on a flat map.
        # Thin lines are wireframe meshes whose degenerate triangles have no usable normals, so only
        # ambient light colours them: at 1.5 they show their own colour.
        self.server.scene.configure_environment_map(None)
        self.server.scene.configure_default_lights(True, cast_shadow=False)
        self.server.scene.add_light_ambient("/lights/ambient", intensity=1.5)
        self.server.gui.configure_theme(show_share_button=False, control_width="large")
        # a browser may still send viser's "share URL" request, which would open a public tunnel
        # around the service's authentication: refuse it (viser looks the method up per request)
        self.server.request_share_url = lambda *args, **kwargs: None  # type: ignore[method-assign]
        self._update_lock = threading.Lock()
        self._cursor = Cursor()
        self._snapshot: MapSnapshot | None = None
        self._view_extent = 0.0
        scene, gui = self.server.scene, self.server.gui
        with self.server.atomic():
            self.map = MapGraphLayer(scene, s)
            self.trajectories = TrajectoryLayer(scene, s)
            self.loops = LoopLayer(scene, s)
            self.place_field = PlaceFieldLayer(scene, s)
            self.robot = RobotMarker(scene, s)
            with gui.add_folder("Camera"):
                self.camera = CameraPanel(gui, s)
            with gui.add_folder("Evidence"):
                self.evidence = EvidencePanel(gui, self._decision_threshold())
            with gui.add_folder("Session"):
                self.stats = StatsPanel(gui)
            with gui.add_folder("Layers", expand_by_default=False):
                self.layers = LayersPanel(gui, [
                    Layer("map nodes", True, lambda v: self.map.set_visible(nodes=v)),
                    Layer("map links", True, lambda v: self.map.set_visible(links=v)),
                    Layer("odometry trajectory (orange)", True, lambda v: self.trajectories.set_visible(odometry=v)),
                    Layer("map trajectory (blue)", True, lambda v: self.trajectories.set_visible(corrected=v)),
                    Layer("accepted loop closures", True, lambda v: self.loops.set_visible(accepted=v)),
                    Layer("rejected loop closures", False, lambda v: self.loops.set_visible(rejected=v)),
                    Layer("place field", True, lambda v: setattr(self.place_field, "visible", v)),
                    Layer("robot", True, lambda v: setattr(self.robot, "visible", v)),
                ])
            with gui.add_folder("Loop closures"):
                self.loop_list = LoopsPanel(gui, self._select_loop, s.max_loops_listed, s.thumbnail_width)
        self.created = time.monotonic()
        self.last_seen = self.created
        self.connections = 0
        self.updates = 0
        self.last_update: GraphUpdate | None = None
        self.errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        try:
            self.update_graph()
        except Exception:  # a broken snapshot must not keep the page from opening; the thread retries
            self.errors += 1
            log.exception("viewer %s: first update failed", source.session_id)
        if start:
            self._thread = threading.Thread(target=self._run, name=f"viewer-{source.session_id}", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ properties
    @property
    def session_id(self) -> str:
        return self.source.session_id

    @property
    def port(self) -> int:
        """The loopback port of this viewer's viser server."""
        return int(self.server.get_port())

    @property
    def closed(self) -> bool:
        return self._stop.is_set()

    def _decision_threshold(self) -> float:
        value = self.source.read(lambda m: m.config.visual.decision_threshold)
        return float(value) if value is not None else 0.9

    # ------------------------------------------------------------------ updates
    def update_graph(self) -> GraphUpdate | None:
        """Copy a snapshot under the session lock and push what changed (thread-safe).

        Returns None when the session has no mapper yet (a service session still restoring)."""
        with self._update_lock:
            t0 = time.perf_counter()
            cursor = self._cursor
            snap = self.source.read(lambda m: take_snapshot(m, cursor))
            if snap is None:
                return None
            t1 = time.perf_counter()
            if snap.same_scene_as(self._snapshot) and not self.place_field.pending(snap.place_field):
                with self.server.atomic():
                    self.stats.update(snap.stats, self.source.lag_s())
                update = GraphUpdate(_NO_MAP, _NO_TRAJECTORY, _NO_LOOPS, False, t1 - t0, time.perf_counter() - t1)
                self.last_update = update
                self.updates += 1
                return update
            with self.server.atomic():
                mu = self.map.update(snap)
                tu = self.trajectories.update(snap)
                lu = self.loops.update(snap)
                pf = self.place_field.update(snap.place_field)
                self.robot.update(snap.robot_pose)
                rec = snap.last_recognition
                if rec is not None and self.evidence.update(rec):
                    query = self.source.frame_at(float(rec["t"]))
                    fid = rec.get("frame_id")
                    key = None if fid is None else self.source.keyframe_image(int(fid))
                    self.camera.update_recognition(rec, query, key)
                self.stats.update(snap.stats, self.source.lag_s())
                self.loop_list.update(snap.decisions)
                self._frame_view(snap)
            self._cursor = snap.cursor
            self._snapshot = snap
            selected = self.loop_list.selected_id
            if selected is not None and selected < len(snap.decisions):
                self.loops.select(snap.decisions[selected], snap.node_poses)
            update = GraphUpdate(mu, tu, lu, pf, t1 - t0, time.perf_counter() - t1)
            self.last_update = update
            self.updates += 1
            return update

    def update_camera(self) -> bool:
        """Push the newest camera frame if it changed."""
        frame = self.source.latest_frame()
        return self.camera.update_live(frame)

    def _frame_view(self, snap: MapSnapshot) -> None:
        """Point the initial ('reset view') camera at the map when it has grown noticeably."""
        if not len(snap.node_poses):
            return
        xy = snap.node_poses[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        extent = float(max(np.max(hi - lo), 2.0))
        if extent <= 1.25 * self._view_extent:
            return
        self._view_extent = extent
        c = 0.5 * (lo + hi)
        cam = self.server.initial_camera
        cam.look_at = (float(c[0]), float(c[1]), 0.0)
        cam.position = (float(c[0]), float(c[1] - 0.6 * extent), float(1.1 * extent))

    def _select_loop(self, decision_id: int | None) -> None:
        """Panel callback: show a loop closure's frames and trace, and mark it in the scene."""
        with self._update_lock:
            self._show_loop(decision_id)

    def _show_loop(self, decision_id: int | None) -> None:
        snap = self._snapshot
        if snap is None or decision_id is None or decision_id >= len(snap.decisions):
            self.loops.select(None, np.zeros((0, 3)))
            self.loop_list.show(None, None)
            return
        d: LoopDecision = snap.decisions[decision_id]
        rid = d.hypothesis.meta.get("recognition")
        rec = None
        if rid is not None:
            rec = self.source.read(lambda m: m.recognitions[rid] if 0 <= rid < len(m.recognitions) else None)
        w = self.settings.thumbnail_width
        if rec is not None:
            query = self.source.frame_at(float(rec["t"]))
            fid = rec.get("frame_id")
            key = None if fid is None else self.source.keyframe_image(int(fid))
            image = pair_panel(query, rec, key, w)
        else:
            image = placeholder(2 * w + 4, w * 3 // 4, f"{d.hypothesis.source} hypothesis: no images")
        with self.server.atomic():
            self.loop_list.show(d, image)
            self.loops.select(d, snap.node_poses)

    def _run(self) -> None:
        s = self.settings
        tick = 1.0 / max(s.camera_hz, s.graph_hz)
        next_graph = 0.0
        while not self._stop.wait(tick):
            if not self.server.get_clients():
                continue
            try:
                with self.server.atomic():
                    self.update_camera()
                now = time.monotonic()
                if now >= next_graph:
                    next_graph = now + 1.0 / s.graph_hz
                    self.update_graph()
            except Exception:  # keep the viewer alive; the next tick retries
                self.errors += 1
                log.exception("viewer %s: update failed", self.session_id)

    # ------------------------------------------------------------------ lifecycle
    def touch(self) -> None:
        self.last_seen = time.monotonic()

    def close(self) -> None:
        """Stop the update thread and the viser server (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        with _quiet_viser():
            self.server.stop()


class ViewerHub:
    """The session viewers of one process: created on first view, closed when idle.

    Thread-safe. :meth:`open` may block (it starts a viser server and copies the first snapshot):
    call it from a worker thread, not from the event loop. The proxy reports connections with
    :meth:`connected` / :meth:`disconnected`; a reaper thread closes viewers that have had no
    connection for ``idle_timeout_s``.
    """

    def __init__(self, settings: ViewerSettings | None = None, reap_every_s: float | None = None) -> None:
        self.settings = settings or ViewerSettings()
        self._viewers: dict[str, SessionViewer] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        period = reap_every_s if reap_every_s is not None else min(10.0, self.settings.idle_timeout_s / 4)
        self._reaper = threading.Thread(target=self._reap_loop, args=(period,), name="viewer-reaper", daemon=True)
        self._reaper.start()

    def open(self, source: SessionSource) -> SessionViewer:
        """The session's viewer, created if there is none (blocking)."""
        with self._lock:
            v = self._viewers.get(source.session_id)
            if v is not None and not v.closed:
                v.touch()
                return v
            v = SessionViewer(source, self.settings)
            self._viewers[source.session_id] = v
            return v

    def get(self, session_id: str) -> SessionViewer | None:
        with self._lock:
            v = self._viewers.get(session_id)
            return None if v is None or v.closed else v

    def connected(self, viewer: SessionViewer) -> None:
        with self._lock:
            viewer.connections += 1
            viewer.touch()

    def disconnected(self, viewer: SessionViewer) -> None:
        with self._lock:
            viewer.connections = max(0, viewer.connections - 1)
            viewer.touch()

    def close(self, session_id: str) -> None:
        """Close a session's viewer (e.g. when the session is deleted)."""
        with self._lock:
            v = self._viewers.pop(session_id, None)
        if v is not None:
            v.close()

    def reap(self, now: float | None = None) -> list[str]:
        """Close viewers idle for longer than ``idle_timeout_s``; returns their session ids."""
        now = time.monotonic() if now is None else now
        with self._lock:
            idle = [sid for sid, v in self._viewers.items()
                    if v.closed or v.source.closed
                    or (v.connections == 0 and now - v.last_seen > self.settings.idle_timeout_s)]
            victims = [self._viewers.pop(sid) for sid in idle]
        for v in victims:
            v.close()
        return idle

    def _reap_loop(self, period: float) -> None:
        while not self._stop.wait(period):
            try:
                self.reap()
            except Exception:
                log.exception("viewer reaper failed")

    @property
    def session_ids(self) -> list[str]:
        with self._lock:
            return list(self._viewers)

    def close_all(self) -> None:
        self._stop.set()
        with self._lock:
            victims = list(self._viewers.values())
            self._viewers.clear()
        for v in victims:
            v.close()
