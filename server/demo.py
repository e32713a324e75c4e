"""``hippomap serve --demo``: a simulated robot streaming into a session of this server.

The robot is a client like any other (the Python client over the websocket), driving the
simulator's corridor loop (:func:`hippomap.sim.loop_world`) in real time: odometry and a
rendered camera frame at every step. It streams into the admin's session named
``demo robot``, created on the first start and reused on later ones (the same data folder
keeps it): a restart picks the run up after the last input the session holds, and a session
that already holds the whole run is left as it is. Each start mints a viewer token for the
session (replacing the previous start's) and prints the session's viewer URL.

After its laps the robot stops and says so: a line on stdout and in the log (level info),
naming the session, whose stats then show the whole run stored (``inputs_stored``, and
``last_odometry_t`` at the run's end).
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, cast

log = logging.getLogger("hippomap.server")

#: the name of the demo's session, found again by name among the admin's sessions on a restart
DEMO_NAME = "demo robot"
#: the label of the viewer token minted for it
VIEWER_LABEL = "demo viewer"


@dataclass(frozen=True)
class DemoSession:
    """The demo's session: its id, the viewer token minted for it at this start, whether it
    was found (not created), and the last odometry / frame times it already holds."""

    id: str
    viewer_token: str
    reused: bool
    last_odometry_t: float | None
    last_frame_t: float | None


def _laps(n: int) -> str:
    return f"{n} lap" if n == 1 else f"{n} laps"


def demo_run(rate_hz: float, laps: int, seed: int) -> Any:
    """The demo robot's simulated run (deterministic for its arguments): an 8 m x 5 m loop
    at 0.6 m/s, so the first revisit (and loop closure) comes within a minute."""
    from hippomap import sim

    world = sim.loop_world(seed=seed, laps=laps, size=(8.0, 5.0), speed_mps=0.6)
    return sim.simulate(
        world,
        rate_hz=rate_hz,
        frame_every=1,
        seed=seed,
        odometry_noise=sim.OdometryNoise(sigma_omega=0.02, omega_bias=0.005),
    )


def open_demo_session(client: Any, camera_hfov_deg: float | None = None) -> DemoSession:
    """The admin's ``demo robot`` session (the oldest, if several) or a new one, with a fresh
    viewer token for it; the viewer tokens earlier starts minted for it are revoked. A new session
    gets the model's default config with the demo camera's field of view, as a robot's client gives
    its calibration (the image shift of a recognition is then a heading: docs/MODEL.md item 56)."""
    found = sorted((s for s in client.sessions() if s["name"] == DEMO_NAME), key=lambda s: s["created"])
    if found:
        sid = found[0]["id"]
        stats = client.stats(sid)
        last_odo, last_frame = stats["last_odometry_t"], stats["last_frame_t"]
        for tok in client.tokens():
            if tok.get("session") == sid and tok.get("label") == VIEWER_LABEL:
                client.delete_token(tok["id"])
    else:
        config = {} if camera_hfov_deg is None else {"mapper": {"camera_hfov_deg": camera_hfov_deg}}
        sid = client.create_session(name=DEMO_NAME, config=config)["id"]
        last_odo = last_frame = None
    viewer = client.create_token("viewer", session=sid, label=VIEWER_LABEL)
    return DemoSession(sid, viewer["token"], bool(found), last_odo, last_frame)


async def _drive(
    stream: Any, run: Any, skip_odo: float, skip_frame: float, speed: float, stopping: Callable[[], bool]
) -> bool:
    """Send the steps of ``run`` after ``skip_odo`` / ``skip_frame`` (what the session holds) on ``stream`` at
    ``speed`` times real time; False if the server began shutting down (the stream stopped early)."""
    from hippomap.client import encode_image
    from hippomap.inputs import Odometry

    frame_at = {int(k): i for i, k in enumerate(run.frame_steps)}
    start = time.monotonic()
    first = None
    for k in range(len(run.times)):
        t = float(run.times[k])
        i = frame_at.get(k)
        if t <= skip_odo and (i is None or t <= skip_frame):
            continue  # the session has this step already (a restart)
        first = t if first is None else first
        delay = start + (t - first) / speed - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        if stopping():  # the server is shutting down: stop driving, a restart resumes here
            log.info("demo robot stopped at t = %.1f s: the server is shutting down", t)
            return False
        if t > skip_odo:
            _, v, omega = (float(x) for x in run.odometry[k])
            # the true pose: drawn by the viewer, unused by the mapper
            gt = cast(tuple[float, float, float], tuple(float(x) for x in run.groundtruth[k]))
            await stream.send_odometry(Odometry(t, v=v, omega=omega, gt=gt))
        if i is not None and t > skip_frame:
            img = await asyncio.to_thread(lambda: encode_image(run.frame(i)))
            await stream.send_frame(t, img)  # the frame of this step, at the same time
    return True


async def run_demo(
    url: str,
    token: str,
    rate_hz: float = 10.0,
    laps: int = 10,
    seed: int = 1,
    stopping: Callable[[], bool] = lambda: False,
    speed: float = 1.0,
) -> str:
    """Stream the demo run into the demo session at ``speed`` times real time (resuming after
    what the session holds); returns the session id. ``stopping()`` tells whether the server
    is shutting down (then a closed stream is expected, not an error)."""
    from hippomap.client import AsyncStream, Client

    if not speed > 0:
        raise ValueError(f"demo speed must be > 0, got {speed}")
    run = await asyncio.to_thread(demo_run, rate_hz, laps, seed)

    def setup() -> DemoSession:
        with Client(url, token) as c:
            return open_demo_session(c, float(run.config.camera.hfov_deg))

    demo = await asyncio.to_thread(setup)
    sid = demo.id
    print(f"demo robot {'back in its' if demo.reused else 'streaming into'} session {sid}", flush=True)
    print(f"viewer: {url}/viewer/{sid}/?token={demo.viewer_token}", flush=True)
    end_t = float(run.times[-1])
    if demo.last_odometry_t is not None and demo.last_odometry_t >= end_t:
        message = (
            f"demo robot: session {sid} already holds its whole run ({_laps(laps)}, {len(run.times)} steps); "
            "it is not driven again"
        )
        print(message, flush=True)
        log.info(message)
        return sid
    skip_odo = -float("inf") if demo.last_odometry_t is None else demo.last_odometry_t
    skip_frame = -float("inf") if demo.last_frame_t is None else demo.last_frame_t
    try:
        async with AsyncStream(url, token, sid, max_in_flight=256) as stream:
            if not await _drive(stream, run, skip_odo, skip_frame, speed, stopping):
                return sid
            await stream.drain()
        message = (
            f"demo robot finished its {_laps(laps)} ({len(run.times)} steps, last input at t = {end_t:.1f} s) "
            f"in session {sid}; it stops here (the map stays in the session)"
        )
        print(message, flush=True)
        log.info(message)
    except asyncio.CancelledError:
        raise
    except Exception as exc:  # the demo must never take the server down
        if not stopping():
            log.warning("demo robot stopped: %s", exc)
    return sid
