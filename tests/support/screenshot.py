"""Screenshot a viewer page in headless Chromium (for docs, e.g. ``docs/viewer-demo.png``).

    python -m tests.support.screenshot URL OUT.png [--wait-s 3] [--size 1400x900]

Opens ``URL`` (a ``/viewer/{session}/?token=...`` link, as ``hippomap serve --demo`` prints), waits
until viser has connected and the map's nodes are in the scene (``window.__viserSceneTree``), lets
the renderer draw for ``--wait-s`` seconds, closes the "software WebGL" notice and saves the page.
Uses Debian's Chromium (/usr/bin/chromium) through Playwright, software WebGL.
"""

from __future__ import annotations

import argparse
import sys

from tests.support.chromium import launch


def screenshot(
    url: str,
    out: str,
    wait_s: float = 3.0,
    width: int = 1400,
    height: int = 900,
    node: str = "/map/nodes/0",
    timeout_s: float = 120.0,
) -> None:
    """Save a PNG of the viewer at ``url`` once ``node`` is in its scene."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = launch(p)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=timeout_s * 1000)
            page.wait_for_function("n => !!window.__viserSceneTree?.getState()[n]", arg=node, timeout=timeout_s * 1000)
            page.wait_for_timeout(wait_s * 1000)
            notice = page.get_by_text("Software WebGL rendering detected")
            if notice.count():
                close = page.locator(".mantine-Notification-closeButton, button[aria-label='Close']")
                if close.count():
                    close.first.click()
                    page.wait_for_timeout(500)
            page.screenshot(path=out)
        finally:
            browser.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tests.support.screenshot",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("url")
    ap.add_argument("out")
    ap.add_argument("--wait-s", type=float, default=3.0, help="seconds to let the scene render (default 3)")
    ap.add_argument("--size", default="1400x900", help="viewport WIDTHxHEIGHT (default 1400x900)")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    screenshot(args.url, args.out, args.wait_s, w, h)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
