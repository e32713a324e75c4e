"""Panel images: camera frames, saccade traces beside the accepted key frame, floor heatmaps.

All functions take and return plain uint8 numpy images (RGB out, as viser expects) and run in
the viewer's update thread, never on the FastAPI event loop. The saccade trace itself is drawn
by :func:`hippomap.visual_memory.draw_trace` (the model's own drawing, shared with the
evaluation's example images); the Mapper keeps recognitions as JSON-ready dicts, which
:meth:`hippomap.visual_memory.Recognition.from_dict` turns back into the typed record.
"""

from __future__ import annotations

from typing import Any, Mapping

import cv2
import numpy as np

from hippomap.visual_memory import Recognition, draw_trace


def to_rgb(image: np.ndarray) -> np.ndarray:
    """Gray, BGR or BGRA uint8 -> RGB uint8 (a new array)."""
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 1:
        return cv2.cvtColor(image[:, :, 0], cv2.COLOR_GRAY2RGB)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def fit_width(image: np.ndarray, width: int) -> np.ndarray:
    """Scale to ``width`` pixels (aspect kept); area interpolation when shrinking."""
    h, w = image.shape[:2]
    if w == width:
        return image
    height = max(1, round(h * width / w))
    interp = cv2.INTER_AREA if width < w else cv2.INTER_LINEAR
    return cv2.resize(image, (width, height), interpolation=interp)


def _label(img: np.ndarray, text: str, y: int = 14) -> None:
    cv2.putText(img, text, (4, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (4, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)


def placeholder(width: int, height: int, text: str) -> np.ndarray:
    """A dark RGB image with a centred message (e.g. "no recognition yet")."""
    img = np.full((height, width, 3), 40, np.uint8)
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    cv2.putText(
        img,
        text,
        (max(2, (width - tw) // 2), (height + th) // 2),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.5,
        (210, 210, 210),
        1,
        cv2.LINE_AA,
    )
    return img


def trace_panel(
    query: np.ndarray | None, recognition: Mapping[str, Any], keyframe: np.ndarray | None, width: int, thumb_width: int
) -> np.ndarray:
    """The query frame with its saccade trace, and the accepted key frame's thumbnail beside it.

    Fixations are numbered; colours follow :func:`hippomap.visual_memory.draw_trace` (blue start,
    green = the predicted feature was found, red = another one, grey = no evidence; a yellow cross
    marks the predicted landing point where it differs). Missing images become placeholders, so
    the panel always shows the recognition's outcome.
    """
    rec = Recognition.from_dict(dict(recognition))
    if query is None:
        w, h = rec.image_size if rec.image_size[0] > 0 else (320, 240)
        query = np.full((h, w), 90, np.uint8)
    left = to_rgb(draw_trace(query, rec, attempt="last"))  # draw_trace returns BGR
    left = fit_width(left, width)
    h = left.shape[0]
    if rec.frame_id is None:
        right = placeholder(thumb_width, h, "rejected")
    elif keyframe is None:
        right = placeholder(thumb_width, h, f"key frame {rec.frame_id}")
    else:
        thumb = fit_width(to_rgb(keyframe), thumb_width)[:h]
        right = np.full((h, thumb_width, 3), 40, np.uint8)
        top = (h - thumb.shape[0]) // 2
        right[top : top + thumb.shape[0]] = thumb
        _label(right, f"key frame {rec.frame_id}", y=max(14, top - 4))
    gap = np.full((h, 4, 3), 255, np.uint8)
    return np.ascontiguousarray(np.hstack([left, gap, right]))


def pair_panel(
    query: np.ndarray | None, recognition: Mapping[str, Any], keyframe: np.ndarray | None, width: int
) -> np.ndarray:
    """A loop closure's two frames at equal size: the query with its trace, and the key frame."""
    return trace_panel(query, recognition, keyframe, width, width)


def heatmap_rgba(values: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Values in [0, 1] (H, W) -> RGBA uint8 through the inferno colour map.

    Transparency grows as the value falls, so the map stays visible under the heatmap;
    pixels of ``mask`` (e.g. the place field itself) are drawn opaque white.
    """
    v = np.clip(np.nan_to_num(np.asarray(values, float)), 0.0, 1.0)
    rgb = cv2.cvtColor(cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)
    alpha = (90 + 165 * v).astype(np.uint8)
    out = np.dstack([rgb, alpha])
    if mask is not None:
        out[mask] = (255, 255, 255, 255)
    return out
