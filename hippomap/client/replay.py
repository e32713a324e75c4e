"""``hippomap replay DATASET --server URL``: stream a recorded data set into a server session.

Any data set ``hippomap run`` reads (hippomap data folder, TUM RGB-D folder, ROS bag) is sent
in time order over the session's websocket: odometry as JSON, frames as the original JPEG/PNG
bytes (other images are JPEG-encoded). ``--speed 1`` replays in real time (``--speed 2``
twice as fast); by default inputs go as fast as the server acknowledges them, with at most
``--window`` messages awaiting acknowledgement. ``--resume`` skips what the session already
has (odometry and frames up to the session's last timestamp of each), so an interrupted
replay can be restarted.
The token comes from ``--token``, ``$HIPPOMAP_TOKEN``, or a local server's
``hippomap-data/admin.token``. The session's id and its live viewer URL are printed first.
A data set with ground truth sends it along: each odometry reading within the ground truth's
time span carries the true pose at its time (``gt``, linearly interpolated) for the viewer;
the mapper never uses it.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

from ..cli import add_progress_argument, progress_enabled
from ..errors import InputError
from ..geometry import wrap_angle
from ..inputs import Odometry, follows

#: consecutive odometry readings sent as one message when not replaying in real time
FAST_BATCH = 200


def ground_truth_at(groundtruth: Any) -> Any:
    """``t -> (x, y, theta)`` interpolating a data set's ground truth ``(times, poses)`` (heading
    unwrapped first), or None outside its time span; None if there is no ground truth."""
    if groundtruth is None:
        return None
    import numpy as np

    gt_t, gt_p = (np.asarray(a, float) for a in groundtruth)
    if len(gt_t) < 2:
        return None
    th = np.unwrap(gt_p[:, 2])

    def at(t: float) -> tuple[float, float, float] | None:
        if not gt_t[0] <= t <= gt_t[-1]:
            return None
        a = float(np.interp(t, gt_t, th))
        return (
            float(np.interp(t, gt_t, gt_p[:, 0])),
            float(np.interp(t, gt_t, gt_p[:, 1])),
            wrap_angle(a),
        )

    return at


def _frame_bytes(ref: Any) -> bytes:
    path = getattr(ref, "path", None)
    if path is not None and Path(path).suffix.lower() in (".jpg", ".jpeg", ".png"):
        return Path(path).read_bytes()
    from . import encode_image

    return encode_image(ref.load().image)


async def replay(
    dataset: Any,
    url: str,
    token: str | None,
    session_id: str,
    speed: float | None = None,
    window: int = 128,
    resume: bool = False,
    progress: bool = False,
) -> dict[str, Any]:
    """Stream ``dataset`` into ``session_id``; returns counts and timing. Raises
    :class:`~hippomap.client.ServerError` on the first input the server rejects, and
    :class:`~hippomap.errors.InputError` before sending anything the session already holds
    (unless ``resume`` skips it)."""
    from . import AsyncStream

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(dataset.odometry) + len(dataset.frames), unit="input", desc="replay")
    gt_at = ground_truth_at(getattr(dataset, "groundtruth", None))
    start = time.perf_counter()
    async with AsyncStream(url, token, session_id, max_in_flight=window) as stream:
        sender = _Sender(stream, bar, batch_odometry=speed is None)
        last = {"odometry": stream.hello.get("last_odometry_t"), "frame": stream.hello.get("last_frame_t")}
        t0: float | None = None
        for item in dataset.events():
            if sender.errors:
                break
            kind = "odometry" if isinstance(item, Odometry) else "frame"
            if not follows(last.get(kind), item.t):
                if not resume:  # refused before sending: pipelined later inputs must not land after a refusal
                    raise InputError(
                        f"session {session_id} already holds {kind} inputs up to t={last.get(kind)!r}, "
                        f"and this replay starts at t={item.t!r}: pass --resume to skip what is stored"
                    )
                sender.counts["skipped"] += 1
                continue
            if speed is not None:
                t0 = item.t if t0 is None else t0
                await sender.wait_until(start + (item.t - t0) / speed)
            if isinstance(item, Odometry):
                pose = gt_at(item.t) if gt_at is not None and item.gt is None else None
                await sender.odometry(item if pose is None else dataclasses.replace(item, gt=pose))
            else:
                await sender.frame(item)
        await sender.flush()
        await stream.drain()
    if bar is not None:
        bar.close()
    if sender.errors:
        raise sender.errors[0]
    elapsed = time.perf_counter() - start
    counts = sender.counts
    return {**counts, "seconds": elapsed, "inputs_per_s": (counts["odometry"] + counts["frames"]) / max(elapsed, 1e-9)}


class _Sender:
    """What :func:`replay` sends on one stream: odometry gathered into batches (``FAST_BATCH`` readings when
    ``batch_odometry``, else one message per reading), frames one by one; counts every input and message, and
    collects the acknowledgements' errors (and advances the progress ``bar``) as they come back."""

    def __init__(self, stream: Any, bar: Any, batch_odometry: bool):
        self.stream = stream
        self.bar = bar
        self.batch_odometry = batch_odometry
        self.errors: list[BaseException] = []
        self.counts = {"odometry": 0, "frames": 0, "skipped": 0, "messages": 0}
        self.batch: list[Odometry] = []

    def watch(self, fut: asyncio.Future, n: int) -> None:
        """Record the outcome of the acknowledgement ``fut`` for ``n`` inputs."""

        def done(f: asyncio.Future) -> None:
            exc = f.exception()
            if exc is not None:
                self.errors.append(exc)
            elif self.bar is not None:
                self.bar.update(n)

        fut.add_done_callback(done)

    async def flush(self) -> None:
        """Send the odometry gathered so far, if any, as one message."""
        if self.batch:
            self.watch(await self.stream.send_odometry(list(self.batch)), len(self.batch))
            self.counts["messages"] += 1
            self.batch.clear()

    async def wait_until(self, when: float) -> None:
        """Real-time replay: send what is gathered, then sleep until ``when`` (``time.perf_counter`` seconds)."""
        delay = when - time.perf_counter()
        if delay > 0:
            await self.flush()
            await asyncio.sleep(delay)

    async def odometry(self, item: Odometry) -> None:
        """Gather one odometry reading; send the batch when it is full (or at once when not batching)."""
        self.counts["odometry"] += 1
        self.batch.append(item)
        if not self.batch_odometry or len(self.batch) >= FAST_BATCH:
            await self.flush()

    async def frame(self, item: Any) -> None:
        """Send the odometry gathered before the frame, then the frame's encoded bytes."""
        await self.flush()
        data = await asyncio.to_thread(_frame_bytes, item)
        self.watch(await self.stream.send_frame(item.t, data), 1)
        self.counts["frames"] += 1
        self.counts["messages"] += 1


def viewer_url(session: dict[str, Any], server: str) -> str:
    """The live viewer of a session, as the server links it (``links.viewer`` of
    ``GET /sessions/{id}``), else built the same way from the server URL."""
    url = (session.get("links") or {}).get("viewer")
    return url or f"{server.rstrip('/')}/viewer/{session['id']}/"


def _cmd(args: argparse.Namespace) -> int:
    from ..cli.run import open_dataset
    from . import Client

    if args.speed is not None and not args.speed > 0:
        raise InputError(f"--speed must be > 0, got {args.speed}")
    if args.window < 1:
        raise InputError(f"--window must be >= 1, got {args.window}")
    dataset = open_dataset(args.dataset, args.image_topic, args.odom_topic)
    config = None
    if args.config:
        try:
            config = json.loads(Path(args.config).read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read config {args.config}: {exc}") from exc
    with Client(args.server, args.token) as client:
        if args.session:
            info = client.session(args.session)
        else:
            info = client.create_session(name=args.name or Path(args.dataset).name, config=config)
        sid = info["id"]
        print(f"session {sid}", flush=True)
        print(
            f"viewer: {viewer_url(info, args.server)}  (in a browser add ?token= with a token that may read "
            "the session)",
            flush=True,
        )
        result = asyncio.run(
            replay(
                dataset,
                args.server,
                client.token,
                sid,
                speed=args.speed,
                window=args.window,
                resume=args.resume,
                progress=progress_enabled(args),
            )
        )
        print(
            f"sent {result['odometry']} odometry readings and {result['frames']} frames in "
            f"{result['seconds']:.1f} s ({result['inputs_per_s']:.0f} inputs/s), all acknowledged"
            + (f"; skipped {result['skipped']} already stored" if result["skipped"] else ""),
            flush=True,
        )
        if not args.no_wait:
            st = client.wait_processed(sid, timeout=args.wait_timeout)
            m = st["mapper"]
            print(
                f"mapper: {m.get('nodes')} nodes, {m.get('links')} links, loop closures accepted "
                f"{m.get('loop_closures_accepted')} (used {m.get('loop_closures_used')}) / rejected "
                f"{m.get('loop_closures_rejected')}",
                flush=True,
            )
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "replay",
        help="stream a data set into a hippomap server session",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", help="hippomap data folder, TUM RGB-D folder, or ROS bag")
    p.add_argument("--server", required=True, help="server URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--token", help="bearer token (default: $HIPPOMAP_TOKEN or ./hippomap-data/admin.token)")
    p.add_argument("--session", help="stream into this existing session (default: create one)")
    p.add_argument("--name", help="name of the created session (default: the data set's name)")
    p.add_argument("--config", help="JSON file of config overrides for the created session")
    p.add_argument(
        "--speed", type=float, default=None, help="real-time factor (1 = real time); default: as fast as acknowledged"
    )
    p.add_argument("--window", type=int, default=128, help="messages in flight before waiting for acks")
    p.add_argument("--resume", action="store_true", help="skip inputs the session already has")
    p.add_argument("--image-topic", help="ROS bag: image topic")
    p.add_argument("--odom-topic", help="ROS bag: odometry topic")
    p.add_argument("--no-wait", action="store_true", help="do not wait for the mapper to finish")
    p.add_argument("--wait-timeout", type=float, default=3600.0, help="seconds to wait for the mapper")
    add_progress_argument(p)
    p.set_defaults(func=_cmd)
