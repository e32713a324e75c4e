"""Panel: what one browser sees — its layer toggles, the time slider, and the camera fitted to the map.

Everything here is per browser (viser's client-scoped GUI and scene): two people watching the
same session each choose their own layers, replay time and camera.

* **Layers** (:class:`web.panels.layers.ClientLayers`): one checkbox per layer.
* **Time slider**: 0-100 % of the run so far; 100 % is the live map. Below it the browser's live
  layers are shadowed and :class:`web.scene.replay.ReplayLayer` draws the map as it was then.
* **Camera**: fitted to the map (nodes and ground truth) when the browser connects, and again
  whenever the map has grown by a quarter while "keep the map in view" is on; the button fits now.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any, Callable

import numpy as np

from ..scene.camera_fit import fit_camera, map_bounds
from ..scene.replay import ReplayLayer, replay_at, time_span
from ..settings import ViewerSettings
from .layers import ClientLayers, LayerSpec

log = logging.getLogger(__name__)

#: canvas pixels covered by the floating control panel ("large", right) and the legend (left)
PANEL_PX = 420.0
LEGEND_PX = 270.0


class ClientView:
    """One browser's view controls (see module doc)."""

    def __init__(
        self,
        client: Any,
        specs: list[LayerSpec],
        settings: ViewerSettings,
        state: Callable[[], tuple[Any, np.ndarray, np.ndarray | None]],
        on_layers: Callable[["ClientView"], None] | None = None,
    ) -> None:
        self.client, self.settings, self._state = client, settings, state
        self._lock = threading.RLock()
        self._fitted_extent = 0.0
        self._fit_pending = False
        self._on_layers = on_layers
        self.replay = ReplayLayer(client.scene, settings)
        gui = client.gui
        with gui.add_folder("View (this browser)", order=-100.0):
            self.slider = gui.add_slider(
                "map at (% of run)",
                min=0,
                max=100,
                step=1,
                initial_value=100,
                hint="Drag back to replay how the map grew; 100 = live",
            )
            self.replay_text = gui.add_markdown("live map")
            self.follow = gui.add_checkbox("keep the map in view", initial_value=True)
            self.fit_button = gui.add_button("fit view to the map")
            self.layers = ClientLayers(client, specs, on_change=self._layers_changed)
        self.slider.on_update(lambda _e: self._replay_changed())
        self.fit_button.on_click(lambda _e: self.fit(force=True))
        client.camera.on_update(self._camera_reported)

    # ---------------------------------------------------------------- camera
    def fit(self, force: bool = False) -> bool:
        """Fit the camera to the map (if forced, or following and the map grew by a quarter)."""
        with self._lock:
            snap, _, gt = self._state()
            if snap is None:
                return False
            box = map_bounds(snap.node_poses, None if gt is None else gt[:, 1:3])
            if box is None:
                return False
            lo, hi = box
            extent = float(np.max(hi - lo))
            if not force and (not self.follow.value or extent <= 1.25 * self._fitted_extent):
                return False
            cam = self.client.camera
            if not cam.update_timestamp:  # the browser has not reported its camera yet: fit when it does
                self._fit_pending = True
                return False
            try:
                aspect = float(cam.aspect)
                width = float(cam.image_width)
            except (ZeroDivisionError, AttributeError, ValueError):
                aspect, width = 1.6, 1400.0
            if not math.isfinite(aspect) or aspect <= 0:
                aspect, width = 1.6, 1400.0
            covered = min(0.45, PANEL_PX / width) if width > 2 * PANEL_PX else 0.0
            covered_left = min(0.3, LEGEND_PX / width) if width > 2 * (PANEL_PX + LEGEND_PX) else 0.0
            fov = float(cam.fov) if 0 < float(cam.fov) < math.pi else math.radians(75.0)
            pts = snap.node_poses[:, :2] if gt is None else np.vstack([snap.node_poses[:, :2], gt[:, 1:3]])
            pos, look = fit_camera(
                lo, hi, fov, aspect, self.settings.fit_margin, covered, covered_left=covered_left, points=pts
            )
            with self.client.atomic():
                cam.up_direction = (0.0, 0.0, 1.0)
                # viser moves look_at along with the position: set the position first, then look_at
                cam.position = tuple(float(v) for v in pos)
                cam.look_at = tuple(float(v) for v in look)
            self._fitted_extent = extent
            return True

    def _camera_reported(self, _camera: Any) -> None:
        if self._fit_pending:
            self._fit_pending = False
            try:
                self.fit(force=True)
            except Exception:
                log.exception("viewer: camera fit failed")

    # ---------------------------------------------------------------- replay
    @property
    def replaying(self) -> bool:
        return int(self.slider.value) < 100

    def _replay_changed(self) -> None:
        try:
            self.refresh_replay()
        except Exception:  # a GUI callback must not kill viser's thread pool worker
            log.exception("replay failed")

    def refresh_replay(self) -> None:
        """Draw the replay at the slider's time, or go back to the live layers at 100 %."""
        with self._lock:
            if not self.replaying:
                with self.client.atomic():
                    self.replay.clear()
                    self.layers.set_replaying(False)
                self.replay_text.content = "live map"
                return
            snap, samples, gt = self._state()
            if snap is None or not len(samples):
                return
            span = time_span(samples)
            assert span is not None  # samples is not empty
            t0, t1 = span
            t = t0 + (t1 - t0) * float(self.slider.value) / 100.0
            frame = replay_at(snap, samples, gt, t, self.settings.replay_max_nodes)
            with self.client.atomic():
                self.layers.set_replaying(True)
                self.replay.draw(frame, self.layers.visible)
            self.replay_text.content = (
                f"replay: t = {t - t0:.1f} s of {t1 - t0:.1f} s, {frame.n_nodes} of {len(snap.node_poses)} nodes"
            )

    def _layers_changed(self) -> None:
        if self.replaying:
            self._replay_changed()
        if self._on_layers is not None:
            self._on_layers(self)


class ClientViews:
    """The :class:`ClientView` of every connected browser of one viewer."""

    def __init__(
        self,
        server: Any,
        specs: list[LayerSpec],
        settings: ViewerSettings,
        state: Callable[[], tuple[Any, np.ndarray, np.ndarray | None]],
        on_layers: Callable[[ClientView], None] | None = None,
    ) -> None:
        self.specs, self.settings, self._state, self._on_layers = specs, settings, state, on_layers
        self.views: dict[int, ClientView] = {}
        self._lock = threading.Lock()
        server.on_client_connect(self._connect)
        server.on_client_disconnect(self._disconnect)

    def _connect(self, client: Any) -> None:
        try:
            view = ClientView(client, self.specs, self.settings, self._state, self._on_layers)
            with self._lock:
                self.views[client.client_id] = view
            view.fit(force=True)
        except Exception:
            log.exception("viewer: setting up a browser's view failed")

    def _disconnect(self, client: Any) -> None:
        with self._lock:
            self.views.pop(client.client_id, None)

    def all(self) -> list[ClientView]:
        with self._lock:
            return list(self.views.values())

    def after_update(self) -> None:
        """After a graph update: refit following cameras when the map has grown."""
        for v in self.all():
            try:
                v.fit()
            except Exception:
                log.exception("viewer: camera fit failed")
