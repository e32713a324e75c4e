"""Panel: the place cells made visible — the current step's iteration drawn like the paper's Fig. 8.

The spatial pathway re-runs the iteration of Eq. 9-10 at the robot's current pose with recording
(:meth:`hippomap.spatial_pathway.SpatialPathway.record`, a copy under the session lock, tens of
milliseconds, no noise drawn), and :func:`hippomap.viz.place_field_figure.place_field_figure` draws
the grid cells' binarised matrices and the position matrix shrinking to one field, with metres on
the axes and the agreement map's colour scale. Drawing takes 1-3 s (matplotlib), so the figure is made
once when the first place field exists and then when a browser presses the button — never per step.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import numpy as np

from ..images import placeholder

log = logging.getLogger(__name__)


class PlaceCellsPanel:
    """GUI image of the figure and a button that redraws it for the current step."""

    def __init__(self, gui: Any, record: Callable[[], Any], width: int = 430) -> None:
        self._record = record
        self.width = width
        self.image = gui.add_image(placeholder(width, 80, "no place field yet"), format="png")
        self.button = gui.add_button("draw the current step")
        self.button.on_click(lambda _e: self.request())
        self.caption = gui.add_markdown("")
        self.drawn = 0
        self.closed = False  # set when the viewer closes: a figure still being drawn is then dropped
        self._busy = threading.Lock()
        self._lock = threading.Lock()

    def request(self) -> None:
        """Redraw in a background thread (a button press must not block viser's callback pool)."""
        threading.Thread(target=self.draw, name="place-cells-figure", daemon=True).start()

    def draw(self) -> bool:
        """Record the iteration at the current pose and show its figure; False if busy or no field."""
        if not self._busy.acquire(blocking=False):
            return False
        try:
            from hippomap.viz.place_field_figure import place_field_figure

            rec = self._record()
            if rec is None or rec.field is None:
                return False
            img = place_field_figure(rec, vertical=True, dpi=80, max_steps=6)
            if self.closed:
                return False
            with self._lock:
                self.image.image = np.ascontiguousarray(img)
                f = rec.field
                self.caption.content = (
                    f"{len(rec.applied)} products; the field: {len(f)} point(s) at "
                    f"({f.centroid[0]:.4f}, {f.centroid[1]:.4f}) m in the coding area"
                )
                self.drawn += 1
            return True
        except Exception:
            log.exception("place-cell figure failed")
            return False
        finally:
            self._busy.release()
