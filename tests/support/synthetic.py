"""Synthetic robot data for tests and benchmarks: a robot circling in front of a textured panorama.

:func:`synthetic_inputs` drives a robot round a circle facing a textured panorama (:func:`view` is
its camera): laps repeat the same views, so the visual memory recognises places and closes loops.
:func:`decoded` is those inputs as the mapper takes them.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from hippomap.inputs import Odometry


@lru_cache(maxsize=4)
def panorama(seed: int = 0, width: int = 2400, height: int = 240) -> np.ndarray:
    """A 360-degree gray panorama with smooth shading and many high-contrast shapes (corners)."""
    import cv2

    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.random((6, width // 40)).astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
    img = np.clip(60 + 120 * base, 0, 255).astype(np.uint8)
    for _ in range(width // 12):
        x, y = int(rng.integers(0, width - 30)), int(rng.integers(0, height - 30))
        w, h = int(rng.integers(8, 40)), int(rng.integers(8, 40))
        g = int(rng.integers(0, 256))
        if rng.random() < 0.6:
            cv2.rectangle(img, (x, y), (x + w, y + h), g, -1)
        else:
            cv2.circle(img, (x + w // 2, y + h // 2), max(w, h) // 2, g, -1)
    return img


def view(heading: float, seed: int = 0, width: int = 320) -> np.ndarray:
    """The camera image facing ``heading`` (radians): a window of the panorama."""
    pano = panorama(seed)
    W = pano.shape[1]
    x0 = int(round((heading % (2 * np.pi)) / (2 * np.pi) * W))
    return np.take(pano, np.arange(x0, x0 + width), axis=1, mode="wrap")


@lru_cache(maxsize=8)
def synthetic_inputs(
    n_odometry: int = 400,
    rate_hz: float = 20.0,
    frame_every: int = 4,
    speed: float = 0.5,
    radius: float = 1.0,
    seed: int = 0,
    quality: int = 85,
) -> tuple[tuple, ...]:
    """Inputs of a robot circling (``speed`` m/s, ``radius`` m): ``("odometry", Odometry)`` and
    ``("frame", t, jpeg)`` items in strictly increasing time order; a frame follows every
    ``frame_every``-th reading by half a period."""
    import cv2

    dt = 1.0 / rate_hz
    omega = speed / radius
    out: list[tuple] = []
    for k in range(n_odometry):
        t = round((k + 1) * dt, 6)
        out.append(("odometry", Odometry(t, v=speed, omega=omega)))
        if k % frame_every == 0:
            tf = round(t + dt / 2, 6)
            ok, buf = cv2.imencode(".jpg", view(omega * tf, seed), [cv2.IMWRITE_JPEG_QUALITY, quality])
            out.append(("frame", tf, buf.tobytes()))
    return tuple(out)


def decoded(items: tuple) -> list:
    """The inputs as the mapper takes them (frames decoded like the server does)."""
    from hippomap.inputs import Frame, decode_jpeg

    return [it[1] if it[0] == "odometry" else Frame(it[1], decode_jpeg(it[2])) for it in items]
