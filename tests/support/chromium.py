"""Debian's Chromium under Playwright, as every real-browser test, screenshot and benchmark starts it.

``/usr/bin/chromium`` (the Debian package; ``playwright install`` is never run), headless, with
software WebGL (SwiftShader) so that viser's renderer draws on a machine without a GPU.
"""

from __future__ import annotations

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--no-sandbox",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def launch(playwright):
    """Debian's Chromium, headless, software WebGL, from a started ``sync_playwright()``."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
