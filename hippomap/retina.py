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

5. **Orientation channels** (V1 complex cells, :meth:`Retina.orientation_channels`): the
   light-adapted image's gradient at scale ``v1_sigma`` is projected on ``v1_orientations``
   directions (simple cells, Hubel & Wiesel 1962; steerable derivative filters, Freeman &
   Adelson 1991), squared and pooled over ``v1_pool_sigma`` (the energy model of complex
   cells, Adelson & Bergen 1985: phase-invariant and tolerant to a shift of a few px), and
   divided by the pooled energy of all orientations in the neighbourhood plus a
   semi-saturation set by the frame's median (normalisation pool, Heeger 1992). Channel
   ``i`` prefers edges at ``i * 180 / n`` degrees (0 = horizontal edges), with the broad
   ``cos^2`` tuning of V1 and no response to the orthogonal edge; its rate is coded as
   ``255 tanh(v1_gain r)``. A gain or a gamma change of the light scales every energy
   alike and cancels in the ratio.

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
    if gray.dtype == np.uint8 and gray.ndim == 2 and gray.size < 1 << 24:
        # the same counts as np.bincount, from OpenCV's histogram (about twice as fast): integer counts, held
        # exactly by its float32 bins below 2^24 pixels
        hist = cv2.calcHist([gray], [0], None, [256], [0, 256]).reshape(256).astype(np.float64)
    else:
        hist = np.bincount(gray.ravel(), minlength=256).astype(np.float64)
    cdf = np.cumsum(hist) / hist.sum()
    lo = int(np.searchsorted(cdf, clip, side="left"))
    hi = int(np.searchsorted(cdf, 1.0 - clip, side="left"))
    if hi <= lo:
        return gray.copy()
    lut = np.clip((np.arange(256) - lo) * (255.0 / (hi - lo)), 0, 255).round().astype(np.uint8)
    return cv2.LUT(gray, lut)  # = lut[gray] (a table read per pixel), without numpy's fancy-index overhead


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
        L = cv2.LUT(gray, _LOG_LUT)  # light adaptation: gain changes become offsets (= _LOG_LUT[gray])
        centre = _gauss(L, cfg.retina_center_sigma)
        surround = _gauss(L, cfg.retina_surround_sigma)
        # centre - surround; the float32 operations below run in place into arrays of this call's own (the
        # same ufunc loops on the same operands as their out-of-place forms), sparing fresh image buffers
        c = np.subtract(centre, surround, out=centre if centre is not surround else None)
        energy = _gauss(c * c, cfg.retina_norm_sigma)  # local contrast energy of the neighbourhood
        C = float(np.sqrt(np.median(energy[::4, ::4])))  # the scene's typical local contrast (sampled)
        k = cfg.retina_semisaturation * C + 1e-3
        den = np.add(energy, k * k, out=energy if energy is not c else None)
        return np.divide(c, cv2.sqrt(den, den), out=c)

    def orientation_channels(self, gray: np.ndarray) -> np.ndarray:
        """V1 complex-cell responses: ``(H, W, v1_orientations)`` uint8 (firing rate 0..255).

        Channel ``i`` prefers edges oriented at ``pi * i / n`` (0 = horizontal: a vertical
        luminance gradient). Cost: two separable derivative filters and three Gaussian pools,
        whatever the number of orientations (the oriented energies are combinations of the
        pooled gradient products ``Jxx, Jxy, Jyy``: steerability)."""
        cfg = self.config
        n = cfg.v1_orientations
        if not isinstance(gray, np.ndarray) or gray.dtype != np.uint8 or gray.ndim != 2 or gray.size == 0:
            raise InputError("the orientation channels need a non-empty 2-D uint8 gray image")
        if n < 1:
            raise InputError(f"v1_orientations must be >= 1 to compute orientation channels, got {n}")
        L = _gauss(
            cv2.LUT(gray, _LOG_LUT), cfg.v1_sigma
        )  # light adaptation (= _LOG_LUT[gray]), then the simple cells' scale
        gx = cv2.Sobel(L, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) * 0.125
        gy = cv2.Sobel(L, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) * 0.125
        jxx = _gauss(gx * gx, cfg.v1_pool_sigma)  # complex cells: squared simple cells, pooled
        jxy = _gauss(gx * gy, cfg.v1_pool_sigma)
        jyy = _gauss(gy * gy, cfg.v1_pool_sigma)
        total = jxx + jyy  # energy summed over all orientations (up to a factor n / 2)
        pool = _gauss(total, cfg.v1_norm_sigma)  # the normalisation pool of the neighbourhood
        C = float(np.median(pool[::4, ::4]))
        den = pool + (cfg.v1_semisaturation * C + 1e-6)
        out = np.empty(gray.shape + (n,), np.uint8)
        for i in range(n):  # n orientations: a handful of whole-image operations
            th = np.pi * i / n
            # a simple cell preferring edges at angle th differentiates across them: along
            # (-sin th, cos th)
            s, c = np.sin(th), np.cos(th)
            e = s * s * jxx - 2.0 * s * c * jxy + c * c * jyy
            r = np.maximum(e, 0.0) / den  # energy ratio: cos^2 tuning, gain and contrast cancel
            out[..., i] = np.clip(np.rint(255.0 * np.tanh(cfg.v1_gain * r)), 0, 255).astype(np.uint8)
        return out

    def sensory_image(self, gray: np.ndarray) -> np.ndarray:
        """What the sensory cells see: the ganglion image (``H x W`` uint8), with the
        orientation channels stacked behind it (``H x W x (1 + n)``) when ``v1_orientations``
        is on and the mode is ``"dog"``."""
        g = self(gray)
        if self.mode == "none" or self.config.v1_orientations == 0:
            return g
        return np.concatenate([g[..., None], self.orientation_channels(gray)], axis=2)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        cfg = self.config
        if self.mode == "none":
            return imadjust(gray, cfg.contrast_clip)
        r = self.ganglion_response(gray)
        # firing rate as a grey level: 128 + 127.5 tanh(gain r), read from a table over r; the same float32
        # operations as np.clip(r * _LUT_STEPS + _LUT_HALF, ...), done in place (r is a fresh array),
        # and np.take, which reads the same entries as fancy indexing, faster
        t = np.multiply(r, _LUT_STEPS, out=r)
        t += _LUT_HALF
        np.clip(t, 0, 2 * _LUT_HALF, out=t)
        return np.take(self._rate_lut, t.astype(np.int32))
