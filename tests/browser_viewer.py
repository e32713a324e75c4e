"""Shared by the real-browser viewer tests: reading a viewer page (Chromium is started by
:mod:`tests.support.chromium`).

A viewer page is read the
way a person's browser holds it: viser's scene tree (``window.__viserSceneTree``, the messages
the browser received) and the canvas's pixels, matched by hue because the renderer shades thin
lines.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: the scene nodes every viewer page of a session with ground truth and loop closures holds
SCENE_NODES = ("/map/nodes/0", "/loops/accepted/0", "/ground_truth/0", "/trajectories/map/0")
LEGEND_LABELS = (
    "map nodes",
    "map trajectory",
    "ground truth",
    "raw odometry",
    "loop closures (used)",
    "place field",
)


def open_viewer(browser, url: str, sid: str, token: str, nodes: tuple[str, ...] = SCENE_NODES):
    """A 1400 x 900 page on the viewer of session ``sid``, once viser has connected, ``nodes`` are in
    its scene tree and the legend names the ground truth; viser's software-WebGL notice closed."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(f"{url}/viewer/{sid}/?token={token}")
    page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=60_000)
    for node in nodes:
        page.wait_for_function("n => !!window.__viserSceneTree?.getState()[n]", arg=node, timeout=60_000)
    page.wait_for_function("() => document.body.innerText.includes('ground truth')", timeout=30_000)
    page.wait_for_timeout(500)
    if page.get_by_text("Software WebGL rendering detected").count():  # headless Chromium: close viser's notice
        close = page.locator(".mantine-Notification-closeButton, button[aria-label='Close']")
        if close.count():
            close.first.click()
    return page


def legend_text(page) -> str:
    """The on-canvas legend's text, after checking that it floats over the canvas's left side."""
    page.wait_for_function("() => document.querySelectorAll('.hippomap-legend').length > 0", timeout=30_000)
    legend = page.locator(".hippomap-legend").first
    assert legend.is_visible()
    box = legend.bounding_box()
    canvas_box = page.locator("canvas").first.bounding_box()
    assert box["x"] < canvas_box["x"] + 0.3 * canvas_box["width"]
    return legend.inner_text()


def message_types(page, *prefixes: str) -> dict[str, str | None]:
    """Scene node name -> the type of the message that made it, for names starting with ``prefixes``."""
    return page.evaluate(
        "ps => { const s = window.__viserSceneTree.getState();"
        " return Object.fromEntries(Object.entries(s).filter(([k]) => ps.some(p => k.startsWith(p)))"
        ".map(([k, v]) => [k, v?.message?.type ?? null])) }",
        list(prefixes),
    )


def canvas(page, path: Path) -> np.ndarray:
    """The 3D canvas as a BGR image, also saved to ``path``."""
    png = page.locator("canvas").first.screenshot(path=str(path))
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def teal(img: np.ndarray) -> int:
    """Pixels of the ground truth's teal (green and blue alike, well above red; the renderer shades
    thin lines, so the hue is matched, not the exact colour)."""
    b, g, r = (img[:, :, i].astype(int) for i in range(3))
    return int(((g - r > 50) & (b - r > 50) & (np.abs(g - b) < 25)).sum())


def blue(img: np.ndarray) -> int:
    """Pixels of the map trajectory's blue."""
    b, g, r = (img[:, :, i].astype(int) for i in range(3))
    return int(((b - g > 60) & (b - r > 120)).sum())


def tan(img: np.ndarray, panels: bool = False) -> int:
    """Pixels of the raw odometry's faded orange as the renderer shades it (red over green over blue),
    outside the control panel (right third) and the legend (bottom left) unless ``panels``."""
    b, g, r = (img[:, :, i].astype(int) for i in range(3))
    mask = (r - g > 12) & (g - b > 12) & (r - b > 35) & (r < 240)
    if not panels:
        h, w = mask.shape
        mask[:, int(0.66 * w) :] = False
        mask[int(0.6 * h) :, : int(0.2 * w)] = False
    return int(mask.sum())
