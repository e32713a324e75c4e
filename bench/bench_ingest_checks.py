"""What the input hardening costs per message: strict JPEG decoding and the JSON depth scan.

    python bench/bench_ingest_checks.py [--repeat 200]

Measured in one run against references measured in the same run:

1. **Frames** (320x240 and 640x480 camera-like JPEGs): ``server.formats.ingest.check_frame`` (header
   sniffing, the strict libjpeg-turbo decode that refuses corrupt data, OpenCV's decode) against
   OpenCV's decode alone (what the mapper needs anyway). Reported: ms per frame and the ratio.
2. **Websocket text**: ``server.formats.protocol.parse_text_message`` (length, depth scan, ``json.loads``)
   against ``json.loads`` alone, for a single odometry reading, a batch of 1,000 readings, and
   the hostile ``'[' * 100000 + ']' * 100000`` (refused by the scan; ``json.loads`` raises
   RecursionError on it after walking 1,000 levels).
3. **Memory returned on delete**: RSS of this process before a queue of decoded frames is
   built, with it, and after it is dropped and ``server.runtime.sessions.release_memory`` runs.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from server.formats.ingest import check_frame  # noqa: E402
from server.formats.protocol import parse_text_message  # noqa: E402
from server.runtime.sessions import release_memory  # noqa: E402
from server.settings import ServerSettings  # noqa: E402


def _per_call(fn, repeat: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat * 1e3


def _camera_jpeg(w: int, h: int) -> bytes:
    rng = np.random.default_rng(0)
    img = cv2.resize((rng.random((h // 8, w // 8)) * 255).astype(np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    img = cv2.add(img, (rng.random((h, w)) * 20).astype(np.uint8))
    return cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes()


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=200)
    args = ap.parse_args()
    settings = ServerSettings()

    print("frames: check_frame (strict decode + OpenCV decode) vs OpenCV decode alone")
    for w, h in ((320, 240), (640, 480)):
        data = _camera_jpeg(w, h)
        ref = _per_call(lambda: cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE), args.repeat)
        full = _per_call(lambda: check_frame(data, 1.0, settings), args.repeat)
        print(
            f"  {w}x{h} ({len(data) / 1e3:.0f} kB): {full:.2f} ms vs {ref:.2f} ms  (x{full / ref:.2f}, "
            f"+{full - ref:.2f} ms per frame)"
        )

    print("websocket text: parse_text_message (length + depth scan + json.loads) vs json.loads alone")
    one = json.dumps({"type": "odometry", "id": 7, "t": 1234.5, "v": 0.2, "omega": -0.01})
    batch = json.dumps(
        {
            "type": "odometry",
            "id": 8,
            "readings": [{"t": 1000.0 + 0.02 * i, "v": 0.2, "omega": 0.01} for i in range(1000)],
        }
    )
    limit, depth = settings.max_text_message_bytes, settings.max_json_depth
    for name, text in (("one reading", one), ("1,000 readings", batch)):
        ref = _per_call(lambda: json.loads(text), args.repeat)
        full = _per_call(lambda: parse_text_message(text, limit, depth), args.repeat)
        print(f"  {name} ({len(text) / 1e3:.1f} kB): {full * 1e3:.1f} us vs {ref * 1e3:.1f} us  (x{full / ref:.2f})")
    hostile = "[" * 100000 + "]" * 100000

    def loads_hostile() -> None:
        try:
            json.loads(hostile)
        except RecursionError:
            pass

    def parse_hostile() -> None:
        try:
            parse_text_message(hostile, limit, depth)
        except ValueError:
            pass

    ref = _per_call(loads_hostile, 20)
    full = _per_call(parse_hostile, 20)
    print(f"  '['*100000+']'*100000: refused in {full:.2f} ms (json.loads raises RecursionError in {ref:.2f} ms)")

    print("memory: a queue of 100 decoded 2000x1000 frames, dropped, then release_memory()")
    before = _rss_mb()
    frames = [np.full((1000, 2000), k, dtype=np.uint8) for k in range(100)]
    held = _rss_mb()
    del frames
    release_memory()
    after = _rss_mb()
    print(
        f"  RSS {before:.0f} MB -> {held:.0f} MB with the queue -> {after:.0f} MB after "
        f"({(held - after) / max(held - before, 1e-9):.0%} of the growth returned)"
    )


if __name__ == "__main__":
    main()
