"""Flat synthetic test scenes: random filled shapes, rich in corners.

Used where a single camera-like image is wanted without a world (visual-memory tests and
benchmarks): every seed gives a different, reproducible scene.
"""

from __future__ import annotations

import cv2
import numpy as np


def shapes_scene(seed: int, width: int = 320, height: int = 240, shapes: int = 40) -> np.ndarray:
    """A random gray uint8 scene of filled circles, rectangles and triangles."""
    r = np.random.default_rng(seed)
    img = np.full((height, width), int(r.integers(60, 200)), np.uint8)
    for _ in range(shapes):
        c = int(r.integers(0, 256))
        t = int(r.integers(0, 3))
        if t == 0:
            cv2.circle(img, (int(r.integers(0, width)), int(r.integers(0, height))), int(r.integers(5, 30)), c, -1)
        elif t == 1:
            x, y = int(r.integers(0, width)), int(r.integers(0, height))
            cv2.rectangle(img, (x, y), (x + int(r.integers(5, 50)), y + int(r.integers(5, 50))), c, -1)
        else:
            pts = r.integers(0, [width, height], size=(3, 2)).astype(np.int32)
            cv2.fillPoly(img, [pts], c)
    return img
