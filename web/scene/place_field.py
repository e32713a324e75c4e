"""The place field of the current step, as a heatmap on the floor at its place (paper §2.3, Eqs. 9-10).

The place cells find the robot's local position by multiplying window comparators
``MB_n = 1[|G_n - T_n| <= ΔT/2]`` (Eq. 9) until a single field remains (Eq. 10). The heatmap
shows, over the whole coding area (L x L, 40 cm by default), the fraction of the grid cells the
iteration applied whose window a place passes (the best place within each pixel): 1 exactly where
the product — the place field — lies, lower where only some cells agree. The field's own points (the ``PlaceField``
returned by the model) are drawn white on top, since at the default resolution (0.05 cm) the
field is far smaller than one heatmap pixel.

The discharges ``T_n`` are read from the rate tables at the field's centroid; without rate
noise (the default) these are exactly the discharges the model used, with noise they are the
noise-free rates at the found place.

The coding area lives in the place-code (odometric) frame, the map is drawn in the relaxed map
frame: the heatmap is carried over by the rigid transform between the robot's odometric pose
and its map pose, so its field lies under the robot's marker.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from hippomap.geometry import between, compose
from hippomap.grid_cells import LEVELS
from hippomap.place_cells import window_levels

from ..images import heatmap_rgba
from ..settings import ViewerSettings
from ..snapshot import PlaceFieldView
from .pose import yaw_wxyz

FIELD_Z = 0.005


@dataclass(frozen=True)
class FieldHeatmap:
    """Heatmap ``values`` (P, P) in [0, 1] and field ``mask`` over the coding area (rows = +y),
    with the area's side (m) and its centre pose in the map frame (x, y, theta)."""

    values: np.ndarray
    mask: np.ndarray
    side_m: float
    centre: np.ndarray


def field_heatmap(view: PlaceFieldView, pixels: int) -> FieldHeatmap:
    """Window-agreement heatmap of the current place code (see module doc).

    The comparators are evaluated at the full resolution of the rate tables (the grid cells'
    spacing is 0.5-2 cm, far below a heatmap pixel, so sampling them would alias) and each
    heatmap pixel shows the best agreement inside its block (max pooling): the pixel holding
    the field reads exactly 1.
    """
    code, tables = view.code, view.tables
    field = code.field
    assert field is not None  # snapshot.py builds a PlaceFieldView only for a code with a field
    N = tables.size
    step = max(1, int(np.ceil(N / pixels)))
    cells = np.asarray(field.cells if field.cells else range(tables.n_cells), dtype=np.int64)
    cx, cy = field.centroid
    ix = int(np.clip(round(cx / tables.resolution), 0, N - 1))
    iy = int(np.clip(round(cy / tables.resolution), 0, N - 1))
    T = tables.levels[cells, iy * N + ix].astype(float) * (view.spatial.g_max / LEVELS)
    lo, hi = window_levels(T, view.spatial)
    count = np.zeros(N * N, np.uint16)
    for k, n in enumerate(cells):  # one vectorised comparator (Eq. 9) per applied cell
        row = tables.levels[n]
        count += (row >= lo[k]) & (row <= hi[k])
    P = -(-N // step)
    padded = np.zeros((P * step, P * step), np.uint16)
    padded[:N, :N] = count.reshape(N, N)
    values = padded.reshape(P, step, P, step).max(axis=(1, 3)) / float(len(cells))
    mask = np.zeros((P, P), bool)
    iy_f, ix_f = np.divmod(field.indices, N)
    mask[iy_f // step, ix_f // step] = True
    side = P * step * tables.resolution
    # area centre in the odometric frame, then carried to the map frame
    centre_odo = np.array([code.origin[0] + 0.5 * side, code.origin[1] + 0.5 * side, 0.0])
    to_map = compose(view.map_pose, between(view.odometric_pose, centre_odo))
    return FieldHeatmap(values, mask, side, to_map)


class PlaceFieldLayer:
    """Scene node ``/place_field``: the heatmap image lying on the floor."""

    def __init__(self, scene: Any, settings: ViewerSettings) -> None:
        self.scene, self.settings = scene, settings
        self.handle: Any = None
        self._code: Any = None
        self._visible = True
        self._drawn_at = -math.inf
        self.last: FieldHeatmap | None = None

    def update(self, view: PlaceFieldView | None) -> bool:
        """Redraw when the place code changed; returns whether anything was sent."""
        if view is None or view.code is self._code:
            return False
        now = time.monotonic()
        if now - self._drawn_at < 1.0 / self.settings.place_field_hz:
            return False
        self._drawn_at = now
        self._code = view.code
        hm = field_heatmap(view, self.settings.place_field_pixels)
        self.last = hm
        # viser lays image row i along the node's local +y and column j along +x (checked in a browser),
        # the heatmap's rows already follow +y of the coding area
        rgba = heatmap_rgba(hm.values, hm.mask)
        self.handle = self.scene.add_image(
            "/place_field",
            rgba,
            render_width=hm.side_m,
            render_height=hm.side_m,
            format="png",
            position=(float(hm.centre[0]), float(hm.centre[1]), FIELD_Z),
            wxyz=yaw_wxyz(float(hm.centre[2])),
            cast_shadow=False,
            receive_shadow=False,
            visible=self._visible,
        )
        return True

    def pending(self, view: PlaceFieldView | None) -> bool:
        """Whether ``view`` has a place code not drawn yet (e.g. held back by ``place_field_hz``)."""
        return view is not None and view.code is not self._code

    @property
    def visible(self) -> bool:
        return self._visible

    @visible.setter
    def visible(self, value: bool) -> None:
        self._visible = bool(value)
        if self.handle is not None:
            self.handle.visible = self._visible
