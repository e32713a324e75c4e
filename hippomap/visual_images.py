"""Frames in, working images out: what the visual memory's sensory cells see (paper §2.2; spec §2).

Every frame is checked once (a numpy uint8 array, gray, BGR or BGRA, large enough for the fovea at
the working width), converted to grey, resized to ``working_width`` and passed through the retina
(:mod:`hippomap.retina`). :func:`working_size` is the check alone, what every frame must pass
whether or not it becomes a key frame.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from .config import VisualConfig
from .errors import InputError
from .retina import Retina

__all__ = ["check_image", "prepare_image", "prepare_views", "working_gray", "working_size"]


def check_image(image: Any, name: str = "image") -> np.ndarray:
    """The frame as grey levels, or :class:`InputError` naming what is wrong with it."""
    if not isinstance(image, np.ndarray):
        raise InputError(
            f"{name} must be a numpy array (H x W gray or H x W x 3 BGR, uint8), got {type(image).__name__}"
        )
    if image.size == 0:
        raise InputError(f"{name} is empty (shape {image.shape})")
    if image.dtype != np.uint8:
        raise InputError(f"{name} must have dtype uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise InputError(f"{name} must be H x W or H x W x 3/4, got shape {image.shape}")


def prepare_image(image: Any, config: VisualConfig | None = None, name: str = "image") -> tuple[np.ndarray, float]:
    """Validate and convert a frame to the memory's working image (what the sensory cells see).

    Gray (BGR/BGRA converted), resized to ``working_width`` (aspect kept), then passed
    through the :class:`~hippomap.retina.Retina` (``retina_mode="none"``: contrast
    stretched like ``imadjust``, spec §2 learning step 1). Returns ``(work, scale)`` where
    ``scale`` = original px per working px. Raises :class:`InputError` for non-arrays,
    empty images, dtypes other than uint8, bad shapes and images too small for the fovea.
    """
    gray, work, scale = prepare_views(image, config, name)
    return work, scale


def working_size(image: Any, cfg: VisualConfig, name: str = "image") -> tuple[np.ndarray, int, int]:
    """``(gray, width, height)``: the frame as grey levels and its size at the working width, or
    :class:`InputError` for anything the memory could not learn or recognise (no image work
    beyond the grey conversion: what every frame must pass, key frame or not)."""
    gray = check_image(image, name)
    h0, w0 = gray.shape
    if min(h0, w0) < cfg.fovea:
        raise InputError(f"{name} of {w0}x{h0} px is too small for the {cfg.fovea}-px fovea")
    width = cfg.working_width
    height = max(1, int(round(h0 * width / w0)))
    need = 2 * cfg.fovea + 2
    if height < need:
        raise InputError(
            f"{name} of {w0}x{h0} px becomes {width}x{height} at the working width; the {cfg.fovea}-px fovea needs "
            f"at least {need} px on each side"
        )
    return gray, width, height


def prepare_views(
    image: Any, config: VisualConfig | None = None, name: str = "image"
) -> tuple[np.ndarray, np.ndarray, float]:
    """Like :func:`prepare_image`, also returning the working-size grey image before the retina:
    ``(gray, work, scale)``; fixation points are chosen on ``gray`` or ``work`` (``corner_source``).
    ``work`` is ``H x W`` (the ganglion image), or ``H x W x (1 + v1_orientations)`` with the V1
    orientation channels behind it (:meth:`~hippomap.retina.Retina.sensory_image`)."""
    cfg = config or VisualConfig()
    work, scale = working_gray(image, cfg, name)
    return work, _retina(cfg).sensory_image(work), scale


def working_gray(image: Any, cfg: VisualConfig, name: str = "image") -> tuple[np.ndarray, float]:
    """``(work, scale)``: the frame's grey levels at the working width (area-averaged down, bilinear up; a copy
    when already that size) before any retina, and the original px per working px; :func:`working_size`'s
    :class:`InputError` for a frame the memory could not take."""
    gray, width, height = working_size(image, cfg, name)
    h0, w0 = gray.shape
    interp = cv2.INTER_AREA if width < w0 else cv2.INTER_LINEAR
    work = cv2.resize(gray, (width, height), interpolation=interp) if (width, height) != (w0, h0) else gray.copy()
    return work, w0 / float(width)


_last_retina: tuple[VisualConfig, Retina] | None = None


def _retina(cfg: VisualConfig) -> Retina:
    """The retina of ``cfg``: the one built for the previous call when the config is the same object. A
    config is frozen and a retina reads it at every call, holding nothing else but the rate table built
    from it, so the same retina gives the same images; building one costs a 4,097-entry tanh table."""
    global _last_retina
    last = _last_retina
    if last is not None and last[0] is cfg:
        return last[1]
    retina = Retina(cfg)
    _last_retina = (cfg, retina)
    return retina
