"""Panel: the latest camera frame, and the last recognition's saccade trace beside its key frame.

The live image follows the newest frame the session received (at ``camera_hz``). The
recognition image shows the query frame of the newest recognition with its numbered fixations
(found vs predicted, :func:`web.images.trace_panel`) and, beside it, the thumbnail of the key
frame it accepted ("rejected" when none was). Images are encoded (JPEG) in the viewer's thread.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from ..images import fit_width, placeholder, to_rgb, trace_panel
from ..settings import ViewerSettings
from ..source import CameraImage


class CameraPanel:
    """GUI images ``camera`` and ``last recognition``."""

    def __init__(self, gui: Any, settings: ViewerSettings) -> None:
        self.settings = settings
        w = settings.camera_width
        self.live = gui.add_image(
            placeholder(w, w * 3 // 4, "no frame yet"),
            label="camera",
            format="jpeg",
            jpeg_quality=settings.jpeg_quality,
        )
        self.trace = gui.add_image(
            placeholder(w + 4 + settings.thumbnail_width, w * 3 // 4, "no recognition yet"),
            label="last recognition: saccades | accepted key frame",
            format="jpeg",
            jpeg_quality=settings.jpeg_quality,
        )
        self._live_t: float | None = None
        self._rec_id: Any = None
        self.trace_shown = False

    def update_live(self, frame: CameraImage | None) -> bool:
        """Show ``frame`` if it is new; returns whether an image was sent."""
        if frame is None or frame.t == self._live_t:
            return False
        self._live_t = frame.t
        self.live.image = fit_width(to_rgb(frame.image), self.settings.camera_width)
        return True

    def update_recognition(
        self, recognition: Mapping[str, Any] | None, query: np.ndarray | None, keyframe: np.ndarray | None
    ) -> bool:
        """Show the trace of ``recognition`` if it is new; returns whether an image was sent."""
        if recognition is None or recognition.get("id") == self._rec_id:
            return False
        self._rec_id = recognition.get("id")
        s = self.settings
        self.trace.image = trace_panel(query, recognition, keyframe, s.camera_width, s.thumbnail_width)
        self.trace_shown = True
        return True
