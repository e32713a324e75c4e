"""The retina: what the sensory cells of the visual memory see (paper §2.2, front end).

The paper's sensory cells ([S] §2.2 after [BBc]) are tuned to raw grey levels, so a
change of lighting moves every pixel away from its cell's preferred value and a revisit
under other light is not recognised. The mammalian retina never passes raw luminance on:
photoreceptors adapt to the mean light level, and retinal ganglion cells respond to
*local contrast* — the difference between a receptive-field centre and its surround
(Kuffler 1953; difference of Gaussians, Rodieck 1965; Enroth-Cugell & Robson 1966) — with
a gain set by the contrast of the neighbourhood (contrast gain control: divisive
normalisation, Heeger 1992; Carandini & Heeger 2012). :class:`Retina` models those
stages, all with Gaussian receptive fields (OpenCV, separable, no Python loop):

1. **Light adaptation** (photoreceptors): ``L = log(1 + I)``. A change of illumination
   (``I -> g I``) becomes an additive offset that the next stage removes entirely.
2. **Centre-surround** (ON/OFF ganglion cells): ``c = G(sigma_c) * L - G(sigma_s) * L``,
   a difference of Gaussians: band-pass, zero for any uniform region or offset.
3. **Contrast gain control** (divisive normalisation): ``r = c / sqrt(G(sigma_n) * c^2 +
   (k C)^2)``, where ``C`` is the image's median local contrast, so the semi-saturation
   constant scales with the scene: a faint and a strong version of the same pattern give
   the same response, and flat noisy regions stay near zero instead of being amplified.
4. **Firing rate** coded as a grey level for the sensory cells: ``128 + 127 tanh(gain r)``
   (ON responses above 128, OFF below), so the 256 sensory cells per fovea pixel of [S] /
   [BBc] and their Gaussian tuning are kept unchanged — they now tune to normalised
   local contrast instead of luminance.

``mode="none"`` keeps the paper's input (grey levels contrast-stretched like MATLAB's
``imadjust``, [BBc]). Parameters are the ``retina_*`` fields of
:class:`~hippomap.config.VisualConfig`.
"""

from __future__ import annotations

import cv2
import numpy as np

from .config import VisualConfig
from .errors import InputError

__all__ = ["Retina", "imadjust"]


def imadjust(gray: np.ndarray, clip: float) -> np.ndarray:
    """MATLAB ``imadjust``: saturate ``clip`` of each tail, map linearly to 0..255."""
    hist = np.bincount(gray.ravel(), minlength=256).astype(np.float64)
    cdf = np.cumsum(hist) / hist.sum()
    lo = int(np.searchsorted(cdf, clip, side="left"))
    hi = int(np.searchsorted(cdf, 1.0 - clip, side="left"))
    if hi <= lo:
        return gray.copy()
    lut = np.clip((np.arange(256) - lo) * (255.0 / (hi - lo)), 0, 255).round().astype(np.uint8)
    return lut[gray]


def _gauss(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian receptive fields (kernel cut at 3 sigma). Wide fields are pooled on a 2 x
    coarser grid and interpolated back — a surround has no fine detail to lose — which
    keeps the cost of an 8-px field near that of a 2-px one."""
    if sigma <= 0:
        return img
    if sigma < 4.0:
        k = 2 * int(np.ceil(3.0 * sigma)) + 1
        return cv2.GaussianBlur(img, (k, k), sigmaX=float(sigma), sigmaY=float(sigma), borderType=cv2.BORDER_REFLECT)
    h, w = img.shape
    small = cv2.resize(img, ((w + 1) // 2, (h + 1) // 2), interpolation=cv2.INTER_AREA)
    # the 2 x 2 area average already has a variance of 1/4 px^2 (coarse px) per axis
    s = float(np.sqrt(max((sigma / 2.0) ** 2 - 0.25, 0.25)))
    k = 2 * int(np.ceil(3.0 * s)) + 1
    small = cv2.GaussianBlur(small, (k, k), sigmaX=s, sigmaY=s, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


_LOG_LUT = np.log1p(np.arange(256, dtype=np.float32)).astype(np.float32)
_LUT_STEPS = 256.0  # table steps per unit of response
_LUT_HALF = 2048  # the table covers |r| <= 8 (tanh is saturated far below)


class Retina:
    """Retinal front end: gray uint8 image (working size) -> ganglion-cell image, uint8.

    >>> Retina(VisualConfig())(gray)     # doctest: +SKIP
    """

    def __init__(self, config: VisualConfig | None = None):
        cfg = config or VisualConfig()
        self.config = cfg
        self.mode = cfg.retina_mode
        if self.mode not in ("none", "dog"):
            raise InputError(f"unknown retina mode {self.mode!r}")
        if cfg.retina_surround_sigma <= cfg.retina_center_sigma:
            raise InputError("retina_surround_sigma must exceed retina_center_sigma (centre-surround)")
        r = (np.arange(2 * _LUT_HALF + 1, dtype=np.float64) - _LUT_HALF) / _LUT_STEPS
        self._rate_lut = np.clip(np.rint(127.5 + 127.5 * np.tanh(cfg.retina_gain * r)), 0, 255).astype(np.uint8)

    def ganglion_response(self, gray: np.ndarray) -> np.ndarray:
        """The normalised centre-surround response ``r`` (float32, roughly in [-1, 1] and beyond)."""
        cfg = self.config
        if not isinstance(gray, np.ndarray) or gray.dtype != np.uint8 or gray.ndim != 2 or gray.size == 0:
            raise InputError("the retina needs a non-empty 2-D uint8 gray image")
        L = _LOG_LUT[gray]  # light adaptation: gain changes become offsets
        c = _gauss(L, cfg.retina_center_sigma) - _gauss(L, cfg.retina_surround_sigma)  # centre - surround
        energy = _gauss(c * c, cfg.retina_norm_sigma)  # local contrast energy of the neighbourhood
        C = float(np.sqrt(np.median(energy[::4, ::4])))  # the scene's typical local contrast (sampled)
        k = cfg.retina_semisaturation * C + 1e-3
        return c / cv2.sqrt(energy + k * k)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        cfg = self.config
        if self.mode == "none":
            return imadjust(gray, cfg.contrast_clip)
        r = self.ganglion_response(gray)
        # firing rate as a grey level: 128 + 127.5 tanh(gain r), read from a table over r
        idx = np.clip(r * _LUT_STEPS + _LUT_HALF, 0, 2 * _LUT_HALF).astype(np.int32)
        return self._rate_lut[idx]
