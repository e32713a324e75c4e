"""RatSLAM-style view-template matcher: the baseline of ``hippomap eval-vpr``.

A re-implementation of OpenRatSLAM's local view cells (``src/ratslam/local_view_match.cpp``,
non-panoramic mode) with the classic RatSLAM *column intensity profile* template
(``template_y_size = 1``): the gray image (optionally cropped) is averaged into
``template_x`` columns x ``template_y`` rows, scaled to [0, 1], optionally mean-normalised
(``vt_normalisation``: every value is multiplied by ``vt_normalisation / mean`` and
clipped to [0, 1]). A view is compared with every stored template by the mean absolute
difference of the template's centre ``template_x - 2 shift`` columns against the view
shifted by ``-shift .. +shift`` columns in steps of ``step`` (OpenRatSLAM's
``compare()``); the best (template, shift) gives the error ``vt_err``. OpenRatSLAM
accepts the match when ``vt_err <= vt_match_threshold``; the evaluation sweeps that
threshold for a PR curve.

Vectorised: all templates and shifts are compared in one numpy expression.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RatSLAMViewTemplateConfig:
    template_x: int = 60  # OpenRatSLAM configs use 60 columns
    template_y: int = 1  # 1 row: the column intensity profile of classic RatSLAM
    shift: int = 5  # vt_shift_match (template columns)
    step: int = 1  # vt_step_match
    normalisation: float = 0.4  # vt_normalisation (0 = off)
    crop_y: tuple[float, float] = (0.0, 1.0)  # image_crop_y_min/max as fractions of the height


class RatSLAMViewTemplates:
    """Store view templates and find the best match of a new view (OpenRatSLAM ``LocalViewMatch``)."""

    def __init__(self, config: RatSLAMViewTemplateConfig | None = None):
        self.config = config or RatSLAMViewTemplateConfig()
        c = self.config
        if c.template_x <= 2 * c.shift:
            raise ValueError("template_x must exceed 2 * shift")
        self._templates: list[np.ndarray] = []
        self._stack: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self._templates)

    def template(self, image: np.ndarray) -> np.ndarray:
        """The (template_y, template_x) view template of an image (gray or BGR uint8)."""
        c = self.config
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        h = image.shape[0]
        y0, y1 = int(round(c.crop_y[0] * h)), int(round(c.crop_y[1] * h))
        sub = image[y0:y1].astype(np.float32)
        t = cv2.resize(sub, (c.template_x, c.template_y), interpolation=cv2.INTER_AREA) / 255.0
        if c.normalisation > 0:
            mean = float(t.mean())
            if mean > 0:
                t = np.clip(t * (c.normalisation / mean), 0.0, 1.0)
        return t.astype(np.float32)

    def add(self, image: np.ndarray) -> int:
        """Learn a view template; returns its id."""
        self._templates.append(self.template(image))
        self._stack = None
        return len(self._templates) - 1

    def errors(self, image: np.ndarray) -> np.ndarray:
        """Best-shift mean absolute difference of the view against every template (n,)."""
        if not self._templates:
            return np.zeros(0, np.float32)
        if self._stack is None:
            self._stack = np.stack(self._templates)  # (n, Y, X)
        c = self.config
        v = self.template(image)
        X = c.template_x
        width = X - 2 * c.shift
        centre = v[:, c.shift : c.shift + width]  # the view's centre columns
        offsets = np.arange(0, 2 * c.shift + 1, c.step)
        # template windows at every offset: (n, n_off, Y, width)
        win = np.stack([self._stack[:, :, o : o + width] for o in offsets], axis=1)
        err = np.abs(win - centre[None, None]).mean(axis=(2, 3))
        return err.min(axis=1)

    def compare(self, image: np.ndarray) -> tuple[int, float]:
        """(best template id, its error); (-1, inf) when nothing is stored."""
        err = self.errors(image)
        if err.size == 0:
            return -1, float("inf")
        k = int(np.argmin(err))
        return k, float(err[k])
