"""Drawing of saccade traces and learned fixation points with OpenCV (for the viewer and the
evaluation's example images).

:func:`draw_trace` draws a :class:`~hippomap.visual_recognition.Recognition` on its query frame,
:func:`draw_frame_features` a learned frame's fixation points; both return BGR uint8 images.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Iterable, Literal

import cv2
import numpy as np

from .errors import InputError
from .visual_recognition import Recognition

if TYPE_CHECKING:
    from .feature_store import FeatureStore

__all__ = ["draw_trace", "draw_frame_features"]

_COLORS = {
    "start": (255, 160, 0),
    "confirmed": (0, 200, 0),
    "mismatch": (0, 0, 255),
    "no_evidence": (160, 160, 160),
}


def _to_bgr(image: Any) -> np.ndarray:
    gray_or_bgr = image
    if not isinstance(gray_or_bgr, np.ndarray) or gray_or_bgr.size == 0 or gray_or_bgr.dtype != np.uint8:
        raise InputError("draw_trace needs a non-empty uint8 image")
    if gray_or_bgr.ndim == 2:
        return cv2.cvtColor(gray_or_bgr, cv2.COLOR_GRAY2BGR)
    if gray_or_bgr.ndim == 3 and gray_or_bgr.shape[2] == 3:
        return gray_or_bgr.copy()
    if gray_or_bgr.ndim == 3 and gray_or_bgr.shape[2] == 4:
        return cv2.cvtColor(gray_or_bgr, cv2.COLOR_BGRA2BGR)
    raise InputError(f"draw_trace: bad image shape {gray_or_bgr.shape}")


def draw_trace(
    image: Any,
    recognition: Recognition,
    attempt: int | Literal["last", "all"] = "last",
    fovea: int | None = None,
    scale: float = 1.0,
) -> np.ndarray:
    """Draw a recognition's saccade trace on the query frame -> BGR uint8 image.

    Numbered fixations (blue = start, green = predicted feature found, red = another
    feature found, gray = no evidence), the saccade lines between them, and for every
    saccade the predicted landing point (yellow cross) where it differs from the fixation
    after the microsaccade. ``fovea``: draw the fovea square (input-image px) at each fixation.
    ``scale``: enlarge the drawing (e.g. 3 for a 160 x 120 frame).
    """
    canvas = _scaled(_to_bgr(image), scale)
    H, W = canvas.shape[:2]
    s = max(1.0, W / 320.0)
    steps = recognition.steps
    if attempt == "last":
        last = steps[-1].attempt if steps else 0
        steps = [st for st in steps if st.attempt == last]
    elif attempt != "all":
        steps = [st for st in steps if st.attempt == int(attempt)]
    prev = None
    prev_attempt = None
    for i, st in enumerate(steps, 1):
        p = (int(round(st.fixation[0] * scale)), int(round(st.fixation[1] * scale)))
        if prev is not None and prev_attempt == st.attempt:
            cv2.line(canvas, prev, p, (0, 0, 230), max(1, int(s)), cv2.LINE_AA)
        if st.target is not None:
            t = (int(round(st.target[0] * scale)), int(round(st.target[1] * scale)))
            if t != p:
                d = int(4 * s)
                cv2.line(canvas, (t[0] - d, t[1] - d), (t[0] + d, t[1] + d), (0, 230, 230), 1, cv2.LINE_AA)
                cv2.line(canvas, (t[0] - d, t[1] + d), (t[0] + d, t[1] - d), (0, 230, 230), 1, cv2.LINE_AA)
        col = _COLORS.get(st.outcome, (255, 255, 255))
        if fovea:
            hf = int(round(fovea * scale)) // 2
            cv2.rectangle(canvas, (p[0] - hf, p[1] - hf), (p[0] + hf, p[1] + hf), col, 1)
        cv2.circle(canvas, p, int(5 * s), col, max(1, int(s)), cv2.LINE_AA)
        _number(canvas, str(i), p, s)
        prev, prev_attempt = p, st.attempt
    label = f"frame {recognition.frame_id}" if recognition.accepted else "rejected"
    label += f"  a={recognition.evidence:.2f}  resets={recognition.n_resets}"
    _label(canvas, label, s)
    return canvas


def _number(canvas: np.ndarray, text: str, p: tuple[int, int], s: float) -> None:
    """A fixation's number (or label) written up and to the right of its circle at ``p``."""
    cv2.putText(
        canvas,
        text,
        (p[0] + int(6 * s), p[1] - int(4 * s)),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.4 * s,
        (255, 255, 255),
        max(1, int(s)),
        cv2.LINE_AA,
    )


def _label(canvas: np.ndarray, text: str, s: float) -> None:
    """White text on a dark box in the top-left corner."""
    fs, th = 0.45 * s, max(1, int(round(s)))
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, fs, th)
    cv2.rectangle(canvas, (0, 0), (w + 8, h + base + 8), (0, 0, 0), -1)
    cv2.putText(canvas, text, (4, h + 4), cv2.FONT_HERSHEY_SIMPLEX, fs, (255, 255, 255), th, cv2.LINE_AA)


def _scaled(canvas: np.ndarray, scale: float) -> np.ndarray:
    if not scale > 0:
        raise InputError(f"drawing scale must be positive, got {scale!r}")
    if scale == 1.0:
        return canvas
    return cv2.resize(canvas, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)


def draw_frame_features(
    image: Any, memory: FeatureStore, frame_id: int, highlight: Iterable[int] | dict[int, str] = (), scale: float = 1.0
) -> np.ndarray:
    """Draw a learned frame's fixation points -> BGR uint8 (the learned image, any size).

    Points are numbered in learning order; ``highlight``: FLC ids drawn filled (e.g. the
    features found in a recognition), or a dict FLC id -> label (e.g. the fixation number
    of the trace): then only the highlighted points are labelled. Others are hollow blue."""
    canvas = _scaled(_to_bgr(image), scale)
    info = memory.frame_features(frame_id)
    W = canvas.shape[1]
    to_px = W / float(info["size"][0])
    s = max(1.0, W / 320.0)
    labels = (
        {int(k): str(v) for k, v in highlight.items()}
        if isinstance(highlight, dict)
        else {int(k): "" for k in highlight}
    )
    for i, (k, (x, y)) in enumerate(zip(info["features"], info["points"]), 1):
        p = (int(round(x * to_px)), int(round(y * to_px)))
        filled = int(k) in labels
        cv2.circle(
            canvas,
            p,
            int(5 * s),
            (0, 200, 0) if filled else (255, 160, 0),
            -1 if filled else max(1, int(s)),
            cv2.LINE_AA,
        )
        if isinstance(highlight, dict):  # label only the found features, by fixation number
            text = labels.get(int(k), "")
        else:
            text = str(i)
        _number(canvas, text, p, s)
    _label(canvas, f"learned frame {frame_id}", s)
    return canvas
