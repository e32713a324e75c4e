"""One live viewer per mapping session, and the hub that creates them on demand and closes idle ones.

A :class:`SessionViewer` owns a ``viser.ViserServer`` bound to 127.0.0.1 on a free port (never
exposed: the browser reaches it only through the FastAPI proxy of :mod:`web.routes`, and it answers
403 to any connection without the viewer's random key, which only the proxy sends), the scene
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
import hmac
import logging
import secrets
import threading
import time
from dataclasses import dataclass
from typing import Iterator, cast

import numpy as np
import viser

from hippomap.cognitive_map import LoopDecision
from hippomap.mapper_queries import MapperConfig, PlaceCellIteration, RecognitionById

from .images import pair_panel, placeholder
from .panels.camera import CameraPanel
from .panels.evidence import EvidencePanel
from .panels.layers import layer_specs, legend_html
from .panels.loops import LoopsPanel
from .panels.place_cells import PlaceCellsPanel
from .panels.stats import StatsPanel
from .panels.view import ClientViews
from .scene.camera_fit import fit_camera, map_bounds
from .scene.chunks import ChunkUpdate
from .scene.ground_truth import GroundTruthLayer
from .scene.loops import LoopLayer, LoopUpdate
from .scene.map import MapGraphLayer, MapUpdate
from .scene.place_field import PlaceFieldLayer
from .scene.placement import Placement, map_poses, placement
from .scene.pose import RobotMarker
from .scene.trajectories import TrajectoryLayer, TrajectoryUpdate
from .settings import ViewerSettings
from .snapshot import Cursor, MapSnapshot, take_snapshot
from .source import SessionSource, ground_truth_rows

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


#: the header the proxy (:mod:`web.routes`) sends with each session viewer's secret key
KEY_HEADER = "X-Hippomap-Viewer-Key"


def require_key(server: viser.ViserServer, key: str) -> None:
    """Make ``server`` refuse (HTTP 403) every request and websocket that does not carry ``key`` in
    :data:`KEY_HEADER`: its loopback port is open to every local user, the key only to the proxy.

    viser has no hook for this: its websockets server checks each opening handshake with the
    server's ``process_request`` attribute (read per connection), which is wrapped here. Clients
    that connected before the wrap (the first milliseconds) are disconnected; the scene is still
    empty then. Raises RuntimeError if viser's server cannot be found (a viser upgrade changed it)."""
    import gc
    from http import HTTPStatus

    from websockets.asyncio.server import Server

    infra = server._websock_server
    loop, port = infra._background_event_loop, server.get_port()
    found = [
        o
        for o in gc.get_objects()
        if type(o) is Server
        and o.loop is loop
        and any(sock.getsockname()[1] == port for sock in (o.server.sockets if o.server else ()))
    ]
    if len(found) != 1:
        raise RuntimeError(f"cannot secure the viewer's viser server on port {port}: found {len(found)} servers")
    ws_server = found[0]
    viser_http = ws_server.process_request
    expected = key.encode()

    def process_request(connection, request):  # noqa: ANN001, ANN202 (websockets' signature)
        given = request.headers.get(KEY_HEADER, "")
        if not hmac.compare_digest(given.encode("utf-8", "replace"), expected):
            return connection.respond(HTTPStatus.FORBIDDEN, "forbidden: connect through the hippomap service\n")
        return None if viser_http is None else viser_http(connection, request)

    ws_server.process_request = process_request
    infra.disconnect_all_clients()


_NOTHING = ChunkUpdate((), 0)
_NO_MAP = MapUpdate(_NOTHING, _NOTHING, _NOTHING)
_NO_TRAJECTORY = TrajectoryUpdate(_NOTHING, _NOTHING)
_NO_LOOPS = LoopUpdate(_NOTHING, _NOTHING, _NOTHING)


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
        parts = (
            self.map.nodes,
            self.map.links,
            self.map.loop_links,
            self.trajectories.odometry,
            self.trajectories.corrected,
            self.loops.accepted,
            self.loops.rejected,
        )
        return sum(p.items for p in parts)


class SessionViewer:
    """The live 3D view of one session (see module doc)."""

    def __init__(self, source: SessionSource, settings: ViewerSettings | None = None, start: bool = True) -> None:
        self.source = source
        self.settings = s = settings or ViewerSettings()
        self._start_server(source)
        self._update_lock = threading.Lock()
        self._cursor = Cursor()
        self._snapshot: MapSnapshot | None = None
        self._view_extent = 0.0
        self._build_scene(s)
        # per browser: layer toggles, time slider, camera fitted to the map (web.panels.view)
        self.views = ClientViews(self.server, self.layer_specs, s, self._view_state)
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

    def _start_server(self, source: SessionSource) -> None:
        """The session's loopback viser server: locked by an access key, lit and themed, its share URL refused."""
        with _quiet_viser():
            self.server = viser.ViserServer(host="127.0.0.1", port=0, label=f"hippomap · {source.title}", verbose=False)
        #: the secret the proxy sends in KEY_HEADER: without it the loopback server answers 403
        self.access_key = secrets.token_urlsafe(32)
        try:
            require_key(self.server, self.access_key)
        except Exception:
            with _quiet_viser():
                self.server.stop()
            raise
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

    def _build_scene(self, s: ViewerSettings) -> None:
        """The layers of the 3D scene and the GUI panels (legend, camera, evidence, session, place cells, loops)."""
        scene, gui = self.server.scene, self.server.gui
        with self.server.atomic():
            self.map = MapGraphLayer(scene, s)
            self.trajectories = TrajectoryLayer(scene, s)
            self.loops = LoopLayer(scene, s)
            self.place_field = PlaceFieldLayer(scene, s)
            self.robot = RobotMarker(scene, s)
            self.ground_truth = GroundTruthLayer(scene, s)
            self.layer_specs = layer_specs(s)
            # the legend floats on the canvas, always visible (bottom left; the controls float top right)
            self.legend_panel = gui.add_panel()
            with self.legend_panel.add_tab("Legend"):
                self.legend = gui.add_html(legend_html(self.layer_specs, ground_truth=False))
            self.legend_panel.float(x=12, y=-12, width=250)
            with gui.add_folder("Camera"):
                self.camera = CameraPanel(gui, s)
            with gui.add_folder("Evidence"):
                self.evidence = EvidencePanel(gui, self._decision_threshold())
            with gui.add_folder("Session"):
                self.stats = StatsPanel(gui)
            with gui.add_folder("Place cells (Fig. 8)"):
                self.place_cells = PlaceCellsPanel(gui, self._record_place_cells)
            with gui.add_folder("Loop closures"):
                self.loop_list = LoopsPanel(gui, self._select_loop, s.max_loops_listed, s.thumbnail_width)

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
        config = self.source.read(MapperConfig())
        return float(config.visual.decision_threshold) if config is not None else 0.9

    # ------------------------------------------------------------------ updates
    def update_graph(self) -> GraphUpdate | None:
        """Copy a snapshot under the session lock and push what changed (thread-safe).

        Returns None when the session has no mapper yet (a service session still restoring)."""
        with self._update_lock:
            t0 = time.perf_counter()
            cursor = self._cursor
            snap = take_snapshot(self.source, cursor)
            if snap is None:
                return None
            t1 = time.perf_counter()
            gt_rows = ground_truth_rows(self.source, self.ground_truth.seen)
            new_gt = gt_rows is not None and len(gt_rows) > 0
            if snap.same_scene_as(self._snapshot) and not self.place_field.pending(snap.place_field) and not new_gt:
                with self.server.atomic():
                    self.stats.update(snap.stats, self.source.lag_s())
                update = GraphUpdate(_NO_MAP, _NO_TRAJECTORY, _NO_LOOPS, False, t1 - t0, time.perf_counter() - t1)
                self.last_update = update
                self.updates += 1
                return update
            placed = placement(snap.stats, snap.decisions)
            with self.server.atomic():
                mu = self.map.update(snap)
                tu = self.trajectories.update(snap, placed)
                lu = self.loops.update(snap, placed.hides_lost_decisions)
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
                had_gt = self.ground_truth.present
                self.ground_truth.update(gt_rows, self._ground_truth_origin(snap, placed))
                if self.ground_truth.present and not had_gt:
                    self.legend.content = legend_html(self.layer_specs, ground_truth=True)
                self._frame_view(snap)
            self._cursor = snap.cursor
            self._snapshot = snap
            self.views.after_update()
            if not self.place_cells.drawn and snap.place_field is not None:
                self.place_cells.request()
            selected = self.loop_list.selected_id
            if selected is not None and selected < len(snap.decisions):
                weight = float(snap.loop_weights[selected])
                self.loops.select(snap.decisions[selected], snap.node_poses, weight)
                with self.server.atomic():
                    self.loop_list.refresh(snap.decisions[selected], weight)
            update = GraphUpdate(mu, tu, lu, pf, t1 - t0, time.perf_counter() - t1)
            self.last_update = update
            self.updates += 1
            return update

    def update_camera(self) -> bool:
        """Push the newest camera frame if it changed."""
        frame = self.source.latest_frame()
        return self.camera.update_live(frame)

    def _ground_truth_origin(self, snap: MapSnapshot, placed: Placement) -> np.ndarray | None:
        """The row (t, x, y, theta) the ground truth's pose at ``t`` is put on (None: not yet).

        A fresh run starts the map: its first trajectory row, at its odometric pose. A run in a saved
        map starts at an unknown pose of the base's frame, so its ground truth waits for the
        placement and is put on the first row on the map, at that row's map pose (the origin
        alignment of trajectory evaluation, taken where the run's map pose begins)."""
        samples = self.trajectories.sampler.samples
        if not placed.based:
            return samples[0] if len(samples) else None
        on_map = samples[samples[:, 0] >= placed.on_map_from_t][:1]
        if placed.lost or not len(on_map):
            return None
        return np.r_[on_map[0, 0], map_poses(on_map, snap.node_poses)[0]]

    def _frame_view(self, snap: MapSnapshot) -> None:
        """Fit the initial ('reset view') camera to the map when it has grown noticeably (each browser's
        own camera is fitted by :mod:`web.panels.view`)."""
        box = map_bounds(snap.node_poses, self.ground_truth.samples[:, 1:3])
        if box is None:
            return
        lo, hi = box
        extent = float(np.max(hi - lo))
        if extent <= 1.25 * self._view_extent:
            return
        self._view_extent = extent
        cam = self.server.initial_camera
        pos, look = fit_camera(lo, hi, float(cam.fov), 1.6, self.settings.fit_margin, covered=0.3, covered_left=0.18)
        # position first: viser may carry look_at along with it
        cam.position = cast(tuple[float, float, float], tuple(float(v) for v in pos))
        cam.look_at = cast(tuple[float, float, float], tuple(float(v) for v in look))

    def _view_state(self) -> tuple[MapSnapshot | None, np.ndarray, np.ndarray | None]:
        """What a browser's view needs: the latest snapshot, the sampled trajectory, the ground truth
        in the map frame (None if the session has none)."""
        gt = self.ground_truth.samples if self.ground_truth.present else None
        return self._snapshot, self.trajectories.sampler.samples.copy(), None if gt is None else gt[:, :4].copy()

    def _record_place_cells(self):
        """The current step's place-cell iteration, recorded (None before the first odometry step)."""
        return self.source.read(PlaceCellIteration())

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
            rec = self.source.read(RecognitionById(int(rid)))
        w = self.settings.thumbnail_width
        if rec is not None:
            query = self.source.frame_at(float(rec["t"]))
            fid = rec.get("frame_id")
            key = None if fid is None else self.source.keyframe_image(int(fid))
            image = pair_panel(query, rec, key, w)
        else:
            image = placeholder(2 * w + 4, w * 3 // 4, f"{d.hypothesis.source} hypothesis: no images")
        weight = float(snap.loop_weights[decision_id])
        with self.server.atomic():
            self.loop_list.show(d, image, weight)
            self.loops.select(d, snap.node_poses, weight)

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
        self.place_cells.closed = True
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
            idle = [
                sid
                for sid, v in self._viewers.items()
                if v.closed
                or v.source.closed
                or (v.connections == 0 and now - v.last_seen > self.settings.idle_timeout_s)
            ]
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
